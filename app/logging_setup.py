"""Python logging to the console and to a rotating file in the user's data folder."""

from __future__ import annotations

import logging
import logging.handlers
import os
from pathlib import Path

from app.paths import log_dir

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
    """Configure the root logger once; return the log file's path (shown in Help → About)."""
    global _configured
    if _configured is not None:
        return _configured
    path = log_dir() / "linarmpp.log"
    path.touch(mode=0o600, exist_ok=True)
    try:
        os.chmod(path, 0o600)  # the log names patients and operators: the user only
    except OSError:
        pass
    root = logging.getLogger()
    root.setLevel(level)
    file_handler = _PrivateRotatingFileHandler(path, maxBytes=5_000_000, backupCount=5, encoding="utf-8")
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
