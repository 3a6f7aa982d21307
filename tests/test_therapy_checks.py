"""Checked before anything moves (issue #36): a therapy plan, an exercise form and a run against the patient's
*current* caps, limits and electrode choices — when the plan is saved, when the session starts and when the run
starts — in the clinician's words; the library's FES exercise stimulates by district; an electrode choice saved
in a running session never brings back a cap lowered since. Pure logic and one dialog: no devices."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from app.core.config import AppConfig
from app.therapy.patients import (
    ClinicalChannelCap,
    ElectrodeChoice,
    PatientFes,
    PatientProfile,
    PlannedExercise,
    load_patient,
    prescription_problems,
    save_patient,
)

SAFETY = AppConfig().safety
ASSISTED = {"repetitions": 2, "use_fes": True, "fes_profile": "frontal_reaching.yaml"}  # channel 1 peaks at 28 mA
BY_DISTRICT = {**ASSISTED, "fes_profile": "reaching_by_district.yaml"}  # anterior deltoid 24 mA, triceps 22 mA


def _capped(patient_id: str = "PZ-CAP", cap_ma: float = 20.0, **fes: Any) -> PatientProfile:
    caps = {ch: ClinicalChannelCap(max_current_ma=cap_ma) for ch in range(1, 9)}
    return PatientProfile(patient_id=patient_id, full_name="Maria Esposito", fes=PatientFes(caps=caps, **fes))


def _chosen(**channels: int) -> dict[str, ElectrodeChoice]:
    return {district.replace("_", " "): ElectrodeChoice(channel=ch, electrodes="1-2") for district, ch in
            channels.items()}


def test_a_plan_with_a_profile_above_the_patients_cap_is_refused_in_words() -> None:
    """Before #36 a plan accepted the 28 mA profile for a patient capped at 20 mA; the step failed at run time,
    after the robot had moved, with "CommandRefused: fes.loadFile(…)"."""
    plan = [PlannedExercise("assisted_reaching_fes", dict(ASSISTED))]
    (problem,) = prescription_problems(plan, _capped(), SAFETY)
    text = str(problem)
    assert problem.step == 1 and problem.parameter == "fes_profile"
    assert text.startswith("Step 1, Assisted reaching with FES — FES profile:")
    assert "28 mA" in text and "20 mA" in text and "clinical cap" in text and "anterior deltoid" in text
    assert "CommandRefused" not in text and "fes.loadFile" not in text
    assert prescription_problems(plan, _capped(cap_ma=30.0), SAFETY) == []
    assert prescription_problems([PlannedExercise("assisted_reaching_fes", {**ASSISTED, "use_fes": False})],
                                 _capped(), SAFETY) == []  # FES off: nothing to check


def test_a_district_profile_needs_the_patients_chosen_combinations_and_their_caps() -> None:
    plan = [PlannedExercise("assisted_reaching_fes", dict(BY_DISTRICT))]
    (missing,) = prescription_problems(plan, _capped(cap_ma=30.0), SAFETY)
    assert "no electrode combination is chosen" in str(missing) and "anterior deltoid and triceps" in str(missing)
    half = _capped(cap_ma=30.0, electrodes=_chosen(anterior_deltoid=2))
    (still,) = prescription_problems(plan, half, SAFETY)
    assert "the triceps" in str(still) and "anterior deltoid" not in str(still)
    both = _capped(cap_ma=30.0, electrodes=_chosen(anterior_deltoid=2, triceps=6))
    assert prescription_problems(plan, both, SAFETY) == []
    low = _capped(cap_ma=20.0, electrodes=_chosen(anterior_deltoid=2, triceps=6))
    (capped,) = prescription_problems(plan, low, SAFETY)
    assert "channel 2 (anterior deltoid)" in str(capped) and "24 mA" in str(capped)


def test_positions_and_speeds_are_checked_against_the_patients_robot_limits() -> None:
    from app.therapy.patients import PatientRobotLimits

    narrow = PatientProfile(patient_id="PZ-ROM", robot=PatientRobotLimits(position_max_m=0.30, max_velocity_m_s=0.1))
    plan = [PlannedExercise("trigger_reaching", {"movements": 3, "start_m": 0.15, "end_m": 0.40, "speed_m_s": 0.2})]
    problems = {p.parameter: str(p) for p in prescription_problems(plan, narrow, SAFETY)}
    assert set(problems) == {"end_m", "speed_m_s"}
    assert "0.4 m is outside this patient's range of movement" in problems["end_m"]
    assert "0.2 m/s is above this patient's limit of 0.1 m/s" in problems["speed_m_s"]


def test_the_plan_dialog_refuses_at_save_time_with_the_sentence(qtbot: Any, tmp_path: Path) -> None:
    from app.ui.plan_dialog import PlanDialog

    save_patient(_capped(), tmp_path, SAFETY)
    dialog = PlanDialog(load_patient("PZ-CAP", SAFETY, tmp_path), SAFETY, tmp_path)
    qtbot.addWidget(dialog)
    dialog.show()
    dialog.add_step("assisted_reaching_fes")
    dialog.editors["fes_profile"].setCurrentText("frontal_reaching.yaml")
    dialog.accept()  # checked and written on a thread of its own (#37): its answer is waited for
    qtbot.waitUntil(lambda: not dialog.saving, timeout=5000)
    assert dialog.result() != 1 and dialog.saved is None
    assert "The plan is not saved" in dialog.error_label.text() and "28 mA" in dialog.error_label.text()
    assert load_patient("PZ-CAP", SAFETY, tmp_path).therapy_plan == []


def test_a_run_is_refused_before_it_starts_when_the_caps_in_force_refuse_it() -> None:
    """At the run's start, against the limiter's caps now (they may have changed since the plan was saved):
    nothing is recorded, nothing started."""
    from types import SimpleNamespace

    from app.safety.fes_limits import ChannelCaps, FesLimiter, FesLimits
    from app.therapy.exercises import find_exercise, start_exercise

    events: list[str] = []
    limits = FesLimits(clinical_caps={ch: ChannelCaps(20.0) for ch in range(1, 9)})
    supervisor = SimpleNamespace(robot=SAFETY.robot, fes_limiter=FesLimiter(limits), robot_hold_reason=lambda: "",
                                 holder=lambda _d: "", record=lambda kind, **_d: events.append(kind))
    manager = SimpleNamespace(supervisor=supervisor, recorder=None, patient_profile=None,
                              driver=lambda _name: None, record_event=lambda *a, **k: events.append(a[0]))
    runner = SimpleNamespace(running=False, started=[], start=lambda *a, **k: runner.started.append(a))
    exercise = find_exercise("assisted_reaching_fes")
    checked = start_exercise(runner, manager, exercise, {**exercise.defaults(), **ASSISTED})
    assert not checked.ok and "28 mA" in checked.errors["fes_profile"]
    assert runner.started == [] and events == []


def test_an_electrode_choice_never_brings_back_a_cap_lowered_since(tmp_path: Path) -> None:
    """The session started with the profile at 30 mA; the cap was lowered to 15 mA in the Patients window; an
    electrode choice accepted afterwards saved the session's copy and put 30 mA back (before #36)."""
    from dataclasses import replace

    from app.archive.station import save_choice
    from app.therapy.electrodes import districts_from_config

    at_start = _capped(cap_ma=30.0)
    save_patient(at_start, tmp_path, SAFETY)
    lowered = replace(at_start, fes=PatientFes(caps={ch: ClinicalChannelCap(max_current_ma=15.0)
                                                     for ch in range(1, 9)}))
    save_patient(lowered, tmp_path, SAFETY)
    district = districts_from_config(AppConfig().devices.fes.electrodes)["anterior deltoid"]
    saved = save_choice(_result(district), 2, at_start, "Dr Bianchi", "", SAFETY, tmp_path)
    on_disk = load_patient("PZ-CAP", SAFETY, tmp_path)
    assert on_disk.fes.caps[1].max_current_ma == 15.0 and saved.fes.caps[1].max_current_ma == 15.0
    assert on_disk.fes.electrodes["anterior deltoid"].channel == 2


def _result(district: Any) -> Any:
    from app.therapy.electrodes import CombinationResult, SetupPlan, SetupResult

    plan = SetupPlan(ceiling_ma=10.0)
    return SetupResult(district, plan, [CombinationResult(c, 10, "the therapist's ceiling")
                                        for c in district.combinations])
