"""Heavy work out of the real-time process (issue #37): the figures of bench/README.md's "Session 6 (#37a)".

    .venv/bin/python bench/bench_heavy_work.py [--trials 3] [--load] [--source DIR] [--only load|open|f12|turns]

A 30-minute session with every stream at its rate (tests/long_session.py, the recorder's on-disk format, its
columnar side-file written as the worker writes it at a session's end) is made in a temporary folder, then:

* ``load``: ``load_session`` of it, best and median of ``--trials``: parsing the CSV files (the only way before
  #37; ``columns=False`` after) and reading the columnar side-file (after).
* ``open``: the window with a therapy running (simulated LINarm homed and ON, the stimulator stimulating), the
  sessions browser on that session; Replay, then Summary, each clicked from inside the event loop as a click is.
  Figures: the GUI thread's longest stall (a 1 ms timer's longest gap) from the click until the window is ready
  -- after #37 split into the worker's load and the window's build --, the host's longest silence towards the
  LINarm (its controller's watchdog trips at 250 ms), whether the FES guardian sent Stop, the alarms; for the
  summary also its first run's tab clicked (built when first shown): the longest stall until it is complete.
* ``turns`` (not in the default run): the window's own turns alone, without a therapy (the machine's load does not
  stop it): the session read in this process as the worker reads it, then its replay opened, closed, its summary
  opened and its first run's tab clicked, each from inside the event loop; per trial the GUI thread's longest turn
  (its CPU and its wall time) in each; median and p99 over ``--trials``.
* ``f12``: Replay clicked, F12 posted from another thread 0.3 s later (during the load, as a key press reaches a
  busy GUI thread): its delay to FES Stop and to robot IDLE on the wire.

``--source DIR`` measures the application in DIR (e.g. ``git archive`` of the code before #37) with this tree's
bench and rig. Each ``open``/``f12`` trial starts a fresh therapy (the code before #37 does not survive one).
``--load``: two ``yes > /dev/null`` meanwhile (killed after). The load average is printed with every figure.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common

SOURCE = ""
if "--source" in sys.argv:
    SOURCE = str(Path(sys.argv[sys.argv.index("--source") + 1]).resolve())
    sys.path.insert(0, SOURCE)  # its app package first; tests/ is a namespace: both trees' files are found


def loadavg() -> str:
    return " ".join(common._read("/proc/loadavg").split()[:3])


def bench_load(folder: Path, trials: int) -> None:
    import inspect

    from app.session import recording

    if "columns" in inspect.signature(recording.load_session).parameters:
        rows = [("CSV parse", lambda: recording.load_session(folder, columns=False)),
                ("columnar side-file", lambda: recording.load_session(folder))]
    else:  # before #37: the CSV parse is the only way
        rows = [("CSV parse", lambda: recording.load_session(folder))]
    for name, fn in rows:
        times = []
        for _ in range(trials):
            t0 = time.perf_counter()
            session = fn()
            times.append(time.perf_counter() - t0)
        samples = sum(len(s) for s in session.streams.values())
        print(f"  load_session, {name}: best {min(times):.3f} s, median {statistics.median(times):.3f} s "
              f"({samples} samples; load average {loadavg()})", flush=True)


def _wait(app: Any) -> Any:
    def wait(predicate: Any, timeout_ms: int) -> None:
        if not common.run_qt_until(predicate, timeout_ms / 1000):
            raise TimeoutError("the bench waited in vain")
    return wait


def _open_old(therapy: Any, action: str) -> dict[str, Any]:
    """The code before #37: the browser's action loads on the GUI thread and returns the window."""
    from PySide6.QtCore import QTimer

    state: dict[str, Any] = {}

    def click() -> None:
        state["t"] = time.monotonic()
        state["w"] = getattr(therapy.browser, action)()
        state["end"] = time.monotonic()

    QTimer.singleShot(0, click)
    common.run_qt_until(lambda: "end" in state, 120.0)
    common.run_qt_until(lambda: False, 0.2)
    t0, t1 = state["t"], state["end"]
    seen = therapy.check_undisturbed(t0, t1 + 0.2)
    state["w"].close()
    return {"open_s": t1 - t0, "stall_s": therapy.meter.longest(t0, t1 + 0.2), **seen}


def _meter_cpu() -> None:
    """The GUI watch's stand-in (tests/heavy_rig.GapMeter) also keeps the GUI thread's CPU time of every turn: on a
    busy PC a turn's wall time is stretched by other processes' work, its CPU time is the window's own."""
    from tests import heavy_rig

    def tick(self: Any) -> None:
        now, cpu = time.monotonic(), time.thread_time()
        self.ticks.append((now, now - self._last))
        if not hasattr(self, "cpu"):
            self.cpu, self._last_cpu = [], cpu
        self.cpu.append(cpu - self._last_cpu)
        self._last, self._last_cpu = now, cpu

    heavy_rig.GapMeter._tick = tick


def _turns(meter: Any, t0: float, t1: float) -> tuple[float, float]:
    """The longest turn's CPU time between t0 and t1 and the median turn's wall time."""
    picked = [(gap, cpu) for (t, gap), cpu in zip(meter.ticks, getattr(meter, "cpu", []), strict=False) if t0 < t <= t1]
    if not picked:
        return 0.0, 0.0
    return max(cpu for _, cpu in picked), statistics.median(gap for gap, _ in picked)


def _open_new(therapy: Any, action: str) -> dict[str, Any]:
    from tests.heavy_rig import open_from_browser

    ready = (lambda w: w.is_ready and not w._events_left) if action == "replay" else (lambda d: d.summary.is_ready)
    o = open_from_browser(therapy, action, ready, _wait(None))
    t1 = time.monotonic()
    cpu, median = _turns(therapy.meter, t1 - o.seconds - 0.06, t1)
    tab = {}
    if action == "open_summary":
        tab_stall, tab_cpu, tab_median = _run_tab(therapy, o.widget.summary)
        tab = {"tab_stall_s": tab_stall, "tab_cpu_s": tab_cpu, "tab_median_s": tab_median}
    o.widget.close()
    return {"open_s": o.seconds, "stall_s": max(o.load_stall_s, o.build_stall_s), "load_stall_s": o.load_stall_s,
            "build_stall_s": o.build_stall_s, "cpu_s": cpu, "median_s": median, **tab, **o.therapy}


def _run_tab(therapy: Any, summary: Any) -> tuple[float, float, float]:
    """The first run's tab clicked in an open summary (built when first shown): the GUI thread's longest stall until
    it is complete (its table and plots), the longest turn's CPU time, the median turn."""
    from PySide6.QtCore import QTimer

    t0 = time.monotonic()
    QTimer.singleShot(0, lambda: summary.tabs.setCurrentIndex(1))  # from inside the event loop, as a click
    common.run_qt_until(lambda: summary.tabs.currentIndex() == 1 and summary.is_ready, 60.0)
    t1 = time.monotonic()
    common.run_qt_until(lambda: therapy.meter.ticks[-1][0] > t1 + 0.05, 5.0)  # the tick that ends a stall at t1
    return (therapy.meter.longest(t0, t1), *_turns(therapy.meter, t0, t1 + 0.05))


def bench_turns(folder: Path, trials: int) -> None:
    """The GUI thread's longest turn (CPU and wall) while a replay, a summary and its first run's tab open."""
    from PySide6.QtCore import QTimer

    from app.worker import jobs
    from app.worker.context import JobContext
    from tests.heavy_rig import GapMeter

    ctx = JobContext(0, None)
    data, summary = jobs.load_data(ctx, folder), jobs.summary(ctx, folder)
    jobs.import_result_types()
    from app.ui.replay_window import ReplayWindow
    from app.ui.session_summary import SessionSummaryDialog

    meter = GapMeter()

    def opening(make: Any, ready: Any) -> tuple[Any, float, float]:
        made: list[Any] = []
        t0 = time.monotonic()
        QTimer.singleShot(0, lambda: made.append(make()))
        if not common.run_qt_until(lambda: bool(made) and ready(made[0]), 60.0):
            raise TimeoutError("the window was not ready within 60 s")
        t1 = time.monotonic()
        common.run_qt_until(lambda: meter.ticks[-1][0] > t1 + 0.05, 5.0)
        return made[0], meter.longest(t0, t1), meter.longest_cpu(t0, t1)

    def replay() -> Any:
        w = ReplayWindow(data, 30.0, staged=True)
        w.show()
        return w

    def summary_dialog() -> Any:
        d = SessionSummaryDialog(folder, data=summary, staged=True)
        d.show()
        return d

    def first_run(d: Any) -> Any:
        d.summary.tabs.setCurrentIndex(1)
        return d

    rows: dict[str, list[tuple[float, float]]] = {"replay": [], "summary": [], "its first run's tab": []}
    for trial in range(trials + 1):  # the first pays the imports and fonts: not counted
        w, wall, cpu = opening(replay, lambda w: w.is_ready and not w._events_left and not w._steps.running)
        w.close()
        common.run_qt_until(lambda: False, 0.2)
        d, wall2, cpu2 = opening(summary_dialog, lambda d: d.summary.is_ready)
        _, wall3, cpu3 = opening(lambda d=d: first_run(d), lambda d: d.summary.is_ready)
        d.close()
        common.run_qt_until(lambda: False, 0.2)
        if trial:
            rows["replay"].append((cpu, wall))
            rows["summary"].append((cpu2, wall2))
            rows["its first run's tab"].append((cpu3, wall3))
    meter.stop()
    for name, values in rows.items():
        cpus, walls = [c * 1e3 for c, _ in values], [w * 1e3 for _, w in values]
        print(f"  {name}: the GUI thread's longest turn, its CPU median {statistics.median(cpus):.1f} ms, p99 "
              f"{common.percentile(cpus, 99):.1f} ms; wall median {statistics.median(walls):.1f} ms, p99 "
              f"{common.percentile(walls, 99):.1f} ms ({len(values)} trials; load average {loadavg()})", flush=True)


def bench_open(folder: Path, trials: int, what: str) -> None:
    from tests.heavy_rig import start_therapy, stop_therapy

    _meter_cpu()
    new = _is_new()
    for action in (("replay", "open_summary") if what == "open" else ("replay",)):
        rows = []
        for _ in range(trials):
            therapy = start_therapy(folder.parent.parent, _wait(None))
            try:
                therapy.browser.set_patient(folder.parent.name)
                therapy.browser.select_folder(folder)
                if new:
                    common.run_qt_until(lambda t=therapy: t.browser.tasks.service.last_start_s is not None, 20.0)
                common.run_qt_until(lambda: False, 1.0)
                if what == "f12":
                    rows.append(_f12(therapy, new))
                else:
                    rows.append(_open_new(therapy, action) if new else _open_old(therapy, action))
            finally:
                stop_therapy(therapy)
        _print(action if what == "open" else "F12 during the load", rows)


def _f12(therapy: Any, new: bool) -> dict[str, Any]:
    from PySide6.QtCore import QTimer

    state: dict[str, Any] = {}

    def click() -> None:
        state["task"] = therapy.browser.replay()

    thread, pressed = therapy.press_f12_later(0.3)
    QTimer.singleShot(0, click)
    thread.join()
    common.run_qt_until(lambda: all(d is not None for d in therapy.stop_delays(pressed["t"])), 30.0)
    fes, robot = therapy.stop_delays(pressed["t"])
    if new:
        common.run_qt_until(lambda: state.get("task") is not None and state["task"].done, 60.0)
    common.run_qt_until(lambda: False, 0.3)
    for w in list(therapy.browser.windows):
        w.close()
    return {"fes_s": fes, "robot_s": robot}


def _print(name: str, rows: list[dict[str, Any]]) -> None:
    if "fes_s" in rows[0]:
        fes = [r["fes_s"] * 1e3 for r in rows if r["fes_s"] is not None]
        robot = [r["robot_s"] * 1e3 for r in rows if r["robot_s"] is not None]
        print(f"  {name}: FES Stop on the wire max {max(fes):.1f} ms (median {statistics.median(fes):.1f}), robot "
              f"IDLE max {max(robot):.1f} ms (median {statistics.median(robot):.1f}); load average {loadavg()}",
              flush=True)
        return
    def ms(key: str) -> str:
        values = [r[key] * 1e3 for r in rows if key in r]
        def f(v: float) -> str:
            return f"{v:.1f}" if v < 10 else f"{v:.0f}"
        return f"max {f(max(values))} ms (median {f(statistics.median(values))})" if values else "—"
    tripped = sum(1 for r in rows if r.get("robot_error") not in (0, None))
    stops = sum(1 for r in rows if r["fes_stop_on_wire"])
    print(f"  {name}: open {statistics.median(r['open_s'] for r in rows):.2f} s; GUI thread's longest stall "
          f"{ms('stall_s')}" + (f" [worker's load {ms('load_stall_s')}, window's build {ms('build_stall_s')}]"
                                if "load_stall_s" in rows[0] else "")
          + (f"; longest turn's CPU {ms('cpu_s')}, median turn {ms('median_s')}" if "cpu_s" in rows[0] else "")
          + (f"; a run's tab shown: longest stall {ms('tab_stall_s')}, its CPU {ms('tab_cpu_s')}, median turn "
             f"{ms('tab_median_s')}" if "tab_stall_s" in rows[0] else "")
          + f"; host silence to the LINarm {ms('host_silence_s')}; watchdog tripped {tripped}/{len(rows)}, "
            f"FES stopped by the guardian {stops}/{len(rows)}; load average {loadavg()}", flush=True)
    for r in rows:
        if r["alarms"]:
            print(f"    alarms: {r['alarms']}")


def _is_new() -> bool:
    import app.ui.sessions_browser as sb

    return hasattr(sb.SessionsBrowser, "opened")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--load", action="store_true", help="two `yes > /dev/null` meanwhile")
    parser.add_argument("--source", default="", help="measure the application in this folder")
    parser.add_argument("--only", choices=("load", "open", "f12", "turns"), default=None)
    parser.add_argument("--session", default="", help="an existing long session folder (else one is made)")
    args = parser.parse_args()
    common.qt_app()
    from app.application import configure_qt_identity

    configure_qt_identity()
    import app

    common.print_machine("bench_heavy_work: a 30-minute session read during a therapy (issue #37)")
    print(f"  application: {Path(app.__file__).parent.parent}{' (before #37)' if not _is_new() else ''}; "
          f"{'two yes beside it' if args.load else 'nothing beside it'}", flush=True)
    if args.session:
        folder = Path(args.session)
    else:
        from app.session import recording
        from tests.long_session import write_long_session

        folder = write_long_session(Path(tempfile.mkdtemp(prefix="linarmpp-bench-long-")),
                                    columns=hasattr(recording, "save_columns"))
    loads = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)] if args.load else []
    for proc in loads:  # ordinary load, even when the bench itself runs under chrt (a stand-in for a quiet machine)
        os.sched_setscheduler(proc.pid, os.SCHED_OTHER, os.sched_param(0))
    try:
        if args.only in (None, "load"):
            bench_load(folder, args.trials)
        if args.only in (None, "open"):
            bench_open(folder, args.trials, "open")
        if args.only in (None, "f12"):
            bench_open(folder, args.trials, "f12")
        if args.only == "turns":
            bench_turns(folder, args.trials)
    finally:
        for proc in loads:
            proc.kill()
            proc.wait()
    os._exit(0)  # the Qt objects of the rigs go with the process


if __name__ == "__main__":
    sys.exit(main())
