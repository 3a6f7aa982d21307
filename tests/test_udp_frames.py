"""UDP frames to/from the patient model and the VR renderer: golden frames, round trips, rejection."""

from __future__ import annotations

import binascii
import math
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.wire.physio_codec import PHYSIO_LAYOUT
from app.wire.udp_frames import (
    ALL_UDP_LAYOUTS,
    FORCE_SCALE,
    PATIENT_MODEL_LAYOUT,
    PATIENT_MODEL_REPLY_LAYOUT,
    POSITION_SCALE,
    VR_EVENT_LAYOUT,
    VR_LAYOUT,
    FrameError,
    PatientModelFrame,
    PatientModelReply,
    ReplyFlag,
    SystemFlag,
    TaskData,
    TaskFlag,
    TaskState,
    VrEvent,
    VrEventFrame,
    VrFrame,
    decode_patient_model_frame,
    decode_patient_model_reply,
    decode_vr_event,
    decode_vr_frame,
    encode_patient_model_frame,
    encode_patient_model_reply,
    encode_vr_event,
    encode_vr_frame,
)

SETTINGS = settings(max_examples=200, deadline=None)
DOC = Path(__file__).resolve().parents[1] / "docs" / "physio-and-udp-frames.md"

TASK = TaskData(3, TaskState.MOVING, TaskFlag.GRIP_TRIGGERED, 1.5, 120)
PM_FRAME = PatientModelFrame(seq=258, heartRate=72.5, skinConductance=5.25, temperature=33.1, force=25.5,
                             interactionForce=-3.2, robotVelocity=0.125, robotPosition=0.25,
                             targetPosition=0.4, task=TASK, clinicalScore=42,
                             flags=SystemFlag.ROBOT_ON | SystemFlag.PHYSIO_VALID)
PM_GOLDEN = bytes.fromhex(
    "4c50"       # 'LP'
    "00009142"   # heart rate float32 72.5
    "0d02"       # skin conductance 525 x 0.01 µS
    "ee0c"       # temperature 3310 x 0.01 °C
    "f609"       # grip force 2550 x 0.01 N
    "c0fe"       # interaction force -320 x 0.01 N
    "0000003e"   # velocity float32 0.125
    "d430"       # position 12500 x 20 µm
    "cdcccc3e"   # target float32 0.4
    "0300" "01" "01" "9600" "7800"   # task: sub-task 3, moving, grip triggered, 150 x 0.01 s, score 120
    "0201" "2a" "03" "0000"          # seq 258, clinical score 42, flags physio valid | robot on, reserved
    "e126"       # CRC
)
REPLY = PatientModelReply(seq=7, ackSeq=258, alpha=0.5, tpi=0.25, mpi=0.75, pti=0.125, alphaMin=0.25,
                          alphaMax=0.75, path=0b01001, level=0.5, flags=ReplyFlag.VALID)
REPLY_GOLDEN = bytes.fromhex("504c" "0700" "0201" "0000003f" "0000803e" "0000403f" "0000003e"
                             "0020" "ff5f" "09" "80" "01" "00" "e566")
VR = VrFrame(seq=1, force=25.5, interactionForce=-3.2, robotVelocity=0.125, robotPosition=0.25,
             targetPosition=0.4, task=TASK, alpha=-0.5, flags=SystemFlag.ROBOT_ON)
VR_GOLDEN = bytes.fromhex("4c56" "f609" "c0fe" "0000003e" "d430" "cdcccc3e" "0300" "01" "01" "9600" "7800"
                          "0100" "00c0" "02" "00" "a058")
EVENT = VrEventFrame(seq=9, event=VrEvent.TARGET_REACHED, subTask=3, score=1000, timeToTarget=2.5)
EVENT_GOLDEN = bytes.fromhex("564c" "0900" "03" "00" "0300" "e8030000" "c409" "1459")

DECODERS: list[Callable[[bytes], Any]] = [decode_patient_model_frame, decode_patient_model_reply,
                                          decode_vr_frame, decode_vr_event]
GOLDENS = [PM_GOLDEN, REPLY_GOLDEN, VR_GOLDEN, EVENT_GOLDEN]


def test_sizes_match_the_seed() -> None:
    assert [layout.size for layout in ALL_UDP_LAYOUTS] == [40, 32, 32, 16]
    pm = PATIENT_MODEL_LAYOUT.offsets()
    # seed: header 2 | HR 4 | SC 2 | temp 2 | force 2 | interaction 2 | vel 4 | pos 2 | target 4 | task 8
    #       | additional 8
    assert [pm[n] for n in ("heartRate", "skinConductance", "temperature", "force", "interactionForce",
                            "robotVelocity", "robotPosition", "targetPosition", "subTask", "seq")] == \
        [2, 6, 8, 10, 12, 14, 18, 20, 24, 32]
    vr = VR_LAYOUT.offsets()
    # seed: header 2 | force 2 | interaction 2 | vel 4 | pos 2 | target 4 | task 8 | additional 8
    assert [vr[n] for n in ("force", "interactionForce", "robotVelocity", "robotPosition", "targetPosition",
                            "subTask", "seq")] == [2, 4, 6, 10, 12, 16, 24]


def test_goldens_carry_valid_crcs() -> None:
    for golden in GOLDENS:
        assert int.from_bytes(golden[-2:], "little") == binascii.crc_hqx(golden[:-2], 0xFFFF)


def test_golden_frames_encode() -> None:
    assert encode_patient_model_frame(PM_FRAME) == PM_GOLDEN
    assert encode_patient_model_reply(REPLY) == REPLY_GOLDEN
    assert encode_vr_frame(VR) == VR_GOLDEN
    assert encode_vr_event(EVENT) == EVENT_GOLDEN


def test_golden_frames_decode() -> None:
    pm = decode_patient_model_frame(PM_GOLDEN)
    assert (pm.seq, pm.clinicalScore, pm.flags, pm.task) == (258, 42, 3, TASK)
    assert pm.heartRate == 72.5 and pm.robotVelocity == 0.125
    assert pm.skinConductance == pytest.approx(5.25) and pm.temperature == pytest.approx(33.1)
    assert pm.interactionForce == pytest.approx(-3.2) and pm.robotPosition == pytest.approx(0.25)
    assert pm.targetPosition == pytest.approx(0.4, abs=1e-7)
    reply = decode_patient_model_reply(REPLY_GOLDEN)
    assert (reply.alpha, reply.tpi, reply.mpi, reply.pti, reply.path) == (0.5, 0.25, 0.75, 0.125, 9)
    assert reply.alphaMin == pytest.approx(0.25, abs=1e-4) and reply.level == pytest.approx(0.5, abs=0.003)
    vr = decode_vr_frame(VR_GOLDEN)
    assert vr.alpha == pytest.approx(-0.5, abs=1e-4) and vr.task == TASK and vr.seq == 1
    assert decode_vr_event(EVENT_GOLDEN) == EVENT


def test_not_available_and_saturation() -> None:
    frame = PatientModelFrame(seq=70000, heartRate=math.nan, skinConductance=math.nan, temperature=math.nan,
                              force=1e6, interactionForce=-1e6, robotVelocity=0.0, robotPosition=2.0,
                              targetPosition=0.0, task=TaskData(score=10**9), clinicalScore=None)
    out = decode_patient_model_frame(encode_patient_model_frame(frame))
    assert math.isnan(out.heartRate) and math.isnan(out.skinConductance) and math.isnan(out.temperature)
    assert out.force == pytest.approx(327.67) and out.interactionForce == pytest.approx(-327.67)
    assert out.robotPosition == pytest.approx(32767 * POSITION_SCALE)
    assert out.seq == 70000 & 0xFFFF and out.clinicalScore is None and out.task.score == 65535
    assert math.isnan(out.task.subTaskTime)


def test_encoders_refuse_values_without_encoding() -> None:
    with pytest.raises(ValueError, match="alpha"):
        encode_patient_model_reply(PatientModelReply(0, 0, 1.5, 0, 0, 0, 0, 1))
    with pytest.raises(ValueError, match="tpi"):
        encode_patient_model_reply(PatientModelReply(0, 0, 0.1, math.nan, 0, 0, 0, 1))
    with pytest.raises(ValueError, match="inverted"):
        encode_patient_model_reply(PatientModelReply(0, 0, 0.1, 0, 0, 0, 0.5, 0.2))
    with pytest.raises(ValueError, match="alpha"):
        encode_vr_frame(VrFrame(0, 0, 0, 0, 0, 0, alpha=-2.0))
    with pytest.raises(ValueError, match="clinicalScore"):
        encode_patient_model_frame(PatientModelFrame(0, 70, 5, 33, 0, 0, 0, 0, 0, clinicalScore=300))


finite = st.floats(allow_nan=False, allow_infinity=False, width=32)


@SETTINGS
@given(seq=st.integers(0, 0xFFFF), hr=finite, sc=st.floats(0, 655), temp=st.floats(-300, 300),
       force=st.floats(-300, 300), pos=st.floats(-0.65, 0.65), vel=finite, target=finite,
       state=st.sampled_from(TaskState), score=st.integers(0, 65535), cs=st.none() | st.integers(0, 254))
def test_patient_model_frame_round_trip(seq: int, hr: float, sc: float, temp: float, force: float, pos: float,
                                        vel: float, target: float, state: TaskState, score: int,
                                        cs: int | None) -> None:
    frame = PatientModelFrame(seq, hr, sc, temp, force, -force, vel, pos, target,
                              TaskData(seq % 100, state, 1, 2.0, score), cs, 5)
    out = decode_patient_model_frame(encode_patient_model_frame(frame))
    assert (out.seq, out.task.taskState, out.task.score, out.clinicalScore) == (seq, state, score, cs)
    assert (out.heartRate, out.robotVelocity, out.targetPosition) == (hr, vel, target)  # float32 exact
    assert abs(out.skinConductance - sc) <= 0.005 + 1e-9 and abs(out.temperature - temp) <= 0.005 + 1e-9
    assert abs(out.force - force) <= FORCE_SCALE / 2 + 1e-9
    assert abs(out.interactionForce + force) <= FORCE_SCALE / 2 + 1e-9
    assert abs(out.robotPosition - pos) <= POSITION_SCALE / 2 + 1e-12


@SETTINGS
@given(alpha=st.floats(-1, 1), lo=st.floats(-1, 0), hi=st.floats(0, 1), idx=st.floats(0, 1),
       level=st.floats(0, 1), path=st.integers(0, 255))
def test_reply_round_trip(alpha: float, lo: float, hi: float, idx: float, level: float, path: int) -> None:
    reply = PatientModelReply(1, 2, alpha, idx, 1 - idx, idx / 2, lo, hi, path, level)
    out = decode_patient_model_reply(encode_patient_model_reply(reply))
    assert out.alpha == pytest.approx(alpha, abs=1e-7) and out.tpi == pytest.approx(idx, abs=1e-7)
    assert abs(out.alphaMin - lo) <= 1 / 32767 and abs(out.alphaMax - hi) <= 1 / 32767
    assert abs(out.level - level) <= 1 / 510 + 1e-12 and out.path == path


@SETTINGS
@given(event=st.sampled_from(VrEvent), score=st.integers(0, 2**32 - 1), seconds=st.floats(0, 65.0))
def test_vr_event_round_trip(event: VrEvent, score: int, seconds: float) -> None:
    out = decode_vr_event(encode_vr_event(VrEventFrame(5, event, 7, score, seconds)))
    assert (out.event, out.score, out.subTask) == (event, score, 7)
    assert abs(out.timeToTarget - seconds) <= 0.0005 + 1e-9


@pytest.mark.parametrize("decode,golden", list(zip(DECODERS, GOLDENS, strict=True)))
def test_rejections_name_the_reason(decode: Callable[[bytes], Any], golden: bytes) -> None:
    with pytest.raises(FrameError, match="wrong size"):
        decode(golden[:-1])
    with pytest.raises(FrameError, match="wrong size"):
        decode(golden + b"\0")
    with pytest.raises(FrameError, match="wrong header"):
        decode(b"XX" + golden[2:])
    damaged = bytearray(golden)
    damaged[5] ^= 0x10
    with pytest.raises(FrameError, match="bad CRC"):
        decode(bytes(damaged))
    with pytest.raises(FrameError, match="not bytes"):
        decode(len(golden))  # type: ignore[arg-type]


@SETTINGS
@given(st.integers(0, 3), st.data())
def test_any_bit_flip_is_rejected(which: int, data: st.DataObject) -> None:
    golden = GOLDENS[which]
    bit = data.draw(st.integers(0, len(golden) * 8 - 1))
    damaged = bytearray(golden)
    damaged[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(FrameError):
        DECODERS[which](bytes(damaged))


def _with_crc(body: bytes) -> bytes:
    return body + binascii.crc_hqx(body, 0xFFFF).to_bytes(2, "little")


@SETTINGS
@given(st.integers(0, 3), st.binary(max_size=48), st.booleans())
def test_garbage_only_ever_raises_frame_error(which: int, payload: bytes, well_formed: bool) -> None:
    layout = ALL_UDP_LAYOUTS[which]
    if well_formed:  # right size, header and CRC around random content: only value checks remain
        payload = _with_crc(layout.header + payload.ljust(layout.size, b"\xa5")[: layout.size - 4])
    try:
        DECODERS[which](payload)
    except FrameError as exc:
        assert exc.reason


def test_value_checks_on_well_formed_frames() -> None:
    body = bytearray(REPLY_GOLDEN[:-2])
    body[6:10] = struct.pack("<f", 2.0)  # alpha
    with pytest.raises(FrameError, match="alpha out of range"):
        decode_patient_model_reply(_with_crc(bytes(body)))
    ev = bytearray(EVENT_GOLDEN[:-2])
    ev[4] = 99
    with pytest.raises(FrameError, match="unknown VR event 99"):
        decode_vr_event(_with_crc(bytes(ev)))
    pm = bytearray(PM_GOLDEN[:-2])
    pm[26] = 42
    with pytest.raises(FrameError, match="unknown task state 42"):
        decode_patient_model_frame(_with_crc(bytes(pm)))


def test_documentation_holds_the_tables() -> None:
    text = DOC.read_text(encoding="utf-8")
    for layout in (PHYSIO_LAYOUT, *ALL_UDP_LAYOUTS):
        assert layout.markdown_table() in text, f"docs out of date for: {layout.title}"
    assert PATIENT_MODEL_REPLY_LAYOUT.header == b"PL" and VR_EVENT_LAYOUT.header == b"VL"
