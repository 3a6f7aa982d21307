"""Synthetic session folders with the run record (app/core/runs.py events), as app.session.recording writes them: known
reaches of the handle, a grip that crosses the trigger threshold before each, runs interrupted, restarted,
refused. Used by the report tests and the screenshots."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.devices.linarm import VSA_STREAM
from app.devices.physio import PHYSIO_STREAM

FS = 200.0
T0 = 1000.0  # the monotonic clock at the session's start
LONG_ALARM = ("FES channel 2: the requested current 45 mA is above the patient's clinical cap of 40 mA, so the "
              "stimulation was refused before the first movement; check the electrode placement and the "
              "patient's caps in the profile before starting again (final words: electrode-check-needed)")


@dataclass
class RunSpec:
    title: str
    ident: str
    kind: str = "exercise"  # exercise | script_file | console
    source: str = "exercises_tab"
    reps: int = 3
    failed: tuple[int, ...] = ()  # repetitions (1-based) the exercise marked not completed
    reason: str = "finished"
    detail: str = ""
    restart_of: int | None = None  # index (0-based) of the run it restarts
    params: list[dict[str, Any]] = field(default_factory=list)
    reaction_s: float = 0.3  # grip crosses the threshold this long before the movement


TRIGGER_PARAMS = [{"name": "movements", "label": "Movements", "value": 3, "unit": ""},
                  {"name": "start_m", "label": "Start point", "value": 0.1, "unit": "m"},
                  {"name": "end_m", "label": "End point", "value": 0.3, "unit": "m"},
                  {"name": "speed_m_s", "label": "Speed", "value": 0.15, "unit": "m/s"},
                  {"name": "trigger_threshold_n", "label": "Trigger threshold", "value": 20.0, "unit": "N"}]


def write_run_session(folder: Path, runs: list[RunSpec], *, start_iso: str = "2026-03-01T10:00:00+01:00",
                      complete: bool = True, operator: str = "dr_rossi", profile: dict[str, Any] | None = None,
                      fes_charge: bool = False) -> Path:
    (folder / "streams").mkdir(parents=True)
    distance, duration, gap = 0.2, 1.0, 1.0
    total = 1.0 + sum(1.0 + max(r.reps, 0) * (duration + gap) for r in runs) + 1.0
    t = np.arange(0.0, total, 1 / FS)
    x = np.full_like(t, 0.1)
    grip = np.full_like(t, 2.0)
    events: list[dict[str, Any]] = [{"kind": "session_start", "t_mono": T0, "data": {}}]
    cursor = 1.0
    direction = 1
    for n, r in enumerate(runs):
        run_id = f"run-{n + 1}"
        program = {"kind": r.kind, "ident": r.ident, "title": r.title, "text_sha256": "0" * 64,
                   "version": "abc123" if r.kind == "exercise" else "", "path": f"/lib/{r.ident}.py"}
        params = r.params if r.params else (TRIGGER_PARAMS if r.kind == "exercise" else [])
        events.append({"kind": "run_start", "t_mono": T0 + cursor, "data": {
            "run_id": run_id, "program": program, "parameters": params, "source": r.source, "operator": operator,
            "restart_of": f"run-{r.restart_of + 1}" if r.restart_of is not None else None}})
        if r.kind == "exercise":
            events.append({"kind": "exercise_start", "t_mono": T0 + cursor, "data": {
                "exercise": r.ident, "title": r.title, "params": {p["name"]: p["value"] for p in params}}})
        events.append({"kind": "script_start", "t_mono": T0 + cursor, "data": {"name": f"{r.ident}.py"}})
        cursor += 0.5
        for k in range(r.reps):
            start = cursor + 0.5
            step = distance * np.clip((t - start) / duration, 0, 1) ** 3 * (
                10 - 15 * np.clip((t - start) / duration, 0, 1) + 6 * np.clip((t - start) / duration, 0, 1) ** 2)
            x += direction * step
            direction = -direction
            squeeze = (t >= start - r.reaction_s) & (t <= start + 0.6)
            grip[squeeze] = 30.0
            # As the exercises mark them: the repetition starts, then the "squeeze now" cue (its prompt).
            events += [{"kind": "repetition_start", "t_mono": T0 + start - r.reaction_s - 0.3,
                        "data": {"run_id": run_id, "index": k + 1, "total": r.reps}},
                       {"kind": "prompt", "t_mono": T0 + start - r.reaction_s - 0.2,
                        "data": {"run_id": run_id, "index": k + 1, "cue": "squeeze"}},
                       {"kind": "repetition_end", "t_mono": T0 + start + duration + 0.2,
                        "data": {"run_id": run_id, "index": k + 1, "ok": (k + 1) not in r.failed}}]
            cursor += duration + gap
        cursor += 0.5
        if r.reason == "emergency_stop":
            events.append({"kind": "emergency_stop", "t_mono": T0 + cursor - 0.1,
                           "data": {"reason": r.detail or "F12 pressed", "who": operator}})
        if r.reason == "refused":
            events.append({"kind": "alarm", "t_mono": T0 + cursor - 0.1,
                           "data": {"level": "WARNING", "source": "fes", "text": LONG_ALARM}})
        if not (not complete and n == len(runs) - 1):
            status = {"finished": "finished", "script_error": "error"}.get(r.reason, "stopped")
            events.append({"kind": "script_stop", "t_mono": T0 + cursor, "data": {"status": status}})
            events.append({"kind": "run_end", "t_mono": T0 + cursor, "data": {
                "run_id": run_id, "reason": r.reason, "detail": r.detail,
                "completed": r.reps - len(r.failed), "not_started": r.reps == 0}})
    vsa = np.column_stack([t + T0, x, np.zeros_like(t), np.full_like(t, 900.0), x, np.gradient(x, 1 / FS),
                           3.0 * np.abs(np.gradient(x, 1 / FS)) * 10])
    physio = np.column_stack([t + T0, 70 + 0 * t, 2 + 0 * t, 33 + 0 * t, grip])[::2]
    streams_meta = {}
    stream_data = [(VSA_STREAM, vsa), (PHYSIO_STREAM, physio)]
    if fes_charge:  # channel 1 at 40 mA, 300 µs, 40 Hz all along: 480 µC per second
        from app.devices.rehastim import FES_STREAM

        tf = np.arange(0.0, total, 1 / 40.0)
        cols = [tf + T0] + [np.full_like(tf, 40.0 if c.name == "current1" else 300.0 if c.name == "pulseWidth1"
                                          else 0.0) for c in FES_STREAM.channels]
        stream_data.append((FES_STREAM, np.column_stack(cols)))
        events.insert(1, {"kind": "fes_profile_loaded", "t_mono": T0 + 0.1, "data": {"frequency_hz": 40.0}})
    for spec, data in stream_data:
        name = spec.name
        lines = ["t_mono_s," + ",".join(c.name for c in spec.channels)]
        lines += [",".join(repr(float(v)) for v in row) for row in data]
        (folder / "streams" / f"{name}.csv").write_text("\n".join(lines) + "\n")
        streams_meta[name] = {"file": f"streams/{name}.csv", "device": name.split(".")[0],
                              "nominal_rate_hz": spec.nominal_rate_hz,
                              "channels": [{"name": c.name, "unit": c.unit, "label": c.label} for c in spec.channels]}
    (folder / "events.jsonl").write_text("".join(json.dumps({"t_wall": "", "who": "", "origin": "app", **e}) + "\n"
                                                 for e in events))
    manifest: dict[str, Any] = {
        "format_version": 1, "status": "complete" if complete else "recording", "patient_id": folder.parent.name,
        "operator": operator, "note": "", "patient": profile or {"affected_side": "left", "scores": {}},
        "start": {"t_wall": start_iso, "t_mono_s": T0, "t_wall_epoch_s": 0.0}, "streams": streams_meta}
    if complete:
        manifest["end"] = {"t_mono_s": T0 + total}
        manifest["duration_s"] = total
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def clinic_day_runs() -> list[RunSpec]:
    """An Exercises-tab run stopped by F12, its restart by Recover, a Script-tab file, a refused run."""
    return [
        RunSpec("Trigger reaching (grip-triggered passive movements)", "trigger_reaching", reps=2,
                reason="emergency_stop", detail="F12 pressed by the operator", failed=(2,)),
        RunSpec("Trigger reaching (grip-triggered passive movements)", "trigger_reaching", source="recover",
                reps=3, restart_of=0, reaction_s=0.6),
        RunSpec("trigger_exercise.py", "trigger_exercise", kind="script_file", source="script_tab", reps=2,
                reaction_s=0.15),
        RunSpec("Assisted reaching with FES", "assisted_reaching_fes", reps=0, reason="refused",
                detail="FES current 45 mA is above the patient's cap of 40 mA",
                params=[{"name": "movements", "label": "Movements", "value": 6, "unit": ""},
                        {"name": "fes_current_ma", "label": "FES current", "value": 45.0, "unit": "mA"}]),
    ]
