"""Physiological acquisition board: the 20-byte frame, its streaming/batch decoder and calibration.

The seed (D2.1, "Connections") fixes only the sizes: header 2, heart rate 4, skin conductance 2,
skin temperature 2, force sensor 2, additional data 8 bytes, at 100 Hz.  The board samples four
analog sensors with 12-bit ADCs and sends raw counts; signal processing happens on the PC.
Everything else is decided here, once, in ``PHYSIO_LAYOUT`` (used by the encoder, the decoders and
the documentation table in docs/physio-and-udp-frames.md):

* little-endian; header ``A5 5A``;
* the 4-byte "heart rate" field carries the raw 12-bit pulse (PPG) sample *and* the board's 16-bit
  millisecond tick at which it was sampled, because beat-to-beat intervals must be measured on the
  sampling clock, not on the bursty USB arrival time.  Beats (and bpm) are detected here, in
  ``BeatDetector``;
* the 8 additional bytes hold a 16-bit sequence counter (lost-frame detection, wraps at 65536),
  sensor-fault flags, 3 reserved zero bytes and a CRC-16/CCITT-FALSE over bytes 0..17.

Pure: bytes in, typed samples / numpy arrays out; no I/O, no Qt.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
import numpy.typing as npt

# ---------------------------------------------------------------------------------------------
# Layout tables (shared with udp_frames.py)


@dataclass(frozen=True)
class Field:
    """One field of a fixed binary frame.  ``physical = raw * scale`` when ``scale`` is set."""

    name: str
    fmt: str  # struct code, little-endian frame: H h B b I i f or Ns
    unit: str
    doc: str
    scale: float | None = None

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.fmt)


@dataclass(frozen=True)
class Layout:
    """A fixed-size little-endian frame described by an ordered tuple of fields."""

    title: str
    header: bytes
    size: int
    fields: tuple[Field, ...]

    def __post_init__(self) -> None:
        # Fail at import time if a table and its declared size disagree.
        if struct.calcsize(self.struct_format) != self.size:
            raise ValueError(f"{self.title}: fields add up to {struct.calcsize(self.struct_format)} bytes,"
                             f" declared {self.size}")
        if self.fields[0].name != "header" or self.fields[-1].name != "crc":
            raise ValueError(f"{self.title}: a layout starts with 'header' and ends with 'crc'")

    @property
    def struct_format(self) -> str:
        return "<" + "".join(f.fmt for f in self.fields)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def offsets(self) -> dict[str, int]:
        out: dict[str, int] = {}
        pos = 0
        for f in self.fields:
            out[f.name] = pos
            pos += f.size
        return out

    def numpy_dtype(self) -> np.dtype:
        codes = {"H": "<u2", "h": "<i2", "B": "u1", "b": "i1", "I": "<u4", "i": "<i4", "f": "<f4"}
        formats = [codes.get(f.fmt, f"V{f.size}") for f in self.fields]
        offs = self.offsets()
        return np.dtype({"names": list(self.names), "formats": formats,
                         "offsets": [offs[n] for n in self.names], "itemsize": self.size})

    def markdown_table(self) -> str:
        """The documentation table; docs/physio-and-udp-frames.md embeds this text verbatim."""
        header = self.header.hex(" ").upper()
        lines = [f"**{self.title}** — {self.size} bytes, little-endian, header `{header}`",
                 "", "| Offset | Size | Field | Type | Scale | Unit | Meaning |",
                 "|---:|---:|---|---|---|---|---|"]
        offs = self.offsets()
        for f in self.fields:
            scale = "" if f.scale is None else f"{f.scale:g}"
            lines.append(f"| {offs[f.name]} | {f.size} | `{f.name}` | `{f.fmt}` | {scale} | {f.unit}"
                         f" | {f.doc} |")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor ("123456789" -> 0x29B1)

CRC_INIT: Final = 0xFFFF


def _crc_table() -> npt.NDArray[np.uint16]:
    table = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table[i] = c & 0xFFFF
    return table


_CRC_TABLE: Final = _crc_table()
_CRC_TABLE_LIST: Final = [int(v) for v in _CRC_TABLE]


def crc16_ccitt(data: bytes | bytearray | memoryview, crc: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (binascii's CRC-CCITT is this CRC given the 0xFFFF start)."""
    return binascii.crc_hqx(data, crc)


def crc16_ccitt_py(data: bytes | bytearray | memoryview, crc: int = CRC_INIT) -> int:
    """The same CRC from the table, byte by byte: the reference the tests hold the fast one to."""
    table = _CRC_TABLE_LIST
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ b) & 0xFF]
    return crc


def crc16_ccitt_rows(rows: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint16]:
    """CRC-16/CCITT-FALSE of every row of a 2-D uint8 array (vectorised over rows)."""
    crc = np.full(rows.shape[0], CRC_INIT, dtype=np.uint16)
    for col in range(rows.shape[1]):
        idx = ((crc >> 8) ^ rows[:, col]).astype(np.uint8)
        crc = ((crc << 8) ^ _CRC_TABLE[idx]).astype(np.uint16, copy=False)  # uint16 already: typed, not copied
    return crc


# ---------------------------------------------------------------------------------------------
# The physiological frame

PHYSIO_HEADER: Final = b"\xA5\x5A"
PHYSIO_FRAME_SIZE: Final = 20
PHYSIO_RATE_HZ: Final = 100.0
ADC_MAX: Final = 4095  # 12-bit ADC

# Sensor-fault flags set by the board (byte ``flags``); the upper three bits are reserved (0).
FLAG_PPG_FAULT: Final = 0x01      # pulse probe off / saturated
FLAG_EDA_FAULT: Final = 0x02      # skin-conductance electrodes off
FLAG_TEMP_FAULT: Final = 0x04     # temperature probe open/short
FLAG_FORCE_FAULT: Final = 0x08    # grip sensor disconnected / saturated
FLAG_ADC_OVERRUN: Final = 0x10    # board missed an ADC deadline

# The fault bits in words, with the channel each one invalidates (None: the whole frame's timing).
FAULT_FLAGS: Final[tuple[tuple[int, str, str | None], ...]] = (
    (FLAG_PPG_FAULT, "pulse probe off", "heartRate"),
    (FLAG_EDA_FAULT, "skin-conductance electrodes off", "skinConductance"),
    (FLAG_TEMP_FAULT, "temperature probe fault", "temperature"),
    (FLAG_FORCE_FAULT, "grip sensor fault", "force"),
    (FLAG_ADC_OVERRUN, "ADC overrun", None),
)

PHYSIO_LAYOUT: Final = Layout(
    title="Physiological board -> manager (serial, 100 Hz)",
    header=PHYSIO_HEADER,
    size=PHYSIO_FRAME_SIZE,
    fields=(
        Field("header", "2s", "", "sync bytes A5 5A"),
        Field("ppg", "H", "count", "heart-rate field, part 1: raw 12-bit pulse (PPG) sample, 0..4095"),
        Field("tick", "H", "ms", "heart-rate field, part 2: board clock at sampling, ms, wraps at 65536"),
        Field("skinConductance", "H", "count", "raw 12-bit skin-conductance sample"),
        Field("temperature", "H", "count", "raw 12-bit skin-temperature sample"),
        Field("force", "H", "count", "raw 12-bit grip-force sample"),
        Field("seq", "H", "", "additional, part 1: sequence counter, +1 per frame, wraps at 65536"),
        Field("flags", "B", "", "additional, part 2: sensor-fault bits (PPG 0x01, EDA 0x02, TEMP 0x04,"
              " FORCE 0x08, ADC overrun 0x10)"),
        Field("reserved", "3s", "", "additional, part 3: reserved, sent as zero, ignored"),
        Field("crc", "H", "", "additional, part 4: CRC-16/CCITT-FALSE of bytes 0..17"),
    ),
)
_PHYSIO_STRUCT: Final = struct.Struct(PHYSIO_LAYOUT.struct_format)
_PHYSIO_DTYPE: Final = PHYSIO_LAYOUT.numpy_dtype()
_CRC_SPAN: Final = PHYSIO_FRAME_SIZE - 2


# ---------------------------------------------------------------------------------------------
# Calibration: raw counts -> physical units (one gain/offset per channel)


@dataclass(frozen=True)
class ChannelCalibration:
    """``value = gain * counts + offset``."""

    gain: float
    offset: float = 0.0

    def to_units(self, counts: float | npt.NDArray[Any]) -> float | npt.NDArray[Any]:
        return self.gain * counts + self.offset

    def to_counts(self, value: float) -> int:
        """Inverse used by the simulator; clipped to the ADC range."""
        return int(min(ADC_MAX, max(0, round((value - self.offset) / self.gain))))


@dataclass(frozen=True)
class Calibration:
    """Per-channel calibration; defaults map the full 12-bit range onto clinically useful spans:
    skin conductance 0..40.95 µS (0.01 µS/count), skin temperature 10..50.95 °C (0.01 °C/count),
    grip force 0..102.4 N (0.025 N/count).  The PPG stays in counts (only its rhythm matters)."""

    skinConductance: ChannelCalibration = field(default_factory=lambda: ChannelCalibration(0.01, 0.0))
    temperature: ChannelCalibration = field(default_factory=lambda: ChannelCalibration(0.01, 10.0))
    force: ChannelCalibration = field(default_factory=lambda: ChannelCalibration(0.025, 0.0))


# ---------------------------------------------------------------------------------------------
# Encoder (simulator, tests)


@dataclass(frozen=True)
class PhysioRawFrame:
    """The frame's fields as sent: raw counts."""

    seq: int
    tick: int
    ppg: int
    skinConductance: int
    temperature: int
    force: int
    flags: int = 0


def encode_physio_frame(frame: PhysioRawFrame) -> bytes:
    body = _PHYSIO_STRUCT.pack(PHYSIO_HEADER, frame.ppg & 0xFFFF, frame.tick & 0xFFFF,
                               frame.skinConductance & 0xFFFF, frame.temperature & 0xFFFF,
                               frame.force & 0xFFFF, frame.seq & 0xFFFF, frame.flags & 0xFF, b"\0\0\0", 0)
    return body[:_CRC_SPAN] + struct.pack("<H", crc16_ccitt(body[:_CRC_SPAN]))


# ---------------------------------------------------------------------------------------------
# Batch decoding (numpy)


@dataclass
class PhysioBatch:
    """Many decoded frames as arrays (one element per accepted frame, in stream order)."""

    seq: npt.NDArray[np.uint16]
    tick: npt.NDArray[np.uint16]
    ppg: npt.NDArray[np.uint16]
    flags: npt.NDArray[np.uint8]
    skinConductance: npt.NDArray[np.float64]  # µS
    temperature: npt.NDArray[np.float64]      # °C
    force: npt.NDArray[np.float64]            # N
    offsets: npt.NDArray[np.int64]            # start of each frame in the scanned buffer
    badFrames: int = 0       # header found, CRC wrong (outside any accepted frame)
    discardedBytes: int = 0  # bytes not belonging to an accepted frame

    def __len__(self) -> int:
        return int(self.seq.shape[0])


def _scan(buf: npt.NDArray[np.uint8]) -> tuple[npt.NDArray[np.int64], int]:
    """Start offsets of accepted frames (non-overlapping, CRC-valid) and the bad-frame count."""
    n = buf.shape[0]
    if n < PHYSIO_FRAME_SIZE:
        return np.zeros(0, dtype=np.int64), 0
    cand = np.flatnonzero((buf[:-1] == PHYSIO_HEADER[0]) & (buf[1:] == PHYSIO_HEADER[1]))
    cand = cand[cand <= n - PHYSIO_FRAME_SIZE].astype(np.int64)
    if cand.size == 0:
        return cand, 0
    rows = buf[cand[:, None] + np.arange(PHYSIO_FRAME_SIZE)]
    stored = rows[:, _CRC_SPAN].astype(np.uint16) | (rows[:, _CRC_SPAN + 1].astype(np.uint16) << 8)
    ok = crc16_ccitt_rows(rows[:, :_CRC_SPAN]) == stored
    valid = cand[ok]
    if valid.size > 1 and np.any(np.diff(valid) < PHYSIO_FRAME_SIZE):
        # Rare: a CRC-valid pattern overlapping another; keep the earliest, greedily.
        keep: list[int] = []
        end = -1
        for p in valid.tolist():
            if p >= end:
                keep.append(p)
                end = p + PHYSIO_FRAME_SIZE
        valid = np.asarray(keep, dtype=np.int64)
    bad = cand[~ok]
    if bad.size and valid.size:
        j = np.searchsorted(valid, bad, side="right") - 1
        inside = (j >= 0) & (bad < valid[np.maximum(j, 0)] + PHYSIO_FRAME_SIZE)
        bad = bad[~inside]
    return valid, int(bad.size)


def _extract(buf: npt.NDArray[np.uint8], starts: npt.NDArray[np.int64], cal: Calibration,
             bad: int, discarded: int) -> PhysioBatch:
    rows = np.ascontiguousarray(buf[starts[:, None] + np.arange(PHYSIO_FRAME_SIZE)])
    rec = rows.view(_PHYSIO_DTYPE).reshape(-1)
    return PhysioBatch(
        seq=rec["seq"].astype(np.uint16), tick=rec["tick"].astype(np.uint16),
        ppg=rec["ppg"].astype(np.uint16), flags=rec["flags"].astype(np.uint8),
        skinConductance=np.asarray(cal.skinConductance.to_units(rec["skinConductance"].astype(np.float64))),
        temperature=np.asarray(cal.temperature.to_units(rec["temperature"].astype(np.float64))),
        force=np.asarray(cal.force.to_units(rec["force"].astype(np.float64))),
        offsets=starts, badFrames=bad, discardedBytes=discarded)


def decode_frames(data: bytes | bytearray | memoryview,
                  calibration: Calibration | None = None) -> PhysioBatch:
    """Decode every valid frame in a complete buffer (e.g. a recording) at once.

    Bytes outside accepted frames (garbage, corrupted frames, a trailing partial frame) are counted
    in ``discardedBytes``; never raises on any input."""
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    starts, bad = _scan(buf)
    return _extract(buf, starts, calibration or Calibration(), bad,
                    int(buf.size) - PHYSIO_FRAME_SIZE * int(starts.size))


def count_lost(seq: npt.NDArray[np.uint16], previous: int | None) -> tuple[npt.NDArray[np.int64], int]:
    """Frames missing before each frame from the 16-bit sequence counter (wraparound-aware).

    A jump of 32768 or more means the counter went backwards (board reset, replay): it counts as
    a discontinuity, not as lost frames.  Returns (lost before each frame, discontinuities)."""
    s = seq.astype(np.int64)
    prev = np.empty_like(s)
    if s.size:
        prev[0] = s[0] - 1 if previous is None else previous
        prev[1:] = s[:-1]
    gap = (s - prev - 1) & 0xFFFF
    backwards = gap >= 0x8000
    return np.where(backwards, 0, gap), int(np.count_nonzero(backwards))


# ---------------------------------------------------------------------------------------------
# Beat detection: PPG counts -> heart rate (bpm)


class BeatDetector:
    """Heart rate from the raw pulse waveform.

    Per sample: remove the baseline (first-order low-pass, tau 1.5 s), follow the pulse amplitude
    with a peak envelope (decay tau 2 s), and mark a beat where the high-passed signal rises through
    40 % of the envelope (time interpolated between samples).  Crossings closer than 0.3 s to the
    previous beat are ignored (refractory: max 200 bpm).  Inter-beat intervals outside 0.3..2.0 s
    are rejected; the heart rate is 60 / median of the last 5 accepted intervals, available after 3
    intervals.  No beat is marked during the first 1.5 s after a (re)start, while the baseline and the
    envelope settle (a spurious early crossing gave a wrong first rate).  With no beat for 3 s the rate
    becomes NaN (probe off) and the history is cleared.
    Timing uses the board clock, so lost frames do not distort intervals."""

    BASELINE_TAU: Final = 1.5
    ENVELOPE_TAU: Final = 2.0
    THRESHOLD: Final = 0.4
    REFRACTORY: Final = 0.3
    IBI_RANGE: Final = (0.3, 2.0)
    HISTORY: Final = 5
    TIMEOUT: Final = 3.0
    WARM_UP: Final = 1.5
    MIN_INTERVALS: Final = 3

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._t: float | None = None
        self._t_start = 0.0
        self._base = 0.0
        self._env = 0.0
        self._prev_hp = 0.0
        self._last_beat: float | None = None
        self._ibis: deque[float] = deque(maxlen=self.HISTORY)
        self.heartRate = math.nan
        self.beats = 0

    def update(self, t: float, ppg: float) -> float:
        """Feed one sample (board time in s, counts); returns the current heart rate (bpm or NaN)."""
        if self._t is None or t <= self._t or t - self._t > self.TIMEOUT:
            self._t = t
            self._t_start = t
            self._base = ppg
            self._prev_hp = 0.0
            return self.heartRate
        dt = t - self._t
        self._base += (ppg - self._base) * (1.0 - math.exp(-dt / self.BASELINE_TAU))
        hp = ppg - self._base
        self._env = max(abs(hp), self._env * math.exp(-dt / self.ENVELOPE_TAU))
        thr = self.THRESHOLD * self._env
        if self._prev_hp < thr <= hp and self._env > 0.0 and t - self._t_start >= self.WARM_UP:
            tc = self._t + dt * (thr - self._prev_hp) / (hp - self._prev_hp)
            if self._last_beat is None or tc - self._last_beat >= self.REFRACTORY:
                if self._last_beat is not None:
                    ibi = tc - self._last_beat
                    if self.IBI_RANGE[0] <= ibi <= self.IBI_RANGE[1]:
                        self._ibis.append(ibi)
                self._last_beat = tc
                self.beats += 1
                if len(self._ibis) >= self.MIN_INTERVALS:
                    self.heartRate = 60.0 / float(np.median(self._ibis))
        if self._last_beat is not None and t - self._last_beat > self.TIMEOUT:
            self._ibis.clear()
            self._last_beat = None
            self.heartRate = math.nan
        self._prev_hp = hp
        self._t = t
        return self.heartRate


# ---------------------------------------------------------------------------------------------
# Streaming decoder


@dataclass(frozen=True)
class PhysioSample:
    """One decoded frame in physical units; field names as the seed's scripts use them."""

    seq: int
    timestamp: float        # s, monotonic: the driver's stamp (boardTime mapped to the host clock, #27)
    boardTime: float        # s, board clock, unwrapped from the 16-bit ms tick
    force: float            # grip force, N
    temperature: float      # skin temperature, °C
    heartRate: float        # bpm from the beat detector; NaN until locked / when the probe is off
    skinConductance: float  # µS
    ppg: int                # raw pulse sample, counts
    flags: int
    lostBefore: int         # frames missing just before this one (sequence gap)


class PhysioStreamDecoder:
    """Incremental decoder for the serial byte stream.

    Finds the header, checks the CRC, resynchronises after garbage or a dropped byte (at worst the
    damaged frame is lost; the next intact frame is found where its header is), counts frames lost
    from the sequence counter, bad frames (header with wrong CRC) and discarded bytes.  Never
    raises on any input; keeps at most 19 bytes between calls."""

    def __init__(self, calibration: Calibration | None = None) -> None:
        self.calibration = calibration or Calibration()
        self.beats = BeatDetector()
        self.reset()

    def reset(self) -> None:
        self._tail = b""
        self._last_seq: int | None = None
        self._last_tick: int | None = None
        self._board_time = 0.0
        self.framesDecoded = 0
        self.framesLost = 0
        self.badFrames = 0
        self.discardedBytes = 0
        self.seqDiscontinuities = 0
        self.beats.reset()

    @property
    def pendingBytes(self) -> int:
        """Bytes held back: the start of a frame not yet complete."""
        return len(self._tail)

    # Inputs up to this many bytes (tail included) are decoded in plain Python: a read at the nominal rate
    # holds one frame, and numpy's per-call overhead (~80 µs a read) was most of the driver's CPU (#16).
    # Longer inputs (a backlog, a recording) take the numpy path: measured per frame, Python ~3 µs flat,
    # numpy ~120 µs at 1 frame a call, ~9 µs at 20, ~4 µs at 100+. Both give identical samples and
    # counters (tests/test_physio_codec.py holds them to it).
    small_input_bytes: int = 100 * PHYSIO_FRAME_SIZE

    def feed_batch(self, data: bytes | bytearray | memoryview) -> tuple[PhysioBatch, npt.NDArray[np.int64],
                                                                         npt.NDArray[np.float64]]:
        """Decode the frames completed by ``data``; returns (batch, lost before each, board time)."""
        return self._feed_batch(self._tail + bytes(data))

    def _feed_batch(self, raw: bytes) -> tuple[PhysioBatch, npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        buf = np.frombuffer(raw, dtype=np.uint8)
        starts, bad = _scan(buf)
        end = int(starts[-1]) + PHYSIO_FRAME_SIZE if starts.size else 0
        keep_from = max(end, buf.size - (PHYSIO_FRAME_SIZE - 1), 0)
        self._tail = raw[keep_from:]
        discarded = keep_from - PHYSIO_FRAME_SIZE * int(starts.size)
        batch = _extract(buf, starts, self.calibration, bad, discarded)
        lost, disc = count_lost(batch.seq, self._last_seq)
        board_time = self._unwrap_ticks(batch.tick)
        if len(batch):
            self._last_seq = int(batch.seq[-1])
        self.framesDecoded += len(batch)
        self.framesLost += int(lost.sum())
        self.badFrames += bad
        self.discardedBytes += discarded
        self.seqDiscontinuities += disc
        return batch, lost, board_time

    def _unwrap_ticks(self, tick: npt.NDArray[np.uint16]) -> npt.NDArray[np.float64]:
        if tick.size == 0:
            return np.zeros(0)
        t = tick.astype(np.int64)
        prev = np.empty_like(t)
        prev[0] = t[0] if self._last_tick is None else self._last_tick
        prev[1:] = t[:-1]
        steps = (t - prev) & 0xFFFF
        times = self._board_time + np.cumsum(steps) / 1000.0
        self._board_time = float(times[-1])
        self._last_tick = int(t[-1])
        return times

    def feed(self, data: bytes | bytearray | memoryview, timestamp: float = 0.0) -> list[PhysioSample]:
        """Decode the frames completed by ``data`` into samples stamped with ``timestamp``."""
        raw = self._tail + bytes(data)
        if len(raw) <= self.small_input_bytes:
            return self._feed_small(raw, timestamp)
        batch, lost, board_time = self._feed_batch(raw)
        beat = self.beats.update
        # tolist(): Python numbers at once; indexing numpy arrays element by element costs ~10x more.
        return [PhysioSample(seq=seq, timestamp=timestamp, boardTime=bt, force=force, temperature=temp,
                             heartRate=beat(bt, float(ppg)), skinConductance=sc, ppg=ppg, flags=flags,
                             lostBefore=lb)
                for seq, bt, force, temp, sc, ppg, flags, lb in zip(
                    batch.seq.tolist(), board_time.tolist(), batch.force.tolist(), batch.temperature.tolist(),
                    batch.skinConductance.tolist(), batch.ppg.tolist(), batch.flags.tolist(), lost.tolist(),
                    strict=True)]

    def _feed_small(self, raw: bytes, timestamp: float) -> list[PhysioSample]:
        """``feed`` for a few frames, in plain Python; the same result as the numpy path, bit for bit:
        the same frame choice (every header is a candidate, CRC-valid ones accepted greedily, bad ones
        counted unless inside an accepted frame), counters, tail and float arithmetic."""
        n = len(raw)
        last_start = n - PHYSIO_FRAME_SIZE
        starts: list[int] = []
        bad = 0
        end = 0  # end of the last accepted frame
        find, crc = raw.find, binascii.crc_hqx
        p = find(PHYSIO_HEADER, 0, max(last_start + 2, 0))
        while p >= 0:
            if crc(raw[p:p + _CRC_SPAN], CRC_INIT) == raw[p + _CRC_SPAN] | raw[p + _CRC_SPAN + 1] << 8:
                if p >= end:
                    starts.append(p)
                    end = p + PHYSIO_FRAME_SIZE
            elif p >= end:
                bad += 1
            p = find(PHYSIO_HEADER, p + 1, last_start + 2)
        keep_from = max(end, n - (PHYSIO_FRAME_SIZE - 1), 0)
        self._tail = raw[keep_from:]
        discarded = keep_from - PHYSIO_FRAME_SIZE * len(starts)
        self.framesDecoded += len(starts)
        self.badFrames += bad
        self.discardedBytes += discarded
        if not starts:
            return []
        cal = self.calibration
        sc_gain, sc_off = cal.skinConductance.gain, cal.skinConductance.offset
        temp_gain, temp_off = cal.temperature.gain, cal.temperature.offset
        force_gain, force_off = cal.force.gain, cal.force.offset
        last_seq, last_tick, board_time = self._last_seq, self._last_tick, self._board_time
        ticks = 0  # cumulative integer ticks of this input, divided once as the numpy path does
        lost_total = 0
        unpack, beat = _PHYSIO_STRUCT.unpack_from, self.beats.update
        out: list[PhysioSample] = []
        for p in starts:
            _, ppg, tick, sc, temp, force, seq, flags, _, _ = unpack(raw, p)
            lost = (seq - (seq - 1 if last_seq is None else last_seq) - 1) & 0xFFFF
            if lost >= 0x8000:  # the counter went backwards: a discontinuity, not losses
                self.seqDiscontinuities += 1
                lost = 0
            lost_total += lost
            last_seq = seq
            ticks += (tick - (tick if last_tick is None else last_tick)) & 0xFFFF
            last_tick = tick
            bt = board_time + ticks / 1000.0
            out.append(PhysioSample(
                seq=seq, timestamp=timestamp, boardTime=bt, force=force_gain * float(force) + force_off,
                temperature=temp_gain * float(temp) + temp_off, heartRate=beat(bt, float(ppg)),
                skinConductance=sc_gain * float(sc) + sc_off, ppg=ppg, flags=flags, lostBefore=lost))
        self._last_seq, self._last_tick, self._board_time = last_seq, last_tick, out[-1].boardTime
        self.framesLost += lost_total
        return out
