"""Where the application writes: logs, sessions, patient profiles, runtime links.

``LINARMPP_HOME`` overrides the user data folder (tests and portable installs use it).

Everything under the data folder is health data: the folder and its sub-folders are 0700 and the app
sets its umask to 077 at start (``set_private_umask``), so every session file and log is 0600; the
recorder and the logger also set these modes explicitly.  On Windows the per-user data folder
(%LOCALAPPDATA%) is already private to the user by its inherited ACL; POSIX modes do not apply there.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import platformdirs

APP_NAME = "LINarmPP"


PRIVATE_DIR_MODE = 0o700
PRIVATE_FILE_MODE = 0o600


def set_private_umask() -> int:
    """Files the app creates are the user's only (returns the previous umask)."""
    return os.umask(0o077)


class DataFolderError(OSError):
    """A folder of the application's data cannot be made or written (a read-only disk, no permission): ``str()``
    is one sentence naming it (issue #37: every entry point died with a traceback instead)."""

    def __init__(self, path: Path, exc: OSError) -> None:
        reason = exc.strerror or str(exc)
        super().__init__(exc.errno, f"the folder {path} cannot be written ({reason})", str(path))
        self.path = path
        self.reason = reason

    def __str__(self) -> str:
        return f"the folder {self.path} cannot be written ({self.reason})"


def private_dir(path: Path) -> Path:
    """``path`` created if needed and made 0700 (best effort where POSIX modes do not apply). Raises
    :class:`DataFolderError` when it cannot be created."""
    try:
        path.mkdir(parents=True, exist_ok=True, mode=PRIVATE_DIR_MODE)
    except OSError as exc:
        raise DataFolderError(path, exc) from exc
    if os.name == "posix":
        try:
            if path.stat().st_mode & 0o777 != PRIVATE_DIR_MODE:
                os.chmod(path, PRIVATE_DIR_MODE)
        except OSError:
            pass
    return path


def data_dir() -> Path:
    override = os.environ.get("LINARMPP_HOME")
    path = Path(override) if override else Path(platformdirs.user_data_dir(APP_NAME, appauthor=False))
    return private_dir(path)


def log_dir() -> Path:
    return private_dir(data_dir() / "logs")


def sessions_dir() -> Path:
    return private_dir(data_dir() / "sessions")


def patients_dir() -> Path:
    return private_dir(data_dir() / "patients")


def runtime_dir() -> Path:
    """A fresh private folder for this run's simulator links (stable names for reconnection)."""
    return Path(tempfile.mkdtemp(prefix="linarmpp-"))


def fes_profiles_dir() -> Path:
    """The user's own FES profiles (the bundled examples under resources/ are offered read-only)."""
    return private_dir(data_dir() / "fes_profiles")
