"""LINarm protocol table, encoders and decoders."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.wire.cmdmessenger import (
    ARDUINO_MAX_MESSAGE,
    MAX_CALLBACKS,
    ArduinoReceiver,
    CmdMessengerDecoder,
    FieldError,
    Frame,
    Kind,
    read_field,
    to_float32,
)
from app.wire.linarm_protocol import (
    COMMANDS_BY_ID,
    CONTROL_MODES,
    CONTROL_STATES,
    CONTROLLER_MESSAGES,
    ENUMS,
    ERROR_STATES,
    HOST_COMMANDS,
    MESSAGES_BY_ID,
    SEQ,
    SEQ_MAX,
    TRAJECTORY_TYPES,
    Ack,
    CommandRejected,
    ControlMode,
    ControlState,
    ErrorEvent,
    ErrorReply,
    ErrorState,
    HomeState,
    Identify,
    LinarmState,
    MotorState,
    ProtocolError,
    ReplyError,
    TrajectoryType,
    TriggerMode,
    VsaState,
    decode_controller_frame,
    decode_host_frame,
    encode_ack,
    encode_command,
    encode_error,
    encode_error_event,
    encode_identify,
    encode_linarm_state,
    encode_motor_state,
    encode_vsa_state,
    next_seq,
    protocol_table,
    read_host_message,
    worst_case_command_length,
)

PROPS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# a float32 whose four bytes are all separators: the worst case for escaping
WORST_FLOAT = struct.unpack("<f", b",;/,")[0]


def one_frame(data: bytes) -> Frame:
    (frame,) = CmdMessengerDecoder().feed(data)
    return frame


def test_enums_match_the_seed() -> None:
    assert [(m.name, int(m)) for m in CONTROL_STATES] == [
        ("IDLE_CTRL_STATE", 0), ("HOME_CTRL_STATE", 1), ("ON_CTRL_STATE", 2)]
    assert [(m.name, int(m)) for m in CONTROL_MODES] == [
        ("POS_REF_BY_VEL", 0), ("POS_REF_BY_TARGET_POS", 1), ("POS_REF_BY_IMPEDANCE", 2),
        ("POS_REF_BY_ADMITTANCE", 3), ("POS_REF_BY_ASSISTANCE", 4)]
    assert ERROR_STATES.NO_ERROR == 0 and ERROR_STATES.WATCHDOG.name == "WATCHDOG"
    assert (TRAJECTORY_TYPES.TRAPEZOIDAL, TRAJECTORY_TYPES.CYCLOIDAL) == (0, 1)


def test_every_seed_service_has_a_command() -> None:
    seed = """setDemo resetError setCtrlState setCtrlMode setCentreVelocity setDeltaVelocity getPidTunings
    moveCentreTo moveDeltaTo setStiffness goToHome setTrajectoryType setAdmittanceParameter
    getAdmittanceParameter setAssistanceParameter getAssistanceParameter setAssistanceTargetPos
    getAssistanceTargetPos enableVirtualVsa setVirtualVsaSpringDisplacement getIsInitialized
    disableEndstrokes setTriggerMode setTriggerParameter startDataStream stopDataStream setMotorOffset
    setMobileOffset setMotorRatio setMobileRatio setMaxTrackingError setMaxForce setMaxCurrent
    setMaxAcceleration setMaxVelocity setHomeParameter setPosLimit setPidTunings heartbeat""".split()
    names = {c.name for c in HOST_COMMANDS}
    assert set(seed) <= names
    ids = [c.id for c in HOST_COMMANDS]
    assert len(set(ids)) == len(ids) and max(ids) < MAX_CALLBACKS  # attached callbacks only
    assert {m.id for m in CONTROLLER_MESSAGES}.isdisjoint(ids)


def test_command_zero_is_harmless_identify() -> None:
    (cmd0,) = [c for c in HOST_COMMANDS if c.id == 0]
    assert cmd0.name == "identify" and cmd0.args == ()
    # garbage before a frame reaches id 0 on the Arduino: it decodes as identify or as a rejection
    (msg,) = ArduinoReceiver().feed(b"\xff\xfegarbage;")
    with pytest.raises(CommandRejected) as info:
        read_host_message(msg)
    assert (info.value.cmd_id, info.value.code, info.value.seq) == (0, ReplyError.BAD_ARGUMENT, 0)
    (msg,) = ArduinoReceiver().feed(b"\xffgarbage,12;")
    assert read_host_message(msg).name == "identify"


def _worst_value(arg: object) -> object:
    kind = arg.kind  # type: ignore[attr-defined]
    if kind is Kind.BIN_FLOAT:
        return WORST_FLOAT
    if kind is Kind.TEXT_BOOL:
        return True
    lo, hi = int(arg.min), int(arg.max)  # type: ignore[attr-defined]
    return lo if len(str(lo)) > len(str(hi)) else hi


@pytest.mark.parametrize("command", HOST_COMMANDS, ids=lambda c: c.name)
def test_largest_encoding_of_every_command_fits_62_bytes(command: object) -> None:
    name = command.name  # type: ignore[attr-defined]
    worst = worst_case_command_length(name)
    assert worst <= ARDUINO_MAX_MESSAGE
    args = [_worst_value(a) for a in command.args]  # type: ignore[attr-defined]
    data = encode_command(name, SEQ_MAX, *args)
    assert len(data) - 1 == worst  # the computed worst case is really reached
    # and the Arduino model receives it whole, as one message with the right id
    (msg,) = ArduinoReceiver().feed(data)
    assert msg.command_id == command.id  # type: ignore[attr-defined]
    decoded = read_host_message(msg) if name != "startDataStream" else None
    if decoded is not None:
        assert decoded.seq == SEQ_MAX


def test_encode_command_checks_arguments() -> None:
    assert encode_command("goToHome", 5) == b"12,5;"
    assert encode_command("setCtrlState", 6, ControlState.ON_CTRL_STATE) == b"4,6,2;"
    with pytest.raises(TypeError):
        encode_command("setCtrlState", 1)  # missing argument
    with pytest.raises(ValueError):
        encode_command("setCtrlState", 1, 7)  # not an enum value
    with pytest.raises(ValueError):
        encode_command("moveCentreTo", 1, float("nan"), 0.1, 0.1, 0.0, False)
    with pytest.raises(ValueError):
        encode_command("goToHome", 70000)
    with pytest.raises(ValueError):
        encode_command("noSuchCommand", 1)
    with pytest.raises(TypeError):
        encode_command("setDemo", 1, 2)


def test_next_seq_skips_zero() -> None:
    assert next_seq(0) == 1 and next_seq(41) == 42 and next_seq(SEQ_MAX) == 1


@PROPS
@given(st.sampled_from(HOST_COMMANDS), st.integers(1, SEQ_MAX), st.data())
def test_host_commands_round_trip_through_both_receivers(command: object, seq: int, data: st.DataObject) -> None:
    args = []
    for a in command.args:  # type: ignore[attr-defined]
        if a.kind is Kind.BIN_FLOAT:
            lo = to_float32(-1e6 if a.min is None else a.min)
            hi = to_float32(1e6 if a.max is None else a.max)
            args.append(data.draw(st.floats(lo, hi).map(to_float32).filter(lambda v, lo=lo, hi=hi: lo <= v <= hi)))
        elif a.kind is Kind.TEXT_BOOL:
            args.append(data.draw(st.booleans()))
        else:
            args.append(data.draw(st.integers(int(a.min), int(a.max))))
    wire = encode_command(command.name, seq, *args)  # type: ignore[attr-defined]
    strict = decode_host_frame(one_frame(wire))
    (msg,) = ArduinoReceiver().feed(wire)
    firmware = read_host_message(msg)
    assert strict == firmware
    assert strict.name == command.name and strict.seq == seq  # type: ignore[attr-defined]
    assert list(strict.args.values()) == args


def test_host_frame_rejections() -> None:
    def rejected(data: bytes) -> CommandRejected:
        (msg,) = ArduinoReceiver().feed(data)
        with pytest.raises(CommandRejected) as info:
            read_host_message(msg)
        return info.value

    r = rejected(b"4,9;")  # missing argument
    assert (r.seq, r.code) == (9, ReplyError.BAD_ARGUMENT)
    assert rejected(b"4,9,1,1;").code is ReplyError.BAD_ARGUMENT  # one too many
    assert rejected(b"4,9,7;").code is ReplyError.OUT_OF_RANGE  # not a control state
    assert rejected(b"4,9,x;").code is ReplyError.BAD_ARGUMENT
    assert rejected(b"2,9,true;").code is ReplyError.BAD_ARGUMENT  # readBoolArg would say false
    assert rejected(b"6,9,\x00\x00;").code is ReplyError.BAD_ARGUMENT  # short float field
    assert rejected(b"6,9," + b"\x00\x00\xc0\x7f".replace(b"\x00", b"/\x00") + b";").code is ReplyError.BAD_ARGUMENT
    assert rejected(b"45,9;").code is ReplyError.UNKNOWN_COMMAND
    assert rejected(b"12,abc;").seq == 0
    with pytest.raises(CommandRejected):
        decode_host_frame(Frame(4, (b"9", b"")))  # empty field


def test_controller_messages_round_trip() -> None:
    state = LinarmState(123456, ControlState.ON_CTRL_STATE, ControlMode.POS_REF_BY_ASSISTANCE, HomeState.HOME_DONE,
                        ErrorState.NO_ERROR, TriggerMode.NO_TRIGGER, True, TrajectoryType.CYCLOIDAL, False, True, False)
    motor = MotorState(2**32 - 1, 1, 0.25, -0.125, 1.5, 0.25)
    vsa = VsaState(0, 0.25, 0.125, 900.0, 0.2578125, 0.0, -7.0)
    event = ErrorEvent(5, ErrorState.OVER_FORCE, ControlState.IDLE_CTRL_STATE, "force 61.0 N, over; limit/")
    stream = encode_linarm_state(state) + encode_motor_state(motor) + encode_vsa_state(vsa) + encode_error_event(event)
    decoded = [decode_controller_frame(f) for f in CmdMessengerDecoder().feed(stream)]
    assert decoded == [state, motor, vsa, event]
    assert isinstance(decoded[0].control_mode, ControlMode)
    assert vsa.centre == vsa.equilibrium_pos
    assert decode_controller_frame(one_frame(encode_ack(3, "getPidTunings", 1, 20000.0, 1e5, 200.0))) == Ack(
        3, 8, "getPidTunings", {"index": 1, "kp": 20000.0, "ki": 1e5, "kd": 200.0})
    assert decode_controller_frame(one_frame(encode_ack(4, "goToHome"))) == Ack(4, 12, "goToHome", {})
    assert decode_controller_frame(one_frame(encode_error(5, 9, ReplyError.OUT_OF_RANGE, "x=1"))) == ErrorReply(
        5, 9, "moveCentreTo", ReplyError.OUT_OF_RANGE, "x=1")
    assert decode_controller_frame(one_frame(encode_error(5, 9, ReplyError.WRONG_MODE))).message == ""
    assert decode_controller_frame(one_frame(encode_identify(0, "fw-2"))) == Identify(0, 1, "LINarm2", "fw-2")


def test_stream_frames_fit_the_link_budget() -> None:
    # 200 Hz of MOTOR x2 + VSA, LINARM every 10th tick: typical size, and worst case escaping
    motor = encode_motor_state(MotorState(10**9, 0, 0.1, 0.2, 0.3, 0.4))
    vsa = encode_vsa_state(VsaState(10**9, 0.25, 0.1, 900.0, 0.25, 0.01, 1.0))
    linarm = encode_linarm_state(LinarmState(10**9, ControlState.ON_CTRL_STATE, ControlMode.POS_REF_BY_VEL,
                                             HomeState.HOME_DONE, ErrorState.NO_ERROR, TriggerMode.NO_TRIGGER,
                                             True, TrajectoryType.TRAPEZOIDAL, False, False, False))
    per_second = 200 * (2 * len(motor) + len(vsa)) + 20 * len(linarm)
    assert per_second < 25_000  # bytes/s: fits 460800 baud (46 kB/s) with margin
    worst_t = struct.unpack("<I", b",;/\x00")[0]  # every byte escaped
    worst_motor = encode_motor_state(MotorState(worst_t, 0, *[WORST_FLOAT] * 4))
    worst_vsa = encode_vsa_state(VsaState(worst_t, *[WORST_FLOAT] * 6))
    assert (len(worst_motor), len(worst_vsa)) == (51, 67)  # the figures in docs/linarm-protocol.md
    assert (len(motor), len(vsa), len(linarm)) == (33, 49, 31)
    assert 200 * (2 * len(worst_motor) + len(worst_vsa)) + 20 * 33 <= 34_460 < 46_080


def test_decoder_rejects_frames_off_the_table() -> None:
    for frame in (Frame(99, ()), Frame(101, (b"1",)), Frame(101, (b"1", b"77")), Frame(110, (b"1",)),
                  Frame(111, (b"\x00\x00\x00\x00", b"2", *[b"\x00\x00\x00\x00"] * 4)),
                  Frame(112, (b"\x00\x00\x00\x00", *[b"\x00\x00\x00"] * 6)),
                  Frame(102, (b"1", b"2", b"99"))):
        with pytest.raises(ProtocolError):
            decode_controller_frame(frame)


@PROPS
@given(st.binary(max_size=400))
def test_garbage_never_crashes_the_host_side(garbage: bytes) -> None:
    for frame in CmdMessengerDecoder().feed(garbage):
        try:
            decode_controller_frame(frame)
        except ProtocolError:
            pass


# -- decode_controller_frame against the plain table-walking reference ------------------------------

def _reference_read_fields(args: tuple, raw: tuple[bytes, ...], what: str) -> dict:
    """The decoder's spec: walk the table's Args, read each field by its kind, check ranges, make enums."""
    optional = sum(1 for a in args if a.optional)
    if not len(args) - optional <= len(raw) <= len(args):
        raise ProtocolError(f"{what}: {len(raw)} fields, expected {len(args)}")
    out: dict = {}
    for arg, data in zip(args, raw, strict=False):
        try:
            value = read_field(data, arg.kind)
        except FieldError as exc:
            raise ProtocolError(f"{what}.{arg.name}: {exc}") from exc
        if arg.kind is Kind.TEXT_INT and not (arg.min is None or arg.min <= value <= arg.max):
            raise ProtocolError(f"{what}.{arg.name}={value} outside {arg.min}..{arg.max}")
        if arg.enum is not None:
            value = ENUMS[arg.enum](value)
        out[arg.name] = value
    for arg in args[len(raw):]:
        out[arg.name] = ""
    return out


def _reference_decode(frame: Frame) -> object:
    msg = MESSAGES_BY_ID.get(frame.cmd_id)
    if msg is None:
        raise ProtocolError(f"unknown controller message id {frame.cmd_id}")
    if msg.name == "ack":
        if len(frame.fields) < 2:
            raise ProtocolError("ack: needs seq and cmdId")
        head = _reference_read_fields(msg.fields, frame.fields[:2], "ack")
        cmd = COMMANDS_BY_ID.get(head["cmdId"])
        if cmd is None:
            raise ProtocolError(f"ack for unknown command id {head['cmdId']}")
        return Ack(head["seq"], cmd.id, cmd.name, _reference_read_fields(cmd.returns, frame.fields[2:],
                                                                         f"ack.{cmd.name}"))
    v = _reference_read_fields(msg.fields, frame.fields, msg.name)
    if msg.name == "identify":
        return Identify(v["seq"], v["protocolVersion"], v["device"], v["firmwareVersion"])
    if msg.name == "error":
        cmd = COMMANDS_BY_ID.get(v["cmdId"])
        return ErrorReply(v["seq"], v["cmdId"], cmd.name if cmd else None, v["code"], v["message"])
    cls = {"linarmState": LinarmState, "motorState": MotorState, "vsaState": VsaState, "errorEvent": ErrorEvent}
    return cls[msg.name](*v.values())


def _outcome(decode: Callable[[Frame], object], frame: Frame) -> tuple[str, str]:
    """Type and repr of the message (NaN equals NaN, enum members shown), or the error's type and text."""
    try:
        msg = decode(frame)
    except Exception as exc:  # any difference in what is raised is a difference
        return type(exc).__name__, str(exc)
    return type(msg).__name__, repr(msg)


def _field_for(arg: object) -> st.SearchStrategy[bytes]:
    kind = arg.kind  # type: ignore[attr-defined]
    if kind is Kind.TEXT_INT:
        lo = -3 if arg.min is None else int(arg.min) - 2  # type: ignore[attr-defined]
        hi = 300 if arg.max is None else int(arg.max) + 2  # type: ignore[attr-defined]
        return st.integers(lo, hi).map(lambda v: str(v).encode())
    if kind is Kind.TEXT_BOOL:
        return st.sampled_from([b"0", b"1", b"2", b"", b"true"])
    if kind is Kind.TEXT_STR:
        return st.binary(max_size=12)
    return st.binary(min_size=4, max_size=4)  # float32 / uint32 (NaN and inf included)


@st.composite
def _controller_frames(draw: st.DrawFn) -> Frame:
    if draw(st.integers(0, 9)) == 0:  # anything at all
        return Frame(draw(st.integers(0, 255)), tuple(draw(st.lists(st.binary(max_size=9), max_size=13))))
    msg = draw(st.sampled_from(CONTROLLER_MESSAGES))
    args = list(msg.fields)
    if msg.name == "ack":
        cmd = draw(st.sampled_from(HOST_COMMANDS))
        fields = [draw(_field_for(args[0])), str(draw(st.sampled_from([cmd.id, cmd.id, 46, 99]))).encode()]
        fields += [draw(_field_for(a)) for a in cmd.returns]
    else:
        fields = [draw(_field_for(a)) for a in args]
    if draw(st.booleans()):  # damage: drop, add or replace a field
        choice = draw(st.sampled_from(["drop", "add", "replace"]))
        at = draw(st.integers(0, len(fields)))
        junk = draw(st.binary(max_size=9))
        if choice == "drop" and fields:
            del fields[min(at, len(fields) - 1)]
        elif choice == "add":
            fields.insert(at, junk)
        elif fields:
            fields[min(at, len(fields) - 1)] = junk
    return Frame(msg.id, tuple(fields))


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_controller_frames())
def test_decoder_equals_the_table_walking_reference(frame: Frame) -> None:
    assert _outcome(decode_controller_frame, frame) == _outcome(_reference_decode, frame)


def test_protocol_table_is_json_and_complete() -> None:
    table = json.loads(json.dumps(protocol_table()))
    assert table["limits"]["arduino_max_message"] == 62
    cmds = {c["name"]: c for c in table["host_commands"]}
    assert cmds["identify"]["id"] == 0
    assert [a["name"] for a in cmds["moveCentreTo"]["args"]] == [
        "seq", "targetPos", "maxVel", "maxAcc", "execTime", "trigger"]
    assert cmds["moveCentreTo"]["args"][1] == {"name": "targetPos", "kind": "<f", "unit": "m"}
    assert all(c["worst_case_length"] <= 62 for c in table["host_commands"])
    assert table["enums"]["CONTROL_MODES"]["POS_REF_BY_ASSISTANCE"] == 4
    assert {m["name"] for m in table["controller_messages"]} >= {"ack", "error", "linarmState", "vsaState"}
    assert SEQ.name == "seq"
