"""The window's own CPU (issue #16, acceptance 3): the GUI thread and the OpenGL rasteriser threads of the app
at nominal stream rates with the main window open (default graphs, the 3D view visible), robot idle or moving.

    xvfb-run -a -s "-screen 0 1920x1080x24" env QT_QPA_PLATFORM=xcb \\
        .venv/bin/python bench/bench_window.py [--seconds 10] [--runs 3] [--moving] [--screenshot out.png]

Under Xvfb the 3D view is drawn by Mesa llvmpipe, i.e. on the CPU by threads of the app's own process named
``llvmpipe-N``; offscreen there is no 3D view (the 2D drawing replaces it), so run it under Xvfb for the real
figure. "Window share" = the GUI thread + the llvmpipe threads; the X server's own CPU (it composes what the app
puts on screen) is printed beside it. ``--moving`` runs bench/scripts/reach_exercise.py (0.10 <-> 0.40 m) during
the measurement. The machine may be shared: the load average is printed with every run.

``--stalls S`` measures instead the GUI thread's normal stalls during therapy (issue #37: the GUI watch's
thresholds leave room for them): every signal in the graphs, FES stimulating, the reach exercise moving the arm,
for S seconds; the longest gap of a 1 ms timer and the largest heartbeat age the GUI watch saw. ``--load``: two
``yes > /dev/null`` meanwhile.

``--fes-start N`` measures instead the GUI thread's longest stall while starting FES (issue #29, acceptance 3):
with the window open, an FES panel (app.ui.fes_panel.FesPanel, the commands frame's) loads
frontal_reaching.yaml and its Start button is clicked N times (each followed by Stop); a 1 ms timer on the GUI
thread records the gaps between its ticks, and the longest gap from the click until stimulation runs (or the
panel says why not) is the stall. The same gaps over a window without a click are printed beside it (what the
GUI thread does anyway). Before #29 the click waited on the GUI thread for the channel list's acks; it runs the
same on either code (it only clicks the button). ``--no-ack`` withholds the init's ack each time (simulators
hosted as threads, to reach their core): the stimulator that does not answer, where the old Start waited
``ack_timeout_s``. ``--load``: two ``yes > /dev/null`` meanwhile.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
if "--no-ack" in sys.argv:  # before the app is imported: the simulators as threads, so their core is reachable
    os.environ["LINARMPP_SIM_HOST"] = "thread"

import common
from bench_headroom import config_at

SCRIPT = common.BENCH / "scripts" / "reach_exercise.py"


def x_server_pid() -> int | None:
    """The Xvfb serving our DISPLAY (several may run on a shared machine)."""
    display = os.environ.get("DISPLAY", "")
    if not display:
        return None
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if argv and argv[0].endswith(b"Xvfb") and display.encode() in argv:
            return int(pid)
    return None


def run_loop(seconds: float) -> None:
    """Run the Qt event loop for ``seconds`` with no polling timer of the benchmark's own
    (common.run_qt_until checks its predicate every 5 ms: 200 wake-ups a second of the GUI thread
    that the application does not have)."""
    from PySide6.QtCore import QEventLoop, QTimer

    loop = QEventLoop()
    QTimer.singleShot(int(seconds * 1000), loop.quit)
    loop.exec()


def window_share(threads: list[tuple[str, float]], gui: float) -> tuple[float, float, float]:
    gl = sum(v for n, v in threads if n.startswith("llvmpipe"))
    return gui, gl, gui + gl


def one_run(seconds: float, moving: bool, screenshot: str, profile: str = "") -> dict[str, Any]:
    from app.ui.plots_frame import DEFAULT_SIGNALS

    config = config_at(1.0)
    manager = common.start_manager(config)
    window = None
    runner = None
    try:
        window = common.open_window(manager, load=False, refresh_hz=config.ui.refresh_hz)
        plots = window.frames.get("PlotsFrame")
        if plots is not None:
            plots.set_selected(list(DEFAULT_SIGNALS))
        if moving:
            from app.core import streams
            from app.scripting.runner import ScriptRunner

            runner = ScriptRunner(manager, lambda _s, _t: None, home_first=True)
            runner.start(SCRIPT.read_text(encoding="utf-8"), str(SCRIPT))

            def moving_now() -> bool:
                s = manager.bus.latest(streams.LINARM_VSA)
                return s is not None and abs(float(s.equilibriumPos) - 0.10) < 0.01
            if not common.run_qt_until(moving_now, 40.0):
                print("  (the reach exercise did not reach its start point within 40 s)")
        common.run_qt_until(lambda: False, 2.0)  # settle
        main_tid = threading.main_thread().native_id  # by id: Python threads are all named "python" too
        x_pid = x_server_pid()
        meter = common.CpuMeter([None, x_pid] if x_pid else [None])
        t0 = time.monotonic()
        before = common.thread_cpu_table()
        spy = common.start_py_spy(profile, seconds) if profile else None
        run_loop(seconds)
        after = common.thread_cpu_table()
        elapsed = time.monotonic() - t0
        threads = common.thread_cpu_percent(before, after, elapsed)
        gui_cpu = 100.0 * (after[main_tid][1] - before[main_tid][1]) / elapsed
        cpu = meter.percent()
        if spy is not None:
            spy.wait()
            print(f"  profile of the GUI thread: {common.summarise_py_spy(profile)}")
        if screenshot:
            window.grab().save(screenshot)
        gui, gl, share = window_share(threads, gui_cpu)
        return {"process": cpu[0], "x": cpu[1] if x_pid else None, "gui": gui, "gl": gl, "share": share,
                "threads": threads, "load": common._read("/proc/loadavg").split()[:3]}
    finally:
        if runner is not None:
            runner.stop("bench done", 5.0)
        common.shutdown(manager, window)


class GapMeter:
    """A 1 ms timer on the GUI thread: (when, gap since the previous tick) for every tick."""

    def __init__(self) -> None:
        from PySide6.QtCore import Qt, QTimer

        self.ticks: list[tuple[float, float]] = []
        self.cpu: list[float] = []  # the GUI thread's CPU time within each gap (its own work, not waiting)
        self._last = time.monotonic()
        self._last_cpu = time.thread_time()
        self.timer = QTimer()
        self.timer.setTimerType(Qt.TimerType.PreciseTimer)
        self.timer.setInterval(1)
        self.timer.timeout.connect(self._tick)
        self.timer.start()

    def _tick(self) -> None:
        now, cpu = time.monotonic(), time.thread_time()
        self.ticks.append((now, now - self._last))
        self.cpu.append(cpu - self._last_cpu)
        self._last, self._last_cpu = now, cpu

    def longest(self, t0: float, t1: float) -> float:
        """The longest gap ending in [t0, t1] (a stall that began in it ends at the first tick after it)."""
        end = next((t for t, _g in self.ticks if t > t1), t1)
        return max((g for t, g in self.ticks if t0 < t <= end), default=0.0)


def fes_start_stall(clicks: int, no_ack: bool) -> dict[str, Any]:
    from PySide6.QtCore import QTimer

    from app.ui.fes_panel import PROFILES_DIR, FesPanel

    manager = common.start_manager(config_at(1.0))
    window = None
    panel = None
    try:
        window = common.open_window(manager, load=False, refresh_hz=manager.config.ui.refresh_hz)
        panel = FesPanel(manager)
        panel.resize(900, 560)
        panel.show()
        fes = panel.driver
        if fes is None:
            raise RuntimeError("no FES device in the configuration")
        if not common.run_qt_until(lambda: fes.device_ready, 10.0):
            raise RuntimeError("the stimulator did not get ready within 10 s")
        if not panel.load_profile_file(PROFILES_DIR / "frontal_reaching.yaml"):
            raise RuntimeError(f"profile not loaded: {panel.message.text()}")
        common.run_qt_until(lambda: False, 1.0)  # settle
        meter = GapMeter()
        stalls, idle, started, outcomes = [], [], 0, []
        sim = manager.devices["fes"].simulator
        for _ in range(clicks):
            manager.supervisor.reset_emergency_stop("benchmark")
            common.run_qt_until(lambda: panel.start_button.isEnabled(), 3.0)
            t_idle = time.monotonic()
            common.run_qt_until(lambda: False, 0.3)  # what the GUI thread does without a click
            idle.append(meter.longest(t_idle, time.monotonic()))
            if no_ack:
                sim.with_core(lambda core: core.inject_no_ack(1))
            message_before = panel.message.text()
            clicked = {"t": 0.0}

            def click(clicked: dict[str, float] = clicked) -> None:
                clicked["t"] = time.monotonic()
                panel.start_button.click()  # as a mouse click does: on the GUI thread, from its event loop

            QTimer.singleShot(0, click)
            def decided_now(clicked: dict[str, float] = clicked, before: str = message_before) -> bool:
                text = panel.message.text()
                return clicked["t"] > 0 and (fes.stimulating or ("Not started" in text and text != before))

            decided = common.run_qt_until(decided_now, 5.0)
            t_end = time.monotonic()
            common.run_qt_until(lambda: False, 0.05)  # the tick that ends a stall still running at t_end
            stalls.append(meter.longest(clicked["t"], t_end))
            started += int(fes.stimulating)
            outcomes.append("started" if fes.stimulating else (panel.message.text() if decided else "undecided"))
            panel.stop_button.click()
            if no_ack:
                sim.with_core(lambda core: core.clear_faults())
            common.run_qt_until(lambda: False, 0.3)
        meter.timer.stop()
        return {"stalls": stalls, "idle": idle, "started": started, "outcomes": outcomes,
                "load": common._read("/proc/loadavg").split()[:3]}
    finally:
        if panel is not None:
            panel.close()
        common.shutdown(manager, window)


def normal_stalls(seconds: float, refresh_hz: float | None) -> dict[str, Any]:
    """The GUI thread's stalls in normal use during therapy (issue #37): the window open with every signal in
    the graphs, FES stimulating (frontal_reaching.yaml) and the reach exercise moving the arm. Two measures: the
    longest gap of a 1 ms timer (the stall itself) and the largest age the GUI watch saw between its heartbeats
    (what its thresholds are compared with: the stall plus up to one beat period)."""
    from app.core import streams
    from app.core.config import RESOURCES
    from app.core.fes_profile import load_profile
    from app.scripting.runner import ScriptRunner

    manager = common.start_manager(config_at(1.0))
    window = None
    runner = None
    try:
        hz = refresh_hz or manager.config.ui.refresh_hz
        window = common.open_window(manager, load=True, refresh_hz=hz)
        runner = ScriptRunner(manager, lambda _s, _t: None, home_first=True)
        runner.start(SCRIPT.read_text(encoding="utf-8"), str(SCRIPT))

        def moving_now() -> bool:
            s = manager.bus.latest(streams.LINARM_VSA)
            return s is not None and abs(float(s.equilibriumPos) - 0.10) < 0.01
        if not common.run_qt_until(moving_now, 60.0):
            print("  (the reach exercise did not reach its start point within 60 s)")
        fes = manager.driver("fes")
        # The running exercise holds the stimulator too (one owner, #36): the profile is loaded and started in the
        # run's name, as its script would. As the FES panel starts it: never waiting for the stimulator's acks on the
        # GUI thread (a start that held the GUI thread while the arm moved is a stall the GUI watch judges)
        try:
            from app.core.ownership import RUN_SOURCES
            source = RUN_SOURCES[0]
        except ImportError:  # the code before #36
            source = "benchmark"
        fes.load_profile(load_profile(RESOURCES / "fes_profiles" / "frontal_reaching.yaml"), source=source)
        fes.submit_start(source)
        if not common.run_qt_until(lambda: fes.stimulating, 10.0):
            print("  (stimulation did not start within 10 s)")
        t_start = time.monotonic()
        try:  # the collections made during the measurement only (not the window's build)
            from app.main_thread_gc import collections as main_thread_collections
        except ImportError:
            main_thread_collections = None  # type: ignore[assignment]
        made = main_thread_collections() if main_thread_collections is not None else None
        if made is not None:
            made.collections, made.longest_s = [0, 0, 0], 0.0
        heartbeat = getattr(window, "gui_heartbeat", None)  # None: the code before #37 (no GUI watch)
        ages: list[float] = []
        last = [time.monotonic()]
        if heartbeat is not None:
            watch = heartbeat.watch
            beat = watch.beat

            def timed_beat(now: float | None = None) -> None:
                t = time.monotonic()
                ages.append(t - last[0])
                if t - last[0] > 0.3:
                    print(f"  (heartbeat gap {1000 * (t - last[0]):.0f} ms at +{t - t_start:.2f} s)", flush=True)
                last[0] = t
                beat(now)

            watch.beat = timed_beat  # type: ignore[method-assign]
        common.run_qt_until(lambda: False, 1.0)  # settle
        meter = GapMeter()
        t0 = time.monotonic()
        del ages[:]
        drives = []
        end = t0 + seconds
        while time.monotonic() < end:
            common.run_qt_until(lambda: False, min(1.0, end - time.monotonic()))
            drives.append(bool(manager.fault_policy.drives_something()))
        meter.timer.stop()
        gaps = [g for t, g in meter.ticks if t > t0]
        gap_cpu = [c for (t, _g), c in zip(meter.ticks, meter.cpu, strict=True) if t > t0]
        alarms = [a.text for a in manager.supervisor.alarms() if a.source == "window"]
        return {"longest": max(gaps, default=0.0), "gaps": gaps, "ages": ages, "gap_cpu": gap_cpu,
                "driving": sum(drives) / max(1, len(drives)), "redraws_hz": hz, "alarms": alarms,
                "moving": runner.running, "load": common._read("/proc/loadavg").split()[:3]}
    finally:
        if runner is not None:
            runner.stop("bench done", 5.0)
        common.shutdown(manager, window)


def stalls_main(args: argparse.Namespace) -> int:
    import subprocess

    common.qt_app()
    common.print_machine("bench_window: the GUI thread's normal stalls during therapy (the GUI watch's margin)")
    loads = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)] if args.load else []
    try:
        r = normal_stalls(args.stalls, args.refresh_hz)
    finally:
        for proc in loads:
            proc.kill()
            proc.wait()
    gaps = sorted(g * 1000 for g in r["gaps"])
    ages = sorted(a * 1000 for a in r["ages"]) or [float("nan")]
    print(f"  {args.stalls:g} s, every signal in the graphs at {r['redraws_hz']:g} Hz, FES stimulating, the arm "
          f"moving (still moving at the end: {r['moving']}); something driving {r['driving'] * 100:.0f} % of the "
          f"time{', two yes' if args.load else ''}; load average {' '.join(r['load'])}")
    print(f"  GUI thread's longest stall (1 ms timer): {gaps[-1]:.1f} ms; p99 of gaps {common.percentile(gaps, 99):.1f}"
          f" ms; gaps > 100 ms: {sum(g > 100 for g in gaps)}; the most CPU the GUI thread used within one gap "
          f"{max(r['gap_cpu'], default=0.0) * 1000:.1f} ms (its own work: what a quiet machine would stall)")
    try:
        from app import gui_watch

        bounds = (f"thresholds: alarm {gui_watch.ALARM_AFTER_S * 1000:.0f} ms, safe state "
                  f"{gui_watch.SAFE_AFTER_S * 1000:.0f} ms")
    except ImportError:
        bounds = "no GUI watch in this code"
    print(f"  GUI watch's heartbeat age: largest {ages[-1]:.1f} ms, p99 {common.percentile(ages, 99):.1f} ms "
          f"(n={len(r['ages'])}); {bounds}; window alarms raised: {r['alarms'] or 'none'}")
    try:
        from app.main_thread_gc import collections
    except ImportError:
        collections = None  # type: ignore[assignment]
    made = collections() if collections is not None else None
    if made is not None:
        print(f"  collections on the main thread during it: {made.collections} (generations 0, 1, 2), the "
              f"longest {made.longest_s * 1000:.1f} ms of wall")
    return 0


def fes_main(args: argparse.Namespace) -> int:
    import subprocess

    common.qt_app()
    common.print_machine("bench_window: the GUI thread's longest stall while starting FES")
    print(f"  {args.fes_start} clicks on the FES panel's Start{', the init not acknowledged' if args.no_ack else ''}"
          f"{', two yes' if args.load else ''}; simulators {common.hosting()}", flush=True)
    loads = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)] if args.load else []
    try:
        r = fes_start_stall(args.fes_start, args.no_ack)
    finally:
        for proc in loads:
            proc.kill()
            proc.wait()
    ms = [s * 1000 for s in r["stalls"]]
    idle = [s * 1000 for s in r["idle"]]
    print(f"  started {r['started']} of {len(ms)}; outcomes other than started: "
          f"{sorted(set(o for o in r['outcomes'] if o != 'started')) or 'none'}")
    print(f"  GUI thread's longest stall while starting FES: max {max(ms):.1f} ms, median {statistics.median(ms):.1f}"
          f" ms (per click: {' '.join(f'{v:.1f}' for v in ms)})")
    print(f"  the same without a click (0.3 s windows): max {max(idle):.1f} ms, median {statistics.median(idle):.1f}"
          f" ms; load average {' '.join(r['load'])}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--moving", action="store_true", help="run the reach exercise while measuring")
    parser.add_argument("--screenshot", default="", help="save the window of the last run as PNG")
    parser.add_argument("--profile", action="store_true", help="py-spy the first run into bench/profiles/window*")
    parser.add_argument("--fes-start", type=int, default=0, metavar="N",
                        help="measure the GUI thread's longest stall over N clicks of the FES panel's Start instead")
    parser.add_argument("--no-ack", action="store_true", help="with --fes-start: the init's ack never comes")
    parser.add_argument("--load", action="store_true", help="with --fes-start / --stalls: two `yes > /dev/null` "
                                                             "meanwhile")
    parser.add_argument("--stalls", type=float, default=0.0, metavar="S",
                        help="measure the GUI thread's normal stalls for S seconds during therapy instead (#37)")
    parser.add_argument("--refresh-hz", type=float, default=None, help="with --stalls: the graphs' rate "
                                                                       "(default: the configuration's)")
    args = parser.parse_args()
    if args.fes_start:
        return fes_main(args)
    if args.stalls:
        return stalls_main(args)
    app = common.qt_app()
    common.print_machine("bench_window: the window's CPU at nominal rates")
    print(f"  platform {app.platformName()}; robot {'moving (reach exercise)' if args.moving else 'idle'}")
    runs = []
    for i in range(max(1, args.runs)):
        profile = ("window_moving" if args.moving else "window_idle") if args.profile and i == 0 else ""
        r = one_run(args.seconds, args.moving, args.screenshot if i == args.runs - 1 else "", profile)
        runs.append(r)
        print(f"  run {i + 1}: window share {r['share']:.1f} % (GUI thread {r['gui']:.1f} + GL rasteriser "
              f"{r['gl']:.1f}); app process {r['process']:.1f} %"
              + (f"; X server {r['x']:.1f} %" if r["x"] is not None else "")
              + f"; load average {' '.join(r['load'])}", flush=True)
        print("    threads (% of one core): " + ", ".join(f"{n} {v:.1f}" for n, v in r["threads"] if v >= 0.05))
        app.processEvents()
    share = statistics.median(r["share"] for r in runs)
    print(f"  window share, median of {len(runs)}: {share:.1f} % of one core "
          f"(GUI {statistics.median(r['gui'] for r in runs):.1f}, GL {statistics.median(r['gl'] for r in runs):.1f})"
          f" | target ≤ 5 %: {common.verdict(share, 5.0)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
