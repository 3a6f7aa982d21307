"""The LINarm driver against the simulated controller over a real pty: every command of the protocol
round-trips with its ACK, a controller error surfaces as an exception carrying its code, and the
seed's reaching motion has the profile asked for, asserted on the samples the driver published."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from app.core import streams
from app.core.config import AppConfig, SafetyConfig
from app.devices.linarm import LinarmCommandError, LinarmDriver
from app.devices.sim.adapters import LinarmSimAdapter
from app.devices.sim.base import SerialSimulator
from app.devices.transport import SerialTransport
from app.safety.supervisor import SafetySupervisor
from app.wire import linarm_protocol as proto
from app.wire.linarm_protocol import ControlMode, ControlState, ReplyError

IDLE, ON = int(ControlState.IDLE_CTRL_STATE), int(ControlState.ON_CTRL_STATE)
VEL, TARGET = int(ControlMode.POS_REF_BY_VEL), int(ControlMode.POS_REF_BY_TARGET_POS)


@pytest.fixture
def robot(tmp_path, qtbot) -> Iterator[LinarmDriver]:
    safety = SafetyConfig()
    # A bench set-up: the ack test also covers disableEndstrokes, which the default limits refuse.
    safety = dataclasses.replace(safety, robot=dataclasses.replace(safety.robot, allow_disable_endstrokes=True,
                                                                      allow_calibration=True))
    sim = SerialSimulator("linarm", lambda: LinarmSimAdapter(None, start_homed=True, initial_centre=0.10),
                          tmp_path / "linarm.tty")
    driver = LinarmDriver(SerialTransport(sim.url), SafetySupervisor(safety), command_timeout_s=2.0)
    driver.start()
    sim.start()
    qtbot.waitUntil(lambda: driver.connected and driver.latest("linarm.state") is not None, timeout=5000)
    yield driver
    driver.stop()
    sim.stop()


def enter(driver: LinarmDriver, qtbot, state: str) -> None:
    """Put the controller in the state a command needs: 'idle', 'on-vel' or 'on-target'."""
    driver.command("setCtrlState", IDLE)
    if state == "idle":
        return
    driver.command("setCtrlMode", VEL if state == "on-vel" else TARGET)
    driver.command("setCtrlState", ON)
    qtbot.waitUntil(lambda: driver.latest("linarm.state").controlState == ON, timeout=2000)


# name → (arguments, the state it needs); every host command but the driver's own
# (identify, heartbeat, startDataStream at connect) is covered, which the last test checks.
CASES: dict[str, tuple[tuple[Any, ...], str]] = {
    "setDemo": ((False,), "idle"),
    "resetError": ((), "idle"),
    "setCtrlState": ((IDLE,), "idle"),
    "setCtrlMode": ((TARGET,), "idle"),
    "setCentreVelocity": ((0.0,), "on-vel"),
    "setDeltaVelocity": ((0.0,), "on-vel"),
    "getPidTunings": ((1,), "idle"),
    "moveCentreTo": ((0.25, 0.15, 0.15, 0.0, False), "on-target"),
    "moveDeltaTo": ((0.02, 0.05, 0.2, 0.0, False), "on-target"),
    "setStiffness": ((900.0, 0.05, 0.2, 0.0), "on-target"),
    "goToHome": ((), "idle"),
    "setTrajectoryType": ((1,), "idle"),
    "setAdmittanceParameter": ((0.002,), "idle"),
    "getAdmittanceParameter": ((), "idle"),
    "setAssistanceParameter": ((50.0,), "idle"),
    "getAssistanceParameter": ((), "idle"),
    "setAssistanceTargetPos": ((0.3,), "idle"),
    "getAssistanceTargetPos": ((), "idle"),
    "enableVirtualVsa": ((False,), "idle"),
    "setVirtualVsaSpringDisplacement": ((0.0,), "idle"),
    "getIsInitialized": ((), "idle"),
    "disableEndstrokes": ((False,), "idle"),
    "setTriggerMode": ((0,), "idle"),
    "setTriggerParameter": ((0.0,), "idle"),
    "startDataStream": ((0.005,), "idle"),
    "stopDataStream": ((), "idle"),
    "setMotorOffset": ((0, 0.0), "idle"),
    "setMobileOffset": ((0.0,), "idle"),
    "setMotorRatio": ((0, 1e-5), "idle"),
    "setMobileRatio": ((1e-5,), "idle"),
    "setMaxTrackingError": ((0.02,), "idle"),
    "setMaxForce": ((50.0,), "idle"),
    "setMaxCurrent": ((2.0,), "idle"),
    "setMaxAcceleration": ((0.5,), "idle"),
    "setMaxVelocity": ((0.2,), "idle"),
    "setHomeParameter": ((0.25, 0.02, 0.05), "idle"),
    "setPosLimit": ((0.05, 0.45), "idle"),
    "setPidTunings": (("read",), "idle"),
    "getState": ((), "idle"),
    "lockEnvelope": ((), "idle"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_every_command_round_trips_with_its_ack(robot: LinarmDriver, qtbot, name: str) -> None:
    args, state = CASES[name]
    enter(robot, qtbot, state)
    if args == ("read",):  # write back the gains just read: a real ack without detuning the loop
        read = robot.command("getPidTunings", 0)
        args = (0, read["kp"], read["ki"], read["kd"])
    values = robot.command(name, *args, source="test")
    returns = [a.name for a in proto.COMMANDS_BY_NAME[name].returns]
    assert sorted(values) == sorted(returns), f"{name} ACK carries {values}"
    if name == "getIsInitialized":
        assert values["initialized"] is True
    if name == "getAdmittanceParameter":
        assert values["Ka"] > 0


def test_every_protocol_command_is_covered() -> None:
    driver_own = {"identify", "heartbeat"}
    assert set(proto.COMMANDS_BY_NAME) - driver_own == set(CASES)


def test_a_controller_error_is_raised_with_its_code(robot: LinarmDriver, qtbot) -> None:
    enter(robot, qtbot, "idle")
    with pytest.raises(LinarmCommandError) as err:  # moves need ON
        robot.command("moveCentreTo", 0.3, 0.1, 0.1, 0.0, False)
    assert err.value.code == ReplyError.WRONG_STATE and "WRONG_STATE" in str(err.value)
    enter(robot, qtbot, "on-vel")
    with pytest.raises(LinarmCommandError) as err:
        robot.command("moveCentreTo", 0.3, 0.1, 0.1, 0.0, False)
    assert err.value.code == ReplyError.WRONG_MODE


def record_centre(robot: LinarmDriver) -> tuple[list[tuple[float, float]], Any]:
    """The centre as the bus delivers it: ``pump()`` moves the queued samples into the list."""
    samples: list[tuple[float, float]] = []
    sub = robot.bus.subscribe("test-centre", [streams.LINARM_VSA], maxlen=100_000)

    def pump() -> list[tuple[float, float]]:
        # The controller's own clock: arrival times on the PC are bunched by the serial reads.
        samples.extend((item.sample.controllerTime, item.sample.equilibriumPos) for item in sub.drain())
        return samples

    pump.close = sub.close  # type: ignore[attr-defined]
    return samples, pump


@pytest.mark.parametrize("trajectory", [0, 1], ids=["trapezoidal", "cycloidal"])
def test_reaching_motion_profile_on_the_recorded_samples(robot: LinarmDriver, qtbot, trajectory: int) -> None:
    enter(robot, qtbot, "on-target")
    robot.command("setTrajectoryType", trajectory)
    samples, pump = record_centre(robot)
    robot.command("moveCentreTo", 0.40, 0.15, 0.15, 0.0, False)
    qtbot.waitUntil(lambda: bool(pump()) and abs(samples[-1][1] - 0.40) < 0.002
                    and abs(robot.latest("linarm.vsa").handleVel) < 0.01, timeout=8000)
    pump.close()
    t = np.array([s[0] for s in samples])
    x = np.array([s[1] for s in samples])
    assert abs(x[-1] - 0.40) <= 0.005
    # Speed from the samples, smoothed over 25 ms to keep encoder quantisation out of it.
    v = np.convolve(np.gradient(x, t), np.ones(5) / 5, mode="same")
    assert v.max() <= 0.15 * 1.05, f"peak speed {v.max():.4f} m/s"
    moving = v > 0.005
    span = t[moving][-1] - t[moving][0]
    at_peak = np.mean(v[moving] > 0.95 * v.max())
    if trajectory == 0:
        # Trapezoid: 1 s ramps at 0.15 m/s² to 0.15 m/s, a cruise at the peak for about a third of the time.
        assert at_peak > 0.25, f"only {at_peak:.0%} of the move near the peak speed"
        assert v.max() >= 0.14
    else:
        # Cycloid: the speed is a sine bump, near its peak only briefly.
        assert at_peak < 0.25, f"{at_peak:.0%} of the move near the peak: not cycloidal"
    assert 2.0 < span < 4.5


def test_commands_are_checked_by_the_supervisor_before_the_wire(robot: LinarmDriver, qtbot) -> None:
    from app.safety.supervisor import SafetyError

    enter(robot, qtbot, "on-target")
    limits = AppConfig().safety.robot
    with pytest.raises(SafetyError, match="outside the allowed range"):
        robot.command("moveCentreTo", limits.position_max_m + 0.01, 0.1, 0.1, 0.0, False)
    assert robot.latest("linarm.state").controlState == ON  # nothing was sent, nothing changed


def test_apply_limits_locks_the_site_envelope_then_narrows_it_through_the_queue(robot: LinarmDriver) -> None:
    """The connect-time limits (#29: LINK-priority statuses, one command after the other's ACK): the site's
    limits are locked as the controller's envelope, a narrower profile follows inside it."""
    site = robot.supervisor.robot
    status = robot.apply_limits(site)
    envelope = status.result(5.0)
    assert envelope["maxVel"] == pytest.approx(site.max_velocity_m_s, rel=1e-6)
    assert envelope["minPos"] == pytest.approx(site.position_min_m, rel=1e-6)
    narrower = dataclasses.replace(site, max_velocity_m_s=site.max_velocity_m_s / 2)
    assert robot.apply_limits(narrower).result(5.0) == envelope
    assert robot.apply_limits(site).result(5.0) == envelope


def test_a_late_or_withheld_heartbeat_is_said_in_the_log(caplog) -> None:
    """The controller stops the motors after WATCHDOG_TIMEOUT without a heartbeat; when the app's heartbeat came
    late (a busy machine, no real-time scheduling) or was withheld (a wedged reading loop), the log says so before
    the controller's WATCHDOG does, so that stop does not read as a fault of the robot. Driven by hand: the queue's
    periodic called directly, the clocks set, no thread started."""
    import logging
    import time as _time

    from app.devices import linarm as linarm_module

    class RecordingLink:
        def __init__(self) -> None:
            self.written: list[bytes] = []

        def write(self, data: bytes) -> None:
            self.written.append(data)

    link = RecordingLink()
    driver = LinarmDriver(link, SafetySupervisor(SafetyConfig()))  # type: ignore[arg-type]
    driver._beating = True
    caplog.set_level(logging.WARNING, logger=linarm_module.__name__)
    now = _time.monotonic()
    driver._reader_alive = now
    driver._last_heartbeat = now - 0.05  # on time: written, nothing said
    driver._beat()
    assert len(link.written) == 1 and not caplog.records

    driver._last_heartbeat = _time.monotonic() - 0.2  # late: written, and said with its gap
    driver._beat()
    assert len(link.written) == 2
    (late,) = [r.getMessage() for r in caplog.records]
    assert "LINarm heartbeat late: 0.2" in late and "the OS refused real-time scheduling" in late
    driver._last_heartbeat = _time.monotonic() - 0.2  # late again within the second: counted, not said again
    driver._beat()
    assert len(link.written) == 3 and len(caplog.records) == 1 and driver._late_beats == 1

    driver._reader_alive = _time.monotonic() - 0.6  # the reading loop wedged: withheld, said once an episode
    driver._beat()
    driver._beat()
    assert len(link.written) == 3
    withheld = [r.getMessage() for r in caplog.records if "withheld" in r.getMessage()]
    assert len(withheld) == 1 and "the reading loop has not run for 0.6" in withheld[0]
