"""The window's side of the worker process (issue #37): a thin Qt adapter on app.worker.TaskService.

Tasks are submitted from the GUI thread and their progress and end come back on the GUI thread (a queued signal
from the service's link thread), so ``on_done(task)`` may build widgets. ``run(..., parent=widget)`` shows a
progress dialog with Cancel after a moment (never modal: nothing waits on the GUI thread, and F12 and every other
window stay live). A failed task's sentence is the caller's to show (``task.error``); nothing here raises.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable
from typing import Any

from PySide6.QtCore import QObject, Qt, Signal
from PySide6.QtWidgets import QProgressDialog, QWidget

from app.worker import Task, TaskService

log = logging.getLogger(__name__)

PROGRESS_AFTER_MS = 400  # a task shorter than this shows no dialog
Done = Callable[[Task], Any]


class QtTasks(QObject):
    """Owns a TaskService (or uses the one given) and delivers its tasks' updates on the GUI thread."""

    updated = Signal(object)  # Task, on the GUI thread

    def __init__(self, service: TaskService | None = None, parent: QObject | None = None) -> None:
        super().__init__(parent)
        from app.worker.jobs import import_result_types

        import_result_types()  # now, not while unpickling a result during a therapy (see there)
        self.service = service or TaskService()
        self._owns = service is None
        self._handlers: dict[int, tuple[Done | None, QProgressDialog | None]] = {}
        self._from_link.connect(self._deliver, Qt.ConnectionType.QueuedConnection)
        self.closed = False
        if self._owns:  # a widget deleted without being closed still ends its worker
            weakref.finalize(self, self.service.close)

    _from_link = Signal(object)

    def warm(self) -> None:
        """Start the worker now (off the GUI thread), so the first task does not wait for it."""
        if not self.closed:
            self.service.warm()

    def run(self, kind: str, *args: Any, title: str, on_done: Done | None = None, parent: QWidget | None = None,
            outputs: tuple[Any, ...] = (), **kwargs: Any) -> Task:
        """Submit ``kind``; ``on_done(task)`` on the GUI thread when it ends. With ``parent``, a progress dialog
        (its label the task's title and step, a Cancel button) shows if it takes longer than a moment."""
        dialog = None
        if parent is not None:
            dialog = QProgressDialog(f"{title}…", "Cancel", 0, 1000, parent)
            dialog.setWindowTitle(title)
            dialog.setWindowModality(Qt.WindowModality.NonModal)
            dialog.setMinimumDuration(PROGRESS_AFTER_MS)
            dialog.setAutoClose(False)
            dialog.setAutoReset(False)
            dialog.setValue(0)
        task = self.service.submit(kind, *args, title=title, on_update=self._from_link.emit, outputs=outputs,
                                   **kwargs)
        self._handlers[task.id] = (on_done, dialog)
        if dialog is not None:
            dialog.canceled.connect(task.cancel)
        if task.done:  # refused at once (the service is closing)
            self._deliver(task)
        return task

    def _deliver(self, task: Task) -> None:
        handler = self._handlers.get(task.id)
        if handler is None:
            return
        on_done, dialog = handler
        if dialog is not None and not task.done:
            dialog.setValue(int(task.fraction * 1000))
            if task.text:
                dialog.setLabelText(f"{task.title}: {task.text}…")
        self.updated.emit(task)
        if not task.done:
            return
        del self._handlers[task.id]
        if dialog is not None:
            dialog.canceled.disconnect()
            dialog.close()
            dialog.deleteLater()
        if on_done is not None:
            try:
                on_done(task)
            except Exception:  # a result the window could not show: said in the log, the window goes on
                log.exception("showing the result of %s failed", task.title)

    def close(self) -> None:
        """End the worker (when this adapter made the service) and forget pending callbacks."""
        if self.closed:
            return
        self.closed = True
        for _on_done, dialog in self._handlers.values():
            if dialog is not None:
                dialog.close()
        self._handlers.clear()
        if self._owns:
            self.service.close()
