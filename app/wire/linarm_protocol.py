"""The LINarm wire protocol: the single source of truth (ids, arguments, replies, stream layouts, enums).

Everything is data in ``HOST_COMMANDS`` and ``CONTROLLER_MESSAGES``; the encoders and decoders below
are driven by those tables, and ``protocol_table()`` exports them as JSON for the firmware's C++
header generator. Rules (see docs/linarm-protocol.md):

* host -> controller: ``<id>,<seq>{,<arg>}*;`` with ids 0..49 (MAXCALLBACKS), seq a text uint16
  (1..65535 on the host, 0 = unsolicited/unknown), integers/enums/bools as text, every float as a
  binary little-endian float32 (escaped). Every frame fits the Arduino's 62-byte buffer.
* controller -> host: ACK(seq, cmdId, returns...), ERROR(seq, cmdId, code[, text]), IDENTIFY,
  ERROR_EVENT and the state stream (LINARM_STATE, MOTOR_STATE, VSA_STATE) with a uint32 µs stamp.
* Command 0 is ``identify``: harmless and idempotent, because garbage before a frame makes the
  Arduino library dispatch it as id 0.
"""

from __future__ import annotations

import math
import operator
import re
import struct
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from enum import IntEnum
from typing import Any

from app.wire.cmdmessenger import (
    ARDUINO_MAX_MESSAGE,
    FIELD_READERS,
    MAX_CALLBACKS,
    ArduinoMessage,
    FieldError,
    Frame,
    Kind,
    encode_field,
    encode_frame,
    escape,
    to_float32,
)
from app.wire.linarm_constants import constants_table

PROTOCOL_VERSION = 1
SEQ_MIN, SEQ_MAX = 0, 65535
HEARTBEAT_PERIOD = 0.100  # s, host -> controller
T_US_WRAP_S = 2**32 * 1e-6  # the controller's micros() wraps every 71.6 min
WATCHDOG_TIMEOUT = 0.250  # s of host silence before the controller stops the motors
DEFAULT_STREAM_PERIOD = 0.005  # s (200 Hz)
LINARM_STATE_DIVIDER = 10  # LINARM_STATE goes out every 10th stream tick (and at once on a change)
DEVICE_NAME = "LINarm2"


# ---------------------------------------------------------------------------------------------
# Enums (names as in the seed's LinarmUser)
# ---------------------------------------------------------------------------------------------


class ControlState(IntEnum):
    IDLE_CTRL_STATE = 0
    HOME_CTRL_STATE = 1
    ON_CTRL_STATE = 2


class ControlMode(IntEnum):
    POS_REF_BY_VEL = 0
    POS_REF_BY_TARGET_POS = 1
    POS_REF_BY_IMPEDANCE = 2
    POS_REF_BY_ADMITTANCE = 3
    POS_REF_BY_ASSISTANCE = 4


class HomeState(IntEnum):
    HOME_NOT_DONE = 0  # encoders not referenced since power-up
    HOME_SEEK_MIN = 1  # both carriages jog towards the min endstroke (references motor 0)
    HOME_SEEK_MAX = 2  # both carriages jog towards the max endstroke (references motor 1)
    HOME_MOVE_TO_HOME = 3  # trajectory to the home centre/delta
    HOME_DONE = 4


class ErrorState(IntEnum):
    NO_ERROR = 0
    TRACKING_ERROR = 1  # |position reference - position| of a motor above maxTrackingError
    ENDSTROKE_HIT = 2  # an endstroke switch closed outside homing
    OVER_FORCE = 3  # |interaction force| above maxForce
    OVER_CURRENT = 4  # |motor current| above maxCurrent for 50 ms
    OVER_VELOCITY = 5  # |handle or carriage velocity| above 1.5 x maxVelocity
    WATCHDOG = 6  # no host bytes for WATCHDOG_TIMEOUT while the motors were on
    POSITION_LIMIT = 7  # handle more than 20 mm outside the position limits
    HOMING_FAILED = 8  # an endstroke was not found in time
    ENVELOPE_BREACH = 9  # handle faster than 1.2 x the locked maxVelocity, or 10 mm outside the locked range


class TriggerMode(IntEnum):
    NO_TRIGGER = 0
    TRIGGER_ON_FORCE = 1  # a move armed with trigger=1 starts when |force| >= triggerParameter (N)
    TRIGGER_ON_POSITION = 2  # ... when the handle is within triggerParameter (m) of the move's target


class TrajectoryType(IntEnum):
    TRAPEZOIDAL = 0
    CYCLOIDAL = 1


class ReplyError(IntEnum):
    """Codes carried by ERROR replies."""

    UNKNOWN_COMMAND = 1  # id not attached (default callback), incl. ids >= 50
    BAD_ARGUMENT = 2  # missing/extra argument, wrong type or size, non-finite float, bad seq
    OUT_OF_RANGE = 3  # value outside its table range or the controller's limits
    WRONG_STATE = 4  # not allowed in the current control state
    WRONG_MODE = 5  # not allowed in the current control mode
    NOT_HOMED = 6  # needs a completed homing
    IN_ERROR = 7  # an error state is latched: resetError first
    BUSY = 8  # homing in progress
    NOT_SUPPORTED = 9  # e.g. a trigger with TRIGGER_MODE NO_TRIGGER
    LOCKED = 10  # beyond the locked safety envelope, or a service command after the lock: restart to change


# The seed's attribute names
CONTROL_STATES = ControlState
CONTROL_MODES = ControlMode
HOME_STATES = HomeState
ERROR_STATES = ErrorState
TRIGGER_MODES = TriggerMode
TRAJECTORY_TYPES = TrajectoryType
REPLY_ERRORS = ReplyError

ENUMS: dict[str, type[IntEnum]] = {
    "CONTROL_STATES": ControlState,
    "CONTROL_MODES": ControlMode,
    "HOME_STATES": HomeState,
    "ERROR_STATES": ErrorState,
    "TRIGGER_MODES": TriggerMode,
    "TRAJECTORY_TYPES": TrajectoryType,
    "REPLY_ERRORS": ReplyError,
}


# ---------------------------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------------------------

INT, BOOL, F32, U32, STR = Kind.TEXT_INT, Kind.TEXT_BOOL, Kind.BIN_FLOAT, Kind.BIN_UINT32, Kind.TEXT_STR
FLOAT32_MAX = 3.4028234663852886e38


@dataclass(frozen=True)
class Arg:
    name: str
    kind: Kind
    unit: str = ""
    enum: str | None = None
    min: float | None = None
    max: float | None = None
    optional: bool = False  # only for a trailing string: omitted when empty (never an empty field)

    def __post_init__(self) -> None:
        if self.enum is not None:
            members = [int(m) for m in ENUMS[self.enum]]
            object.__setattr__(self, "min", min(members))
            object.__setattr__(self, "max", max(members))


@dataclass(frozen=True)
class Command:
    """A host -> controller command. ``seq`` is implicit as the first field."""

    id: int
    name: str
    args: tuple[Arg, ...] = ()
    returns: tuple[Arg, ...] = ()  # ACK values after (seq, cmdId)
    reply: str = "ack"  # 'ack', 'identify' or 'none' (errors are always replied)
    doc: str = ""


@dataclass(frozen=True)
class Message:
    """A controller -> host message."""

    id: int
    name: str
    fields: tuple[Arg, ...]
    doc: str = ""


SEQ = Arg("seq", INT, min=SEQ_MIN, max=SEQ_MAX)
INDEX = Arg("index", INT, min=0, max=1)


def _f(name: str, unit: str, lo: float | None = None, hi: float | None = None) -> Arg:
    return Arg(name, F32, unit, min=lo, max=hi)


_MOVE = (_f("maxVel", "m/s", 0.0), _f("maxAcc", "m/s^2", 0.0), _f("execTime", "s", 0.0))

HOST_COMMANDS: tuple[Command, ...] = (
    Command(0, "identify", reply="identify", doc="Harmless ping; garbage before a frame lands here."),
    Command(1, "heartbeat", reply="none", doc="Every 100 ms; any host byte feeds the watchdog."),
    Command(2, "setDemo", (Arg("demo", BOOL),), doc="IDLE only. Run without the robot (kinematic)."),
    Command(3, "resetError", doc="Clear the latched error state; the controller stays IDLE."),
    Command(4, "setCtrlState", (Arg("controlState", INT, enum="CONTROL_STATES"),)),
    Command(5, "setCtrlMode", (Arg("controlMode", INT, enum="CONTROL_MODES"),)),
    Command(6, "setCentreVelocity", (_f("centreVelocity", "m/s"),), doc="POS_REF_BY_VEL."),
    Command(7, "setDeltaVelocity", (_f("deltaVelocity", "m/s"),), doc="POS_REF_BY_VEL."),
    Command(8, "getPidTunings", (INDEX,), returns=(INDEX, _f("kp", "N/m"), _f("ki", "N/(m s)"), _f("kd", "N s/m"))),
    Command(9, "moveCentreTo", (_f("targetPos", "m"), *_MOVE, Arg("trigger", BOOL))),
    Command(10, "moveDeltaTo", (_f("targetDeltaPos", "m"), *_MOVE, Arg("trigger", BOOL))),
    Command(11, "setStiffness", (_f("stiffness", "N/m", 0.0), *_MOVE)),
    Command(12, "goToHome", doc="Full homing if not initialised, else a move to the home position."),
    Command(13, "setTrajectoryType", (Arg("type", INT, enum="TRAJECTORY_TYPES"),)),
    Command(14, "setAdmittanceParameter", (_f("Ka", "m/(N s)", 0.0),)),
    Command(15, "getAdmittanceParameter", returns=(_f("Ka", "m/(N s)"),)),
    Command(16, "setAssistanceParameter", (_f("Kt", "N/m", 0.0),)),
    Command(17, "getAssistanceParameter", returns=(_f("Kt", "N/m"),)),
    Command(18, "setAssistanceTargetPos", (_f("Apos", "m"),)),
    Command(19, "getAssistanceTargetPos", returns=(_f("Apos", "m"),)),
    Command(20, "enableVirtualVsa", (Arg("virtual", BOOL),)),
    Command(21, "setVirtualVsaSpringDisplacement", (_f("disp", "m"),)),
    Command(22, "getIsInitialized", returns=(Arg("initialized", BOOL),)),
    Command(23, "disableEndstrokes", (Arg("disable", BOOL),)),
    Command(24, "setTriggerMode", (Arg("mode", INT, enum="TRIGGER_MODES"),)),
    Command(25, "setTriggerParameter", (_f("param", ""),)),
    Command(26, "startDataStream", (_f("period", "s", 0.001, 1.0),)),
    Command(27, "stopDataStream"),
    Command(28, "setMotorOffset", (INDEX, _f("offset", "m"))),
    Command(29, "setMobileOffset", (_f("offset", "m"),)),
    Command(30, "setMotorRatio", (INDEX, _f("ratio", "m/count"))),
    Command(31, "setMobileRatio", (_f("ratio", "m/count"),)),
    Command(32, "setMaxTrackingError", (_f("maxTrackingError", "m", 0.0),)),
    Command(33, "setMaxForce", (_f("maxForce", "N", 0.0),)),
    Command(34, "setMaxCurrent", (_f("maxCurrent", "A", 0.0),)),
    Command(35, "setMaxAcceleration", (_f("maxAcc", "m/s^2", 0.0),)),
    Command(36, "setMaxVelocity", (_f("maxVel", "m/s", 0.0),)),
    Command(37, "setHomeParameter", (_f("homeCentre", "m"), _f("homeDelta", "m"), _f("homingVelocity", "m/s", 0.0))),
    Command(38, "setPosLimit", (_f("minPos", "m"), _f("maxPos", "m"))),
    Command(39, "setPidTunings", (INDEX, _f("kp", "N/m", 0.0), _f("ki", "N/(m s)", 0.0), _f("kd", "N s/m", 0.0))),
    Command(40, "getState", doc="ACK, then one LINARM_STATE, two MOTOR_STATE and one VSA_STATE frame."),
    Command(41, "lockEnvelope", returns=(_f("maxVel", "m/s"), _f("maxAcc", "m/s^2"), _f("maxForce", "N"),
                                         _f("maxCurrent", "A"), _f("maxTrackingError", "m"), _f("minPos", "m"),
                                         _f("maxPos", "m")),
            doc="The current limits become the safety envelope until the controller restarts: setters may "
                "narrow within it, never widen beyond it; after it, PID gains, calibration and disabling the "
                "endstrokes are refused (LOCKED) unless booted in service mode. ACK: the locked envelope."),
)

T_US = Arg("t_us", U32, "us")
CONTROLLER_MESSAGES: tuple[Message, ...] = (
    Message(100, "identify", (SEQ, Arg("protocolVersion", INT, min=0, max=255), Arg("device", STR),
                              Arg("firmwareVersion", STR)), doc="Reply to cmd 0; sent with seq 0 at boot."),
    Message(101, "ack", (SEQ, Arg("cmdId", INT, min=0, max=255)), doc="Followed by the command's returns."),
    Message(102, "error", (SEQ, Arg("cmdId", INT, min=0, max=255), Arg("code", INT, enum="REPLY_ERRORS"),
                           Arg("message", STR, optional=True))),
    Message(103, "errorEvent", (T_US, Arg("errorState", INT, enum="ERROR_STATES"),
                                Arg("controlState", INT, enum="CONTROL_STATES"), Arg("message", STR, optional=True)),
            doc="Unsolicited, when an error latches (also without the stream)."),
    Message(110, "linarmState", (
        T_US,
        Arg("controlState", INT, enum="CONTROL_STATES"),
        Arg("controlMode", INT, enum="CONTROL_MODES"),
        Arg("homeState", INT, enum="HOME_STATES"),
        Arg("errorState", INT, enum="ERROR_STATES"),
        Arg("triggerMode", INT, enum="TRIGGER_MODES"),
        Arg("initialized", BOOL),
        Arg("trajectoryType", INT, enum="TRAJECTORY_TYPES"),
        Arg("demo", BOOL),
        Arg("virtualVsa", BOOL),
        Arg("endstrokesDisabled", BOOL),
    )),
    Message(111, "motorState", (T_US, INDEX, _f("position", "m"), _f("velocity", "m/s"), _f("current", "A"),
                                _f("target", "m"))),
    Message(112, "vsaState", (T_US, _f("equilibriumPos", "m"), _f("delta", "m"), _f("stiffness", "N/m"),
                              _f("handlePos", "m"), _f("handleVel", "m/s"), _f("force", "N"))),
)

COMMANDS_BY_NAME: dict[str, Command] = {c.name: c for c in HOST_COMMANDS}
COMMANDS_BY_ID: dict[int, Command] = {c.id: c for c in HOST_COMMANDS}
MESSAGES_BY_NAME: dict[str, Message] = {m.name: m for m in CONTROLLER_MESSAGES}
MESSAGES_BY_ID: dict[int, Message] = {m.id: m for m in CONTROLLER_MESSAGES}
assert len(COMMANDS_BY_ID) == len(HOST_COMMANDS) and max(COMMANDS_BY_ID) < MAX_CALLBACKS
assert not set(COMMANDS_BY_ID) & set(MESSAGES_BY_ID)


class ProtocolError(ValueError):
    """A controller frame that does not match the table (the driver counts it and skips it)."""


class CommandRejected(Exception):
    """Controller side: a host command that must be answered with ERROR(seq, cmdId, code, message)."""

    def __init__(self, seq: int, cmd_id: int, code: ReplyError, message: str = "") -> None:
        super().__init__(f"{code.name}: {message}" if message else code.name)
        self.seq = seq
        self.cmd_id = cmd_id
        self.code = code
        self.message = message


# ---------------------------------------------------------------------------------------------
# Typed messages (SI units)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class HostCommand:
    name: str
    cmd_id: int
    seq: int
    args: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Identify:
    seq: int
    protocol_version: int
    device: str
    firmware_version: str


@dataclass(frozen=True, slots=True)
class Ack:
    seq: int
    cmd_id: int
    command: str
    values: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class ErrorReply:
    seq: int
    cmd_id: int
    command: str | None  # None when the id is not a known command
    code: ReplyError
    message: str = ""


@dataclass(frozen=True, slots=True)
class ErrorEvent:
    t_us: int
    error_state: ErrorState
    control_state: ControlState
    message: str = ""


@dataclass(frozen=True, slots=True)
class LinarmState:
    t_us: int  # controller micros(), wraps every 2**32 µs (71.6 min)
    control_state: ControlState
    control_mode: ControlMode
    home_state: HomeState
    error_state: ErrorState
    trigger_mode: TriggerMode
    initialized: bool
    trajectory_type: TrajectoryType
    demo: bool
    virtual_vsa: bool
    endstrokes_disabled: bool


@dataclass(frozen=True, slots=True)
class MotorState:
    t_us: int
    index: int
    position: float  # m
    velocity: float  # m/s
    current: float  # A
    target: float  # m, the position reference of the motor's loop


@dataclass(frozen=True, slots=True)
class VsaState:
    t_us: int
    equilibrium_pos: float  # m, the centre: mean of the two carriages
    delta: float  # m, the springs' pretension: carriage distance - 2 x free length (0.01..0.06 m)
    stiffness: float  # N/m, k(delta) of the spring pair around the centre
    handle_pos: float  # m
    handle_vel: float  # m/s
    force: float  # N, interaction force on the handle (+ pushes towards +x)

    @property
    def centre(self) -> float:
        return self.equilibrium_pos


ControllerMessage = Identify | Ack | ErrorReply | ErrorEvent | LinarmState | MotorState | VsaState

_STATE_FIELDS: dict[str, tuple[type, tuple[str, ...]]] = {
    "linarmState": (LinarmState, ("t_us", "control_state", "control_mode", "home_state", "error_state",
                                  "trigger_mode", "initialized", "trajectory_type", "demo", "virtual_vsa",
                                  "endstrokes_disabled")),
    "motorState": (MotorState, ("t_us", "index", "position", "velocity", "current", "target")),
    "vsaState": (VsaState, ("t_us", "equilibrium_pos", "delta", "stiffness", "handle_pos", "handle_vel", "force")),
    "errorEvent": (ErrorEvent, ("t_us", "error_state", "control_state", "message")),
}


# ---------------------------------------------------------------------------------------------
# Value checks shared by both directions
# ---------------------------------------------------------------------------------------------


def _check_value(arg: Arg, value: Any) -> Any:
    """Type/range check of one outgoing value; returns the value to encode."""
    if arg.kind is INT:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{arg.name} must be an int, got {value!r}")
        if (arg.min is not None and value < arg.min) or (arg.max is not None and value > arg.max):
            raise ValueError(f"{arg.name}={value} outside {arg.min}..{arg.max}")
        return int(value)
    if arg.kind is BOOL:
        if not isinstance(value, (bool, int)) or value not in (0, 1):
            raise TypeError(f"{arg.name} must be a bool, got {value!r}")
        return bool(value)
    if arg.kind in (F32, Kind.TEXT_FLOAT):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"{arg.name} must be a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v) or abs(v) > FLOAT32_MAX:
            raise ValueError(f"{arg.name}={v!r} is not a finite float32")
        return v
    if arg.kind is U32:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFFFFFF:
            raise ValueError(f"{arg.name} must be a uint32, got {value!r}")
        return value
    if arg.kind is STR:
        return str(value)
    raise TypeError(f"unsupported kind {arg.kind}")  # pragma: no cover


def _fields_for(args: Sequence[Arg], values: Sequence[Any]) -> list[tuple[Kind, Any]]:
    out: list[tuple[Kind, Any]] = []
    for arg, value in zip(args, values, strict=True):
        v = _check_value(arg, value)
        if arg.optional and v == "":
            continue
        out.append((arg.kind, v))
    return out


# ---------------------------------------------------------------------------------------------
# Host side: encode commands, decode controller frames
# ---------------------------------------------------------------------------------------------


def next_seq(seq: int) -> int:
    """The host's sequence counter: 1..65535, wrapping; 0 is reserved for unsolicited replies."""
    return 1 if seq >= SEQ_MAX else seq + 1


def encode_command(name: str, seq: int, *args: Any) -> bytes:
    """``encode_command('moveCentreTo', 7, 0.40, 0.15, 0.15, 0.0, False)`` -> bytes (<= 62 before ';')."""
    try:
        cmd = COMMANDS_BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown LINarm command {name!r}") from None
    if len(args) != len(cmd.args):
        names = ", ".join(a.name for a in cmd.args)
        raise TypeError(f"{name} takes {len(cmd.args)} arguments ({names}), got {len(args)}")
    return encode_frame(cmd.id, _fields_for((SEQ, *cmd.args), (seq, *args)))


_Step = tuple[str, Callable[[bytes], Any], float | None, float | None, dict[int, IntEnum] | None, type[IntEnum] | None]
_BULK_KINDS = frozenset((F32, U32))  # fixed-size binary fields without a check beyond their size


@dataclass(frozen=True, slots=True)
class _FieldsReader:
    """How to read one table row's fields, worked out once from its ``Arg``s: the reader of each kind, the
    range of each integer, the members of each enum (a dict lookup, not an enum call, per field).

    The stream's binary fields (float32, uint32) are read with one struct call when all of them have
    their size; the other fields one by one, in order, so errors are the same as field by field."""

    what: str
    names: tuple[str, ...]
    steps: tuple[_Step, ...]
    required: int
    bulk: struct.Struct | None  # the binary fields' struct (None: fewer than two of them)
    bulk_fields: Callable[[Sequence[bytes]], tuple[bytes, ...]]  # picks the binary fields
    bulk_sizes: tuple[int, ...]
    other_steps: tuple[tuple[int, _Step], ...]  # the other fields: (index, step)
    order: Callable[[tuple[Any, ...]], tuple[Any, ...]]  # (binary values + other values) -> table order

    @classmethod
    def of(cls, args: Sequence[Arg], what: str) -> _FieldsReader:
        steps: list[_Step] = []
        for arg in args:
            ranged = arg.kind is INT and arg.min is not None
            enum = ENUMS[arg.enum] if arg.enum is not None else None
            steps.append((arg.name, FIELD_READERS[arg.kind], arg.min if ranged else None, arg.max if ranged else None,
                          {int(m): m for m in enum} if enum is not None else None, enum))
        binary = [i for i, a in enumerate(args) if a.kind in _BULK_KINDS and not a.optional]
        other = [i for i in range(len(args)) if i not in binary]
        bulk = struct.Struct("<" + "".join(args[i].kind.value[1:] for i in binary)) if len(binary) >= 2 else None
        position = {i: k for k, i in enumerate(binary + other)}
        return cls(what, tuple(a.name for a in args), tuple(steps), len(args) - sum(1 for a in args if a.optional),
                   bulk, operator.itemgetter(*binary) if bulk is not None else tuple,
                   tuple(struct.calcsize(args[i].kind.value) for i in binary),
                   tuple((i, steps[i]) for i in other),
                   operator.itemgetter(*(position[i] for i in range(len(args)))) if len(args) >= 2 else tuple)

    def values(self, raw: Sequence[bytes]) -> list[Any]:
        """The fields' values in table order (a missing optional string is ''); ProtocolError if they do
        not match the table."""
        if not self.required <= len(raw) <= len(self.steps):
            raise ProtocolError(f"{self.what}: {len(raw)} fields, expected {len(self.steps)}")
        if self.bulk is not None and len(raw) == len(self.steps):
            fields = self.bulk_fields(raw)
            if tuple(map(len, fields)) == self.bulk_sizes:  # else: field by field says which one is wrong
                others = tuple(self._value(step, raw[i]) for i, step in self.other_steps)
                return list(self.order(self.bulk.unpack(b"".join(fields)) + others))
        out = [self._value(step, data) for step, data in zip(self.steps, raw, strict=False)]
        out += [""] * (len(self.steps) - len(raw))
        return out

    def _value(self, step: _Step, data: bytes) -> Any:
        name, read, lo, hi, members, enum = step
        try:
            value = read(data)
        except FieldError as exc:
            raise ProtocolError(f"{self.what}.{name}: {exc}") from exc
        if lo is not None and not lo <= value <= hi:
            raise ProtocolError(f"{self.what}.{name}={value} outside {lo}..{hi}")
        if members is not None:
            member = members.get(value)
            value = enum(value) if member is None else member  # type: ignore[misc]
        return value

    def read(self, raw: Sequence[bytes]) -> dict[str, Any]:
        return dict(zip(self.names, self.values(raw), strict=True))


_MESSAGE_READERS: dict[str, _FieldsReader] = {m.name: _FieldsReader.of(m.fields, m.name) for m in CONTROLLER_MESSAGES}
_ACK_HEAD_READER = _FieldsReader.of(MESSAGES_BY_NAME["ack"].fields, "ack")
_RETURNS_READERS: dict[int, _FieldsReader] = {c.id: _FieldsReader.of(c.returns, f"ack.{c.name}")
                                              for c in HOST_COMMANDS}
_STATE_CLASSES: dict[int, tuple[type, int]] = {MESSAGES_BY_NAME[name].id: (cls, len(names))
                                               for name, (cls, names) in _STATE_FIELDS.items()}


def _read_fields(args: Sequence[Arg], raw: Sequence[bytes], what: str) -> dict[str, Any]:
    return _FieldsReader.of(args, what).read(raw)


def decode_controller_frame(frame: Frame) -> ControllerMessage:
    """Controller -> host frame to a typed message; ProtocolError if it does not match the table."""
    state = _STATE_CLASSES.get(frame.cmd_id)
    if state is not None:  # the stream (and error events): most frames
        cls, n = state
        return cls(*_MESSAGE_READERS_BY_ID[frame.cmd_id].values(frame.fields)[:n])  # type: ignore[no-any-return]
    msg = MESSAGES_BY_ID.get(frame.cmd_id)
    if msg is None:
        raise ProtocolError(f"unknown controller message id {frame.cmd_id}")
    if msg.name == "ack":
        if len(frame.fields) < 2:
            raise ProtocolError("ack: needs seq and cmdId")
        seq, cmd_id = _ACK_HEAD_READER.values(frame.fields[:2])
        cmd = COMMANDS_BY_ID.get(cmd_id)
        if cmd is None:
            raise ProtocolError(f"ack for unknown command id {cmd_id}")
        return Ack(seq, cmd.id, cmd.name, _RETURNS_READERS[cmd.id].read(frame.fields[2:]))
    values = _MESSAGE_READERS[msg.name].read(frame.fields)
    if msg.name == "identify":
        return Identify(values["seq"], values["protocolVersion"], values["device"], values["firmwareVersion"])
    cmd = COMMANDS_BY_ID.get(values["cmdId"])  # "error"
    return ErrorReply(values["seq"], values["cmdId"], cmd.name if cmd else None, values["code"], values["message"])


_MESSAGE_READERS_BY_ID: dict[int, _FieldsReader] = {m.id: _MESSAGE_READERS[m.name] for m in CONTROLLER_MESSAGES}


# ---------------------------------------------------------------------------------------------
# Controller side (simulator / firmware mirror): decode host commands, encode replies and stream
# ---------------------------------------------------------------------------------------------


_STRICT_INT = re.compile(rb"-?[0-9]{1,10}")


def _convert_host_value(arg: Arg, data: bytes, seq: int, cmd_id: int) -> Any:
    """Firmware-side conversion of one raw (unescaped) argument, strict, with the table's ranges."""
    bad = ReplyError.BAD_ARGUMENT
    if arg.kind is F32:
        if len(data) != 4:
            raise CommandRejected(seq, cmd_id, bad, f"{arg.name}: {len(data)} bytes, expected a float32")
        (value,) = struct.unpack("<f", data)
        if not math.isfinite(value):
            raise CommandRejected(seq, cmd_id, bad, f"{arg.name} is not finite")
    elif arg.kind is BOOL:
        if data not in (b"0", b"1"):
            raise CommandRejected(seq, cmd_id, bad, f"{arg.name}: expected 0 or 1")
        return data == b"1"
    elif arg.kind is INT:
        if not _STRICT_INT.fullmatch(data):
            raise CommandRejected(seq, cmd_id, bad, f"{arg.name}: not an integer")
        value = int(data)
    else:  # pragma: no cover - the table has no other host argument kinds
        raise CommandRejected(seq, cmd_id, bad, f"{arg.name}: unsupported kind")
    lo, hi = arg.min, arg.max
    if arg.kind is F32:  # compare like the firmware: against the float32 bounds
        lo = None if lo is None else to_float32(lo)
        hi = None if hi is None else to_float32(hi)
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise CommandRejected(seq, cmd_id, ReplyError.OUT_OF_RANGE, f"{arg.name}={value:g} outside "
                              f"{arg.min:g}..{arg.max if arg.max is not None else 'inf'}")
    if arg.enum is not None:
        return ENUMS[arg.enum](value)
    return value


def _host_command(cmd_id: int, raw_seq: bytes | None, raw_args: list[bytes], extra: bool) -> HostCommand:
    seq = 0
    if raw_seq is not None and _STRICT_INT.fullmatch(raw_seq) and SEQ_MIN <= int(raw_seq) <= SEQ_MAX:
        seq = int(raw_seq)
    cmd = COMMANDS_BY_ID.get(cmd_id)
    if cmd is None:
        raise CommandRejected(seq, cmd_id, ReplyError.UNKNOWN_COMMAND, f"no command with id {cmd_id}")
    if raw_seq is None or not _STRICT_INT.fullmatch(raw_seq) or seq != int(raw_seq):
        raise CommandRejected(0, cmd_id, ReplyError.BAD_ARGUMENT, "missing or bad sequence number")
    if len(raw_args) != len(cmd.args) or extra:
        raise CommandRejected(seq, cmd_id, ReplyError.BAD_ARGUMENT,
                              f"{cmd.name} takes {len(cmd.args)} arguments")
    args = {a.name: _convert_host_value(a, d, seq, cmd_id) for a, d in zip(cmd.args, raw_args, strict=True)}
    return HostCommand(cmd.name, cmd.id, seq, args)


def decode_host_frame(frame: Frame) -> HostCommand:
    """Strict decode of a host command from a PC-side ``Frame`` (tests, tools, log replay).
    Raises CommandRejected with the reply the controller would send."""
    raw = list(frame.fields)
    raw_seq = raw[0] if raw else None
    args = raw[1:]
    if any(not f for f in raw):
        seq = int(raw_seq) if raw_seq and _STRICT_INT.fullmatch(raw_seq) else 0
        raise CommandRejected(seq if 0 <= seq <= SEQ_MAX else 0, frame.cmd_id, ReplyError.BAD_ARGUMENT,
                              "empty field")
    return _host_command(frame.cmd_id, raw_seq, args, extra=False)


def read_host_message(msg: ArduinoMessage) -> HostCommand:
    """What the firmware does in a callback: read seq and the table's arguments with the project's
    strict helpers on top of CmdMessenger 4.2.0, then check that no argument is left over."""
    if not msg.id_arg_ok:
        raise CommandRejected(0, msg.command_id, ReplyError.UNKNOWN_COMMAND, "message without a command id")
    raw_seq = msg.read_raw_field()
    cmd = COMMANDS_BY_ID.get(msg.command_id)
    n = len(cmd.args) if cmd else 0
    raw_args: list[bytes] = []
    for _ in range(n):
        data = msg.read_raw_field()
        if data is None:
            break
        raw_args.append(data)
    extra = len(raw_args) == n and msg.available()
    return _host_command(msg.command_id, raw_seq, raw_args, extra)


def encode_message(name: str, *values: Any) -> bytes:
    """Controller -> host frame for a table message, values in table order (no length limit)."""
    msg = MESSAGES_BY_NAME[name]
    optional = sum(1 for a in msg.fields if a.optional)
    if len(values) == len(msg.fields) - optional:
        values = (*values, *([""] * optional))
    return encode_frame(msg.id, _fields_for(msg.fields, values), max_len=None)


def encode_ack(seq: int, command: str | int, *returns: Any) -> bytes:
    cmd = COMMANDS_BY_NAME[command] if isinstance(command, str) else COMMANDS_BY_ID[command]
    head = _fields_for(MESSAGES_BY_NAME["ack"].fields, (seq, cmd.id))
    return encode_frame(MESSAGES_BY_NAME["ack"].id, head + _fields_for(cmd.returns, returns), max_len=None)


def encode_error(seq: int, cmd_id: int, code: ReplyError, message: str = "") -> bytes:
    return encode_message("error", seq, cmd_id, int(code), _safe_text(message))


def encode_rejection(rejected: CommandRejected) -> bytes:
    return encode_error(rejected.seq, rejected.cmd_id, rejected.code, rejected.message)


def encode_identify(seq: int, firmware_version: str) -> bytes:
    return encode_message("identify", seq, PROTOCOL_VERSION, DEVICE_NAME, firmware_version)


def _safe_text(text: str) -> str:
    return text.encode("ascii", "replace").decode("ascii")[:120]


def _encode_state(name: str, state: Any) -> bytes:
    fast = _STREAM_ENCODERS.get(name)
    if fast is not None:
        return fast.encode(state)
    _, names = _STATE_FIELDS[name]
    values = [getattr(state, n) for n in names]
    values = [int(v) if isinstance(v, IntEnum) else v for v in values]
    if name == "errorEvent":
        values[-1] = _safe_text(values[-1])
    return encode_message(name, *values)


_FLOAT32_LIMIT = float(FLOAT32_MAX)


class _StreamEncoder:
    """``encode_message(name, *values)`` of one stream message (the controller's 200 Hz state frames), worked out
    once: the id's text, each field's packer. Byte for byte the same frame, and the same errors: a value the fast
    checks do not pass (another type, out of range, not finite) goes through ``_check_value`` and
    ``encode_field`` as before. The simulated LINarm encodes ~600 of these a second (#38: 37-45 µs each the
    generic way, ~7 µs here)."""

    def __init__(self, name: str) -> None:
        msg = MESSAGES_BY_NAME[name]
        _, names = _STATE_FIELDS[name]
        if len(names) != len(msg.fields) or any(a.optional for a in msg.fields):
            raise ValueError(f"{name}: not a plain stream message")
        self.prefix = str(msg.id).encode("ascii")
        self.get = operator.attrgetter(*names)
        self.fields = tuple((arg, struct.Struct(arg.kind.value).pack if arg.kind in (F32, U32) else None)
                            for arg in msg.fields)

    def encode(self, state: Any) -> bytes:
        parts = [self.prefix]
        append = parts.append
        for (arg, pack), v in zip(self.fields, self.get(state), strict=True):
            kind = arg.kind
            if kind is F32:
                if type(v) is float and -_FLOAT32_LIMIT <= v <= _FLOAT32_LIMIT:  # NaN fails both comparisons
                    append(escape(pack(v)))  # type: ignore[misc]
                    continue
            elif kind is U32:
                if type(v) is int and 0 <= v <= 0xFFFFFFFF:
                    append(escape(pack(v)))  # type: ignore[misc]
                    continue
            elif kind is INT:
                if isinstance(v, int) and not isinstance(v, bool):
                    v = int(v)  # an IntEnum member: its number
                    if arg.min is None or arg.min <= v <= arg.max:  # type: ignore[operator]
                        append(str(v).encode("ascii"))  # digits and '-': nothing to escape
                        continue
            elif kind is BOOL:
                if v is True or v is False:
                    append(b"1" if v else b"0")
                    continue
            if isinstance(v, IntEnum):
                v = int(v)
            append(encode_field(kind, _check_value(arg, v)))  # the general way: its errors
        return b",".join(parts) + b";"


_STREAM_ENCODERS: dict[str, _StreamEncoder] = {name: _StreamEncoder(name)
                                               for name in ("linarmState", "motorState", "vsaState")}


def encode_linarm_state(state: LinarmState) -> bytes:
    return _encode_state("linarmState", state)


def encode_motor_state(state: MotorState) -> bytes:
    return _encode_state("motorState", state)


def encode_vsa_state(state: VsaState) -> bytes:
    return _encode_state("vsaState", state)


def encode_error_event(event: ErrorEvent) -> bytes:
    return _encode_state("errorEvent", event)


# ---------------------------------------------------------------------------------------------
# Sizes and export
# ---------------------------------------------------------------------------------------------

_TEXT_WORST = {BOOL: 1}


def worst_case_field_length(arg: Arg) -> int:
    """Longest escaped encoding of one argument (binary: every byte escaped)."""
    if arg.kind in (F32, U32):
        return 2 * struct.calcsize(arg.kind.value)
    if arg.kind is BOOL:
        return 1
    if arg.kind is INT:
        assert arg.min is not None and arg.max is not None, f"{arg.name} needs a range"
        return max(len(str(int(arg.min))), len(str(int(arg.max))))
    raise ValueError(f"no worst case for {arg.kind}")


def worst_case_command_length(name: str) -> int:
    """Longest possible bytes before ';' of a host command."""
    cmd = COMMANDS_BY_NAME[name]
    return len(str(cmd.id)) + sum(1 + worst_case_field_length(a) for a in (SEQ, *cmd.args))


def _arg_dict(arg: Arg) -> dict[str, Any]:
    d = asdict(arg)
    d["kind"] = arg.kind.value
    return {k: v for k, v in d.items() if v is not None and v is not False and v != ""}


def protocol_table() -> dict[str, Any]:
    """Everything above as JSON-serialisable data (for the firmware's header generator and the docs)."""
    return {
        "protocol_version": PROTOCOL_VERSION,
        "device": DEVICE_NAME,
        "limits": {
            "arduino_max_message": ARDUINO_MAX_MESSAGE,
            "max_callbacks": MAX_CALLBACKS,
            "seq_min": SEQ_MIN,
            "seq_max": SEQ_MAX,
            "heartbeat_period_s": HEARTBEAT_PERIOD,
            "watchdog_timeout_s": WATCHDOG_TIMEOUT,
            "default_stream_period_s": DEFAULT_STREAM_PERIOD,
            "linarm_state_divider": LINARM_STATE_DIVIDER,
        },
        "kinds": {k.value: k.name for k in Kind},
        "enums": {name: {m.name: int(m) for m in enum} for name, enum in ENUMS.items()},
        "host_commands": [
            {
                "id": c.id,
                "name": c.name,
                "args": [_arg_dict(a) for a in (SEQ, *c.args)],
                "returns": [_arg_dict(a) for a in c.returns],
                "reply": c.reply,
                "doc": c.doc,
                "worst_case_length": worst_case_command_length(c.name),
            }
            for c in HOST_COMMANDS
        ],
        "controller_messages": [
            {"id": m.id, "name": m.name, "fields": [_arg_dict(a) for a in m.fields], "doc": m.doc}
            for m in CONTROLLER_MESSAGES
        ],
        "constants": constants_table(),
    }
