"""False "stopped sending data" at start-up (issue #27, acceptance 5): fresh starts of the window, counted.

    .venv/bin/python bench/bench_startup_silence.py [--runs 20] [--load]

One run = a fresh process: the manager with every device simulated (simulators in their own process, the
app's default), the real MainWindow shown (under Xvfb when available, so the 3D view builds with OpenGL as on a
desk), then ``--hold-s`` (3 s) after every device connected. Counted per run: "stopped sending data" warnings
and whether any of them is still on the banner (a resumed stream's warning leaves it, #27). ``--load``: two
``yes > /dev/null`` beside every run. Exit status 0 when no run saw a silence warning.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common


def child(hold_s: float) -> int:
    from app.core.config import AppConfig
    from app.manager import LinarmppManager
    from app.ui.main_window import MainWindow

    common.qt_app()
    t0 = time.monotonic()
    manager = LinarmppManager(AppConfig())
    manager.start()
    window = MainWindow(manager)
    window.show()
    try:
        connected = common.run_qt_until(manager.all_connected, 30.0)
        connected_s = time.monotonic() - t0
        common.run_qt_for(hold_s)
        silent = [a for a in manager.supervisor.alarms() if "stopped sending" in a.text]
        banner = window.alarm_banner.current
        report = {"connected": connected, "connected_s": round(connected_s, 2),
                  "silence": [a.text for a in silent],
                  "on_banner": bool(banner is not None and "stopped sending" in banner.text)}
    finally:
        window.close()
        manager.shutdown()
    print("RESULT " + json.dumps(report), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--hold-s", type=float, default=3.0)
    p.add_argument("--load", action="store_true", help="two `yes > /dev/null` beside every run")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args.hold_s)
    common.print_machine(f"bench_startup_silence: {args.runs} fresh starts of the window"
                         f"{' beside two yes' if args.load else ''}")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--hold-s", str(args.hold_s)]
    env = {**os.environ, "LINARMPP_SIM_HOST": "process"}
    if shutil.which("xvfb-run"):
        cmd = ["xvfb-run", "-a", "-s", "-screen 0 1920x1080x24", *cmd]
        env["QT_QPA_PLATFORM"] = "xcb"
    warnings = failed = 0
    yes = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2 if args.load else 0)]
    try:
        for i in range(args.runs):
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
                line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")), None)
            except subprocess.TimeoutExpired:
                line = None
            load = common._read("/proc/loadavg").split()[0]
            if line is None:
                failed += 1
                print(f"  run {i + 1:2d}: did not finish  load {load}", flush=True)
                continue
            r = json.loads(line[7:])
            warnings += len(r["silence"])
            print(f"  run {i + 1:2d}: connected {r['connected']} in {r['connected_s']} s  silence warnings "
                  f"{len(r['silence'])}{' ' + str(r['silence']) if r['silence'] else ''}"
                  f"{'  STILL ON THE BANNER' if r['on_banner'] else ''}  load {load}", flush=True)
    finally:
        for proc_yes in yes:
            proc_yes.kill()
            proc_yes.wait()
    print(f"verdict: {warnings} \"stopped sending data\" warnings in {args.runs - failed} starts"
          f" ({failed} did not finish): {'met' if warnings == 0 and failed == 0 else 'MISSED'}")
    return 0 if warnings == 0 and failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
