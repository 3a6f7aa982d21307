"""UDP frame codecs: manager <-> patient model, manager <-> VR renderer.  One place for the layouts.

The seed (D2.1, "Connections") fixes only sizes: manager -> patient model 40 bytes at 100 Hz,
manager -> VR renderer 32 bytes at 50 Hz.  Decided here (tables below, rendered into
docs/physio-and-udp-frames.md):

* little-endian; a 2-byte ASCII header per direction (``LP`` manager->patient model, ``PL`` its
  reply, ``LV`` manager->VR, ``VL`` VR events); a 16-bit sequence number; a CRC-16/CCITT-FALSE of
  every byte before it in the last two bytes (UDP's own checksum is optional on IPv4);
* 4-byte fields are float32 in SI units; 2-byte physical fields are fixed-point: ``value = raw *
  scale``, saturating at the range limits; the most negative int16 (-32768) / the largest uint16
  (65535) means "not available" and decodes to NaN;
* "task data" (8 bytes, same in both frames): sub-task index, task state, task flags, time in the
  sub-task, game score; "additional data": sequence number, clinical score / assistance level,
  system flags, CRC.

Decoders raise ``FrameError`` (a ``ValueError``) with a reason on a wrong size, header, CRC or an
out-of-range value, and raise nothing else on any input.

Authentication (our own embedded model and VR stand-in; optional for an ``external`` peer, whose
datagrams keep the seed's plain layout): the frame is followed by ``MAC_SIZE`` bytes of
HMAC-SHA256(key, frame), truncated (``seal`` / ``unseal``), with a per-session ``KEY_SIZE``-byte key the
manager creates and hands to its helper process privately (environment, never the command line).
Replays are refused by ``SequenceGuard`` (each direction's 16-bit sequence number must increase,
modulo wrap-around) on both ends; the manager also refuses a reply acknowledging no frame it sent in
the last ``ACK_WINDOW_S``.  Encoders raise ``ValueError`` on values
that have no encoding (alpha outside [-1, 1], an index outside [0, 1]).
"""

from __future__ import annotations

import binascii
import enum
import functools
import hashlib
import hmac
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

from app.wire.physio_codec import Field, Layout

PATIENT_MODEL_RATE_HZ: Final = 100.0
VR_RATE_HZ: Final = 50.0

FORCE_SCALE: Final = 0.01          # N per count, int16: ±327.67 N
CONDUCTANCE_SCALE: Final = 0.01    # µS per count, uint16: 0..655.34 µS
TEMPERATURE_SCALE: Final = 0.01    # °C per count, int16: ±327.67 °C
POSITION_SCALE: Final = 2e-5       # m per count, int16: ±0.65534 m in 20 µm steps
SUBTASK_TIME_SCALE: Final = 0.01   # s per count, uint16: 0..655.34 s
Q15: Final = 1.0 / 32767.0         # int16 fraction: ±1
LEVEL_SCALE: Final = 1.0 / 255.0   # uint8 fraction: 0..1

MAC_SIZE: Final = 8          # bytes of HMAC-SHA256 kept (64 bits: forging one takes ~2^63 tries)
KEY_SIZE: Final = 32         # bytes of per-session key
ACK_WINDOW_S: Final = 0.5    # a reply must acknowledge a frame sent this recently
LINK_KEY_ENV: Final = "LINARMPP_LINK_KEY"  # how the manager hands the key to its helper process (hex)

INT16_NA: Final = -32768
UINT16_NA: Final = 0xFFFF
CLINICAL_SCORE_NA: Final = 0xFF


class FrameError(ValueError):
    """A datagram that is not a valid frame; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class TaskState(enum.IntEnum):
    IDLE = 0
    MOVING = 1      # a sub-task (reach a target) is running
    HOLDING = 2     # in the target, holding
    REACHED = 3     # sub-task completed
    FAILED = 4      # sub-task timed out / given up
    REST = 5


class TaskFlag(enum.IntFlag):
    GRIP_TRIGGERED = 0x01  # grip force above the exercise threshold
    IN_TARGET = 0x02       # handle within the target tolerance


class SystemFlag(enum.IntFlag):
    PHYSIO_VALID = 0x01    # physiological stream fresh and fault-free
    ROBOT_ON = 0x02
    FES_ON = 0x04
    EMERGENCY_STOP = 0x08


class ReplyFlag(enum.IntFlag):
    VALID = 0x01      # the model had enough data for every index
    FALLBACK = 0x02   # some index missing: its neutral value was used


class VrEvent(enum.IntEnum):
    HELLO = 1            # renderer (re)started
    SUBTASK_STARTED = 2
    TARGET_REACHED = 3
    TARGET_MISSED = 4
    SCORE = 5
    PAUSED = 6
    RESUMED = 7
    QUIT = 8


_TASK_FIELDS: Final = (
    Field("subTask", "H", "", "task data: index of the current sub-task in the exercise"),
    Field("taskState", "B", "", "task data: TaskState (0 idle, 1 moving, 2 holding, 3 reached, 4 failed,"
          " 5 rest)"),
    Field("taskFlags", "B", "", "task data: TaskFlag bits (0x01 grip triggered, 0x02 in target)"),
    Field("subTaskTime", "H", "s", "task data: time since the sub-task started (65535 = n/a)",
          SUBTASK_TIME_SCALE),
    Field("score", "H", "", "task data: game score (saturates at 65535)"),
)
_SYSTEM_FLAGS_DOC: Final = "SystemFlag bits (0x01 physio valid, 0x02 robot on, 0x04 FES on, 0x08 e-stop)"

PATIENT_MODEL_LAYOUT: Final = Layout(
    title="Manager -> patient model (UDP, 100 Hz)",
    header=b"LP", size=40,
    fields=(
        Field("header", "2s", "", "ASCII 'LP'"),
        Field("heartRate", "f", "bpm", "float32, NaN = not available"),
        Field("skinConductance", "H", "µS", "uint16 fixed-point", CONDUCTANCE_SCALE),
        Field("temperature", "h", "°C", "int16 fixed-point, skin temperature", TEMPERATURE_SCALE),
        Field("force", "h", "N", "int16 fixed-point, grip force", FORCE_SCALE),
        Field("interactionForce", "h", "N", "int16 fixed-point, handle force, + toward +x", FORCE_SCALE),
        Field("robotVelocity", "f", "m/s", "float32, handle velocity"),
        Field("robotPosition", "h", "m", "int16 fixed-point, handle position", POSITION_SCALE),
        Field("targetPosition", "f", "m", "float32, current target"),
        *_TASK_FIELDS,
        Field("seq", "H", "", "additional: sequence number, +1 per frame, wraps"),
        Field("clinicalScore", "B", "", "additional: clinical score set by the therapist (255 = n/a)"),
        Field("flags", "B", "", "additional: " + _SYSTEM_FLAGS_DOC),
        Field("reserved", "2s", "", "additional: zero"),
        Field("crc", "H", "", "additional: CRC-16/CCITT-FALSE of bytes 0..37"),
    ),
)

PATIENT_MODEL_REPLY_LAYOUT: Final = Layout(
    title="Patient model -> manager (UDP, one per received frame or slower)",
    header=b"PL", size=32,
    fields=(
        Field("header", "2s", "", "ASCII 'PL'"),
        Field("seq", "H", "", "reply sequence number, wraps"),
        Field("ackSeq", "H", "", "seq of the latest manager frame used"),
        Field("alpha", "f", "", "float32 assistance level: +1 full assistance .. -1 full resistance"),
        Field("tpi", "f", "", "float32 Task Performance Index 0..1"),
        Field("mpi", "f", "", "float32 Motor Performance Index 0..1"),
        Field("pti", "f", "", "float32 Physiological Trend Index 0..1"),
        Field("alphaMin", "h", "", "int16 Q15, lower end of the final alpha range", Q15),
        Field("alphaMax", "h", "", "int16 Q15, upper end of the final alpha range", Q15),
        Field("path", "B", "", "decision path code (see decision_tree.path_code)"),
        Field("level", "B", "", "layer-5 support level inside the range, 0..1", LEVEL_SCALE),
        Field("flags", "B", "", "ReplyFlag bits (0x01 valid, 0x02 fallback)"),
        Field("reserved", "1s", "", "zero"),
        Field("crc", "H", "", "CRC-16/CCITT-FALSE of bytes 0..29"),
    ),
)

VR_LAYOUT: Final = Layout(
    title="Manager -> VR renderer (UDP, 50 Hz)",
    header=b"LV", size=32,
    fields=(
        Field("header", "2s", "", "ASCII 'LV'"),
        Field("force", "h", "N", "int16 fixed-point, grip force", FORCE_SCALE),
        Field("interactionForce", "h", "N", "int16 fixed-point, handle force, + toward +x", FORCE_SCALE),
        Field("robotVelocity", "f", "m/s", "float32, handle velocity"),
        Field("robotPosition", "h", "m", "int16 fixed-point, handle position", POSITION_SCALE),
        Field("targetPosition", "f", "m", "float32, current target"),
        *_TASK_FIELDS,
        Field("seq", "H", "", "additional: sequence number, +1 per frame, wraps"),
        Field("alpha", "h", "", "additional: int16 Q15 assistance level being applied", Q15),
        Field("flags", "B", "", "additional: " + _SYSTEM_FLAGS_DOC),
        Field("reserved", "1s", "", "additional: zero"),
        Field("crc", "H", "", "additional: CRC-16/CCITT-FALSE of bytes 0..29"),
    ),
)

VR_EVENT_LAYOUT: Final = Layout(
    title="VR renderer -> manager (UDP, on events)",
    header=b"VL", size=16,
    fields=(
        Field("header", "2s", "", "ASCII 'VL'"),
        Field("seq", "H", "", "event sequence number, wraps"),
        Field("event", "B", "", "VrEvent (1 hello, 2 sub-task started, 3 target reached, 4 target missed,"
              " 5 score, 6 paused, 7 resumed, 8 quit)"),
        Field("reserved", "1s", "", "zero"),
        Field("subTask", "H", "", "sub-task index the event refers to"),
        Field("score", "I", "", "game score after the event"),
        Field("timeToTarget", "H", "s", "uint16 fixed-point, sub-task duration (65535 = n/a)", 0.001),
        Field("crc", "H", "", "CRC-16/CCITT-FALSE of bytes 0..13"),
    ),
)

ALL_UDP_LAYOUTS: Final = (PATIENT_MODEL_LAYOUT, PATIENT_MODEL_REPLY_LAYOUT, VR_LAYOUT, VR_EVENT_LAYOUT)

# ---------------------------------------------------------------------------------------------
# Table-driven packing, compiled once per layout (the drivers run it hundreds of times a second)

_INT_LIMITS: Final = {"h": (-32767, 32767, INT16_NA), "H": (0, 65534, UINT16_NA),
                      "B": (0, 255, None), "I": (0, 0xFFFFFFFF, None)}
_FIXED: Final = ("header", "crc", "reserved")  # not carried in the values: constants of the layout


def _nan_error(name: str) -> int:
    raise ValueError(f"{name}: NaN has no encoding")


def _decoder(f: Field) -> Callable[[Any], Any] | None:
    """raw -> value of ``f``; None when the raw value is the value."""
    if f.scale is None or f.fmt == "f":
        return None
    na, scale = _INT_LIMITS[f.fmt][2], f.scale
    if na is None:
        return lambda raw: raw * scale
    return lambda raw: math.nan if raw == na else raw * scale


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (``physio_codec.crc16_ccitt``, the one definition; tests hold them equal),
    computed by the C library's ``binascii.crc_hqx``: 20× faster than the table loop."""
    return binascii.crc_hqx(data, 0xFFFF)


class _Codec:
    """One layout's packer / unpacker, made once from its table.  The packer is generated source (one
    expression per field, as ``_encoder`` would convert it): a call per field was most of a frame's cost."""

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        self.header = layout.header
        self.frame = struct.Struct(layout.struct_format)
        self.size = layout.size
        self.pack: Callable[[dict[str, Any]], bytes] = self._make_packer(layout)
        self.unpack_plan = tuple((i, f.name, _decoder(f)) for i, f in enumerate(layout.fields)
                                 if f.name not in _FIXED)

    @staticmethod
    def _make_packer(layout: Layout) -> Callable[[dict[str, Any]], bytes]:
        env: dict[str, Any] = {"_body": struct.Struct(layout.struct_format[:-1]),  # all but the CRC ("H")
                               "_crc": crc16, "_header": layout.header, "_nan_error": _nan_error}
        args = []
        for f in layout.fields[:-1]:
            if f.name == "header":
                args.append("_header")
            elif f.name == "reserved":
                args.append("b''")
            elif f.fmt == "f":
                args.append(f"float(v[{f.name!r}])")
            else:
                lo, hi, na = _INT_LIMITS[f.fmt]
                if f.scale is None:  # plain integers use the whole range: no "not available" code
                    lo, hi = (-32768, 32767) if f.fmt == "h" else (0, 65535) if f.fmt == "H" else (lo, hi)
                    args.append(f"min({hi}, max({lo}, int(v[{f.name!r}])))")
                else:
                    on_nan = f"_nan_error({f.name!r})" if na is None else str(na)
                    args.append(f"({on_nan} if (x := float(v[{f.name!r}])) != x "
                                f"else min({hi}, max({lo}, round(x / {f.scale!r}))))")
        source = ("def pack(v):\n"
                  f"    body = _body.pack({', '.join(args)})\n"
                  "    return body + _crc(body).to_bytes(2, 'little')\n")
        exec(compile(source, f"<packer of {layout.title}>", "exec"), env)  # our own table, at import
        return env["pack"]  # type: ignore[no-any-return]

    def unpack(self, data: Any) -> dict[str, Any]:
        if not isinstance(data, bytes | bytearray | memoryview):
            raise FrameError(f"not bytes: {type(data).__name__}")
        raw = bytes(data)
        layout = self.layout
        if len(raw) != self.size:
            raise FrameError(f"wrong size: {len(raw)} bytes, expected {layout.size}")
        if raw[:2] != self.header:
            raise FrameError(f"wrong header: {raw[:2].hex()}, expected {layout.header.hex()}")
        stored = int.from_bytes(raw[-2:], "little")
        computed = crc16(raw[:-2])
        if stored != computed:
            raise FrameError(f"bad CRC: {stored:04x}, computed {computed:04x}")
        values = self.frame.unpack(raw)
        return {name: values[i] if dec is None else dec(values[i]) for i, name, dec in self.unpack_plan}


_CODECS: Final = {layout.header: _Codec(layout) for layout in ALL_UDP_LAYOUTS}


def _pack(layout: Layout, values: dict[str, Any]) -> bytes:
    return _CODECS[layout.header].pack(values)


def _unpack(layout: Layout, data: Any) -> dict[str, Any]:
    return _CODECS[layout.header].unpack(data)


def _check_unit(name: str, value: float, lo: float, hi: float, exc: type[ValueError]) -> None:
    if not lo <= value <= hi:  # also rejects NaN
        raise exc(f"{name} out of range: {value!r}, expected {lo}..{hi}")


# ---------------------------------------------------------------------------------------------
# Frames


@dataclass(frozen=True)
class TaskData:
    subTask: int = 0
    taskState: TaskState = TaskState.IDLE
    taskFlags: int = 0
    subTaskTime: float = math.nan  # s
    score: int = 0

    def _values(self) -> dict[str, Any]:
        return {"subTask": self.subTask, "taskState": int(self.taskState), "taskFlags": self.taskFlags,
                "subTaskTime": self.subTaskTime, "score": self.score}

    @staticmethod
    def _from(values: dict[str, Any]) -> TaskData:
        try:
            state = TaskState(values["taskState"])
        except ValueError as exc:
            raise FrameError(f"unknown task state {values['taskState']}") from exc
        return TaskData(values["subTask"], state, values["taskFlags"], values["subTaskTime"], values["score"])


@dataclass(frozen=True)
class PatientModelFrame:
    """Manager -> patient model, 100 Hz."""

    seq: int
    heartRate: float          # bpm (NaN = n/a)
    skinConductance: float    # µS
    temperature: float        # °C
    force: float              # grip, N
    interactionForce: float   # N, + toward +x
    robotVelocity: float      # m/s
    robotPosition: float      # m
    targetPosition: float     # m
    task: TaskData = field(default_factory=TaskData)
    clinicalScore: int | None = None
    flags: int = 0


def encode_patient_model_frame(frame: PatientModelFrame) -> bytes:
    score = CLINICAL_SCORE_NA if frame.clinicalScore is None else frame.clinicalScore
    if not 0 <= score <= 254 and score != CLINICAL_SCORE_NA:
        raise ValueError(f"clinicalScore out of range: {score}, expected 0..254")
    values = {"seq": frame.seq & 0xFFFF, "heartRate": frame.heartRate,
              "skinConductance": frame.skinConductance, "temperature": frame.temperature,
              "force": frame.force, "interactionForce": frame.interactionForce,
              "robotVelocity": frame.robotVelocity, "robotPosition": frame.robotPosition,
              "targetPosition": frame.targetPosition, "clinicalScore": score, "flags": frame.flags & 0xFF,
              **frame.task._values()}
    return _pack(PATIENT_MODEL_LAYOUT, values)


def decode_patient_model_frame(data: bytes) -> PatientModelFrame:
    v = _unpack(PATIENT_MODEL_LAYOUT, data)
    score = v["clinicalScore"]
    return PatientModelFrame(
        seq=v["seq"], heartRate=v["heartRate"], skinConductance=v["skinConductance"],
        temperature=v["temperature"], force=v["force"], interactionForce=v["interactionForce"],
        robotVelocity=v["robotVelocity"], robotPosition=v["robotPosition"],
        targetPosition=v["targetPosition"], task=TaskData._from(v),
        clinicalScore=None if score == CLINICAL_SCORE_NA else score, flags=v["flags"])


@dataclass(frozen=True)
class PatientModelReply:
    """Patient model -> manager: the assistance level and how it was reached."""

    seq: int
    ackSeq: int
    alpha: float
    tpi: float
    mpi: float
    pti: float
    alphaMin: float
    alphaMax: float
    path: int = 0
    level: float = 0.0
    flags: int = ReplyFlag.VALID


def encode_patient_model_reply(reply: PatientModelReply) -> bytes:
    for name in ("alpha", "alphaMin", "alphaMax"):
        _check_unit(name, getattr(reply, name), -1.0, 1.0, ValueError)
    for name in ("tpi", "mpi", "pti", "level"):
        _check_unit(name, getattr(reply, name), 0.0, 1.0, ValueError)
    if reply.alphaMin > reply.alphaMax:
        raise ValueError(f"alpha range inverted: {reply.alphaMin} > {reply.alphaMax}")
    values = {"seq": reply.seq & 0xFFFF, "ackSeq": reply.ackSeq & 0xFFFF, "alpha": reply.alpha,
              "tpi": reply.tpi, "mpi": reply.mpi, "pti": reply.pti, "alphaMin": reply.alphaMin,
              "alphaMax": reply.alphaMax, "path": reply.path & 0xFF, "level": reply.level,
              "flags": int(reply.flags) & 0xFF}
    return _pack(PATIENT_MODEL_REPLY_LAYOUT, values)


def decode_patient_model_reply(data: bytes) -> PatientModelReply:
    v = _unpack(PATIENT_MODEL_REPLY_LAYOUT, data)
    for name in ("alpha", "alphaMin", "alphaMax"):
        _check_unit(name, v[name], -1.0, 1.0, FrameError)
    for name in ("tpi", "mpi", "pti"):
        _check_unit(name, v[name], 0.0, 1.0, FrameError)
    if v["alphaMin"] > v["alphaMax"]:
        raise FrameError(f"alpha range inverted: {v['alphaMin']:.4f} > {v['alphaMax']:.4f}")
    return PatientModelReply(v["seq"], v["ackSeq"], v["alpha"], v["tpi"], v["mpi"], v["pti"],
                             v["alphaMin"], v["alphaMax"], v["path"], v["level"], v["flags"])


@dataclass(frozen=True)
class VrFrame:
    """Manager -> VR renderer, 50 Hz."""

    seq: int
    force: float              # grip, N
    interactionForce: float   # N
    robotVelocity: float      # m/s
    robotPosition: float      # m
    targetPosition: float     # m
    task: TaskData = field(default_factory=TaskData)
    alpha: float = 0.0
    flags: int = 0


def encode_vr_frame(frame: VrFrame) -> bytes:
    _check_unit("alpha", frame.alpha, -1.0, 1.0, ValueError)
    values = {"seq": frame.seq & 0xFFFF, "force": frame.force, "interactionForce": frame.interactionForce,
              "robotVelocity": frame.robotVelocity, "robotPosition": frame.robotPosition,
              "targetPosition": frame.targetPosition, "alpha": frame.alpha, "flags": frame.flags & 0xFF,
              **frame.task._values()}
    return _pack(VR_LAYOUT, values)


def decode_vr_frame(data: bytes) -> VrFrame:
    v = _unpack(VR_LAYOUT, data)
    if math.isnan(v["alpha"]):
        raise FrameError("alpha not available")
    return VrFrame(v["seq"], v["force"], v["interactionForce"], v["robotVelocity"], v["robotPosition"],
                   v["targetPosition"], TaskData._from(v), v["alpha"], v["flags"])


@dataclass(frozen=True)
class VrEventFrame:
    """VR renderer -> manager."""

    seq: int
    event: VrEvent
    subTask: int = 0
    score: int = 0
    timeToTarget: float = math.nan  # s (NaN = n/a)


def encode_vr_event(ev: VrEventFrame) -> bytes:
    values = {"seq": ev.seq & 0xFFFF, "event": int(ev.event), "subTask": ev.subTask & 0xFFFF,
              "score": ev.score, "timeToTarget": ev.timeToTarget}
    return _pack(VR_EVENT_LAYOUT, values)


def decode_vr_event(data: bytes) -> VrEventFrame:
    v = _unpack(VR_EVENT_LAYOUT, data)
    try:
        event = VrEvent(v["event"])
    except ValueError as exc:
        raise FrameError(f"unknown VR event {v['event']}") from exc
    return VrEventFrame(v["seq"], event, v["subTask"], v["score"], v["timeToTarget"])


# ---------------------------------------------------------------------------------------------
# Authentication and replay protection (pure)


@functools.lru_cache(maxsize=8)
def _keyed(key: bytes) -> hmac.HMAC:
    """HMAC-SHA256 with ``key`` already absorbed: each frame copies it instead of keying anew."""
    return hmac.new(key, digestmod=hashlib.sha256)


def mac(key: bytes, frame: bytes) -> bytes:
    h = _keyed(bytes(key)).copy()
    h.update(frame)
    return h.digest()[:MAC_SIZE]


def seal(key: bytes, frame: bytes) -> bytes:
    """``frame`` followed by its MAC."""
    return bytes(frame) + mac(key, bytes(frame))


def unseal(key: bytes, data: Any) -> bytes:
    """The frame inside an authenticated datagram; FrameError("bad MAC") unless it carries a valid MAC."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise FrameError(f"not bytes: {type(data).__name__}")
    raw = bytes(data)
    if len(raw) <= MAC_SIZE:
        raise FrameError(f"wrong size: {len(raw)} bytes, too short for a MAC")
    frame, tag = raw[:-MAC_SIZE], raw[-MAC_SIZE:]
    if not hmac.compare_digest(tag, mac(key, frame)):
        raise FrameError("bad MAC: not from the session's peer")
    return frame


class SequenceGuard:
    """Accepts a 16-bit sequence number only when it is newer than the last accepted one (wrap-aware:
    newer = 1..32767 ahead).  ``reset`` forgets the last one (a new peer, a new key)."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.rejected = 0

    def reset(self) -> None:
        self.last = None

    def accept(self, seq: int) -> bool:
        seq &= 0xFFFF
        if self.last is not None and not 0 < ((seq - self.last) & 0xFFFF) < 0x8000:
            self.rejected += 1
            return False
        self.last = seq
        return True
