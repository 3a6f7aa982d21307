"""The archive's figures (issue #39): listing 10 000 sessions of 2 000 patients (the sessions browser's query and
the progress report's query for one patient) and uploading a 30-minute session, on SQLite and on a PostgreSQL
server on loopback (started here like the tests': tests/postgres.py, stopped at the end).

    .venv/bin/python bench/bench_archive.py [--sessions 10000] [--patients 2000] [--minutes 30] [--trials 30]
                                            [--engines sqlite,postgresql] [--load]

``--load`` runs two ``yes > /dev/null`` beside it (killed at the end). The 10 000 sessions are inserted as rows
(each with two runs of five repetitions, a manifest of realistic size, one to three of eight exercise titles): the
figure is the queries', not the import's. Besides the queries, the readers the application runs on them: the
sessions browser's rows of one patient (``reads.session_listing``: sessions, their journals' statuses) and the
progress report's rows (``reads.progress_rows``). The upload is the whole of ``upload_session``: hashing, reading the
session and its metrics, and the one transaction with the files' bytes re-hashed by the database; its parts are
timed apart before it (reading the stream files imports pandas once per process: timed on its own). Each figure
also gives the process's CPU time (``time.process_time``: what a quiet machine would take, less the database
server's and the disk's part), and the load average is printed at the start and at the end.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import common  # noqa: F401  (sys.path, LINARMPP_HOME)
from sqlalchemy import insert

from app.archive.models import Patient, RepetitionRow, RunRow, SessionRow
from app.archive.store import SqlArchive, canonical, open_archive
from app.core.config import AppConfig, config_as_dict

TARGET_LIST_MS = 200.0
TARGET_UPLOAD_S = 5.0


EXERCISES = ("Trigger reaching", "Assisted reaching", "Temperature follow", "Grip squeeze", "Tracking",
             "Free reaching", "Resistance", "Relaxation")


def titles_of(k: int) -> list[str]:
    """One to three exercises a session, varying from session to session (not one list repeated)."""
    return [EXERCISES[(k * 7 + j * 3) % len(EXERCISES)] for j in range(1 + k % 3)]


def populate(archive: SqlArchive, n_sessions: int, n_patients: int) -> None:
    manifest = json.dumps({"format_version": 1, "config": config_as_dict(AppConfig()),
                           "patient": {"scores": {"fugl_meyer_ue": 31}}})
    rep = canonical({"index": 1, "completed": True, "peak_speed_m_s": 0.3, "sparc": -1.5, "duration_s": 1.8,
                     "reaction_time_s": 0.2, "path_length_m": 0.2})
    summary = canonical({"repetitions": 10, "completed": 9, "sparc": {"mean": -1.5, "sd": 0.1, "n": 10}})
    t0 = 1_767_225_600.0
    batch = 2000
    with archive.engine.begin() as conn:
        conn.execute(insert(Patient), [{
            "patient_id": f"P{k:05d}", "version": 1, "full_name": f"Name {k}", "birth_date": "", "record_number":
            f"MRN-{k}", "affected_side": "left", "notes": "", "fes_profile": "", "scores": "{}", "assistance": "{}",
            "robot": "{}", "fes_caps": "{}", "search_text": f"p{k:05d} name {k} mrn-{k}", "created": "",
            "updated": "", "changed_at": "", "changed_by": "", "changed_station": ""} for k in range(n_patients)])
        for a in range(0, n_sessions, batch):
            sessions, runs, reps = [], [], []
            for k in range(a, min(n_sessions, a + batch)):
                uuid = f"00000000-0000-4000-8000-{k:012d}"
                start = t0 + k * 3600.0
                sessions.append({
                    "uuid": uuid, "patient_id": f"P{k % n_patients:05d}", "station": f"room-{k % 3}",
                    "operator": "dr_rossi", "note": "", "start_iso": time.strftime("%Y-%m-%dT%H:%M:%S+00:00",
                                                                                  time.gmtime(start)),
                    "start_epoch_s": start, "end_iso": "", "duration_s": 1800.0, "status": "complete",
                    "app_version": "0.1.0", "format_version": 1, "folder_name": f"P{k % n_patients:05d}/{k}",
                    "manifest": manifest, "exercises": canonical(titles_of(k)),
                    "alarms": k % 2, "summary": summary, "problems": "[]", "content_digest": "0" * 64,
                    "journal_head": "0" * 64, "journal_rows": 0, "archived_at": "", "archived_station": ""})
                for position in (1, 2):
                    runs.append({"session_uuid": uuid, "position": position, "run_id": f"run-{position}",
                                 "program": "{}", "title": "Trigger reaching", "parameters": "[]", "source": "plan",
                                 "operator": "dr_rossi", "restart_of": None, "started_s": 10.0 * position,
                                 "ended_s": 10.0 * position + 5, "end_reason": "finished", "end_detail": "",
                                 "summary": summary})
                    reps += [{"session_uuid": uuid, "run_position": position, "idx": i, "run_id": f"run-{position}",
                              "metrics": rep} for i in range(1, 6)]
            conn.execute(insert(SessionRow), sessions)
            conn.execute(insert(RunRow), runs)
            conn.execute(insert(RepetitionRow), reps)
    if archive.dialect == "postgresql":
        with archive.engine.connect() as conn:
            conn.exec_driver_sql("COMMIT")
            conn.exec_driver_sql("ANALYZE")
    else:
        with archive.engine.connect() as conn:
            conn.exec_driver_sql("ANALYZE")


def timed(fn, trials: int) -> tuple[float, float, float]:
    """(median, p99, median CPU time) in ms."""
    fn()  # warm: the first call's plan and pages
    times, cpu = [], []
    for _ in range(trials):
        t, c = time.perf_counter(), time.process_time()
        fn()
        times.append((time.perf_counter() - t) * 1000)
        cpu.append((time.process_time() - c) * 1000)
    times.sort()
    return statistics.median(times), times[min(len(times) - 1, round(0.99 * (len(times) - 1)))], statistics.median(cpu)


def load_average() -> str:
    with open("/proc/loadavg") as fh:
        return " ".join(fh.read().split()[:3])


def run_engine(name: str, archive: SqlArchive, args: argparse.Namespace, work: Path) -> list[tuple[str, str]]:
    from app.archive import folders, reads
    from tests.archive_data import long_session

    rows = []
    populate(archive, args.sessions, args.patients)
    assert archive.count_sessions() == args.sessions
    patient = "P00042"
    root = work / f"{name}-station"  # this station's folders: none (every session is archived)
    root.mkdir()
    checks = {
        "sessions browser, newest 200 of all": lambda: archive.list_sessions(limit=200),
        f"all {args.sessions} sessions in one query": lambda: archive.list_sessions(limit=args.sessions),
        "sessions browser, one patient's rows (reads.session_listing: sessions and their statuses)":
            lambda: reads.session_listing(patient, root, archive, True),
        "--progress, one patient's rows (reads.progress_rows: sessions, runs, repetitions)":
            lambda: reads.progress_rows(patient, root, archive),
        f"patients list ({args.patients}, with session counts)": lambda: archive.list_patients(limit=args.patients),
    }
    for label, fn in checks.items():
        med, p99, cpu = timed(fn, args.trials)
        verdict = "ok" if p99 <= TARGET_LIST_MS else "MISSED"
        rows.append((f"{name}: {label}", f"{med:.1f} / {p99:.1f} ms ({verdict}); CPU {cpu:.1f} ms"))
    folder = long_session(work / f"{name}-sessions" / "PZ-900" / "20260302-100000", minutes=args.minutes,
                          seed=hash(name) % 1000)
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    from app.session import metrics
    from app.session.recording import load_session

    parts = []
    t, c = time.perf_counter(), time.process_time()
    import pandas  # noqa: F401  (once per process: the worker that uploads has it after its first session)
    parts.append(("importing pandas (once per process)", time.perf_counter() - t, time.process_time() - c))
    for label, fn in (("hashing its files", lambda: folders.session_files(folder)),
                      ("reading it (load_session: the stream files parsed)", lambda: load_session(folder)),
                      ("its metrics (app.session.metrics)", lambda: metrics.metrics_of_session(load_session(folder)))):
        t, c = time.perf_counter(), time.process_time()
        fn()
        parts.append((label, time.perf_counter() - t, time.process_time() - c))
    parts[-1] = (parts[-1][0], parts[-1][1] - parts[-2][1], parts[-1][2] - parts[-2][2])  # less the read
    from app.archive import derive

    inside: list[float] = []  # the upload's own reading and metrics (derive_session), timed where it runs
    original = derive.derive_session

    def timed_derive(*a: object) -> derive.Derived:
        t = time.perf_counter()
        try:
            return original(*a)  # type: ignore[arg-type]
        finally:
            inside.append(time.perf_counter() - t)

    derive.derive_session = timed_derive  # type: ignore[assignment]
    try:
        t, c = time.perf_counter(), time.process_time()
        result = archive.upload_session(folder)
        elapsed, cpu_s = time.perf_counter() - t, time.process_time() - c
    finally:
        derive.derive_session = original  # type: ignore[assignment]
    assert result.outcome == "uploaded"
    verdict = "ok" if elapsed <= TARGET_UPLOAD_S else "MISSED"
    rows.append((f"{name}: upload of a {args.minutes:g}-minute session ({size / 1e6:.0f} MB, "
                 f"{len(archive.journal(result.uuid))} events), end to end",
                 f"{elapsed:.2f} s ({verdict}); CPU {cpu_s:.2f} s"))
    rows.append((f"{name}: … in it, reading the session and its metrics (derive_session)", f"{sum(inside):.2f} s"))
    rows.append((f"{name}: … in it, the rest: hashing the files and the one transaction (files, rows, journal, the "
                 "database's re-hash)", f"{elapsed - sum(inside):.2f} s"))
    for label, wall, cpu in parts:
        rows.append((f"{name}: … apart, before it: {label}", f"{wall:.2f} s; CPU {cpu:.2f} s"))
    t = time.perf_counter()
    assert archive.upload_session(folder).outcome == "already_archived"
    rows.append((f"{name}: the same upload again (no-op)", f"{(time.perf_counter() - t) * 1000:.0f} ms"))
    # The application's own path: at a session's end the worker writes the columnar side-file (index_session)
    # before the outbox's pass uploads it, so the upload reads mapped columns instead of parsing the CSV.
    from app.session.recording import index_session

    other = long_session(work / f"{name}-sessions" / "PZ-901" / "20260303-100000", minutes=args.minutes,
                         seed=hash(name) % 1000 + 1)
    assert index_session(other, force=True) == ""
    t, c = time.perf_counter(), time.process_time()
    assert archive.upload_session(other).outcome == "uploaded"
    elapsed, cpu_s = time.perf_counter() - t, time.process_time() - c
    rows.append((f"{name}: upload of another {args.minutes:g}-minute session whose columnar side-file the worker "
                 "wrote at its end (the application's path)",
                 f"{elapsed:.2f} s ({'ok' if elapsed <= TARGET_UPLOAD_S else 'MISSED'}); CPU {cpu_s:.2f} s"))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sessions", type=int, default=10_000)
    parser.add_argument("--patients", type=int, default=2_000)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--engines", default="sqlite,postgresql")
    parser.add_argument("--load", action="store_true", help="two `yes > /dev/null` beside the benchmark")
    args = parser.parse_args()
    start_load = load_average()
    loaders = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)] if args.load else []
    work = Path(tempfile.mkdtemp(prefix="linarmpp-bench-archive-"))
    rows: list[tuple[str, str]] = []
    server = None
    try:
        for engine in args.engines.split(","):
            if engine == "sqlite":
                with open_archive(url=f"sqlite:///{work / 'archive.sqlite3'}", station="bench") as archive:
                    rows += run_engine("SQLite", archive, args, work)
            elif engine == "postgresql":
                from tests.postgres import APP, start_server

                server = start_server()
                db = server.new_database()
                with open_archive(url=db.url(APP), password_file=db.password_file(APP), station="bench") as archive:
                    rows += run_engine("PostgreSQL", archive, args, work)
    finally:
        if server is not None:
            server.destroy()
        for p in loaders:
            p.kill()
            p.wait()
        shutil.rmtree(work, ignore_errors=True)
    print(f"load average at the start: {start_load}, at the end: {load_average()}; "
          f"{'two yes beside it' if args.load else 'no yes beside it'}")
    print("| figure | median / p99 (target: listing ≤ 200 ms, upload ≤ 5 s) |\n|---|---|")
    for label, value in rows:
        print(f"| {label} | {value} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
