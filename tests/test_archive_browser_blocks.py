"""The sessions browser fills a patient's 10 000 sessions in blocks (issue #39): the newest are listed while the rest
is still being read (app.archive.reads.session_blocks: one page of the archive each, keyset-paged), and the rows go
into the table a few at a time, so no turn of the window's thread holds much of its CPU (before: every row in one
turn, ~0.7-1 s of CPU for 10 000).

What is proven is counted, not timed: the archive is read a page at a time on the loader thread, never on the
window's (the thread of every read); each turn of the window's thread that fills the table puts in a few hundred rows
at most (the fill's budget: MOST_ROWS_A_TURN below), the first while the rest are still being read. The GUI thread's CPU
is also measured between the ticks of a 1 ms timer on it (``time.thread_time``: what the thread itself ran, not the
wall clock another process's load stretches), against a bound that only a frozen window reaches (FROZEN_TURN_CPU_S);
the CPU a turn takes, median and p99, quiet and loaded, is bench/bench_browser_turns.py's (bench/README.md)."""

from __future__ import annotations

import itertools
import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import QTimer
from sqlalchemy import insert

from app.archive import reads, station
from app.archive.chain import canonical
from app.archive.models import JournalRow, SessionRow
from app.archive.store import open_archive
from app.therapy.patients import PatientProfile

PATIENT = "PZ-10K"
N = 10_000
STOPPED = 4_321  # the session (counted from the newest, 0-based) that raised a STOP alarm
T0 = 1_767_225_600.0
# The most rows one turn of the GUI thread may put in: the fill's budget (SessionsBrowser.FILL_BUDGET_S, 4 ms of CPU)
# at the cheapest cost a row it assumes (10 µs) is 400. Before the blocks, all 10 000 went in in one turn.
MOST_ROWS_A_TURN = 400
# A frozen window, not a speed: the most CPU of the GUI thread between two ticks of its 1 ms timer. The listing's
# longest is 11-21 ms (alone, load 6-9; bench/bench_browser_turns.py has its median and p99, quiet and loaded); every
# row in one turn was 700-1 000 ms; the GUI watch warns at 350 ms of wall clock. An earlier test's windows destroyed
# in this test's first turn made 143-685 ms (fixed: tests/conftest.py destroys them in their own teardown).
FROZEN_TURN_CPU_S = 0.25


def uuid_of(k: int) -> str:
    return f"00000000-0000-4000-8000-{k:012d}"


def populate(archive: Any) -> None:
    """10 000 archived sessions of one patient, one an hour, newest = k 0; one with a STOP alarm in its journal."""
    archive.save_patient(PatientProfile(patient_id=PATIENT, full_name="Maria Esposito"), expected_version=None,
                         operator="dr_rossi")
    sessions = []
    for k in range(N):
        start = T0 - k * 3600.0
        sessions.append({
            "uuid": uuid_of(k), "patient_id": PATIENT, "station": f"room-{'AB'[k % 2]}", "operator": "dr_rossi",
            "note": "", "start_iso": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime(start)),
            "start_epoch_s": start, "end_iso": "", "duration_s": 1800.0, "status": "complete", "app_version": "0.1.0",
            "format_version": 1, "folder_name": f"{PATIENT}/{k}", "manifest": "{}",
            "exercises": canonical(["Trigger reaching"] if k % 3 else ["Trigger reaching", "Grip squeeze"]),
            "alarms": 1 if k == STOPPED else 0, "summary": "{}", "problems": "[]", "content_digest": "0" * 64,
            "journal_head": "0" * 64, "journal_rows": 1 if k == STOPPED else 0, "archived_at": "",
            "archived_station": ""})
    with archive.engine.begin() as conn:
        conn.execute(insert(SessionRow), sessions)
        conn.execute(insert(JournalRow), [{
            "session_uuid": uuid_of(STOPPED), "seq": 1, "t_wall": "", "t_mono": 1.0, "kind": "alarm", "who": "",
            "origin": "safety", "data": json.dumps({"level": "STOP", "text": "e-stop"}), "prev_hash": "0" * 64,
            "hash": "0" * 64}])


# Its CPU bound is a measurement on the GUI thread of a suite worker: a quiet suite (7cf965f) still saw one turn of
# 253 ms (the listing's own turns: at most 64 rows, 13-16 ms) after the teardown's deferred deletions: a cause not
# found yet (docs/decisions.md #38, session 13). Until it is, the one rerun a timing test gets.
@pytest.mark.realtime
def test_ten_thousand_sessions_are_listed_newest_first_in_blocks_without_a_long_turn(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.ui.sessions_browser import COLUMNS, SessionsBrowser

    archive = open_archive(url=f"sqlite:///{tmp_path / 'archive.sqlite3'}", station="room-B")
    populate(archive)
    pages: list[int] = []  # the limit of each read of the archive's session list
    readers: list[str] = []  # the thread that made each read
    real_list = archive.list_sessions

    def list_sessions(*args: Any, **kwargs: Any) -> Any:
        pages.append(kwargs.get("limit", 200))
        readers.append(threading.current_thread().name)
        return real_list(*args, **kwargs)

    archive.list_sessions = list_sessions
    rows_a_turn: list[int] = []  # the rows each turn of the browser's pump (its timer on the GUI thread) put in
    pump = SessionsBrowser._take

    def take(self: Any) -> None:
        before = self.table.rowCount()
        pump(self)
        rows_a_turn.append(self.table.rowCount() - before)

    monkeypatch.setattr(SessionsBrowser, "_take", take)
    station.install(archive)
    ticks: list[tuple[float, int, bool]] = []  # (the GUI thread's CPU, rows in the table, still loading)
    browser: Any = None
    clock = QTimer()
    clock.setInterval(1)
    clock.timeout.connect(lambda: ticks.append((time.thread_time(), browser.table.rowCount() if browser else 0,
                                                bool(browser and browser.loading))))
    try:
        (tmp_path / "sessions").mkdir()
        clock.start()
        ticks.append((time.thread_time(), 0, True))
        browser = SessionsBrowser(tmp_path / "sessions")  # lists its first patient (the only one) at once
        qtbot.addWidget(browser)
        browser.show()
        built = len(ticks)  # the window's construction is not the listing's: measured from here
        ticks.append((time.thread_time(), browser.table.rowCount(), browser.loading))
        qtbot.waitUntil(lambda: not browser.loading, timeout=120_000)
        clock.stop()
        table = browser.table
        ticks.append((time.thread_time(), table.rowCount(), browser.loading))
        # no turn of the window's thread held more than the bound of its CPU
        gaps = [b[0] - a[0] for a, b in itertools.pairwise(ticks[built:])]
        longest = max(gaps)
        print(f"\n{N} sessions: {len(gaps)} gaps, the GUI thread's longest {longest * 1000:.1f} ms of CPU (next: "
              f"{', '.join(f'{g * 1000:.1f}' for g in sorted(gaps)[-6:-1])}), total {sum(gaps) * 1000:.0f} ms; "
              f"{sum(1 for n in rows_a_turn if n)} turns filled, at most {max(rows_a_turn)} rows a turn")
        # the archive read on the loader thread, never on the window's
        main = threading.main_thread().name
        assert readers and main not in readers, f"the archive's session list was read on {sorted(set(readers))}"
        # the rows put in a few hundred a turn, in many turns
        assert max(rows_a_turn) <= MOST_ROWS_A_TURN, \
            f"a turn of the GUI thread put {max(rows_a_turn)} rows in the table (at most {MOST_ROWS_A_TURN})"
        assert sum(rows_a_turn) == N and sum(1 for n in rows_a_turn if n) >= N // MOST_ROWS_A_TURN
        # no frozen window meanwhile
        assert longest <= FROZEN_TURN_CPU_S, f"the GUI thread held {longest * 1000:.0f} ms of CPU in one turn"
        # the newest were listed while the rest was still coming
        first = next(((rows, loading) for _cpu, rows, loading in ticks if rows), None)
        assert first is not None and first[1] and first[0] < N, \
            f"the first rows came with {first[0] if first else 0} of {N} in the table, loading {first and first[1]}"
        # every session once, newest first, the status from its journal in its row
        assert table.rowCount() == N and len(browser.summaries) == N
        assert [s.uuid for s in browser.summaries] == [uuid_of(k) for k in range(N)]
        dates = [table.item(r, 0).text() for r in range(0, N, 997)]
        assert dates == sorted(dates, reverse=True)
        status, where = COLUMNS.index("Status"), COLUMNS.index("Station")
        assert table.item(STOPPED, status).text() == "ended: 1 stop alarm(s)"
        assert table.item(STOPPED - 1, status).text() == "complete"
        assert [table.item(r, where).text() for r in (0, 1, N - 1)] == ["room-A", "room-B", "room-B"]
        # the loader read the archive a page at a time, never all 10 000 in one query
        assert pages and max(pages) == reads.BLOCK and len(pages) >= N // reads.BLOCK, pages
    finally:
        clock.stop()
        if browser is not None:
            browser.close()
        station.uninstall()
        archive.close()
