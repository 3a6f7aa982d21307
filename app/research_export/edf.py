"""EDF+ (European Data Format, for clinical viewers such as EDFbrowser): every recorded channel as a signal with
its physical unit, the session's course as annotations. Written with pyedflib (edflib underneath) data record by
data record, read back with pyedflib before it is called written.

What EDF cannot hold, and what this does about it (docs/export.md says it to the reader):

* **One time grid.** EDF puts sample k of a signal at ``record_start + k / rate``; every signal has a whole number
  of samples per data record. The record lasts :func:`record_duration` (1 s for the application's rates), so each
  stream keeps its own rate. A sample goes to the grid slot nearest its recorded time (at most half a sample
  period away). A slot no sample reached (a device's clock slightly slower than its nominal rate) holds the
  previous value; longer empty stretches (a device gap) hold the "no value" code. Two samples nearest one slot (a
  device clock faster than its nominal rate, about one sample in 10⁶/ppm) cannot both be kept: the second is
  dropped and counted in the export's notes.
* **16 bits.** Each signal's physical minimum and maximum come from its own data (a first pass), so the resolution
  is (max − min) / 65534; the digital value −32768 is reserved for "no value" (NaN in the record, before a
  stream's first sample, in a device gap).
* **Irregular streams** (the FES channels, published on change) are held from one update to the next on the grid of
  their nominal rate; their exact times are in XDF and BIDS.
* **Annotations** carry the session's course (runs, repetitions with their durations, prompts, alarms, the
  emergency stop, device gaps, FES on/off) with onsets to 100 µs; commands and acknowledgements are left out.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import math
import os
import warnings
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np

from app.research_export import channels as kinds
from app.research_export.common import (
    Cancel,
    ExportError,
    ExportResult,
    Progress,
    Steps,
    fsync_file,
    part_path,
    remove_quietly,
)
from app.research_export.marks import CLINICAL_KINDS, FesSwitches, event_marks
from app.research_export.source import Session, StreamInfo

NO_VALUE = -32768  # the digital value reserved for "no value"
DIGITAL_MIN, DIGITAL_MAX = -32768, 32767
RECORDS_PER_BATCH = 60  # data records placed at once (numpy over a minute, not a record, at a time)
MAX_SHIFT_SLOTS = 1  # a sample whose nearest slot is taken may go to the next one, never further
HOLD_SLOTS = 1  # a regular stream's empty stretch up to this many slots holds the previous value
ANNOTATION_CHARS = 80  # an annotation's text (EDFbrowser shows the start of longer ones)
RECORD_CHOICES = (1.0, 2.0, 4.0, 5.0, 10.0)
MAX_ANNOTATION_SIGNALS = 64  # edflib's limit
EDF_EARLIEST = _dt.datetime(1985, 1, 1)  # EDF's two-digit years start in 1985


def record_duration(rates: list[float]) -> float:
    """The shortest data record (from :data:`RECORD_CHOICES`) in which every rate has a whole number of samples."""
    for d in RECORD_CHOICES:
        if all(abs(r * d - round(r * d)) < 1e-9 for r in rates):
            return d
    return 1.0


def physical_range(lo: float, hi: float) -> tuple[float, float]:
    """A physical minimum below ``lo`` and maximum above ``hi`` that EDF's 8-character header fields hold
    exactly, leaving the lowest digital value free for "no value"."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return -1.0, 1.0
    if hi <= lo:
        pad = max(abs(lo) * 1e-3, 1e-3)
        lo, hi = lo - pad, hi + pad
    step = (hi - lo) / (DIGITAL_MAX - DIGITAL_MIN - 1)
    return _fit8(lo - 1.5 * step, math.floor), _fit8(hi + 0.5 * step, math.ceil)


def _fit8(x: float, rounding: Any) -> float:
    """``x`` rounded (down or up) to the most decimals an 8-character field holds."""
    for decimals in range(7, -1, -1):
        q = rounding(Decimal(repr(x)) * (Decimal(10) ** decimals))
        text = f"{Decimal(q) / (Decimal(10) ** decimals):.{decimals}f}"
        if len(text) <= 8:
            return float(text)
    raise ExportError(f"the value {x:g} does not fit an EDF header (8 characters): change the unit")


@dataclass
class _Signal:
    stream: str
    column: int
    label: str
    unit: str
    transducer: str
    lo: float = math.inf
    hi: float = -math.inf
    pmin: float = -1.0
    pmax: float = 1.0
    digest: Any = field(default_factory=lambda: hashlib.blake2b(digest_size=16))

    def header(self, rate: float) -> dict[str, Any]:
        return {"label": self.label, "dimension": self.unit, "sample_frequency": rate, "physical_max": self.pmax,
                "physical_min": self.pmin, "digital_max": DIGITAL_MAX, "digital_min": DIGITAL_MIN,
                "transducer": self.transducer[:80], "prefilter": ""}


def _labels(session: Session) -> dict[tuple[str, str], str]:
    """EDF labels (16 ASCII characters): the channel's name where it is unique, else with its stream's part."""
    names = [(s.name, c.name) for s in session.streams.values() for c in s.channels]
    counts: dict[str, int] = {}
    for _, ch in names:
        counts[ch] = counts.get(ch, 0) + 1
    out: dict[tuple[str, str], str] = {}
    used: set[str] = set()
    for stream, ch in names:
        text = ch if counts[ch] == 1 else f"{kinds.acq_label(stream)} {ch}"
        text = _text(text)[:16]
        base, n = text, 2
        while text in used:
            text = f"{base[:14]}{n}"
            n += 1
        used.add(text)
        out[(stream, ch)] = text
    return out


@dataclass
class _Placer:
    """Puts one stream's samples into the EDF grid, a data record at a time (its chunks read on demand)."""

    info: StreamInfo
    signals: list[_Signal]
    spr: int  # samples per record
    record_s: float
    t0: float
    session: Session
    placed: int = 0
    dropped: int = 0
    held: int = 0
    worst_s: float = 0.0
    last_slot: int = -1
    last_digital: np.ndarray | None = None
    chunks: Any = None
    slots: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    digital: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int16))
    done: bool = False
    nbytes: int = 0
    _carry_slot: int | None = None

    def __post_init__(self) -> None:
        self.chunks = self.session.chunks(self.info.name)
        self.rate = self.spr / self.record_s
        self.scale = np.array([(DIGITAL_MAX - DIGITAL_MIN) / (s.pmax - s.pmin) for s in self.signals])
        self.offset = np.array([s.pmin for s in self.signals])
        self.digital = np.zeros((0, len(self.signals)), dtype=np.int16)

    def _read(self) -> bool:
        try:
            chunk = next(self.chunks)
        except StopIteration:
            self.done = True
            return False
        self.nbytes += chunk.nbytes
        natural = np.rint((chunk.t - self.t0) * self.rate).astype(np.int64)
        if self.info.irregular:
            keep = self._latest_per_slot(natural)
            slots = natural[keep]
        else:
            keep, slots = self._displace(natural)
        self.dropped += int((~keep).sum())
        values = chunk.values[keep]
        if len(slots):
            self.last_slot = int(slots[-1])
            err = np.abs(chunk.t[keep] - (self.t0 + slots / self.rate))
            self.worst_s = max(self.worst_s, float(err.max()))
        natural = slots
        dig = np.rint((values - self.offset) * self.scale + DIGITAL_MIN)
        dig = np.where(np.isfinite(dig), np.clip(dig, DIGITAL_MIN + 1, DIGITAL_MAX), NO_VALUE).astype(np.int16)
        self.placed += len(natural)
        self.slots = np.concatenate([self.slots, natural])
        self.digital = np.concatenate([self.digital, dig])
        return True

    def _displace(self, natural: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slots for a regular stream's samples: the nearest, or the next free one when a sample took it (at most
        MAX_SHIFT_SLOTS later); a sample that would go further is dropped. Vectorised: slot_i = i + running max of
        (natural_j − j), started after the last slot used; recomputed after each (rare) drop."""
        keep = np.ones(len(natural), dtype=bool)
        start = 0
        last = self.last_slot
        slots = np.empty(len(natural), dtype=np.int64)
        while start < len(natural):
            idx = np.arange(start, len(natural))
            lifted = np.maximum.accumulate(np.maximum(natural[start:] - (idx - start), last + 1))
            s = lifted + (idx - start)
            bad = np.nonzero(s - natural[start:] > MAX_SHIFT_SLOTS)[0]
            if not len(bad):
                slots[start:] = s
                break
            b = start + int(bad[0])
            slots[start:b] = s[: b - start]
            keep[b] = False
            last = int(slots[b - 1]) if b > start else last
            start = b + 1
        return keep, slots[keep]

    def _latest_per_slot(self, natural: np.ndarray) -> np.ndarray:
        """An irregular stream (a setting published on change): of several updates nearest one slot, the latest
        is the setting in force; the earlier ones are superseded (counted as dropped)."""
        later_same = np.concatenate([natural[1:] == natural[:-1], [False]])
        return ~later_same & (natural > self.last_slot)

    def records(self, r: int, n: int) -> np.ndarray:
        """The (n·spr, signals) digital block of data records ``r`` … ``r + n − 1``."""
        first, end = r * self.spr, (r + n) * self.spr
        length = end - first
        while not self.done and (not len(self.slots) or self.slots[-1] < end):
            if not self._read():
                break
        n = int(np.searchsorted(self.slots, end))
        slots, digital = self.slots[:n], self.digital[:n]
        self.slots, self.digital = self.slots[n:], self.digital[n:]
        block = np.full((length, len(self.signals)), NO_VALUE, dtype=np.int16)
        filled = np.zeros(length, dtype=bool)
        inside = slots >= first  # samples before the grid's start (none: t0 is the earliest time) are dropped
        self.dropped += int((~inside).sum())
        idx = slots[inside] - first
        block[idx] = digital[inside]
        filled[idx] = True
        self._hold(block, filled, first)
        return block

    def _hold(self, block: np.ndarray, filled: np.ndarray, first: int) -> None:
        """Empty slots: the previous value where the stream holds it (irregular: until the next update; regular:
        a single empty slot between two samples), "no value" elsewhere."""
        far = np.iinfo(np.int64).max // 4
        length = len(filled)
        idx = np.arange(length)
        last_index = np.maximum.accumulate(np.where(filled, idx, -1))
        carry = self._carry_slot if self._carry_slot is not None else -far
        prev = np.where(last_index >= 0, first + last_index, carry)
        next_index = np.minimum.accumulate(np.where(filled, idx, length)[::-1])[::-1]
        pending = int(self.slots[0]) if len(self.slots) else far
        nxt = np.where(next_index < length, first + next_index, pending)
        empty = ~filled & (prev > -far)
        if self.info.irregular:
            hold = empty if not (self.done and not len(self.slots)) else empty & (first + idx <= self.last_slot)
        else:
            hold = empty & (nxt < far) & (nxt - prev <= HOLD_SLOTS + 1)
        from_block = hold & (last_index >= 0)
        block[from_block] = block[last_index[from_block]]
        from_carry = hold & (last_index < 0)
        if from_carry.any() and self.last_digital is not None:
            block[from_carry] = self.last_digital
        self.held += int(hold.sum())
        if filled.any():
            k = int(np.nonzero(filled)[0][-1])
            self._carry_slot = first + k
            self.last_digital = block[k].copy()


def _edf_start(session: Session, t0: float, shift_days: int) -> _dt.datetime:
    """The local wall time of ``t0`` (the station's clock, as the manifest gives the session's start)."""
    iso = session.start_iso
    try:
        start = _dt.datetime.fromisoformat(iso)
    except ValueError:
        start = _dt.datetime.fromtimestamp(session.start_wall or 0.0).astimezone()
    moment = start + _dt.timedelta(seconds=t0 - session.start_mono) - _dt.timedelta(days=shift_days)
    moment = moment.replace(tzinfo=None)
    if moment < EDF_EARLIEST:
        raise ExportError(f"EDF cannot hold a start date before 1985 ({moment:%Y-%m-%d}): shift the dates by "
                          "fewer days")
    return moment


def _text(text: str) -> str:
    """EDF header text: printable ASCII only (µ → u, ° → deg, anything else → ?)."""
    text = text.replace("µ", "u").replace("°", "deg")
    return "".join(ch if " " <= ch <= "~" else "?" for ch in text)


def _ascii(text: str) -> str:
    return text.encode("ascii", errors="replace").decode("ascii").replace(" ", "_")


def export_edf(session: Session, path: str | Path, *, include_names: bool = False, shift_days: int = 0,
               progress: Progress | None = None, cancel: Cancel | None = None) -> ExportResult:
    """Write ``session`` to one EDF+ file (a temporary name first, moved into place once read back)."""
    import pyedflib

    path = Path(path)
    tmp = part_path(path)
    steps = Steps(progress, cancel, session.total_bytes * 2.2 + 1)
    result = ExportResult()
    labels = _labels(session)
    # pass 1: each signal's range, the streams' extent, FES switches
    signals: dict[str, list[_Signal]] = {}
    t_first, t_last = session.start_mono, session.start_mono
    switches: list[FesSwitches] = []
    for info in session.streams.values():
        sw = FesSwitches([c.name for c in info.channels]) if info.irregular else None
        if sw is not None:
            switches.append(sw)
        sigs = [_Signal(info.name, i, labels[(info.name, c.name)], kinds.edf_unit(c.unit),
                        _text(f"{info.name} {c.name} ({c.label})")) for i, c in enumerate(info.channels)]
        for chunk in session.chunks(info.name):
            with np.errstate(invalid="ignore"):
                lo, hi = np.nanmin(chunk.values, axis=0), np.nanmax(chunk.values, axis=0)
            for s, a, b in zip(sigs, lo, hi, strict=True):
                if math.isfinite(a):
                    s.lo, s.hi = min(s.lo, float(a)), max(s.hi, float(b))
            t_first = min(t_first, float(chunk.t[0]))
            t_last = max(t_last, float(chunk.t[-1]))
            if sw is not None:
                sw.feed(chunk.t, chunk.values)
            steps.advance(chunk.nbytes, f"EDF {session.patient_id}: ranges")
        for s in sigs:
            s.pmin, s.pmax = physical_range(s.lo, s.hi)
        signals[info.name] = sigs
    marks = [m for m in event_marks(session.events, session.end_mono) if m.kind in CLINICAL_KINDS]
    fes_marks = sorted((m for sw in switches for m in sw.marks), key=lambda m: m.t)
    t0 = min(t_first, session.start_mono, *(m.t for m in marks[:1]))
    t_end = max(t_last, session.end_mono, *(m.t + m.duration for m in marks))
    rates = {n: (s.rate_hz if s.rate_hz > 0 else 10.0) for n, s in session.streams.items()}
    record_s = record_duration(list(rates.values()))
    spr = {n: max(1, round(r * record_s)) for n, r in rates.items()}
    for name, r in rates.items():
        if abs(spr[name] / record_s - r) > 1e-9:
            result.notes.append(f"{name}: {r:g} Hz is not a whole number of samples per {record_s:g} s record; "
                                f"written at {spr[name] / record_s:g} Hz")
    n_records = max(1, math.ceil((t_end - t0) * (1 + 1e-12) / record_s + 1e-9))
    room = MAX_ANNOTATION_SIGNALS * n_records - 1  # edflib: one annotation per annotation signal and record
    if len(marks) > room:
        raise ExportError(f"{session.label}: {len(marks)} events do not fit the annotations of {n_records} EDF "
                          "records")
    if len(marks) + len(fes_marks) > room:
        result.notes.append(f"{path.name}: {len(marks) + len(fes_marks) - room} of {len(fes_marks)} FES on/off "
                            "switches left out of the annotations (no room in EDF's records); XDF and BIDS have them")
        fes_marks = fes_marks[: room - len(marks)]
    marks = sorted(marks + fes_marks, key=lambda m: m.t)
    start = _edf_start(session, t0, shift_days)
    placers = []
    for name, info in session.streams.items():
        placers.append(_Placer(info, signals[name], spr[name], record_s, t0, session))
    headers = [s.header(spr[p.info.name] / record_s) for p in placers for s in p.signals]
    if not headers:
        raise ExportError(f"{session.label} has no stream to write")
    try:
        writer = pyedflib.EdfWriter(str(tmp), len(headers), file_type=pyedflib.FILETYPE_EDFPLUS)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot create {tmp}: {exc.strerror or exc}", str(tmp)) from exc
    written_annotations = 0
    try:
        try:
            with warnings.catch_warnings():  # pyedflib warns that a set record duration fixes the rates: it must
                warnings.simplefilter("ignore", UserWarning)
                writer.setDatarecordDuration(record_s)
            # edflib stores one annotation per annotation signal in each data record: room for all of them
            writer.set_number_of_annotation_signals(min(MAX_ANNOTATION_SIGNALS, len(marks) // n_records + 1))
            writer.setSignalHeaders(headers)
            writer.setStartdatetime(start)
            writer.setPatientCode(_ascii(session.patient_id))
            profile = session.manifest.get("patient") if isinstance(session.manifest.get("patient"), dict) else {}
            if include_names and profile.get("full_name"):
                writer.setPatientName(_ascii(str(profile["full_name"])))
                if profile.get("birth_date"):
                    writer.setBirthdate(_dt.date.fromisoformat(str(profile["birth_date"])))
            else:
                writer.setPatientName("X")
            if include_names and session.manifest.get("operator"):
                writer.setTechnician(_ascii(str(session.manifest["operator"]))[:30])
            writer.setEquipment(_ascii(f"LINarm++ Manager {session.manifest.get('app_version', '')}".strip())[:30])
            read = 0
            for r0 in range(0, n_records, RECORDS_PER_BATCH):
                n = min(RECORDS_PER_BATCH, n_records - r0)
                blocks = [p.records(r0, n) for p in placers]
                for p, b in zip(placers, blocks, strict=True):
                    for i, sig in enumerate(p.signals):
                        sig.digest.update(np.ascontiguousarray(b[:, i]).tobytes())
                for k in range(n):
                    data = np.concatenate([b[k * p.spr:(k + 1) * p.spr].T.reshape(-1)
                                           for p, b in zip(placers, blocks, strict=True)])
                    if writer.blockWriteDigitalShortSamples(data) != 0:
                        raise OSError(f"writing data record {r0 + k + 1} of {tmp.name} failed (disk full?)")
                now = sum(p.nbytes for p in placers)
                steps.advance(now - read, f"EDF {session.patient_id}: {r0 * record_s:.0f} s")
                read = now
            for m in marks:
                writer.writeAnnotation(m.t - t0, m.duration if m.duration > 0 else -1, m.label[:ANNOTATION_CHARS])
                written_annotations += 1
        finally:
            writer.close()
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        steps.advance(0, f"{path.name}: reading back")
        _verify(tmp, [s for p in placers for s in p.signals], [spr[p.info.name] for p in placers for _ in p.signals],
                n_records, written_annotations)
        steps.advance(session.total_bytes * 0.2, f"{path.name}: read back")
        os.replace(tmp, path)
        fsync_file(path)
    except BaseException:
        remove_quietly(tmp)
        raise
    result.written.append(path)
    figures: dict[str, Any] = {"record_s": record_s, "records": n_records, "annotations": written_annotations,
                               "streams": {}}
    for p in placers:
        figures["streams"][p.info.name] = {"placed": p.placed, "dropped": p.dropped, "held": p.held,
                                           "rate_hz": p.rate, "worst_time_error_s": p.worst_s}
        if p.dropped and p.info.irregular:
            result.notes.append(f"{path.name}: {p.info.name}: {p.dropped} of {p.placed + p.dropped} updates were "
                                f"superseded within one {1 / p.rate * 1000:g} ms slot of EDF's grid (the later "
                                "one is kept); XDF and BIDS keep them all")
        elif p.dropped:
            result.notes.append(f"{path.name}: {p.info.name}: {p.dropped} of {p.placed + p.dropped} samples found no "
                                "free slot on EDF's time grid within one sample period of their time (a device "
                                "clock faster than its nominal rate, or bunched time stamps); XDF and BIDS keep them")
    result.figures[str(path)] = figures
    return result


def _verify(path: Path, signals: list[_Signal], spr: list[int], records: int, annotations: int) -> None:
    """Read the file back with pyedflib: the header, every signal's digital samples, the annotations."""
    import pyedflib

    try:
        reader = pyedflib.EdfReader(str(path))
    except OSError as exc:
        raise OSError(f"{path.name} does not read back as EDF+: {exc}") from exc
    try:
        if reader.signals_in_file != len(signals) or reader.datarecords_in_file != records:
            raise OSError(f"{path.name} reads back with {reader.signals_in_file} signals and "
                          f"{reader.datarecords_in_file} records ({len(signals)} and {records} written)")
        for i, s in enumerate(signals):
            if reader.getLabel(i) != s.label or not math.isclose(reader.getPhysicalMinimum(i), s.pmin) or \
                    not math.isclose(reader.getPhysicalMaximum(i), s.pmax):
                raise OSError(f"{path.name}: the header of signal {s.label} reads back different")
            digest = hashlib.blake2b(digest_size=16)
            n = spr[i] * records
            step = spr[i] * 600
            for a in range(0, n, step):
                block = reader.readSignal(i, a, min(step, n - a), digital=True)
                digest.update(block.astype(np.int16).tobytes())
            if digest.digest() != s.digest.digest():
                raise OSError(f"{path.name}: the samples of {s.label} read back different from those written")
        got = len(reader.readAnnotations()[0])
        if got != annotations:
            raise OSError(f"{path.name}: {got} of {annotations} annotations read back")
    finally:
        reader.close()
