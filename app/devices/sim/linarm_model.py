"""Pure simulation core of the LINarm2 and its DUE controller firmware (no transport, no threads).

``LinarmSimCore`` takes host bytes and returns controller bytes; a thin wrapper puts it on the far
side of a pty. Host bytes go through the CmdMessenger 4.2.0 receiver model, so the core shows the
real library's quirks (62-byte buffer, garbage as command 0, ...). The C++ firmware mirrors the
controller part (FSM, modes, trajectories, supervision); the physics stands in for the robot.

Mechanics (SI units, x along the rail, + to the right):

* Two motor carriages at x0 < x1, each a mass with viscous + Coulomb friction driven by a motor
  force ``KF * i`` (current-controlled drive, |i| <= ``current_hw_limit``).
* The handle at h between them, tied to each carriage by a tension spring of free length L:
  elongations eL = (h - x0) - L and eR = (x1 - h) - L, tension f(e) = a*e + b*e**3 for e > 0
  (slack otherwise). The force on the handle is f(eR) - f(eL); at rest h = centre = (x0 + x1)/2.
* delta (on the wire and in the state stream) is the springs' pretension displacement:
  delta = (x1 - x0) - 2*L, the carriage distance minus both free lengths. Around the centre each
  spring is stretched by e0 = delta/2, so the VSA stiffness is k(delta) = 2*(a + 3*b*(delta/2)**2):
  it rises with the pretension. With a = 150 N/m, b = 1e6 N/m^3, L = 0.04 m and delta in
  0.01..0.06 m (carriage distance 0.09..0.14 m), k spans 450..5700 N/m (900 N/m at the default 0.02 m).
* Handle mass and viscous damping, rubber bumpers between handle and carriages, hard stops at the
  rail ends (0.0..0.50 m) and endstroke switches closing at 0.005 m (motor 0) and 0.495 m (motor 1).
* An optional patient object adds ``handle_force(t, handle_pos, handle_vel)`` newtons on the handle.

Controller (1 kHz): FSM IDLE/HOME/ON, homing on the endstroke switches, the five control modes,
trapezoidal/cycloidal trajectories, position limits, error supervision with latching error states,
the host-silence watchdog and the state stream.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

from app.wire.cmdmessenger import ArduinoReceiver
from app.wire.linarm_constants import K
from app.wire.linarm_protocol import (
    DEFAULT_STREAM_PERIOD,
    LINARM_STATE_DIVIDER,
    WATCHDOG_TIMEOUT,
    CommandRejected,
    ControlMode,
    ControlState,
    ErrorEvent,
    ErrorState,
    HomeState,
    HostCommand,
    LinarmState,
    MotorState,
    ReplyError,
    TrajectoryType,
    TriggerMode,
    VsaState,
    encode_ack,
    encode_error_event,
    encode_identify,
    encode_linarm_state,
    encode_motor_state,
    encode_rejection,
    encode_vsa_state,
    read_host_message,
)

FIRMWARE_VERSION = "sim-1.0"
SERVICE_SUFFIX = "+service"  # appended to the IDENTIFY's firmware version when booted in service mode
OUTBOX_LIMIT = 256 * 1024  # bytes kept for a host that does not read
# The controller's constants: one table (app/wire/linarm_constants.py) for this model, the firmware and the panel.
DT = K["DT"]  # s, the controller's loop period
SEEK_LEAD = K["SEEK_LEAD"]  # m, how far the homing reference may lead a carriage
HOMING_VELOCITY = K["HOMING_VELOCITY"]  # m/s, default endstroke seek speed
HOME_SETTLE = K["HOME_SETTLE_TICKS"] * DT  # s at rest after the move to home, before the handle encoder is referenced
OVER_CURRENT_TIME = K["OVER_CURRENT_TICKS"] * DT  # s above maxCurrent before OVER_CURRENT
POSITION_LIMIT_MARGIN = K["POSITION_LIMIT_MARGIN"]  # m outside [minPos, maxPos]: POSITION_LIMIT
OVER_VELOCITY_FACTOR = K["OVER_VELOCITY_FACTOR"]  # x maxVelocity: OVER_VELOCITY
ENVELOPE_VELOCITY_FACTOR = K["ENVELOPE_VELOCITY_FACTOR"]  # x the locked maxVelocity: ENVELOPE_BREACH
ENVELOPE_POSITION_MARGIN = K["ENVELOPE_POSITION_MARGIN"]  # m outside the locked range: ENVELOPE_BREACH


class PatientForce(Protocol):
    def handle_force(self, t: float, handle_pos: float, handle_vel: float) -> float: ...


class NoPatient:
    def handle_force(self, t: float, handle_pos: float, handle_vel: float) -> float:
        return 0.0


@dataclass(frozen=True)
class LinarmParams:
    """Physical constants of the simulated LINarm2."""

    rail_min: float = K["RAIL_MIN"]  # m
    rail_max: float = K["RAIL_MAX"]  # m
    switch_min: float = K["SWITCH_MIN_POS"]  # m, motor 0's endstroke closes at or below this
    switch_max: float = K["SWITCH_MAX_POS"]  # m, motor 1's endstroke closes at or above this
    carriage_mass: float = K["CARRIAGE_MASS"]  # kg
    carriage_viscous: float = K["CARRIAGE_VISCOUS"]  # N s/m
    carriage_coulomb: float = K["CARRIAGE_COULOMB"]  # N (lead screw: holds delta when the motors are off)
    handle_mass: float = K["HANDLE_MASS"]  # kg
    handle_damping: float = K["HANDLE_DAMPING"]  # N s/m
    spring_a: float = K["SPRING_A"]  # N/m
    spring_b: float = K["SPRING_B"]  # N/m^3
    spring_free_length: float = K["SPRING_FREE_LENGTH"]  # m
    delta_min: float = K["DELTA_MIN"]  # m, pretension (carriage distance 0.09 m)
    delta_max: float = K["DELTA_MAX"]  # m, pretension (carriage distance 0.14 m)
    bumper: float = K["BUMPER"]  # m, closest handle-carriage distance before contact
    contact_stiffness: float = K["CONTACT_STIFFNESS"]  # N/m
    contact_damping: float = K["CONTACT_DAMPING"]  # N s/m
    force_constant: float = K["FORCE_CONSTANT"]  # N/A
    current_hw_limit: float = K["CURRENT_HW_LIMIT"]  # A
    encoder_resolution: float = K["ENCODER_RESOLUTION"]  # m/count

    def spring_tension(self, elongation: float) -> float:
        if elongation <= 0.0:
            return 0.0
        return self.spring_a * elongation + self.spring_b * elongation**3

    def span(self, delta: float) -> float:
        """Carriage distance x1 - x0 for a pretension delta."""
        return delta + 2.0 * self.spring_free_length

    def delta_of(self, x0: float, x1: float) -> float:
        """Pretension delta of carriages at x0 < x1."""
        return (x1 - x0) - 2.0 * self.spring_free_length

    def stiffness(self, delta: float) -> float:
        """k(delta) of the spring pair around the centre; delta is the pretension displacement."""
        e0 = delta / 2.0
        if e0 <= 0.0:
            return 0.0
        return 2.0 * (self.spring_a + 3.0 * self.spring_b * e0 * e0)

    def delta_for_stiffness(self, k: float) -> float:
        e0 = math.sqrt(max(0.0, (k / 2.0 - self.spring_a) / (3.0 * self.spring_b)))
        return 2.0 * e0


# ---------------------------------------------------------------------------------------------
# Trajectories
# ---------------------------------------------------------------------------------------------


class TrajectoryError(ValueError):
    pass


@dataclass
class Trajectory:
    start: float
    target: float
    duration: float
    kind: TrajectoryType
    t_acc: float = 0.0  # trapezoid: acceleration time
    v_peak: float = 0.0  # trapezoid: cruise speed (signed by direction below)
    t0: float | None = None  # None while armed on a trigger

    def sample(self, t: float) -> tuple[float, float, bool]:
        """(position, velocity, finished) at controller time t."""
        if self.t0 is None:
            return self.start, 0.0, False
        tau = t - self.t0
        d = self.target - self.start
        if tau >= self.duration or self.duration <= 0.0:
            return self.target, 0.0, True
        tau = max(tau, 0.0)
        sign = 1.0 if d >= 0 else -1.0
        if self.kind is TrajectoryType.CYCLOIDAL:
            r = tau / self.duration
            s = d * (r - math.sin(2 * math.pi * r) / (2 * math.pi))
            v = d / self.duration * (1 - math.cos(2 * math.pi * r))
            return self.start + s, v, False
        a = self.v_peak / self.t_acc if self.t_acc > 0 else 0.0
        if tau < self.t_acc:
            s, v = 0.5 * a * tau * tau, a * tau
        elif tau < self.duration - self.t_acc:
            s, v = 0.5 * a * self.t_acc**2 + self.v_peak * (tau - self.t_acc), self.v_peak
        else:
            rem = self.duration - tau
            s, v = abs(d) - 0.5 * a * rem * rem, a * rem
        return self.start + sign * s, sign * v, False


def plan_trajectory(start: float, target: float, max_vel: float, max_acc: float, exec_time: float,
                    kind: TrajectoryType) -> Trajectory:
    """Trapezoidal or cycloidal profile from (max_vel, max_acc), or of duration exec_time (> 0).

    With exec_time the trapezoid splits the time in thirds (v = 1.5 D/T, a = 4.5 D/T^2) and the
    cycloid peaks at v = 2 D/T, a = 2 pi D/T^2; both must stay within max_vel and max_acc.
    """
    dist = abs(target - start)
    if max_vel <= 0.0 or max_acc <= 0.0:
        raise TrajectoryError("maxVel and maxAcc must be positive")
    if dist == 0.0:
        return Trajectory(start, target, 0.0, kind)
    if exec_time > 0.0:
        T = exec_time
        if kind is TrajectoryType.CYCLOIDAL:
            v_pk, a_pk = 2 * dist / T, 2 * math.pi * dist / T**2
        else:
            v_pk, a_pk = 1.5 * dist / T, 4.5 * dist / T**2
        if v_pk > max_vel * (1 + 1e-6) or a_pk > max_acc * (1 + 1e-6):
            raise TrajectoryError(f"execTime {T:g} s too short: needs {v_pk:.3g} m/s and {a_pk:.3g} m/s^2")
        if kind is TrajectoryType.CYCLOIDAL:
            return Trajectory(start, target, T, kind)
        return Trajectory(start, target, T, kind, t_acc=T / 3, v_peak=v_pk)
    if kind is TrajectoryType.CYCLOIDAL:
        T = max(2 * dist / max_vel, math.sqrt(2 * math.pi * dist / max_acc))
        return Trajectory(start, target, T, kind)
    if dist >= max_vel**2 / max_acc:
        t_acc = max_vel / max_acc
        return Trajectory(start, target, 2 * t_acc + (dist - max_vel * t_acc) / max_vel, kind, t_acc, max_vel)
    v_pk = math.sqrt(dist * max_acc)
    return Trajectory(start, target, 2 * v_pk / max_acc, kind, v_pk / max_acc, v_pk)


# ---------------------------------------------------------------------------------------------
# The core
# ---------------------------------------------------------------------------------------------


class _Refuse(Exception):
    def __init__(self, code: ReplyError, message: str = "") -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass
class _Pid:
    kp: float = K["PID_KP"]  # N/m
    ki: float = K["PID_KI"]  # N/(m s)
    kd: float = K["PID_KD"]  # N s/m
    integral: float = 0.0


@dataclass(frozen=True)
class Envelope:
    """The limits frozen by lockEnvelope: setters may narrow inside it until restart, never widen beyond it."""

    max_vel: float
    max_acc: float
    max_force: float
    max_current: float
    max_tracking_error: float
    pos_min: float
    pos_max: float


class LinarmSimCore:
    """LINarm2 + controller firmware. Time only moves with ``step``/``advance_to`` (1 kHz ticks)."""

    def __init__(self, params: LinarmParams | None = None, patient: PatientForce | None = None, *,
                 initial_centre: float = 0.20, initial_delta: float = 0.02, start_homed: bool = False,
                 firmware_version: str = FIRMWARE_VERSION, service_mode: bool = False) -> None:
        self.p = params or LinarmParams()
        self.patient: PatientForce = patient or NoPatient()
        # Booted with the service jumper fitted: calibration, endstrokes and PID gains stay open after the lock.
        self.service_mode = service_mode
        self.firmware_version = firmware_version + (SERVICE_SUFFIX if service_mode else "")
        self.receiver = ArduinoReceiver()
        self._ticks = 0
        self._clock = 0.0
        self._outbox = bytearray()
        # true mechanical state
        span = self.p.span(initial_delta)
        self.x = [initial_centre - span / 2, initial_centre + span / 2]
        self.v = [0.0, 0.0]
        self.h = initial_centre
        self.vh = 0.0
        self.current = [0.0, 0.0]
        self.f_ext = 0.0
        # sensors: incremental encoders count from power-up until homing references them
        self._x_power = list(self.x)
        self._h_power = self.h
        self.motor_ratio = [self.p.encoder_resolution] * 2
        self.motor_offset = [0.0, 0.0]
        self.mobile_ratio = self.p.encoder_resolution
        self.mobile_offset = 0.0
        # controller state
        self.ctrl_state = ControlState.IDLE_CTRL_STATE
        self.ctrl_mode = ControlMode.POS_REF_BY_VEL
        self.home_state = HomeState.HOME_NOT_DONE
        self.error_state = ErrorState.NO_ERROR
        self.trigger_mode = TriggerMode.NO_TRIGGER
        self.trigger_param = 0.0
        self.trajectory_type = TrajectoryType.TRAPEZOIDAL
        self.initialized = False
        self.demo = False
        self.virtual_vsa = False
        self.virtual_disp = 0.0
        self.endstrokes_disabled = False
        # limits and parameters (setters in the protocol)
        self.pos_min, self.pos_max = K["POS_MIN"], K["POS_MAX"]
        self.max_tracking_error = K["MAX_TRACKING_ERROR"]
        self.max_force = K["MAX_FORCE"]
        self.max_current = K["MAX_CURRENT"]
        self.max_acc = K["MAX_ACCELERATION"]
        self.max_vel = K["MAX_VELOCITY"]
        # 0.2 m/s seek: a full homing takes ~4 s (every exercise starts with one)
        self.home_centre, self.home_delta, self.homing_velocity = K["HOME_CENTRE"], K["HOME_DELTA"], HOMING_VELOCITY
        self.ka = K["ADMITTANCE_KA"]  # m/(N s)
        self.kt = K["ASSISTANCE_KT"]  # N/m
        self.assist_target = K["ASSISTANCE_TARGET"]
        self.pid = [_Pid(), _Pid()]
        self.envelope: Envelope | None = None  # lockEnvelope: until restart
        # references
        self.centre_ref = initial_centre
        self.delta_ref = initial_delta
        self.centre_vel_ref = 0.0
        self.delta_vel_ref = 0.0
        self.centre_vel_cmd = 0.0
        self.delta_vel_cmd = 0.0
        self.centre_traj: Trajectory | None = None
        self.delta_traj: Trajectory | None = None
        self.motor_ref = [self.x[0], self.x[1]]
        self.motor_vel_ref = [0.0, 0.0]
        self._home_deadline = 0.0
        self._home_settle_until: float | None = None
        self._over_current_since: float | None = None
        # host link
        self._host_seen = False
        self._last_host_time = 0.0
        self._watchdog_fed_until = -1.0
        self.stream_enabled = False
        self.stream_period = DEFAULT_STREAM_PERIOD
        self._stream_start = 0
        self._stream_ticks = round(DEFAULT_STREAM_PERIOD / DT)
        self._stream_count = 0
        self._last_sent_linarm: tuple[Any, ...] | None = None
        self.endstroke_closures = [0, 0]  # rising edges of the min (motor 0) and max (motor 1) switches
        self._switch_closed = self.endstrokes_closed()
        self._meas = self._measure()
        if start_homed:
            self._reference_encoders()
            self.initialized = True
            self.home_state = HomeState.HOME_DONE
            self._meas = self._measure()
        self._outbox += encode_identify(0, self.firmware_version)  # the boot message

    # -- time -------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        return self._ticks * DT

    def step(self, dt: float) -> None:
        """Advance the simulation by dt seconds (in 1 ms ticks; fractions carry over)."""
        self.advance_to(self._clock + dt)

    def next_output_time(self) -> float | None:
        """The core time of the next stream frame (None while the stream is off): the simulator's thread sleeps
        until then instead of waking every tick (events of the ticks between go out with that frame, or on the
        next poll)."""
        if not self.stream_enabled:
            return None
        k = self._ticks + 1
        late = (k - self._stream_start) % self._stream_ticks
        if late:
            k += self._stream_ticks - late
        return k * DT

    def advance_to(self, t: float) -> None:
        if t > self._clock:
            self._clock = t
        while (self._ticks + 1) * DT <= self._clock + 1e-9:
            self._tick()

    # -- transport-facing API ---------------------------------------------------------------
    def handle_host_bytes(self, data: bytes, t: float | None = None) -> bytes:
        """Bytes from the host, arriving at core time t (the core first catches up to t).
        Returns the immediate replies; asynchronous frames come out of ``stream_bytes``."""
        if t is not None:
            if data and self._host_seen:
                # These bytes were already in the link while the simulator thread was not running (a
                # starved thread catches up in one go): the real controller would have read them in
                # time. Catch up with the watchdog fed, so a host that was talking is never "silent".
                self._watchdog_fed_until = t
            self.advance_to(t)
        if data:
            self._host_seen = True
            self._last_host_time = self.time
        out = bytearray()
        for msg in self.receiver.feed(data):
            try:
                cmd = read_host_message(msg)
                out += self._execute(cmd)
            except CommandRejected as rejected:
                out += encode_rejection(rejected)
        return bytes(out)

    def stream_bytes(self, t: float | None = None) -> bytes:
        """Catch up to t and return everything queued since the last call (boot message, error
        events, state stream frames), in time order."""
        if t is not None:
            self.advance_to(t)
        out = bytes(self._outbox)
        self._outbox.clear()
        return out

    # -- snapshots (SI) -----------------------------------------------------------------------
    @property
    def t_us(self) -> int:
        return round(self.time * 1e6) & 0xFFFFFFFF

    def linarm_state(self) -> LinarmState:
        return LinarmState(self.t_us, self.ctrl_state, self.ctrl_mode, self.home_state, self.error_state,
                           self.trigger_mode, self.initialized, self.trajectory_type, self.demo,
                           self.virtual_vsa, self.endstrokes_disabled)

    def motor_state(self, index: int) -> MotorState:
        m = self._meas
        return MotorState(self.t_us, index, m["x"][index], m["v"][index], self.current[index],
                          self.motor_ref[index])

    def vsa_state(self) -> VsaState:
        m = self._meas
        centre = (m["x"][0] + m["x"][1]) / 2
        delta = self.p.delta_of(m["x"][0], m["x"][1])
        return VsaState(self.t_us, centre, delta, self.p.stiffness(delta), m["h"], m["vh"], m["force"])

    def endstrokes_closed(self) -> tuple[bool, bool]:
        return self.x[0] <= self.p.switch_min, self.x[1] >= self.p.switch_max

    @property
    def motors_on(self) -> bool:
        return self.ctrl_state is not ControlState.IDLE_CTRL_STATE

    # -- sensors --------------------------------------------------------------------------------
    def _measure(self) -> dict[str, Any]:
        p = self.p
        res = p.encoder_resolution
        if self.demo:
            x = list(self.x)
            h = self.h
        else:
            x = [round((self.x[i] - self._x_power[i]) / res) * self.motor_ratio[i] + self.motor_offset[i]
                 for i in (0, 1)]
            h = round((self.h - self._h_power) / res) * self.mobile_ratio + self.mobile_offset
        if self.demo:
            force = self.f_ext if not self.virtual_vsa else p.stiffness(p.delta_of(x[0], x[1])) * self.virtual_disp
        else:
            # the interaction force is read from the two spring elongations
            force = p.spring_tension(h - x[0] - p.spring_free_length) - p.spring_tension(
                x[1] - h - p.spring_free_length)
        return {"x": x, "v": list(self.v), "h": h, "vh": self.vh, "force": force}

    def _reference_encoders(self) -> None:
        """Make every measured position equal the true one (what a successful homing achieves)."""
        res = self.p.encoder_resolution
        for i in (0, 1):
            self.motor_offset[i] = self.x[i] - round((self.x[i] - self._x_power[i]) / res) * self.motor_ratio[i]
        self.mobile_offset = self.h - round((self.h - self._h_power) / res) * self.mobile_ratio

    # -- the 1 kHz loop -----------------------------------------------------------------------
    def _tick(self) -> None:
        t = self.time
        self.f_ext = float(self.patient.handle_force(t, self.h, self.vh))
        self._meas = m = self._measure()
        self._supervise(t, m)
        if self.motors_on:
            self._references(t, m)
            self._motor_loops(m)
        else:
            self.current = [0.0, 0.0]
            for pid in self.pid:
                pid.integral = 0.0
        if self.demo:
            self._kinematic_demo()
        else:
            self._physics(DT)
        closed = self.endstrokes_closed()
        for i in (0, 1):
            if closed[i] and not self._switch_closed[i]:
                self.endstroke_closures[i] += 1
        self._switch_closed = closed
        self._ticks += 1
        self._stream()

    def _physics(self, dt: float) -> None:
        p = self.p
        x0, x1 = self.x
        v0, v1 = self.v
        h, vh = self.h, self.vh
        f_left = p.spring_tension(h - x0 - p.spring_free_length)
        f_right = p.spring_tension(x1 - h - p.spring_free_length)
        # bumpers: handle against each carriage
        c_left = c_right = 0.0
        gap = h - x0 - p.bumper
        if gap < 0.0:
            c_left = max(0.0, -p.contact_stiffness * gap - p.contact_damping * (vh - v0))
        gap = x1 - h - p.bumper
        if gap < 0.0:
            c_right = max(0.0, -p.contact_stiffness * gap - p.contact_damping * (v1 - vh))
        force_h = f_right - f_left - p.handle_damping * vh + self.f_ext + c_left - c_right
        force_h += self._rail_stop(h, vh)
        force_0 = p.force_constant * self.current[0] + f_left - c_left + self._rail_stop(x0, v0)
        force_1 = p.force_constant * self.current[1] - f_right + c_right + self._rail_stop(x1, v1)
        self.vh = vh + force_h / p.handle_mass * dt
        self.h = h + self.vh * dt
        for i, force in ((0, force_0), (1, force_1)):
            v = self.v[i]
            if v == 0.0 and abs(force) <= p.carriage_coulomb:
                continue  # stiction
            friction = -p.carriage_viscous * v - math.copysign(p.carriage_coulomb, v if v != 0.0 else force)
            v_new = v + (force + friction) / p.carriage_mass * dt
            if v != 0.0 and v * v_new < 0.0 and abs(force) <= p.carriage_coulomb:
                v_new = 0.0  # friction stops, never reverses
            self.v[i] = v_new
            self.x[i] += v_new * dt

    def _rail_stop(self, pos: float, vel: float) -> float:
        p = self.p
        if pos < p.rail_min:
            return max(0.0, p.contact_stiffness * (p.rail_min - pos) - p.contact_damping * vel)
        if pos > p.rail_max:
            return min(0.0, -p.contact_stiffness * (pos - p.rail_max) - p.contact_damping * vel)
        return 0.0

    def _kinematic_demo(self) -> None:
        """Demo mode: no robot; the carriages follow their references and the handle sits where a
        quasi-static spring puts it (or at the virtual VSA displacement)."""
        p = self.p
        if self.motors_on:
            self.x = list(self.motor_ref)
            self.v = list(self.motor_vel_ref)
        else:
            self.v = [0.0, 0.0]
        centre = (self.x[0] + self.x[1]) / 2
        k = max(p.stiffness(p.delta_of(self.x[0], self.x[1])), 1.0)
        old = self.h
        self.h = centre + (self.virtual_disp if self.virtual_vsa else self.f_ext / k)
        self.vh = (self.h - old) / DT

    def _motor_loops(self, m: dict[str, Any]) -> None:
        p = self.p
        limit = p.current_hw_limit
        for i in (0, 1):
            pid = self.pid[i]
            err = self.motor_ref[i] - m["x"][i]
            u = pid.kp * err + pid.ki * pid.integral + pid.kd * (self.motor_vel_ref[i] - m["v"][i])
            amps = u / p.force_constant
            if abs(amps) < limit:
                pid.integral += err * DT  # no wind-up while saturated
            self.current[i] = max(-limit, min(limit, amps))

    # -- references ---------------------------------------------------------------------------
    def _set_motor_refs(self, centre: float, delta: float, centre_vel: float, delta_vel: float) -> None:
        self.centre_ref, self.delta_ref = centre, delta
        self.centre_vel_ref, self.delta_vel_ref = centre_vel, delta_vel
        half = self.p.span(delta) / 2
        self.motor_ref = [centre - half, centre + half]
        self.motor_vel_ref = [centre_vel - delta_vel / 2, centre_vel + delta_vel / 2]

    def _ramp(self, current_vel: float, wanted: float) -> float:
        """Velocity towards wanted within maxAcceleration and maxVelocity."""
        wanted = max(-self.max_vel, min(self.max_vel, wanted))
        step = self.max_acc * DT
        return current_vel + max(-step, min(step, wanted - current_vel))

    def _references(self, t: float, m: dict[str, Any]) -> None:
        if self.ctrl_state is ControlState.HOME_CTRL_STATE:
            self._homing(t, m)
            return
        self._check_triggers(m)
        centre, delta = self.centre_ref, self.delta_ref
        cv, dv = 0.0, 0.0
        mode = self.ctrl_mode
        if mode is ControlMode.POS_REF_BY_VEL:
            cv = self._ramp(self.centre_vel_ref, self.centre_vel_cmd)
            dv = self._ramp(self.delta_vel_ref, self.delta_vel_cmd)
            centre, cv = self._integrate_clamped(centre, cv, self.pos_min, self.pos_max)
            delta, dv = self._integrate_clamped(delta, dv, self.p.delta_min, self.p.delta_max)
        else:
            if mode in (ControlMode.POS_REF_BY_TARGET_POS, ControlMode.POS_REF_BY_IMPEDANCE):
                if self.centre_traj is not None:
                    centre, cv, done = self.centre_traj.sample(t)
                    if done:
                        self.centre_traj = None
            else:
                force = m["force"]
                if mode is ControlMode.POS_REF_BY_ASSISTANCE:
                    force += self.kt * (self.assist_target - m["h"])  # the virtual assistance spring
                cv = self._ramp(self.centre_vel_ref, self.ka * force)
                centre, cv = self._integrate_clamped(centre, cv, self.pos_min, self.pos_max)
            if self.delta_traj is not None:
                delta, dv, done = self.delta_traj.sample(t)
                if done:
                    self.delta_traj = None
        self._set_motor_refs(centre, delta, cv, dv)

    @staticmethod
    def _integrate_clamped(pos: float, vel: float, lo: float, hi: float) -> tuple[float, float]:
        pos += vel * DT
        if pos <= lo:
            return lo, max(vel, 0.0) if pos < lo else vel
        if pos >= hi:
            return hi, min(vel, 0.0) if pos > hi else vel
        return pos, vel

    def _check_triggers(self, m: dict[str, Any]) -> None:
        for traj in (self.centre_traj, self.delta_traj):
            if traj is None or traj.t0 is not None:
                continue
            if self.trigger_mode is TriggerMode.TRIGGER_ON_FORCE:
                fire = abs(m["force"]) >= self.trigger_param
            else:
                fire = abs(m["h"] - traj.target) <= self.trigger_param
            if fire:
                traj.t0 = self.time

    # -- homing ---------------------------------------------------------------------------------
    def _start_homing(self) -> None:
        m = self._meas
        self._motors_on_from(m)
        self.ctrl_state = ControlState.HOME_CTRL_STATE
        if self.initialized:
            self._start_move_home(m)
            return
        if self.demo:
            self._reference_encoders()
            self.initialized = True
            self._start_move_home(self._measure())
            return
        self.home_state = HomeState.HOME_SEEK_MIN
        self._home_deadline = self.time + self._seek_timeout()

    def _seek_timeout(self) -> float:
        return 1.5 * (self.p.rail_max - self.p.rail_min) / self._seek_velocity() + 1.0

    def _seek_velocity(self) -> float:
        # The locked envelope holds during homing too (a patient's narrower limits do not slow homing down).
        return min(self.homing_velocity, self.envelope.max_vel) if self.envelope else self.homing_velocity

    def _start_move_home(self, m: dict[str, Any]) -> None:
        self.home_state = HomeState.HOME_MOVE_TO_HOME
        centre = (m["x"][0] + m["x"][1]) / 2
        delta = self.p.delta_of(m["x"][0], m["x"][1])
        self._set_motor_refs(centre, delta, 0.0, 0.0)
        vel = max(self.homing_velocity, K["HOME_MOVE_MIN_VELOCITY"])
        if self.envelope is not None:
            vel = min(vel, self.envelope.max_vel)  # homing stays in the envelope
        self.centre_traj = plan_trajectory(centre, self.home_centre, vel, self.max_acc, 0.0, self.trajectory_type)
        self.delta_traj = plan_trajectory(delta, self.home_delta, vel, self.max_acc, 0.0, self.trajectory_type)
        self.centre_traj.t0 = self.delta_traj.t0 = self.time
        self._home_settle_until = None

    def _homing(self, t: float, m: dict[str, Any]) -> None:
        hs = self.home_state
        if hs in (HomeState.HOME_SEEK_MIN, HomeState.HOME_SEEK_MAX):
            if t > self._home_deadline:
                self._latch(ErrorState.HOMING_FAILED, f"endstroke not found in {self._seek_timeout():.0f} s")
                return
            direction = -1.0 if hs is HomeState.HOME_SEEK_MIN else 1.0
            vel = direction * self._seek_velocity()
            self.motor_vel_ref = [vel, vel]
            # the reference may lead the carriage by 5 mm at most: a stalled carriage is not a
            # tracking error here, it runs into the homing timeout instead
            self.motor_ref = [min(max(r + vel * DT, m["x"][i] - SEEK_LEAD), m["x"][i] + SEEK_LEAD)
                              for i, r in enumerate(self.motor_ref)]
            if hs is HomeState.HOME_SEEK_MIN and self.x[0] <= self.p.switch_min:
                self._reference_motor(0, self.p.switch_min)
                self.home_state = HomeState.HOME_SEEK_MAX
                self._home_deadline = t + self._seek_timeout()
            elif hs is HomeState.HOME_SEEK_MAX and self.x[1] >= self.p.switch_max:
                self._reference_motor(1, self.p.switch_max)
                self._start_move_home(self._measure())
            return
        if hs is HomeState.HOME_MOVE_TO_HOME:
            centre, cv, done_c = self.centre_traj.sample(t) if self.centre_traj else (self.centre_ref, 0.0, True)
            delta, dv, done_d = self.delta_traj.sample(t) if self.delta_traj else (self.delta_ref, 0.0, True)
            self._set_motor_refs(centre, delta, cv, dv)
            if done_c and done_d:
                self.centre_traj = self.delta_traj = None
                if self._home_settle_until is None:
                    self._home_settle_until = t + HOME_SETTLE
                elif t >= self._home_settle_until:
                    # no load on the handle at rest: it sits at the centre, which references it
                    mm = self._measure()
                    self.mobile_offset += (mm["x"][0] + mm["x"][1]) / 2 - mm["h"]
                    self._meas = self._measure()  # the state sent with `initialized` uses the new reference
                    self.initialized = True
                    self.home_state = HomeState.HOME_DONE
            return
        self._set_motor_refs(self.centre_ref, self.delta_ref, 0.0, 0.0)  # HOME_DONE: hold

    def _reference_motor(self, i: int, position: float) -> None:
        """An endstroke switch closed: this is the motor's known position from now on."""
        measured = self._measure()["x"][i]
        shift = position - measured
        self.motor_offset[i] += shift
        self.motor_ref[i] += shift
        self._meas = self._measure()

    # -- supervision ----------------------------------------------------------------------------
    def _latch(self, error: ErrorState, message: str) -> None:
        if self.error_state is not ErrorState.NO_ERROR:
            return
        self.error_state = error
        self._motors_off()
        self._outbox += encode_error_event(ErrorEvent(self.t_us, error, self.ctrl_state, message))
        self._trim_outbox()

    def _motors_off(self) -> None:
        self.ctrl_state = ControlState.IDLE_CTRL_STATE
        if self.home_state is not HomeState.HOME_DONE:
            self.home_state = HomeState.HOME_DONE if self.initialized else HomeState.HOME_NOT_DONE
        self.current = [0.0, 0.0]
        self._clear_motion()

    def _clear_motion(self) -> None:
        self.centre_traj = self.delta_traj = None
        self.centre_vel_cmd = self.delta_vel_cmd = 0.0
        self.centre_vel_ref = self.delta_vel_ref = 0.0
        self.motor_vel_ref = [0.0, 0.0]

    def _motors_on_from(self, m: dict[str, Any]) -> None:
        """Bumpless start: references at the measured positions, integrators cleared."""
        self._clear_motion()
        centre = (m["x"][0] + m["x"][1]) / 2
        self._set_motor_refs(centre, self.p.delta_of(m["x"][0], m["x"][1]), 0.0, 0.0)
        for pid in self.pid:
            pid.integral = 0.0
        self._over_current_since = None

    def _supervise(self, t: float, m: dict[str, Any]) -> None:
        if not self.motors_on:
            return
        if t <= self._watchdog_fed_until:
            self._last_host_time = t
        if self._host_seen and t - self._last_host_time > WATCHDOG_TIMEOUT:
            self._latch(ErrorState.WATCHDOG, f"no host bytes for {t - self._last_host_time:.3f} s")
            return
        on = self.ctrl_state is ControlState.ON_CTRL_STATE
        env = self.envelope
        if env is not None and on and not self.demo:  # the locked envelope first: the host's monitor, one layer down
            margin = ENVELOPE_POSITION_MARGIN
            if abs(m["vh"]) > ENVELOPE_VELOCITY_FACTOR * env.max_vel:
                self._latch(ErrorState.ENVELOPE_BREACH, f"handle at {abs(m['vh']):.3f} m/s, above "
                                                        f"{ENVELOPE_VELOCITY_FACTOR:g} x the locked "
                                                        f"{env.max_vel:g} m/s")
                return
            if not env.pos_min - margin <= m["h"] <= env.pos_max + margin:
                self._latch(ErrorState.ENVELOPE_BREACH, f"handle at {m['h']:.3f} m, outside the locked "
                                                        f"{env.pos_min:g}..{env.pos_max:g} m")
                return
        if on and abs(m["force"]) > self.max_force:
            self._latch(ErrorState.OVER_FORCE, f"interaction force {m['force']:.1f} N")
            return
        margin = POSITION_LIMIT_MARGIN
        if on and (m["h"] < self.pos_min - margin or m["h"] > self.pos_max + margin):
            self._latch(ErrorState.POSITION_LIMIT, f"handle at {m['h']:.3f} m")
            return
        if self.demo:
            return
        for i in (0, 1):
            if abs(self.motor_ref[i] - m["x"][i]) > self.max_tracking_error:
                self._latch(ErrorState.TRACKING_ERROR,
                            f"motor {i}: {abs(self.motor_ref[i] - m['x'][i]) * 1000:.1f} mm")
                return
        if on and not self.endstrokes_disabled and (self.x[0] <= self.p.switch_min or
                                                     self.x[1] >= self.p.switch_max):
            self._latch(ErrorState.ENDSTROKE_HIT, "endstroke switch closed")
            return
        vmax = OVER_VELOCITY_FACTOR * self.max_vel
        if on and (abs(m["vh"]) > vmax or abs(m["v"][0]) > vmax or abs(m["v"][1]) > vmax):
            self._latch(ErrorState.OVER_VELOCITY, f"handle at {m['vh']:.2f} m/s")
            return
        if max(abs(self.current[0]), abs(self.current[1])) > self.max_current:
            if self._over_current_since is None:
                self._over_current_since = t
            elif t - self._over_current_since >= OVER_CURRENT_TIME:
                self._latch(ErrorState.OVER_CURRENT, f"motor current above {self.max_current:g} A for 50 ms")
        else:
            self._over_current_since = None

    # -- stream ---------------------------------------------------------------------------------
    def _stream(self) -> None:
        # whole-millisecond schedule, as the firmware counts loop ticks
        if not self.stream_enabled or (self._ticks - self._stream_start) % self._stream_ticks:
            return
        self._outbox += self._state_frames(force_linarm=self._stream_count % LINARM_STATE_DIVIDER == 0)
        self._stream_count += 1
        self._trim_outbox()

    def _state_frames(self, force_linarm: bool = True) -> bytes:
        out = bytearray()
        ls = self.linarm_state()
        key = tuple(getattr(ls, f) for f in ls.__slots__ if f != "t_us")  # type: ignore[attr-defined]
        if force_linarm or key != self._last_sent_linarm:
            out += encode_linarm_state(ls)
            self._last_sent_linarm = key
        out += encode_motor_state(self.motor_state(0))
        out += encode_motor_state(self.motor_state(1))
        out += encode_vsa_state(self.vsa_state())
        return bytes(out)

    def sent_control_and_error(self) -> tuple[int, int] | None:
        """(control state, error state) of the last linarmState frame sent (None before the first): what the
        host was last told, without decoding the stream (the simulator process's state watch)."""
        key = self._last_sent_linarm  # LinarmState's fields after t_us: controlState first, errorState fourth
        return None if key is None else (int(key[0]), int(key[3]))

    def _trim_outbox(self) -> None:
        if len(self._outbox) > OUTBOX_LIMIT:
            del self._outbox[: len(self._outbox) - OUTBOX_LIMIT]

    # -- commands -------------------------------------------------------------------------------
    def _execute(self, cmd: HostCommand) -> bytes:
        if cmd.name == "identify":
            return encode_identify(cmd.seq, self.firmware_version)
        if cmd.name == "heartbeat":
            return b""
        handler = getattr(self, "_cmd_" + cmd.name)
        try:
            returns = handler(**cmd.args)
        except _Refuse as refuse:
            raise CommandRejected(cmd.seq, cmd.cmd_id, refuse.code, refuse.message) from None
        except TrajectoryError as exc:
            raise CommandRejected(cmd.seq, cmd.cmd_id, ReplyError.OUT_OF_RANGE, str(exc)) from None
        ack = encode_ack(cmd.seq, cmd.cmd_id, *(returns or ()))
        if cmd.name == "getState":
            ack += self._state_frames()
        return ack

    # guards
    def _need_state(self, *states: ControlState) -> None:
        if self.ctrl_state not in states:
            raise _Refuse(ReplyError.WRONG_STATE, f"not allowed in {self.ctrl_state.name}")

    def _need_mode(self, *modes: ControlMode) -> None:
        if self.ctrl_mode not in modes:
            raise _Refuse(ReplyError.WRONG_MODE, f"not allowed in {self.ctrl_mode.name}")

    def _need_no_error(self) -> None:
        if self.error_state is not ErrorState.NO_ERROR:
            raise _Refuse(ReplyError.IN_ERROR, f"{self.error_state.name} latched: resetError first")

    def _homing_busy(self) -> bool:
        return self.ctrl_state is ControlState.HOME_CTRL_STATE and self.home_state is not HomeState.HOME_DONE

    @staticmethod
    def _in_range(name: str, value: float, lo: float, hi: float) -> None:
        tol = 1e-6 * max(1.0, abs(lo), abs(hi))  # the host's values arrive as float32
        if not lo - tol <= value <= hi + tol:
            raise _Refuse(ReplyError.OUT_OF_RANGE, f"{name}={value:.6g} outside {lo:.6g}..{hi:.6g}")

    def _plan(self, start: float, target: float, max_vel: float, max_acc: float, exec_time: float,
              trigger: bool) -> Trajectory:
        if exec_time == 0.0:
            self._in_range("maxVel", max_vel, K["MOVE_LIMIT_MIN"], self.max_vel)
            self._in_range("maxAcc", max_acc, K["MOVE_LIMIT_MIN"], self.max_acc)
        vel = max_vel if max_vel > 0 else self.max_vel
        acc = max_acc if max_acc > 0 else self.max_acc
        traj = plan_trajectory(start, target, min(vel, self.max_vel), min(acc, self.max_acc), exec_time,
                               self.trajectory_type)
        if trigger:
            if self.trigger_mode is TriggerMode.NO_TRIGGER:
                raise _Refuse(ReplyError.NOT_SUPPORTED, "trigger requested but TRIGGER_MODE is NO_TRIGGER")
        else:
            traj.t0 = self.time
        return traj

    # handlers: keyword names are the table's argument names
    def _cmd_setDemo(self, demo: bool) -> None:
        self._need_state(ControlState.IDLE_CTRL_STATE)
        if demo != self.demo:
            self.demo = demo
            self.initialized = False  # a different "robot": home again
            self.home_state = HomeState.HOME_NOT_DONE

    def _cmd_resetError(self) -> None:
        self.error_state = ErrorState.NO_ERROR
        self._over_current_since = None

    def _cmd_setCtrlState(self, controlState: ControlState) -> None:
        if controlState is ControlState.IDLE_CTRL_STATE:
            self._motors_off()
            return
        self._need_no_error()
        if self._homing_busy():
            raise _Refuse(ReplyError.BUSY, "homing in progress")
        if controlState is ControlState.HOME_CTRL_STATE:
            self._start_homing()
            return
        if not self.initialized:
            raise _Refuse(ReplyError.NOT_HOMED, "home the robot first")
        if self.ctrl_state is not ControlState.ON_CTRL_STATE:
            self._motors_on_from(self._meas)
            self.ctrl_state = ControlState.ON_CTRL_STATE

    def _cmd_setCtrlMode(self, controlMode: ControlMode) -> None:
        if self._homing_busy():
            raise _Refuse(ReplyError.BUSY, "homing in progress")
        self.ctrl_mode = controlMode
        self._clear_motion()

    def _jog(self, which: str, velocity: float) -> None:
        self._need_state(ControlState.ON_CTRL_STATE)
        self._need_mode(ControlMode.POS_REF_BY_VEL)
        self._in_range(which, velocity, -self.max_vel, self.max_vel)

    def _cmd_setCentreVelocity(self, centreVelocity: float) -> None:
        self._jog("centreVelocity", centreVelocity)
        self.centre_vel_cmd = centreVelocity

    def _cmd_setDeltaVelocity(self, deltaVelocity: float) -> None:
        self._jog("deltaVelocity", deltaVelocity)
        self.delta_vel_cmd = deltaVelocity

    def _cmd_getPidTunings(self, index: int) -> tuple[Any, ...]:
        pid = self.pid[index]
        return index, pid.kp, pid.ki, pid.kd

    def _cmd_moveCentreTo(self, targetPos: float, maxVel: float, maxAcc: float, execTime: float,
                          trigger: bool) -> None:
        self._need_state(ControlState.ON_CTRL_STATE)
        self._need_mode(ControlMode.POS_REF_BY_TARGET_POS, ControlMode.POS_REF_BY_IMPEDANCE)
        self._in_range("targetPos", targetPos, self.pos_min, self.pos_max)
        self.centre_traj = self._plan(self.centre_ref, targetPos, maxVel, maxAcc, execTime, trigger)

    def _move_delta(self, target: float, max_vel: float, max_acc: float, exec_time: float, trigger: bool) -> None:
        self._need_state(ControlState.ON_CTRL_STATE)
        if self.ctrl_mode is ControlMode.POS_REF_BY_VEL:
            raise _Refuse(ReplyError.WRONG_MODE, "use setDeltaVelocity in POS_REF_BY_VEL")
        self._in_range("targetDeltaPos", target, self.p.delta_min, self.p.delta_max)
        self.delta_traj = self._plan(self.delta_ref, target, max_vel, max_acc, exec_time, trigger)

    def _cmd_moveDeltaTo(self, targetDeltaPos: float, maxVel: float, maxAcc: float, execTime: float,
                         trigger: bool) -> None:
        self._move_delta(targetDeltaPos, maxVel, maxAcc, execTime, trigger)

    def _cmd_setStiffness(self, stiffness: float, maxVel: float, maxAcc: float, execTime: float) -> None:
        lo, hi = self.p.stiffness(self.p.delta_min), self.p.stiffness(self.p.delta_max)
        self._in_range("stiffness", stiffness, lo, hi)
        self._move_delta(self.p.delta_for_stiffness(stiffness), maxVel, maxAcc, execTime, False)

    def _cmd_goToHome(self) -> None:
        self._need_no_error()
        if self._homing_busy():
            raise _Refuse(ReplyError.BUSY, "homing in progress")
        self._start_homing()

    def _cmd_setTrajectoryType(self, type: TrajectoryType) -> None:  # the seed names it "type"
        self.trajectory_type = type

    def _cmd_setAdmittanceParameter(self, Ka: float) -> None:
        self._in_range("Ka", Ka, 0.0, K["KA_MAX"])
        self.ka = Ka

    def _cmd_getAdmittanceParameter(self) -> tuple[float]:
        return (self.ka,)

    def _cmd_setAssistanceParameter(self, Kt: float) -> None:
        self._in_range("Kt", Kt, 0.0, K["KT_MAX"])
        self.kt = Kt

    def _cmd_getAssistanceParameter(self) -> tuple[float]:
        return (self.kt,)

    def _cmd_setAssistanceTargetPos(self, Apos: float) -> None:
        self._in_range("Apos", Apos, self.pos_min, self.pos_max)
        self.assist_target = Apos

    def _cmd_getAssistanceTargetPos(self) -> tuple[float]:
        return (self.assist_target,)

    def _cmd_enableVirtualVsa(self, virtual: bool) -> None:
        self.virtual_vsa = virtual

    def _cmd_setVirtualVsaSpringDisplacement(self, disp: float) -> None:
        self._in_range("disp", disp, -K["VIRTUAL_DISP_MAX"], K["VIRTUAL_DISP_MAX"])
        self.virtual_disp = disp

    def _cmd_getIsInitialized(self) -> tuple[bool]:
        return (self.initialized,)

    def _cmd_disableEndstrokes(self, disable: bool) -> None:
        if disable:  # enabling them again is always allowed
            self._need_service("disableEndstrokes")
        self.endstrokes_disabled = disable

    def _cmd_setTriggerMode(self, mode: TriggerMode) -> None:
        self.trigger_mode = mode

    def _cmd_setTriggerParameter(self, param: float) -> None:
        self.trigger_param = param

    def _cmd_startDataStream(self, period: float) -> None:
        self._stream_ticks = max(1, round(period / DT))  # the firmware counts whole milliseconds
        self.stream_period = self._stream_ticks * DT
        self.stream_enabled = True
        self._stream_start = self._ticks + 1  # the first frames go out on the next tick

    def _cmd_stopDataStream(self) -> None:
        self.stream_enabled = False

    def _cmd_setMotorOffset(self, index: int, offset: float) -> None:
        self._need_service("setMotorOffset")
        self._need_state(ControlState.IDLE_CTRL_STATE)
        self.motor_offset[index] = offset

    def _cmd_setMobileOffset(self, offset: float) -> None:
        self._need_service("setMobileOffset")
        self._need_state(ControlState.IDLE_CTRL_STATE)
        self.mobile_offset = offset

    def _cmd_setMotorRatio(self, index: int, ratio: float) -> None:
        self._need_service("setMotorRatio")
        self._need_state(ControlState.IDLE_CTRL_STATE)
        self._in_range("ratio", ratio, K["RATIO_MIN"], K["RATIO_MAX"])
        self.motor_ratio[index] = ratio

    def _cmd_setMobileRatio(self, ratio: float) -> None:
        self._need_service("setMobileRatio")
        self._need_state(ControlState.IDLE_CTRL_STATE)
        self._in_range("ratio", ratio, K["RATIO_MIN"], K["RATIO_MAX"])
        self.mobile_ratio = ratio

    def _cmd_setMaxTrackingError(self, maxTrackingError: float) -> None:
        self._in_range("maxTrackingError", maxTrackingError, K["MAX_TRACKING_ERROR_MIN"], K["MAX_TRACKING_ERROR_MAX"])
        self._within_envelope("maxTrackingError", maxTrackingError, "max_tracking_error")
        self.max_tracking_error = maxTrackingError

    def _cmd_setMaxForce(self, maxForce: float) -> None:
        self._in_range("maxForce", maxForce, K["MAX_FORCE_MIN"], K["MAX_FORCE_MAX"])
        self._within_envelope("maxForce", maxForce, "max_force")
        self.max_force = maxForce

    def _cmd_setMaxCurrent(self, maxCurrent: float) -> None:
        self._in_range("maxCurrent", maxCurrent, K["MAX_CURRENT_MIN"], self.p.current_hw_limit)
        self._within_envelope("maxCurrent", maxCurrent, "max_current")
        self.max_current = maxCurrent

    def _cmd_setMaxAcceleration(self, maxAcc: float) -> None:
        self._in_range("maxAcc", maxAcc, K["MAX_ACC_MIN"], K["MAX_ACC_MAX"])
        self._within_envelope("maxAcc", maxAcc, "max_acc")
        self.max_acc = maxAcc

    def _cmd_setMaxVelocity(self, maxVel: float) -> None:
        self._in_range("maxVel", maxVel, K["MAX_VEL_MIN"], K["MAX_VEL_MAX"])
        self._within_envelope("maxVel", maxVel, "max_vel")
        self.max_vel = maxVel

    def _cmd_setHomeParameter(self, homeCentre: float, homeDelta: float, homingVelocity: float) -> None:
        if self._homing_busy():
            raise _Refuse(ReplyError.BUSY, "homing in progress")
        self._in_range("homeCentre", homeCentre, self.pos_min, self.pos_max)
        self._in_range("homeDelta", homeDelta, self.p.delta_min, self.p.delta_max)
        self._in_range("homingVelocity", homingVelocity, K["HOMING_VELOCITY_MIN"], self.max_vel)
        self.home_centre, self.home_delta, self.homing_velocity = homeCentre, homeDelta, homingVelocity

    def _cmd_setPosLimit(self, minPos: float, maxPos: float) -> None:
        self._in_range("minPos", minPos, self.p.rail_min, self.p.rail_max)
        self._in_range("maxPos", maxPos, minPos + K["POS_LIMIT_MIN_SPAN"], self.p.rail_max)
        env = self.envelope
        if env is not None and (minPos < env.pos_min or maxPos > env.pos_max):
            raise _Refuse(ReplyError.LOCKED, f"position limits {minPos:g}..{maxPos:g} m beyond the locked "
                                             f"{env.pos_min:g}..{env.pos_max:g} m (restart to change them)")
        self.pos_min, self.pos_max = minPos, maxPos

    def _cmd_setPidTunings(self, index: int, kp: float, ki: float, kd: float) -> None:
        self._in_range("kp", kp, 0.0, K["KP_MAX"])
        self._in_range("ki", ki, 0.0, K["KI_MAX"])
        self._in_range("kd", kd, 0.0, K["KD_MAX"])
        self._need_service("setPidTunings")
        pid = self.pid[index]
        pid.kp, pid.ki, pid.kd = kp, ki, kd

    def _cmd_getState(self) -> None:
        return None

    def _cmd_lockEnvelope(self) -> tuple[float, ...]:
        # Locking again can only narrow: the limits are inside the envelope already.
        env = self.envelope = Envelope(self.max_vel, self.max_acc, self.max_force, self.max_current,
                                       self.max_tracking_error, self.pos_min, self.pos_max)
        return (env.max_vel, env.max_acc, env.max_force, env.max_current, env.max_tracking_error, env.pos_min,
                env.pos_max)

    # the envelope: after lockEnvelope, limits only inside it; service commands only in service mode
    def _within_envelope(self, name: str, value: float, field: str) -> None:
        if self.envelope is not None and value > getattr(self.envelope, field):
            raise _Refuse(ReplyError.LOCKED, f"{name}={value:g} beyond the locked {getattr(self.envelope, field):g} "
                                             "(restart to change it)")

    def _need_service(self, name: str) -> None:
        if self.envelope is not None and not self.service_mode:
            raise _Refuse(ReplyError.LOCKED, f"{name} refused: the envelope is locked (service mode only, "
                                             "entered at boot)")
