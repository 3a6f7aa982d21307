"""Trigger latency: the grip-force frame that crosses 20 N leaves the physiological simulator → the script's
``moveCentreTo`` reaches the LINarm simulator. Targets: p99 ≤ 2 ms (GUI idle), ≤ 5 ms (graphs redrawing).

    .venv/bin/python bench/bench_trigger.py [--trials N] [--refresh-hz HZ] [--profile]

The script is the seed's trigger exercise pattern (D2.2 Fig. 18): ``waitCondition("...force>20", locals(), 10)``
then ``linarm.moveCentreTo(...)``, looped; between triggers it waits for the grip to relax (< 15 N). It runs
twice per GUI condition in one process: once with the application's event-driven ``waitCondition`` and once
with the seed's own busy-wait ``waitCondition`` (its ``def`` copied verbatim from
resources/scripts/trigger_exercise.py). The simulated patient squeezes every 0.4 s.

GUI idle = the real MainWindow open (offscreen), no graph selected. GUI load = every signal of every device
in the graphs, redrawn by the graphs' timer at ``--refresh-hz`` (120 Hz, the configuration's maximum: the GUI
thread redraws back to back).

Both ends are stamped on the simulator threads with time.monotonic_ns(): the physio core's emitted frames
(decoded afterwards to find the crossing frame) and the LINarm core's received host bytes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

from app.config import RESOURCES, UdpEndpoint

TRIGGER_N = 20.0  # Fig. 18's threshold
RELAX_N = 15.0  # the script re-arms below this
SQUEEZE_PERIOD_S = 0.4
SQUEEZE_DUTY = 0.5
POSITIONS = (0.20, 0.22)  # small alternating moves: the robot never has to travel far between trials


def seed_wait_condition() -> str:
    """The seed's busy-wait ``waitCondition`` definition, as printed in Fig. 18."""
    lines = (RESOURCES / "scripts" / "trigger_exercise.py").read_text(encoding="utf-8").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("def waitCondition"))
    end = next(i for i in range(start + 1, len(lines)) if lines[i] and not lines[i].startswith((" ", "\t")))
    return "\n".join(lines[start:end]).rstrip() + "\n"


def script(trials: int, busy: bool) -> str:
    head = seed_wait_condition() if busy else ""
    return head + f"""
linarm.resetError()  # a host-silence watchdog trip in an earlier case (GIL starvation) must not end this one
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
positions = {POSITIONS!r}
for i in range({trials}):
    waitCondition("physiologicalSensors.physiologicalSensorsData.force<{RELAX_N}", locals(), 10)
    waitCondition("physiologicalSensors.physiologicalSensorsData.force>{TRIGGER_N}", locals(), 10)
    linarm.moveCentreTo(positions[i % 2], 0.15, 0.15, 0, False)
"""


def move_times(host: list[tuple[int, bytes]], since_ns: int) -> list[int]:
    """Times (ns) at which a complete moveCentreTo frame reached the LINarm simulator."""
    from app.devices import linarm_protocol as proto
    from app.devices.cmdmessenger import CmdMessengerDecoder

    move_id = proto.COMMANDS_BY_NAME["moveCentreTo"].id
    decoder = CmdMessengerDecoder()
    out = []
    for t_ns, data in host:
        for frame in decoder.feed(data):
            if frame.cmd_id == move_id and t_ns >= since_ns:
                out.append(t_ns)
    return out


def force_frames(device: list[tuple[int, bytes]], calibration: object) -> list[tuple[int, float]]:
    """(time written, grip force) of every frame the physio simulator emitted."""
    from app.devices.physio_codec import PhysioStreamDecoder

    decoder = PhysioStreamDecoder(calibration)  # type: ignore[arg-type]
    out = []
    for t_ns, data in device:
        for sample in decoder.feed(data, t_ns / 1e9):
            out.append((t_ns, float(sample.force)))
    return out


def latencies(moves: list[int], frames: list[tuple[int, float]]) -> tuple[list[float], int]:
    """For each move: the first frame above TRIGGER_N after the last frame below RELAX_N that precedes the move
    (what the script reacted to). Returns latencies in ms and the number of moves that matched nothing."""
    import bisect

    times = [t for t, _ in frames]
    out: list[float] = []
    unmatched = 0
    for t_move in moves:
        k = bisect.bisect_right(times, t_move) - 1
        while k >= 0 and frames[k][1] >= RELAX_N:
            k -= 1
        if k < 0:
            unmatched += 1
            continue
        j = k + 1
        while j < len(frames) and frames[j][1] <= TRIGGER_N:
            j += 1
        if j >= len(frames) or frames[j][0] > t_move:
            unmatched += 1
            continue
        out.append((t_move - frames[j][0]) / 1e6)
    return out, unmatched


def run_case(manager: object, linarm_tap: common.WireTap, physio_tap: common.WireTap, trials: int,
             busy: bool, label: str) -> list[float]:
    from app.scripting.runner import ScriptRunner

    output: list[str] = []
    runner = ScriptRunner(manager, lambda _s, text: output.append(text))
    since = time.monotonic_ns()
    n_host, n_dev = len(linarm_tap.host), len(physio_tap.device)
    runner.start(script(trials, busy), f"<trigger bench: {label}>")
    done = common.run_qt_until(lambda: not runner.running, timeout_s=60.0 + trials * 3 * SQUEEZE_PERIOD_S)
    if not done:
        runner.stop("benchmark timeout")
        common.run_qt_until(lambda: not runner.running, 5.0)
    result = runner.result
    if result is None or result.status != "finished":
        message = result.message if result is not None else "timeout"
        print(f"  {label}: the script ended early ({message}); the trials before that are kept")
    moves = move_times(linarm_tap.host[n_host:], since)
    driver = manager.driver("physio")  # type: ignore[attr-defined]
    frames = force_frames(physio_tap.device[max(0, n_dev - 200):], driver.calibration)
    values, unmatched = latencies(moves, frames)
    if unmatched:
        print(f"  ({label}: {unmatched} moves matched no crossing frame)")
    return values


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=40, help="triggers per case (README figures: 300)")
    parser.add_argument("--refresh-hz", type=float, default=120.0, help="graph redraw rate under GUI load")
    parser.add_argument("--profile", action="store_true", help="py-spy the GUI-load cases into "
                                                                "bench/profiles/trigger_gui_load.{raw,txt}")
    args = parser.parse_args()
    common.print_machine("trigger latency: grip frame written → moveCentreTo on the LINarm wire")
    app = common.qt_app()
    # The UDP helpers are not part of this path; they stay off so their processes do not add noise.
    config = common.bench_config(patient_model=UdpEndpoint(mode="off"), vr=UdpEndpoint(mode="off"))
    manager = common.start_manager(config)
    window = None
    profiler = None
    try:
        manager.sim_patient().squeeze_periodically(period=SQUEEZE_PERIOD_S, duty=SQUEEZE_DUTY)
        linarm_tap = common.tap(manager.devices["linarm"].simulator)
        physio_tap = common.tap(manager.devices["physio"].simulator)
        window = common.open_window(manager, load=False)
        # Home once (the runner homes a robot that is not), outside the measured cases.
        from app.scripting.runner import ScriptRunner

        homing = ScriptRunner(manager, lambda _s, _t: None)
        homing.start("pass", "<homing>")
        common.run_qt_until(lambda: not homing.running, 90.0)
        results: dict[str, list[float]] = {}
        for load in (False, True):
            drawn = common.set_gui_load(window, load, args.refresh_hz)
            gui = f"GUI load ({drawn} signals, {args.refresh_hz:g} Hz)" if load else "GUI idle"
            common.run_qt_until(lambda: False, 1.0)  # let the graphs settle into their rhythm
            if load and args.profile:
                profiler = common.start_py_spy("trigger_gui_load", 20.0)
            r0, t0 = common.redraw_count(window), time.monotonic()
            for busy in (False, True):
                kind = "seed busy-wait waitCondition" if busy else "event-driven waitCondition"
                results[f"{gui}: {kind}"] = run_case(manager, linarm_tap, physio_tap, args.trials, busy,
                                                     f"{gui}, {kind}")
            if profiler is not None:
                profiler.wait()
            rate = (common.redraw_count(window) - r0) / (time.monotonic() - t0)
            print(f"  {gui}: graphs redrawn {rate:.0f} times/s during the trials", flush=True)
        print()
        trips = sum("WATCHDOG" in a.text for a in manager.supervisor.alarms())
        if trips:
            print(f"  the LINarm's host-silence watchdog (250 ms without a byte from the driver) tripped {trips} times")
        for key, values in results.items():
            target = 5.0 if key.startswith("GUI load") else 2.0
            common.report(key, values, target)
        if profiler is not None:
            print(f"  profile: {common.summarise_py_spy('trigger_gui_load')}")
    finally:
        common.shutdown(manager, window)
        app.processEvents()
    return 0


if __name__ == "__main__":
    sys.exit(main())
