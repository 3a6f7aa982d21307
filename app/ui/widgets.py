"""Small pieces the viewers share."""

from __future__ import annotations

from PySide6.QtWidgets import QLabel


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
