"""A clinic day's session folder with everything a session can deliver, as the application records it (the event
shapes copied from a session recorded in the real window on the simulated devices): exercise runs (one stopped
by F12 and restarted by Recover, the seed's trigger script from the Script tab, one refused), then an electrode
set-up of the anterior deltoid (48 test bursts up to 30 mA, discomfort ratings, the proposal accepted) and of the
triceps (ended early by an emergency stop), stimulation started from the FES panel outside any exercise (a time
profile that ran to its end, one stopped by the emergency stop), and alarms: stops with their resets, warnings,
a repeat, information messages, acknowledgements. Engineering detail is in the record as the devices write it
(an exception's name, an enum name, a temporary path, hashes): the report must say it in words."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from app.core.resources import RESOURCES
from app.core.runs import text_hash
from app.devices.rehastim import FES_STREAM
from tests.run_sessions import T0, clinic_day_runs, write_run_session

SEED_SCRIPT = RESOURCES / "scripts" / "trigger_exercise.py"
REFUSAL = ("CommandRefused: fes.loadFile('/tmp/tmpq8x2k1ab/assisted_reaching_fes.yaml') was refused: stimulation "
           "refused: current 45 mA is above the patient's cap of 40 mA on channel 3")
ENVELOPE = "LINarm error: ENVELOPE_BREACH (handle at 0.512 m/s, above 1.2 x the locked maxVelocity 0.300 m/s)"
DELTOID = [(1, "1-2"), (2, "3-4"), (3, "1-3"), (4, "2-4")]
LADDER = list(range(8, 31, 2))  # 8 … 30 mA: 12 bursts per combination
DISCOMFORT = {1: 7, 2: 3, 3: 4}  # channel 4 not rated
# The number every view must show for this session (app/session/alarm_count.py): the warning, stop and fatal alarms
# raised:
# 3 emergency stops, the robot's envelope breach, and 3 warnings (the refused FES run, physio, the patient model).
EXPECTED_ALARMS = 7
# What the sessions browser and the reports counted before: every `alarm` event (the 4 INFO messages too), and
# alarm + emergency_stop events (each stop twice, and a press while latched).
OLD_BROWSER_COUNT = 11
OLD_REPORT_COUNT = 15


def _event(t: float, kind: str, who: str, origin: str, **data: Any) -> dict[str, Any]:
    return {"t_wall": "", "t_mono": T0 + t, "kind": kind, "who": who, "origin": origin, "data": data}


def write_delivered_session(folder: Path, operator: str = "Dr Rossi") -> Path:
    """The session folder (``folder`` = ``…/<patient>/<YYYYMMDD-HHMMSS>``); returns it."""
    profile = {"patient_id": folder.parent.name, "affected_side": "right", "full_name": "Maria Bianchi",
               "birth_date": "1956-04-02", "record_number": "MRN-20417", "scores": {}}
    runs = clinic_day_runs()
    runs[3].detail = REFUSAL
    write_run_session(folder, runs, operator=operator, profile=profile)
    events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
    manifest = json.loads((folder / "manifest.json").read_text())
    end = float(manifest["duration_s"])  # the runs' part; what follows is added after it
    # The Script-tab run ran the app's own seed script (its path and text as the runner records them).
    seed_text = SEED_SCRIPT.read_text(encoding="utf-8")
    for e in events:
        program = (e.get("data") or {}).get("program")
        if e["kind"] == "run_start" and program and program["kind"] == "script_file":
            program.update(ident=str(SEED_SCRIPT), path=str(SEED_SCRIPT), text_sha256=text_hash(seed_text),
                           title=SEED_SCRIPT.name)
    added: list[dict[str, Any]] = []
    # Run 1's F12: the supervisor's STOP alarm with it, Recover's acknowledgement and reset (an INFO message).
    estop = next(e for e in events if e["kind"] == "emergency_stop")
    t_stop = float(estop["t_mono"]) - T0
    estop["data"] = {"source": "keyboard", "reason": "emergency stop pressed"}
    added += [_event(t_stop, "alarm", "keyboard", "safety", level="STOP", source="keyboard",
                     text="Emergency stop: emergency stop pressed", ident=1),
              _event(t_stop + 0.02, "emergency_stop", "keyboard", "safety", source="keyboard",
                     reason="emergency stop pressed"),  # pressed again while latched: no new alarm
              _event(t_stop + 0.9, "alarm_acknowledged", operator, "safety", ident=1, operator=operator),
              _event(t_stop + 0.9, "emergency_stop_reset", operator, "safety", operator=operator),
              _event(t_stop + 0.9, "alarm", operator, "safety", level="INFO", source=operator,
                     text="Emergency stop reset", ident=2)]
    # During the Script-tab run: a physiological-sensor warning, repeated while open, and acknowledged.
    script_run = next(e for e in events if e["kind"] == "run_start" and e["data"]["program"]["kind"] == "script_file")
    t_script = float(script_run["t_mono"]) - T0
    added += [_event(t_script + 1.0, "alarm", "physio", "safety", level="WARNING", source="physio",
                     text="skin conductance sensor: no contact for 5 s", ident=3),
              _event(t_script + 2.0, "alarm_repeated", "physio", "safety", ident=3, level="WARNING", source="physio",
                     text="skin conductance sensor: no contact for 5 s", repeats=4),
              _event(t_script + 2.5, "alarm_acknowledged", operator, "safety", ident=3, operator=operator)]
    t = end + 2.0
    # The electrode set-up of the anterior deltoid: 4 combinations, 8 … 30 mA at 250 µs.
    fes_on: list[tuple[float, float, int, float, float]] = []  # (start, end, channel, current mA, pulse width µs)
    added.append(_event(t, "electrode_setup_started", operator, "app", district="anterior deltoid", ceiling_ma=30.0,
                        start_ma=8.0, step_ma=2.0, pulse_width_us=250.0, frequency_hz=40.0,
                        combinations=[{"channel": ch, "electrodes": el, "ceiling_ma": 30,
                                       "ceiling_set_by": "the therapist's ceiling"} for ch, el in DELTOID]))
    for ch, el in DELTOID:
        for current in LADDER:
            t += 0.2
            added += [_event(t, "fes_profile_loaded", "safety", "safety", name=f"electrode test: channel {ch}, "
                             f"{current} mA", channels=[ch], frequency_hz=40.0),
                      _event(t + 0.01, "fes_started", "electrode set-up", "safety", profile=f"electrode test: "
                             f"channel {ch}, {current} mA", source="electrode set-up", current_scale=1.0,
                             pulse_width_scale=1.0)]
            fes_on.append((t + 0.01, t + 1.5, ch, float(current), 250.0))
            gain = {1: 0.0, 2: 0.25, 3: 0.05, 4: 0.09}[ch]
            response = round(max(0.0, gain * (current - 10)), 3)
            added += [_event(t + 1.5, "fes_stopped", "fes profile", "safety", reason="the time profile finished",
                             source="fes profile"),
                      _event(t + 1.5, "electrode_burst", operator, "app", district="anterior deltoid", channel=ch,
                             electrodes=el, current_ma=current, pulse_width_us=250, baseline_n=-0.01,
                             response_n=response, motion_mm=round(response * 2, 2), samples=20)]
            t += 1.7
    added.append(_event(t, "electrode_setup_result", operator, "app", district="anterior deltoid",
                        proposed_channel=2, reason="channel 2: the largest response per mA (0.168 N/mA), 87 % above "
                        "the next (channel 4)", ranking=[{"channel": 2, "response_per_ma": 0.1667},
                                                         {"channel": 4, "response_per_ma": 0.06}],
                        motor_thresholds_ma={"1": None, "2": 14, "3": 22, "4": 16}))
    for ch, rating in DISCOMFORT.items():
        t += 0.5
        added.append(_event(t, "electrode_discomfort", operator, "app", district="anterior deltoid", channel=ch,
                            discomfort=rating))
    t += 1.0
    added += [_event(t, "fes_district_channels", "safety", "safety", channels={"anterior deltoid": 2}),
              _event(t, "electrode_choice", operator, "app", district="anterior deltoid", channel=2,
                     electrodes="3-4", proposed_channel=2, accepted_proposal=True, response_per_ma=0.1667,
                     motor_threshold_ma=14.0, discomfort=3, chosen_by=operator,
                     chosen_at="2026-03-01T10:04:10+01:00", saved=True)]
    # The triceps: ended by an emergency stop during its third burst.
    t += 2.0
    added.append(_event(t, "electrode_setup_started", operator, "app", district="triceps", ceiling_ma=20.0,
                        start_ma=8.0, step_ma=4.0, pulse_width_us=250.0, frequency_hz=40.0,
                        combinations=[{"channel": 5, "electrodes": "1-2", "ceiling_ma": 20,
                                       "ceiling_set_by": "the therapist's ceiling"},
                                      {"channel": 6, "electrodes": "3-4", "ceiling_ma": 18,
                                       "ceiling_set_by": "the channel's cap"}]))
    for current in (8, 12):
        t += 0.2
        added += [_event(t, "fes_started", "electrode set-up", "safety", profile=f"electrode test: channel 5, "
                         f"{current} mA", source="electrode set-up", current_scale=1.0, pulse_width_scale=1.0),
                  _event(t + 1.5, "fes_stopped", "fes profile", "safety", reason="the time profile finished",
                         source="fes profile"),
                  _event(t + 1.5, "electrode_burst", operator, "app", district="triceps", channel=5, electrodes="1-2",
                         current_ma=current, pulse_width_us=250, baseline_n=0.0, response_n=0.2, motion_mm=0.4,
                         samples=20)]
        fes_on.append((t, t + 1.5, 5, float(current), 250.0))
        t += 1.7
    added += [_event(t + 0.5, "fes_started", "electrode set-up", "safety", profile="electrode test: channel 5, 16 mA",
                     source="electrode set-up", current_scale=1.0, pulse_width_scale=1.0),
              _event(t + 1.0, "emergency_stop", "button", "safety", source="button", reason="emergency stop pressed"),
              _event(t + 1.0, "fes_stopped", "emergency stop", "safety", reason="emergency stop pressed (button)",
                     source="emergency stop"),
              _event(t + 1.0, "alarm", "button", "safety", level="STOP", source="button",
                     text="Emergency stop: emergency stop pressed", ident=4),
              _event(t + 1.05, "electrode_setup_aborted", operator, "app", district="triceps",
                     reason="the emergency stop was pressed", bursts=2),
              _event(t + 4.0, "alarm_acknowledged", operator, "safety", ident=4, operator=operator),
              _event(t + 4.0, "emergency_stop_reset", operator, "safety", operator=operator),
              _event(t + 4.0, "alarm", operator, "safety", level="INFO", source=operator, text="Emergency stop reset",
                     ident=5)]
    fes_on.append((t + 0.5, t + 1.0, 5, 16.0, 250.0))
    t += 6.0
    # Stimulation from the FES panel, outside any exercise: a time profile that ran to its end (8 s) …
    added += [_event(t, "fes_profile_loaded", "safety", "safety", name="Wrist extension, 8 s cycle (example)",
                     channels=[3], frequency_hz=30.0),
              _event(t + 0.1, "fes_started", "FES panel", "safety", profile="Wrist extension, 8 s cycle (example)",
                     source="FES panel", current_scale=1.0, pulse_width_scale=1.0),
              _event(t + 8.1, "fes_stopped", "fes profile", "safety", reason="the time profile finished",
                     source="fes profile")]
    fes_on.append((t + 0.1, t + 8.1, 3, 20.0, 200.0))
    t += 10.0
    # … and the same profile again, stopped after 3 s by an emergency stop (with a lost link of the patient model).
    added += [_event(t, "fes_started", "FES panel", "safety", profile="Wrist extension, 8 s cycle (example)",
                     source="FES panel", current_scale=0.8, pulse_width_scale=1.0),
              _event(t + 3.0, "emergency_stop", "keyboard", "safety", source="keyboard",
                     reason="emergency stop pressed"),
              _event(t + 3.0, "alarm", "keyboard", "safety", level="STOP", source="keyboard",
                     text="Emergency stop: emergency stop pressed", ident=6),
              _event(t + 3.0, "fes_stopped", "emergency stop", "safety", reason="emergency stop pressed (keyboard)",
                     source="emergency stop"),
              _event(t + 3.5, "gap_start", "patient_model", "device", device="patient_model", cause="disconnected",
                     detail="no valid datagram from patient_model for 0.5 s", streams=["patient_model.main"]),
              _event(t + 3.5, "alarm", "patient_model", "safety", level="WARNING", source="patient_model",
                     text="patient_model connection lost: no valid datagram from patient_model for 0.5 s", ident=7),
              _event(t + 4.0, "gap_end", "patient_model", "device", device="patient_model", cause="connected",
                     detail="receiving", streams=["patient_model.main"]),
              _event(t + 4.0, "alarm", "patient_model", "safety", level="INFO", source="patient_model",
                     text="patient_model reconnected", ident=8),
              _event(t + 5.0, "alarm", "linarm", "safety", level="STOP", source="linarm", text=ENVELOPE, ident=9),
              _event(t + 9.0, "recovery", operator, "safety", step="acknowledged", operator=operator, count=4)]
    added += [_event(t + 9.0, "alarm_acknowledged", operator, "safety", ident=i, operator=operator)
              for i in (6, 7, 8, 9)]
    added += [_event(t + 9.0, "emergency_stop_reset", operator, "safety", operator=operator),
              _event(t + 9.0, "alarm", operator, "safety", level="INFO", source=operator, text="Emergency stop reset",
                     ident=10)]
    fes_on.append((t, t + 3.0, 3, 16.0, 200.0))
    new_end = t + 12.0
    events = sorted(events + added, key=lambda e: float(e["t_mono"]))
    (folder / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))
    _extend_streams(folder, manifest, end, new_end)
    _write_fes_stream(folder, manifest, new_end, fes_on)
    manifest["end"] = {"t_mono_s": T0 + new_end}
    manifest["duration_s"] = new_end
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def _extend_streams(folder: Path, manifest: dict[str, Any], end: float, new_end: float) -> None:
    """The handle rests and the sensors read on after the runs, to the session's new end."""
    for info in manifest["streams"].values():
        path = folder / info["file"]
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
        last = rows[-1]
        period = 1.0 / float(info["nominal_rate_hz"])
        t = float(last[0]) + period
        extra = []
        while t < T0 + new_end:
            extra.append([repr(t), *last[1:]])
            t += period * 4  # a quarter of the rate is plenty for a resting handle
        with path.open("a", newline="") as fh:
            csv.writer(fh, lineterminator="\n").writerows(extra)


def _write_fes_stream(folder: Path, manifest: dict[str, Any], end: float,
                      on: list[tuple[float, float, int, float, float]]) -> None:
    """What was sent to each channel, 40 times a second: zero but while stimulating."""
    names = [c.name for c in FES_STREAM.channels]
    lines = ["t_mono_s," + ",".join(names)]
    t = 0.0
    while t < end:
        values = dict.fromkeys(names, 0.0)
        for start, stop, ch, current, width in on:
            if start <= t <= stop:
                values[f"current{ch}"] = current
                values[f"pulseWidth{ch}"] = width
        lines.append(",".join([repr(T0 + t), *(repr(values[n]) for n in names)]))
        t += 1 / 40.0
    (folder / "streams" / f"{FES_STREAM.name}.csv").write_text("\n".join(lines) + "\n")
    manifest["streams"][FES_STREAM.name] = {
        "file": f"streams/{FES_STREAM.name}.csv", "device": "fes", "nominal_rate_hz": FES_STREAM.nominal_rate_hz,
        "channels": [{"name": c.name, "unit": c.unit, "label": c.label} for c in FES_STREAM.channels]}
