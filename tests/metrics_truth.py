"""The recorded sessions of known truth (tests/data/metrics, made by make_sessions.py) as session folders,
their variants (noise, tremor) and their truth: shared by tests/test_metrics_truth.py and the before/after
table of issue #28."""

from __future__ import annotations

import gzip
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parent / "data" / "metrics"
T_ZERO = 1000.0  # the rebuilt session's monotonic start (any value: the metrics work from the start)
NOISE_M = 0.0001  # "noisy": white noise of 0.1 mm SD on the handle position (10 counts of its encoder)
TREMOR_HZ, TREMOR_M = 8.0, 0.00015  # "tremor": 8 Hz, ±0.15 mm on the handle (a robot holding the arm stiffly)
LARGE_TREMOR_HZ, LARGE_TREMOR_M = 6.0, 0.0005  # "tremor_large": 6 Hz, ±0.5 mm (the speed it adds: ±19 mm/s)


def load_case(name: str) -> dict[str, Any]:
    with gzip.open(DATA / f"{name}.json.gz", "rt", encoding="utf-8") as fh:
        return json.load(fh)


def _undelta(d: list[int], scale: float) -> np.ndarray:
    return np.cumsum(np.asarray(d, dtype=np.int64)) / scale


def streams_of(case: dict[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    out = {}
    for name, entry in case["streams"].items():
        cols = {"t": _undelta(entry["t_us"], 1e6)}
        for ch, v in entry.items():
            if isinstance(v, dict):
                cols[ch] = _undelta(v["d"], v["scale"])
        out[name] = cols
    return out


def variant(case: dict[str, Any], kind: str, seed: int = 1) -> dict[str, dict[str, np.ndarray]]:
    """The case's streams with the handle's recorded position made noisy or tremulous (the commanded centre,
    the truth, untouched)."""
    streams = streams_of(case)
    vsa = streams["linarm.vsa"]
    t = vsa["t"]
    if kind == "noisy":
        vsa["handlePos"] = vsa["handlePos"] + np.random.default_rng(seed).normal(0.0, NOISE_M, len(t))
    elif kind in ("tremor", "tremor_large"):
        hz, amp = (TREMOR_HZ, TREMOR_M) if kind == "tremor" else (LARGE_TREMOR_HZ, LARGE_TREMOR_M)
        phase = np.random.default_rng(seed).uniform(0, 2 * math.pi)
        vsa["handlePos"] = vsa["handlePos"] + amp * np.sin(2 * math.pi * hz * t + phase)
    elif kind != "clean":
        raise ValueError(kind)
    return streams


def write_session(case: dict[str, Any], folder: Path, streams: dict[str, dict[str, np.ndarray]] | None = None) -> Path:
    """A session folder app.session.recording.load_session reads (manifest, events.jsonl, streams/*.csv)."""
    streams = streams_of(case) if streams is None else streams
    (folder / "streams").mkdir(parents=True, exist_ok=True)
    spec = {}
    for name, cols in streams.items():
        channels = [c for c in cols if c != "t"]
        rel = f"streams/{name}.csv"
        rows = np.column_stack([cols["t"] + T_ZERO, *[cols[c] for c in channels]])
        lines = ["t_mono_s," + ",".join(channels)] + [",".join(f"{v:.7f}" for v in row) for row in rows]
        (folder / rel).write_text("\n".join(lines) + "\n", encoding="utf-8")
        spec[name] = {"file": rel, "device": name.split(".")[0],
                      "nominal_rate_hz": case["streams"][name]["rate_hz"],
                      "channels": [{"name": c, "unit": "", "label": c} for c in channels]}
    manifest = {"status": "complete", "patient_id": "truth", "operator": "make_sessions",
                "start": {"t_mono_s": T_ZERO, "t_wall_epoch_s": 0.0},
                "end": {"t_mono_s": T_ZERO + case["duration_s"]}, "duration_s": case["duration_s"], "streams": spec}
    (folder / "manifest.json").write_text(json.dumps(manifest), encoding="utf-8")
    with open(folder / "events.jsonl", "w", encoding="utf-8") as fh:
        for e in case["events"]:
            fh.write(json.dumps({"t_mono": e["t_s"] + T_ZERO, "kind": e["kind"], "data": e["data"]}) + "\n")
    return folder


def truth_movements(case: dict[str, Any]) -> list[dict[str, float]]:
    """The commanded movements after the exercise's first prompt. Passive (the robot moves the arm): read off
    the noise-free commanded centre (equilibriumPos), split where it turns: its range and duration (where its
    speed exceeds 5 % of its peak: the metrics' own onset rule, on the command instead of the handle); the
    peak speed is the clean handle's within that label (the handle runs 1-2 % over the command through the
    spring between them). Sway (the patient moves the handle, the admittance centre follows behind): labelled
    at the clean recorded handle's turns (one per push of the simulated patient the other way: a test checks
    it); range, peak speed and duration are the clean handle's within each label."""
    from app.session.metrics import lowpass, regular_times, resample_uniform, turning_points

    s = streams_of(case)["linarm.vsa"]
    rate = case["streams"]["linarm.vsa"]["rate_hz"]
    prompts = [e["t_s"] for e in case["events"] if e["kind"] == "prompt"]
    first = prompts[0] if prompts else 0.0
    t_dev = regular_times(s["t"], rate)  # samples decoded together share a time stamp: spread them back
    sel = t_dev >= first - 0.01
    t, x = resample_uniform(t_dev[sel], s["equilibriumPos"][sel], rate)
    _, h = resample_uniform(t_dev[sel], s["handlePos"][sel], rate)
    n = min(len(x), len(h))
    t, x, h = t[:n], x[:n], h[:n]
    # the centre is updated in steps of the controller's trajectory: its speed low-passed is the command's
    v = np.abs(np.gradient(lowpass(x, rate), 1.0 / rate))
    vh = np.abs(np.gradient(lowpass(h, rate), 1.0 / rate))
    bounds = [0, *turning_points(x, 0.002), len(x)]
    sway = case["truth"]["kind"] == "sway"
    if sway:  # the patient moved the handle (the centre follows it, behind): labelled where the clean handle
        # turns, one turn after each push the other way (checked), from the first push to the end
        first_push = int(np.searchsorted(t, case["truth"]["patient_commands"][0][0]))
        turns = [i for i in turning_points(lowpass(h, rate), 0.002) if i > first_push]
        bounds = [first_push, *turns, len(t)][:case["truth"]["count"] + 1]  # after the last: the arm at rest
    out = []
    for p, q in itertools.pairwise(bounds):
        if sway:
            x_, v_ = h[p:q], vh[p:q]
            above = np.nonzero(v_ > 0.05 * v_.max())[0]
            a, b = p + int(above[0]), p + int(above[-1])
            out.append({"onset_s": float(t[a]), "end_s": float(t[b]), "duration_s": float(t[b] - t[a]),
                        "range_m": float(np.ptp(x_)), "peak_speed_m_s": float(v_.max())})
            continue
        vv = v[p:q]
        if not len(vv) or np.ptp(x[p:q]) < 0.01:
            continue
        above = np.nonzero(vv > 0.05 * vv.max())[0]
        a, b = p + int(above[0]), p + int(above[-1])
        out.append({"onset_s": float(t[a]), "end_s": float(t[b]), "duration_s": float(t[b] - t[a]),
                    "range_m": float(np.ptp(x[p:q])), "command_peak_speed_m_s": float(vv.max()),
                    # the handle's own (clean) peak within the labelled movement: it runs ~1-2 % over the
                    # command, the spring between the two
                    "peak_speed_m_s": float(vh[p:q].max())})
    return out
