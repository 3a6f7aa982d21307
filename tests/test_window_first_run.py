"""Issue #30 item 7: on its first run the window takes the whole screen, with or without a window manager
(without one, "maximised" alone left it 1366×768 in a corner of a 1920×1080 screen)."""

from __future__ import annotations

from PySide6.QtCore import QSettings, Qt

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow


def test_first_run_fills_the_screen(qtbot) -> None:
    settings = QSettings()
    for key in ("main/geometry", "main/state"):
        settings.remove(key)
    manager = LinarmppManager(AppConfig(), factories={})  # no device: the window alone
    window = MainWindow(manager)
    qtbot.addWidget(window)
    try:
        screen = window.screen().availableGeometry()
        if screen.width() >= 1366 and screen.height() >= 768:
            assert window.geometry().size() == screen.size() or window.isMaximized()
            assert window.width() >= screen.width() - 2 and window.height() >= screen.height() - 40
        else:  # a small (offscreen) screen: the 1366×768 the layout is designed for
            assert (window.width(), window.height()) == (1366, 768)
        assert window.windowState() & Qt.WindowState.WindowMaximized
    finally:
        window.close()
        manager.shutdown()
