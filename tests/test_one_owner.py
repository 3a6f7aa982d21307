"""One owner of each device during a run (issue #36): the run holds the robot; the VR task's target and the
patient model's assistance are refused, or composed only where the exercise declares it, clamped to the run's
range — seen on the wire (the robot's acknowledged commands in the session record)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from app.core.config import RESOURCES, AppConfig
from app.session.recording import load_session
from tests.reaching import ReachingPatient

EXERCISES = RESOURCES / "exercises"
PARAMS = {"repetitions": 2, "start_m": 0.15, "target_m": 0.35, "use_fes": False, "timeout_s": 6.0, "rest_s": 0.3}


def _script(tmp: Path, params: dict[str, Any]) -> Path:
    text = (EXERCISES / "assisted_reaching_fes.py").read_text(encoding="utf-8")
    path = tmp / "assisted_reaching_run.py"
    path.write_text(f"exerciseParams = {params!r}\n" + text, encoding="utf-8")
    return path


@pytest.mark.realtime
def test_the_vr_task_does_not_pull_the_robot_out_of_the_exercises_range(tmp_path: Path) -> None:
    """The default configuration (the VR stand-in and the embedded patient model running), headless: the
    assisted-reaching exercise prescribes 0.15 .. 0.35 m. Before #36 the VR task sent its own targets (0.10 and
    0.40 m) to the robot during the run and every repetition was "not reached"."""
    from app.scripting.headless import EXIT_OK, run_headless

    out: list[str] = []
    reaching: list[ReachingPatient] = []

    def prepare(manager: Any) -> None:
        manager.sim_patient().idle()
        manager.sim_patient().passive()
        reaching.append(ReachingPatient(manager, PARAMS["start_m"], PARAMS["target_m"]))

    try:
        code = run_headless(AppConfig(), str(_script(tmp_path, PARAMS)), record_dir=str(tmp_path / "rec"),
                            prepare=prepare, output=lambda stream, text: out.append(text))
    finally:
        for patient in reaching:
            patient.close()
    assert code == EXIT_OK, "".join(out)
    folder = next((tmp_path / "rec").rglob("manifest.json")).parent
    events = load_session(folder).events
    run_start = next(e["t_mono"] for e in events if e["kind"] == "run_start")
    run_end = next(e["t_mono"] for e in events if e["kind"] == "run_end")
    targets = [(e["data"]["source"], e["data"]["args"]["Apos"]) for e in events
               if e["kind"] == "robot_command" and e["data"].get("command") == "setAssistanceTargetPos"
               and run_start <= e["t_mono"] <= run_end]
    assert targets, "no assistance target reached the robot during the run"
    outside = [(s, v) for s, v in targets if not 0.15 - 1e-9 <= v <= 0.35 + 1e-9]
    assert outside == [], f"targets outside the exercise's range on the wire: {outside}"
    ends = [e["data"]["ok"] for e in events if e["kind"] == "repetition_end"]
    assert ends == [True] * 2, ends


# ---------------------------------------------------------------------------------------------- the supervisor
def _supervisor() -> Any:
    from app.core.config import SafetyConfig
    from app.safety.supervisor import SafetySupervisor

    sup = SafetySupervisor(SafetyConfig())
    events: list[tuple[str, dict[str, Any]]] = []
    sup.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    sup.recorded = events  # type: ignore[attr-defined]
    return sup


def _lease(compose: tuple[Any, ...] = (), devices: frozenset[str] = frozenset({"robot", "stimulator"})) -> Any:
    from app.core.ownership import RUN_SOURCES, Lease

    return Lease(key="run-1", holder="Trigger reaching", devices=devices, sources=RUN_SOURCES, compose=compose,
                 run_id="run-1")


def test_a_run_holding_the_robot_refuses_every_other_source_with_a_sentence(qapp: Any) -> None:
    from app.safety.supervisor import SafetyError

    sup = _supervisor()
    sup.take_lease(_lease())
    assert sup.holder("robot") == "Trigger reaching"
    sup.check_robot_command("moveCentreTo", {"targetPos": 0.2, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 0.0},
                            "script")  # the run's own
    sup.check_robot_command("setAssistanceTargetPos", {"Apos": 0.2}, "script: fes.electrodeSetup")
    for source, name, args in (("VR task", "setAssistanceTargetPos", {"Apos": 0.2}),
                               ("assistance", "setAdmittanceParameter", {"Ka": 0.002}),
                               ("gui", "setCtrlState", {"controlState": 2}),
                               ("gui", "moveCentreTo", {"targetPos": 0.2, "maxVel": 0.1, "maxAcc": 0.1,
                                                        "execTime": 0.0})):
        with pytest.raises(SafetyError, match="is held by Trigger reaching"):
            sup.check_robot_command(name, args, source)
    # the safe state, reads and the controller's limits pass whoever holds the robot
    sup.check_robot_command("setCtrlState", {"controlState": 0}, "gui")
    sup.check_robot_command("getAssistanceTargetPos", {}, "gui")
    sup.check_robot_command("setMaxVelocity", {"maxVel": 0.2}, "limits")
    with pytest.raises(SafetyError, match="the stimulator is held by Trigger reaching"):
        sup.check_fes_command("start", "FES panel")
    refused = [d for k, d in sup.recorded if k == "lease_refused"]
    assert {(d["source"], d["what"]) for d in refused} == {("VR task", "setAssistanceTargetPos"),
                                                          ("assistance", "setAdmittanceParameter"),
                                                          ("gui", "setCtrlState"), ("gui", "moveCentreTo"),
                                                          ("FES panel", "start")}
    with pytest.raises(SafetyError):  # a second refusal of the same is counted, not recorded again
        sup.check_robot_command("setAssistanceTargetPos", {"Apos": 0.3}, "VR task")
    assert len([k for k, _d in sup.recorded if k == "lease_refused"]) == len(refused)
    held = sup.release_lease("run-1", "finished")
    assert held is not None and held.refused["VR task: setAssistanceTargetPos"] == 2
    released = next(d for k, d in sup.recorded if k == "lease_released")
    assert released["holder"] == "Trigger reaching" and released["reason"] == "finished"
    sup.check_robot_command("setAssistanceTargetPos", {"Apos": 0.1}, "VR task")  # nobody holds it now
    from app.core.ownership import Lease

    sup.take_lease(_lease())
    with pytest.raises(SafetyError, match="held by Trigger reaching"):  # one owner at a time
        sup.take_lease(Lease(key="other", holder="Electrode set-up", devices=frozenset({"robot"}), sources=()))


def test_a_composed_target_is_clamped_to_the_runs_range_and_the_patients_limits(qapp: Any) -> None:
    from dataclasses import replace

    from app.core.ownership import Composition
    from app.safety.supervisor import SafetyError

    sup = _supervisor()
    sup.robot = replace(sup.robot, position_min_m=0.18, position_max_m=0.40)  # the patient's narrower range
    sup.take_lease(_lease((Composition("VR task", "assistance_target", (0.15, 0.35)),)))
    assert sup.composed_target("VR task", 0.10) == 0.18  # the patient's limit is the narrower
    assert sup.composed_target("VR task", 0.40) == 0.35  # the run's range
    assert sup.composed_target("VR task", 0.25) == 0.25
    clamps = [d for k, d in sup.recorded if k == "clamped"]
    assert [(d["requested"], d["applied"]) for d in clamps] == [(0.10, 0.18), (0.40, 0.35)]
    sup.check_robot_command("setAssistanceTargetPos", {"Apos": 0.30}, "VR task")
    with pytest.raises(SafetyError, match="outside Trigger reaching's range"):  # nothing bypasses the clamp
        sup.check_robot_command("setAssistanceTargetPos", {"Apos": 0.40}, "VR task")
    with pytest.raises(SafetyError, match="is held by"):  # composing the target is not composing the gains
        sup.check_robot_command("setAssistanceParameter", {"Kt": 100.0}, "VR task")
    assert sup.composed_target("assistance", 0.3) is None  # not declared: refused


def test_the_exercises_declare_what_they_hold_and_compose() -> None:
    from app.therapy.exercises import find_exercise

    assisted = find_exercise("assisted_reaching_fes")
    params = {**assisted.defaults(), "start_m": 0.15, "target_m": 0.35}
    assert assisted.holds(params) == ("robot", "stimulator")
    assert assisted.holds({**params, "use_fes": False}) == ("robot",)
    (comp,) = assisted.compositions(params)
    assert (comp.source, comp.sets, comp.range_m) == ("VR task", "assistance_target", (0.15, 0.35))
    trigger = find_exercise("trigger_reaching")
    assert trigger.holds(trigger.defaults()) == ("robot",) and trigger.compositions(trigger.defaults()) == ()


def test_losing_a_link_the_running_owner_refuses_is_a_warning_not_a_stop(qapp: Any) -> None:
    """The patient model's α drives nothing the electrode set-up holds: its loss during the set-up no longer stops
    it (under load it did; the set-up never used it). A program's run may read α itself: there it stays a STOP."""
    from types import SimpleNamespace

    from app.core.ownership import RUN_SOURCES, Composition, Lease
    from app.manager import LinarmppManager
    from app.safety.supervisor import AlarmLevel

    manager = LinarmppManager(AppConfig(), factories={})
    manager.fault_policy.loss_level = lambda _device: AlarmLevel.STOP  # an actuator is active
    manager.driver = lambda name: SimpleNamespace(stimulating=True) if name == "fes" else None  # type: ignore
    assert manager.loss_level("patient_model") == AlarmLevel.STOP  # nobody holds the stimulator: α reaches it
    sup = manager.supervisor
    sup.take_lease(Lease("electrode-setup", "Electrode set-up", frozenset({"robot", "stimulator"}),
                         ("electrode set-up",)))
    assert manager.loss_level("patient_model") == AlarmLevel.WARNING
    assert manager.loss_level("vr") == AlarmLevel.WARNING
    sup.release_lease("electrode-setup")
    # a program's run may read α itself (the script API's patientModel): its loss stays a STOP
    sup.take_lease(Lease("run-2", "Assisted reaching", frozenset({"robot", "stimulator"}), RUN_SOURCES,
                         compose=(Composition("assistance", "pulse_width"),)))
    assert manager.loss_level("patient_model") == AlarmLevel.STOP


def test_a_run_of_the_next_sessions_log_holds_its_devices_though_an_earlier_log_used_its_id(qapp: Any) -> None:
    """Each session has a run log of its own, numbered from run-1, and a run ends in the log it began in: a run
    of the earlier log may still run when the next session's run-1 starts. The lease is the run's, not its id's:
    before, the new run-1 was taken for the old one — it held nothing, and the old run's end released a lease by
    that id (found reading the code; the runner's start check keeps today's entry points from reaching it)."""
    from app.core.runs import Program
    from app.manager import LinarmppManager

    manager = LinarmppManager(AppConfig(), factories={})
    sup = manager.supervisor
    earlier = manager.runs
    old = earlier.start(Program("script_file", "look.py", "look.py", ""), (), "script_tab", "t",
                        holds=("stimulator",))
    assert sup.holder("stimulator") == old.title and sup.holder("robot") == ""
    later = manager._new_run_log()  # as start_session makes it
    new = later.start(Program("exercise", "trigger_reaching", "Trigger reaching", ""), (), "exercises_tab", "t",
                      holds=("robot",))
    assert new.run_id == old.run_id  # the collision itself: both are run-1
    assert sup.holder("robot") == "Trigger reaching", "the next session's run-1 does not hold the robot"
    earlier.end(old.run_id, "finished")
    assert sup.holder("robot") == "Trigger reaching", "the earlier run's end released the new run's lease"
    assert sup.holder("stimulator") == ""
    later.end(new.run_id, "finished")
    assert sup.holder("robot") == ""
