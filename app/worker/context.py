"""What a job of the worker process gets besides its arguments (app/worker/jobs.py, process.py)."""

from __future__ import annotations

import os
import threading
import time

from app.worker.protocol import LinkClosed, Sender

_PROGRESS_EVERY_S = 0.05  # at most 20 progress messages a second


class Cancelled(Exception):
    """The application asked the running task to stop."""


class JobError(Exception):
    """A task that cannot do what was asked: ``str()`` is the sentence the user reads."""


class JobContext:
    """What a job gets besides its arguments: progress (which also answers a cancel), and ``retire`` (this worker
    should not run another task: native code failed in it)."""

    def __init__(self, task_id: int, sender: Sender | None, cancelled: threading.Event | None = None) -> None:
        self.task_id = task_id
        self._sender = sender
        self._cancelled = cancelled or threading.Event()
        self._last = 0.0
        self.retire = False

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    def check(self) -> None:
        if self._cancelled.is_set():
            raise Cancelled()

    def progress(self, fraction: float, text: str = "") -> bool:
        """Report how far the task is (0..1); False once cancelled (app/session/export.py's Progress protocol)."""
        now = time.monotonic()
        if self._sender is not None and (now - self._last >= _PROGRESS_EVERY_S or fraction >= 1.0):
            self._last = now
            try:
                self._sender.send("progress", self.task_id, float(min(1.0, max(0.0, fraction))), text)
            except LinkClosed:
                os._exit(0)  # the application has gone: nothing to report to
        return not self._cancelled.is_set()

    def step(self, fraction: float, text: str = "") -> None:
        """Progress, raising Cancelled when asked to stop."""
        if not self.progress(fraction, text):
            raise Cancelled()
