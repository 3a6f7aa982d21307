"""XDF (the file format of LabRecorder and the Lab Streaming Layer): a small writer from the format's
specification (XDF 1.0, github.com/sccn/xdf wiki "Specifications"), a chunk scanner that reads a file back without
loading it, and the session export.

The format: the magic ``XDF:``, then chunks ``[NumLengthBytes][Length][Tag u16][content]`` (little-endian; Length
counts the tag and the content; NumLengthBytes is 1, 4 or 8). Tags: 1 FileHeader (XML), 2 StreamHeader (u32 stream
id + XML), 3 Samples (u32 id, a variable-length sample count, then per sample ``[TimeStampBytes 0|8][f64 time]``
and the values), 4 ClockOffset (u32 id, f64 collection time, f64 offset), 5 Boundary (a fixed 16-byte UUID that
lets a reader resynchronise in a damaged file), 6 StreamFooter (u32 id + XML). A string value is a variable-length
byte count and UTF-8 bytes. pyxdf (the reference reader) reads what this writes: tests/test_research_export_xdf.py.

The export writes every chunk as it goes — stream headers first, then the samples of all streams interleaved in
windows of :data:`WINDOW_S` of session time (as LabRecorder interleaves them), a clock offset per stream and
window, a boundary chunk every :data:`BOUNDARY_S`, the footers last — so memory holds a window, never a session.
"""

from __future__ import annotations

import math
import os
import struct
import uuid
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from app.research_export import channels as kinds
from app.research_export.common import (
    Cancel,
    ExportResult,
    HashingWriter,
    Progress,
    Steps,
    file_digest,
    fsync_file,
    open_private,
    part_path,
    remove_quietly,
)
from app.research_export.marks import FesSwitches, Mark, event_marks, exported, record_json
from app.research_export.source import Chunk, Session
from app.session import recording

MAGIC = b"XDF:"
TAG_FILE_HEADER, TAG_STREAM_HEADER, TAG_SAMPLES, TAG_CLOCK_OFFSET, TAG_BOUNDARY, TAG_STREAM_FOOTER = 1, 2, 3, 4, 5, 6
BOUNDARY_UUID = bytes([0x43, 0xA5, 0x46, 0xDC, 0xCB, 0xF5, 0x41, 0x0F, 0xB3, 0x0E, 0xD5, 0x46, 0x73, 0x83, 0xCB, 0xE4])
WINDOW_S = 5.0  # samples are written in windows of session time; one clock offset per stream per window
BOUNDARY_S = 10.0  # LabRecorder writes a boundary chunk about every 10 s
MAX_CHUNK_SAMPLES = 65536
EVENTS_STREAM = "linarmpp.events"  # the live LSL event outlet's name (app.session.lsl.EVENTS_STREAM)
MARKERS_STREAM = "linarmpp.markers"
SOURCE_PREFIX = "linarmpp"  # source ids as the live outlets have them (app.session.lsl.SOURCE_PREFIX)


def _varlen(n: int) -> bytes:
    """A variable-length count: one byte saying how many bytes follow (1, 4 or 8), then the count."""
    if n < 1 << 8:
        return struct.pack("<BB", 1, n)
    if n < 1 << 32:
        return struct.pack("<BI", 4, n)
    return struct.pack("<BQ", 8, n)


def _chunk_head(tag: int, content_len: int) -> bytes:
    length = content_len + 2  # the length counts the tag
    return _varlen(length) + struct.pack("<H", tag)


class XdfWriter:
    """Writes XDF chunks to a binary file object as they come (nothing is kept but the file position)."""

    def __init__(self, fh: IO[bytes] | HashingWriter) -> None:
        self.fh = fh
        fh.write(MAGIC)
        self._chunk(TAG_FILE_HEADER, b'<?xml version="1.0"?><info><version>1.0</version></info>')

    def _chunk(self, tag: int, content: bytes | bytearray) -> None:
        self.fh.write(_chunk_head(tag, len(content)))
        self.fh.write(content)

    def stream_header(self, stream_id: int, xml: str) -> None:
        self._chunk(TAG_STREAM_HEADER, struct.pack("<I", stream_id) + xml.encode("utf-8"))

    def samples(self, stream_id: int, t: np.ndarray, values: np.ndarray) -> None:
        """Numeric (double64) samples, each with its time stamp; ``values`` is (n, channels)."""
        n = len(t)
        if n == 0:
            return
        channels = values.shape[1]
        dtype = np.dtype([("stamp_bytes", "u1"), ("t", "<f8"), ("v", "<f8", (channels,))])
        packed = np.empty(n, dtype=dtype)
        packed["stamp_bytes"] = 8
        packed["t"] = t
        packed["v"] = values
        body = packed.tobytes()
        head = struct.pack("<I", stream_id) + _varlen(n)
        self.fh.write(_chunk_head(TAG_SAMPLES, len(head) + len(body)))
        self.fh.write(head)
        self.fh.write(body)

    def string_samples(self, stream_id: int, t: list[float], texts: list[str]) -> None:
        """One-channel string samples (markers), each with its time stamp."""
        if not t:
            return
        parts = [struct.pack("<I", stream_id), _varlen(len(t))]
        for stamp, text in zip(t, texts, strict=True):
            data = text.encode("utf-8")
            parts += [struct.pack("<Bd", 8, stamp), _varlen(len(data)), data]
        self._chunk(TAG_SAMPLES, b"".join(parts))

    def clock_offset(self, stream_id: int, collection_time: float, offset: float) -> None:
        self._chunk(TAG_CLOCK_OFFSET, struct.pack("<Idd", stream_id, collection_time, offset))

    def boundary(self) -> None:
        self._chunk(TAG_BOUNDARY, BOUNDARY_UUID)

    def stream_footer(self, stream_id: int, xml: str) -> None:
        self._chunk(TAG_STREAM_FOOTER, struct.pack("<I", stream_id) + xml.encode("utf-8"))


# ---------------------------------------------------------------------------------------------- XML
@dataclass
class StreamDescription:
    """A stream header as an LSL outlet describes itself (and as LabRecorder writes it)."""

    name: str
    type: str
    channel_count: int
    nominal_srate: float  # 0: irregular
    channel_format: str  # "double64" or "string"
    source_id: str
    created_at: float
    uid: str
    session_id: str = "default"
    hostname: str = ""
    channels: list[dict[str, str]] = field(default_factory=list)  # label, unit, type, description
    extra: dict[str, str] = field(default_factory=dict)  # desc children (text)
    device_clock: dict[str, str] = field(default_factory=dict)  # desc/device_clock children (text), see below


def header_xml(d: StreamDescription) -> str:
    info = ET.Element("info")
    for tag, value in (("name", d.name), ("type", d.type), ("channel_count", str(d.channel_count)),
                       ("nominal_srate", _num(d.nominal_srate)), ("channel_format", d.channel_format),
                       ("source_id", d.source_id), ("version", "1.1000000000000001"),
                       ("created_at", _num(d.created_at)), ("uid", d.uid), ("session_id", d.session_id),
                       ("hostname", d.hostname), ("v4address", ""), ("v4data_port", "0"),
                       ("v4service_port", "0"), ("v6address", ""), ("v6data_port", "0"), ("v6service_port", "0")):
        ET.SubElement(info, tag).text = value
    desc = ET.SubElement(info, "desc")
    ET.SubElement(desc, "manufacturer").text = "LINarm++ Manager"
    if d.channels:
        chans = ET.SubElement(desc, "channels")
        for ch in d.channels:
            c = ET.SubElement(chans, "channel")
            for key in ("label", "unit", "type", "description"):
                if key in ch:
                    ET.SubElement(c, key).text = ch[key]
    for key, value in d.extra.items():
        ET.SubElement(desc, key).text = value
    if d.device_clock:
        dc = ET.SubElement(desc, "device_clock")
        for key, value in d.device_clock.items():
            ET.SubElement(dc, key).text = value
    return '<?xml version="1.0"?>' + ET.tostring(info, encoding="unicode")


def footer_xml(first: float, last: float, count: int, offsets: list[tuple[float, float]]) -> str:
    info = ET.Element("info")
    ET.SubElement(info, "first_timestamp").text = _num(first)
    ET.SubElement(info, "last_timestamp").text = _num(last)
    ET.SubElement(info, "sample_count").text = str(count)
    co = ET.SubElement(info, "clock_offsets")
    for time, value in offsets:
        o = ET.SubElement(co, "offset")
        ET.SubElement(o, "time").text = _num(time)
        ET.SubElement(o, "value").text = _num(value)
    return '<?xml version="1.0"?>' + ET.tostring(info, encoding="unicode")


def _num(x: float) -> str:
    x = float(x)
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


# ---------------------------------------------------------------------------------------------- reading back
@dataclass
class ScannedStream:
    header: str = ""
    footer: str = ""
    samples: int = 0
    offsets: int = 0


@dataclass
class Scan:
    streams: dict[int, ScannedStream] = field(default_factory=dict)
    boundaries: int = 0
    file_header: str = ""


def _read_varlen(fh: IO[bytes]) -> int:
    head = fh.read(1)
    if not head:
        raise EOFError
    nbytes = head[0]
    fmt = {1: "<B", 4: "<I", 8: "<Q"}.get(nbytes)
    if fmt is None:
        raise ValueError(f"invalid length width {nbytes}")
    data = fh.read(nbytes)
    if len(data) != nbytes:
        raise ValueError("file ends inside a chunk length")
    return int(struct.unpack(fmt, data)[0])


def scan_xdf(path: Path) -> Scan:
    """Walk the chunks of an XDF file (seeking over sample data): every chunk's framing, the stream headers and
    footers and each stream's sample count. Raises ValueError on a malformed file."""
    scan = Scan()
    size = path.stat().st_size
    with open(path, "rb") as fh:
        if fh.read(4) != MAGIC:
            raise ValueError("not an XDF file (no XDF: magic)")
        while fh.tell() < size:
            length = _read_varlen(fh)
            start = fh.tell()
            if length < 2 or start + length > size:
                raise ValueError(f"chunk at byte {start} runs past the end of the file")
            (tag,) = struct.unpack("<H", fh.read(2))
            if tag == TAG_FILE_HEADER:
                scan.file_header = fh.read(length - 2).decode("utf-8")
            elif tag in (TAG_STREAM_HEADER, TAG_STREAM_FOOTER):
                (sid,) = struct.unpack("<I", fh.read(4))
                xml = fh.read(length - 6).decode("utf-8")
                ET.fromstring(xml.split("?>", 1)[-1])  # well-formed
                entry = scan.streams.setdefault(sid, ScannedStream())
                if tag == TAG_STREAM_HEADER:
                    entry.header = xml
                else:
                    entry.footer = xml
            elif tag == TAG_SAMPLES:
                (sid,) = struct.unpack("<I", fh.read(4))
                scan.streams.setdefault(sid, ScannedStream()).samples += _read_varlen(fh)
            elif tag == TAG_CLOCK_OFFSET:
                (sid,) = struct.unpack("<I", fh.read(4))
                scan.streams.setdefault(sid, ScannedStream()).offsets += 1
            elif tag == TAG_BOUNDARY:
                if fh.read(16) != BOUNDARY_UUID:
                    raise ValueError("a boundary chunk with the wrong UUID")
                scan.boundaries += 1
            else:
                raise ValueError(f"unknown chunk tag {tag}")
            fh.seek(start + length)
    return scan


# ---------------------------------------------------------------------------------------------- the export
class _Pending:
    """One stream's samples read from its file and not yet written: whole chunks, taken up to a time."""

    def __init__(self, chunks: Iterator[Chunk]) -> None:
        self.chunks = chunks
        self.t = np.zeros(0)
        self.values: np.ndarray | None = None
        self.done = False
        self.nbytes = 0  # file bytes read so far (progress)

    def _fill(self) -> bool:
        try:
            chunk = next(self.chunks)
        except StopIteration:
            self.done = True
            return False
        self.nbytes += chunk.nbytes
        if self.values is None or not len(self.t):
            self.t, self.values = chunk.t, chunk.values
        else:
            self.t = np.concatenate([self.t, chunk.t])
            self.values = np.concatenate([self.values, chunk.values])
        return True

    def take_before(self, t_end: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The samples (in file order) up to the first with a time at or after ``t_end``."""
        while not self.done and (not len(self.t) or self.t[-1] < t_end):
            if not self._fill():
                break
        if self.values is None or not len(self.t):
            return None
        below = self.t < t_end
        n = len(below) if below.all() else int(np.argmin(below))
        if n == 0:
            return None
        t, v = self.t[:n], self.values[:n]
        self.t, self.values = self.t[n:], self.values[n:]
        return t, v

    def next_time(self) -> float:
        if not len(self.t) and not self.done:
            self._fill()
        return float(self.t[0]) if len(self.t) else math.inf


@dataclass
class _Out:
    sid: int
    name: str
    count: int = 0
    first: float = math.nan
    last: float = math.nan
    offsets: list[tuple[float, float]] = field(default_factory=list)

    def wrote(self, t: np.ndarray | list[float]) -> None:
        if len(t):
            if self.count == 0:
                self.first = float(t[0])
            self.last = float(t[-1])
            self.count += len(t)


CLOCKS = ("host", "device")  # export_xdf's ``clock``: what the device streams' time stamps are (docs/export.md)
HOST_CLOCK = ("time stamps: the host's monotonic clock in seconds (the recorder's); clock offsets are therefore 0")
HOST_CLOCK_OF_DEVICE = ("time stamps: the host's monotonic clock in seconds, each sample at the time the application "
                        "recorded for it (the {device}'s own clock mapped to the host's while recording, "
                        "app/devices/clock.py); clock offsets are therefore 0. The {device}'s own clock is in "
                        "device_clock: each sample's device time is recoverable from its time stamp")
DEVICE_CLOCK_LINES = ("one line per estimate of the map the application used while recording (clocks.csv), in "
                      "force from its host_s on: device = device_s + (t - host_s) / (1 + drift) for a time stamp t "
                      "(the {device}'s clock in seconds, unwrapped, continued across a restart of the device)")
DEVICE_CLOCK = ("time stamps: the {device}'s own clock in seconds (unwrapped; continued across a restart of the "
                "device); the ClockOffset chunks hold the map to the host's monotonic clock the application "
                "estimated while recording (app/devices/clock.py): load with pyxdf's synchronize_clocks (its default) "
                "to put the samples on the host's clock")


def clock_lines_text(lines: recording.ClockLines) -> str:
    """A device's clock estimates as the text of desc/device_clock/lines: ``host_s,device_s,drift`` per line, each
    number as the shortest text that reads back to the same double (nothing lost)."""
    return "".join(f"{h!r},{d!r},{k!r}\n" for h, d, k in zip(lines.host.tolist(), lines.device.tolist(),
                                                          lines.drift.tolist(), strict=True))


def device_times(stream: dict) -> np.ndarray:
    """The device-clock time of every sample of a stream as pyxdf loads it (``load_xdf``'s stream dict, host-clock
    form): its time stamps mapped back by the clock estimates in its header's desc/device_clock. The same numbers
    the device-clock form (``clock="device"``) writes as time stamps. Raises KeyError for a stream without a device
    clock."""
    text = stream["info"]["desc"][0]["device_clock"][0]["lines"][0]
    table = np.loadtxt(text.splitlines(), delimiter=",", ndmin=2, dtype=np.float64)
    lines = recording.ClockLines(table[:, 0].copy(), table[:, 1].copy(), table[:, 2].copy())
    return lines.to_device(np.asarray(stream["time_stamps"], dtype=np.float64))


def stream_descriptions(session: Session, clock_form: str = "host") -> list[StreamDescription]:
    """The header of every stream of the session, then the events' and the markers' (ids 1, 2, … in order).
    ``clock_form`` "host": every stream on the host's clock, a device's clock estimates in desc/device_clock;
    "device": a device's streams on its clock (ClockOffset chunks map it to the host's)."""
    host = str((session.manifest.get("host") or {}).get("node") or "")
    session_uuid = str(session.manifest.get("session_uuid") or "")
    ns = uuid.UUID(session_uuid) if recording.is_session_uuid(session_uuid) else uuid.uuid5(
        uuid.NAMESPACE_URL, f"linarmpp:{session.patient_id}:{session.start_iso}:{session.start_mono!r}")
    out = []
    clocks = session.device_clocks()
    clock = HOST_CLOCK
    for info in session.streams.values():
        chans = [{"label": c.name, "unit": c.unit, "type": kinds.kind(info.name, c).xdf_type, "description": c.label}
                 for c in info.channels]
        lines = clocks.get(info.device)
        has_clock = lines is not None and len(lines) > 0
        text = clock if not has_clock else (DEVICE_CLOCK if clock_form == "device" else HOST_CLOCK_OF_DEVICE)
        out.append(StreamDescription(
            info.name, info.device, len(info.channels), 0.0 if info.irregular else info.rate_hz, "double64",
            f"{SOURCE_PREFIX}.{info.name}", session.start_mono, str(uuid.uuid5(ns, info.name)), session_uuid or
            "default", host, chans, {"device": info.device, "clock": text.format(device=info.device),
                                     "rate": "irregular: published on change" if info.irregular else
                                     f"nominal {info.rate_hz:g} Hz (the device's clock)"},
            {"device": info.device, "columns": "host_s,device_s,drift",
             "description": DEVICE_CLOCK_LINES.format(device=info.device),
             "lines": clock_lines_text(lines)} if has_clock and clock_form == "host" and lines is not None else {}))
    for name, what in ((EVENTS_STREAM, "every recorded event as JSON (events.jsonl), as the live LSL outlet sends it"),
                       (MARKERS_STREAM, "the session's course as short markers (runs, repetitions, prompts, alarms, "
                                        "emergency stop, FES on/off): the BIDS events' trial_type and value")):
        out.append(StreamDescription(name, "Markers", 1, 0.0, "string", f"{SOURCE_PREFIX}.{name.split('.')[-1]}",
                                     session.start_mono, str(uuid.uuid5(ns, name)), session_uuid or "default", host,
                                     [{"label": name.split(".")[-1], "unit": "", "type": "Marker"}],
                                     {"content": what, "clock": clock}))
    return out


def marker_marks(marks: list[Mark]) -> list[Mark]:
    """The instants of the session's course (spans are given by their start and end events)."""
    from app.research_export.marks import CLINICAL_KINDS, SPAN_KINDS

    instant = (CLINICAL_KINDS - set(SPAN_KINDS)) | {k for pair in SPAN_KINDS.values() for k in pair}
    return [m for m in marks if m.record is not None and m.kind in instant]


def export_xdf(session: Session, path: str | Path, progress: Progress | None = None,
               cancel: Cancel | None = None, shift_days: int = 0, clock: str = "host") -> ExportResult:
    """Write ``session`` to one XDF file at ``path`` (a temporary name first; moved into place once read back).
    ``clock`` (:data:`CLOCKS`): "host" (every sample at its recorded time, offsets 0; the devices' clocks in the
    headers) or "device" (LabRecorder's form for a stream from another machine: a device's streams on its clock,
    the measured map as ClockOffset chunks). Raises ExportCancelled (nothing left behind) or OSError."""
    if clock not in CLOCKS:
        raise ValueError(f"clock must be one of {CLOCKS}, not {clock!r}")
    path = Path(path)
    tmp = part_path(path)
    steps = Steps(progress, cancel, session.total_bytes * 1.05 + 1)
    result = ExportResult()
    try:
        with open_private(tmp) as raw:
            out = HashingWriter(raw)
            counts = _write_xdf(session, out, steps, shift_days, clock)
            raw.flush()
            os.fsync(raw.fileno())
        steps.advance(0, f"{path.name}: reading back")
        _verify(tmp, out, counts)
        steps.advance(session.total_bytes * 0.05, f"{path.name}: read back")
        os.replace(tmp, path)
        fsync_file(path)
    except BaseException:
        remove_quietly(tmp)
        raise
    result.written.append(path)
    result.figures[str(path)] = {"samples": {o.name: o.count for o in counts.values()}}
    return result


def _write_xdf(session: Session, out: HashingWriter, steps: Steps, shift_days: int = 0,
               clock_form: str = "host") -> dict[int, _Out]:
    writer = XdfWriter(out)
    descriptions = stream_descriptions(session, clock_form)
    outs: dict[int, _Out] = {}
    for sid, d in enumerate(descriptions, start=1):
        writer.stream_header(sid, header_xml(d))
        outs[sid] = _Out(sid, d.name)
    names = list(session.streams)
    pending = {sid: _Pending(session.chunks(name)) for sid, name in enumerate(names, start=1)}
    # The device-clock form: a stream of a device with a clock is written on that clock, with the offsets measured
    # (_DeviceOffsets). Otherwise (and for the others) every stream is on the host's (the recorder's) clock: offset 0.
    clocks = session.device_clocks() if clock_form == "device" else {}
    offsets = {sid: _DeviceOffsets(clocks[session.streams[n].device]) for sid, n in enumerate(names, start=1)
               if len(clocks.get(session.streams[n].device, ()))}
    events_sid, markers_sid = len(names) + 1, len(names) + 2
    fes_sid = next((sid for sid, n in enumerate(names, start=1) if session.streams[n].irregular and any(
        c.name.startswith("current") for c in session.streams[n].channels)), None)
    switches = FesSwitches([c.name for c in session.streams[names[fes_sid - 1]].channels]) if fes_sid else None
    marks = event_marks(session.events, session.end_mono)
    markers = marker_marks(marks)
    events = session.events
    ev_i = mk_i = 0
    begin = min([session.start_mono, *[p.next_time() for p in pending.values()],
                 *(float(e["t_mono"]) for e in events[:1])])
    t = math.floor(begin / WINDOW_S) * WINDOW_S
    next_boundary = t + BOUNDARY_S
    read_bytes = 0
    while True:
        t_end = t + WINDOW_S
        for sid, p in pending.items():
            while True:  # a window's samples, in chunks of at most MAX_CHUNK_SAMPLES
                got = p.take_before(t_end)
                if got is None:
                    break
                ts, values = got
                stamps = offsets[sid].clock.to_device(ts) if sid in offsets else ts
                for a in range(0, len(ts), MAX_CHUNK_SAMPLES):
                    writer.samples(sid, stamps[a:a + MAX_CHUNK_SAMPLES], values[a:a + MAX_CHUNK_SAMPLES])
                outs[sid].wrote(stamps)
                if sid == fes_sid and switches is not None:
                    switches.feed(ts, values)
        ev_j = ev_i
        while ev_j < len(events) and float(events[ev_j]["t_mono"]) < t_end:
            ev_j += 1
        if ev_j > ev_i:
            stamps = [float(e["t_mono"]) for e in events[ev_i:ev_j]]
            writer.string_samples(events_sid, stamps, [record_json(exported(e, shift_days))
                                                       for e in events[ev_i:ev_j]])
            outs[events_sid].wrote(stamps)
            ev_i = ev_j
        mk_j = mk_i
        while mk_j < len(markers) and markers[mk_j].t < t_end:
            mk_j += 1
        window_marks = markers[mk_i:mk_j] + (switches.marks if switches is not None else [])
        mk_i = mk_j
        if switches is not None:
            switches.marks = []
        if window_marks:
            window_marks.sort(key=lambda m: m.t)
            writer.string_samples(markers_sid, [m.t for m in window_marks], [m.label for m in window_marks])
            outs[markers_sid].wrote([m.t for m in window_marks])
        for sid in outs:  # the offsets between each stream's clock and the file's (the host's)
            for collected, value in (offsets[sid].until(t, t_end) if sid in offsets else [(t, 0.0)]):
                writer.clock_offset(sid, collected, value)
                outs[sid].offsets.append((collected, value))
        if t_end >= next_boundary:
            writer.boundary()
            next_boundary = t_end + BOUNDARY_S
        now_read = sum(p.nbytes for p in pending.values())
        steps.advance(now_read - read_bytes, f"XDF {session.patient_id}: {t_end - session.start_mono:.0f} s")
        read_bytes = now_read
        finished = all(p.done and not len(p.t) for p in pending.values()) and ev_i >= len(events) \
            and mk_i >= len(markers)
        if finished:
            break
        # the next window with something in it (a long gap, a time stamp far away): no empty windows on the way
        upcoming = min([p.next_time() for p in pending.values()]
                       + [float(events[ev_i]["t_mono"]) if ev_i < len(events) else math.inf,
                          markers[mk_i].t if mk_i < len(markers) else math.inf])
        t = max(t_end, math.floor(upcoming / WINDOW_S) * WINDOW_S) if math.isfinite(upcoming) else t_end
    if switches is not None and switches.marks:
        writer.string_samples(markers_sid, [m.t for m in switches.marks], [m.label for m in switches.marks])
        outs[markers_sid].wrote([m.t for m in switches.marks])
    for sid, o in outs.items():
        first = o.first if o.count else 0.0
        last = o.last if o.count else 0.0
        writer.stream_footer(sid, footer_xml(first, last, o.count, o.offsets))
    return outs


class _DeviceOffsets:
    """The ClockOffset chunks of a stream on a device's clock: each estimate the recorder kept (clocks.csv), as
    LabRecorder writes a measurement — CollectionTime on the *stream's* clock (LabRecorder writes ``now − offset``;
    pyxdf fits the offsets against it and applies the fit to the stream's time stamps, so a collection time on the
    host's clock would misplace every sample by drift × offset: 0.1 s for 100 ppm and a device clock 1000 s from
    the host's), OffsetValue = host − device, what to add to the stream's time stamps. A window without a new
    estimate gets the one in force at its start, so pyxdf finds one at least every WINDOW_S as LabRecorder writes
    them."""

    def __init__(self, clock: recording.ClockLines) -> None:
        self.clock = clock
        self.next = 0  # the first estimate not written yet

    def until(self, t: float, t_end: float) -> list[tuple[float, float]]:
        c, i = self.clock, self.next
        j = int(np.searchsorted(c.host, t_end, side="left"))
        self.next = max(i, j)
        out = [(float(c.device[k]), float(c.host[k] - c.device[k])) for k in range(i, j)]
        if not out and c.host[0] <= t:  # no new estimate in this window: the one in force, as measured at its start
            device = float(c.to_device(np.array([t]))[0])
            out.append((device, t - device))
        return out


def _verify(path: Path, out: HashingWriter, counts: dict[int, _Out]) -> None:
    """The file on disk is the bytes written (digest), every chunk is well framed, every stream has its header,
    footer and the samples written."""
    digest, size = file_digest(path)
    if digest != out.digest.hexdigest() or size != out.size:
        raise OSError(f"{path.name} reads back different from what was written ({size} of {out.size} bytes)")
    try:
        scan = scan_xdf(path)
    except (ValueError, EOFError) as exc:
        raise OSError(f"{path.name} does not read back as XDF: {exc}") from exc
    for sid, o in counts.items():
        got = scan.streams.get(sid)
        if got is None or not got.header or not got.footer or got.samples != o.count:
            raise OSError(f"{path.name}: stream {o.name} reads back with {got.samples if got else 0} of "
                          f"{o.count} samples")
