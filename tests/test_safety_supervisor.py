"""The supervisor's robot rules: commands outside limits are refused before anything is sent; a
measured excursion stops the robot once per excursion; the e-stop latches until reset."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from app.core import journal
from app.core.config import SafetyConfig
from app.safety.supervisor import AlarmLevel, SafetyError, SafetySupervisor


def sup() -> SafetySupervisor:
    return SafetySupervisor(SafetyConfig())


@pytest.mark.parametrize(("name", "args", "fragment"), [
    ("moveCentreTo", {"targetPos": 0.6, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 0.0}, "outside the allowed range"),
    ("moveCentreTo", {"targetPos": 0.3, "maxVel": 0.5, "maxAcc": 0.1, "execTime": 0.0}, "velocity limit"),
    ("moveCentreTo", {"targetPos": 0.3, "maxVel": 0.1, "maxAcc": 5.0, "execTime": 0.0}, "acceleration limit"),
    ("moveCentreTo", {"targetPos": 0.3, "maxVel": 0.1, "maxAcc": 0.1, "execTime": float("nan")}, "finite"),
    ("moveDeltaTo", {"targetDeltaPos": 0.2, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 0.0}, "delta"),
    ("setStiffness", {"stiffness": 1e5, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 0.0}, "stiffness"),
    ("setCentreVelocity", {"centreVelocity": -0.9}, "velocity limit"),
    ("setAdmittanceParameter", {"Ka": 1.0}, "velocity limit"),
    ("setPosLimit", {"minPos": 0.0, "maxPos": 0.5}, "outside the allowed range"),
    ("setMaxForce", {"maxForce": 500.0}, "force limit"),
    ("disableEndstrokes", {"disable": True}, "endstroke"),
])
def test_out_of_limit_commands_are_refused_with_a_reason(name, args, fragment) -> None:
    s = sup()
    refused = []
    s.bus.listen("test", lambda r: refused.append(r.data["reason"]) if r.kind == journal.COMMAND_REFUSED else None)
    with pytest.raises(SafetyError, match=fragment):
        s.check_robot_command(name, args, "test")
    assert refused and fragment in refused[0]


def test_timed_move_is_checked_against_the_current_centre() -> None:
    s = sup()
    s.latest_centre_m = lambda: 0.10
    s.check_robot_command("moveCentreTo", {"targetPos": 0.40, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 3.0})
    with pytest.raises(SafetyError, match="needs up to"):
        s.check_robot_command("moveCentreTo", {"targetPos": 0.40, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 1.0})


def test_estop_latches_refuses_motion_but_allows_idle_and_reads() -> None:
    s = sup()
    calls = []
    s.register_estop_action("robot IDLE", calls.append)
    s.emergency_stop("test")
    assert s.estop_latched and len(calls) == 1
    with pytest.raises(SafetyError, match="latched"):
        s.check_robot_command("moveCentreTo", {"targetPos": 0.3, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 0.0})
    s.check_robot_command("setCtrlState", {"controlState": 0})
    s.check_robot_command("getIsInitialized", {})
    s.reset_emergency_stop("op")
    s.check_robot_command("moveCentreTo", {"targetPos": 0.3, "maxVel": 0.1, "maxAcc": 0.1, "execTime": 0.0})


def test_measured_excursion_stops_the_robot_once_per_excursion() -> None:
    s = sup()
    s.robot_homed = lambda: True
    stops = []
    s.register_estop_action("robot IDLE", stops.append)
    s.register_estop_action("FES stop", lambda reason: stops.append("fes"))
    ok = SimpleNamespace(handleVel=0.1, interactionForce=5.0, handlePos=0.3)
    fast = SimpleNamespace(handleVel=0.9, interactionForce=5.0, handlePos=0.3)
    # Right after homing a few samples may carry the old encoder reference: they are not judged on force.
    s.check_robot_sample(SimpleNamespace(handleVel=0.0, interactionForce=9000.0, handlePos=0.0))
    for _ in range(10):
        s.check_robot_sample(ok)
    assert stops == []
    s.check_robot_sample(fast)
    s.check_robot_sample(fast)
    assert len(stops) == 1 and "handle speed" in stops[0]
    assert s.alarms()[-1].level == AlarmLevel.STOP
    s.check_robot_sample(ok)
    s.check_robot_sample(SimpleNamespace(handleVel=0.0, interactionForce=-80.0, handlePos=0.3))
    assert len(stops) == 2 and "interaction force" in stops[1]


def test_patient_model_outputs_are_clamped_and_logged() -> None:
    s = sup()
    events = []
    s.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    assert s.clamp_assistance("alpha", 1.7, -1.0, 1.0) == 1.0
    assert events[-1][0] == "clamped" and events[-1][1]["requested"] == 1.7
