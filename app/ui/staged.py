"""Work on the GUI thread done a piece per turn of the event loop (issue #37: a window opened during a therapy must
not hold that thread longer than 50 ms in one turn; the GUI watch judges its stalls while the patient is driven).

The pieces are the steps of a generator: each ``next()`` does one piece and yields. :class:`Steps` runs one per
turn, by a timer -- not by posted calls (``QTimer.singleShot(0, ...)``): Qt holds its timers back while posted
calls follow one another (a timer that has fired waits until the posted events are done), so a chain of posted
pieces starved every timer of the window, the GUI watch's heartbeat among them, which then saw two or three pieces
as one stall."""

from __future__ import annotations

from collections.abc import Iterator

from PySide6.QtCore import QObject, QTimer, Signal


class Steps(QObject):
    """Runs ``steps`` a step per turn of the event loop once started; ``done`` when they are exhausted. Stopped
    (the window closed), the rest is not run."""

    done = Signal()

    def __init__(self, steps: Iterator[None], parent: QObject | None = None) -> None:
        super().__init__(parent)
        self._steps: Iterator[None] | None = steps
        self.started = False
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.timeout.connect(self._step)

    @property
    def running(self) -> bool:
        return self._steps is not None

    def start(self, delay_ms: int = 0) -> None:
        """The first step after ``delay_ms`` (again: sooner or later than said before), the others a turn apart."""
        if self._steps is not None:
            self._timer.start(delay_ms)

    def stop(self) -> None:
        self._timer.stop()
        self._steps = None

    def _step(self) -> None:
        if self._steps is None:
            return
        self.started = True
        try:
            next(self._steps)
        except StopIteration:
            self._steps = None
            self.done.emit()
            return
        self._timer.start(0)
