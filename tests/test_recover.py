"""Recover in one place (issue #19): after a STOP in the middle of an exercise, the alarm banner's
Recover acknowledges the alarms in the session operator's name, resets the e-stop and the robot's
error, and starts the interrupted exercise again: STOP -> running again in two actions, each step
in the session record with the operator's name."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from PySide6.QtWidgets import QMessageBox

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow

ROOT = Path(__file__).resolve().parent.parent


def test_stop_to_running_again_in_two_actions(qtbot, tmp_path, monkeypatch) -> None:
    manager = LinarmppManager(AppConfig())
    events: list[tuple[str, dict[str, Any]]] = []
    manager.start()
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=20000)
        manager.start_session("P-RECOVER", "Dr Rossi", root=tmp_path)
        manager.bus.listen("test", lambda r: events.append((r.kind, r.data)))
        console = window.frames["CommandsFrame"].panels["ScriptConsole"]
        console.load_file(ROOT / "resources" / "scripts" / "trigger_exercise.py")
        assert console.start_script()
        runner = console.runner
        robot = manager.driver("linarm")
        # STOP in the middle of the exercise: the script running and the robot out of Idle (homing
        # or moving; waiting for the whole homing made the test hostage to a loaded machine).
        qtbot.waitUntil(lambda: runner.running and robot.latest("linarm.state") is not None
                        and robot.latest("linarm.state").controlState != 0, timeout=20000)

        window.estop_button.click()  # the STOP (the script ends by itself or Recover stops it)
        banner = window.alarm_banner
        qtbot.waitUntil(lambda: not banner.recover_button.isHidden(), timeout=2000)
        assert banner.current is not None and "STOP" in banner.label.full_text()
        assert not any(b.isVisible() for b in window.findChildren(QMessageBox))

        actions = 0
        banner.recover_button.click()
        actions += 1
        dialog = banner.dialog
        assert dialog is not None and dialog.restart_button is not None, runner.result
        assert dialog.operator.text() == "Dr Rossi", "the session's operator, never retyped"
        assert "trigger_exercise.py" in dialog.restart_button.text()
        dialog.restart_button.click()
        actions += 1
        qtbot.waitUntil(lambda: runner.running, timeout=10000)
        assert actions <= 3
        sup = manager.supervisor
        assert not sup.estop_latched
        assert not [a for a in sup.alarms() if not a.acknowledged]
        steps = [d for k, d in events if k == "recovery"]
        names = [d["step"] for d in steps]
        assert names[:1] == ["start"] and "exercise_restarted" in names and "estop_reset" in names
        assert all(d["operator"] == "Dr Rossi" for d in steps)
        assert all(d.get("operator") == "Dr Rossi" for k, d in events if k == "alarm_acknowledged")
        assert banner.recover_button.isHidden()
    finally:
        console = window.frames["CommandsFrame"].panels.get("ScriptConsole")
        if console is not None:
            console.runner.stop("test over", wait_s=2.0)
        monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
        window.close()
        manager.shutdown()
