"""The patient's record through the archive (issue #39, stage 2): one versioned record per patient across writers.

* The issue's sequence through the application's own entry points: the cap lowered from 25 to 15 mA in the
  Patients window, then a running session's electrode choice accepted (the electrode set-up dialog's Choose),
  then a therapy-plan dialog opened before both saved — the lowered cap, the choice and the plan are all kept
  (on one station, and on two stations sharing the archive).
* Two writers of one patient (two profile forms, on two stations): one saves, the other is refused naming the
  operator, the station and the time; Reload shows the saved values with the form's own change put back; every
  field checked — on SQLite and on the real PostgreSQL server the archive's tests start (tests/postgres.py).
* Start-up: the embedded archive takes the data folder's YAML patients once; an archive newer than the app is one
  sentence and exit 2 headless; an archive that cannot be reached lets the station run, saying patients cannot
  be saved, and refuses a session whose patient cannot be read.

Written so that the sequence and the two forms also run on the code before stage 2 (no ``app.archive.station``:
each station is then its own data folder of YAML files, as it was), where they fail.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtWidgets import QTableWidgetItem

from app.core.config import AppConfig
from app.therapy.patients import (
    ClinicalChannelCap,
    PatientFes,
    PatientProfile,
    PlannedExercise,
    load_patient,
    save_patient,
)

try:
    from app.archive import station
except ImportError:  # the code before stage 2: every station keeps its own YAML folder
    station = None  # type: ignore[assignment]

CFG = AppConfig()
SAFETY = CFG.safety


class Stations:
    """Station A and station B of one clinic: each its own data folder; with stage 2, one archive (the SQLite file
    in A's data folder, opened by each station under its own name) installed as the running station's."""

    def __init__(self, tmp_path: Path, monkeypatch: Any, shared: bool = True) -> None:
        self.monkeypatch = monkeypatch
        self.homes = {"room-A": tmp_path / "A", "room-B": tmp_path / ("B" if shared else "A")}
        self.archives: dict[str, Any] = {}
        if station is not None:
            from app.archive.store import open_archive

            url = f"sqlite:///{tmp_path / 'A' / 'archive.sqlite3'}"
            for name in self.homes:
                self.archives[name] = open_archive(url=url, station=name)

    def use(self, name: str) -> None:
        """Station ``name`` runs from now on (its data folder, its archive connection)."""
        self.monkeypatch.setenv("LINARMPP_HOME", str(self.homes[name]))
        if station is not None:
            station.install(self.archives[name])

    def create(self, profile: PatientProfile, operator: str) -> None:
        if station is not None:
            station.save_profile(profile, expected_version=None, operator=operator, safety=SAFETY)
        else:  # as a clinic does without the archive: the patient made on each station
            for home in set(self.homes.values()):
                save_patient(profile, home / "patients", SAFETY)

    def close(self) -> None:
        if station is not None:
            station.uninstall()
            for a in self.archives.values():
                a.close()


@pytest.fixture
def stations(tmp_path: Path, monkeypatch: Any) -> Iterator[Stations]:
    s = Stations(tmp_path, monkeypatch)
    yield s
    s.close()


def _profile(patient_id: str) -> PatientProfile:
    caps = {1: ClinicalChannelCap(max_current_ma=25.0), 5: ClinicalChannelCap(max_current_ma=20.0)}
    return PatientProfile(patient_id=patient_id, full_name="Maria Esposito", record_number="MRN-39",
                          affected_side="left", fes=PatientFes(caps=caps), notes="first visit",
                          therapy_plan=[PlannedExercise("trigger_reaching", {"movements": 6}, "")])


def _setup_result(district_name: str) -> Any:
    """What an electrode set-up of ``district_name`` measured (every combination up to 10 mA): the dialog's
    Choose saves one of them."""
    from app.therapy.electrodes import CombinationResult, SetupPlan, SetupResult, districts_from_config

    district = districts_from_config(CFG.devices.fes.electrodes)[district_name]
    return SetupResult(district, SetupPlan(ceiling_ma=10.0),
                       [CombinationResult(c, 10, "the therapist's ceiling") for c in district.combinations])


@pytest.mark.parametrize("shared", [True, False], ids=["two stations", "one station"])
def test_lowered_cap_then_a_sessions_electrode_choice_then_an_old_plan_dialog_all_kept(
        qtbot: Any, tmp_path: Path, monkeypatch: Any, shared: bool) -> None:
    """The issue's sequence. Before #36 on one PC the choice put 25 mA back and the plan dialog removed the
    choice; before stage 2, on two stations, the session's station never learnt of the lowered cap (the choice
    was saved with 25 mA) and the plan dialog's station never learnt of the choice."""
    from app.manager import LinarmppManager
    from app.ui.electrode_setup import ElectrodeSetupDialog
    from app.ui.patients_window import PatientsDialog
    from tests.fakes import counter_factory

    st = Stations(tmp_path, monkeypatch, shared=shared)
    manager = None
    try:
        st.use("room-A")
        st.create(_profile("PZ-039"), "dr_rossi")
        # Station B: a session of PZ-039 runs (its copy: 25 mA on channel 1)
        st.use("room-B")
        manager = LinarmppManager(CFG, factories={"alpha": counter_factory(tmp_path, "alpha")})
        manager.start()
        manager.start_session("PZ-039", "dr_verdi", root=tmp_path / "sessions")
        assert manager.patient_profile.fes.caps[1].max_current_ma == 25.0
        # Station A: a plan dialog opened now (its copy: 25 mA, no choice, the old plan) and left open
        st.use("room-A")
        # one station: its Patients window is the session's window's (a change applies to the session at once)
        patients = PatientsDialog(SAFETY, manager=None if shared else manager)
        qtbot.addWidget(patients)
        qtbot.waitUntil(lambda: patients.loaded, timeout=5000)
        patients.search.setText("PZ-039")
        old_plan = patients.edit_plan()
        assert old_plan is not None
        # Station A: the cap lowered from 25 to 15 mA in the Patients window
        edit = patients.edit_profile()
        edit.caps_table.setItem(0, 0, QTableWidgetItem("15"))
        edit.accept()
        assert edit.result() == edit.DialogCode.Accepted, edit.error_label.text()
        if not shared:  # #36 kept: the running session meets 15 mA at once, with the record's new version
            assert manager.patient_profile.fes.caps[1].max_current_ma == 15.0
            assert "channel 1 current cap 25 mA → 15 mA" in patients.session_note.text()
            if station is not None:
                assert manager.patient_version == station.read_record("PZ-039").version == 2
        # Station B: the running session's electrode set-up, its proposal accepted
        st.use("room-B")
        setup = ElectrodeSetupDialog(manager)
        qtbot.addWidget(setup)
        setup.result = _setup_result("anterior deltoid")
        channel = setup.result.combinations[1].combination.channel
        assert setup.choose(channel), setup.status.text()
        assert manager.patient_profile.fes.caps[1].max_current_ma == 15.0, "the session raised the cap again"
        # Station A: the old plan dialog saved
        st.use("room-A")
        old_plan.add_step("trigger_reaching")
        old_plan.accept()  # saved on a thread of its own (#37): its answer is waited for
        qtbot.waitUntil(lambda: not old_plan.saving, timeout=5000)
        assert old_plan.result() == old_plan.DialogCode.Accepted, old_plan.error_label.text()
        for name in ("room-A", "room-B"):  # what each station reads now
            st.use(name)
            final = load_patient("PZ-039", SAFETY)
            assert final.fes.caps[1].max_current_ma == 15.0, f"{name}: the lowered cap was lost"
            chosen = final.fes.electrodes.get("anterior deltoid")
            assert chosen is not None and chosen.channel == channel, f"{name}: the electrode choice was lost"
            assert [s.exercise for s in final.therapy_plan] == ["trigger_reaching"] * 2, f"{name}: the plan"
            assert final.fes.caps[5].max_current_ma == 20.0 and final.notes == "first visit"
        assert manager.patient_profile.fes.electrodes["anterior deltoid"].channel == channel
    finally:
        if manager is not None:
            manager.shutdown(timeout_s=1.0)
        st.close()


# ---------------------------------------------------------------------------------------------- two writers
def _two_writers(qtbot: Any, use_a: Any, use_b: Any, create: Any, read: Any, archive_a: Any = None,
                 archive_b: Any = None) -> None:
    """Two profile forms of one patient, on station A (dr_rossi) and station B (dr_neri), opened on the same
    record: A saves first; B's save is refused naming A's operator, station and time, nothing of it written;
    B's Reload shows A's values with B's own change put back; B saves; every field is as both meant."""
    from app.ui.patient_dialog import PatientDialog

    kw_a = {"archive": archive_a, "operator": "dr_rossi"} if station is not None else {}
    kw_b = {"archive": archive_b, "operator": "dr_neri"} if station is not None else {}
    use_a()
    start = _profile("PZ-040")
    create(start)
    use_a()
    form_a = PatientDialog(read("PZ-040"), SAFETY, parent=None, **kw_a)
    use_b()
    form_b = PatientDialog(read("PZ-040"), SAFETY, parent=None, **kw_b)
    for f in (form_a, form_b):
        qtbot.addWidget(f)
        f.show()
    # A: cap 25 -> 15 mA on channel 1, notes; B: the name (each only their own fields)
    form_a.caps_table.setItem(0, 0, QTableWidgetItem("15"))
    form_a.notes.setPlainText("shoulder pain: cap lowered")
    form_b.name_edit.setText("Maria Esposito Bianchi")
    use_a()
    form_a.accept()
    assert form_a.result() == form_a.DialogCode.Accepted, form_a.error_label.text()
    saved_by_a = read("PZ-040")
    use_b()
    form_b.accept()
    message = form_b.error_label.text()
    assert form_b.result() != form_b.DialogCode.Accepted, "B's save overwrote A's silently"
    assert "dr_rossi" in message and "room-A" in message and "Reload" in message, message
    assert saved_by_a.updated in message  # when: the time of A's save
    assert form_b.reload_button.isVisible()
    assert read("PZ-040") == saved_by_a  # nothing of B's refused save was written
    both = form_b.reload()
    assert both == []
    assert form_b.name_edit.text() == "Maria Esposito Bianchi"  # B's own change put back
    assert form_b.caps_table.item(0, 0).text() == "15.0" and "cap lowered" in form_b.notes.toPlainText()
    form_b.accept()
    assert form_b.result() == form_b.DialogCode.Accepted, form_b.error_label.text()
    final = read("PZ-040")
    expected = replace(start, full_name="Maria Esposito Bianchi", notes="shoulder pain: cap lowered",
                       fes=replace(start.fes, caps={**start.fes.caps, 1: ClinicalChannelCap(max_current_ma=15.0)}),
                       created=final.created, updated=final.updated)
    assert final == expected  # every field: A's cap and notes, B's name, the plan and the rest untouched


@pytest.mark.parametrize("shared", [True, False], ids=["two stations", "two windows on one station"])
def test_two_profile_forms_of_one_patient_the_second_is_refused_with_who_where_when(
        qtbot: Any, tmp_path: Path, monkeypatch: Any, shared: bool) -> None:
    """Before stage 2, on one PC, the second form's save put the first one's cap and notes back silently."""
    st = Stations(tmp_path, monkeypatch, shared=shared)
    try:
        def create(p: PatientProfile) -> None:
            st.create(p, "dr_rossi")

        _two_writers(qtbot, lambda: st.use("room-A"), lambda: st.use("room-B"), create,
                     lambda pid: load_patient(pid, SAFETY))
    finally:
        st.close()


@pytest.fixture(scope="module")
def pg_db() -> Iterator[Any]:
    from tests.postgres import server_or_skip

    with server_or_skip() as server:
        yield server.new_database()


def test_two_profile_forms_on_two_stations_of_a_postgresql_archive(qtbot: Any, pg_db: Any) -> None:
    """The same on the real PostgreSQL server (the stations' role, its password from a file only it reads)."""
    from app.archive.store import open_archive
    from tests.postgres import APP

    a = open_archive(url=pg_db.url(APP), password_file=pg_db.password_file(APP), station="room-A")
    b = open_archive(url=pg_db.url(APP), password_file=pg_db.password_file(APP), station="room-B")
    try:
        def create(p: PatientProfile) -> None:
            station.save_profile(p, expected_version=None, operator="dr_rossi", safety=SAFETY, archive=a)

        _two_writers(qtbot, lambda: None, lambda: None, create, lambda pid: b.get_patient(pid).profile,
                     archive_a=a, archive_b=b)
        history = b.patient_history("PZ-040")
        assert [(h.changed_by, h.changed_station) for h in history] == [
            ("dr_rossi", "room-A"), ("dr_rossi", "room-A"), ("dr_neri", "room-B")]
    finally:
        a.close()
        b.close()


# ---------------------------------------------------------------------------------------------- start-up
def test_the_embedded_archive_takes_the_data_folders_patients_once(tmp_path: Path, monkeypatch: Any) -> None:
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    save_patient(_profile("PZ-001"), safety=SAFETY)
    save_patient(replace(_profile("PZ-002"), therapy_plan=[]), safety=SAFETY)
    yaml_before = load_patient("PZ-001", SAFETY)
    opened = station.open_station(CFG)
    try:
        assert opened.imported == ["PZ-001", "PZ-002"] and opened.message() == ""
        assert opened.archive.get_patient("PZ-001").profile == yaml_before  # every field, created/updated kept
    finally:
        opened.archive.close()
    save_patient(_profile("PZ-003"), safety=SAFETY)  # a file written after: not the archive's business any more
    again = station.open_station(CFG)
    try:
        assert again.imported == []
        assert [p.patient_id for p in again.archive.list_patients()] == ["PZ-001", "PZ-002"]
    finally:
        again.archive.close()


def test_headless_refuses_an_archive_newer_than_the_app_in_one_sentence(tmp_path: Path, monkeypatch: Any,
                                                                       capsys: Any) -> None:
    import sqlite3

    from app.archive.store import open_archive
    from app.cli import main

    home = tmp_path / "home"
    monkeypatch.setenv("LINARMPP_HOME", str(home))
    open_archive(CFG).close()
    with sqlite3.connect(home / "archive.sqlite3") as db:
        db.execute("UPDATE alembic_version SET version_num = '9999_future'")
    script = tmp_path / "s.py"
    script.write_text("print('ran')\n", encoding="utf-8")
    assert main(["--headless", "--script", str(script)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot use the patients' archive, nothing was started" in err[0], err
    assert "newer version of LINarm++ Manager" in err[0] and "Traceback" not in err[0]
    assert station.current() is None and not station.in_use()


def test_an_unreachable_archive_lets_the_station_run_and_says_patients_cannot_be_saved(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    import socket

    from app.core.config import ArchiveConfig
    from app.manager import LinarmppManager
    from app.therapy.patients import PatientError
    from app.ui.patients_window import PatientsDialog
    from tests.fakes import counter_factory

    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = replace(CFG, archive=ArchiveConfig(url=f"postgresql+psycopg://linarmpp_app@127.0.0.1:{port}/linarmpp"))
    opened = station.open_station(cfg)
    assert opened.archive is None and "cannot be reached" in opened.message()
    assert "patients cannot be opened or saved" in opened.message()
    station.install(opened.archive, opened.problem)
    manager = LinarmppManager(cfg, factories={"alpha": counter_factory(tmp_path, "alpha")})
    try:
        manager.start()
        patients = PatientsDialog(cfg.safety, manager=manager)
        qtbot.addWidget(patients)
        qtbot.waitUntil(lambda: patients.loaded, timeout=5000)
        assert patients.archive_note.isVisibleTo(patients) and not patients.new_button.isEnabled()
        assert "cannot be reached" in patients.archive_note.text()
        from app.ui.patient_dialog import StartSessionDialog

        start = StartSessionDialog(cfg.safety)
        qtbot.addWidget(start)
        qtbot.waitUntil(lambda: start.loaded, timeout=5000)
        assert "cannot be reached" in start.problem.text() and "Create a patient" not in start.problem.text()
        with pytest.raises(PatientError, match="the session is not started: the patient's profile cannot be read"):
            manager.start_session("PZ-001", "dr_verdi", root=tmp_path / "sessions")
        assert manager.recorder is None
    finally:
        manager.shutdown(timeout_s=1.0)
        station.uninstall()


@pytest.fixture(autouse=True)
def _no_station_left() -> Iterator[None]:
    yield
    if station is not None:
        left = station.uninstall()
        if left is not None:
            left.close()


def test_two_plan_dialogs_the_second_is_refused_and_reload_shows_the_saved_plan(
        qtbot: Any, stations: Stations) -> None:
    """The plan dialog writes the plan alone: a plan saved meanwhile by someone else refuses it (who, where, when);
    nothing of it is written; Reload shows the saved plan. A cap saved meanwhile does not refuse it."""
    from app.ui.plan_dialog import PlanDialog

    stations.use("room-A")
    stations.create(_profile("PZ-041"), "dr_rossi")
    first = PlanDialog(load_patient("PZ-041"), SAFETY, operator="dr_rossi")
    stations.use("room-B")
    second = PlanDialog(load_patient("PZ-041"), SAFETY, operator="dr_neri")
    for d in (first, second):
        qtbot.addWidget(d)
        d.show()
    stations.use("room-A")
    first.add_step("trigger_reaching")
    first.accept()  # saved on a thread of its own (#37): its answer is waited for
    qtbot.waitUntil(lambda: not first.saving, timeout=5000)
    assert first.result() == first.DialogCode.Accepted, first.error_label.text()
    saved = load_patient("PZ-041")
    stations.use("room-B")
    second.remove_step()
    second.accept()
    qtbot.waitUntil(lambda: not second.saving, timeout=5000)
    text = second.error_label.text()
    assert second.result() != second.DialogCode.Accepted
    assert "dr_rossi" in text and "room-A" in text and saved.updated in text and "Reload" in text, text
    assert second.reload_button.isVisible() and load_patient("PZ-041") == saved
    assert second.reload() and len(second.steps) == 2
    second.accept()  # as of the version it reloaded: saved
    qtbot.waitUntil(lambda: not second.saving, timeout=5000)
    assert second.result() == second.DialogCode.Accepted, second.error_label.text()
    assert len(load_patient("PZ-041").therapy_plan) == 2


def test_a_sessions_electrode_choice_of_a_district_chosen_meanwhile_elsewhere_is_refused_in_words(
        qtbot: Any, tmp_path: Path, stations: Stations) -> None:
    """Two choices of one district from two copies: the second is not saved over the first; the dialog says who
    chose it, where and when; the first choice stays."""
    from app.manager import LinarmppManager
    from app.therapy.electrodes import choice_for
    from app.ui.electrode_setup import ElectrodeSetupDialog
    from tests.fakes import counter_factory

    stations.use("room-B")
    stations.create(_profile("PZ-042"), "dr_rossi")
    manager = LinarmppManager(CFG, factories={"alpha": counter_factory(tmp_path, "alpha")})
    try:
        manager.start()
        manager.start_session("PZ-042", "dr_verdi", root=tmp_path / "sessions")
        result = _setup_result("triceps")
        first = result.combinations[0].combination.channel
        stations.use("room-A")  # the same district chosen on station A meanwhile
        station.choose_electrodes("PZ-042", "triceps", choice_for(result, first, "dr_rossi"), expected_version=1,
                                  operator="dr_rossi")
        stations.use("room-B")
        setup = ElectrodeSetupDialog(manager)
        qtbot.addWidget(setup)
        setup.result = result
        assert not setup.choose(result.combinations[1].combination.channel)
        text = setup.status.text()
        assert "could not be saved" in text and "dr_rossi" in text and "room-A" in text, text
        assert station.read_record("PZ-042").profile.fes.electrodes["triceps"].channel == first
    finally:
        manager.shutdown(timeout_s=1.0)


def test_the_window_refuses_an_archive_newer_than_the_app_in_a_dialog_and_opens_nothing(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    """run_gui: the archive opened (on its own thread) before the devices start; refused → one sentence in a
    dialog, the devices never started, no window, exit 2."""
    import sqlite3
    from types import SimpleNamespace

    from PySide6.QtWidgets import QMessageBox

    import app.application as application
    from app.archive.store import open_archive

    home = tmp_path / "home"
    monkeypatch.setenv("LINARMPP_HOME", str(home))
    open_archive(CFG).close()
    with sqlite3.connect(home / "archive.sqlite3") as db:
        db.execute("UPDATE alembic_version SET version_num = '9999_future'")
    life: list[str] = []

    class Manager:  # the devices' side, as far as start-up and shutdown go
        def __init__(self, _config: Any) -> None:
            self.supervisor = SimpleNamespace(bring_to_safe_state=lambda _why: None)

        def start(self) -> None:
            life.append("started")

        def shutdown(self) -> None:
            life.append("shut down")

    shown: list[str] = []
    monkeypatch.setattr(application, "LinarmppManager", Manager)
    monkeypatch.setattr(QMessageBox, "critical", lambda _parent, _title, text: shown.append(text))
    monkeypatch.setattr("app.ui.main_window.MainWindow", lambda *_a: life.append("window") or 1 / 0)
    for name in ("configure_qt_identity", "apply_desktop_identity"):  # the suite's QApplication stays as it is
        monkeypatch.setattr(application, name, lambda *_a: None)
    monkeypatch.setattr("app.ui.theme.apply_palette", lambda *_a: None)
    assert application.run_gui(CFG) == 2
    assert life == ["shut down"]  # never started: the archive is opened before anything is driven
    (text,) = shown
    assert text.startswith("LINarm++ Manager cannot use the patients' archive, nothing was started:")
    assert "newer version of LINarm++ Manager" in text and "\n" not in text
    assert not station.in_use()
