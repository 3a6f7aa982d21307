"""Small pieces the viewers share."""

from __future__ import annotations

from typing import Any

from PySide6.QtWidgets import QLabel, QWidget


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
