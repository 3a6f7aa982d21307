"""A long session folder in the recorder's own on-disk format, built synthetically (issue #37): every stream of every
device at its rate (LINarm state, VSA and both motors at 200 Hz, physiological sensors 100 Hz, FES 40 Hz, patient
model 100 Hz, VR 50 Hz), each line written as the recorder writes it (``repr`` of every float, the arrival column
last), the events of exercise runs with their repetitions, and a complete manifest. Thirty minutes are some
two million lines (about 150 MB): made once per test process (:func:`long_session`) and by the bench.

The values look like a recording's: 17-digit times, a handle that reaches back and forth, noisy physiology, FES
currents that ramp; nothing the loader could parse faster than a real file."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from app.core.bus import StreamSpec
from app.devices.linarm import STATE_STREAM, VSA_STREAM, _motor_stream
from app.devices.patient_model import PATIENT_MODEL_STREAM
from app.devices.physio import PHYSIO_STREAM
from app.devices.rehastim import FES_STREAM
from app.devices.vr import VR_STREAM
from app.session import recording

T0 = 51234.56789012345  # the monotonic clock at the start (17 significant digits, as a real one)
RATES: tuple[tuple[StreamSpec, float], ...] = (
    (STATE_STREAM, 200.0), (VSA_STREAM, 200.0), (_motor_stream(0), 200.0), (_motor_stream(1), 200.0),
    (PHYSIO_STREAM, 100.0), (FES_STREAM, 40.0), (PATIENT_MODEL_STREAM, 100.0), (VR_STREAM, 50.0),
)
REACH_S, REST_S, DISTANCE_M = 2.0, 1.5, 0.25
BLOCK_S = 70.0  # the channels' values repeat with this period (ten reach-and-back cycles)


def _reach(t: np.ndarray) -> np.ndarray:
    """The handle's position: minimum-jerk reaches of DISTANCE_M there and back, a rest between."""
    period = REACH_S + REST_S
    phase = np.mod(t, 2 * period)
    out = np.empty_like(t)
    going = phase < period
    for mask, start, sign in ((going, 0.0, 1.0), (~going, period, -1.0)):
        s = np.clip((phase[mask] - start) / REACH_S, 0.0, 1.0)
        base = 0.10 if sign > 0 else 0.10 + DISTANCE_M
        out[mask] = base + sign * DISTANCE_M * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
    return out


def _columns(spec: StreamSpec, t: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    n = len(t)
    rel = t - T0
    noise = lambda scale: rng.standard_normal(n) * scale  # noqa: E731
    names = [c.name for c in spec.channels]
    if spec is STATE_STREAM:
        return [np.full(n, v) for v in (2.0, 0.0, 2.0, 0.0, 0.0, 1.0)]
    if spec is VSA_STREAM:
        x = _reach(rel) + noise(1e-5)
        v = np.gradient(x, rel)
        return [x + noise(1e-4), noise(1e-4), 900.0 + noise(5.0), x, v, 8.0 * v + noise(0.3)]
    if spec.name.startswith("linarm.motor"):
        x = _reach(rel)
        return [x + noise(1e-4), np.gradient(x, rel) + noise(1e-3), 0.4 + noise(0.05), x]
    if spec is PHYSIO_STREAM:
        grip = 2.0 + 25.0 * (np.mod(rel, 2 * (REACH_S + REST_S)) < 0.6) + noise(0.2)
        return [72.0 + noise(1.5), 2.0 + noise(0.05), 33.0 + noise(0.02), grip]
    if spec is FES_STREAM:
        ramp = np.clip(np.mod(rel, REACH_S + REST_S) / REACH_S, 0.0, 1.0)
        out = []
        for name in names:
            if name in ("current1", "current2"):
                out.append(np.round(20.0 * ramp, 1))
            elif name in ("pulseWidth1", "pulseWidth2"):
                out.append(np.where(ramp > 0, 250.0, 0.0))
            else:
                out.append(np.zeros(n))
        return out
    if spec is PATIENT_MODEL_STREAM:
        return [np.clip(0.5 + noise(0.05), 0, 1), np.clip(0.3 + noise(0.05), 0, 1), np.clip(0.2 + noise(0.05), 0, 1),
                rng.random(n), rng.random(n), rng.random(n)]
    return [np.where(np.mod(rel, 7.0) < 3.5, 0.10, 0.35), np.floor(rel / 7.0), np.floor(rel / 7.0)]


def _write_stream(path: Path, spec: StreamSpec, rate_hz: float, seconds: float, rng: np.random.Generator
                  ) -> tuple[list[str], np.ndarray]:
    """The stream file; returns its header and its values [columns, samples] (what parsing it gives). The
    channels' values repeat every BLOCK_S (their text is made once: 17-digit floats are slow to format); the
    times never do."""
    n = int(seconds * rate_hz)
    header = [recording.TIME_COLUMN, *(c.name for c in spec.channels), recording.ARRIVAL_COLUMN]
    nb = min(n, int(BLOCK_S * rate_hz))
    block = np.column_stack(_columns(spec, T0 + np.arange(nb) / rate_hz, rng)) if nb else np.zeros((0, 0))
    text = repr(block.tolist())
    block_lines = text[2:-2].split("], [") if nb else []
    block_lines = [ln.replace(", ", ",") for ln in block_lines]
    times, arrivals = [], []
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(header) + "\n")
        for a in range(0, n, nb or 1):
            i = np.arange(a, min(n, a + nb))
            t = T0 + i / rate_hz + rng.random(len(i)) * 1e-4  # a device's clock mapped to the host's
            arrival = t + 0.0012 + rng.random(len(i)) * 1e-3
            t_text = repr(t.tolist())[1:-1].split(", ")
            a_text = repr(arrival.tolist())[1:-1].split(", ")
            fh.write("\n".join(map(",".join, zip(t_text, block_lines, a_text, strict=False))) + "\n")
            times.append(t)
            arrivals.append(arrival)
    t_all = np.concatenate(times)
    values = np.tile(block.T, (1, -(-n // nb)))[:, :n] if nb else np.zeros((len(spec.channels), 0))
    return header, np.vstack([t_all, values, np.concatenate(arrivals)])


def _events(seconds: float) -> list[dict[str, Any]]:
    """Exercise runs filling the session: a trigger-reaching run, then FES-assisted reaching, with their
    repetitions marked as the exercises mark them."""
    events: list[dict[str, Any]] = [{"kind": "session_start", "t": 0.0, "who": "dr_rossi", "data": {}}]
    period = 2 * (REACH_S + REST_S)
    runs = (("trigger_reaching", "Trigger reaching (grip-triggered passive movements)", 0.0, seconds / 2),
            ("assisted_reaching_fes", "Assisted reaching with FES", seconds / 2 + 5.0, seconds - 5.0))
    for k, (ident, title, start, end) in enumerate(runs):
        run_id = f"run-{k + 1}"
        program = {"kind": "exercise", "ident": ident, "title": title, "text_sha256": "0" * 64, "version": "v1",
                   "path": f"/lib/{ident}.py"}
        params = [{"name": "movements", "label": "Movements", "value": int((end - start) // period), "unit": ""},
                  {"name": "start_m", "label": "Start point", "value": 0.1, "unit": "m"},
                  {"name": "end_m", "label": "End point", "value": 0.35, "unit": "m"}]
        events.append({"kind": "run_start", "t": start + 1.0, "who": "dr_rossi", "data": {
            "run_id": run_id, "program": program, "parameters": params, "source": "exercises_tab",
            "operator": "dr_rossi", "restart_of": None}})
        events.append({"kind": "exercise_start", "t": start + 1.0, "who": "dr_rossi", "data": {
            "exercise": ident, "title": title, "params": {p["name"]: p["value"] for p in params}}})
        events.append({"kind": "script_start", "t": start + 1.0, "who": "dr_rossi", "data": {"name": f"{ident}.py"}})
        index = 0
        rep = np.ceil((start + 1.5) / period) * period
        while rep + period < end:
            index += 1
            events += [{"kind": "repetition_start", "t": rep - 0.05, "who": "script",
                        "data": {"run_id": run_id, "index": index, "total": 0}},
                       {"kind": "prompt", "t": rep - 0.04, "who": "script",
                        "data": {"run_id": run_id, "index": index, "cue": "squeeze"}},
                       {"kind": "robot_command", "t": rep, "who": "script",
                        "data": {"source": "script", "command": "moveCentreTo", "args": {"x": 0.35}, "ok": True}},
                       {"kind": "repetition_end", "t": rep + REACH_S + 0.1, "who": "script",
                        "data": {"run_id": run_id, "index": index, "ok": True}}]
            rep += period
        events.append({"kind": "script_stop", "t": end, "who": "dr_rossi", "data": {"status": "finished"}})
        events.append({"kind": "run_end", "t": end, "who": "dr_rossi", "data": {
            "run_id": run_id, "reason": "finished", "detail": "", "completed": index, "not_started": False}})
    events.append({"kind": "session_stop", "t": seconds, "who": "", "data": {"reason": "ended by the operator"}})
    return events


def write_long_session(root: Path, seconds: float = 1800.0, patient: str = "P-LONG", seed: int = 37,
                       columns: bool = True) -> Path:
    """A session of ``seconds`` under ``root/<patient>/<stamp>``, as the recorder leaves a stopped one; with
    ``columns``, also its columnar side-file as the worker writes it at the session's end (from the values
    written, which is what parsing the files gives: no parse needed here)."""
    folder = root / recording.safe_name(patient) / "20260301-100000"
    (folder / recording.STREAMS_DIR).mkdir(parents=True)
    rng = np.random.default_rng(seed)
    specs, counts = {}, {}
    for spec, rate in RATES:
        rel = f"{recording.STREAMS_DIR}/{recording.stream_file_name(spec.name)}"
        header, values = _write_stream(folder / rel, spec, rate, seconds, rng)
        counts[spec.name] = values.shape[1]
        specs[spec.name] = recording._spec_dict(spec, spec.name.split(".")[0], rate)
        if columns:
            recording.save_columns(folder, rel, header, values)
        del values
    epoch = time.mktime((2026, 3, 1, 10, 0, 0, 0, 0, -1))
    lines = []
    for e in _events(seconds):
        t = e.pop("t")
        lines.append(json.dumps({"t_wall": recording.wall_iso(epoch + t), "t_mono": T0 + t, "origin": "app", **e}))
    (folder / recording.EVENTS_FILE).write_text("\n".join(lines) + "\n", encoding="utf-8")
    start = {"t_wall": recording.wall_iso(epoch), "t_wall_epoch_s": epoch, "t_mono_s": T0, "time_zone": "",
             "utc_offset": ""}
    manifest = {"format_version": recording.FORMAT_VERSION, "status": "complete", "patient_id": patient,
                "patient": None, "patient_error": "", "operator": "dr_rossi", "note": "synthetic long session",
                "app_version": recording.app_version(), "start": start,
                "end": {**start, "t_mono_s": T0 + seconds, "reason": "ended by the operator"},
                "duration_s": seconds, "devices": {}, "streams": specs, "counts": counts,
                "event_count": len(lines), "dropped_samples": {}, "dropped_device_events": 0}
    recording.write_json_atomic(folder / recording.MANIFEST_FILE, manifest)
    return folder


def shared_long_session(tmp_path_factory: Any, seconds: float = 1800.0) -> Path:
    """The 30-minute session, made once per test run and shared by its processes (xdist workers wait on a lock
    while the first makes it). Read-only for the tests that use it."""
    import fcntl
    import os
    import shutil

    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    target = root / f"long-session-{int(seconds)}"
    with open(root / f"long-session-{int(seconds)}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (target / "made").exists():
            shutil.rmtree(target, ignore_errors=True)
            write_long_session(target, seconds)
            (target / "made").touch()
    return target / "P-LONG" / "20260301-100000"
