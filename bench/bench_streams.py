"""Are the streams on time? (issue #27, acceptance 1): gaps between consecutive sample timestamps, per stream,
in every link mode and hosting, quiet and beside two CPU-bound ``yes`` processes.

    .venv/bin/python bench/bench_streams.py [--seconds 8] [--only socket,pty] [--no-loaded | --no-quiet]

One run = a fresh manager with every device simulated (no window), in a child process; after the devices
connect and one second of settling, every sample every driver publishes is collected for ``--seconds`` from
the drivers' listeners — the timestamp the recorder, LSL, the scripts and the graphs see. Printed per stream:
p50 / p99 / max gap between consecutive timestamps (ms), the largest group of samples sharing one timestamp,
and the verdict for streams of 50 Hz and more: p99 gap ≤ 2.5 periods and no timestamp shared; then the same
figures for the arrival times (when each sample's read returned: how the link and the host delivered them —
before #27 the two were the same).

Configurations (the simulator hosting decides which links exist):

* ``socket``   simulators in their own process, loopback TCP links (the default configuration);
* ``pty``      simulators in their own process, pty links;
* ``firmware`` as ``socket``, the LINarm being the firmware's software-in-the-loop executable (built with
  CMake in firmware/build; skipped with a note when it is not built);
* ``thread``   simulators in the app's process (pty links: in-process hosting always uses ptys).

Exit status 0 when every stream of ≥ 50 Hz meets both targets in every run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import itertools

import common

from app.core.bus import SampleItem

CONFIGS: dict[str, dict[str, str]] = {
    "socket": {"LINARMPP_SIM_HOST": "process", "LINARMPP_SIM_LINK": "socket"},
    "pty": {"LINARMPP_SIM_HOST": "process", "LINARMPP_SIM_LINK": "pty"},
    "firmware": {"LINARMPP_SIM_HOST": "process", "LINARMPP_SIM_LINK": "socket", "BENCH_LINARM": "firmware"},
    "thread": {"LINARMPP_SIM_HOST": "thread"},
}
PERIODS_ALLOWED = 2.5
FAST_HZ = 50.0


def child(seconds: float) -> int:
    from dataclasses import replace

    from app.core.config import AppConfig

    cfg = AppConfig()
    if os.environ.get("BENCH_LINARM") == "firmware":
        cfg = replace(cfg, simulation=replace(cfg.simulation, linarm="firmware"))
    common.qt_app()
    manager = common.start_manager(cfg)
    times: dict[str, list[float]] = {}
    arrivals: dict[str, list[float]] = {}
    rates: dict[str, float] = {}
    try:
        common.run_qt_for(1.0)
        for handle in manager.devices.values():
            for spec in handle.driver.streams:
                times.setdefault(spec.name, [])
                arrivals.setdefault(spec.name, [])
                rates[spec.name] = float(spec.nominal_rate_hz)
        # Every stream's samples on a queued bus subscription, drained once the run is over (its drops counted).
        watched = manager.bus.subscribe("bench streams", list(times), maxlen=10_000_000)
        common.run_qt_for(seconds)
        watched.close()
        for item in watched.drain():
            if isinstance(item, SampleItem):
                times[item.stream].append(item.t)
                arrivals[item.stream].append(item.arrival)  # before #27: the stamp was the arrival
        if watched.dropped:
            print(f"the bench's queue dropped {watched.dropped} samples", file=sys.stderr)
    finally:
        manager.shutdown()
    print("RESULT " + json.dumps({"times": times, "arrivals": arrivals, "rates": rates,
                                  "load": common._read("/proc/loadavg").split()[0]}))
    return 0


def summarise(times: list[float]) -> dict[str, float]:
    gaps = [1000.0 * (b - a) for a, b in itertools.pairwise(times)]
    group, run = (1 if times else 0), 1
    for a, b in itertools.pairwise(times):
        run = run + 1 if b == a else 1
        group = max(group, run)
    s = common.stats(gaps)
    return {"n": len(times), "p50": s.median, "p99": s.p99, "max": s.max, "group": group,
            "backwards": sum(g < 0 for g in gaps)}


def run_one(name: str, loaded: bool, seconds: float) -> tuple[bool, list[str]]:
    env = {**os.environ, **CONFIGS[name]}
    loads = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2 if loaded else 0)]
    try:
        proc = subprocess.run([sys.executable, __file__, "--child", "--seconds", str(seconds)], env=env,
                              capture_output=True, text=True, timeout=120 + seconds)
    finally:
        for p in loads:
            p.kill()
            p.wait()
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")), None)
    title = f"{name:8} {'2 x yes' if loaded else 'quiet':7}"
    if line is None:
        return False, [f"{title}: the run failed (exit {proc.returncode}): {proc.stderr.strip()[-400:]}"]
    result = json.loads(line[len("RESULT "):])
    out = [f"{title} (load average {result['load']} at the end)"]
    ok = True
    for stream, ts in sorted(result["times"].items()):
        rate = result["rates"][stream]
        s = summarise(ts)
        a = summarise(result.get("arrivals", {}).get(stream, ts))
        period_ms = 1000.0 / rate if rate else float("nan")
        verdict = ""
        if rate >= FAST_HZ:
            fine = s["p99"] <= PERIODS_ALLOWED * period_ms and s["group"] <= 1 and s["n"] > 1
            ok &= fine
            verdict = "met" if fine else "MISSED"
        out.append(f"   {stream:22} {rate:5.0f} Hz n={s['n']:5d}  gap p50 {s['p50']:7.2f}  p99 {s['p99']:7.2f}"
                   f"  max {s['max']:7.2f} ms  ({s['p99'] / period_ms:4.1f} periods)  largest shared-timestamp "
                   f"group {s['group']}{'  BACKWARDS ' + str(s['backwards']) if s['backwards'] else ''}  {verdict}"
                   f"   | arrivals: p99 {a['p99']:7.2f} max {a['max']:7.2f} ms, group {a['group']}")
    return ok, out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--only", default=",".join(CONFIGS), help="comma-separated configurations")
    p.add_argument("--no-loaded", action="store_true")
    p.add_argument("--no-quiet", action="store_true")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args.seconds)
    common.print_machine("bench_streams: gaps between sample timestamps")
    from app.devices.sim.host import find_firmware_sil

    all_ok = True
    for name in args.only.split(","):
        if name == "firmware" and find_firmware_sil() is None:
            print("firmware: skipped (the SIL executable is not built: cmake -S firmware/host -B firmware/build "
                  "&& cmake --build firmware/build)")
            continue
        for loaded in (False, True):
            if (loaded and args.no_loaded) or (not loaded and args.no_quiet):
                continue
            t0 = time.monotonic()
            ok, lines = run_one(name, loaded, args.seconds)
            all_ok &= ok
            print("\n".join(lines) + f"   [{time.monotonic() - t0:.0f} s]", flush=True)
    print("verdict: every stream ≥ 50 Hz with p99 gap ≤ 2.5 periods and no shared timestamp:",
          "met" if all_ok else "MISSED")
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(main())
