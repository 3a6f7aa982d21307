"""Python logging to the console and to a rotating file in the user's data folder."""

from __future__ import annotations

import logging
import logging.handlers
import os
from pathlib import Path

from app.core.paths import DataFolderError, log_dir

LOG_FORMAT = "%(asctime)s %(levelname)-7s %(threadName)s %(name)s: %(message)s"
_configured: Path | None = None


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
    root.addHandler(file_handler)
    if console:
        stream = logging.StreamHandler()
        stream.setFormatter(logging.Formatter(LOG_FORMAT))
        root.addHandler(stream)
    _configured = path
    return path


def log_file() -> Path | None:
    return _configured
