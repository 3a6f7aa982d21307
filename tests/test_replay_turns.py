"""Issue #37, acceptance 1 (the replay's build): opening a replay never holds the GUI thread long in one turn of the
event loop. The sessions browser reads the session in the worker; the window is then built on the GUI thread a
piece per turn. Before this test, its graphs were built a signal per turn by posted calls, each pane added
re-laying out and re-drawing every pane before it: with many graphs a turn grew with their number, and the
posted calls held back the timers between them (the GUI watch's heartbeat is one), so the heartbeat saw two or
three pieces as one stall.

The window is opened here on eleven graphs (one signal of each unit the session recorded: every pane a new one), as a
clinician's choice of many graphs would be, with a 1 ms timer on the GUI thread measuring its turns (what the GUI
watch's heartbeat sees). What is proven is counted, not timed: the panes laid out a bounded number of times however
many there are, the graphs drawn once complete, no paint drawing more than one pane's axes. The CPU of a turn is
held only against a frozen window's bound (FROZEN_TURN_CPU_S); the issue's 50 ms and the CPU a turn takes, median and
p99, quiet and loaded, are the benches' (bench/bench_heavy_work.py --only turns, bench/README.md)."""

from __future__ import annotations

import contextlib
import gc
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pyqtgraph as pg
from PySide6.QtCore import QTimer

from app.session.recording import load_session
from app.ui import replay_window
from app.ui.plots_frame import LiveViewBox, _TimedGraphics
from app.ui.replay_window import ReplayWindow
from app.ui.signal_store import signal_key
from app.worker.session_data import session_data
from tests.heavy_rig import GapMeter
from tests.long_session import write_long_session

# A frozen window, not a speed: the most CPU of the GUI thread in one turn while a past session's replay or summary
# opens. Its CPU, not the wall clock (on this shared 2-core machine a turn's wall time is its CPU stretched by
# whatever else runs). A turn's CPU itself grows with the machine's load, so a speed bound flaked: "run tab 28.7 ms >
# 25 ms" in a quiet suite run. Measured now: the 30-minute session's replay 9-21 ms, its summary 11 ms, its first
# run's tab up to 29 ms; eleven graphs 20-33 ms; before the staged build 17-38 ms and 46-91 ms. The GUI watch warns
# at 350 ms of wall clock. The change itself is proven by what made the long turns, counted: the axes drawn in one
# paint, the layouts of a pane. The figures, median and p99: bench/bench_heavy_work.py --only turns.
FROZEN_TURN_CPU_S = 0.25
# Layouts of a pane (its view resized) while the window opens, whatever the number of panes: two of its own while it
# is built, one in the graphs once they are all there, one to spare. Before, a pane was laid out again for every
# pane added after it: 13 times for the first of eleven.
MAX_LAYOUTS = 4
SESSION_S = 120.0  # the turns do not depend on the length (the first screen is 30 s); a short one is quick to write


@contextlib.contextmanager
def settled_heap() -> Iterator[list[float]]:
    """As the window's heap policy does while a therapy runs (app.core.gc_policy.HeapPolicy.settle): what lives now
    (the test runner's objects, earlier tests' windows, the session read) is out of the garbage collector's walk,
    given back after -- otherwise a full collection's walk over them lands in one of the turns measured (99 ms of CPU
    in a suite's process). Yields the CPU time of each collection the GUI thread made meanwhile."""
    passes: list[float] = []
    started: list[float] = []

    def collector(phase: str, _info: dict) -> None:  # type: ignore[type-arg]
        if threading.current_thread() is not threading.main_thread():
            return
        if phase == "start":
            started[:] = [time.thread_time()]
        elif started:
            passes.append(time.thread_time() - started[0])

    gc.freeze()
    gc.callbacks.append(collector)
    try:
        yield passes
    finally:
        gc.callbacks.remove(collector)
        gc.unfreeze()


def count_axes_per_paint(monkeypatch) -> list[int]:  # type: ignore[no-untyped-def]
    """From now on, for each paint of a pyqtgraph view (the replay's graphs, a summary plot), how many axes it drew
    (generated their ticks, labels and grid) within that paint: the list returned grows a number per paint."""
    axes_per_paint: list[int] = []
    painting: list[int] = []
    original_specs, original_paint = pg.AxisItem.generateDrawSpecs, pg.GraphicsView.paintEvent

    def specs(axis, painter):  # type: ignore[no-untyped-def]
        if painting:
            painting[-1] += 1
        return original_specs(axis, painter)

    def paint(view, event) -> None:  # type: ignore[no-untyped-def]
        painting.append(0)
        try:
            original_paint(view, event)
        finally:
            axes_per_paint.append(painting.pop())

    monkeypatch.setattr(pg.AxisItem, "generateDrawSpecs", specs)
    monkeypatch.setattr(pg.GraphicsView, "paintEvent", paint)
    return axes_per_paint


def _one_signal_per_unit(rec) -> list[str]:  # type: ignore[no-untyped-def]
    chosen: dict[str, str] = {}
    for stream in rec.streams.values():
        for channel in stream.channels:
            chosen.setdefault(channel.unit or "", signal_key(stream.name, channel.name))
    return list(chosen.values())


def _open(data, qtbot, meter: GapMeter) -> tuple[ReplayWindow, float, float]:  # type: ignore[no-untyped-def]
    """Open the window from inside the event loop (as the browser does when the worker's result comes) and wait until
    it is complete; returns it, its GUI thread's longest turn meanwhile and that thread's most CPU time in one."""
    opened: list[ReplayWindow] = []

    def make() -> None:
        window = ReplayWindow(data, 30.0, staged=True)
        qtbot.addWidget(window)
        window.show()
        opened.append(window)

    t0 = time.monotonic()
    QTimer.singleShot(0, make)
    qtbot.waitUntil(lambda: bool(opened) and opened[0].is_ready and not opened[0]._events_left, timeout=30000)
    t1 = time.monotonic()
    qtbot.waitUntil(lambda: meter.ticks[-1][0] > t1 + 0.05, timeout=5000)  # the tick that ends a turn running at t1
    return opened[0], meter.longest(t0, t1), meter.longest_cpu(t0, t1)


def test_opening_a_replay_on_many_graphs_holds_no_turn_long(qtbot, tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    folder = write_long_session(tmp_path, seconds=SESSION_S)
    data = session_data(load_session(folder))  # what the worker hands over (its samples mapped, not copied)
    wanted = _one_signal_per_unit(data.open())
    assert len(wanted) >= 10
    monkeypatch.setattr(replay_window, "default_replay_signals", lambda _rec: list(wanted))
    meter = GapMeter()
    with settled_heap() as collections:
        try:
            warm, _, _ = _open(data, qtbot, meter)  # the first window of the process pays its imports and fonts
            warm.close()
            resized: Counter[int] = Counter()  # ViewBox -> times laid out (resized) while the window opens
            painted: list[int] = []  # the graphs' paints, with the number of panes then
            original_resize, original_paint = LiveViewBox.resizeEvent, _TimedGraphics.paintEvent

            def resize(vb, event) -> None:  # type: ignore[no-untyped-def]
                resized[id(vb)] += 1
                original_resize(vb, event)

            def paint(view, event) -> None:  # type: ignore[no-untyped-def]
                painted.append(len(view.ci.items))
                original_paint(view, event)

            monkeypatch.setattr(LiveViewBox, "resizeEvent", resize)
            monkeypatch.setattr(_TimedGraphics, "paintEvent", paint)
            axes_per_paint = count_axes_per_paint(monkeypatch)
            window, longest, longest_cpu = _open(data, qtbot, meter)
        finally:
            meter.stop()
    assert len(window.plots.plots) == len(wanted) and sorted(window.plots.selected) == sorted(wanted)
    assert all(len(c.getData()[0]) > 1 for c in window.plots.curves.values())  # the first screen is drawn
    assert window.events.count() == len([e for e in data.events if isinstance(e.get("t_mono"), int | float)])
    print(f"\nreplay on {len(wanted)} graphs: the GUI thread's longest turn {longest * 1e3:.0f} ms "
          f"({longest_cpu * 1e3:.0f} ms of its CPU); panes laid out "
          f"{sorted(resized.values())} times; the graphs drawn with {painted} panes; the collector's longest pass "
          f"{max(collections, default=0.0) * 1e3:.1f} ms")
    # The graphs are laid out once they are all there, not again for every pane added to them (a turn per pane grew
    # with the panes) ...
    assert len(resized) == len(wanted) and max(resized.values()) <= MAX_LAYOUTS, \
        f"while the replay opened, its {len(wanted)} panes were laid out {sorted(resized.values())} times"
    # ... and drawn once complete, not each time one more was added.
    assert painted and all(n == len(wanted) for n in painted), \
        f"while the replay opened, its graphs were drawn with {painted} panes"
    # ... and that first paint does not draw every pane's axes (ticks, labels, grid; ~2 ms a pane): they are
    # prepared a pane per turn before it (the panes in view, 12 axes, were drawn in one turn before).
    assert axes_per_paint and max(axes_per_paint) <= 2, \
        f"a paint of the {len(wanted)} graphs drew {max(axes_per_paint)} axes in one turn: {axes_per_paint}"
    # No frozen window meanwhile: the turn's own CPU time, not how long a loaded machine kept it waiting (the wall
    # clock's turn failed at load 13); the figures, quiet and loaded, are the bench's.
    assert longest_cpu <= FROZEN_TURN_CPU_S, (
        f"opening the replay held the GUI thread {longest_cpu * 1e3:.0f} ms of CPU in one turn "
        f"({longest * 1e3:.0f} ms of wall clock)")


def _loadavg() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def test_opening_a_long_sessions_replay_and_summary_holds_no_turn_long(qtbot, tmp_path_factory,  # type: ignore[no-untyped-def]
                                                                      monkeypatch) -> None:
    """Acceptance 1's GUI-thread part: a 30-minute session's replay (its default graphs, its thousand events), then
    its summary and its first run's tab, opened as the sessions browser opens them once the worker has read the session
    (the window made and shown in the turn the result comes, then built a piece per turn): no turn of the GUI thread
    takes more than FROZEN_TURN_CPU_S of its CPU (a frozen window; see there); what made the difference is counted:
    the first paint of the replay's graphs drew every pane's axes (ticks, labels, grid: ~2 ms a pane) in that one
    turn ("a paint of the graphs drew 8 axes in one turn" before); they are prepared a pane per turn before it now."""
    from app.session.reports import run_reports
    from app.ui.session_summary import SessionSummaryDialog
    from app.worker.jobs import SummaryData
    from tests.long_session import shared_long_session

    folder = shared_long_session(tmp_path_factory)
    session = load_session(folder)
    data = session_data(session)  # what the worker hands over (its samples mapped, not copied)
    summary = SummaryData(folder, str(session.manifest.get("patient_id")), run_reports(session), [])
    del session
    assert len(summary.runs) == 2 and len(summary.runs[0].repetitions) > 100

    def replay() -> ReplayWindow:
        window = ReplayWindow(data, 30.0, staged=True)
        qtbot.addWidget(window)
        window.show()
        return window

    def summary_dialog() -> SessionSummaryDialog:
        dialog = SessionSummaryDialog(folder, data=summary, staged=True)
        qtbot.addWidget(dialog)
        dialog.show()
        return dialog

    def first_run(dialog: SessionSummaryDialog) -> SessionSummaryDialog:
        dialog.summary.tabs.setCurrentIndex(1)  # built when first shown
        return dialog

    def opening(make, ready) -> tuple[object, float, float]:  # type: ignore[no-untyped-def]
        """``make()`` from inside the event loop, as a click or the worker's answer; the GUI thread's longest turn
        and its most CPU in one turn until ``ready(widget)``."""
        made: list[object] = []
        t0 = time.monotonic()
        QTimer.singleShot(0, lambda: made.append(make()))
        qtbot.waitUntil(lambda: bool(made) and ready(made[0]), timeout=60000)
        t1 = time.monotonic()
        qtbot.waitUntil(lambda: meter.ticks[-1][0] > t1 + 0.05, timeout=5000)  # the tick that ends a turn at t1
        return made[0], meter.longest(t0, t1), meter.longest_cpu(t0, t1)

    def replay_ready(w) -> bool:  # type: ignore[no-untyped-def]
        return bool(w.is_ready and not w._events_left and not w._steps.running)

    axes_per_paint = count_axes_per_paint(monkeypatch)
    meter = GapMeter()
    with settled_heap() as collections:
        try:
            for _warm in range(2):  # the first of each in the process pays its imports and fonts; measured: the second
                axes_per_paint.clear()
                window, replay_wall, replay_cpu = opening(replay, replay_ready)
                window.close()  # type: ignore[attr-defined]
                dialog, summary_wall, summary_cpu = opening(summary_dialog, lambda d: d.summary.is_ready)
                _, tab_wall, tab_cpu = opening(lambda d=dialog: first_run(d), lambda d: d.summary.is_ready)
                dialog.close()  # type: ignore[attr-defined]
        finally:
            meter.stop()
    assert window.events.count() == len([e for e in data.events if isinstance(e.get("t_mono"), int | float)])
    # its default graphs, each drawn
    assert sorted(window.plots.selected) == sorted(replay_window.default_replay_signals(window.source.session))  # type: ignore[attr-defined]
    assert all(len(c.getData()[0]) > 1 for c in window.plots.curves.values())  # type: ignore[attr-defined]
    assert dialog.summary.run_views[summary.runs[0].run.run_id].plots_built
    assert axes_per_paint and max(axes_per_paint) <= 2, \
        f"a paint of the graphs drew {max(axes_per_paint)} axes in one turn (one pane has two): {axes_per_paint}"
    figures = (f"replay {replay_cpu * 1e3:.1f} ms of CPU ({replay_wall * 1e3:.0f} ms wall), summary "
               f"{summary_cpu * 1e3:.1f} ({summary_wall * 1e3:.0f}), its first run's tab {tab_cpu * 1e3:.1f} "
               f"({tab_wall * 1e3:.0f}); the collector's longest pass "
               f"{max(collections, default=0.0) * 1e3:.1f} ms; load average {_loadavg()}")
    print(f"\n30-minute session, the GUI thread's longest turn: {figures}")
    assert max(replay_cpu, summary_cpu, tab_cpu) <= FROZEN_TURN_CPU_S, \
        f"opening a 30-minute session held the GUI thread too long in one turn: {figures}"
