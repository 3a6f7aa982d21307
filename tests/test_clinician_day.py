"""A clinician's day in the real window (issue #26, acceptance 2), end to end on simulated devices:

new patient and therapy plan in Session → Patients… → the session started with an explicitly chosen operator →
the plan's first exercise from the Exercises tab → F12 in the middle of it → Recover (restart) → it runs to its
end → a second exercise from the Script tab → end of the session → the session PDF and the progress PDF.

What is checked is what the clinician files: ``pdftotext`` of the session PDF lists every run with its title and
how it ended (the interrupted one too), repetitions numbered within each run, the reaction times the window
showed; neither PDF has overlapping text boxes. With ``LINARMPP_DAY_SHOTS=<folder>`` the screens and PDF pages
are saved there to be looked at (the lead's check, not part of the assertion).
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication, QDialogButtonBox, QMessageBox

from app.config import AppConfig, UdpEndpoint
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow
from tests.pdf_layout import overlaps, pdf_text

pytestmark = pytest.mark.realtime

ROOT = Path(__file__).resolve().parent.parent
PATIENT = "PZ-DAY-01"
OPERATOR = "Dr Giulia Bianchi"
PLAN_PARAMS = {"movements": "3", "start_m": "0.15", "end_m": "0.30", "speed_m_s": "0.2",
               "trigger_threshold_n": "20", "rest_s": "0.3"}
REACTION_DELAY_S = 0.4  # the simulated patient squeezes this long after the handle arrives


def _shot(widget: Any, name: str) -> None:
    folder = os.environ.get("LINARMPP_DAY_SHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        widget.grab().save(str(Path(folder) / f"{name}.png"))


@pytest.fixture
def day(qtbot: Any, monkeypatch: Any, tmp_path: Path) -> Iterator[tuple[LinarmppManager, MainWindow]]:
    # A clinic of its own: patients, sessions and settings under this test's folder (a rerun starts afresh).
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = AppConfig()
    # The assistance link and the VR game play no part in these exercises: off, as a site without them.
    cfg = replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"),
                                       vr=UdpEndpoint(mode="off")))
    manager = LinarmppManager(cfg)
    manager.start()
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.resize(1366, 768)
    window.show()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=30000)
        yield manager, window
    finally:
        for panel in window.frames["CommandsFrame"].panels.values():
            runner = getattr(panel, "runner", None)
            if runner is not None:
                runner.stop("test over", wait_s=2.0)
        monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
        for w in QApplication.topLevelWidgets():
            if w is not window and w.isVisible():
                w.close()
        window.close()
        manager.shutdown()


def test_a_clinicians_day(day: tuple[LinarmppManager, MainWindow], qtbot: Any, monkeypatch: Any,
                          tmp_path: Path) -> None:
    manager, window = day
    commands = window.frames["CommandsFrame"]

    # 1. A new patient and their therapy plan, in Session → Patients…
    from PySide6.QtGui import QAction

    next(a for a in window.findChildren(QAction) if a.text() == "&Patients…").trigger()
    patients = window._patients_window
    qtbot.waitExposed(patients)
    new = patients.new_patient()
    new.id_edit.setText(PATIENT)
    new.name_edit.setText("Maria Esposito")
    new.accept()
    assert new.result() == 1, new.error_label.text()
    qtbot.waitUntil(lambda: patients.selected_id() == PATIENT, timeout=3000)
    plan = patients.edit_plan()
    assert plan is not None
    plan.add_step("trigger_reaching")
    qtbot.waitExposed(plan)
    for name, value in PLAN_PARAMS.items():
        plan.editors[name].setText(value)
    assert plan.error_label.text() == ""
    _shot(plan, "01-plan-dialog")
    plan.accept()
    assert plan.result() == 1, plan.error_label.text()
    _shot(patients, "02-patients-dialog")
    patients.close()

    # 2. The session, with the operator chosen (never pre-filled).
    window.prompt_session()
    start = window._session_dialog
    qtbot.waitExposed(start)
    start.reload(PATIENT)
    assert start.operator_edit.text() == ""
    start.operator_edit.setText(OPERATOR)
    start.buttons.button(QDialogButtonBox.StandardButton.Ok).click()
    qtbot.waitUntil(lambda: manager.recorder is not None, timeout=5000)
    folder = manager.recorder.folder
    assert manager.operator == OPERATOR

    # 3. The plan's first exercise, one click in the Exercises tab (brought forward by the session's start).
    panel = commands.panels["ExercisesPanel"]
    assert commands.tabs.tabText(commands.tabs.currentIndex()) == "Exercises"
    assert panel.exercise is not None and panel.exercise.ident == "trigger_reaching"
    assert panel.values()["movements"] == "3"
    manager.sim_patient().squeeze_at_targets([0.15, 0.30], tolerance=0.006, duration=0.8,
                                             reaction_delay=REACTION_DELAY_S)
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    runner = panel.runner
    _wait(qtbot, manager, window, lambda: manager.runs.current() is not None
          and any(m.end_mono is not None for m in manager.runs.current().repetitions), 60000, "a first repetition")
    first = manager.runs.current()
    assert first.source == "exercises_tab" and first.operator == OPERATOR  # a click's `checked` was its source
    _shot(window, "03-exercise-running")

    # 4. F12 in the middle of it; Recover restarts exactly that run (two actions).
    QTest.keyClick(window, Qt.Key.Key_F12)
    qtbot.waitUntil(lambda: not runner.running, timeout=5000)
    assert manager.runs.get(first.run_id).end_reason == "emergency_stop"
    banner = window.alarm_banner
    qtbot.waitUntil(lambda: not banner.recover_button.isHidden(), timeout=5000)
    _shot(window, "04-after-f12")
    banner.recover_button.click()
    dialog = banner.dialog
    assert dialog is not None and dialog.restart_button is not None
    assert "Trigger reaching" in dialog.restart_button.text()
    _shot(dialog, "05-recover-dialog")
    dialog.restart_button.click()
    qtbot.waitUntil(lambda: manager.runs.current() is not None
                    and manager.runs.current().restart_of == first.run_id, timeout=15000)
    again = manager.runs.current()
    assert again.program == first.program and again.params_dict() == first.params_dict()
    _wait(qtbot, manager, window, lambda: manager.runs.get(again.run_id).end_reason is not None, 120000,
          "the restarted run's end")
    assert manager.runs.get(again.run_id).end_reason == "finished"
    # The exercise's summary (on screen): its reaction times, to be found again in the PDF.
    # The restarted run's own summary (the interrupted run's may have opened first, after the STOP).
    def restarted_summary() -> bool:
        d = panel.summary_dialog
        return d is not None and d.isVisible() and [r.run.run_id for r in d.summary.runs] == [again.run_id]
    _wait(qtbot, manager, window, restarted_summary, 15000, "the restarted run's summary")
    summary = panel.summary_dialog
    _shot(summary, "06-exercise-summary")
    screen_rts = _column_texts(summary, "RT s")
    assert screen_rts and all(t not in ("", "—") for t in screen_rts), screen_rts
    summary.close()

    # 5. A second exercise from the Script tab (the seed's Fig. 18 trigger exercise, its own file).
    manager.sim_patient().squeeze_at_targets([0.10, 0.40], tolerance=0.006, duration=0.8,
                                             reaction_delay=REACTION_DELAY_S)
    window.show_tab("Script")
    console = commands.panels["ScriptConsole"]
    console.load_file(ROOT / "resources" / "scripts" / "trigger_exercise.py")
    assert console.start_script()
    qtbot.waitUntil(lambda: manager.runs.current() is not None
                    and manager.runs.current().program.kind == "script_file", timeout=15000)
    script_run = manager.runs.current()
    _wait(qtbot, manager, window, lambda: manager.runs.get(script_run.run_id).end_reason is not None, 150000,
          "the script run's end")
    assert manager.runs.get(script_run.run_id).end_reason == "finished", console.runner.result
    _shot(window, "07-script-done")
    for w in QApplication.topLevelWidgets():  # a summary the script tab may have opened
        if w is not window and w.isVisible() and w.isModal() is False and "summary" in w.windowTitle().lower():
            w.close()

    # 6. End of the session, then its report and the patient's progress report.
    monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
    window.end_session()
    qtbot.waitUntil(lambda: manager.recorder is None, timeout=10000)
    from app.reports import progress_rows, write_progress_report, write_session_report

    session_pdf, progress_pdf = tmp_path / "session.pdf", tmp_path / "progress.pdf"
    assert write_session_report(folder, session_pdf) >= 1
    assert write_progress_report(PATIENT, progress_pdf, progress_rows(PATIENT)) >= 1
    text = pdf_text(session_pdf)
    runs = [r for r in manager.runs.runs() if r.run_id in (first.run_id, again.run_id, script_run.run_id)] \
        if manager.runs is not None else []
    assert text.count("Trigger reaching") >= 2 and "trigger_exercise.py" in text
    assert "emergency stop" in text and "finished" in text
    assert "Maria Esposito" in text and OPERATOR in text
    for rt in screen_rts:
        assert rt in text, f"reaction time {rt} s shown on screen is not in the PDF"
    # Repetitions numbered within each run: the run headings each followed by a repetition 1.
    assert len(re.findall(r"(?m)^1 ", text)) >= 3, text
    assert overlaps(session_pdf) == [] and overlaps(progress_pdf) == []
    assert "Maria Esposito" in pdf_text(progress_pdf)  # the patient identified on both reports
    # The Script-tab run cues the patient once the robot has arrived; the simulated patient squeezes
    # REACTION_DELAY_S after arriving: the reaction times measured from the record agree (first movement: no
    # squeeze, the script's 10 s timeout moved it; that repetition has none).
    from app.metrics import session_metrics

    by_run = {r["run_id"]: r for r in session_metrics(folder)["runs"]}
    rts = [r["reaction_time_s"] for r in by_run[script_run.run_id]["repetitions"] if r.get("reaction_time_s")]
    assert len(rts) >= 6 and all(abs(rt - REACTION_DELAY_S) < 0.1 for rt in rts), rts
    folder_out = os.environ.get("LINARMPP_DAY_SHOTS")
    if folder_out:
        for pdf in (session_pdf, progress_pdf):
            subprocess.run(["pdftoppm", "-png", "-r", "70", str(pdf), str(Path(folder_out) / pdf.stem)], check=True)
    assert len(runs) == 3


def _wait(qtbot: Any, manager: LinarmppManager, window: MainWindow, cond: Any, timeout_ms: int, what: str) -> None:
    """qtbot.waitUntil, saying on a timeout where the day stood (runs, their states, the window's picture)."""
    try:
        qtbot.waitUntil(cond, timeout=timeout_ms)
    except Exception as exc:
        _shot(window, f"timeout-{what.replace(' ', '-')}")
        runs = [(r.run_id, r.title, r.state, r.end_reason, len(r.repetitions)) for r in manager.runs.runs()] \
            if manager.runs is not None else None
        state = manager.driver("linarm").latest("linarm.state") if manager.driver("linarm") else None
        raise AssertionError(f"timed out waiting for {what}: runs {runs}, robot {state}, "
                             f"alarms {[a.text for a in manager.supervisor.alarms()]}") from exc


def _column_texts(summary: Any, header: str) -> list[str]:
    """The cells of the column ``header`` in every repetition table of an on-screen summary."""
    from PySide6.QtWidgets import QTableWidget

    out: list[str] = []
    for table in summary.findChildren(QTableWidget):
        cols = [table.horizontalHeaderItem(c).text() if table.horizontalHeaderItem(c) else ""
                for c in range(table.columnCount())]
        if header in cols:
            col = cols.index(header)
            out += [table.item(r, col).text() for r in range(table.rowCount()) if table.item(r, col)]
    return out
