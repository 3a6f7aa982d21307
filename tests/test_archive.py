"""The archive on its embedded default, SQLite in ``<data>`` (issue #39): schema, patients with optimistic
concurrency, sessions uploaded once, import and export without loss, the outbox, verify naming the first
mismatch, the command line. The same behaviour on a real PostgreSQL server: tests/test_archive_postgres.py."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import replace

import pytest
from sqlalchemy import create_engine, text

from app.archive import folders
from app.archive.api import (
    ArchiveTooNew,
    ArchiveUnavailable,
    ConfigProblem,
    NeedsUpgrade,
    PatientExists,
    SessionConflict,
    StaleRecord,
)
from app.archive.outbox import Outbox
from app.archive.store import open_archive
from app.archive.transfer import export_profiles, import_data_folder
from app.core.config import AppConfig, ConfigError, load_config
from app.session.metrics import session_metrics
from app.session.recording import SessionRecorder, load_session
from app.therapy.patients import ClinicalChannelCap, ElectrodeChoice, PlannedExercise, load_patient
from tests.archive_data import full_profile, make_data_folder
from tests.recorder_host import recorder_host


@pytest.fixture
def archive(tmp_path):
    a = open_archive(url=f"sqlite:///{tmp_path / 'archive.sqlite3'}", station="A")
    yield a
    a.close()


def _canon(value) -> str:
    return json.dumps(value, sort_keys=True)


# ---------------------------------------------------------------------------------------------- schema
def test_the_migrations_make_the_models_schema(tmp_path) -> None:
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from app.archive.models import Base

    a = open_archive(url=f"sqlite:///{tmp_path / 'a.sqlite3'}", station="A")
    with a.engine.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
    a.close()


def test_no_configuration_is_an_sqlite_file_in_the_data_folder(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "data"))
    with open_archive(AppConfig()) as a:
        assert a.url.endswith("data/archive.sqlite3") and a.station  # the computer's name
        assert a.schema_revision()
    path = tmp_path / "data" / "archive.sqlite3"
    assert path.is_file() and path.stat().st_mode & 0o077 == 0


def test_an_archive_newer_than_the_app_is_refused_and_an_unversioned_one_needs_upgrade(tmp_path) -> None:
    url = f"sqlite:///{tmp_path / 'a.sqlite3'}"
    open_archive(url=url).close()
    with sqlite3.connect(tmp_path / "a.sqlite3") as db:
        db.execute("UPDATE alembic_version SET version_num = '9999_future'")
    with pytest.raises(ArchiveTooNew, match=r"newer version of LINarm\+\+ Manager.*Update LINarm"):
        open_archive(url=url)
    with sqlite3.connect(tmp_path / "a.sqlite3") as db:
        db.execute("DELETE FROM alembic_version")
    with pytest.raises(NeedsUpgrade, match="no schema version"):
        open_archive(url=url)


def test_a_url_holding_a_password_is_refused_with_a_sentence(tmp_path) -> None:
    with pytest.raises(ConfigProblem, match=r"holds a password.*password_file"):
        open_archive(url="postgresql+psycopg://app:secret@db.clinic/archive")
    cfg = tmp_path / "site.yaml"
    cfg.write_text("archive:\n  url: postgresql+psycopg://app:secret@db.clinic/archive\nstation: room-2\n")
    with pytest.raises(ConfigError, match="url holds a password"):
        load_config(cfg)
    cfg.write_text("archive:\n  url: postgresql+psycopg://app@db.clinic/archive\n  password_file: ~/.linarmpp-db\n"
                   "station: room-2\n")
    loaded = load_config(cfg)
    assert loaded.station == "room-2" and loaded.archive.password_file == "~/.linarmpp-db"


def test_a_password_file_others_can_read_is_refused(tmp_path) -> None:
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n")
    secret.chmod(0o644)
    with pytest.raises(ConfigProblem, match="can be read by other users"):
        open_archive(url="postgresql+psycopg://app@127.0.0.1:1/archive", password_file=str(secret))


def test_an_unreachable_server_is_archive_unavailable(tmp_path) -> None:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ArchiveUnavailable, match="cannot be reached"):
        open_archive(url=f"postgresql+psycopg://app@127.0.0.1:{port}/archive")


# ---------------------------------------------------------------------------------------------- patients
def test_the_stale_copy_sequence_keeps_the_lowered_cap_the_choice_and_the_plan(archive) -> None:
    """Issue #39: cap lowered 25 -> 15 mA; then the running session's electrode choice from its copy made before;
    then an old plan dialog's save. Before the archive the second put 25 mA back and the third dropped the choice."""
    start = archive.save_patient(full_profile(), expected_version=None, operator="dr_rossi")
    session_copy = plan_dialog_copy = start  # both opened before the cap was lowered
    lowered = replace(start.profile, fes=replace(start.profile.fes, caps={**start.profile.fes.caps,
                                                                          1: ClinicalChannelCap(15.0, 250.0, 6.0)}))
    archive.save_patient(lowered, expected_version=start.version, operator="dr_bianchi")
    choice = ElectrodeChoice(channel=3, electrodes="1-3", chosen_by="dr_verdi", session="20260302-100000")
    archive.choose_electrodes("PZ-017", "anterior deltoid", choice, expected_version=session_copy.version,
                              operator="dr_verdi")
    # The old dialog saving the whole profile is refused, naming who changed it where and when ...
    new_plan = [PlannedExercise("trigger_reaching", {"movements": 8, "speed_m_s": 0.1}, "longer")]
    with pytest.raises(StaleRecord) as stale:
        archive.save_patient(replace(plan_dialog_copy.profile, therapy_plan=new_plan),
                             expected_version=plan_dialog_copy.version, operator="dr_neri")
    assert stale.value.changed_by == "dr_verdi" and stale.value.changed_station == "A"
    said = str(stale.value)
    assert "dr_verdi" in said and "station A" in said and "nothing was saved" in said
    # ... and the plan dialog's own save (its field only) goes through without touching the others.
    archive.save_patient(replace(plan_dialog_copy.profile, therapy_plan=new_plan),
                         expected_version=plan_dialog_copy.version, operator="dr_neri", fields=["therapy_plan"])
    final = archive.get_patient("PZ-017")
    assert final.version == 4
    assert final.profile.fes.caps[1].max_current_ma == 15.0
    assert final.profile.fes.electrodes["anterior deltoid"] == choice
    assert final.profile.therapy_plan == new_plan
    expected = replace(full_profile(), fes=replace(lowered.fes, electrodes={"anterior deltoid": choice}),
                       therapy_plan=new_plan, updated=final.profile.updated)
    assert final.profile == expected  # every other field as it was
    history = archive.patient_history("PZ-017")
    assert [(h.version, h.fields, h.changed_by) for h in history[1:]] == [
        (2, ("fes.caps",), "dr_bianchi"), (3, ("fes.electrodes.anterior deltoid",), "dr_verdi"),
        (4, ("therapy_plan",), "dr_neri")]


def test_a_plan_save_over_a_plan_changed_meanwhile_is_refused(archive) -> None:
    start = archive.save_patient(full_profile(), expected_version=None, operator="a")
    archive.save_patient(replace(start.profile, therapy_plan=[]), expected_version=1, operator="b",
                         fields=["therapy_plan"])
    with pytest.raises(StaleRecord, match="therapy_plan"):
        archive.save_patient(start.profile, expected_version=1, operator="c", fields=["therapy_plan"])
    with pytest.raises(PatientExists):
        archive.save_patient(full_profile(), expected_version=None, operator="d")
    with pytest.raises(ValueError, match="unknown patient field"):
        archive.save_patient(start.profile, expected_version=2, operator="c", fields=["fes"])


def test_two_connections_to_one_file_one_save_wins(tmp_path) -> None:
    url = f"sqlite:///{tmp_path / 'a.sqlite3'}"
    with open_archive(url=url, station="room-1") as a, open_archive(url=url, station="room-2") as b:
        a.save_patient(full_profile(), expected_version=None, operator="ann")
        copy_a, copy_b = a.get_patient("PZ-017"), b.get_patient("PZ-017")
        b.save_patient(replace(copy_b.profile, notes="B's note"), expected_version=copy_b.version, operator="bob")
        with pytest.raises(StaleRecord) as stale:
            a.save_patient(replace(copy_a.profile, notes="A's note"), expected_version=copy_a.version, operator="ann")
        assert (stale.value.changed_by, stale.value.changed_station) == ("bob", "room-2")
        assert a.get_patient("PZ-017").profile.notes == "B's note"


def test_list_and_search_patients(archive) -> None:
    archive.save_patient(full_profile("PZ-017"), expected_version=None, operator="a")
    archive.save_patient(replace(full_profile("pz-002"), full_name="Luca Bianchi", record_number="X-1", notes=""),
                         expected_version=None, operator="a")
    assert [p.patient_id for p in archive.list_patients()] == ["pz-002", "PZ-017"]
    assert [p.patient_id for p in archive.list_patients("maria mrn-5512")] == ["PZ-017"]
    assert [p.patient_id for p in archive.list_patients("bianchi")] == ["pz-002"]
    assert archive.list_patients("%") == []


# ---------------------------------------------------------------------------------------------- sessions
def test_the_recorder_writes_a_session_uuid_at_the_start(tmp_path) -> None:
    recorder = SessionRecorder(fsync=False)
    folder = recorder.start(recorder_host(AppConfig(), {}), "P1", "op", root=tmp_path)
    first = json.loads((folder / "manifest.json").read_text())["session_uuid"]
    recorder.stop()
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["session_uuid"] == first == folders.session_uuid(folder)
    assert len(first) == 36


def test_upload_is_idempotent_and_a_different_session_with_the_same_uuid_is_refused(archive, tmp_path) -> None:
    sessions = make_data_folder(tmp_path / "data")
    monday = sessions["monday"]
    first = archive.upload_session(monday)
    assert first.outcome == "uploaded" and archive.count_sessions() == 1
    assert archive.upload_session(monday).outcome == "already_archived"
    assert folders.session_uuid(monday) == first.uuid  # derived (no session_uuid): stable
    impostor = tmp_path / "impostor" / "PZ-017" / "20260302-100000"
    import shutil

    shutil.copytree(monday, impostor)
    with open(impostor / "events.jsonl", "a") as fh:
        fh.write(json.dumps({"t_mono": 1.0, "kind": "note", "data": {}}) + "\n")
    with pytest.raises(SessionConflict, match="another session with the UUID"):
        archive.upload_session(impostor)
    assert archive.count_sessions() == 1 and len(archive.journal(first.uuid)) == len(load_session(monday).events)


def test_import_keeps_everything_and_export_round_trips(archive, tmp_path) -> None:
    data = tmp_path / "data"
    sessions = make_data_folder(data)
    report = import_data_folder(archive, data)
    assert report.failed == [] and sorted(report.patients_added) == ["PZ-017", "PZ-018"]
    assert len(report.sessions_added) == 4
    again = import_data_folder(archive, data)  # run twice: nothing added, nothing lost
    assert again.sessions_added == [] and len(again.sessions_same) == 4 and len(again.patients_same) == 2
    # profiles: every field, created/updated kept; the export loads back identical
    out = tmp_path / "exported"
    export_profiles(archive, out)
    for pid in ("PZ-017", "PZ-018"):
        assert load_patient(pid, folder=out) == load_patient(pid, folder=data / "patients")
    # sessions: listed newest first, the interrupted one as such; metrics identical from the folder and the archive
    listed = archive.list_sessions("PZ-017")
    assert [s.start[:10] for s in listed] == ["2026-03-05", "2026-03-04", "2026-03-02"]
    assert [s.status for s in listed] == ["recording", "complete", "complete"] and listed[0].end == ""
    for name, folder in sessions.items():
        uuid = folders.session_uuid(folder)
        with archive.materialised(uuid) as copy:
            assert _canon(session_metrics(copy)) == _canon(session_metrics(folder)), name
            assert sorted(p.relative_to(copy).as_posix() for p in copy.rglob("*") if p.is_file()) == \
                sorted(f.name for f in folders.session_files(folder))
        from_folder = session_metrics(folder)
        stored = [r.metrics for r in archive.repetitions(uuid)]
        assert _canon(stored) == _canon([r for run in from_folder["runs"] for r in run["repetitions"]]), name
        assert [r.run_id for r in archive.runs(uuid)] == [r["run_id"] for r in from_folder["runs"]]
        assert archive.get_session(uuid).summary == json.loads(_canon(from_folder["summary"]))
    interrupted = archive.get_session(folders.session_uuid(sessions["interrupted"]))
    assert any("not stopped normally" in p for p in interrupted.problems)
    assert [r.end_reason for r in archive.runs(interrupted.info.uuid)] == ["crashed"]
    progress = archive.progress_sessions("PZ-017")
    assert [p.info.start[:10] for p in progress] == ["2026-03-02", "2026-03-04", "2026-03-05"]
    assert archive.verify().ok


def test_files_read_like_the_folder(archive, tmp_path) -> None:
    folder = make_data_folder(tmp_path / "data")["monday"]
    uuid = archive.upload_session(folder).uuid
    files = archive.session_files(uuid)
    assert {f.name for f in files.files()} == {"manifest.json", "events.jsonl", "streams/linarm.vsa.csv",
                                               "streams/physio.main.csv"}
    with files.open("streams/linarm.vsa.csv") as fh:
        assert fh.readline() == (folder / "streams/linarm.vsa.csv").open("rb").readline()
    assert files.read_bytes("events.jsonl") == (folder / "events.jsonl").read_bytes()


def test_the_device_clocks_file_is_archived_and_comes_back(archive, tmp_path) -> None:
    """The recorder's clocks.csv (the device clocks' maps to the host clock, #41's XDF clock offsets) is part of
    the session: archived with it and written back, so an archived session exports with its real offsets."""
    from app.session.recording import CLOCK_FILE

    folder = make_data_folder(tmp_path / "data")["monday"]
    clocks = "t_mono_s,device,device_s,drift\n5000.0,linarm,12.5,1.00008\n"
    (folder / CLOCK_FILE).write_text(clocks, encoding="utf-8")
    uuid = archive.upload_session(folder).uuid
    assert CLOCK_FILE in {f.name for f in archive.session_files(uuid).files()}
    with archive.materialised(uuid) as copy:
        assert (copy / CLOCK_FILE).read_text(encoding="utf-8") == clocks


def test_verify_names_the_file_after_one_byte_and_the_journal_row_after_one_change(archive, tmp_path) -> None:
    sessions = make_data_folder(tmp_path / "data")
    import_data_folder(archive, tmp_path / "data")
    report = archive.verify()
    assert report.ok and report.files >= 8 and report.rows > 50
    uuid = folders.session_uuid(sessions["monday"])
    engine = create_engine(archive.url)
    with engine.begin() as conn:  # one byte of the handle's stream, as someone with the database file could
        sha = conn.execute(text("SELECT sha256 FROM session_files WHERE session_uuid = :u AND name = "
                                "'streams/linarm.vsa.csv'"), {"u": uuid}).scalar()
        data = bytearray(conn.execute(text("SELECT data FROM blob_chunks WHERE sha256 = :s AND seq = 0"),
                                      {"s": sha}).scalar())
        data[1000] ^= 0x01
        conn.execute(text("UPDATE blob_chunks SET data = :d WHERE sha256 = :s AND seq = 0"),
                     {"d": bytes(data), "s": sha})
    problem = archive.verify().first_problem
    assert problem is not None and f"streams/linarm.vsa.csv of session {uuid}" in problem.where
    assert "seq=0" in problem.where
    with engine.begin() as conn:
        data[1000] ^= 0x01
        conn.execute(text("UPDATE blob_chunks SET data = :d WHERE sha256 = :s AND seq = 0"),
                     {"d": bytes(data), "s": sha})
        conn.execute(text("UPDATE journal SET who = 'nobody' WHERE session_uuid = :u AND seq = 17"), {"u": uuid})
    problem = archive.verify().first_problem
    assert problem is not None and problem.where.startswith(f"session {uuid} journal row 17 (")
    assert "does not match its hash" in problem.what
    with engine.begin() as conn:
        conn.execute(text("UPDATE journal SET who = '' WHERE session_uuid = :u AND seq = 17"), {"u": uuid})
        conn.execute(text("UPDATE patients SET fes_caps = '{}' WHERE patient_id = 'PZ-017'"))
    problem = archive.verify().first_problem
    assert problem is not None and problem.where == "patient PZ-017 (patients row)" and "fes.caps" in problem.what
    engine.dispose()


# ---------------------------------------------------------------------------------------------- the outbox
def test_the_outbox_waits_while_the_archive_is_unreachable_then_uploads_once(tmp_path) -> None:
    sessions = make_data_folder(tmp_path / "data")
    root = tmp_path / "data" / "sessions"
    now = [0.0]
    reachable = [False]
    url = f"sqlite:///{tmp_path / 'archive.sqlite3'}"

    def connect():
        if not reachable[0]:
            raise ArchiveUnavailable("the archive at db.clinic cannot be reached (connection refused)")
        return open_archive(url=url, station="A")

    outbox = Outbox(root, connect, clock=lambda: now[0])
    outbox.set_active([sessions["wednesday"]])  # being recorded: not uploaded yet
    status = outbox.run_once()
    assert status.waiting == 3
    assert status.text().startswith("3 sessions waiting for the archive (the archive at db.clinic cannot")
    assert status.next_try_in_s == 5.0 and not outbox.due()
    now[0] = 5.0
    assert outbox.run_once().next_try_in_s == 15.0  # backing off
    reachable[0] = True
    assert outbox.run_once().uploaded == 0  # not due yet
    now[0] = 25.0
    status = outbox.run_once()
    assert (status.uploaded, status.waiting, status.text()) == (3, 0, "")
    outbox.set_active([])
    status = outbox.run_once(force=True)
    assert (status.uploaded, status.waiting) == (1, 0)
    assert outbox.run_once(force=True).uploaded == 0
    assert all(folders.is_archived(f) for f in sessions.values())
    with open_archive(url=url) as a:
        assert a.count_sessions() == 4


# ---------------------------------------------------------------------------------------------- command line
def test_the_archive_commands(tmp_path, monkeypatch, capsys) -> None:
    from app.cli import main

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    data = tmp_path / "data"
    make_data_folder(data)
    assert main(["archive", "import", str(data)]) == 0
    assert "sessions: 4 added" in capsys.readouterr().out
    assert main(["archive", "verify"]) == 0
    assert main(["archive", "export", str(tmp_path / "out"), "--patient", "PZ-017"]) == 0
    assert load_patient("PZ-017", folder=tmp_path / "out") == load_patient("PZ-017", folder=data / "patients")
    assert main(["archive", "upgrade"]) == 0 and "already up to date" in capsys.readouterr().out
    assert main(["archive", "grants", "linarmpp_app"]) == 0
    grants = capsys.readouterr().out
    assert "GRANT SELECT, INSERT ON public.journal TO \"linarmpp_app\"" in grants
    assert "UPDATE ON public.journal" not in grants and "DELETE ON public.journal" not in grants
    with sqlite3.connect(tmp_path / "home" / "archive.sqlite3") as db:
        db.execute("UPDATE journal SET kind = 'x' WHERE seq = 3")
    assert main(["archive", "verify"]) == 3
    assert "MISMATCH session " in capsys.readouterr().err
    assert main(["archive", "bogus"]) == 2
