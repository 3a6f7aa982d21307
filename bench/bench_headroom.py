"""Headroom: the highest stream rates the application sustains with zero frames lost, and its CPU at the
nominal rates (100 Hz physio, 200 Hz LINarm state, 100 Hz / 50 Hz UDP) with the window open.
Targets: ≥ 10× nominal lossless; ≤ 10 % of one core at nominal.

    .venv/bin/python bench/bench_headroom.py [--seconds S] [--steps 1,5,10,20] [--profile] [--only physio,linarm]
        [--runs 3] [--no-window]

Every step runs all the streams at once at ``step × nominal`` for ``--seconds`` (README figures: 60 s), in the
real application (manager + MainWindow offscreen, the graphs showing their default signals at the configured
30 Hz). Losses counted per stream:

* physio: the decoder's sequence-gap count and bad frames, and frames emitted by the simulator vs decoded;
* LINarm: gaps in the controller clock of the VSA state stream (one frame per stream period);
* patient model (UDP): gaps in the model's reply sequence and in the echoed frame sequence;
* VR (UDP): gaps in its frame sequence, when its samples carry one.

The LINarm rate is capped at 1000 Hz by the protocol (startDataStream's period ≥ 1 ms: the controller's loop
runs at 1 kHz), i.e. 5× nominal; higher steps run it at 1000 Hz and say so.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

from app.core import streams
from app.core.bus import SampleItem

NOMINAL = {"physio": 100.0, "linarm": 200.0, "patient_model": 100.0, "vr": 50.0}
LINARM_MAX_HZ = 1000.0  # startDataStream(period ≥ 0.001 s)


class SeqGaps:
    """Counts missing values in a 16-bit sequence seen by a listener."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.seen = 0
        self.missing = 0

    def add(self, seq: int) -> None:
        if self.last is not None:
            gap = (seq - self.last) & 0xFFFF
            if 1 < gap < 0x8000:
                self.missing += gap - 1
        self.last = seq
        self.seen += 1


class ClockGaps:
    """Missing periods in a controller clock (s) stamped on every frame."""

    def __init__(self, period_s: float) -> None:
        self.period = period_s
        self.last: float | None = None
        self.seen = 0
        self.missing = 0

    def add(self, t: float) -> None:
        if self.last is not None:
            steps = round((t - self.last) / self.period)
            if steps > 1:
                self.missing += steps - 1
        self.last = t
        self.seen += 1


DEVICES = ("physio", "linarm", "fes", "patient_model", "vr")


def config_at(step: float, only: tuple[str, ...] = DEVICES) -> Any:
    cfg = common.bench_config()
    d = cfg.devices
    d = replace(d, **{n: replace(getattr(d, n), mode="off") for n in DEVICES if n not in only})
    linarm_hz = min(LINARM_MAX_HZ, NOMINAL["linarm"] * step)
    return replace(cfg, devices=replace(
        d,
        physio=replace(d.physio, rate_hz=NOMINAL["physio"] * step),
        linarm=replace(d.linarm, state_rate_hz=linarm_hz),
        patient_model=replace(d.patient_model, rate_hz=NOMINAL["patient_model"] * step),
        vr=replace(d.vr, rate_hz=NOMINAL["vr"] * step),
    ))


def helper_pids(manager: Any) -> dict[str, int]:
    out = {}
    process = getattr(getattr(manager, "simulators", None), "process", None)
    if process is not None and process.pid is not None:
        out["serial simulators"] = process.pid
    for name, handle in manager.devices.items():
        for proc in handle.extras.get("processes", []):
            pid = getattr(proc, "pid", None)
            if isinstance(pid, int):
                out[name] = pid
    return out


def run_step(step: float, seconds: float, profile: str = "", headless: bool = False,
             only: tuple[str, ...] = DEVICES) -> dict[str, Any]:
    config = config_at(step, only)
    manager = common.start_manager(config)
    window = None
    try:
        if not headless:
            window = common.open_window(manager, load=False, refresh_hz=config.ui.refresh_hz)
        plots = window.frames.get("PlotsFrame") if window is not None else None
        if plots is not None:
            from app.ui.plots_frame import DEFAULT_SIGNALS

            plots.set_selected(list(DEFAULT_SIGNALS))
        period = 1.0 / config.devices.linarm.state_rate_hz
        linarm_gaps, model_seq, model_ack, vr_seq = ClockGaps(period), SeqGaps(), SeqGaps(), SeqGaps()

        def on_sample(item: SampleItem) -> None:
            s = item.sample
            if item.stream == streams.LINARM_VSA:
                linarm_gaps.add(s.controllerTime)
            elif item.stream == streams.PATIENT_MODEL_MAIN:
                model_seq.add(int(s.seq))
                model_ack.add(int(s.ackSeq))
            elif item.stream == streams.VR_MAIN:
                seq = getattr(s, "seq", None)
                if seq is not None:
                    vr_seq.add(int(seq))

        common.run_qt_for(2.0)  # settle: connections, first stream periods
        physio = manager.driver("physio")
        physio_sim = manager.devices["physio"].simulator if physio is not None else None
        lost0, bad0 = (physio.frames_lost, physio.bad_frames) if physio is not None else (0, 0)
        sent0 = physio_sim.control("frames_sent") if physio_sim is not None else 0
        got0 = physio.total_samples("physio.main") if physio is not None else 0
        # The sequence checks read a queued bus subscription, drained once the run is over (nothing of the bench
        # runs on the driver threads or the GUI thread meanwhile); one big enough for the run, its drops counted.
        watched = manager.bus.subscribe("bench sequences", (streams.LINARM_VSA, streams.PATIENT_MODEL_MAIN,
                                                            streams.VR_MAIN), maxlen=10_000_000)
        helpers = helper_pids(manager)
        udp = {n: manager.driver(n) for n in ("patient_model", "vr") if manager.driver(n) is not None}
        udp0 = {n: (d.datagrams_sent, d.datagrams_received) for n, d in udp.items()}
        sims = common.simulator_threads()
        sim0 = sum(common.thread_cpu_seconds(t) for t in sims)
        t_start = time.monotonic()
        meter = common.CpuMeter([None, *helpers.values()])
        threads0 = common.thread_cpu_table()
        spy = common.start_py_spy(profile, min(seconds, 20.0)) if profile else None
        common.run_qt_for(seconds)
        cpu = meter.percent()
        threads = common.thread_cpu_percent(threads0, common.thread_cpu_table(), time.monotonic() - t_start)
        sim_cpu = 100.0 * (sum(common.thread_cpu_seconds(t) for t in sims) - sim0) / (time.monotonic() - t_start)
        udp1 = {n: (d.datagrams_sent, d.datagrams_received) for n, d in udp.items()}
        elapsed = time.monotonic() - t_start
        sent1 = physio_sim.control("frames_sent") if physio_sim is not None else 0
        if physio is not None:  # frames in flight (emitted, not yet decoded) arrive; still missing after 1 s: lost
            common.run_qt_until(lambda: physio.total_samples("physio.main") - got0 >= sent1 - sent0, 1.0)
        got1 = physio.total_samples("physio.main") if physio is not None else 0
        if spy is not None:
            spy.wait()
            print(f"  profile: {common.summarise_py_spy(profile)}")
        watched.close()
        for item in watched.drain():
            if isinstance(item, SampleItem):
                on_sample(item)
        if watched.dropped:
            print(f"  the sequence check's queue dropped {watched.dropped} samples: its gaps are not the link's")
        rates = {name: h.driver.rates() for name, h in manager.devices.items()}
        return {
            "step": step, "config": config.devices,
            "physio": {"lost": (physio.frames_lost if physio is not None else 0) - lost0,
                       "bad": (physio.bad_frames if physio is not None else 0) - bad0,
                       "sent": sent1 - sent0, "decoded": got1 - got0},
            "linarm": {"seen": linarm_gaps.seen, "missing": linarm_gaps.missing},
            "patient_model": {"seen": model_seq.seen, "missing": model_seq.missing,
                              "missing_out": model_ack.missing},
            "vr": {"seen": vr_seq.seen, "missing": vr_seq.missing},
            "udp": {n: ((udp1[n][0] - udp0[n][0]) / elapsed, (udp1[n][1] - udp0[n][1]) / elapsed) for n in udp},
            "cpu_process": cpu[0], "cpu_sims": sim_cpu, "cpu_app": cpu[0] - sim_cpu,
            "cpu_helpers": dict(zip(helpers, cpu[1:], strict=True)), "rates": rates, "threads": threads,
            "seconds": seconds,
        }
    finally:
        common.shutdown(manager, window)


def describe(r: dict[str, Any]) -> tuple[str, bool]:
    d = r["config"]
    p, lin, pm, vr = r["physio"], r["linarm"], r["patient_model"], r["vr"]
    udp = r["udp"]

    def sustained(name: str, hz: float) -> bool:  # the UDP drivers skip a send when they fall behind
        return name in udp and udp[name][0] >= 0.95 * hz

    def off(name: str) -> bool:
        return getattr(d, name).mode == "off"

    physio_ok = off("physio") or (p["lost"] == 0 and p["bad"] == 0 and p["decoded"] >= p["sent"])
    linarm_ok = off("linarm") or (lin["missing"] == 0 and lin["seen"] >= 0.95 * d.linarm.state_rate_hz * r["seconds"])
    model_ok = off("patient_model") or (pm["missing"] == 0 and pm["missing_out"] == 0
                                        and sustained("patient_model", d.patient_model.rate_hz))
    vr_ok = off("vr") or (vr["missing"] == 0 and sustained("vr", d.vr.rate_hz))
    lines = [
        f"  step {r['step']:g}× for {r['seconds']:g} s: app CPU {r['cpu_app']:.1f} % of one core (process "
        f"{r['cpu_process']:.1f} % minus the in-process device simulators {r['cpu_sims']:.1f} %); helper processes "
        + ", ".join(f"{k} {v:.1f} %" for k, v in r["cpu_helpers"].items()),
        f"    physio {d.physio.rate_hz:g} Hz: emitted {p['sent']}, decoded {p['decoded']}, sequence gaps {p['lost']}, "
        f"bad frames {p['bad']} → {'lossless' if physio_ok else 'LOSSES'}",
        f"    LINarm state {d.linarm.state_rate_hz:g} Hz: VSA frames {lin['seen']}, missing {lin['missing']} "
        f"→ {'lossless' if linarm_ok else 'LOSSES'}",
        f"    patient model {d.patient_model.rate_hz:g} Hz: sent {udp.get('patient_model', (0, 0))[0]:.0f}/s, "
        f"replies {udp.get('patient_model', (0, 0))[1]:.0f}/s, missing replies {pm['missing']}, "
        f"unanswered frames {pm['missing_out']} → {'lossless' if model_ok else 'LOSSES or rate not sustained'}",
        f"    VR {d.vr.rate_hz:g} Hz: sent {udp.get('vr', (0, 0))[0]:.0f}/s, received {udp.get('vr', (0, 0))[1]:.0f}/s"
        f" → {'sustained' if vr_ok else 'rate not sustained'}",
        "    threads (% of one core): " + ", ".join(f"{n} {v:.1f}" for n, v in r["threads"] if v >= 0.05),
        "    measured rates (Hz): " + "; ".join(
            f"{dev} " + ", ".join(f"{s.split('.', 1)[-1]} {v:.0f}" for s, v in rates.items())
            for dev, rates in r["rates"].items()),
    ]
    return "\n".join(lines), physio_ok and linarm_ok and model_ok and vr_ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="per step (README figures: 60)")
    parser.add_argument("--steps", default="1,10,20", help="multiples of the nominal rates")
    parser.add_argument("--profile", action="store_true", help="py-spy the nominal step into "
                                                                "bench/profiles/headroom_nominal.{raw,txt}")
    parser.add_argument("--runs", type=int, default=3, help="nominal-rate CPU runs (window, headless): the median")
    parser.add_argument("--only", default=",".join(DEVICES), help="devices to run (the others off), e.g. physio")
    parser.add_argument("--no-window", action="store_true", help="skip the window-open CPU runs")
    args = parser.parse_args()
    only = tuple(n for n in args.only.split(",") if n)
    common.print_machine("headroom: stream rates without loss, and CPU at nominal rates, window open")
    app = common.qt_app()
    steps = [float(s) for s in args.steps.split(",")]
    summary = []
    for step in steps:
        r = run_step(step, args.seconds, "headroom_nominal" if args.profile and step == 1.0 else "", only=only)
        text, ok = describe(r)
        print(text, flush=True)
        summary.append((step, ok, r))
        app.processEvents()
    print()
    import statistics

    for label, headless, target in (("window open", False, 10.0), ("headless", True, 5.0)):
        if args.no_window and not headless:
            continue
        runs = [run_step(1.0, args.seconds, headless=headless, only=only) for _ in range(max(1, args.runs))]
        app_cpu = statistics.median(r["cpu_app"] for r in runs)
        sims = {k: statistics.median(r["cpu_helpers"].get(k, 0.0) for r in runs) for k in runs[0]["cpu_helpers"]}
        print(f"  CPU at nominal rates, {label}: app {app_cpu:.1f} % of one core (median of {len(runs)}: "
              + ", ".join(f"{r['cpu_app']:.1f}" for r in runs) + "), simulators and helpers excluded ("
              + ", ".join(f"{k} {v:.1f} %" for k, v in sims.items())
              + f") | target ≤ {target:g} %: {common.verdict(app_cpu, target)}", flush=True)
        mid = sorted(runs, key=lambda r: r["cpu_app"])[len(runs) // 2]
        print("    threads of the median run (% of one core): "
              + ", ".join(f"{n} {v:.1f}" for n, v in mid["threads"] if v >= 0.05), flush=True)
    lossless = [s for s, ok, _r in summary if ok]
    best = max(lossless) if lossless else 0.0
    print(f"  highest lossless step (all streams at once, LINarm capped at {LINARM_MAX_HZ:g} Hz): {best:g}× "
          f"| target ≥ 10×: {common.verdict(best, 10.0, higher_is_better=True)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
