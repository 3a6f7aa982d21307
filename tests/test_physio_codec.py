"""The 20-byte physiological frame: golden frames, resynchronisation, lost-frame counting, speed."""

from __future__ import annotations

import binascii
import dataclasses
import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.devices.sim.patient import SimulatedPatient
from app.devices.sim.physio_signals import PhysioSimSource
from app.wire.physio_codec import (
    FLAG_PPG_FAULT,
    PHYSIO_FRAME_SIZE,
    PHYSIO_HEADER,
    PHYSIO_LAYOUT,
    Calibration,
    ChannelCalibration,
    PhysioRawFrame,
    PhysioStreamDecoder,
    count_lost,
    crc16_ccitt,
    crc16_ccitt_py,
    crc16_ccitt_rows,
    decode_frames,
    encode_physio_frame,
)

SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# Golden frames, written out by hand from the layout in docs/physio-and-udp-frames.md.
GOLDEN_1 = bytes.fromhex(
    "a55a"      # header
    "0008"      # ppg 2048
    "0a00"      # tick 10 ms
    "f401"      # skin conductance 500 counts -> 5.00 µS
    "fc08"      # temperature 2300 counts -> 33.00 °C
    "2800"      # force 40 counts -> 1.000 N
    "0100"      # seq 1
    "00"        # flags
    "000000"    # reserved
    "6a83"      # CRC-16/CCITT-FALSE of the 18 bytes above
)
GOLDEN_2 = bytes.fromhex("a55a" "ff0f" "ffff" "0000" "ff0f" "ff0f" "ffff" "1f" "000000" "66d3")


def frame(seq: int, **kw: int) -> bytes:
    values = {"tick": seq * 10, "ppg": 2000 + seq % 50, "skinConductance": 500, "temperature": 2300,
              "force": 40 + seq % 7}
    values.update(kw)
    return encode_physio_frame(PhysioRawFrame(seq=seq, **values))


def stream(seqs: list[int]) -> bytes:
    return b"".join(frame(s) for s in seqs)


def decode_all(data: bytes, chunks: list[int] | None = None) -> tuple[PhysioStreamDecoder, list[int]]:
    dec = PhysioStreamDecoder()
    seqs: list[int] = []
    pos = 0
    for size in chunks or []:
        seqs += [s.seq for s in dec.feed(data[pos:pos + size])]
        pos += size
    seqs += [s.seq for s in dec.feed(data[pos:])]
    return dec, seqs


# -- CRC and layout -------------------------------------------------------------------------------

def test_crc_check_value() -> None:
    assert crc16_ccitt(b"123456789") == 0x29B1


@SETTINGS
@given(st.lists(st.binary(min_size=18, max_size=18), min_size=1, max_size=20))
def test_crc_matches_independent_implementation(rows: list[bytes]) -> None:
    arr = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(len(rows), 18)
    expected = [binascii.crc_hqx(r, 0xFFFF) for r in rows]
    assert [crc16_ccitt(r) for r in rows] == expected
    assert [crc16_ccitt_py(r) for r in rows] == expected
    assert crc16_ccitt_rows(arr).tolist() == expected


def test_layout_matches_seed_sizes() -> None:
    offs = PHYSIO_LAYOUT.offsets()
    assert PHYSIO_LAYOUT.size == PHYSIO_FRAME_SIZE == 20
    # seed: header 2 | heart rate 4 | skin conductance 2 | skin temperature 2 | force 2 | additional 8
    names = ("ppg", "skinConductance", "temperature", "force", "seq")
    assert [offs[n] for n in names] == [2, 6, 8, 10, 12]
    assert offs["crc"] == 18


# -- golden frames --------------------------------------------------------------------------------

def test_golden_frame_encodes() -> None:
    assert frame(1, tick=10, ppg=2048, force=40) == GOLDEN_1
    raw = PhysioRawFrame(seq=0xFFFF, tick=0xFFFF, ppg=4095, skinConductance=0, temperature=4095, force=4095,
                         flags=0x1F)
    assert encode_physio_frame(raw) == GOLDEN_2


def test_golden_frame_decodes_to_units() -> None:
    [s] = PhysioStreamDecoder().feed(GOLDEN_1, timestamp=12.5)
    assert (s.seq, s.ppg, s.flags, s.timestamp) == (1, 2048, 0, 12.5)
    assert s.skinConductance == pytest.approx(5.0)
    assert s.temperature == pytest.approx(33.0)
    assert s.force == pytest.approx(1.0)
    assert math.isnan(s.heartRate)  # no beats yet
    [s2] = PhysioStreamDecoder().feed(GOLDEN_2)
    assert (s2.seq, s2.flags, s2.ppg) == (0xFFFF, 0x1F, 4095)
    assert s2.force == pytest.approx(4095 * 0.025)
    assert s2.temperature == pytest.approx(50.95)


def test_custom_calibration() -> None:
    cal = Calibration(force=ChannelCalibration(0.05, -2.0))
    [s] = PhysioStreamDecoder(cal).feed(frame(3, force=100))
    assert s.force == pytest.approx(3.0)
    assert cal.force.to_counts(3.0) == 100
    assert cal.force.to_counts(1e6) == 4095 and cal.force.to_counts(-1e6) == 0


# -- streaming: splits, garbage, truncation, damage -------------------------------------------------

@SETTINGS
@given(st.integers(1, 40), st.lists(st.integers(0, 45), max_size=30))
def test_any_split_of_a_clean_stream(n: int, chunks: list[int]) -> None:
    data = stream(list(range(n)))
    dec, seqs = decode_all(data, chunks)
    assert seqs == list(range(n))
    assert (dec.framesLost, dec.badFrames, dec.discardedBytes, dec.pendingBytes) == (0, 0, 0, 0)


@SETTINGS
@given(st.binary(max_size=400), st.lists(st.integers(0, 60), max_size=20))
def test_garbage_never_raises_and_bytes_are_accounted(garbage: bytes, chunks: list[int]) -> None:
    dec, seqs = decode_all(garbage, chunks)
    assert len(seqs) == dec.framesDecoded
    assert dec.framesDecoded * PHYSIO_FRAME_SIZE + dec.discardedBytes + dec.pendingBytes == len(garbage)
    assert dec.pendingBytes < PHYSIO_FRAME_SIZE


@SETTINGS
@given(st.lists(st.binary(max_size=30), min_size=6, max_size=6), st.lists(st.integers(1, 50), max_size=10))
def test_garbage_between_frames_loses_no_frame(gaps: list[bytes], chunks: list[int]) -> None:
    data = b"".join(g + frame(i) for i, g in enumerate(gaps[:5])) + gaps[5]
    dec, seqs = decode_all(data, chunks)
    assert seqs == [0, 1, 2, 3, 4]
    assert dec.framesLost == 0
    assert dec.discardedBytes + dec.pendingBytes == sum(len(g) for g in gaps)


@SETTINGS
@given(st.integers(0, 9), st.integers(0, PHYSIO_FRAME_SIZE - 1), st.lists(st.integers(1, 50), max_size=10))
def test_dropped_byte_costs_only_that_frame(k: int, pos: int, chunks: list[int]) -> None:
    frames = [frame(i) for i in range(10)]
    frames[k] = frames[k][:pos] + frames[k][pos + 1:]
    dec, seqs = decode_all(b"".join(frames), chunks)
    assert seqs == [i for i in range(10) if i != k]
    assert dec.framesLost == (1 if k not in (0, 9) else 0)  # a loss at either end is invisible
    assert dec.discardedBytes + dec.pendingBytes == PHYSIO_FRAME_SIZE - 1


@SETTINGS
@given(st.integers(1, 8), st.integers(0, PHYSIO_FRAME_SIZE * 8 - 1),
       st.lists(st.integers(1, 50), max_size=10))
def test_bit_flip_costs_only_that_frame(k: int, bit: int, chunks: list[int]) -> None:
    frames = [bytearray(frame(i)) for i in range(10)]
    frames[k][bit // 8] ^= 1 << (bit % 8)
    dec, seqs = decode_all(b"".join(frames), chunks)
    assert seqs == [i for i in range(10) if i != k]
    assert dec.framesLost == 1
    assert dec.discardedBytes == PHYSIO_FRAME_SIZE
    assert dec.badFrames == (0 if bit < 16 else 1)  # a damaged header is not even a bad frame


@SETTINGS
@given(st.integers(1, 5 * PHYSIO_FRAME_SIZE - 1))
def test_truncated_stream_keeps_the_partial_frame(cut: int) -> None:
    data = stream([0, 1, 2, 3, 4])
    dec = PhysioStreamDecoder()
    first = [s.seq for s in dec.feed(data[:cut])]
    assert first == list(range(cut // PHYSIO_FRAME_SIZE))
    assert dec.pendingBytes == cut % PHYSIO_FRAME_SIZE
    rest = [s.seq for s in dec.feed(data[cut:])]
    assert first + rest == [0, 1, 2, 3, 4]


# -- lost frames ----------------------------------------------------------------------------------

@SETTINGS
@given(st.integers(0, 0xFFFF), st.lists(st.booleans(), min_size=2, max_size=120),
       st.lists(st.integers(1, 200), max_size=10))
def test_lost_frames_counted_exactly_across_wraparound(start: int, keep: list[bool],
                                                       chunks: list[int]) -> None:
    keep[0] = True  # losses before the first frame cannot be seen
    sent = [(start + i) & 0xFFFF for i in range(len(keep))]
    received = [s for s, k in zip(sent, keep, strict=True) if k]
    dec, seqs = decode_all(stream(received), chunks)
    assert seqs == received
    last = max(i for i, k in enumerate(keep) if k)
    assert dec.framesLost == sum(not k for k in keep[:last + 1])


def test_lost_before_each_sample_and_backward_jump() -> None:
    dec = PhysioStreamDecoder()
    samples = dec.feed(stream([65534, 65535, 2, 3]))
    assert [s.lostBefore for s in samples] == [0, 0, 2, 0]
    later = dec.feed(stream([1, 2]))  # counter went backwards: a reset, not 65533 lost frames
    assert [s.lostBefore for s in later] == [0, 0]
    assert (dec.framesLost, dec.seqDiscontinuities) == (2, 1)
    lost, disc = count_lost(np.array([5, 6, 9], dtype=np.uint16), 3)
    assert lost.tolist() == [1, 0, 2] and disc == 0


def test_board_time_unwraps_the_tick() -> None:
    ticks = [65500, 65510, 4, 14]  # wraps at 65536 ms
    data = b"".join(frame(i, tick=t) for i, t in enumerate(ticks))
    times = [s.boardTime for s in PhysioStreamDecoder().feed(data)]
    assert times == pytest.approx([0.0, 0.010, 0.040, 0.050])


# -- batch ----------------------------------------------------------------------------------------

@SETTINGS
@given(st.lists(st.tuples(st.binary(max_size=25), st.booleans()), min_size=1, max_size=30))
def test_batch_equals_stream(parts: list[tuple[bytes, bool]]) -> None:
    data = b"".join(g + (frame(i) if ok else b"") for i, (g, ok) in enumerate(parts))
    batch = decode_frames(data)
    dec = PhysioStreamDecoder()
    samples = dec.feed(data)
    assert batch.seq.tolist() == [s.seq for s in samples]
    assert np.allclose(batch.force, [s.force for s in samples])
    assert batch.discardedBytes == dec.discardedBytes + dec.pendingBytes


def test_batch_decode_is_fast() -> None:
    n = 200_000
    data = stream([i & 0xFFFF for i in range(n)])
    t0 = time.perf_counter()
    batch = decode_frames(data)
    elapsed = time.perf_counter() - t0
    assert len(batch) == n and batch.discardedBytes == 0
    assert n / elapsed > 100_000, f"{n / elapsed:.0f} frames/s"


# -- the two feed() paths: plain Python for a few frames, numpy for many ---------------------------

# The strategies are built once: a strategy built at each draw (a few hundred per example) is validated and
# labelled each time — that was ~85 % of this test's time, for the same examples.
# 0x5AA5 puts a header inside a frame's payload; 0/1/0xFFFF exercise the wraps
_WORD = st.one_of(st.integers(0, 0xFFFF), st.sampled_from([0x5AA5, 0xA55A, 0, 1, 0xFFFF]))
_PART_KIND = st.sampled_from(["frame", "frame", "frame", "garbage", "flip", "cut", "header"])
_PART_COUNT = st.integers(0, 25)
_GARBAGE = st.binary(max_size=30)
_FLAGS = st.integers(0, 255)
_FLIPPED_BIT = st.integers(0, 8 * PHYSIO_FRAME_SIZE - 1)
_CUT_AT = st.integers(0, PHYSIO_FRAME_SIZE - 1)


@st.composite
def _damaged_stream(draw: st.DrawFn) -> bytes:
    out = bytearray()
    for _ in range(draw(_PART_COUNT)):
        kind = draw(_PART_KIND)
        if kind == "garbage":
            out += draw(_GARBAGE)
        elif kind == "header":
            out += b"\xa5\x5a"
        else:
            raw = bytearray(encode_physio_frame(PhysioRawFrame(
                seq=draw(_WORD), tick=draw(_WORD), ppg=draw(_WORD), skinConductance=draw(_WORD),
                temperature=draw(_WORD), force=draw(_WORD), flags=draw(_FLAGS))))
            if kind == "flip":
                bit = draw(_FLIPPED_BIT)
                raw[bit // 8] ^= 1 << (bit % 8)
            elif kind == "cut":
                raw = raw[:draw(_CUT_AT)]
            out += raw
    return bytes(out)


def _bits(samples: list) -> list[tuple]:
    """Samples as tuples with every float as its exact bits (NaN equals NaN here)."""
    return [tuple(v.hex() if isinstance(v, float) else v for v in dataclasses.astuple(s)) for s in samples]


def _state(dec: PhysioStreamDecoder) -> tuple:
    return (dec.framesDecoded, dec.framesLost, dec.badFrames, dec.discardedBytes, dec.seqDiscontinuities,
            dec._tail, dec._last_seq, dec._last_tick, dec._board_time.hex(), dec.beats.beats)


def _paths() -> tuple[PhysioStreamDecoder, PhysioStreamDecoder]:
    cal = Calibration(force=ChannelCalibration(0.05, -2.0), temperature=ChannelCalibration(0.013, 7.1))
    numpy_path, python_path = PhysioStreamDecoder(cal), PhysioStreamDecoder(cal)
    numpy_path.small_input_bytes = -1
    python_path.small_input_bytes = 1 << 30
    return numpy_path, python_path


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_damaged_stream(), st.lists(st.integers(0, 70), max_size=30), st.floats(0, 1e6))
def test_python_and_numpy_paths_agree_bit_for_bit(data: bytes, chunks: list[int], t: float) -> None:
    numpy_path, python_path = _paths()
    pos = 0
    for size in [*chunks, len(data)]:
        piece = data[pos:pos + size]
        pos += size
        assert _bits(python_path.feed(piece, t)) == _bits(numpy_path.feed(piece, t))
        assert _state(python_path) == _state(numpy_path)


def _overlapping_valid_frames() -> bytes:
    """Frame A whose bytes 6..19 are the start of a valid frame B, A's CRC made valid too (2 free bytes)."""
    b = frame(9, ppg=1234)
    k = 6
    for free in range(1 << 16):
        a = PHYSIO_HEADER + free.to_bytes(2, "little") + b"\x00\x00" + b[:PHYSIO_FRAME_SIZE - k]
        if crc16_ccitt(a[:18]) == int.from_bytes(a[18:20], "little"):
            return a + b[PHYSIO_FRAME_SIZE - k:]
    raise AssertionError("no free bytes make A valid")  # pragma: no cover



def test_paths_agree_on_overlapping_valid_frames_and_headers_inside_frames() -> None:
    data = _overlapping_valid_frames() + frame(10, ppg=0x5AA5, force=0xA55A) + frame(11)
    numpy_path, python_path = _paths()
    got = python_path.feed(data)
    assert _bits(got) == _bits(numpy_path.feed(data))
    assert _state(python_path) == _state(numpy_path)
    assert len(got) == 3  # A (the earliest of the overlapping pair), 10, 11; B is inside A
    assert python_path.badFrames == 0


def test_a_read_at_the_nominal_rate_takes_the_python_path(monkeypatch: pytest.MonkeyPatch) -> None:
    import app.wire.physio_codec as codec

    def no_numpy(*_a: object) -> None:
        raise AssertionError("numpy path used for one frame")

    monkeypatch.setattr(codec, "_scan", no_numpy)
    dec = PhysioStreamDecoder()
    assert [s.seq for s in dec.feed(frame(1) + frame(2)[:7])] == [1]
    assert [s.seq for s in dec.feed(frame(2)[7:])] == [2]


# -- heart rate from the pulse --------------------------------------------------------------------

def test_beat_detector_follows_simulated_heart_rate() -> None:
    src = PhysioSimSource(SimulatedPatient(seed=2), seed=2)
    dec = PhysioStreamDecoder()
    estimated, truth = [], []
    for i in range(1, 3001):  # 30 s at 100 Hz
        for s in dec.feed(src.frames_until(i * 0.01)):
            estimated.append(s.heartRate)
            truth.append(src.heart.heartRate)
    est = np.array(estimated[1000:])
    # the detector reports the median of the last beats: compare with the mean of the last 5 s
    smoothed_truth = np.convolve(truth, np.ones(500) / 500)[1000:len(truth)]
    assert not np.isnan(est).any()
    assert np.max(np.abs(est - smoothed_truth)) < 5.0
    assert 60.0 <= est.min() and est.max() <= 100.0


def test_heart_rate_lost_when_probe_off() -> None:
    src = PhysioSimSource(SimulatedPatient(seed=3), seed=3)
    dec = PhysioStreamDecoder()
    dec.feed(src.frames_until(10.0))
    assert not math.isnan(dec.beats.heartRate)
    src.set_fault_flags(FLAG_PPG_FAULT)
    samples = dec.feed(src.frames_until(15.0))
    assert samples[-1].flags & FLAG_PPG_FAULT
    assert math.isnan(samples[-1].heartRate)
