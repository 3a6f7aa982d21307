"""The offline patient cache (issue #39): with the clinic's PostgreSQL server down, a station still lists and opens the
patients it read last — read-only, the Patients window saying the archive cannot be reached and since when — and a
session can be run for one of them; it waits in the outbox and is archived once the server is back.

A real PostgreSQL server of its own (tests/postgres.py: it is stopped in the middle; never a mock; under CI=true
the test fails rather than skips when the server cannot start)."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from app.archive import station
from app.archive.api import ArchiveUnavailable
from app.archive.cache import CACHE_DIR
from app.archive.outbox import Outbox
from app.archive.store import open_archive
from app.core.config import AppConfig, ArchiveConfig
from app.therapy.patients import ClinicalChannelCap, PatientFes, PatientProfile
from tests.postgres import APP, PostgresServer, server_or_skip

SEEN, UNSEEN = "PZ-060", "PZ-061"


@pytest.fixture(scope="module")
def own_server() -> Iterator[PostgresServer]:
    with server_or_skip() as server:  # its own: this test stops it
        yield server


pytestmark = pytest.mark.usefixtures("no_station_left")


def test_with_the_server_down_the_patients_seen_are_listed_read_only_and_a_session_runs_and_waits(
        qtbot: Any, own_server: PostgresServer, tmp_path: Path, monkeypatch: Any) -> None:
    from app.manager import LinarmppManager
    from app.ui.patients_window import PatientsDialog
    from tests.fakes import counter_factory

    db = own_server.new_database()
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = replace(AppConfig(), archive=ArchiveConfig(url=db.url(APP), password_file=db.password_file(APP)),
                  station="room-A")
    profile = PatientProfile(patient_id=SEEN, full_name="Maria Esposito",
                             fes=PatientFes(caps={1: ClinicalChannelCap(15.0, 250.0, None)}))
    with open_archive(url=db.url(APP), password_file=db.password_file(APP), station="room-B") as other:
        other.save_patient(profile, expected_version=None, operator="dr_rossi")

    # Monday, the server up: the Patients window lists SEEN (the station keeps its copy of what it read)
    opened = station.open_station(cfg)
    assert opened.archive is not None, opened.message()
    station.install(opened.archive)
    patients = PatientsDialog(cfg.safety)
    qtbot.addWidget(patients)
    qtbot.waitUntil(lambda: patients.loaded, timeout=10_000)
    assert [e.patient_id for e in patients.entries] == [SEEN] and not patients.archive_note.isVisibleTo(patients)
    patients.close()
    with open_archive(url=db.url(APP), password_file=db.password_file(APP), station="room-B") as other:
        other.save_patient(PatientProfile(patient_id=UNSEEN), expected_version=None, operator="dr_rossi")
    copies = tmp_path / "home" / CACHE_DIR / "patients"
    assert [p.name for p in copies.iterdir()] == [f"{SEEN}.json"]
    assert stat.S_IMODE(copies.stat().st_mode) == 0o700
    assert stat.S_IMODE((copies / f"{SEEN}.json").stat().st_mode) == 0o600  # health data on the station
    station.uninstall().close()  # type: ignore[union-attr]

    # Tuesday, the server down when the station starts
    own_server.stop()
    try:
        opened = station.open_station(cfg)
        assert opened.archive is None and "cannot be reached" in opened.problem
        station.install(None, opened.problem)
        patients = PatientsDialog(cfg.safety)
        qtbot.addWidget(patients)
        qtbot.waitUntil(lambda: patients.loaded, timeout=10_000)
        assert [e.patient_id for e in patients.entries] == [SEEN]  # the one this station read; UNSEEN it never saw
        note = patients.archive_note.text()
        assert patients.archive_note.isVisibleTo(patients)
        assert "cannot be reached" in note and f", since {station.offline_since()[:16].replace('T', ' ')}" in note
        assert "read-only" in note, note
        patients.table.selectRow(0)
        assert patients.selected_entry() is not None and patients.selected_entry().profile == replace(
            profile, created=patients.selected_entry().profile.created,
            updated=patients.selected_entry().profile.updated)
        assert "This station's copy" in patients.details.text() and "Maria Esposito" in patients.details.text()
        assert not patients.edit_button.isEnabled() and not patients.plan_button.isEnabled()
        assert not patients.new_button.isEnabled() and patients.edit_profile() is None
        patients.close()

        # the Start-session dialog offers it too
        from app.ui.patient_dialog import StartSessionDialog

        start = StartSessionDialog(cfg.safety)
        qtbot.addWidget(start)
        qtbot.waitUntil(lambda: start.loaded, timeout=10_000)
        assert list(start.entries) == [SEEN]
        start.close()
        # a session for SEEN runs, its caps the copy's; it waits in the outbox
        manager = LinarmppManager(cfg, factories={"alpha": counter_factory(tmp_path, "alpha")})
        try:
            manager.start()
            folder = manager.start_session(SEEN, "dr_verdi", root=tmp_path / "home" / "sessions")
            assert manager.recorder is not None
            assert manager.patient_profile is not None and \
                manager.patient_profile.fes.caps[1].max_current_ma == 15.0
            # ... without stimulation: a cap lowered on another station since the copy would not be known (a stale
            # copy never raises a lowered cap); said on screen and in the record
            from app.safety.supervisor import SafetyError

            with pytest.raises(SafetyError, match="stimulation is withheld: this session uses this station's copy "
                                                  f"of patient {SEEN}'s record"):
                manager.supervisor.check_fes_command("load profile", "script")  # every FES entry point's check
            assert [a.text for a in manager.supervisor.alarms() if "Stimulation withheld" in a.text], \
                "the window's alarms do not say why stimulation is withheld"
            manager.end_session()
            assert manager.supervisor.stimulation_withheld == ""
        finally:
            manager.shutdown(timeout_s=1.0)
        outbox = Outbox(tmp_path / "home" / "sessions", lambda: open_archive(cfg))
        waiting = outbox.run_once(force=True)
        assert (waiting.uploaded, waiting.waiting) == (0, 1), waiting.text()
        assert waiting.text().startswith("1 session waiting for the archive")
        # a patient this station never read: no copy, said as the archive being unreachable
        with pytest.raises(ArchiveUnavailable, match="cannot be reached"):
            station.read_record(UNSEEN, cfg.safety)
        # copies are the archive's they were read from: another archive unreachable offers none of them
        station.uninstall()
        elsewhere = replace(cfg, archive=ArchiveConfig(url="postgresql+psycopg://linarmpp_app@127.0.0.1:1/other"))
        station.install(None, station.open_station(elsewhere).problem)
        with pytest.raises(ArchiveUnavailable, match="cannot be reached"):
            station.read_record(SEEN, cfg.safety)
    finally:
        own_server.start()

    # the server back: the session is archived, once
    outbox = Outbox(tmp_path / "home" / "sessions", lambda: open_archive(cfg))
    back = outbox.run_once(force=True)
    assert (back.uploaded, back.waiting) == (1, 0), back.text()
    assert outbox.run_once(force=True).uploaded == 0
    with open_archive(url=db.url(APP), password_file=db.password_file(APP), station="room-B") as other:
        (session,) = other.list_sessions(SEEN)
        assert session.station == "room-A" and session.operator == "dr_verdi"
        assert Path(folder).name in session.folder_name
    assert os.listdir(copies) == [f"{SEEN}.json"]


def test_the_server_going_down_while_the_station_runs_the_copy_stands_in_until_it_is_back(
        own_server: PostgresServer, tmp_path: Path, monkeypatch: Any) -> None:
    db = own_server.new_database()
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = replace(AppConfig(), archive=ArchiveConfig(url=db.url(APP), password_file=db.password_file(APP)),
                  station="room-A")
    opened = station.open_station(cfg)
    assert opened.archive is not None, opened.message()
    station.install(opened.archive)
    station.save_profile(PatientProfile(patient_id=SEEN, full_name="Maria Esposito"), expected_version=None,
                         operator="dr_rossi")
    read = station.read_record(SEEN, cfg.safety)
    assert read is not None and read.version == 1 and station.offline_since() == ""
    own_server.stop()
    try:
        copy = station.read_record(SEEN, cfg.safety)  # the open archive fails: this station's copy, said so
        assert copy is not None and copy.version == 1 and copy.profile.full_name == "Maria Esposito"
        assert station.offline_since() and "cannot be reached" in station.offline_sentence()
        with pytest.raises(ArchiveUnavailable):  # nothing is saved from a copy
            station.save_profile(replace(copy.profile, notes="offline"), expected_version=1, operator="dr_verdi")
    finally:
        own_server.start()
    again = station.read_record(SEEN, cfg.safety)  # the archive back: its record, and the window's line goes
    assert again is not None and again.profile.notes == "" and station.offline_since() == ""
