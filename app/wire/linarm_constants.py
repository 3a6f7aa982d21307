"""The LINarm2 controller's constants: the one source for the firmware, the simulator and the panel.

The protocol table (``app/wire/linarm_protocol.py``) says what goes on the wire; this sibling table says
what the controller starts with and what it accepts: its defaults (limits, home, gains, Ka/Kt), the ranges
its setters check, the supervision rules, the mechanics (rail, switches, springs, drives) and the plant
of the simulators. ``protocol_table()["constants"]`` exports it; ``firmware/tools/gen_protocol_header.py``
turns it into ``firmware/linarm_controller/src/linarm_constants_generated.h`` (the build fails when the
committed copy differs); ``app/devices/sim/linarm_model.py`` and ``app/ui/linarm_panel.py`` read ``K``.
tests/test_firmware_constants.py fails if any of them disagrees.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Constant:
    name: str  # C++ name in namespace cfg
    value: float
    unit: str
    doc: str
    group: str
    integer: bool = False  # emitted as an unsigned long (tick counts)


def _group(group: str, *rows: tuple[str, float, str, str]) -> tuple[Constant, ...]:
    return tuple(Constant(name, value, unit, doc, group, integer=unit == "ticks") for name, value, unit, doc in rows)


CONSTANTS: tuple[Constant, ...] = (
    *_group(
        "loop",
        ("DT", 0.001, "s", "control period (1 kHz)"),
        ("HOME_SETTLE_TICKS", 300, "ticks", "at rest after the move to home before the handle encoder is referenced"),
        ("OVER_CURRENT_TICKS", 50, "ticks", "current above maxCurrent this long before OVER_CURRENT"),
    ),
    *_group(
        "mechanics",
        ("RAIL_MIN", 0.0, "m", "rail start"),
        ("RAIL_MAX", 0.50, "m", "rail end"),
        ("SWITCH_MIN_POS", 0.005, "m", "motor 0's endstroke closes at or below this"),
        ("SWITCH_MAX_POS", 0.495, "m", "motor 1's endstroke closes at or above this"),
        ("FORCE_CONSTANT", 20.0, "N/A", "motor force per amp of the current-controlled drives"),
        ("CURRENT_HW_LIMIT", 6.0, "A", "what the drives can deliver"),
        ("ENCODER_RESOLUTION", 1.0e-5, "m/count", "motors and handle, until setMotorRatio/setMobileRatio"),
        ("SPRING_A", 150.0, "N/m", "spring tension f(e) = a e + b e^3 (e > 0)"),
        ("SPRING_B", 1.0e6, "N/m^3", "cubic term of the spring tension"),
        ("SPRING_FREE_LENGTH", 0.04, "m", "free length L of each spring"),
        ("DELTA_MIN", 0.01, "m", "least pretension (carriage distance 0.09 m, k = 450 N/m)"),
        ("DELTA_MAX", 0.06, "m", "most pretension (carriage distance 0.14 m, k = 5700 N/m)"),
    ),
    *_group(
        "plant",  # the simulated robot (Python simulator and the C++ SIL plant)
        ("CARRIAGE_MASS", 1.0, "kg", "each motor carriage"),
        ("CARRIAGE_VISCOUS", 30.0, "N s/m", "carriage viscous friction"),
        ("CARRIAGE_COULOMB", 8.0, "N", "carriage Coulomb friction (the lead screw holds delta with the motors off)"),
        ("HANDLE_MASS", 0.5, "kg", "handle"),
        ("HANDLE_DAMPING", 20.0, "N s/m", "handle viscous damping"),
        ("BUMPER", 0.015, "m", "closest handle-carriage distance before contact"),
        ("CONTACT_STIFFNESS", 5.0e4, "N/m", "bumpers and rail-end stops"),
        ("CONTACT_DAMPING", 200.0, "N s/m", "bumpers and rail-end stops"),
    ),
    *_group(
        "defaults",  # what the controller starts with (setters in the protocol)
        ("POS_MIN", 0.08, "m", "minPos"),
        ("POS_MAX", 0.42, "m", "maxPos"),
        ("MAX_TRACKING_ERROR", 0.02, "m", "maxTrackingError"),
        ("MAX_FORCE", 60.0, "N", "maxForce"),
        ("MAX_CURRENT", 5.0, "A", "maxCurrent"),
        ("MAX_ACCELERATION", 2.0, "m/s^2", "maxAcceleration"),
        ("MAX_VELOCITY", 0.5, "m/s", "maxVelocity"),
        ("HOME_CENTRE", 0.25, "m", "homeCentre"),
        ("HOME_DELTA", 0.02, "m", "homeDelta"),
        ("HOMING_VELOCITY", 0.2, "m/s", "homingVelocity: a full homing takes ~4 s"),
        ("HOME_MOVE_MIN_VELOCITY", 0.05, "m/s", "the move to home runs at least this fast"),
        ("SEEK_LEAD", 0.005, "m", "how far a seek reference may lead its carriage"),
        ("ADMITTANCE_KA", 0.005, "m/(N s)", "Ka"),
        ("ASSISTANCE_KT", 100.0, "N/m", "Kt"),
        ("ASSISTANCE_TARGET", 0.25, "m", "Apos"),
        ("PID_KP", 20000.0, "N/m", "kp of both position loops"),
        ("PID_KI", 100000.0, "N/(m s)", "ki of both position loops"),
        ("PID_KD", 200.0, "N s/m", "kd of both position loops"),
    ),
    *_group(
        "supervision",
        ("POSITION_LIMIT_MARGIN", 0.02, "m", "handle outside [minPos, maxPos] by more: POSITION_LIMIT"),
        ("OVER_VELOCITY_FACTOR", 1.5, "", "speed above this x maxVelocity: OVER_VELOCITY"),
        ("ENVELOPE_VELOCITY_FACTOR", 1.2, "", "handle speed above this x the locked maxVelocity: ENVELOPE_BREACH"),
        ("ENVELOPE_POSITION_MARGIN", 0.01, "m", "handle outside the locked range by more: ENVELOPE_BREACH"),
    ),
    *_group(
        "ranges",  # what the controller's setters accept (beyond the protocol table's argument ranges)
        ("MOVE_LIMIT_MIN", 1.0e-6, "", "least maxVel/maxAcc of a move planned from them"),
        ("KA_MAX", 1.0, "m/(N s)", "setAdmittanceParameter"),
        ("KT_MAX", 5000.0, "N/m", "setAssistanceParameter"),
        ("VIRTUAL_DISP_MAX", 0.05, "m", "setVirtualVsaSpringDisplacement, +-"),
        ("RATIO_MIN", 1.0e-9, "m/count", "setMotorRatio / setMobileRatio"),
        ("RATIO_MAX", 1.0, "m/count", "setMotorRatio / setMobileRatio"),
        ("MAX_TRACKING_ERROR_MIN", 1.0e-6, "m", "setMaxTrackingError"),
        ("MAX_TRACKING_ERROR_MAX", 0.1, "m", "setMaxTrackingError"),
        ("MAX_FORCE_MIN", 0.1, "N", "setMaxForce"),
        ("MAX_FORCE_MAX", 200.0, "N", "setMaxForce"),
        ("MAX_CURRENT_MIN", 0.01, "A", "setMaxCurrent (its maximum is CURRENT_HW_LIMIT)"),
        ("MAX_ACC_MIN", 1.0e-3, "m/s^2", "setMaxAcceleration"),
        ("MAX_ACC_MAX", 10.0, "m/s^2", "setMaxAcceleration"),
        ("MAX_VEL_MIN", 1.0e-3, "m/s", "setMaxVelocity"),
        ("MAX_VEL_MAX", 1.0, "m/s", "setMaxVelocity"),
        ("HOMING_VELOCITY_MIN", 1.0e-3, "m/s", "setHomeParameter (its maximum is maxVelocity)"),
        ("POS_LIMIT_MIN_SPAN", 1.0e-3, "m", "setPosLimit: maxPos - minPos at least"),
        ("KP_MAX", 1.0e6, "N/m", "setPidTunings"),
        ("KI_MAX", 1.0e7, "N/(m s)", "setPidTunings"),
        ("KD_MAX", 1.0e4, "N s/m", "setPidTunings"),
    ),
    *_group(
        "host",  # what the host asks of the controller (the firmware does not use them; the setters check them)
        ("PRETENSION_MOVE_VELOCITY", 0.05, "m/s",
         "maxVel of the host's pretension (delta) moves: the assistance's setStiffness, the runner's moveDeltaTo"),
        ("PRETENSION_MOVE_ACCELERATION", 0.2, "m/s^2",
         "maxAcc of the host's pretension (delta) moves: the assistance's setStiffness, the runner's moveDeltaTo"),
        ("STIFFNESS_LIMIT_MAX", 10000.0, "N/m", "the largest stiffness limit a site or a patient may set"),
    ),
)

K: dict[str, float] = {c.name: c.value for c in CONSTANTS}
assert len(K) == len(CONSTANTS), "duplicate constant names"

# The host's pretension (delta) move as a command's (maxVel, maxAcc, execTime) arguments: execTime 0 = planned
# from that velocity and acceleration. setStiffness (the assistance split) and moveDeltaTo (the runner) use it.
PRETENSION_MOVE: tuple[float, float, float] = (K["PRETENSION_MOVE_VELOCITY"], K["PRETENSION_MOVE_ACCELERATION"], 0.0)


def constants_table() -> list[dict[str, object]]:
    """JSON-serialisable rows (``protocol_table()['constants']``)."""
    return [{"name": c.name, "value": c.value, "unit": c.unit, "doc": c.doc, "group": c.group,
             "integer": c.integer} for c in CONSTANTS]
