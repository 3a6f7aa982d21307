"""Data for the archive's tests: a ``<data>`` folder as today's version leaves it (patient profiles with a plan,
caps and electrode choices; sessions complete and interrupted), and a long session in the recorder's format."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.therapy.patients import (
    ClinicalChannelCap,
    ClinicalScores,
    ElectrodeChoice,
    PatientAssistance,
    PatientFes,
    PatientProfile,
    PatientRobotLimits,
    PlannedExercise,
    save_patient,
)
from tests.run_sessions import RunSpec, clinic_day_runs, write_run_session


def full_profile(patient_id: str = "PZ-017") -> PatientProfile:
    """Every field of a profile set (so a test that checks every field checks something)."""
    return PatientProfile(
        patient_id=patient_id, full_name="Maria Rossi", birth_date="1956-04-23", record_number="MRN-5512",
        affected_side="left",
        scores=ClinicalScores(fugl_meyer_ue=31, modified_ashworth=1.5, action_research_arm_test=20, box_and_block=12,
                              assessed_on="2025-03-01", other={"NIHSS": 4.0}),
        assistance=PatientAssistance(k_r=0.7, k_f=0.3),
        fes=PatientFes(profile="reach_biceps_triceps.yaml",
                       caps={1: ClinicalChannelCap(25.0, 250.0, 6.0), 5: ClinicalChannelCap(20.0, 200.0, None)},
                       electrodes={"anterior deltoid": ElectrodeChoice(channel=2, electrodes="3-4",
                                                                        chosen_at="2025-03-02T10:00:00+01:00",
                                                                        chosen_by="dr_rossi", proposed_channel=2,
                                                                        response_per_ma=0.8, motor_threshold_ma=11.0,
                                                                        discomfort=2, session="20250302-100000")}),
        robot=PatientRobotLimits(position_min_m=0.05, position_max_m=0.40, max_velocity_m_s=0.2),
        notes="Shoulder pain above 0.4 m.",
        therapy_plan=[PlannedExercise("trigger_reaching", {"movements": 6, "speed_m_s": 0.12}, "start gently")],
        created="2025-03-01T10:12:00+01:00", updated="2025-03-04T09:00:11+01:00")


def make_data_folder(data: Path) -> dict[str, Path]:
    """``<data>/patients`` (two profiles) and ``<data>/sessions`` (three sessions of PZ-017, one interrupted, and
    one of PZ-018); returns the session folders by name."""
    patients = data / "patients"
    patients.mkdir(parents=True)
    save_patient(full_profile("PZ-017"), patients)
    save_patient(replace(full_profile("PZ-018"), full_name="", fes=PatientFes(), therapy_plan=[]), patients)
    # save_patient stamps `updated` with now: the files as a station left them are the reference
    root = data / "sessions"
    out = {
        "monday": write_run_session(root / "PZ-017" / "20260302-100000", clinic_day_runs(),
                                    start_iso="2026-03-02T10:00:00+01:00"),
        "wednesday": write_run_session(root / "PZ-017" / "20260304-100000",
                                       [RunSpec("Trigger reaching (grip-triggered passive movements)",
                                                "trigger_reaching", reps=4)],
                                       start_iso="2026-03-04T10:00:00+01:00"),
        "interrupted": write_run_session(root / "PZ-017" / "20260305-100000",
                                         [RunSpec("Trigger reaching (grip-triggered passive movements)",
                                                  "trigger_reaching", reps=2)],
                                         start_iso="2026-03-05T10:00:00+01:00", complete=False),
        "other": write_run_session(root / "PZ-018" / "20260302-110000",
                                   [RunSpec("Trigger reaching (grip-triggered passive movements)",
                                            "trigger_reaching", reps=3)],
                                   start_iso="2026-03-02T11:00:00+01:00"),
    }
    return out


def long_session(folder: Path, minutes: float = 30.0, patient_id: str = "PZ-900", seed: int = 1) -> Path:
    """A session in the recorder's format (docs/sessions.md) as long as asked: the LINarm state at 200 Hz
    (11 channels), the physio board at 100 Hz, the patient model at 100 Hz, a run with a repetition every
    10 s and its events. Values written with repr like the recorder's writer."""
    from app.devices.linarm import VSA_STREAM
    from app.devices.physio import PHYSIO_STREAM

    rng = np.random.default_rng(seed)
    (folder / "streams").mkdir(parents=True)
    total = minutes * 60.0
    t0 = 5000.0
    streams = {}
    for spec, rate in ((VSA_STREAM, 200.0), (PHYSIO_STREAM, 100.0)):
        t = t0 + np.arange(0.0, total, 1 / rate)
        cols = [t] + [0.1 + 0.1 * np.sin(t / 5 + k) + rng.normal(0, 1e-3, len(t)) for k in range(len(spec.channels))]
        cols.append(t + 0.002)
        data = np.column_stack(cols)
        header = ",".join(["t_mono_s", *(c.name for c in spec.channels), "t_arrival_s"])
        path = folder / "streams" / f"{spec.name}.csv"
        with open(path, "w") as fh:
            fh.write(header + "\n")
            step = 20_000
            for a in range(0, len(data), step):
                fh.write("\n".join(",".join(map(repr, row)) for row in data[a:a + step].tolist()) + "\n")
        streams[spec.name] = {"device": spec.name.split(".")[0], "file": f"streams/{spec.name}.csv",
                              "nominal_rate_hz": rate,
                              "channels": [{"name": c.name, "unit": c.unit, "label": c.label} for c in spec.channels]}
    events = [{"t_wall": "", "t_mono": t0, "kind": "session_start", "who": "op", "origin": "app", "data": {}},
              {"t_wall": "", "t_mono": t0 + 1, "kind": "run_start", "who": "op", "origin": "app", "data": {
                  "run_id": "run-1", "program": {"kind": "exercise", "ident": "trigger_reaching",
                                                 "title": "Trigger reaching", "text_sha256": "0" * 64},
                  "parameters": [], "source": "exercises_tab", "operator": "op", "restart_of": None}}]
    for k in range(int(total // 10) - 1):
        a = t0 + 2 + 10 * k
        events += [{"t_wall": "", "t_mono": a, "kind": "repetition_start", "who": "", "origin": "app",
                    "data": {"run_id": "run-1", "index": k + 1}},
                   {"t_wall": "", "t_mono": a + 4, "kind": "repetition_end", "who": "", "origin": "app",
                    "data": {"run_id": "run-1", "index": k + 1, "ok": True}}]
    events.append({"t_wall": "", "t_mono": t0 + total - 1, "kind": "run_end", "who": "", "origin": "app",
                   "data": {"run_id": "run-1", "reason": "finished"}})
    (folder / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))
    manifest = {"format_version": 1, "session_uuid": None, "status": "complete", "patient_id": patient_id,
                "operator": "op", "note": "", "patient": None,
                "start": {"t_wall": "2026-03-02T10:00:00+01:00", "t_wall_epoch_s": 1772442000.0 + seed,
                          "t_mono_s": t0},
                "end": {"t_wall": "2026-03-02T10:30:00+01:00", "t_mono_s": t0 + total}, "duration_s": total,
                "streams": streams, "counts": {}}
    import uuid as _uuid

    manifest["session_uuid"] = str(_uuid.uuid4())
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder
