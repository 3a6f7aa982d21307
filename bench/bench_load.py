"""The control path under load (issue #16, acceptance 1): reach exercises with and without two CPU-bound
processes beside the app, counting watchdog trips, false silence alarms and moves not done.

    .venv/bin/python bench/bench_load.py [--headless-runs 20] [--window-runs 5] [--no-control | --no-loaded]

One run = a fresh application (every device simulated, simulators in their own process) running
``bench/scripts/reach_exercise.py`` (homing first, then 6 cycles 0.10 <-> 0.40 m in target-position mode,
~30 s), in a child process:

* headless: manager + script runner, no window;
* window: the real MainWindow on an X server (Xvfb, so the 3D device view draws with OpenGL), the graphs
  showing their default signals, while the script runs.

Counted per run: WATCHDOG errors from the controller, silence alarms ("stopped sending data"), connection-loss
alarms, other STOP alarms, and whether all 12 moves arrived. "Loaded" runs have two ``yes > /dev/null``
processes running for the whole phase; the "control" phase runs the same without them. Exit status 0 only
when the loaded phase has 0 trips, 0 silence alarms and every move done.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

SCRIPT = common.BENCH / "scripts" / "reach_exercise.py"
MOVES = 12
RUN_TIMEOUT_S = 120.0
LOGS = Path(os.environ.get("BENCH_LOAD_LOGS", "/tmp/bench_load_logs"))


# ---------------------------------------------------------------------------------------------- one run (child)
def child(mode: str) -> int:
    from app.core.config import AppConfig
    from app.safety.supervisor import AlarmLevel
    from app.scripting.runner import ScriptRunner

    app = common.qt_app()
    out: list[str] = []
    t0 = time.monotonic()
    manager = common.start_manager(AppConfig())
    connected_s = time.monotonic() - t0
    window = None
    try:
        if mode == "window":
            window = common.open_window(manager, load=False, refresh_hz=AppConfig().ui.refresh_hz)
            plots = window.frames.get("PlotsFrame")
            if plots is not None and hasattr(plots, "set_selected"):
                from app.ui.plots_frame import DEFAULT_SIGNALS

                plots.set_selected(list(DEFAULT_SIGNALS))
        runner = ScriptRunner(manager, lambda _stream, text: out.append(text), home_first=True)
        runner.start(SCRIPT.read_text(encoding="utf-8"), str(SCRIPT))
        done = common.run_qt_until(lambda: runner.wait(0.0), RUN_TIMEOUT_S)
        if not done:
            runner.stop("bench timeout", 5.0)
        result = runner.result
        alarms = manager.supervisor.alarms()
        text = "".join(out)
        moves = next((int(line.split()[1]) for line in text.splitlines() if line.startswith("MOVES_DONE")), 0)
        report = {
            "mode": mode, "connected_s": round(connected_s, 3),
            "status": result.status if result else "none", "message": (result.message if result else "")[:200],
            "watchdog": sum("WATCHDOG" in a.text for a in alarms),
            "silence": sum("stopped sending data" in a.text for a in alarms),
            "connection_lost": sum("connection lost" in a.text for a in alarms),
            "other_stop": sum(a.level >= AlarmLevel.STOP and "WATCHDOG" not in a.text
                              and "connection lost" not in a.text for a in alarms),
            "moves": moves, "gl": bool(window is not None and app.platformName() == "xcb"),
        }
    finally:
        common.shutdown(manager, window)
    print("RESULT " + json.dumps(report), flush=True)
    return 0


# ---------------------------------------------------------------------------------------------- the phases (parent)
def run_one(mode: str) -> dict[str, Any]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", mode]
    env = {**os.environ}
    if mode == "window":
        if shutil.which("xvfb-run"):
            cmd = ["xvfb-run", "-a", "-s", "-screen 0 1920x1080x24", *cmd]
            env["QT_QPA_PLATFORM"] = "xcb"
        else:
            env["QT_QPA_PLATFORM"] = "offscreen"
    else:
        env["QT_QPA_PLATFORM"] = "offscreen"
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S + 60, env=env)
    except subprocess.TimeoutExpired:
        return {"mode": mode, "status": "hung", "watchdog": 0, "silence": 0, "connection_lost": 0,
                "other_stop": 0, "moves": 0}
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            result = json.loads(line[7:])
            if result.get("status") != "finished" or result.get("watchdog") or result.get("silence"):
                LOGS.mkdir(parents=True, exist_ok=True)  # the evidence of a failed run
                log = LOGS / f"{mode}-{time.strftime('%H%M%S')}-{os.getpid()}.log"
                log.write_text(proc.stdout + "\n" + proc.stderr, encoding="utf-8")
                result["log"] = str(log)
            return result
    return {"mode": mode, "status": f"crashed ({proc.returncode})", "message": proc.stderr[-300:], "watchdog": 0,
            "silence": 0, "connection_lost": 0, "other_stop": 0, "moves": 0}


def phase(name: str, loads: int, headless: int, window: int) -> dict[str, int]:
    yes = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(loads)]
    totals = {"runs": 0, "watchdog": 0, "silence": 0, "connection_lost": 0, "other_stop": 0, "moves_missing": 0,
              "not_finished": 0}
    try:
        for mode, n in (("headless", headless), ("window", window)):
            for i in range(n):
                r = run_one(mode)
                totals["runs"] += 1
                for key in ("watchdog", "silence", "connection_lost", "other_stop"):
                    totals[key] += int(r.get(key, 0))
                totals["moves_missing"] += MOVES - int(r.get("moves", 0))
                totals["not_finished"] += r.get("status") != "finished"
                print(f"  {name:8} {mode:8} run {i + 1:2d}/{n}: {r.get('status'):9}"
                      f" moves {r.get('moves', 0):2d}/{MOVES}"
                      f"  watchdog {r.get('watchdog', 0)}  silence {r.get('silence', 0)}"
                      f"  lost {r.get('connection_lost', 0)}  other STOP {r.get('other_stop', 0)}"
                      f"  gl {r.get('gl', '-')}  connected in {r.get('connected_s', '-')} s"
                      f"  load {common._read('/proc/loadavg').split()[0]}"
                      + (f"  ({r.get('message')})" if r.get("status") != "finished" else "")
                      + (f"  log {r['log']}" if r.get("log") else ""), flush=True)
    finally:
        for p in yes:
            p.kill()
            p.wait()
    return totals


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--headless-runs", type=int, default=20)
    p.add_argument("--window-runs", type=int, default=5)
    p.add_argument("--no-control", action="store_true", help="skip the unloaded control phase")
    p.add_argument("--no-loaded", action="store_true", help="skip the loaded phase (run the control alone)")
    p.add_argument("--control-runs", default="", help="headless,window runs of the control phase (default: same)")
    p.add_argument("--child", choices=("headless", "window"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args.child)
    common.print_machine("bench_load: reach exercises under two CPU-bound processes (shared machine)")
    results = {} if args.no_loaded else {"loaded": phase("loaded", 2, args.headless_runs, args.window_runs)}
    if not args.no_control:
        h, w = (int(x) for x in args.control_runs.split(",")) if args.control_runs else (args.headless_runs,
                                                                                       args.window_runs)
        results["control"] = phase("control", 0, h, w)
    print("\nCounts (runs, watchdog trips, silence alarms, connection-loss alarms, other STOP alarms, "
          "moves missing, runs not finished):")
    for name, t in results.items():
        print(f"  {name:8} runs {t['runs']:3d}  watchdog {t['watchdog']}  silence {t['silence']}"
              f"  lost {t['connection_lost']}  other STOP {t['other_stop']}  moves missing {t['moves_missing']}"
              f"  not finished {t['not_finished']}")
    verdicts = {name: not (t["watchdog"] or t["silence"] or t["moves_missing"] or t["not_finished"])
                for name, t in results.items()}
    for name, met in verdicts.items():
        print(f"\nverdict ({name}): {'met' if met else 'MISSED'}  (see the load average on every line)")
    ok = all(verdicts.values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
