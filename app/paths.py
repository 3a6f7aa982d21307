"""Where the application writes: logs, sessions, patient profiles, runtime links.

``LINARMPP_HOME`` overrides the user data folder (tests and portable installs use it).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import platformdirs

APP_NAME = "LINarmPP"


def data_dir() -> Path:
    override = os.environ.get("LINARMPP_HOME")
    path = Path(override) if override else Path(platformdirs.user_data_dir(APP_NAME, appauthor=False))
    path.mkdir(parents=True, exist_ok=True)
    return path


def log_dir() -> Path:
    path = data_dir() / "logs"
    path.mkdir(parents=True, exist_ok=True)
    return path


def sessions_dir() -> Path:
    path = data_dir() / "sessions"
    path.mkdir(parents=True, exist_ok=True)
    return path


def patients_dir() -> Path:
    path = data_dir() / "patients"
    path.mkdir(parents=True, exist_ok=True)
    return path


def runtime_dir() -> Path:
    """A fresh private folder for this run's simulator links (stable names for reconnection)."""
    return Path(tempfile.mkdtemp(prefix="linarmpp-"))
