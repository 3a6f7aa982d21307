"""The window thread's heartbeat for the GUI watch (issue #37, app.gui_watch): a Qt timer on the window's thread
that beats every BEAT_PERIOD_S — to the watch's thread in this process and to the FES guardian in its own. The
timer runs only when the window's thread returns to its event loop (a modal dialog's loop counts): a slot that
holds the thread stops the beats, whatever it is waiting on."""

from __future__ import annotations

from typing import Any

from PySide6.QtCore import QObject, QTimer

from app.core import streams
from app.gui_watch import BEAT_PERIOD_S, GUARDIAN_WINDOW_TRIP_S, GuiWatch, what_drives


class GuiHeartbeat(QObject):
    """Beats ``watch`` from the thread it lives on (the window's) until :meth:`close`."""

    def __init__(self, watch: GuiWatch, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.watch = watch
        self._on_close: list[Any] = []
        self.timer = QTimer(self)
        self.timer.setInterval(round(BEAT_PERIOD_S * 1000))
        self.timer.timeout.connect(self._beat)
        self.timer.start()
        watch.beat()

    def _beat(self) -> None:
        self.watch.beat()

    def close(self) -> None:
        """The window closes: no more beats, no more judgement (and the guardian stops watching the window)."""
        self.timer.stop()
        self.watch.close()
        for fn in self._on_close:
            fn()
        self._on_close.clear()


def install_gui_watch(manager: Any, parent: QObject | None = None) -> GuiHeartbeat:
    """Watch the calling (window's) thread for ``manager``'s devices; the FES guardian, when there is one, is fed
    the window's beats too."""
    watch = GuiWatch(manager.supervisor, lambda: what_drives(manager))
    heartbeat = GuiHeartbeat(watch, parent)
    fes = manager.driver(streams.FES)
    guardian = getattr(fes, "guardian", None)
    if guardian is not None and hasattr(guardian, "window_beat"):
        watch.beat_listeners.append(lambda now: guardian.window_beat(GUARDIAN_WINDOW_TRIP_S, now))
        heartbeat._on_close.append(guardian.window_off)
    return heartbeat
