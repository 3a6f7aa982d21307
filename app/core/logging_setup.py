"""Python logging to the console and to a rotating file in the user's data folder.

Every thread's log call only queues its line; one writer thread writes them to the file and the console. The
drivers' real-time threads log too (the LINarm heartbeat's late and withheld beats, a link's loss): a write to a
slow or full disk, or to a console pipe nobody reads, must not hold them. The queue is drained when logging shuts
down (``logging.shutdown``: at exit, and before each forced ``os._exit``), within ``DRAIN_S``."""

from __future__ import annotations

import logging
import logging.handlers
import os
import queue
from collections.abc import Sequence
from pathlib import Path

from app.core.paths import DataFolderError, log_dir

LOG_FORMAT = "%(asctime)s %(levelname)-7s %(threadName)s %(name)s: %(message)s"
DRAIN_S = 2.0  # the most a shutdown waits for the writer to write what is queued (a stuck disk: lines are lost)
_configured: Path | None = None


class BackgroundHandler(logging.handlers.QueueHandler):
    """Queues each record (formatted on the caller's thread: no I/O there) for ``handlers``, written by one writer
    thread. ``close`` drains the queue (within ``DRAIN_S``) and ends the writer."""

    def __init__(self, handlers: Sequence[logging.Handler]) -> None:
        super().__init__(queue.SimpleQueue())
        self.listener: logging.handlers.QueueListener | None = logging.handlers.QueueListener(
            self.queue, *handlers, respect_handler_level=True)
        self.listener.start()
        writer = getattr(self.listener, "_thread", None)
        if writer is not None:
            writer.name = "log-writer"

    def close(self) -> None:
        listener, self.listener = self.listener, None
        writer = getattr(listener, "_thread", None)
        if listener is not None and writer is not None:
            listener.enqueue_sentinel()
            writer.join(DRAIN_S)
            listener._thread = None
        for handler in listener.handlers if listener is not None else ():
            handler.close()  # its own: written by the writer only
        super().close()


class _PrivateRotatingFileHandler(logging.handlers.RotatingFileHandler):
    """Every rotated-in log file is 0600 too, whatever the umask."""

    def _open(self):  # type: ignore[no-untyped-def]
        stream = super()._open()
        try:
            os.chmod(self.baseFilename, 0o600)
        except OSError:
            pass
        return stream


def setup_logging(level: int = logging.INFO, console: bool = True) -> Path:
    """Configure the root logger once; return the log file's path (shown in Help → About).

    Raises :class:`app.core.paths.DataFolderError` (one sentence naming the folder) when the log cannot be written:
    a read-only data folder is said in one line by the entry point, not as a traceback (issue #37)."""
    global _configured
    if _configured is not None:
        return _configured
    folder = log_dir()
    path = folder / "linarmpp.log"
    try:
        path.touch(mode=0o600, exist_ok=True)
        with open(path, "a", encoding="utf-8"):  # touch succeeds on an existing file of a read-only disk
            pass
    except OSError as exc:
        raise DataFolderError(folder, exc) from exc
    try:
        os.chmod(path, 0o600)  # the log names patients and operators: the user only
    except OSError:
        pass
    root = logging.getLogger()
    root.setLevel(level)
    try:
        file_handler = _PrivateRotatingFileHandler(path, maxBytes=5_000_000, backupCount=5, encoding="utf-8")
    except OSError as exc:
        raise DataFolderError(folder, exc) from exc
    file_handler.setFormatter(logging.Formatter(LOG_FORMAT))
    handlers: list[logging.Handler] = [file_handler]
    if console:
        stream = logging.StreamHandler()
        stream.setFormatter(logging.Formatter(LOG_FORMAT))
        handlers.append(stream)
    root.addHandler(BackgroundHandler(handlers))
    _configured = path
    return path


def log_file() -> Path | None:
    return _configured


def shutdown() -> None:
    """End the configured logging, its queue drained and its writer thread ended; ``setup_logging`` may then
    configure it again (a test that ran an entry point in-process)."""
    global _configured
    root = logging.getLogger()
    for handler in root.handlers[:]:
        if isinstance(handler, BackgroundHandler):
            root.removeHandler(handler)
            handler.close()
    _configured = None
