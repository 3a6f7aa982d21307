"""Memory: RSS over a 60-minute simulated session, time-compressed. Target: flat within 5 %.

    .venv/bin/python bench/bench_memory.py [--minutes M] [--speed X]

The real application (manager + MainWindow offscreen, every signal in the graphs at the configured rate) runs a
recorded session (SessionRecorder, as Session → Start does) with every stream ``--speed`` times faster than
nominal (physio, UDP; the LINarm state stream at most 1000 Hz, the protocol's ceiling), until the physio
stream has delivered ``--minutes`` of nominal-rate data (README figures: 60 minutes at 10×, i.e. 6 minutes).
The RSS of the application's process is sampled every second. "Flat" compares the end with the RSS after the
warm-up (the first 10 % of the run, when the graphs' ring buffers have filled): growth ≤ 5 %.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

NOMINAL_PHYSIO_HZ = 100.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=6.0, help="simulated session length (README: 60)")
    parser.add_argument("--speed", type=float, default=10.0, help="stream rates as a multiple of nominal")
    args = parser.parse_args()
    common.print_machine(f"memory: RSS over {args.minutes:g} simulated minutes at {args.speed:g}× the nominal rates")
    _app = common.qt_app()  # kept: the QApplication must outlive the window
    cfg = common.bench_config()
    d = cfg.devices
    cfg = replace(cfg, devices=replace(
        d, physio=replace(d.physio, rate_hz=NOMINAL_PHYSIO_HZ * args.speed),
        linarm=replace(d.linarm, state_rate_hz=min(1000.0, d.linarm.state_rate_hz * args.speed)),
        patient_model=replace(d.patient_model, rate_hz=d.patient_model.rate_hz * args.speed),
        vr=replace(d.vr, rate_hz=d.vr.rate_hz * args.speed)))
    manager = common.start_manager(cfg)
    window = None
    try:
        window = common.open_window(manager, load=True, refresh_hz=cfg.ui.refresh_hz)
        manager.sim_patient().squeeze_periodically(period=2.0 / args.speed, duty=0.5)
        try:
            folder = manager.start_session("BENCH-MEM", "benchmark", root=Path(tempfile.mkdtemp(prefix="bench-mem-")))
            print(f"  recording the session in {folder}")
        except Exception as exc:
            print(f"  (no recording: {type(exc).__name__}: {exc})")
        physio = manager.driver("physio")
        got0 = physio.total_samples("physio.main")
        target_frames = args.minutes * 60.0 * NOMINAL_PHYSIO_HZ
        t0 = time.monotonic()
        samples: list[tuple[float, float, float]] = []  # wall s, simulated min, RSS MiB
        last_print = 0.0
        while True:
            common.run_qt_until(lambda: False, 1.0)
            done = physio.total_samples("physio.main") - got0
            now = time.monotonic() - t0
            sim_min = done / NOMINAL_PHYSIO_HZ / 60.0
            samples.append((now, sim_min, common.rss_bytes() / 2**20))
            if now - last_print >= 30.0:
                last_print = now
                print(f"  {now:6.0f} s wall, {sim_min:5.1f} simulated min, RSS {samples[-1][2]:.1f} MiB", flush=True)
            if done >= target_frames or now > args.minutes * 60.0 / args.speed * 3 + 60:
                break
        if manager.recorder is not None:
            manager.end_session("benchmark done")
    finally:
        common.shutdown(manager, window)
    warm = samples[max(0, len(samples) // 10)]
    end = samples[-1]
    peak = max(s[2] for s in samples)
    growth = 100.0 * (end[2] - warm[2]) / warm[2]
    # least-squares slope after the warm-up, in MiB per simulated hour
    tail = samples[len(samples) // 10:]
    mx = sum(s[1] for s in tail) / len(tail)
    my = sum(s[2] for s in tail) / len(tail)
    den = sum((s[1] - mx) ** 2 for s in tail) or 1.0
    slope = sum((s[1] - mx) * (s[2] - my) for s in tail) / den * 60.0
    print()
    print(f"  simulated {end[1]:.1f} min in {end[0]:.0f} s wall; RSS after warm-up {warm[2]:.1f} MiB "
          f"(at {warm[1]:.1f} simulated min), at the end {end[2]:.1f} MiB, peak {peak:.1f} MiB")
    print(f"  growth after warm-up {growth:+.1f} % (trend {slope:+.1f} MiB per simulated hour) "
          f"| target within 5 %: {common.verdict(abs(growth), 5.0)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
