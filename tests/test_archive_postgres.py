"""The archive on a real PostgreSQL server started by the tests (tests/postgres.py; under CI=true a server that
cannot start fails these tests): two stations on one database, optimistic concurrency between two processes,
the stale-copy sequence of issue #39, the application role's rights, offline and back, a kill -9 in the middle of
an upload, verify naming the first mismatch."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import psycopg
import pytest
from sqlalchemy import text

from app.archive import folders
from app.archive.api import StaleRecord
from app.archive.outbox import Outbox
from app.archive.store import SqlArchive, open_archive
from app.therapy.patients import ClinicalChannelCap, ElectrodeChoice, PlannedExercise
from tests.archive_data import full_profile, long_session, make_data_folder
from tests.postgres import APP, Database, PostgresServer, server_or_skip

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def pg_server():
    with server_or_skip() as server:
        yield server


@pytest.fixture(scope="module")
def pg_db(pg_server: PostgresServer) -> Database:
    return pg_server.new_database()


def station(db: Database, name: str) -> SqlArchive:
    return open_archive(url=db.url(APP), password_file=db.password_file(APP), station=name)


def count(db: Database, sql: str, **params: object) -> int:
    with psycopg.connect(host="127.0.0.1", port=db.server.port, user="postgres", dbname=db.name) as conn:
        return int(conn.execute(sql, params).fetchone()[0])


def test_the_schema_and_the_application_roles_rights(pg_db: Database) -> None:
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from app.archive.models import APPEND_ONLY, Base

    with station(pg_db, "A") as a:
        with a.engine.connect() as conn:
            assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
        for table in ("journal", "patient_history", "ledger"):
            for statement in (f"UPDATE {table} SET prev_hash = prev_hash", f"DELETE FROM {table}"):
                with pytest.raises(Exception, match="permission denied"), a.engine.begin() as conn:
                    conn.execute(text(statement))
        with pytest.raises(Exception, match="must be owner"), a.engine.begin() as conn:
            conn.execute(text("DROP TABLE journal"))
    privileges = {(t, p) for t in APPEND_ONLY for p in ("UPDATE", "DELETE")
                  if count(pg_db, "SELECT has_table_privilege(%(r)s, %(t)s, %(p)s)::int", r=APP, t=t, p=p)}
    assert privileges == set()
    assert count(pg_db, "SELECT has_table_privilege(%(r)s, 'patients', 'UPDATE')::int", r=APP) == 1


def test_two_stations_share_patients_plans_and_sessions(pg_db: Database, tmp_path) -> None:
    sessions = make_data_folder(tmp_path / "data")
    with station(pg_db, "room-A") as a, station(pg_db, "room-B") as b:
        profile = replace(full_profile("PZ-100"), therapy_plan=[PlannedExercise("trigger_reaching",
                                                                                 {"movements": 6}, "")])
        a.save_patient(profile, expected_version=None, operator="dr_rossi")
        a.upload_session(sessions["monday"])
        on_b = b.get_patient("PZ-100")
        assert on_b.profile == replace(profile, updated=on_b.profile.updated) and on_b.changed_station == "room-A"
        assert "PZ-100" in [p.patient_id for p in b.list_patients("maria")]
        b.upload_session(sessions["wednesday"])
        for archive in (a, b):
            progress = archive.progress_sessions("PZ-017")
            assert [(p.info.station, p.info.start[:10]) for p in progress] == [("room-A", "2026-03-02"),
                                                                              ("room-B", "2026-03-04")]
            assert sum(len(p.repetitions) for p in progress) > 0


def test_the_stale_copy_sequence_across_stations(pg_db: Database) -> None:
    """Cap lowered 25 -> 15 mA on A; a session running on B accepts an electrode choice made from its copy of
    before; an old plan dialog on A saves: the lowered cap, the choice and the plan are all kept."""
    with station(pg_db, "room-A") as a, station(pg_db, "room-B") as b:
        start = a.save_patient(full_profile("PZ-200"), expected_version=None, operator="dr_rossi")
        session_copy = b.get_patient("PZ-200")
        plan_copy = a.get_patient("PZ-200")
        lowered = replace(start.profile, fes=replace(start.profile.fes, caps={
            **start.profile.fes.caps, 1: ClinicalChannelCap(15.0, 250.0, 6.0)}))
        a.save_patient(lowered, expected_version=start.version, operator="dr_bianchi")
        with pytest.raises(StaleRecord):  # the session's whole stale copy would raise the cap again: refused
            b.save_patient(session_copy.profile, expected_version=session_copy.version, operator="dr_verdi")
        choice = ElectrodeChoice(channel=4, electrodes="2-4", chosen_by="dr_verdi")
        b.choose_electrodes("PZ-200", "anterior deltoid", choice, expected_version=session_copy.version,
                            operator="dr_verdi")
        plan = [PlannedExercise("trigger_reaching", {"movements": 10}, "")]
        with pytest.raises(StaleRecord) as stale:
            a.save_patient(replace(plan_copy.profile, therapy_plan=plan), expected_version=plan_copy.version,
                           operator="dr_neri")
        assert (stale.value.changed_by, stale.value.changed_station) == ("dr_verdi", "room-B")
        a.save_patient(replace(plan_copy.profile, therapy_plan=plan), expected_version=plan_copy.version,
                       operator="dr_neri", fields=["therapy_plan"])
        final = b.get_patient("PZ-200").profile
        assert final.fes.caps[1].max_current_ma == 15.0 and final.fes.electrodes["anterior deltoid"] == choice
        assert final.therapy_plan == plan
        assert final == replace(lowered, fes=replace(lowered.fes, electrodes={"anterior deltoid": choice}),
                                therapy_plan=plan, updated=final.updated)


_SAVER = """
import json, sys, time
from dataclasses import replace
from pathlib import Path
from app.archive.api import StaleRecord
from app.archive.store import open_archive
url, pw, name, go = sys.argv[1:5]
a = open_archive(url=url, password_file=pw, station=name)
copy = a.get_patient("PZ-300")
print("READ", copy.version, flush=True)
while not Path(go).exists():
    time.sleep(0.01)
try:
    rec = a.save_patient(replace(copy.profile, notes=f"note from {name}", record_number=f"MRN-{name}"),
                         expected_version=copy.version, operator=f"operator-{name}")
    print("SAVED", rec.version, flush=True)
except StaleRecord as exc:
    print("STALE", json.dumps([exc.changed_by, exc.changed_station, str(exc)]), flush=True)
a.close()
"""


def test_concurrent_saves_from_two_processes_one_wins_the_other_is_told_who(pg_db: Database, tmp_path) -> None:
    with station(pg_db, "setup") as s:
        s.save_patient(full_profile("PZ-300"), expected_version=None, operator="dr_rossi")
    go = tmp_path / "go"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [subprocess.Popen([sys.executable, "-c", _SAVER, pg_db.url(APP), pg_db.password_file(APP), name,
                               str(go)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
             for name in ("room-A", "room-B")]
    try:
        for p in procs:
            assert p.stdout is not None and p.stdout.readline().startswith("READ 1")
        go.touch()  # both hold version 1: save now
        outs = [p.communicate(timeout=60)[0].strip() for p in procs]
    finally:
        for p in procs:
            p.kill() if p.poll() is None else None
    assert sorted(o.split()[0] for o in outs) == ["SAVED", "STALE"], outs
    winner = ["room-A", "room-B"][[o.startswith("SAVED") for o in outs].index(True)]
    who, where, said = json.loads(outs[[o.startswith("STALE") for o in outs].index(True)].split(" ", 1)[1])
    assert (who, where) == (f"operator-{winner}", winner) and winner in said
    with station(pg_db, "check") as c:
        rec = c.get_patient("PZ-300")
        assert rec.version == 2 and rec.profile.notes == f"note from {winner}"
        assert rec.profile == replace(full_profile("PZ-300"), notes=f"note from {winner}",
                                      record_number=f"MRN-{winner}", updated=rec.profile.updated)


def test_offline_the_session_waits_then_is_uploaded_exactly_once(pg_db: Database, tmp_path) -> None:
    server = pg_db.server
    folder = make_data_folder(tmp_path / "data")["other"]
    uuid = folders.session_uuid(folder)
    outbox = Outbox(tmp_path / "data" / "sessions", lambda: station(pg_db, "room-A"))
    outbox.set_active([f for f in folders.session_folders(tmp_path / "data" / "sessions") if f != folder])
    server.stop()
    try:
        status = outbox.run_once(force=True)
        assert status.waiting == 1 and status.uploaded == 0
        assert status.text().startswith("1 session waiting for the archive (the archive at ")
        assert "cannot be reached" in status.text() and not folders.is_archived(folder)
    finally:
        server.start()
    status = outbox.run_once(force=True)
    assert (status.uploaded, status.waiting) == (1, 0) and folders.is_archived(folder)
    assert outbox.run_once(force=True).uploaded == 0
    assert count(pg_db, "SELECT count(*) FROM sessions WHERE uuid = %(u)s", u=uuid) == 1
    assert count(pg_db, "SELECT count(*) FROM ledger WHERE key = %(u)s", u=uuid) == 1


_UPLOADER = """
import sys, time
from app.archive.store import open_archive
url, pw, folder = sys.argv[1:4]
a = open_archive(url=url, password_file=pw, station="room-A")
def progress(fraction):
    if fraction > 0.5:
        print("MID", flush=True)
        time.sleep(600)  # killed here, inside the upload's transaction
a.upload_session(folder, progress=progress)
print("DONE", flush=True)
"""


def test_kill_9_in_the_middle_of_an_upload_leaves_nothing_then_uploads_exactly_once(pg_db: Database,
                                                                                   tmp_path) -> None:
    folder = long_session(tmp_path / "sessions" / "PZ-900" / "20260302-100000", minutes=2.0)
    uuid = folders.session_uuid(folder)
    n_events = len((folder / "events.jsonl").read_text().splitlines())
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _UPLOADER, pg_db.url(APP), pg_db.password_file(APP), str(folder)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "MID", proc.stderr.read()
        in_flight = count(pg_db, "SELECT count(*) FROM pg_stat_activity WHERE usename = %(r)s AND state = "
                                 "'idle in transaction'", r=APP)
        assert in_flight == 1  # the upload's transaction is open, its rows written ...
        with station(pg_db, "room-B") as b:  # ... and another station sees none of them
            assert not b.has_session(uuid) and b.list_sessions("PZ-900") == []
        for table in ("sessions WHERE uuid", "journal WHERE session_uuid", "session_files WHERE session_uuid",
                      "runs WHERE session_uuid", "ledger WHERE key"):
            assert count(pg_db, f"SELECT count(*) FROM {table} = %(u)s", u=uuid) == 0, table
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
    deadline = time.monotonic() + 30  # the server ends the dead client's transaction when its socket closes
    while count(pg_db, "SELECT count(*) FROM pg_stat_activity WHERE usename = %(r)s AND state = "
                       "'idle in transaction'", r=APP) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not folders.is_archived(folder)
    outbox = Outbox(tmp_path / "sessions", lambda: station(pg_db, "room-A"))
    assert outbox.status().waiting == 1
    assert outbox.run_once(force=True).uploaded == 1 and outbox.run_once(force=True).uploaded == 0
    assert count(pg_db, "SELECT count(*) FROM sessions WHERE uuid = %(u)s", u=uuid) == 1
    assert count(pg_db, "SELECT count(*) FROM journal WHERE session_uuid = %(u)s", u=uuid) == n_events
    assert count(pg_db, "SELECT count(*) FROM session_files WHERE session_uuid = %(u)s", u=uuid) == 4
    assert count(pg_db, "SELECT count(*) FROM ledger WHERE key = %(u)s", u=uuid) == 1
    with station(pg_db, "room-B") as b:
        with b.materialised(uuid) as copy:
            for f in folders.session_files(folder):
                assert (copy / f.name).read_bytes() == f.path.read_bytes()


def test_verify_on_postgres_names_the_changed_chunk_and_journal_row(pg_db: Database, tmp_path) -> None:
    sessions = make_data_folder(tmp_path / "data")
    with station(pg_db, "room-A") as a:
        uuid = a.upload_session(sessions["interrupted"]).uuid
        assert a.verify().ok
        with psycopg.connect(host="127.0.0.1", port=pg_db.server.port, user="postgres", dbname=pg_db.name,
                             autocommit=True) as admin:
            sha = admin.execute("SELECT sha256 FROM session_files WHERE session_uuid = %s AND name = "
                                "'streams/physio.main.csv'", (uuid,)).fetchone()[0]
            admin.execute("UPDATE blob_chunks SET data = overlay(data placing '\\x39'::bytea from 200 for 1) "
                          "WHERE sha256 = %s AND seq = 0", (sha,))
            problem = a.verify().first_problem
            assert problem is not None and f"streams/physio.main.csv of session {uuid}" in problem.where
            admin.execute("UPDATE blob_chunks SET data = overlay(data placing '\\x30'::bytea from 200 for 1) "
                          "WHERE sha256 = %s AND seq = 0", (sha,))
            original = (sessions["interrupted"] / "streams/physio.main.csv").read_bytes()
            admin.execute("UPDATE blob_chunks SET data = %s WHERE sha256 = %s AND seq = 0", (original, sha))
            assert a.verify().ok
            admin.execute("UPDATE journal SET data = '{}' WHERE session_uuid = %s AND seq = 5", (uuid,))
            problem = a.verify().first_problem
            assert problem is not None and problem.where.startswith(f"session {uuid} journal row 5 (")

