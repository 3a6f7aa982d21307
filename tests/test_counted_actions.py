"""Counted actions in the real window (issue #36, acceptance 2), every click, double-click and typed field through
the widgets a clinician uses (tests/ui_actions.py: a field typed counts one):

* a new patient with a two-step plan to the first exercise running: ≤ 12 (counted: 9);
* STOP → the same exercise running: ≤ 2 (counted: 2);
* a returning patient to the plan's first exercise running: ≤ 3 (counted: 3).

The counts are printed (``-s``) for the lead's note, with each action named.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import QSettings, Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QDialogButtonBox, QMessageBox

from app.core.config import AppConfig, UdpEndpoint
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow
from tests.ui_actions import Actions

pytestmark = pytest.mark.realtime

OPERATOR = "Dr Paolo Neri"


@pytest.fixture
def window(qtbot: Any, monkeypatch: Any, tmp_path: Path) -> Iterator[MainWindow]:
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = AppConfig()
    cfg = replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"), vr=UdpEndpoint(mode="off")))
    manager = LinarmppManager(cfg)
    manager.start()
    win = MainWindow(manager)
    qtbot.addWidget(win)
    win.resize(1366, 768)
    win.show()
    settings = QSettings()
    before = settings.value("session/operator", "")
    settings.remove("session/operator")  # a first day on this computer: no last operator to offer
    try:
        qtbot.waitUntil(manager.all_connected, timeout=30000)
        yield win
    finally:
        console = win.frames["CommandsFrame"].panels.get("ScriptConsole")
        if console is not None:
            console.runner.stop("test over", wait_s=2.0)
        monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
        win.close()
        manager.shutdown()
        if before:
            settings.setValue("session/operator", before)


def _running(manager: LinarmppManager, runner: Any) -> bool:
    run = manager.runs.current()
    return runner.running and run is not None and run.state not in ("starting", "homing")


def test_the_counted_actions_of_a_day(qtbot: Any, window: MainWindow, monkeypatch: Any) -> None:
    manager = window.manager
    panel = window.frames["CommandsFrame"].panels["ExercisesPanel"]
    window.show_tab("Exercises")
    runner = panel.runner
    a = Actions()

    # A new patient with a two-step plan, to the first exercise running.
    a.click(panel.new_patient_button, "New patient…")
    new = panel.patient_dialog
    qtbot.waitExposed(new)
    a.type(new.id_edit, "PZ-NEW-7", "patient ID")
    a.type(new.name_edit, "Lucia Ferri", "name")
    a.click(new.findChild(QDialogButtonBox).button(QDialogButtonBox.StandardButton.Save), "Save (the profile)")
    qtbot.waitUntil(lambda: getattr(panel, "plan_dialog", None) is not None and panel.plan_dialog.isVisible(),
                    timeout=3000)
    plan = panel.plan_dialog
    qtbot.waitExposed(plan)
    a.pick(plan.library_list, 0, "Trigger reaching", double=True)
    a.pick(plan.library_list, 1, "Assisted reaching with FES", double=True)
    assert [plan.step_list.item(i).text()[:3] for i in range(plan.step_list.count())] == ["1. ", "2. "]
    a.click(plan.buttons.button(QDialogButtonBox.StandardButton.Save), "Save (the plan)")
    qtbot.waitUntil(lambda: not plan.isVisible() and panel.selected_patient() == "PZ-NEW-7", timeout=3000)
    a.type(panel.operator_edit, OPERATOR, "operator")
    a.click(panel.session_button, panel.session_button.text())
    qtbot.waitUntil(lambda: _running(manager, runner), timeout=30000)
    new_patient = a.done[:]
    assert manager.runs.current().program.ident == "trigger_reaching"
    assert len(new_patient) <= 12, new_patient

    # STOP → the same exercise running.
    QTest.keyClick(window, Qt.Key.Key_F12)
    qtbot.waitUntil(lambda: not runner.running, timeout=5000)
    stopped = manager.runs.last()
    mark = a.count
    banner = window.alarm_banner
    qtbot.waitUntil(lambda: not banner.recover_button.isHidden(), timeout=5000)
    a.click(banner.recover_button, "Recover…")
    a.click(banner.dialog.continue_button or banner.dialog.restart_button, "Recover and continue")
    qtbot.waitUntil(lambda: _running(manager, runner) and manager.runs.current().restart_of == stopped.run_id,
                    timeout=30000)
    stop_to_running = a.since(mark)
    assert len(stop_to_running) <= 2, stop_to_running

    runner.stop("the counted day goes on", wait_s=3.0)
    monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
    window.end_session()
    qtbot.waitUntil(lambda: manager.recorder is None and panel.session_box.isVisible(), timeout=10000)

    # A returning patient, to the plan's first exercise running.
    mark = a.count
    row = next(i for i in range(panel.patient_list.count()) if "PZ-NEW-7" in panel.patient_list.item(i).text())
    a.pick(panel.patient_list, row, "the patient")
    a.click(panel.last_operator_button, panel.last_operator_button.text())
    a.click(panel.session_button, panel.session_button.text())
    qtbot.waitUntil(lambda: _running(manager, runner), timeout=30000)
    returning = a.since(mark)
    assert manager.runs.current().program.ident == "trigger_reaching" and manager.operator == OPERATOR
    assert len(returning) <= 3, returning
    print(f"\nnew patient with a two-step plan -> first exercise running: {len(new_patient)} actions: {new_patient}"
          f"\nSTOP -> the same exercise running: {len(stop_to_running)} actions: {stop_to_running}"
          f"\nreturning patient -> first exercise running: {len(returning)} actions: {returning}")
    runner.stop("test over", wait_s=3.0)
