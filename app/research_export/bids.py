"""BIDS (Brain Imaging Data Structure, 1.11): one dataset for many sessions of many patients.

    dataset_description.json  README  CHANGES  participants.tsv/.json  task-therapy_events.json
    sub-<label>/sub-<label>_sessions.tsv/.json
    sub-<label>/ses-<n>/sub-<label>_ses-<n>_scans.tsv
    sub-<label>/ses-<n>/motion/
        …_task-therapy_tracksys-LINarm_acq-<stream>_motion.tsv/.json, …_channels.tsv   the LINarm's streams
        …_task-therapy_recording-<stream>_physio.tsv.gz/.json                         sensors, patient model
        …_task-therapy_recording-<stream>_stim.tsv.gz/.json                           FES, the VR task
        …_task-therapy_events.tsv
    derivatives/linarmpp-metrics/…_desc-repetitions_metrics.tsv/.json                 per-repetition metrics

Times: every time in the dataset is seconds from the session's start (the manifest's start): the LATENCY channel of
each motion file, the ``timestamp`` column of each physio/stim file, the events' onsets, StartTime. Every stream
keeps its own rate and every sample its recorded time (no resampling), except FES: a stim file needs one rate, so
the stimulator's settings, published on change, are held on a grid at its nominal rate, each row also giving the
time of the update in force (so the updates and their exact times are all there).

The dataset is written into a temporary folder beside the target, every file read back (its digest, JSON parsed,
gzip decompressed), then the folder is renamed into place.
"""

from __future__ import annotations

import datetime as _dt
import gzip
import json
import math
import os
import struct
import zlib
from collections.abc import Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from app.core import streams
from app.research_export import channels as kinds
from app.research_export.common import (
    DIR_MODE,
    Cancel,
    ExportError,
    ExportResult,
    Progress,
    Steps,
    open_private,
    remove_quietly,
)
from app.research_export.marks import FesSwitches, Mark, event_marks, exported, record_json
from app.research_export.source import Chunk, LineLayout, Session, StreamInfo, runs_mask

BIDS_VERSION = "1.11.0"
TASK = "therapy"
GZIP_LEVEL = 1  # the physio/stim files: fast (a two-hour session in a few seconds)
# How they are compressed (zlib's strategy). Rows of numbers at their full precision hardly repeat: Huffman coding
# alone makes them smaller than LZ77 at level 1 (45.4 % of the text against 46.7 % for the physio, patient-model and
# VR files of the bench's session) in 60 % of the time. FES held on its grid repeats whole rows: LZ77 (7 % against
# 30 %).
CONTINUOUS_STRATEGY = zlib.Z_HUFFMAN_ONLY
HELD_STRATEGY = zlib.Z_DEFAULT_STRATEGY
GZIP_HEADER = b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x04\xff"  # deflate, no name, mtime 0, fastest, OS unknown
METRICS_PIPELINE = "linarmpp-metrics"
PROFILE_SCORES = ("fugl_meyer_ue", "modified_ashworth", "action_research_arm_test", "box_and_block")


@dataclass
class BidsOptions:
    name: str = "LINarm++ Manager sessions"
    include_names: bool = False  # the patients' full names in participants.tsv (off: pseudonyms only)
    shift_days: int = 0  # every date moved back by this many days (BIDS: de-identification by date shifting)
    metrics: bool = True  # derivatives/linarmpp-metrics


# ---------------------------------------------------------------------------------------------- files
class _Check:
    """What a file's read-back is compared with: the CRC-32 and the length of its text (the check gzip makes of
    its members). It guards against a write that went wrong (a short or damaged file), not against tampering, and
    costs a fifth of a cryptographic digest: BLAKE2b over a two-hour dataset's 600 MB, twice (written, read back),
    was ~2.5 s of its 30 s budget."""

    def __init__(self, data: bytes = b"") -> None:
        self.crc = zlib.crc32(data)
        self.size = len(data)

    def update(self, data: bytes) -> None:
        self.crc = zlib.crc32(data, self.crc)
        self.size += len(data)

    def hexdigest(self) -> str:
        return f"{self.crc:08x}-{self.size}"


class _Digest:
    """Every file of the dataset with the digest of what was written (read back at the end). A stream's file is
    synced to disk on a thread once written (fsync waits for the disk without the interpreter's lock), while the next
    one is made; :meth:`verify` first waits for every sync (and raises what one raised)."""

    def __init__(self) -> None:
        self.files: dict[Path, tuple[str, bool]] = {}
        self._syncer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bids-fsync")
        self._syncs: list[Future[None]] = []

    def sync_and_close(self, fh: IO[bytes]) -> None:
        self._syncs.append(self._syncer.submit(_fsync_and_close, fh))

    def abandon(self) -> None:
        for f in self._syncs:
            f.exception()  # waits; what it raised does not matter now
        self._syncer.shutdown(wait=True)

    def wait_for_syncs(self) -> None:
        try:
            for f in self._syncs:
                f.result()
        finally:
            self._syncer.shutdown(wait=True)

    def write_bytes(self, path: Path, data: bytes) -> None:
        path.parent.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
        with open_private(path) as fh:
            fh.write(data)
        self.files[path] = (_Check(data).hexdigest(), False)

    def write_json(self, path: Path, data: Any) -> None:
        self.write_bytes(path, (json.dumps(data, indent=2, ensure_ascii=False) + "\n").encode("utf-8"))

    def write_tsv(self, path: Path, header: list[str] | None, rows: Iterable[Iterable[Any]]) -> None:
        lines = ["\t".join(header)] if header else []
        lines += ["\t".join(_cell(v) for v in row) for row in rows]
        self.write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))

    def stream(self, path: Path, gz: bool, strategy: int = CONTINUOUS_STRATEGY) -> _StreamOut:
        path.parent.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
        return _StreamOut(self, path, gz, strategy)

    def verify(self, steps: Steps) -> None:
        self.wait_for_syncs()
        for path, (digest, gz) in self.files.items():
            steps.check()
            h = _Check()
            try:
                opener: Any = gzip.open if gz else open
                with opener(path, "rb") as fh:
                    while block := fh.read(1 << 20):
                        h.update(block)
            except (OSError, EOFError) as exc:
                raise OSError(f"{path.name} does not read back: {exc}") from exc
            if h.hexdigest() != digest:
                raise OSError(f"{path.name} reads back different from what was written")
            if path.suffix == ".json":
                json.loads(path.read_text(encoding="utf-8"))


class _StreamOut:
    """A TSV written block by block (for physio/stim a gzip member, written with zlib: its trailer's CRC-32 and
    length are the text's digest, computed once), through a digest of its text."""

    def __init__(self, owner: _Digest, path: Path, gz: bool, strategy: int = CONTINUOUS_STRATEGY) -> None:
        self.owner, self.path, self.gz = owner, path, gz
        self.raw: IO[bytes] = open_private(path)
        self.deflate = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, -zlib.MAX_WBITS, 8, strategy) if gz else None
        if gz:
            self.raw.write(GZIP_HEADER)
        self.hash = _Check()
        self.rows = 0

    def write(self, data: bytes, rows: int) -> None:
        self.hash.update(data)
        self.raw.write(self.deflate.compress(data) if self.deflate is not None else data)
        self.rows += rows

    def close(self) -> None:
        if self.deflate is not None:
            self.raw.write(self.deflate.flush())
            self.raw.write(struct.pack("<II", self.hash.crc, self.hash.size & 0xFFFFFFFF))
        self.raw.flush()
        self.owner.files[self.path] = (self.hash.hexdigest(), self.gz)
        self.owner.sync_and_close(self.raw)


def _fsync_and_close(fh: IO[bytes]) -> None:
    try:
        os.fsync(fh.fileno())
    finally:
        fh.close()


def _cell(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "n/a" if not math.isfinite(value) else repr(value)
    text = str(value)
    return text.replace("\t", " ").replace("\n", " ").replace("\r", " ") if text else "n/a"


# ---------------------------------------------------------------------------------------------- samples as text
def tsv_block(chunk: Chunk, t0: float) -> bytes:
    """A chunk's samples as TSV rows: the time from ``t0`` (s, to the nanosecond), then the values as the session's
    file holds them (Python's shortest repr: they read back to the same doubles); missing values ``n/a``."""
    if chunk.raw is not None and chunk.layout is not None and len(chunk.layout.starts) == len(chunk.t):
        return _tsv_from_layout(chunk.raw, chunk.layout, chunk.t - t0, chunk.arrival_column)
    times = (chunk.t - t0).tolist()
    # to the nanosecond, in one C loop: half the cost of each time's shortest repr, and shorter text; it reads back
    # within 0.5 ns of the recorded time
    seconds = (("%.9f\n" * len(times)) % tuple(times)).encode().split(b"\n")
    seconds.pop()
    if chunk.raw is not None:  # the file's own text: only the time and the arrival column change
        rows = chunk.raw.split(b"\n")
        rows.pop()  # the block ends with a newline
        if chunk.arrival_column:
            middle = [r[r.index(b",") + 1:r.rindex(b",")] for r in rows]
        else:
            middle = [r[r.index(b",") + 1:] for r in rows]
        if len(middle) == len(seconds):
            text = b"\n".join(map(b"\t".join, zip(seconds, middle, strict=True))) + b"\n"
            return text.replace(b",", b"\t").replace(b"nan", b"n/a")
    lines = []
    for s, row in zip(seconds, chunk.values.tolist(), strict=True):
        lines.append(b"\t".join([s, *(repr(v).encode() if math.isfinite(v) else b"n/a" for v in row)]))
    return b"\n".join(lines) + b"\n"


_COMMA_TO_TAB = bytes.maketrans(b",", b"\t")
_NS_DIGITS = 10 ** np.arange(8, -1, -1, dtype=np.int64)  # the nine decimals of a time to the nanosecond
MAX_FIXED_S = 1e9  # times this far from the session's start (never, but) go through Python's formatting


def seconds_text(x: np.ndarray, end: int = ord("\t")) -> tuple[np.ndarray, np.ndarray]:
    """Times ``x`` (s) as text to the nanosecond, each followed by ``end``: the bytes (uint8) and each one's length.
    Built with numpy from the nanosecond count round(x·1e9): the text reads back within 0.5 ns (+ 1e-15 relative,
    the product's rounding) of ``x``, as ``%.9f`` does (the two agree but where x·1e9 falls within a rounding of
    a half nanosecond)."""
    n = len(x)
    if not n or not np.all(np.isfinite(x)) or np.max(np.abs(x)) >= MAX_FIXED_S:
        text = (("%.9f" + chr(end)) * n % tuple(x.tolist())).encode()
        arr = np.frombuffer(text, np.uint8)
        ends = np.flatnonzero(arr == end)
        return arr, np.diff(ends, prepend=-1)
    ns = np.rint(x * 1e9).astype(np.int64)
    negative = ns < 0
    ns = np.abs(ns)
    whole, frac = np.divmod(ns, 1_000_000_000)
    width = len(str(int(whole.max())))
    powers = 10 ** np.arange(width - 1, -1, -1, dtype=np.int64)
    digits = np.count_nonzero(whole[:, None] >= np.maximum(powers[:-1], 1)[None, :], axis=1) + 1 if width > 1 \
        else np.ones(n, dtype=np.int64)
    chars = np.empty((n, width + 12), dtype=np.uint8)  # sign, whole digits, point, nine decimals, end
    chars[:, 0] = ord("-")
    chars[:, 1:width + 1] = (whole[:, None] // powers) % 10 + ord("0")
    chars[:, width + 1] = ord(".")
    chars[:, width + 2:width + 11] = (frac[:, None] // _NS_DIGITS) % 10 + ord("0")
    chars[:, width + 11] = end
    valid = np.ones((n, width + 12), dtype=np.bool_)
    valid[:, 0] = negative
    valid[:, 1:width + 1] = np.arange(width, 0, -1)[None, :] <= digits[:, None]
    return chars[valid], valid.sum(axis=1)


def _tsv_from_layout(raw: bytes, lay: LineLayout, x: np.ndarray, arrival: bool) -> bytes:
    """:func:`tsv_block` with numpy over the whole block: each line's time field replaced by ``x`` (s, to the
    nanosecond), its arrival field dropped, commas made tabs, ``nan`` made ``n/a`` (the same bytes as line by
    line)."""
    # "nan" → "n/a" and commas → tabs on the block as read: the same length, so the layout holds (a time or an
    # arrival field changed with them is dropped below; the times written are numbers)
    arr = np.frombuffer(raw.replace(b"nan", b"n/a").translate(_COMMA_TO_TAB), np.uint8)
    last = lay.last_comma if arrival else lay.newline
    # each line: drop "time,", keep the values, drop ",arrival", keep the newline
    keep = runs_mask(np.column_stack([lay.first_comma - lay.starts + 1, last - lay.first_comma - 1,
                                      lay.newline - last, np.ones_like(last)]), (False, True, False, True))
    times, lengths = seconds_text(x)
    is_time = runs_mask(np.column_stack([lengths, last - lay.first_comma]), (True, False))
    out = np.empty(len(is_time), dtype=np.uint8)
    out[is_time] = times
    out[~is_time] = arr[keep]
    text = out.tobytes()
    return text if np.all(np.isfinite(x)) else text.replace(b"nan", b"n/a")  # a time "nan" (Python's text)


# ---------------------------------------------------------------------------------------------- the dataset
@dataclass
class _Planned:
    session: Session
    subject: str
    ses: str  # "1", "2", …
    start: _dt.datetime  # local wall time of the session's start, dates shifted
    shift_days: int = 0


@dataclass
class _Written:
    scans: list[tuple[str, str]] = field(default_factory=list)  # (path in the session folder, acq_time)
    samples: dict[str, int] = field(default_factory=dict)


def plan(sessions: list[Session], shift_days: int = 0) -> list[_Planned]:
    """Subjects (``sub-`` + the patient's pseudonym in letters and digits) and sessions numbered in time order."""
    labels: dict[str, str] = {}
    taken: set[str] = set()
    for s in sorted(sessions, key=lambda s: s.patient_id):
        pid = s.patient_id
        if pid in labels:
            continue
        base = kinds.bids_label(pid, "unknown")
        label, n = base, 2
        while label in taken:
            label, n = f"{base}{n}", n + 1
        labels[pid] = label
        taken.add(label)
    out: list[_Planned] = []
    by_subject: dict[str, list[Session]] = {}
    for s in sessions:
        by_subject.setdefault(labels[s.patient_id], []).append(s)
    for label, group in sorted(by_subject.items()):
        group.sort(key=lambda s: (_local_start(s), s.label))
        for k, s in enumerate(group, start=1):
            out.append(_Planned(s, label, str(k), _local_start(s) - _dt.timedelta(days=shift_days), shift_days))
    return out


def _local_start(session: Session) -> _dt.datetime:
    try:
        return _dt.datetime.fromisoformat(session.start_iso).replace(tzinfo=None)
    except ValueError:
        return _dt.datetime.fromtimestamp(session.start_wall or 0.0)


def _acq_time(moment: _dt.datetime) -> str:
    return moment.isoformat(timespec="microseconds")


def export_bids(sessions: list[Session], root: str | Path, options: BidsOptions | None = None,
                progress: Progress | None = None, cancel: Cancel | None = None) -> ExportResult:
    """Write one BIDS dataset at ``root`` (which must not exist, or be an empty folder) from ``sessions``."""
    options = options or BidsOptions()
    root = Path(root)
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise ExportError(f"{root} already exists and is not an empty folder: choose a new folder for the dataset")
    tmp = root.with_name(f".{root.name}.part")
    remove_quietly(tmp)
    total = sum(s.total_bytes for s in sessions)
    steps = Steps(progress, cancel, total * (1.6 if options.metrics else 1.1) + 1)
    result = ExportResult()
    planned = plan(sessions, options.shift_days)
    out = _Digest()
    try:
        tmp.mkdir(parents=True, mode=DIR_MODE)
        per_subject: dict[str, list[tuple[_Planned, _Written]]] = {}
        for p in planned:
            written = _write_session(out, tmp, p, steps)
            per_subject.setdefault(p.subject, []).append((p, written))
            result.figures[f"sub-{p.subject}/ses-{p.ses}"] = {"source": p.session.label, "samples": written.samples}
            if options.metrics:
                _write_metrics(out, tmp, p, steps, result)
        _write_top(out, tmp, options, per_subject)
        steps.advance(0, "BIDS: reading back")
        out.verify(steps)
        steps.advance(total * 0.1, "BIDS: read back")
        if root.exists():
            root.rmdir()  # empty (checked above)
        os.replace(tmp, root)
    except BaseException:
        out.abandon()  # the syncs under way end (their files closed) before the folder goes
        remove_quietly(tmp)
        raise
    result.written.append(root)
    return result


def _prefix(p: _Planned) -> str:
    return f"sub-{p.subject}_ses-{p.ses}_task-{TASK}"


def _write_session(out: _Digest, root: Path, p: _Planned, steps: Steps) -> _Written:
    s = p.session
    t0 = s.start_mono
    ses_dir = root / f"sub-{p.subject}" / f"ses-{p.ses}"
    motion = ses_dir / "motion"
    written = _Written()
    switches: FesSwitches | None = None
    acq_time = _acq_time(p.start)
    for info in s.streams.values():
        place = kinds.BIDS_PLACE.get(info.name, "physio")
        label = kinds.acq_label(info.name)
        steps.advance(0, f"BIDS sub-{p.subject} ses-{p.ses}: {info.name}")
        if place == "motion":
            name = f"{_prefix(p)}_tracksys-{kinds.TRACKSYS}_acq-{label}"
            count = _write_motion(out, motion, name, s, info, steps)[0]
            written.scans.append((f"motion/{name}_motion.tsv", acq_time))
        else:
            name = f"{_prefix(p)}_recording-{label}_{place}"
            if info.irregular:
                sw = FesSwitches([c.name for c in info.channels])
                count = _write_held(out, motion, name, s, info, steps, sw)[0]
                switches = sw
            else:
                count = _write_continuous(out, motion, name, s, info, steps)[0]
            written.scans.append((f"motion/{name}.tsv.gz", acq_time))
        written.samples[info.name] = count
    marks = event_marks(s.events, s.end_mono) + (switches.marks if switches else [])
    marks.sort(key=lambda m: m.t)
    rows = [_event_row(m, t0, p.shift_days) for m in marks]
    out.write_tsv(motion / f"{_prefix(p)}_events.tsv", EVENT_COLUMNS, rows)
    out.write_tsv(ses_dir / f"sub-{p.subject}_ses-{p.ses}_scans.tsv", ["filename", "acq_time"], written.scans)
    return written


EVENT_COLUMNS = ["onset", "duration", "trial_type", "value", "who", "origin", "data"]


def _event_row(m: Mark, t0: float, shift_days: int = 0) -> list[Any]:
    record = exported(m.record, shift_days) if m.record else {}
    data = record_json(record["data"]) if "data" in record else None
    return [m.t - t0, m.duration, m.kind, m.value or None, record.get("who") or None, record.get("origin") or None,
            data]


def _stream_rows(out: _Digest, path: Path, gz: bool, s: Session, info: StreamInfo,
                 steps: Steps) -> tuple[int, float, float]:
    """Every sample of ``info``'s stream as TSV rows in ``path`` (times from the session's start), a chunk at a
    time; the rows written and the first and last sample times (nan when the stream is empty)."""
    t0 = s.start_mono
    tsv = out.stream(path, gz=gz)
    first = last = math.nan
    try:
        for chunk in s.chunks(info.name, raw=True, columns=[]):
            tsv.write(tsv_block(chunk, t0), len(chunk))
            if math.isnan(first):
                first = float(chunk.t[0])
            last = float(chunk.t[-1])
            steps.advance(chunk.nbytes)
    finally:
        tsv.close()
    return tsv.rows, first, last


def _write_motion(out: _Digest, folder: Path, name: str, s: Session, info: StreamInfo,
                  steps: Steps) -> tuple[int, float, float]:
    n, first, last = _stream_rows(out, folder / f"{name}_motion.tsv", False, s, info, steps)
    ch_rows = [["latency", "n/a", "LATENCY", "n/a", "s", "time of the sample from the session's start (its recorded "
                "time: the device's clock mapped to the host's)", "n/a"]]
    counts: dict[str, int] = {"LATENCY": 1}
    points: set[str] = set()
    for c in info.channels:
        k = kinds.kind(info.name, c)
        ch_rows.append([c.name, k.component, k.motion_type, k.tracked_point, kinds.bids_unit(c.unit), c.label,
                        info.rate_hz or "n/a"])
        counts[k.motion_type] = counts.get(k.motion_type, 0) + 1
        if k.tracked_point != "n/a":
            points.add(k.tracked_point)
    out.write_tsv(folder / f"{name}_channels.tsv", ["name", "component", "type", "tracked_point", "units",
                                                   "description", "sampling_frequency"], ch_rows)
    effective = (n - 1) / (last - first) if n > 1 and last > first else "n/a"
    sidecar: dict[str, Any] = {
        "TaskName": TASK,
        "TaskDescription": "Upper-limb rehabilitation with the LINarm2 robot (exercise runs of the session)",
        "SamplingFrequency": info.rate_hz or 0,
        "SamplingFrequencyEffective": effective,
        "TrackingSystemName": f"LINarm2 robot, {info.name}",
        "Manufacturer": "LINarm++",
        "ManufacturersModelName": "LINarm2",
        "SoftwareVersions": _software(s, info.device),
        "Instructions": "the exercise's cues to the patient are the events with trial_type prompt",
        "SubjectArtefactDescription": "n/a",
        "MotionChannelCount": len(info.channels) + 1,
        "LATENCYChannelCount": 1,
        **{f"{kind}ChannelCount": 0 for kind in ("ACCEL", "ANGACCEL", "GYRO", "JNTANG", "MAGN", "ORNT")},
        "POSChannelCount": counts.get("POS", 0),
        "VELChannelCount": counts.get("VEL", 0),
        "MiscChannelCount": counts.get("MISC", 0),
        "TrackedPointsCount": len(points),
        "MissingValues": "n/a",
        "RecordingDuration": (last - first) if n > 1 else 0,
        "RecordingType": "continuous",
    }
    out.write_json(folder / f"{name}_motion.json", sidecar)
    return n, first, last


def _software(s: Session, device: str) -> str:
    dev = (s.manifest.get("devices") or {}).get(device) or {}
    firmware = dev.get("firmware_version") if isinstance(dev, dict) else None
    app = f"LINarm++ Manager {s.manifest.get('app_version', '')}".strip()
    return f"{app}; firmware {firmware}" if firmware else app


def _columns_sidecar(info: StreamInfo, timestamp_text: str) -> dict[str, Any]:
    cols: dict[str, Any] = {"timestamp": {"Description": timestamp_text, "Units": "s"}}
    for c in info.channels:
        entry = {"Description": c.label}
        if c.unit:
            entry["Units"] = kinds.bids_unit(c.unit)
        cols[c.name] = entry
    return cols


def _write_continuous(out: _Digest, folder: Path, name: str, s: Session, info: StreamInfo,
                      steps: Steps) -> tuple[int, float, float]:
    t0 = s.start_mono
    rows, first, last = _stream_rows(out, folder / f"{name}.tsv.gz", True, s, info, steps)
    sidecar = {
        "TaskName": TASK,
        "SamplingFrequency": info.rate_hz or 0,
        "StartTime": (first - t0) if rows else 0,
        "Columns": ["timestamp", *(c.name for c in info.channels)],
        "Description": f"{info.name} as recorded: one row per sample at its own time (column timestamp, seconds "
                       f"from the session's start); nominal rate {info.rate_hz:g} Hz, not resampled.",
        **({"PhysioType": "generic"} if name.endswith("_physio") else {}),
        "SoftwareVersions": _software(s, info.device),
        **_columns_sidecar(info, "time the sample was taken, in seconds from the session's start (the device's "
                                 "clock mapped to the host's)"),
    }
    out.write_json(folder / f"{name}.json", sidecar)
    return rows, first, last


def _cells(row: tuple[float, ...]) -> bytes:
    return b"\t".join(repr(v).encode() if math.isfinite(v) else b"n/a" for v in row)


def _write_held(out: _Digest, folder: Path, name: str, s: Session, info: StreamInfo, steps: Steps,
                switches: FesSwitches) -> tuple[int, float, float]:
    """A stream published on change (FES) on a regular grid at its nominal rate: each row holds the update in force
    (its values and, in ``timestamp``, its time), from the first update to the last."""
    t0 = s.start_mono
    rate = info.rate_hz if info.rate_hz > 0 else 10.0
    tsv = out.stream(folder / f"{name}.tsv.gz", gz=True, strategy=HELD_STRATEGY)
    grid0: float | None = None
    k = 0  # the next grid row
    prev_t: float | None = None
    prev_text = b""
    updates = 0
    first = last = math.nan
    settings: dict[tuple[float, ...], bytes] = {}  # a setting's text, written once (the same few settings recur)
    try:
        for chunk in s.chunks(info.name):
            switches.feed(chunk.t, chunk.values)
            texts = [repr(t - t0).encode() + b"\t" + (settings.get(row) or settings.setdefault(row, _cells(row)))
                     for t, row in zip(chunk.t.tolist(), map(tuple, chunk.values.tolist()), strict=True)]
            if grid0 is None:
                grid0 = float(chunk.t[0])
                first = grid0
            last = float(chunk.t[-1])
            updates += len(chunk)
            # grid rows up to (not including) this chunk's last update; that one waits for what follows it
            end = math.floor((last - grid0) * rate + 1e-9)
            rows = []
            if k < end:
                grid_t = grid0 + np.arange(k, end) / rate
                j = np.searchsorted(chunk.t, grid_t, side="right") - 1
                for kk, jj in zip(range(k, end), j.tolist(), strict=True):
                    held = texts[jj] if jj >= 0 else prev_text
                    rows.append(repr(grid0 + kk / rate - t0).encode() + b"\t" + held)
                k = end
            if rows:
                tsv.write(b"\n".join(rows) + b"\n", len(rows))
            prev_t, prev_text = last, texts[-1]
            steps.advance(chunk.nbytes)
        if grid0 is not None and prev_t is not None:
            end = math.floor((prev_t - grid0) * rate + 1e-9) + 1
            rows = [repr(grid0 + kk / rate - t0).encode() + b"\t" + prev_text for kk in range(k, end)]
            if rows:
                tsv.write(b"\n".join(rows) + b"\n", len(rows))
    finally:
        tsv.close()
    sidecar = {
        "TaskName": TASK,
        "SamplingFrequency": rate,
        "StartTime": (first - t0) if rows else 0,
        "Columns": ["time", "timestamp", *(c.name for c in info.channels)],
        "Description": f"{info.name}: the stimulator's settings, published when they change (not at a fixed rate), "
                       f"held on a grid at {rate:g} Hz from the first update to the last (sample-and-hold: each row "
                       "is the update in force at its time). Column timestamp gives that update's own time, so "
                       f"every update and its exact time are here ({updates} updates).",
        "SoftwareVersions": _software(s, info.device),
        "time": {"Description": "time of the grid row, in seconds from the session's start", "Units": "s"},
        **_columns_sidecar(info, "time of the update in force at this row, in seconds from the session's start"),
    }
    out.write_json(folder / f"{name}.json", sidecar)
    return updates, first, last


# ---------------------------------------------------------------------------------------------- top level
def _write_top(out: _Digest, root: Path, options: BidsOptions,
               per_subject: dict[str, list[tuple[_Planned, _Written]]]) -> None:
    from app.session.recording import app_version

    out.write_json(root / "dataset_description.json", {
        "Name": options.name, "BIDSVersion": BIDS_VERSION, "DatasetType": "raw",
        "GeneratedBy": [{"Name": "LINarm++ Manager", "Version": app_version(),
                         "Description": "research export (linarmpp export --format bids)"}],
        "HowToAcknowledge": "Cite the LINarm++ project.",
    })
    out.write_bytes(root / "README", README.encode("utf-8"))
    out.write_bytes(root / "CHANGES", f"1.0.0 {_dt.date.today().isoformat()}\n  - exported by LINarm++ Manager "
                                      f"{app_version()}\n".encode())
    participants = []
    for label, entries in sorted(per_subject.items()):
        first = entries[0][0]
        profile = first.session.manifest.get("patient") if isinstance(first.session.manifest.get("patient"),
                                                                      dict) else {}
        scores = profile.get("scores") if isinstance(profile.get("scores"), dict) else {}
        row: list[Any] = [f"sub-{label}", first.session.patient_id, _age(profile, first), "n/a", "n/a",
                          profile.get("affected_side") or None]
        row += [scores.get(k) for k in PROFILE_SCORES]
        if options.include_names:
            row.append(profile.get("full_name") or None)
        participants.append(row)
        _write_sessions_tsv(out, root, label, entries)
    header = ["participant_id", "pseudonym", "age", "sex", "handedness", "affected_side", *PROFILE_SCORES]
    if options.include_names:
        header.append("full_name")
    out.write_tsv(root / "participants.tsv", header, participants)
    out.write_json(root / "participants.json", PARTICIPANTS_JSON | ({"full_name": {
        "Description": "the patient's full name (exported with --include-names)"}} if options.include_names else {}))
    out.write_json(root / f"task-{TASK}_events.json", EVENTS_JSON)


def _age(profile: dict[str, Any], p: _Planned) -> Any:
    birth = profile.get("birth_date")
    if not birth:
        return None
    try:
        born = _dt.date.fromisoformat(str(birth))
    except ValueError:
        return None
    at = _local_start(p.session).date()
    years = at.year - born.year - ((at.month, at.day) < (born.month, born.day))
    return min(years, 89)  # BIDS: ages above 89 are given as 89 (de-identification)


def _write_sessions_tsv(out: _Digest, root: Path, label: str, entries: list[tuple[_Planned, _Written]]) -> None:
    rows = []
    for p, _ in entries:
        s = p.session
        rows.append([f"ses-{p.ses}", _acq_time(p.start), s.end_mono - s.start_mono, s.manifest.get("status")])
    out.write_tsv(root / f"sub-{label}" / f"sub-{label}_sessions.tsv", ["session_id", "acq_time", "duration",
                                                                        "recording_status"], rows)
    out.write_json(root / f"sub-{label}" / f"sub-{label}_sessions.json", {
        "acq_time": {"Description": "the session's start (local time of the station; shifted when the export "
                                    "shifts dates)"},
        "duration": {"Description": "from the session's start to its end", "Units": "s"},
        "recording_status": {"Description": "how the recording ended",
                             "Levels": {"complete": "stopped normally", "failed": "a write error stopped it",
                                        "recording": "never stopped (a crash); data end at the last flush"}}})


PARTICIPANTS_JSON: dict[str, Any] = {
    "participant_id": {"Description": "sub- and the patient's pseudonym in letters and digits"},
    "pseudonym": {"Description": "the patient's identifier in LINarm++ Manager (a pseudonym)"},
    "age": {"Description": "age at the first exported session", "Units": "year"},
    "sex": {"Description": "not recorded by LINarm++ Manager"},
    "handedness": {"Description": "not recorded by LINarm++ Manager"},
    "affected_side": {"Description": "the affected upper limb",
                      "Levels": {"left": "left", "right": "right", "both": "both", "unknown": "unknown"}},
    "fugl_meyer_ue": {"Description": "Fugl-Meyer Assessment, upper extremity (0-66)"},
    "modified_ashworth": {"Description": "Modified Ashworth Scale (0-4)"},
    "action_research_arm_test": {"Description": "Action Research Arm Test (0-57)"},
    "box_and_block": {"Description": "Box and Block Test", "Units": "blocks/min"},
}

EVENTS_JSON: dict[str, Any] = {
    "onset": {"Description": "seconds from the session's start", "Units": "s"},
    "duration": {"Description": "0 for an instant; a repetition, an exercise run or a device's data gap lasts "
                                "from its start to its end", "Units": "s"},
    "trial_type": {"Description": "the recorded event's kind (events.jsonl: session_start, run_start, prompt, "
                                  "alarm, emergency_stop, command, …), or one made from them: repetition (from "
                                  "repetition_start to repetition_end), run (run_start to run_end), device_gap "
                                  "(gap_start to gap_end), fes_on / fes_off (an FES channel's current rose above or "
                                  "fell to 0 mA)"},
    "value": {"Description": "what the event is about: the repetition's index, the prompt's cue, the alarm's level "
                             "and text, the run's title, the FES channel"},
    "who": {"Description": "who or what caused the event (operator, exercise, device, safety)"},
    "origin": {"Description": "the part of the application that recorded it (app, safety, device, recorder)"},
    "data": {"Description": "the event's data as recorded (JSON)"},
}

README = """LINarm++ Manager sessions (BIDS)

Upper-limb rehabilitation sessions with the LINarm2 robot, its physiological sensors, functional electrical
stimulation (FES), a patient model and a VR task, exported by LINarm++ Manager (linarmpp export --format bids).

Layout: motion/ holds, per session, the LINarm's streams (tracksys-LINarm; acq- names the stream: vsa = the
variable-stiffness actuator's kinematics and interaction force, motor0/motor1, state), the sensors and the patient
model as physio, FES and the VR task as stim, and the events. Every time is in seconds from the session's start;
each stream keeps its own rate and each sample its recorded time (LATENCY channel / timestamp column). FES
settings, published on change, are held on a grid at the stimulator's nominal rate (see its JSON).

derivatives/linarmpp-metrics holds the per-repetition metrics (definitions: the application's docs/metrics.md).
Patients appear by pseudonym only unless the export was asked for names.
"""


# ---------------------------------------------------------------------------------------------- derivatives
METRIC_UNITS = {"s": "s", "m": "m", "m/s": "m/s", "N": "N", "bpm": "bpm", "µS": "uS", "": "n/a"}


RUN_BOUNDARIES = frozenset({"run_start", "run_end", "script_start", "script_stop"})
WINDOW_MARGIN_S = 1.0  # data kept either side of a run (a movement's onset just before its start)


def _write_metrics(out: _Digest, root: Path, p: _Planned, steps: Steps, result: ExportResult) -> None:
    """Per-repetition metrics (app.session.metrics), one exercise run at a time: a run's data are read, its metrics
    computed, then the next run's — memory holds one run, not the session."""
    from app.session.metrics import SUMMARY_METRICS, _runs_of, metrics_by_run
    from app.session.recording import RecordedSession

    s = p.session
    steps.advance(0, f"BIDS sub-{p.subject} ses-{p.ses}: metrics")
    runs = _runs_of(RecordedSession(Path(s.label), s.manifest, {}, s.events))
    windows = _RunWindows(s, steps)
    reps: list[dict[str, Any]] = []
    summaries: dict[str, Any] = {}
    for run in runs:
        lo = run.started_mono - WINDOW_MARGIN_S
        hi = (run.ended_mono if run.ended_mono is not None else s.end_mono) + WINDOW_MARGIN_S
        events = [e for e in s.events if e.get("kind") not in RUN_BOUNDARIES
                  or run.started_mono - 1e-6 <= float(e["t_mono"]) <= hi - WINDOW_MARGIN_S + 1e-6]
        light = RecordedSession(Path(s.label), s.manifest, windows.take(lo, hi), events, list(s.problems))
        try:
            found = [r for r in metrics_by_run(light) if r.run.run_id == run.run_id]
        except Exception as exc:  # a run the metrics cannot read: the others still, and said
            result.notes.append(f"{s.label}: no metrics for run {run.run_id} ({type(exc).__name__}: {exc})")
            continue
        for r in found:
            reps += r.repetitions
            summaries[run.run_id] = r.summary
        del light
    windows.finish()
    deriv = root / "derivatives" / METRICS_PIPELINE
    if not (deriv / "dataset_description.json").exists():
        from app.session.recording import app_version

        out.write_json(deriv / "dataset_description.json", {
            "Name": "LINarm++ per-repetition metrics", "BIDSVersion": BIDS_VERSION, "DatasetType": "derivative",
            "GeneratedBy": [{"Name": "LINarm++ Manager metrics", "Version": app_version(),
                             "Description": "app.session.metrics (docs/metrics.md)"}]})
    columns = ["run_id", "index", "start_s", "end_s", "duration_s", "completed", "source",
               *[k for k in SUMMARY_METRICS if k != "duration_s"], "prompt_s", "movement_onset_s", "movement_end_s"]
    rows = [[r.get(c) for c in columns] for r in reps]
    folder = deriv / f"sub-{p.subject}" / f"ses-{p.ses}" / "motion"
    name = f"{_prefix(p)}_desc-repetitions_metrics"
    out.write_tsv(folder / f"{name}.tsv", columns, rows)
    described = {c: {"Description": SUMMARY_METRICS[c][1], "Units": METRIC_UNITS.get(SUMMARY_METRICS[c][0],
                                                                                     SUMMARY_METRICS[c][0])}
                 for c in columns if c in SUMMARY_METRICS}
    described.update({
        "run_id": {"Description": "the exercise run (events: trial_type run)"},
        "index": {"Description": "the repetition's number within its run"},
        "start_s": {"Description": "start, seconds from the session's start", "Units": "s"},
        "end_s": {"Description": "end, seconds from the session's start", "Units": "s"},
        "completed": {"Description": "the repetition was completed (docs/metrics.md)"},
        "source": {"Description": "marks: the exercise marked it; speed: segmented from the handle's speed"},
        "prompt_s": {"Description": "the prompt, seconds from the session's start", "Units": "s"},
        "movement_onset_s": {"Description": "the movement's onset, seconds from the session's start", "Units": "s"},
        "movement_end_s": {"Description": "the movement's end, seconds from the session's start", "Units": "s"},
    })
    out.write_json(folder / f"{name}.json", {"Description": "per-repetition metrics (LINarm++ Manager, "
                                                            "docs/metrics.md)", **described})
    out.write_json(folder / f"{_prefix(p)}_desc-summary_metrics.json", {"runs": summaries})


# What the metrics read (app.session.metrics.signals_from_session), stream -> channels (None: all of them).
METRIC_CHANNELS: dict[str, tuple[str, ...] | None] = {
    streams.LINARM_STATE: ("controlState",),  # homing (app.session.metrics.homing_intervals)
    streams.LINARM_VSA: ("handlePos", "interactionForce"),
    streams.PHYSIO_MAIN: ("force", "heartRate", "skinConductance"),
    streams.PATIENT_MODEL_MAIN: ("alpha", "a_r", "a_f"),
    streams.FES_CHANNELS: None,
}


class _RunWindows:
    """The streams the metrics read, in windows of time taken in order (one pass over each file)."""

    def __init__(self, s: Session, steps: Steps) -> None:
        from app.session.recording import RecordedStream

        self._stream_type = RecordedStream
        self.steps = steps
        self.readers: dict[str, Any] = {}
        for name, wanted in METRIC_CHANNELS.items():
            info = s.streams.get(name)
            if info is None:
                continue
            cols = [i for i, c in enumerate(info.channels) if wanted is None or c.name in wanted]
            chans = tuple(info.channels[i] for i in cols)
            self.readers[name] = [info, chans, s.chunks(name, columns=cols), np.zeros(0), np.zeros((0, len(cols))),
                                  False]

    def take(self, lo: float, hi: float) -> dict[str, Any]:
        out = {}
        for name, entry in self.readers.items():
            info, chans, chunks, t, v, done = entry
            keep = t >= lo
            t, v = t[keep], v[keep]
            parts_t, parts_v = [t], [v]
            while not done and (not len(parts_t[-1]) or parts_t[-1][-1] <= hi):
                try:
                    chunk = next(chunks)
                except StopIteration:
                    done = True
                    break
                self.steps.advance(chunk.nbytes * 0.5)
                keep = chunk.t >= lo
                parts_t.append(chunk.t[keep])
                parts_v.append(chunk.values[keep])
            t = np.concatenate(parts_t)
            v = np.concatenate(parts_v)
            entry[3], entry[4], entry[5] = t, v, done
            inside = t <= hi
            wt, wv = t[inside], v[inside]
            out[name] = self._stream_type(name, chans, info.rate_hz, wt,
                                          {c.name: np.ascontiguousarray(wv[:, k]) for k, c in enumerate(chans)},
                                          device=info.device)
        return out

    def finish(self) -> None:
        """Read what is left (the streams' tallies count every line) and let go of it."""
        for entry in self.readers.values():
            for chunk in entry[2]:
                self.steps.advance(chunk.nbytes * 0.5)
            entry[3] = entry[4] = None
