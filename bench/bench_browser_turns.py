"""The sessions browser's listing of a patient's 10 000 sessions (#39; #38: the figures out of the test):

    xvfb-run -a .venv/bin/python bench/bench_browser_turns.py [--trials 5] [--load]

The archive (SQLite, 10 000 sessions of one patient, as tests/test_archive_browser_blocks.py makes it) is listed by
the real SessionsBrowser, trial after trial, in one process with the collector on the main thread as in the app.
A 1 ms timer on the GUI thread measures its CPU (``time.thread_time``) between ticks: each gap is one or a few turns
of its event loop, paints included. Figures: every gap of every trial (median and p99), each trial's longest gap
(median and p99 over the trials), and the most rows one turn of the browser's pump put in. The first trial pays the
imports and fonts: not counted. ``--load``: two ``yes > /dev/null`` meanwhile (killed after). The load average is
printed with every figure. The test proves the structure (the reads off the GUI thread, a few hundred rows a turn)
and holds the turn only against a frozen window's bound; the CPU a turn takes is measured here.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common


def loadavg() -> str:
    return " ".join(common._read("/proc/loadavg").split()[:3])


def one_listing(root: Path) -> tuple[list[float], int, list[tuple[int, float]]]:
    """The GUI thread's CPU per gap (s) while the browser lists the archive; the most rows a pump's turn put in; the
    collections the GUI thread made meanwhile (generation, CPU s)."""
    import gc
    import threading

    from PySide6.QtCore import QTimer

    from app.ui.sessions_browser import SessionsBrowser

    ticks: list[float] = []
    rows_a_turn: list[int] = []
    pump = SessionsBrowser._take

    def take(self: Any) -> None:
        before = self.table.rowCount()
        pump(self)
        rows_a_turn.append(self.table.rowCount() - before)

    SessionsBrowser._take = take  # type: ignore[method-assign]
    passes: list[tuple[int, float]] = []
    started: list[float] = []

    def collector(phase: str, info: dict[str, Any]) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        if phase == "start":
            started[:] = [time.thread_time()]
        elif started:
            passes.append((int(info.get("generation", -1)), time.thread_time() - started[0]))

    gc.callbacks.append(collector)
    clock = QTimer()
    clock.setInterval(1)
    clock.timeout.connect(lambda: ticks.append(time.thread_time()))
    browser = SessionsBrowser(root)
    try:
        browser.show()
        clock.start()
        ticks.append(time.thread_time())
        if not common.run_qt_until(lambda: not browser.loading, 120.0):
            raise TimeoutError("the listing did not end within 120 s")
        ticks.append(time.thread_time())
    finally:
        clock.stop()
        gc.callbacks.remove(collector)
        SessionsBrowser._take = pump  # type: ignore[method-assign]
        browser.close()
        browser.deleteLater()
        common.run_qt_until(lambda: False, 0.2)
    if browser.summaries and len(browser.summaries) != 10_000:
        raise AssertionError(f"{len(browser.summaries)} sessions listed, not 10 000")
    return [b - a for a, b in itertools.pairwise(ticks)], max(rows_a_turn, default=0), passes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--load", action="store_true", help="two `yes > /dev/null` beside it")
    args = parser.parse_args()
    common.print_machine("the sessions browser's listing, 10 000 sessions")
    common.qt_app()
    from app.archive import station
    from app.archive.store import open_archive
    from tests.test_archive_browser_blocks import populate

    with tempfile.TemporaryDirectory(prefix="bench-browser-") as tmp:
        root = Path(tmp)
        archive = open_archive(url=f"sqlite:///{root / 'archive.sqlite3'}", station="room-B")
        populate(archive)
        (root / "sessions").mkdir()
        station.install(archive)
        hogs = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)] if args.load else []
        try:
            gaps: list[float] = []
            longest: list[float] = []
            most_rows = 0
            for trial in range(args.trials + 1):
                trial_gaps, rows, passes = one_listing(root / "sessions")
                longest_pass = max(passes, key=lambda p: p[1], default=(-1, 0.0))
                if trial:  # the first pays the imports and fonts
                    gaps += trial_gaps
                    longest.append(max(trial_gaps))
                    most_rows = max(most_rows, rows)
                print(f"  trial {trial}{' (not counted)' if not trial else ''}: {len(trial_gaps)} gaps, the longest "
                      f"{max(trial_gaps) * 1e3:.1f} ms of CPU, at most {rows} rows a turn; {len(passes)} collections "
                      f"on it, the longest generation {longest_pass[0]}, {longest_pass[1] * 1e3:.1f} ms; "
                      f"load average {loadavg()}",
                      flush=True)
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
            station.uninstall()
            archive.close()
    label = "two `yes` beside it" if args.load else "no `yes`"
    print(f"\n{label}; load average {loadavg()}")
    common.report("the GUI thread's CPU between two 1 ms ticks (every gap)", [g * 1e3 for g in gaps])
    common.report("each trial's longest gap", [g * 1e3 for g in longest])
    print(f"  most rows one turn put in: {most_rows}; longest gap median over trials "
          f"{statistics.median(longest) * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
