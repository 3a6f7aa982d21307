"""The sessions browser's research export reads the archive (issues #39, #41): on station room-B, a session recorded on
room-A (no folder of it on room-B, only in the clinic's archive) is exported as XDF, EDF+ and BIDS straight from the
archive as its files stream (``ArchivedSource``: each file checked against its SHA-256), never copied into a folder
first, and the files are those an export of room-A's own folder makes, byte for byte. On the SQLite archive and on
the real PostgreSQL server of tests/postgres.py (never a mock; under CI=true it fails rather than skips)."""

from __future__ import annotations

import filecmp
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.archive import station
from tests.postgres import APP, PostgresServer, server_or_skip
from tests.test_archive_reads import PATIENT, Clinic, make_two_stations
from tests.waits import WORKER_TASK_MS

MONDAY = "20260302-100000"  # recorded on room-A


@pytest.fixture(scope="module")
def pg_server() -> Iterator[PostgresServer]:
    with server_or_skip() as server:
        yield server


@pytest.fixture(params=["sqlite", "postgresql"])
def clinic(request: Any, tmp_path: Path) -> Clinic:
    if request.param == "sqlite":
        return Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    db = request.getfixturevalue("pg_server").new_database()
    return Clinic(tmp_path / "clinic", db.url(APP), db.password_file(APP))


def files_under(folder: Path) -> dict[str, Path]:
    return {str(p.relative_to(folder)): p for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_session_of_another_station_is_exported_from_the_archive_without_a_copy(
        qtbot: Any, clinic: Clinic, tmp_path: Path, monkeypatch: Any) -> None:
    from app.research_export.jobs import export_sessions
    from app.ui.sessions_browser import SessionsBrowser

    make_two_stations(clinic)  # Monday on room-A, Wednesday on room-B (archived), Friday on room-B (waiting)
    monkeypatch.setenv("LINARMPP_HOME", str(clinic.home("room-B")))
    archive = clinic.archive("room-B")
    station.install(archive)
    browser: Any = None
    try:
        browser = SessionsBrowser(clinic.home("room-B") / "sessions")
        qtbot.addWidget(browser)
        browser.set_patient(PATIENT)
        qtbot.waitUntil(lambda: not browser.loading and browser.table.rowCount() == 3, timeout=30_000)
        (monday,) = [s for s in browser.summaries if s.station == "room-A"]
        assert monday.folder is None  # room-B has no folder of it
        for fmt in ("xdf", "edf", "bids"):
            out = tmp_path / f"from-archive-{fmt}"
            out.mkdir()
            done: list[Any] = []
            assert browser.research_export([monday], fmt, out, on_done=done.append) is not None
            qtbot.waitUntil(lambda done=done: bool(done), timeout=WORKER_TASK_MS)
            assert done[0].ok, done[0].error
            assert "Left out" not in str(done[0].result), done[0].result
            # what an export of room-A's own folder writes, byte for byte (the dataset folder's stamp aside)
            ref = tmp_path / f"from-folder-{fmt}"
            ref.mkdir()
            export_sessions(fmt, [clinic.home("room-A") / "sessions" / PATIENT / MONDAY], ref, "ref")
            got, want = files_under(out), files_under(ref)
            strip = (lambda name: name.split("/", 1)[1]) if fmt == "bids" else (lambda name: name)
            assert sorted(map(strip, got)) == sorted(map(strip, want)) and got, (sorted(got), sorted(want))
            by_name = {strip(k): v for k, v in want.items()}
            for name, path in got.items():
                assert filecmp.cmp(path, by_name[strip(name)], shallow=False), f"{fmt}: {name} differs"
        # read as it streamed: nothing of the session was copied into the browser's folder for it
        assert browser._cache is None or not any(browser._cache.iterdir()), \
            f"the session was copied first: {sorted(browser._cache.rglob('*'))[:5]}"
    finally:
        if browser is not None:
            browser.close()
        station.uninstall()
        archive.close()
