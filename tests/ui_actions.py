"""Counted actions through the real window (issue #36, acceptance 2): every click, double-click, shortcut and
typed field goes through QTest on the widget a person would use, and is counted. A field typed is one action (a
name is one thing to enter, whatever its length)."""

from __future__ import annotations

from typing import Any

from PySide6.QtCore import Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QAbstractButton, QLineEdit, QListWidget, QWidget


class Actions:
    def __init__(self) -> None:
        self.done: list[str] = []

    @property
    def count(self) -> int:
        return len(self.done)

    def since(self, mark: int) -> list[str]:
        return self.done[mark:]

    def click(self, button: QAbstractButton, what: str = "") -> None:
        assert button.isVisible() and button.isEnabled(), f"{what or button.text()}: not clickable"
        QTest.mouseClick(button, Qt.MouseButton.LeftButton)
        self.done.append(f"click {what or button.text()}")

    def type(self, edit: QLineEdit, text: str, what: str = "") -> None:
        assert edit.isVisible() and edit.isEnabled(), f"{what}: not editable"
        edit.setFocus()
        edit.selectAll()
        QTest.keyClicks(edit, text)
        self.done.append(f"type {what or edit.accessibleName()}: {text}")

    def pick(self, items: QListWidget, row: int, what: str = "", double: bool = False) -> None:
        """Click (or double-click) row ``row`` of a list where it is drawn."""
        item = items.item(row)
        assert item is not None, f"{what}: no row {row}"
        items.scrollToItem(item)
        pos = items.visualItemRect(item).center()
        if double:
            QTest.mouseClick(items.viewport(), Qt.MouseButton.LeftButton, pos=pos)
            QTest.mouseDClick(items.viewport(), Qt.MouseButton.LeftButton, pos=pos)
        else:
            QTest.mouseClick(items.viewport(), Qt.MouseButton.LeftButton, pos=pos)
        self.done.append(f"{'double-click' if double else 'click'} {what or item.text()}")

    def key(self, widget: QWidget, key: Any, what: str) -> None:
        QTest.keyClick(widget, key)
        self.done.append(f"key {what}")
