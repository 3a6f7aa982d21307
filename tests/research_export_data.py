"""Sessions for the research-export tests (issue #41).

* :func:`record_session` — a short session made by the real recorder (app.session.recording.SessionRecorder) on a
  virtual clock: every stream of the application with the time stamps its driver would give (the LINarm's and
  the physiological board's device clocks mapped by app.devices.clock.DeviceClock from delayed, batched
  arrivals, a crystal off by some ppm; the patient model and VR on a CountedClock; FES published on change),
  the exercise's marks, a grip onset at a known time and an emergency stop through the safety supervisor.
* :func:`synth_session` — a long session written straight in the recorder's on-disk format (for the memory and
  speed checks: recording two hours in real time is not an option).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from app.core import bus as bus_module
from app.core import streams
from app.core.bus import StreamSpec
from app.core.config import AppConfig
from app.devices.clock import CountedClock, DeviceClock
from app.devices.linarm import STATE_STREAM, VSA_STREAM, _motor_stream
from app.devices.patient_model import PATIENT_MODEL_STREAM
from app.devices.physio import PHYSIO_STREAM
from app.devices.rehastim import FES_STREAM
from app.devices.vr import VR_STREAM
from app.safety.supervisor import SafetySupervisor
from app.session import recording
from tests.fakes import ListenerDriver
from tests.recorder_host import recorder_host

DEVICE_SPECS: dict[str, tuple[StreamSpec, ...]] = {
    streams.LINARM: (STATE_STREAM, VSA_STREAM, _motor_stream(0), _motor_stream(1)),
    streams.PHYSIO: (PHYSIO_STREAM,),
    streams.FES: (FES_STREAM,),
    streams.PATIENT_MODEL: (PATIENT_MODEL_STREAM,),
    streams.VR: (VR_STREAM,),
}
GRIP_THRESHOLD_N = 20.0


class VirtualClock:
    """The recorder's ``time`` module on a clock the test moves (events get the times the test chooses)."""

    def __init__(self, t0: float = 5000.0, wall0: float = 1_772_355_600.0) -> None:  # 2026-03-01 09:00 UTC
        self.t = t0
        self.wall0 = wall0 - t0

    def monotonic(self) -> float:
        return self.t

    def time(self) -> float:
        return self.wall0 + self.t


@dataclass
class Recorded:
    folder: Path
    grip_onset_t: float  # the first grip sample at or above GRIP_THRESHOLD_N (its recorded time)
    estop_t: float  # the emergency stop's recorded time
    start_t: float
    truth: dict[str, Any] = field(default_factory=dict)


def _feeder(rate_hz: float, seconds: float, t0: float, ppm: float, rng: np.random.Generator,
            clock: DeviceClock | CountedClock) -> np.ndarray:
    """Recorded time stamps of a device sampling at ``rate_hz`` on a crystal ``ppm`` off: arrivals come in
    batches of a few samples, late by a varying delay; the driver's clock maps them as it does live."""
    n = int(seconds * rate_hz)
    device = np.arange(n) / rate_hz  # device seconds
    true_host = t0 + device / (1 + ppm * 1e-6)
    batch = rng.integers(1, 5, size=n)
    arrival = np.maximum.accumulate(true_host + 0.0005 + rng.exponential(0.002, size=n)
                                    + np.minimum((batch - 1) / rate_hz, 0.015))  # reads every ~5-15 ms
    out = np.empty(n)
    for k in range(n):
        if isinstance(clock, CountedClock):
            out[k] = clock.map(float(arrival[k]))
        else:
            out[k] = clock.map(float(device[k]), float(arrival[k]))
    return out


def record_session(root: Path, patient_id: str = "PZ-017", seconds: float = 6.0, seed: int = 7,
                   estop_at: float = 4.5, grip_at: float = 1.3, profile: Any = None, monkeypatch: Any = None,
                   operator: str = "dr_rossi") -> Recorded:
    """A session recorded by the real recorder; the virtual clock needs ``monkeypatch`` (pytest's)."""
    rng = np.random.default_rng(seed)
    clock = VirtualClock(t0=5000.0 + seed * 1000.0)
    assert monkeypatch is not None
    monkeypatch.setattr(recording, "time", clock)
    monkeypatch.setattr(bus_module, "time", clock)  # the journal's records are stamped where they are published
    drivers = {device: ListenerDriver(*specs) for device, specs in DEVICE_SPECS.items()}
    config = AppConfig()
    supervisor = SafetySupervisor(config.safety)
    host = recorder_host(config, drivers, supervisor=supervisor)
    recorder = recording.SessionRecorder(fsync=False)
    folder = recorder.start(host, patient_id, operator, note="export test", root=root, profile=profile)
    start = clock.t
    t0 = start + 0.05
    stamps = {
        streams.LINARM_VSA: _feeder(200.0, seconds, t0, 40.0, rng, DeviceClock(wrap_s=2**32 * 1e-6)),
        streams.LINARM_STATE: _feeder(20.0, seconds, t0, 40.0, rng, DeviceClock(wrap_s=2**32 * 1e-6)),
        streams.LINARM_MOTOR0: _feeder(200.0, seconds, t0 + 0.001, 40.0, rng, DeviceClock(wrap_s=2**32 * 1e-6)),
        streams.LINARM_MOTOR1: _feeder(200.0, seconds, t0 + 0.002, 40.0, rng, DeviceClock(wrap_s=2**32 * 1e-6)),
        streams.PHYSIO_MAIN: _feeder(100.0, seconds, t0 + 0.003, -25.0, rng, DeviceClock()),
        streams.PATIENT_MODEL_MAIN: _feeder(100.0, seconds, t0 + 0.004, 0.0, rng, CountedClock(100.0, wrap=0x10000)),
        streams.VR_MAIN: _feeder(50.0, seconds, t0 + 0.005, 0.0, rng, CountedClock(50.0, wrap=0x10000)),
    }
    # the stimulator's driver publishes on each update, at most 10 a second (and every 0.1 s when idle)
    fes_t = t0 + np.cumsum(0.1 + rng.uniform(0.0, 0.004, size=int(seconds * 9.5)))
    stamps[streams.FES_CHANNELS] = fes_t
    grip_t = stamps[streams.PHYSIO_MAIN]
    grip_k = int(np.searchsorted(grip_t, t0 + grip_at))
    estop_t = t0 + estop_at
    # what to publish, in time order
    queue: list[tuple[float, str, int]] = []
    for stream, ts in stamps.items():
        queue += [(float(t), stream, k) for k, t in enumerate(ts)]
    queue.sort()
    spec_of = {s.name: s for specs in DEVICE_SPECS.values() for s in specs}
    driver_of = {s.name: drivers[d] for d, specs in DEVICE_SPECS.items() for s in specs}
    plan = [(t0 + 0.2, "run_start"), (t0 + 0.5, "repetition_start"), (t0 + grip_at - 0.3, "prompt"),
            (t0 + 3.0, "repetition_end"), (t0 + 3.5, "parameter_change"), (estop_t, "estop"),
            (t0 + seconds - 0.2, "run_end")]
    p = 0
    for t, stream, k in queue:
        while p < len(plan) and plan[p][0] <= t:
            clock.t = plan[p][0]
            _act(plan[p][1], recorder, supervisor)
            p += 1
        clock.t = max(clock.t, t)
        values = _values(stream, spec_of[stream], k, t, t0, grip_k)
        for fn in driver_of[stream].listeners:
            fn(stream, t, SimpleNamespace(**values))
    for _, what in plan[p:]:
        _act(what, recorder, supervisor)
    clock.t += 0.1
    recorder.stop("test ended")
    manifest = json.loads((folder / recording.MANIFEST_FILE).read_text())
    events = [json.loads(ln) for ln in (folder / recording.EVENTS_FILE).read_text().splitlines()]
    estop = next(e for e in events if e["kind"] == "emergency_stop")
    assert manifest["status"] == "complete"
    return Recorded(folder, float(grip_t[grip_k]), float(estop["t_mono"]), float(manifest["start"]["t_mono_s"]))


def _act(what: str, recorder: recording.SessionRecorder, supervisor: SafetySupervisor) -> None:
    if what == "run_start":
        recorder.event("run_start", "dr_rossi", run_id="run-1", program={"kind": "exercise",
                       "ident": "trigger_reaching", "title": "Trigger reaching"}, parameters=[], source="test")
    elif what == "repetition_start":
        recorder.event("repetition_start", "exercise", run_id="run-1", index=1, total=1)
    elif what == "prompt":
        recorder.event("prompt", "exercise", run_id="run-1", index=1, cue="squeeze", threshold=GRIP_THRESHOLD_N)
    elif what == "repetition_end":
        recorder.event("repetition_end", "exercise", run_id="run-1", index=1, ok=True)
    elif what == "parameter_change":
        recorder.event("parameter_change", "dr_rossi", name="k_r", old=0.5, new=0.7)
    elif what == "estop":
        supervisor.emergency_stop("operator", "button")
    elif what == "run_end":
        recorder.event("run_end", "dr_rossi", run_id="run-1", reason="emergency_stop", completed=1)


def _values(stream: str, spec: StreamSpec, k: int, t: float, t0: float, grip_k: int) -> dict[str, float]:
    x = t - t0
    names = [c.name for c in spec.channels]
    if stream == streams.LINARM_VSA:
        pos = 0.2 + 0.1 * math.sin(2 * math.pi * 0.25 * x)
        return {"equilibriumPos": pos, "delta": 0.001 * math.cos(x), "stiffness": 900.0 + k % 7,
                "handlePos": pos + 1e-4 * math.sin(31 * x), "handleVel": 0.05 * math.pi * math.cos(math.pi * 0.5 * x),
                "interactionForce": float("nan") if k < 20 else 3.0 * math.sin(3 * x)}
    if stream in streams.LINARM_MOTORS:
        return {"position": 0.2 + 0.01 * math.sin(x + k), "velocity": 0.01 * math.cos(x),
                "current": 0.3 + 0.01 * (k % 5), "target": 0.2}
    if stream == streams.LINARM_STATE:
        return {n: float((k // 20 + i) % 3) for i, n in enumerate(names)}
    if stream == streams.PHYSIO_MAIN:
        return {"heartRate": 72.0 + math.sin(x), "skinConductance": 2.0 + 0.1 * x, "temperature": 33.2 + 0.01 * x,
                "force": 30.0 + 0.5 * math.sin(9 * x) if k >= grip_k else 2.0 + 0.01 * (k % 3)}
    if stream == streams.FES_CHANNELS:
        on = 2.0 <= x <= 4.0
        return {n: ((20.0 if n == "current1" else 250.0 if n == "pulseWidth1" else 0.0) if on else 0.0) for n in names}
    if stream == streams.PATIENT_MODEL_MAIN:
        return {n: min(1.0, 0.1 * i + 0.01 * x) for i, n in enumerate(names)}
    if stream == streams.VR_MAIN:
        return {"targetPos": 0.3, "score": float(k // 50), "targetsReached": float(k // 100)}
    raise AssertionError(stream)


# ---------------------------------------------------------------------------------------------- long sessions
def synth_session(root: Path, patient_id: str, seconds: float, *, start_iso: str = "2026-03-01T10:00:00+01:00",
                  start_epoch: float = 1_772_355_600.0, t0: float = 20_000.0, only: tuple[str, ...] | None = None,
                  folder_name: str = "20260301-100000", run_s: float = 600.0) -> Path:
    """A session of ``seconds`` in the recorder's on-disk format, every stream at its default rate (FES at 10 Hz),
    written quickly (each stream's value columns repeat a one-minute cycle; times advance): a reach out and back
    every 5 s, a grip squeeze and 2 s of FES on channels 1-2 in each, exercise runs of ``run_s``."""
    folder = root / patient_id / folder_name
    (folder / recording.STREAMS_DIR).mkdir(parents=True)
    rates = {streams.LINARM_STATE: 20.0, streams.LINARM_VSA: 200.0, streams.LINARM_MOTOR0: 200.0,
             streams.LINARM_MOTOR1: 200.0, streams.PHYSIO_MAIN: 100.0, streams.FES_CHANNELS: 10.0,
             streams.PATIENT_MODEL_MAIN: 100.0, streams.VR_MAIN: 50.0}
    rng = np.random.default_rng(3)
    meta: dict[str, Any] = {}
    counts: dict[str, int] = {}
    for device, specs in DEVICE_SPECS.items():
        for spec in specs:
            if only is not None and spec.name not in only:
                continue
            rate = rates[spec.name]
            n = int(seconds * rate)
            cycle = int(60 * rate)
            cols = 0.01 * rng.standard_normal((cycle, len(spec.channels)))  # sensor noise
            x = np.arange(cycle) / rate
            reach = 0.1 * (1 - np.cos(2 * np.pi * x / 5.0))  # a reach out and back every 5 s, as the marks say
            if spec.name in (streams.LINARM_VSA, *streams.LINARM_MOTORS):
                cols[:, 0] += 0.1 + reach
            if spec.name == streams.LINARM_VSA:
                cols[:, 3] = 0.1 + reach + 1e-4 * cols[:, 3]  # handle position
                cols[:, 4] = np.gradient(cols[:, 3], 1 / rate)
            if spec.name == streams.PHYSIO_MAIN:
                cols[:, 3] = np.where(x % 5.0 < 1.0, 30.0, 2.0) + cols[:, 3]  # grip squeezes
            if spec.name == streams.FES_CHANNELS:  # channels 1 and 2 stimulate for 2 s of every 5 s
                on = (x % 5.0 >= 1.0) & (x % 5.0 < 3.0)
                cols[:] = 0.0
                cols[:, 0] = cols[:, 1] = np.where(on, 20.0, 0.0)
                cols[:, 8] = cols[:, 9] = np.where(on, 250.0, 0.0)
            rests = [",".join(repr(float(v)) for v in row) for row in cols]
            t = t0 + 0.01 + np.arange(n) / rate * (1 + 30e-6)
            arrival = t + 0.002
            path = folder / recording.STREAMS_DIR / recording.stream_file_name(spec.name)
            with open(path, "w", encoding="utf-8", newline="\n") as fh:
                fh.write(",".join([recording.TIME_COLUMN, *(c.name for c in spec.channels),
                                   recording.ARRIVAL_COLUMN]) + "\n")
                tl, al = t.tolist(), arrival.tolist()
                for a in range(0, n, 100_000):
                    fh.write("".join(f"{tl[k]!r},{rests[k % cycle]},{al[k]!r}\n"
                                     for k in range(a, min(n, a + 100_000))))
            counts[spec.name] = n
            meta[spec.name] = {"device": device, "file": f"{recording.STREAMS_DIR}/{path.name}",
                               "nominal_rate_hz": spec.nominal_rate_hz if spec.name != streams.LINARM_VSA else 200.0,
                               "channels": [{"name": c.name, "unit": c.unit, "label": c.label}
                                            for c in spec.channels]}
    events = [{"t_wall": start_iso, "t_mono": t0, "kind": "session_start", "who": "dr_rossi", "origin": "app",
               "data": {}}]
    # an exercise run every ``run_s`` (ten minutes), repetitions every 5 s within it
    for n, run_start in enumerate(np.arange(5.0, max(seconds - 10.0, 5.0), run_s), start=1):
        run_id, run_end = f"run-{n}", min(run_start + run_s - 5.0, seconds - 5.0)
        events.append({"t_wall": "", "t_mono": t0 + run_start, "kind": "run_start", "who": "dr_rossi",
                       "origin": "app", "data": {"run_id": run_id, "program": {
                           "kind": "exercise", "ident": "trigger_reaching", "title": "Trigger reaching"},
                           "parameters": [], "source": "exercises_tab", "operator": "dr_rossi"}})
        for k, rep_start in enumerate(np.arange(run_start + 5.0, run_end - 5.0, 5.0), start=1):
            events += [{"t_wall": "", "t_mono": t0 + rep_start, "kind": "repetition_start", "who": "exercise",
                        "origin": "app", "data": {"index": k, "run_id": run_id}},
                       {"t_wall": "", "t_mono": t0 + rep_start + 0.2, "kind": "prompt", "who": "exercise",
                        "origin": "app", "data": {"index": k, "cue": "squeeze", "run_id": run_id}},
                       {"t_wall": "", "t_mono": t0 + rep_start + 3.0, "kind": "repetition_end", "who": "exercise",
                        "origin": "app", "data": {"index": k, "ok": True, "run_id": run_id}}]
        events.append({"t_wall": "", "t_mono": t0 + run_end, "kind": "run_end", "who": "dr_rossi", "origin": "app",
                       "data": {"run_id": run_id, "reason": "finished"}})
    events.append({"t_wall": "", "t_mono": t0 + seconds, "kind": "session_stop", "who": "", "origin": "app",
                   "data": {"reason": "stopped"}})
    (folder / recording.EVENTS_FILE).write_text("".join(json.dumps(e) + "\n" for e in events))
    manifest = {"format_version": 1, "status": "complete", "patient_id": patient_id, "patient": None,
                "operator": "dr_rossi", "note": "", "app_version": "0.1.0", "host": {"node": "station-1"},
                "start": {"t_wall": start_iso, "t_wall_epoch_s": start_epoch, "t_mono_s": t0},
                "end": {"t_mono_s": t0 + seconds}, "duration_s": seconds, "streams": meta, "counts": counts,
                "event_count": len(events)}
    (folder / recording.MANIFEST_FILE).write_text(json.dumps(manifest))
    return folder
