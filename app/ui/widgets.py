"""Small pieces the viewers share."""

from __future__ import annotations

from typing import Any

from PySide6.QtCore import QEvent, QSize, Qt
from PySide6.QtWidgets import QLabel, QSizePolicy, QWidget


def on_screen(widget: QWidget) -> bool:
    """True when some of ``widget`` can be seen: shown (not on a hidden tab, in a closed dock or a
    closed window), its window not minimised, and not clipped away entirely (scrolled out, squeezed
    to nothing). The live views' timers skip their drawing otherwise: the GUI thread must keep idle
    time for the emergency stop, and a view nobody sees is not worth a paint. They catch up when shown."""
    if not widget.isVisible() or widget.window().isMinimized():
        return False
    return not widget.visibleRegion().isEmpty()


class RefreshWhenVisible:
    """Mixin for a live view with a ``refresh()`` driven by a timer connected to ``_tick``: no work
    while nobody can see it, and it catches up at once when shown again."""

    def _tick(self) -> None:
        if on_screen(self):  # type: ignore[arg-type]
            self.refresh()  # type: ignore[attr-defined]

    def showEvent(self, event: Any) -> None:
        super().showEvent(event)  # type: ignore[misc]
        self.refresh()  # type: ignore[attr-defined]


class LabelBoard:
    """A set of value labels by key that are only touched when their text or colour changes: a style
    sheet re-polishes the widget, far too slow for dozens of labels at 20 Hz. Mixed into a viewer that
    fills ``self.values``."""

    values: dict[str, QLabel]

    def _set(self, key: str, text: str, colour: str) -> None:
        shown = self.__dict__.setdefault("_shown", {})
        if shown.get(key) == (text, colour):
            return
        shown[key] = (text, colour)
        label = self.values[key]
        label.setText(text)
        label.setStyleSheet(f"color: {colour};")
        label.setAccessibleName(text)

    def text_of(self, key: str) -> str:
        """The text shown for ``key``."""
        return self.values[key].text()


class ElidedLabel(QLabel):
    """A one-line plain-text label that elides its end when narrower than its text, and then shows the
    whole text as its tooltip (the only acceptable clipping: where the room truly cannot grow).
    ``full_text()`` is the text it was given; the clipping test reads it."""

    def __init__(self, text: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._full = ""
        self._tip = ""
        self.setTextFormat(Qt.TextFormat.PlainText)
        self.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        self.setMinimumWidth(40)
        self.set_full_text(text)

    def set_full_text(self, text: str, tooltip: str = "") -> None:
        """Show ``text`` (elided when needed); ``tooltip`` is shown always (else the text when elided)."""
        if text == self._full and tooltip == self._tip:
            return
        self._full = text
        self._tip = tooltip
        self.setAccessibleName(text)
        self._elide()

    def full_text(self) -> str:
        return self._full

    def is_elided(self) -> bool:
        return self.text() != self._full

    def sizeHint(self) -> QSize:
        hint = super().sizeHint()
        return QSize(self.fontMetrics().horizontalAdvance(self._full) + 8, hint.height())

    def resizeEvent(self, event: Any) -> None:
        super().resizeEvent(event)
        self._elide()

    def changeEvent(self, event: Any) -> None:
        super().changeEvent(event)
        if event.type() in (QEvent.Type.FontChange, QEvent.Type.StyleChange):
            self._elide()

    def _elide(self) -> None:
        width = self.contentsRect().width() - 2 * self.margin()
        shown = self.fontMetrics().elidedText(self._full, Qt.TextElideMode.ElideRight, max(width, 0))
        if shown != self.text():
            super().setText(shown)
        tip = self._tip or (self._full if shown != self._full else "")
        if tip != self.toolTip():
            self.setToolTip(tip)
