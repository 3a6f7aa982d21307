"""A session started from this station's copy of a patient (the archive unreachable) runs without stimulation
(#39); it is lifted only when the archive's own record reaches the session (``update_session_profile`` with the
record's version while the archive answers), and the record says so. A clinic archive of its own (a SQLite file
that is not the station's embedded one, so the station keeps copies of what it reads: app/archive/station.py);
unreachable the way a file can be (a folder where the database file was: "unable to open database file"), opened
and installed as the application does at its start."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from app.archive import station
from app.core.config import AppConfig, ArchiveConfig
from app.safety.supervisor import SafetyError
from app.therapy.patients import ClinicalChannelCap, PatientFes, PatientProfile

PATIENT = "PZ-070"


pytestmark = pytest.mark.usefixtures("no_station_left")


def test_stimulation_withheld_for_a_copy_is_lifted_only_by_the_archives_own_record(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.manager import LinarmppManager
    from tests.fakes import counter_factory

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = replace(AppConfig(), archive=ArchiveConfig(url=f"sqlite:///{tmp_path / 'clinic.db'}"), station="room-A")
    opened = station.open_station(cfg)
    assert opened.archive is not None, opened.message()
    station.install(opened.archive)
    profile = PatientProfile(patient_id=PATIENT, full_name="Anna Bianchi",
                             fes=PatientFes(caps={1: ClinicalChannelCap(15.0, 250.0, None)}))
    station.save_profile(profile, expected_version=None, operator="dr_rossi")
    read = station.read_record(PATIENT, cfg.safety)  # the station keeps its copy
    assert read is not None and read.version == 1

    # the next morning the archive cannot be reached when the station starts: the copy stands in
    station.uninstall().close()  # type: ignore[union-attr]
    database = tmp_path / "clinic.db"
    database.rename(tmp_path / "clinic.db.away")
    database.mkdir()
    down = station.open_station(cfg)
    assert down.archive is None and "cannot be reached" in down.problem
    station.install(None, down.problem)
    assert station.copy_in_use(PATIENT)
    manager = LinarmppManager(cfg, factories={"alpha": counter_factory(tmp_path, "alpha")})
    try:
        manager.start()
        manager.start_session(PATIENT, "dr_verdi", root=tmp_path / "home" / "sessions")
        supervisor = manager.supervisor
        assert supervisor.stimulation_withheld.startswith(f"this session uses this station's copy of patient {PATIENT}")
        copy = station.read_record(PATIENT, cfg.safety)
        assert copy is not None
        # the copy again, with a version: not the archive's record, nothing lifted
        assert "stimulation no longer withheld (the archive's record)" not in manager.update_session_profile(
            copy.profile, version=copy.version)
        with pytest.raises(SafetyError, match="stimulation is withheld"):
            supervisor.check_fes_command("load profile", "script")

        # the archive answers again; a profile without its version (a form's copy) does not lift it either
        database.rmdir()
        (tmp_path / "clinic.db.away").rename(database)
        back = station.open_station(cfg)
        assert back.archive is not None
        station.install(back.archive)
        manager.update_session_profile(replace(copy.profile, full_name="Anna Bianchi"))
        assert supervisor.stimulation_withheld

        # the archive's own record with its version: lifted, in the words of the record
        record = station.read_record(PATIENT, cfg.safety)
        assert record is not None and record.version == 1
        changes = manager.update_session_profile(record.profile, version=record.version)
        assert changes == ["stimulation no longer withheld (the archive's record)"], changes
        assert supervisor.stimulation_withheld == ""
        supervisor.check_fes_command("load profile", "script")  # no longer refused
        folder = manager.recorder.folder
        manager.end_session()
        from app.session.recording import load_session

        updates = [e for e in load_session(folder).events if e.get("kind") == "patient_profile_updated"]
        assert [u["data"]["changes"] for u in updates] == [changes], updates  # the record says it, once
    finally:
        manager.shutdown(timeout_s=1.0)
