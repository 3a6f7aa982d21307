"""LINarm2 simulation core: driven by simulated time through the real wire protocol."""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import pytest

from app.devices.sim.linarm_model import LinarmParams, LinarmSimCore, TrajectoryError, plan_trajectory
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import (
    Ack,
    ControlMode,
    ControlState,
    ErrorEvent,
    ErrorReply,
    ErrorState,
    HomeState,
    Identify,
    LinarmState,
    MotorState,
    ReplyError,
    VsaState,
    decode_controller_frame,
    encode_command,
    next_seq,
)


@dataclass
class StepForce:
    """A patient pushing with `force` newtons from `start` seconds on (ramped over `ramp` s)."""

    force: float
    start: float = 0.0
    ramp: float = 0.0

    def handle_force(self, t: float, handle_pos: float, handle_vel: float) -> float:
        if t < self.start:
            return 0.0
        if self.ramp > 0:
            return self.force * min(1.0, (t - self.start) / self.ramp)
        return self.force


@dataclass
class Host:
    """A minimal host: encodes commands, sends heartbeats, decodes everything the core returns."""

    core: LinarmSimCore
    seq: int = 0
    decoder: CmdMessengerDecoder = field(default_factory=CmdMessengerDecoder)
    received: list = field(default_factory=list)

    def send(self, name: str, *args: object) -> Ack | ErrorReply | Identify:
        self.seq = next_seq(self.seq)
        replies = self._decode(self.core.handle_host_bytes(encode_command(name, self.seq, *args)))
        direct = [r for r in replies if isinstance(r, (Ack, ErrorReply, Identify))]
        assert direct and direct[0].seq == self.seq, replies
        return direct[0]

    def ok(self, name: str, *args: object) -> Ack:
        reply = self.send(name, *args)
        assert isinstance(reply, Ack), reply
        return reply

    def run(self, seconds: float, heartbeat: bool = True, sample: list | None = None) -> None:
        """Advance simulated time; heartbeat every 100 ms; optionally sample (t, centre speed)."""
        end = self.core.time + seconds
        next_hb = self.core.time
        while self.core.time < end - 1e-9:
            if heartbeat and self.core.time >= next_hb - 1e-9:
                self.seq = next_seq(self.seq)
                self.core.handle_host_bytes(encode_command("heartbeat", self.seq))
                next_hb += 0.1
            self.core.step(0.001)
            if sample is not None:
                sample.append((self.core.time, (self.core.v[0] + self.core.v[1]) / 2))
        self.drain()

    def drain(self) -> list:
        out = self._decode(self.core.stream_bytes())
        return out

    def _decode(self, data: bytes) -> list:
        msgs = [decode_controller_frame(f) for f in self.decoder.feed(data)]
        assert self.decoder.frames_bad == 0
        self.received += msgs
        return msgs

    def events(self) -> list[ErrorEvent]:
        return [m for m in self.received if isinstance(m, ErrorEvent)]


def centre(core: LinarmSimCore) -> float:
    return (core.x[0] + core.x[1]) / 2


def ready_host(mode: ControlMode = ControlMode.POS_REF_BY_TARGET_POS, patient: object = None,
               params: LinarmParams | None = None, at: float = 0.10) -> Host:
    """A homed controller in ON with the centre at `at`."""
    core = LinarmSimCore(params, patient, initial_centre=at, start_homed=True)  # type: ignore[arg-type]
    host = Host(core)
    host.ok("setCtrlMode", int(mode))
    host.ok("setCtrlState", int(ControlState.ON_CTRL_STATE))
    host.run(0.2)
    assert core.ctrl_state is ControlState.ON_CTRL_STATE and core.error_state is ErrorState.NO_ERROR
    return host


# ---------------------------------------------------------------------------------------------
# Trajectories
# ---------------------------------------------------------------------------------------------


def test_move_centre_trapezoidal() -> None:
    host = ready_host(at=0.10)
    core = host.core
    assert centre(core) == pytest.approx(0.10, abs=0.002)
    t0 = core.time
    host.ok("moveCentreTo", 0.40, 0.15, 0.15, 0.0, False)
    samples: list[tuple[float, float]] = []
    host.run(4.0, sample=samples)
    assert centre(core) == pytest.approx(0.40, abs=0.005)
    assert core.h == pytest.approx(0.40, abs=0.005)
    speeds = [(t - t0, v) for t, v in samples]
    assert max(v for _, v in speeds) <= 0.15 * 1.05
    # trapezoid: D = 0.3 m, ta = 1 s, cruise 1 s, T = 3 s
    def speed_at(tau: float) -> float:
        return min(speeds, key=lambda s: abs(s[0] - tau))[1]
    assert speed_at(0.5) == pytest.approx(0.075, abs=0.01)  # linear ramp
    assert speed_at(0.75) == pytest.approx(0.1125, abs=0.01)
    for tau in (1.2, 1.5, 1.8):
        assert speed_at(tau) == pytest.approx(0.15, abs=0.005)  # plateau
    assert speed_at(2.5) == pytest.approx(0.075, abs=0.01)
    assert abs(speed_at(3.3)) < 0.005
    assert core.error_state is ErrorState.NO_ERROR


def test_move_centre_cycloidal() -> None:
    host = ready_host(at=0.10)
    core = host.core
    host.ok("setTrajectoryType", 1)
    t0 = core.time
    host.ok("moveCentreTo", 0.40, 0.15, 0.15, 0.0, False)
    samples: list[tuple[float, float]] = []
    host.run(4.6, sample=samples)
    assert centre(core) == pytest.approx(0.40, abs=0.005)
    speeds = [(t - t0, v) for t, v in samples]
    assert max(v for _, v in speeds) <= 0.15 * 1.05

    def speed_at(tau: float) -> float:
        return min(speeds, key=lambda s: abs(s[0] - tau))[1]
    # cycloid: T = max(2D/v, sqrt(2 pi D/a)) = 4 s, v(t) = D/T (1 - cos(2 pi t/T))
    assert speed_at(0.25) == pytest.approx(0.075 * (1 - 0.92388), abs=0.004)  # starts gently
    assert speed_at(1.0) == pytest.approx(0.075, abs=0.006)  # a trapezoid would be at 0.15 here
    assert speed_at(2.0) == pytest.approx(0.15, abs=0.006)
    assert speed_at(3.0) == pytest.approx(0.075, abs=0.006)


def test_plan_trajectory_exec_time_and_refusals() -> None:
    tr = plan_trajectory(0.1, 0.4, 0.5, 2.0, 3.0, 0)  # type: ignore[arg-type]
    tr.t0 = 0.0
    assert tr.duration == 3.0
    assert tr.sample(1.5)[1] == pytest.approx(1.5 * 0.3 / 3.0)
    assert tr.sample(3.0)[0] == pytest.approx(0.4)
    with pytest.raises(TrajectoryError):
        plan_trajectory(0.1, 0.4, 0.1, 2.0, 1.0, 0)  # type: ignore[arg-type]  # needs 0.45 m/s
    short = plan_trajectory(0.0, 0.01, 0.5, 1.0, 0.0, 0)  # type: ignore[arg-type]  # triangular
    assert short.duration == pytest.approx(2 * (0.01 / 1.0) ** 0.5)


def test_out_of_limit_target_is_refused() -> None:
    host = ready_host(at=0.20)
    reply = host.send("moveCentreTo", 0.46, 0.15, 0.15, 0.0, False)
    assert isinstance(reply, ErrorReply) and reply.code is ReplyError.OUT_OF_RANGE
    assert reply.command == "moveCentreTo"
    host.run(0.5)
    assert centre(host.core) == pytest.approx(0.20, abs=0.002)
    # too fast for the controller's limit, and the wrong mode
    assert host.send("moveCentreTo", 0.30, 0.9, 0.15, 0.0, False).code is ReplyError.OUT_OF_RANGE  # type: ignore[union-attr]
    host.ok("setCtrlMode", int(ControlMode.POS_REF_BY_VEL))
    assert host.send("moveCentreTo", 0.30, 0.1, 0.1, 0.0, False).code is ReplyError.WRONG_MODE  # type: ignore[union-attr]


def test_commands_refused_before_homing() -> None:
    host = Host(LinarmSimCore())
    reply = host.send("setCtrlState", int(ControlState.ON_CTRL_STATE))
    assert isinstance(reply, ErrorReply) and reply.code is ReplyError.NOT_HOMED
    assert host.ok("getIsInitialized").values == {"initialized": False}


# ---------------------------------------------------------------------------------------------
# Homing
# ---------------------------------------------------------------------------------------------


def test_homing_uses_the_endstrokes() -> None:
    core = LinarmSimCore(initial_centre=0.20)
    host = Host(core)
    assert host.drain()[0] == Identify(0, 1, "LINarm2", "sim-1.0")  # boot message
    assert core.vsa_state().equilibrium_pos == pytest.approx(0.0)  # encoders count from power-up
    host.ok("goToHome")
    t0 = core.time
    assert core.ctrl_state is ControlState.HOME_CTRL_STATE
    seen: list[HomeState] = []
    for _ in range(3000):
        host.run(0.01)
        if not seen or seen[-1] is not core.home_state:
            seen.append(core.home_state)
        if core.home_state is HomeState.HOME_DONE:
            break
    assert seen == [HomeState.HOME_SEEK_MIN, HomeState.HOME_SEEK_MAX, HomeState.HOME_MOVE_TO_HOME,
                    HomeState.HOME_DONE]
    assert core.time - t0 <= 5.0  # every exercise starts with a homing: keep it short
    assert core.endstroke_closures == [1, 1]  # each switch closed once
    assert core.error_state is ErrorState.NO_ERROR
    vsa = core.vsa_state()
    assert vsa.equilibrium_pos == pytest.approx(0.25, abs=0.002) == pytest.approx(centre(core), abs=0.001)
    assert vsa.delta == pytest.approx(0.02, abs=0.002)  # pretension: carriages 0.10 m apart
    assert core.x[1] - core.x[0] == pytest.approx(0.10, abs=0.002)
    assert vsa.handle_pos == pytest.approx(core.h, abs=0.001)
    assert host.ok("getIsInitialized").values == {"initialized": True}
    host.ok("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS))
    host.ok("setCtrlState", int(ControlState.ON_CTRL_STATE))


def test_homing_refuses_motion_while_busy() -> None:
    host = Host(LinarmSimCore())
    host.ok("setCtrlState", int(ControlState.HOME_CTRL_STATE))
    host.run(0.2)
    assert host.send("setCtrlState", int(ControlState.ON_CTRL_STATE)).code is ReplyError.BUSY  # type: ignore[union-attr]
    assert host.send("setCtrlMode", 1).code is ReplyError.BUSY  # type: ignore[union-attr]
    host.ok("setCtrlState", int(ControlState.IDLE_CTRL_STATE))  # IDLE is always allowed
    assert host.core.ctrl_state is ControlState.IDLE_CTRL_STATE and host.core.current == [0.0, 0.0]


# ---------------------------------------------------------------------------------------------
# Watchdog and errors
# ---------------------------------------------------------------------------------------------


def test_host_silence_trips_the_watchdog() -> None:
    host = ready_host(at=0.20)
    core = host.core
    core.handle_host_bytes(encode_command("heartbeat", 1))
    host.run(0.2, heartbeat=False)  # 200 ms: still fine
    assert core.ctrl_state is ControlState.ON_CTRL_STATE
    host.run(0.1, heartbeat=False)  # 300 ms of silence
    assert core.ctrl_state is ControlState.IDLE_CTRL_STATE
    assert core.error_state is ErrorState.WATCHDOG
    assert core.current == [0.0, 0.0]
    (event,) = host.events()
    assert event.error_state is ErrorState.WATCHDOG and event.control_state is ControlState.IDLE_CTRL_STATE
    assert host.send("setCtrlState", 2).code is ReplyError.IN_ERROR  # type: ignore[union-attr]
    host.ok("resetError")
    assert core.error_state is ErrorState.NO_ERROR
    host.ok("setCtrlState", 2)


def _trip(host: Host, expected: ErrorState, seconds: float = 3.0) -> None:
    for _ in range(int(seconds / 0.05)):
        host.run(0.05)
        if host.core.error_state is not ErrorState.NO_ERROR:
            break
    core = host.core
    assert core.error_state is expected
    assert core.ctrl_state is ControlState.IDLE_CTRL_STATE and core.current == [0.0, 0.0]
    assert [e.error_state for e in host.events()] == [expected]
    host.ok("resetError")
    assert core.error_state is ErrorState.NO_ERROR
    host.run(0.1)
    assert core.error_state is ErrorState.NO_ERROR  # stays cleared while IDLE


def test_tracking_error() -> None:
    host = ready_host(at=0.20)
    host.ok("setMaxTrackingError", 1e-5)
    host.ok("moveCentreTo", 0.30, 0.2, 1.0, 0.0, False)
    _trip(host, ErrorState.TRACKING_ERROR)


def test_endstroke_hit() -> None:
    host = ready_host(at=0.40)
    host.ok("setPosLimit", 0.0, 0.5)
    host.ok("moveCentreTo", 0.48, 0.1, 0.5, 0.0, False)  # motor 1 would go to 0.53 m
    _trip(host, ErrorState.ENDSTROKE_HIT)
    assert host.core.x[1] >= host.core.p.switch_max


def test_endstrokes_can_be_disabled() -> None:
    host = ready_host(at=0.40)
    host.ok("disableEndstrokes", True)
    host.ok("setPosLimit", 0.0, 0.5)
    host.ok("setMaxTrackingError", 0.05)
    host.ok("moveCentreTo", 0.445, 0.1, 0.5, 0.0, False)  # motor 1 at 0.495 m: on the switch
    host.run(1.5)
    assert host.core.error_state is ErrorState.NO_ERROR and host.core.x[1] >= host.core.p.switch_max - 1e-3


def test_over_force() -> None:
    host = ready_host(at=0.20, patient=StepForce(10.0, ramp=0.5))
    host.ok("setMaxForce", 5.0)
    _trip(host, ErrorState.OVER_FORCE)


def test_over_current() -> None:
    host = ready_host(at=0.20)
    host.ok("setMaxCurrent", 0.05)  # overcoming the carriages' 8 N friction needs 0.4 A
    host.ok("moveCentreTo", 0.30, 0.1, 0.5, 0.0, False)
    _trip(host, ErrorState.OVER_CURRENT)


def test_over_velocity() -> None:
    host = ready_host(at=0.20)
    host.ok("setMaxVelocity", 0.02)
    host.core.patient = StepForce(20.0, start=host.core.time)  # a sudden push
    _trip(host, ErrorState.OVER_VELOCITY)


def test_position_limit() -> None:
    host = ready_host(at=0.42)  # at the upper position limit
    host.core.patient = StepForce(50.0, start=host.core.time, ramp=2.0)  # slowly out to ~0.445 m
    _trip(host, ErrorState.POSITION_LIMIT, seconds=4.0)


def test_homing_failed_when_a_switch_never_closes() -> None:
    core = LinarmSimCore(LinarmParams(switch_min=-0.01), initial_centre=0.20)
    host = Host(core)
    host.ok("setHomeParameter", 0.25, 0.02, 0.2)
    host.ok("setMaxCurrent", 6.0)  # else the stalled carriage trips OVER_CURRENT first
    host.ok("goToHome")
    _trip(host, ErrorState.HOMING_FAILED, seconds=8.0)
    assert not core.initialized


# ---------------------------------------------------------------------------------------------
# Modes
# ---------------------------------------------------------------------------------------------


def test_velocity_mode_integrates_and_clamps_at_limits() -> None:
    host = ready_host(mode=ControlMode.POS_REF_BY_VEL, at=0.20)
    host.ok("setCentreVelocity", 0.05)
    host.run(1.0)
    assert centre(host.core) == pytest.approx(0.25, abs=0.003)
    host.run(4.0)
    assert host.core.centre_ref == pytest.approx(0.42)  # the position limit
    host.ok("setCentreVelocity", 0.0)
    host.ok("setDeltaVelocity", 0.02)
    host.run(1.0)
    assert host.core.vsa_state().delta == pytest.approx(0.04, abs=0.003)
    assert host.send("setCentreVelocity", 2.0).code is ReplyError.OUT_OF_RANGE  # type: ignore[union-attr]


def test_admittance_moves_with_the_patient() -> None:
    host = ready_host(mode=ControlMode.POS_REF_BY_ADMITTANCE, at=0.20)
    host.ok("setAdmittanceParameter", 0.005)
    assert host.ok("getAdmittanceParameter").values["Ka"] == pytest.approx(0.005)
    host.core.patient = StepForce(10.0, start=host.core.time, ramp=0.2)
    start = centre(host.core)
    host.run(0.5)
    before = centre(host.core)
    host.run(1.0)
    assert centre(host.core) - before == pytest.approx(0.05, rel=0.1)  # v = Ka * F
    assert centre(host.core) > start
    assert host.core.vsa_state().force == pytest.approx(10.0, rel=0.1)


def test_assistance_pulls_towards_the_target() -> None:
    host = ready_host(mode=ControlMode.POS_REF_BY_ASSISTANCE, at=0.20)
    host.ok("setAssistanceParameter", 200.0)
    host.ok("setAssistanceTargetPos", 0.30)
    assert host.ok("getAssistanceTargetPos").values["Apos"] == pytest.approx(0.30)
    host.run(6.0)
    assert centre(host.core) == pytest.approx(0.30, abs=0.005)
    assert host.send("setAssistanceTargetPos", 0.49).code is ReplyError.OUT_OF_RANGE  # type: ignore[union-attr]


def test_stiffness_follows_delta() -> None:
    host = ready_host(mode=ControlMode.POS_REF_BY_IMPEDANCE, at=0.20)
    k0 = host.core.vsa_state().stiffness
    host.ok("setStiffness", 2000.0, 0.05, 0.5, 0.0)
    host.run(1.5)
    vsa = host.core.vsa_state()
    assert vsa.stiffness == pytest.approx(2000.0, rel=0.02) and vsa.stiffness > k0
    assert vsa.delta > 0.02
    # the handle feels that stiffness: a 10 N push displaces it by about F/k
    host.core.patient = StepForce(10.0, start=host.core.time, ramp=0.3)
    host.run(1.0)
    assert host.core.h - centre(host.core) == pytest.approx(10.0 / 2000.0, rel=0.15)
    assert host.send("setStiffness", 99999.0, 0.05, 0.5, 0.0).code is ReplyError.OUT_OF_RANGE  # type: ignore[union-attr]


def test_delta_is_the_spring_pretension() -> None:
    """The seed's exercise (D2.2 Fig. 18) calls moveDeltaTo(0.010, 0.150, 0.150, 0, False) unmodified."""
    host = ready_host(at=0.20)
    core = host.core
    assert core.vsa_state().delta == pytest.approx(0.02, abs=0.002)
    host.ok("moveDeltaTo", 0.010, 0.150, 0.150, 0.0, False)
    host.run(1.0)
    vsa = core.vsa_state()
    assert vsa.delta == pytest.approx(0.010, abs=0.001)
    assert core.x[1] - core.x[0] == pytest.approx(0.010 + 2 * core.p.spring_free_length, abs=0.001)
    assert vsa.stiffness == pytest.approx(450.0, rel=0.05)  # the softest setting
    for bad in (0.005, 0.10):  # below the free length / a carriage distance, not a pretension
        assert host.send("moveDeltaTo", bad, 0.1, 0.1, 0.0, False).code is ReplyError.OUT_OF_RANGE  # type: ignore[union-attr]
    assert host.send("setHomeParameter", 0.25, 0.10, 0.2).code is ReplyError.OUT_OF_RANGE  # type: ignore[union-attr]


def test_trigger_needs_a_trigger_mode_and_waits_for_it() -> None:
    host = ready_host(at=0.20)
    assert host.send("moveCentreTo", 0.30, 0.1, 0.5, 0.0, True).code is ReplyError.NOT_SUPPORTED  # type: ignore[union-attr]
    host.ok("setTriggerMode", 1)
    host.ok("setTriggerParameter", 3.0)
    host.ok("moveCentreTo", 0.30, 0.1, 0.5, 0.0, True)
    host.run(1.0)
    assert centre(host.core) == pytest.approx(0.20, abs=0.002)  # armed, waiting
    host.core.patient = StepForce(5.0, start=host.core.time)
    host.run(3.0)
    assert centre(host.core) == pytest.approx(0.30, abs=0.01)


def test_demo_mode_with_virtual_vsa() -> None:
    core = LinarmSimCore(initial_centre=0.20)
    host = Host(core)
    host.ok("setDemo", True)
    host.ok("goToHome")
    host.run(6.0)
    assert core.home_state is HomeState.HOME_DONE and core.initialized
    host.ok("enableVirtualVsa", True)
    host.ok("setVirtualVsaSpringDisplacement", 0.01)
    host.ok("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS))
    host.ok("setCtrlState", 2)
    host.run(0.1)
    vsa = core.vsa_state()
    assert vsa.handle_pos == pytest.approx(0.26, abs=1e-6)
    assert vsa.force == pytest.approx(vsa.stiffness * 0.01)
    assert host.send("setDemo", False).code is ReplyError.WRONG_STATE  # type: ignore[union-attr]


# ---------------------------------------------------------------------------------------------
# Link behaviour
# ---------------------------------------------------------------------------------------------


def test_the_next_frame_is_due_when_the_core_says() -> None:
    """The simulator's thread sleeps until ``next_output_time`` instead of waking every tick: nothing may come out
    before it, and the frame comes out at it (a frame later than its due time would be late on the wire)."""
    host = ready_host(at=0.20)
    assert host.core.next_output_time() is None  # no stream: nothing scheduled
    host.ok("startDataStream", 0.005)
    host.drain()
    for _ in range(40):
        due = host.core.next_output_time()
        assert due is not None and due > host.core.time - 1e-9
        before = host.core.stream_bytes(due - 0.0005)
        assert not [m for m in host._decode(before) if isinstance(m, VsaState)], (due, host.core.time)
        frames = [m for m in host._decode(host.core.stream_bytes(due)) if isinstance(m, VsaState)]
        assert len(frames) == 1 and frames[0].t_us == round(due * 1e6), (due, frames)
        host.core.handle_host_bytes(encode_command("heartbeat", next_seq(host.seq)), due)


def test_state_stream_rate_and_content() -> None:
    host = ready_host(at=0.20)
    host.received.clear()
    host.ok("startDataStream", 0.005)
    host.run(1.0)
    vsa = [m for m in host.received if isinstance(m, VsaState)]
    motors = [m for m in host.received if isinstance(m, MotorState)]
    states = [m for m in host.received if isinstance(m, LinarmState)]
    assert 199 <= len(vsa) <= 201
    assert len(motors) == 2 * len(vsa) and {m.index for m in motors} == {0, 1}
    assert 20 <= len(states) <= 22  # every 10th tick
    assert states[-1].control_state is ControlState.ON_CTRL_STATE and states[-1].initialized
    stamps = [m.t_us for m in vsa]
    assert all(b - a == 5000 for a, b in itertools.pairwise(stamps))
    assert vsa[-1].equilibrium_pos == pytest.approx(0.20, abs=0.002)
    host.ok("stopDataStream")
    host.received.clear()
    host.run(0.2)
    assert not [m for m in host.received if isinstance(m, VsaState)]
    reply = host.core.handle_host_bytes(encode_command("getState", 99))
    kinds = [type(decode_controller_frame(f)) for f in CmdMessengerDecoder().feed(reply)]
    assert kinds == [Ack, LinarmState, MotorState, MotorState, VsaState]


def test_garbage_runs_as_harmless_command_zero() -> None:
    host = ready_host(at=0.20)
    core = host.core
    before = core.linarm_state()
    replies = [decode_controller_frame(f) for f in CmdMessengerDecoder().feed(core.handle_host_bytes(b"\x07zz;"))]
    assert replies == [ErrorReply(0, 0, "identify", ReplyError.BAD_ARGUMENT, "missing or bad sequence number")]
    # an overlong frame: its tail is dispatched as cmd 0 on 4.2.0, again harmlessly
    data = b"9,1," + b"A" * 70 + b";"
    replies = [decode_controller_frame(f) for f in CmdMessengerDecoder().feed(core.handle_host_bytes(data))]
    assert all(isinstance(r, ErrorReply) and r.cmd_id == 0 for r in replies) and replies
    host.run(0.2)
    after = core.linarm_state()
    assert (after.control_state, after.error_state) == (before.control_state, before.error_state)
    # identify answers with the caller's seq; unknown ids get UNKNOWN_COMMAND
    assert isinstance(host.send("identify"), Identify)
    reply = [decode_controller_frame(f) for f in CmdMessengerDecoder().feed(core.handle_host_bytes(b"45,7;"))]
    assert reply == [ErrorReply(7, 45, None, ReplyError.UNKNOWN_COMMAND, "no command with id 45")]


def test_split_host_bytes_are_reassembled() -> None:
    host = ready_host(at=0.20)
    data = encode_command("getAdmittanceParameter", 1234)
    out = b"".join(host.core.handle_host_bytes(data[i:i + 1]) for i in range(len(data)))
    (ack,) = [decode_controller_frame(f) for f in CmdMessengerDecoder().feed(out)]
    assert isinstance(ack, Ack) and ack.seq == 1234


def test_runs_much_faster_than_real_time() -> None:
    host = ready_host(at=0.10)
    host.ok("startDataStream", 0.005)
    host.ok("moveCentreTo", 0.40, 0.15, 0.15, 0.0, False)
    start = time.perf_counter()
    host.run(2.0)
    elapsed = time.perf_counter() - start
    assert elapsed < 1.0, f"2 s of simulated time took {elapsed:.2f} s"


def test_service_mode_is_only_chosen_at_boot() -> None:
    from app.wire.linarm_protocol import ReplyError

    for service in (False, True):
        core = LinarmSimCore(start_homed=True, service_mode=service)
        assert core.firmware_version.endswith("+service") is service
        host = Host(core)
        host.ok("lockEnvelope")
        if service:
            host.ok("setMotorOffset", 0, 0.0)
            host.ok("disableEndstrokes", True)
        else:
            for name, args in (("setMotorOffset", (0, 0.0)), ("disableEndstrokes", (True,))):
                reply = host.send(name, *args)
                assert isinstance(reply, ErrorReply) and reply.code is ReplyError.LOCKED, reply
        reply = host.send("setMaxVelocity", 0.9)  # the limits lock in both
        assert isinstance(reply, ErrorReply) and reply.code is ReplyError.LOCKED, reply
