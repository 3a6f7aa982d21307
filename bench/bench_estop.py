"""E-stop latency: the operator's action → FES Stop and robot IDLE on the wire. Target p99 ≤ 20 ms.

    .venv/bin/python bench/bench_estop.py [--trials N] [--refresh-hz HZ]

Three sources, each with the GUI idle and with every signal in the graphs redrawn at ``--refresh-hz``:

* button: a mouse press + release posted to the real MainWindow's ``estop_button`` from another thread (as the
  window system delivers input: queued behind whatever the GUI thread is doing);
* shortcut: the configured e-stop key (F12) posted the same way; the application-wide key filter catches it;
* API: ``supervisor.emergency_stop("api")`` called from a non-GUI thread (a script, a remote caller).

t0 is stamped (time.monotonic_ns) just before the event is posted or the call is made, by an "operator" thread
after a random 50–150 ms while the window's thread runs its event loop with nothing of the benchmark's in it; the
wire is read once ``SETTLE_S`` later (reading it from the simulators' process is a call on the window's thread: a
press must not wait behind it). Before session 11 the window's thread was blocked in the benchmark's join of the
operator thread when the press was posted, and read the wire every 50 ms meanwhile (``--blocked-gui``): both
were in the figures. The ends are the
simulator threads receiving the bytes: the RehaStim core decodes a ScienceMode Stop, the LINarm core a
``setCtrlState(IDLE)``. Before every trial the e-stop is reset and stimulation restarted (profile
frontal_reaching.yaml), so Stop interrupts a running stimulation.

The simulators run as the application runs them, in a process of their own on its default link (loopback
sockets), and the wire stamps are taken in that process (``common.RemoteWire``); ``--host thread`` hosts them as
threads of the benchmark's process (the layout of the figures before #27). ``--load``: two ``yes`` meanwhile.

Beside the latencies (issue #37): during each GUI condition, how many graph frames a second were shown (drawn
and on screen, whichever thread drew them; the graphs' timer ticks apart) and the GUI thread's longest stall (the
longest gap of a 5 ms timer on it, as bench_trigger.py measures it). ``--split``: each latency cut where the
supervisor's ``emergency_stop`` is entered: "→ handler" (the event posted → the window's thread acting on it: what
the press waits for that thread) and "handler → both" (the stop itself, as the API's path).
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
if "--host" in sys.argv:  # before the app is imported: where the simulators run
    os.environ["LINARMPP_SIM_HOST"] = sys.argv[sys.argv.index("--host") + 1]

import common

SETTLE_S = 0.05  # after the press, before the wire is read (a stop takes a few ms; a later one is still seen)


class Watch:
    """Stamps, on a simulator thread, every host message that ``match`` accepts."""

    def __init__(self, decoder: Any, match: Callable[[Any], bool]) -> None:
        self.decoder = decoder
        self.match = match
        self.times: list[int] = []

    def __call__(self, t_ns: int, data: bytes) -> None:
        for item in self.decoder.feed(data):
            if self.match(item):
                self.times.append(t_ns)

    def after(self, t0: int) -> int | None:
        return next((t for t in reversed(self.times) if t >= t0), None) if self.times and self.times[-1] >= t0 \
            else None


def idle_watch() -> Watch:
    from app.wire import linarm_protocol as proto
    from app.wire.cmdmessenger import CmdMessengerDecoder

    set_state = proto.COMMANDS_BY_NAME["setCtrlState"].id
    idle = str(int(proto.ControlState.IDLE_CTRL_STATE)).encode()
    return Watch(CmdMessengerDecoder(), lambda f: f.cmd_id == set_state and f.fields[1:2] == (idle,))


def fes_stop_watch(protocol: str) -> Watch:
    from app.wire import sciencemode as sm

    if protocol == "sm1":
        return Watch(sm.Sm1CommandDecoder(), lambda m: isinstance(m, sm.Sm1Stop))
    return Watch(sm.Sm2Decoder(), lambda m: type(m).__name__.startswith("Sm2StopChannelList"))


def triggers(window: Any, manager: Any) -> dict[str, Callable[[], None]]:
    """Each source as a callable run on a non-GUI thread right after t0."""
    from PySide6.QtCore import QCoreApplication, QEvent, QPointF, Qt
    from PySide6.QtGui import QKeyEvent, QKeySequence, QMouseEvent

    button = window.estop_button
    combo = QKeySequence(manager.config.ui.emergency_stop_shortcut)[0]
    left, none = Qt.MouseButton.LeftButton, Qt.MouseButton.NoButton

    def click() -> None:
        centre = QPointF(button.width() / 2, button.height() / 2)
        glob = QPointF(button.mapToGlobal(centre.toPoint()))
        press = QMouseEvent(QEvent.Type.MouseButtonPress, centre, glob, left, left, Qt.KeyboardModifier.NoModifier)
        release = QMouseEvent(QEvent.Type.MouseButtonRelease, centre, glob, left, none,
                              Qt.KeyboardModifier.NoModifier)
        QCoreApplication.postEvent(button, press)
        QCoreApplication.postEvent(button, release)

    def key() -> None:
        target = QCoreApplication.instance().focusWidget() or window  # type: ignore[union-attr]
        QCoreApplication.postEvent(target, QKeyEvent(QEvent.Type.KeyPress, combo.key(), combo.keyboardModifiers()))
        QCoreApplication.postEvent(target, QKeyEvent(QEvent.Type.KeyRelease, combo.key(),
                                                     combo.keyboardModifiers()))

    def api() -> None:
        manager.supervisor.emergency_stop("api", "benchmark")

    return {"button": click, "shortcut (" + manager.config.ui.emergency_stop_shortcut + ")": key, "API": api}


class Gaps:
    """A 5 ms timer on the GUI thread: the longest gap between its ticks since ``start``."""

    def __init__(self) -> None:
        from PySide6.QtCore import QTimer

        self.longest = 0.0
        self.longest_cpu = 0.0  # the most CPU time the GUI thread used within one gap (its own work)
        self._last = time.monotonic()
        self._last_cpu = time.thread_time()
        self.timer = QTimer()
        self.timer.setInterval(5)
        self.timer.timeout.connect(self._tick)

    def start(self) -> None:
        self.longest, self.longest_cpu = 0.0, 0.0
        self._last, self._last_cpu = time.monotonic(), time.thread_time()
        self.timer.start()

    def _tick(self) -> None:
        now, cpu = time.monotonic(), time.thread_time()
        self.longest = max(self.longest, now - self._last)
        self.longest_cpu = max(self.longest_cpu, cpu - self._last_cpu)
        self._last, self._last_cpu = now, cpu

    def stop(self) -> float:
        self.timer.stop()
        return self.longest


def frames_shown(window: Any) -> int:
    """Graph frames shown so far: drawn on the GUI thread (frame_times) or shown from the renderer (#37)."""
    plots = window.frames.get("PlotsFrame")
    if plots is None:
        return 0
    return int(getattr(plots, "_shown_seq", 0)) + int(getattr(plots, "_bench_item_frames", 0))


def start_stimulation(manager: Any) -> str:
    """Reset the e-stop and (re)start stimulation; returns '' or why stimulation is not running."""
    from app.core.config import RESOURCES
    from app.core.fes_profile import load_profile

    manager.supervisor.reset_emergency_stop("benchmark")
    fes = manager.driver("fes")
    if fes is None:
        return "no FES device"
    try:
        if getattr(fes, "profile", None) is None:
            fes.load_profile(load_profile(RESOURCES / "fes_profiles" / "frontal_reaching.yaml"))
        fes.start_stimulation("benchmark")
    except Exception as exc:  # the FES driver is still being finished: measure Stop without stimulation
        return f"{type(exc).__name__}: {exc}"
    return ""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=20, help="trials per source and GUI condition "
                                                               "(README figures: 100)")
    parser.add_argument("--refresh-hz", type=float, default=120.0)
    parser.add_argument("--profile", action="store_true", help="py-spy the GUI-load phase into "
                                                                "bench/profiles/estop_gui_load.{raw,txt}")
    parser.add_argument("--host", choices=("process", "thread"), default="process",
                        help="simulators in their own process (the app's default) or threads of this one")
    parser.add_argument("--load", action="store_true", help="two `yes > /dev/null` processes meanwhile")
    parser.add_argument("--blocked-gui", action="store_true",
                        help="post each press while the window's thread waits in the benchmark's own join (the "
                             "trials before session 11: that wait, and reading the wire, were part of the figure)")
    parser.add_argument("--split", action="store_true", help="also cut each latency where the supervisor's "
                                                             "emergency_stop is entered")
    args = parser.parse_args()
    import subprocess

    loads = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)] if args.load else []
    try:
        return run(args)
    finally:
        for proc in loads:
            proc.kill()
            proc.wait()


def run(args: argparse.Namespace) -> int:
    common.print_machine("e-stop latency: button / shortcut / API → FES Stop and robot IDLE on the wire")
    print(f"   simulators: {common.hosting()} hosting, link {common.link_kind()}"
          f"{', two yes' if args.load else ''}", flush=True)
    app = common.qt_app()
    manager = common.start_manager(common.bench_config())
    window = None
    rng = random.Random(1)
    try:
        linarm_watch, fes_watch = idle_watch(), fes_stop_watch(manager.config.devices.fes.protocol)
        wires = [common.wire(manager.devices["linarm"].simulator, on_host=linarm_watch),
                 common.wire(manager.devices["fes"].simulator, on_host=fes_watch)]
        remote = any(isinstance(w, common.RemoteWire) for w in wires)
        window = common.open_window(manager, load=False)
        sources = triggers(window, manager)
        entered: list[int] = []  # --split: when the supervisor's emergency_stop was entered (any thread)
        if args.split:
            supervisor = manager.supervisor
            real_stop = supervisor.emergency_stop

            def stamped(*a: Any, real_stop: Callable[..., None] = real_stop, **k: Any) -> None:
                entered.append(time.monotonic_ns())
                real_stop(*a, **k)
            supervisor.emergency_stop = stamped
        results: dict[str, list[float]] = {}
        not_stimulating: dict[str, int] = {}
        plots = window.frames.get("PlotsFrame")
        if plots is not None and not hasattr(plots, "_shown_seq"):  # the code before #37: every frame on the GUI
            plots._bench_item_frames = 0

            def counted(redraw: Callable[[], None] = plots.redraw) -> None:
                before = (len(plots.frame_times), plots.frame_times[-1] if plots.frame_times else None)
                redraw()
                plots._bench_item_frames += before != (len(plots.frame_times), plots.frame_times[-1]
                                                       if plots.frame_times else None)
            plots.redraw = counted
        gaps = Gaps()
        rates: list[str] = []
        for load in (False, True):
            drawn = common.set_gui_load(window, load, args.refresh_hz)
            gui = f"GUI load ({drawn} signals, {args.refresh_hz:g} Hz)" if load else "GUI idle"
            common.run_qt_until(lambda: False, 1.0)
            spy = common.start_py_spy("estop_gui_load", 10.0) if load and args.profile else None
            f0, r0, t_phase = frames_shown(window), common.redraw_count(window), time.monotonic()
            gaps.start()
            for _ in range(args.trials):
                for name, fire in sources.items():
                    why = start_stimulation(manager)
                    if why:
                        not_stimulating[why] = not_stimulating.get(why, 0) + 1
                    t0 = [0]
                    delay = rng.uniform(0.05, 0.15)  # a random point in the GUI's rhythm
                    if args.blocked_gui:
                        common.run_qt_until(lambda: False, delay)

                    def go(fire: Callable[[], None] = fire, t0: list[int] = t0, delay: float = delay) -> None:
                        if not args.blocked_gui:
                            time.sleep(delay)
                        t0[0] = time.monotonic_ns()
                        fire()
                        if not args.blocked_gui:
                            time.sleep(SETTLE_S)

                    thread = threading.Thread(target=go, name="operator")
                    thread.start()
                    if not args.blocked_gui:  # the window's thread turns as it does in use, nothing of ours in it
                        common.run_qt_until(lambda thread=thread: not thread.is_alive(), 5.0)
                    thread.join()
                    def seen(t0: list[int] = t0) -> bool:
                        for w in wires:
                            w.refresh()
                        return linarm_watch.after(t0[0]) is not None and fes_watch.after(t0[0]) is not None

                    # the simulator process's log is fetched over its control pipe: not every 5 ms
                    ok = common.run_qt_until(seen, 3.0, poll_ms=50 if remote else 5)
                    t_idle, t_fes = linarm_watch.after(t0[0]), fes_watch.after(t0[0])
                    if not ok or t_idle is None or t_fes is None:
                        print(f"  {gui}, {name}: no stop seen on the wire within 3 s "
                              f"(robot IDLE {t_idle is not None}, FES Stop {t_fes is not None})")
                        continue
                    for what, t in (("FES Stop", t_fes), ("robot IDLE", t_idle), ("both", max(t_fes, t_idle))):
                        results.setdefault(f"{gui}: {name} → {what}", []).append((t - t0[0]) / 1e6)
                    t_in = next((t for t in entered if t >= t0[0]), None)
                    if t_in is not None:
                        results.setdefault(f"{gui}: {name} → handler", []).append((t_in - t0[0]) / 1e6)
                        results.setdefault(f"{gui}: {name} handler → both", []).append(
                            (max(t_fes, t_idle) - t_in) / 1e6)
                    entered.clear()
            longest = gaps.stop()
            elapsed = time.monotonic() - t_phase
            rates.append(f"  {gui}: graph frames shown {(frames_shown(window) - f0) / elapsed:.1f}/s (timer ticks "
                         f"{(common.redraw_count(window) - r0) / elapsed:.1f}/s); the GUI thread's longest stall "
                         f"{longest * 1000:.1f} ms (its own CPU time within one stall at most "
                         f"{gaps.longest_cpu * 1000:.1f} ms)")
            if spy is not None:
                spy.wait()
                print(f"  profile: {common.summarise_py_spy('estop_gui_load')}")
        print()
        for line in rates:
            print(line)
        for why, count in not_stimulating.items():
            print(f"  (stimulation not running in {count} trials: {why})")
        for key, values in results.items():
            common.report(key, values, 20.0)
    finally:
        common.shutdown(manager, window)
        app.processEvents()
    return 0


if __name__ == "__main__":
    sys.exit(main())
