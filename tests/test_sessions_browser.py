"""Sessions browser, patient dialog and start-session dialog."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QDialogButtonBox, QTableWidgetItem

from app.core.bus import Channel, StreamSpec
from app.core.config import AppConfig
from app.safety.supervisor import AlarmLevel, SafetySupervisor
from app.session.export import load_hdf5
from app.session.recording import SessionRecorder, load_session
from app.therapy.patients import PatientProfile, load_patient, save_patient
from tests.fakes import ListenerDriver
from tests.recorder_host import recorder_host
from tests.waits import WORKER_TASK_MS


def _Driver() -> ListenerDriver:
    return ListenerDriver(StreamSpec("fake.main", (Channel("x", "m", "Position"),), 50.0))



def record(root, patient: str, script: str | None, alarm: bool, crashed: bool = False):
    driver = _Driver()
    config = AppConfig()
    manager = recorder_host(config, {"fake": driver})
    recorder = SessionRecorder()
    folder = recorder.start(manager, patient, "dr_bianchi", root=root)
    t0 = time.monotonic()
    for i in range(500):
        driver.listeners[0]("fake.main", t0 + i / 50.0, SimpleNamespace(x=float(np.sin(i / 10))))
    if script:
        recorder.event("script_start", "dr_bianchi", name=script, text=f"# {script}\nlinarm.moveCentreTo(0.2)\n")
    if alarm:
        manager.supervisor.raise_alarm(AlarmLevel.WARNING, "physio", "sensor off")
    recorder.stop()
    if crashed:  # what a killed process leaves: the start manifest
        manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
        manifest.update(status="recording", end=None)
        manifest.pop("duration_s")
        (folder / "manifest.json").write_text(json.dumps(manifest), encoding="utf-8")
    return folder


@pytest.fixture
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    return tmp_path


def test_browser_lists_opens_exports_and_replays(home, qtbot) -> None:
    from app.ui.sessions_browser import SessionsBrowser

    root = home / "sessions"
    first = record(root, "P030", "reach.py", alarm=True)
    second = record(root, "P030", None, alarm=False, crashed=True)
    record(root, "P031", None, alarm=False)
    browser = SessionsBrowser(root)
    qtbot.addWidget(browser)
    browser.set_patient("P030")
    assert browser.table.rowCount() == 2
    rows = {browser.table.item(r, 0).data(0x0100): [browser.table.item(r, c).text() for c in range(6)]
            for r in range(2)}
    assert rows[str(first)][2:4] == ["reach.py", "1"] and rows[str(first)][5] == "complete"
    assert rows[str(second)][2:4] == ["—", "0"] and rows[str(second)][5] == "interrupted"
    assert rows[str(first)][1] == "0:00", "duration from the manifest (start to stop)"
    assert rows[str(second)][1] == "0:10", "interrupted: duration up to the last sample written"

    browser.select_folder(first)
    with qtbot.waitSignal(browser.opened, timeout=WORKER_TASK_MS) as opened:  # read in the worker process (#37)
        browser.open_details()
    details = opened.args[0]
    assert details.events.rowCount() == len(load_session(first).events)
    assert "linarm.moveCentreTo(0.2)" in details.script_text.toPlainText()

    done: list[tuple[bool, str]] = []
    job = browser.export(first, "hdf5", home / "out.h5", on_done=lambda ok, msg: done.append((ok, msg)))
    qtbot.waitUntil(lambda: bool(done), timeout=WORKER_TASK_MS)
    assert done[0][0] and "Exported" in browser.status.text() and "verified" in browser.status.text()
    assert job.fraction == 1.0
    exported = load_hdf5(home / "out.h5").streams["fake.main"]
    assert np.array_equal(exported.data["x"], load_session(first).streams["fake.main"].data["x"])

    with qtbot.waitSignal(browser.opened, timeout=WORKER_TASK_MS) as opened:
        browser.replay()
    window = opened.args[0]
    qtbot.addWidget(window)
    qtbot.waitUntil(lambda: window.is_ready, timeout=5000)  # built a piece per turn of the event loop
    assert "fake.main.x" in window.plots.curves
    assert len(window.plots.curves["fake.main.x"].getData()[1]) > 0


def test_cancelled_export_reports_and_leaves_nothing(home, qtbot) -> None:
    from app.ui.sessions_browser import ExportJob

    folder = record(home / "sessions", "P032", None, alarm=False)
    job = ExportJob(folder, "csv", home / "csv_out")
    job.cancel()
    job.start()
    qtbot.waitUntil(lambda: job.done, timeout=WORKER_TASK_MS)
    assert not job.ok and job.message == "export cancelled"
    assert not (home / "csv_out").exists() and not list(home.glob(".csv_out*"))


def test_patient_dialog_shows_validation_at_the_field(home, qtbot) -> None:
    from app.ui.patient_dialog import PatientDialog

    dialog = PatientDialog(None, AppConfig().safety)
    qtbot.addWidget(dialog)
    dialog.id_edit.setText("P040")
    dialog.k_r.setText("1.5")
    assert dialog.validate() is None
    assert "assistance.k_r" in dialog.error_label.text() and "outside the allowed range" in dialog.error_label.text()
    assert dialog.k_r.styleSheet() != ""
    dialog.k_r.setText("0.7")
    dialog.fields["robot.max_velocity_m_s"].setText("0.9")
    dialog.accept()
    assert dialog.result() == 0 and "robot.max_velocity_m_s" in dialog.error_label.text()
    assert "configured limit" in dialog.error_label.text()
    dialog.fields["robot.max_velocity_m_s"].setText("0.2")
    dialog.caps_table.setItem(0, 0, QTableWidgetItem("45"))
    assert dialog.validate() is None and "fes.caps.1.max_current_ma" in dialog.error_label.text()
    dialog.caps_table.setItem(0, 0, QTableWidgetItem("25"))
    dialog.fields["scores.fugl_meyer_ue"].setText("30")
    dialog.notes.setPlainText("left-handed")
    dialog.accept()
    assert dialog.result() == 1, dialog.error_label.text()
    saved = load_patient("P040", AppConfig().safety)
    assert (saved.assistance.k_r, saved.robot.max_velocity_m_s, saved.scores.fugl_meyer_ue) == (0.7, 0.2, 30)
    assert saved.fes.caps[1].max_current_ma == 25.0 and saved.notes == "left-handed"

    again = PatientDialog(None, AppConfig().safety)
    qtbot.addWidget(again)
    again.id_edit.setText("P040")
    again.accept()
    assert again.result() == 0 and "already exists" in again.error_label.text()

    edit = PatientDialog(saved, AppConfig().safety)
    qtbot.addWidget(edit)
    assert edit.id_edit.isReadOnly() and edit.k_r.text() == "0.7"
    edit.k_f.setText("0.1")
    edit.accept()
    assert edit.result() == 1 and load_patient("P040").assistance.k_f == 0.1
    assert load_patient("P040").created == saved.created


def test_start_session_needs_patient_and_operator(home, qtbot) -> None:
    from app.ui.patient_dialog import StartSessionDialog

    dialog = StartSessionDialog(AppConfig().safety)
    qtbot.addWidget(dialog)
    ok = dialog.buttons.button(QDialogButtonBox.StandardButton.Ok)
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
    assert not ok.isEnabled() and "Create a patient" in dialog.problem.text()
    save_patient(PatientProfile(patient_id="P050"))
    (home / "home" / "patients" / "P051.yaml").write_text("patient_id: P051\nassistance: {k_r: 7}\n", encoding="utf-8")
    dialog.reload("P050")
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
    dialog.operator_edit.setText("")
    assert not ok.isEnabled() and "operator" in dialog.problem.text()
    dialog.operator_edit.setText("dr_verdi")
    assert ok.isEnabled()
    assert dialog.values() == ("P050", "dr_verdi", "")
    dialog.reload("P051")
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
    assert not ok.isEnabled() and "assistance.k_r" in dialog.problem.text()


def test_statuses_say_what_happened(home, qtbot) -> None:
    """Issue #19: aborted exercises and stop alarms are not "complete"; the session being recorded
    is "in progress", not "interrupted"."""
    from app.session.recording import list_sessions
    from app.ui.sessions_browser import SessionsBrowser, session_status

    root = home / "sessions"
    clean = record(root, "P040", "reach.py", alarm=False)
    time.sleep(1.1)  # session folders are named by the second
    driver = _Driver()
    config = AppConfig()
    sup = SafetySupervisor(config.safety)
    manager = recorder_host(config, {"fake": driver}, sup)
    recorder = SessionRecorder()
    rough = recorder.start(manager, "P040", "dr_bianchi", root=root)
    for i in range(5):
        recorder.event("script_start", "dr_bianchi", name=f"ex{i}.py", text="pass")
        recorder.event("script_stop", "dr_bianchi", name=f"ex{i}.py", status="stopped",
                       reason="robot STOP: WATCHDOG")
    sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: WATCHDOG")
    recorder.stop()
    time.sleep(1.1)
    live = SessionRecorder()
    now = live.start(manager, "P040", "dr_bianchi", root=root)
    try:
        by_folder = {s.folder: s for s in list_sessions("P040", root)}
        assert session_status(by_folder[clean]).text == "complete"
        rough_status = session_status(by_folder[rough])
        assert rough_status.text == "ended: 5 of 5 exercise(s) aborted, 1 stop alarm(s)" and not rough_status.ok
        assert "WATCHDOG" in rough_status.tooltip
        assert session_status(by_folder[now]).text == "interrupted"  # nobody says it is being recorded
        browser = SessionsBrowser(root, active=lambda: now)
        qtbot.addWidget(browser)
        browser.set_patient("P040")
        statuses = {browser.table.item(r, 0).data(Qt.ItemDataRole.UserRole): browser.table.item(r, 5).text()
                    for r in range(browser.table.rowCount())}
        assert statuses[str(now)] == "in progress"
        assert statuses[str(rough)].startswith("ended: 5 of 5")
        assert statuses[str(clean)] == "complete"
    finally:
        live.stop()


def test_patient_dialog_browses_for_the_fes_profile(home, qtbot, monkeypatch) -> None:
    """Issue #19: the FES profile was free text only."""
    from PySide6.QtWidgets import QFileDialog

    from app.ui.fes_panel import PROFILES_DIR
    from app.ui.patient_dialog import PatientDialog

    dialog = PatientDialog(None, AppConfig().safety)
    qtbot.addWidget(dialog)
    monkeypatch.setattr(QFileDialog, "getOpenFileName",
                        lambda *a, **k: (str(PROFILES_DIR / "frontal_reaching.yaml"), ""))
    dialog.fes_browse.click()
    assert dialog.fes_profile.text() == "frontal_reaching.yaml"
    elsewhere = home / "mine.yaml"
    monkeypatch.setattr(QFileDialog, "getOpenFileName", lambda *a, **k: (str(elsewhere), ""))
    dialog.fes_browse.click()
    assert dialog.fes_profile.text() == str(elsewhere)
