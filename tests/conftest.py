"""Suite-wide set-up: a headless Qt platform when there is no display, a private data folder, and
the OpenGL rule (GL tests run only on xcb, e.g. under Xvfb; offscreen GL segfaults uncatchably)."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
    os.environ["QT_QPA_PLATFORM"] = "offscreen"
# Never write into the developer's real data folder or QSettings.
os.environ["LINARMPP_HOME"] = tempfile.mkdtemp(prefix="linarmpp-test-home-")
os.environ.setdefault("PYDEVD_DISABLE_FILE_VALIDATION", "1")

from app.application import share_gl_contexts  # noqa: E402 - must run before pytest-qt creates the app

share_gl_contexts()


def screenshot_path(name: str) -> Path:
    """Where a test saves a screenshot: docs/screenshots when LINARMPP_SCREENSHOTS=1 (to refresh the
    docs), else a temporary folder, so a test run never changes the working tree."""
    if os.environ.get("LINARMPP_SCREENSHOTS") == "1":
        folder = ROOT / "docs" / "screenshots"
    else:
        folder = Path(tempfile.gettempdir()) / "linarmpp-test-screenshots"
    folder.mkdir(parents=True, exist_ok=True)
    return folder / name


def gl_available() -> bool:
    from PySide6.QtGui import QGuiApplication

    return QGuiApplication.platformName() == "xcb"


@pytest.fixture
def require_gl(qapp) -> None:
    """Skip before any GL widget exists unless Qt runs on a real X server."""
    if not gl_available():
        pytest.skip(f"OpenGL needs xcb (Xvfb); platform is {qapp.platformName()!r}")


@pytest.fixture(autouse=True, scope="session")
def _qt_identity(qapp):
    from app.application import configure_qt_identity

    configure_qt_identity()
    yield
