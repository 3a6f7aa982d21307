"""Issue #30 item 6: opening the Script tab with a run's status ("Running trigger_exercise.py — 967 s") shrank
the Values frame from ~660 px (to 308 px here with a long status): the status label asked for its whole text's
width. It is elided now, whole in its tooltip, and the Values frame keeps its width."""

from __future__ import annotations

from PySide6.QtCore import Qt

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow


def test_a_long_script_status_does_not_squeeze_the_values(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    window = MainWindow(manager)
    qtbot.addWidget(window)
    try:
        window.setWindowState(Qt.WindowState.WindowNoState)
        window.resize(1366, 768)
        window.show()
        window._reset_layout(short=True)
        window.show_tab("Robot")
        qtbot.wait(300)
        values = window.docks["ValuesFrame"]
        before = values.width()
        console = window.frames["CommandsFrame"].panels["ScriptConsole"]
        window.show_tab("Script")
        long_status = "Running trigger_exercise.py — 967 s, " + "a status that goes on " * 6
        console.status.setText(long_status)
        qtbot.wait(300)
        assert values.width() >= before - 2, (before, values.width())
        assert console.status.text() == long_status  # the whole text is kept
        assert console.status.toolTip() == long_status  # and shown in the tooltip when elided
    finally:
        window.close()
        manager.shutdown()
