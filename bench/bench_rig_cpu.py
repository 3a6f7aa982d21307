"""The rig's CPU (#38): what a connected, idle manager with every device simulated costs, per thread, in the
application's process and in each helper process (the simulators' host, the patient model, the VR stand-in, the
FES guardian) — what every running test of the suite pays whatever it waits for.

    .venv/bin/python bench/bench_rig_cpu.py [--seconds 20] [--runs 3] [--warmup 3] [--unhomed]

The manager is built as the suite's tests build theirs (tests/rigs.py: the default configuration, a homed LINarm
unless ``--unhomed``), started, every device connected; then nothing is asked of it while the Qt event loop runs
(no timer of the benchmark's own). Each run takes every thread's user + system time from /proc over
``--seconds``: the application's threads are named by their Python names (QThreads by their object name), a
helper's by py-spy's dump when py-spy is there ($PY_SPY, bench/.venv, the PATH), else by the OS's name. Prints the share
of one core per thread (≥ 0.2 %), per process and in all, with the load average: the machine is shared, so
compare figures taken the same way at the same load.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

_CLK_TCK = os.sysconf("SC_CLK_TCK")


def _read(path: str) -> str:
    with open(path, encoding="utf-8", errors="replace") as f:
        return f.read()


def descendants(pid: int) -> list[int]:
    """Every live descendant of ``pid`` (children's children too)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = _read(f"/proc/{entry}/stat").rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        children.setdefault(int(fields[1]), []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def process_name(pid: int) -> str:
    try:
        argv = _read(f"/proc/{pid}/cmdline").split("\0")
    except OSError:
        return str(pid)
    for arg in argv[1:]:  # the module or script it runs
        if arg.startswith("app.") or arg.endswith(".py"):
            return f"{Path(arg).name if arg.endswith('.py') else arg} ({pid})"
    return f"{' '.join(argv[:3])[:60]} ({pid})"


def thread_times(pid: int) -> dict[int, tuple[str, float, float, int]]:
    """tid -> (OS name, user s, system s, voluntary context switches: its wake-ups) of every thread of ``pid``."""
    out: dict[int, tuple[str, float, float, int]] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            name = _read(f"/proc/{pid}/task/{tid}/comm").strip()
            fields = _read(f"/proc/{pid}/task/{tid}/stat").rsplit(")", 1)[1].split()
            status = _read(f"/proc/{pid}/task/{tid}/status")
        except (OSError, IndexError):
            continue
        switches = int(re.search(r"^voluntary_ctxt_switches:\s*(\d+)", status, re.M).group(1))  # type: ignore[union-attr]
        out[int(tid)] = (name, int(fields[11]) / _CLK_TCK, int(fields[12]) / _CLK_TCK, switches)
    return out


def py_spy() -> str | None:
    """py-spy from $PY_SPY, bench/.venv or the PATH (only to name the helpers' threads)."""
    named = os.environ.get("PY_SPY")
    if named:
        return named
    candidate = Path(__file__).resolve().parent / ".venv/bin/py-spy"
    return str(candidate) if candidate.exists() else shutil.which("py-spy")


def python_thread_names(pid: int, spy: str | None) -> dict[int, str]:
    """tid -> Python thread name of another process, from ``py-spy dump`` (empty without py-spy)."""
    if spy is None:
        return {}
    try:
        text = subprocess.run([spy, "dump", "--pid", str(pid)], capture_output=True, text=True, timeout=20).stdout
    except (OSError, subprocess.TimeoutExpired):
        return {}
    # py-spy dump names each thread as: Thread <OS thread id> (idle|active…): "<name>"
    out = {}
    for m in re.finditer(r'Thread (\d+) \((?:idle|active)[^)]*\): "([^"]*)"', text):
        out[int(m.group(1))] = m.group(2)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--warmup", type=float, default=3.0)
    parser.add_argument("--unhomed", action="store_true")
    args = parser.parse_args()
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    if not args.unhomed:
        from app.devices.sim.base import HOMED_ENV

        os.environ[HOMED_ENV] = "1"
    common.print_machine("the rig's CPU per thread (idle manager, every device simulated)")
    common.qt_app()
    manager = common.start_manager(common.bench_config())
    spy = py_spy()
    try:
        common.run_qt_for(args.warmup)
        me = os.getpid()
        pids = [me, *descendants(me)]
        names = {me: {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}}
        for pid in pids[1:]:
            names[pid] = python_thread_names(pid, spy)
        totals: list[float] = []
        for run in range(args.runs):
            load = _read("/proc/loadavg").split()[:3]
            before = {pid: thread_times(pid) for pid in pids}
            t0 = time.monotonic()
            common.run_qt_for(args.seconds)
            wall = time.monotonic() - t0
            after = {pid: thread_times(pid) for pid in pids}
            print(f"\nrun {run + 1}: {wall:.1f} s, loadavg {' '.join(load)}")
            total = 0.0
            for pid in pids:
                rows: dict[str, list[float]] = {}  # label -> [user %, system %, wake-ups/s]
                for tid, (os_name, user, system, switches) in after[pid].items():
                    _n, user0, system0, switches0 = before[pid].get(tid, (os_name, 0.0, 0.0, 0))
                    label = names.get(pid, {}).get(tid) or os_name
                    if label.startswith("Dummy-"):  # a QThread seen from Python: its OS name is its objectName
                        label = os_name
                    row = rows.setdefault(label, [0.0, 0.0, 0.0])
                    row[0] += 100.0 * (user - user0) / wall
                    row[1] += 100.0 * (system - system0) / wall
                    row[2] += (switches - switches0) / wall
                share = sum(r[0] + r[1] for r in rows.values())
                total += share
                print(f"  {process_name(pid) if pid != me else f'application ({pid})'}: {share:.1f} %")
                for label, (user, system, wakes) in sorted(rows.items(), key=lambda kv: -kv[1][0] - kv[1][1]):
                    if user + system >= 0.2:
                        print(f"      {user + system:5.1f} %  (user {user:4.1f}, system {system:4.1f}; "
                              f"{wakes:5.0f} wake-ups/s)  {label}")
            print(f"  all: {total:.1f} % of one core")
            totals.append(total)
        print(f"\nall processes, {args.runs} runs: " + ", ".join(f"{t:.1f}" for t in totals) + " % of one core")
    finally:
        common.shutdown(manager)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
