"""Where an export reads a session from: a *session source* — a session folder (:class:`FolderSource`), or a session
the clinic's archive holds, streamed from it (:class:`ArchivedSource` over ``app.archive``'s ``SessionFiles``).

An export never loads a whole session: the manifest and the events are small and read at once, the stream files
are read in blocks of whole lines (:meth:`Session.chunks`), so a two-hour session costs what one block costs.
The parsing follows :func:`app.session.recording.load_session` (the same column rules, a last line cut short is dropped
and counted, a line with the wrong number of fields is dropped and counted) and gives the same float64 values.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np

from app.core.bus import Channel
from app.session import recording

BLOCK_BYTES = 4 << 20  # one read of a stream file: ~250 000 values, a few MB of arrays


class SessionSource(Protocol):
    """The files of one recorded session, by their names in the recorder's layout (``manifest.json``,
    ``events.jsonl``, ``streams/<stream>.csv``)."""

    label: str  # for messages: the folder, or the archive's name of the session

    def names(self) -> list[str]: ...

    def size(self, name: str) -> int: ...

    def open(self, name: str) -> IO[bytes]: ...

    def read_bytes(self, name: str) -> bytes: ...


class FolderSource:
    """A session folder on disk (the recorder's own, or one the archive materialised)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.label = str(self.folder)

    def _path(self, name: str) -> Path:
        path = self.folder / name
        # A folder may come from elsewhere: only regular files inside it (as load_session reads them).
        if not path.resolve().is_relative_to(self.folder.resolve()):
            raise ValueError(f"{name!r} is not a file of the session")
        return path

    def names(self) -> list[str]:
        out = [n for n in (recording.MANIFEST_FILE, recording.EVENTS_FILE, recording.CLOCK_FILE)
               if (self.folder / n).is_file()]
        streams_dir = self.folder / recording.STREAMS_DIR
        if streams_dir.is_dir():
            out += [f"{recording.STREAMS_DIR}/{p.name}" for p in sorted(streams_dir.glob("*.csv")) if p.is_file()]
        return out

    def size(self, name: str) -> int:
        return self._path(name).stat().st_size

    def open(self, name: str) -> IO[bytes]:
        path = self._path(name)
        if not path.is_file():
            raise FileNotFoundError(f"{path} is not a regular file")
        return open(path, "rb")

    def read_bytes(self, name: str) -> bytes:
        with self.open(name) as fh:
            return fh.read()


class ArchivedSource:
    """A session the clinic's archive holds, read as it streams from the archive, never copied into a folder first:
    any object with the archive's ``SessionFiles`` calls (``files()`` → entries with ``name``, ``size`` and
    ``sha256``, ``open(name)`` streaming the bytes; app/archive/api.py, issue #39); ``linarmpp export`` names a
    session by its UUID this way (app/research_export/command.py).

    Each file read to its end is checked against its SHA-256 (as ``SessionFiles.materialise`` checks what it writes):
    a copy changed or damaged in the database fails the read of that session, it is never exported as the session.
    What the archive raises while reading (a server gone away) reaches the exporters as an OSError with its sentence,
    as a folder's unreadable file does."""

    def __init__(self, files: Any, label: str = "") -> None:
        self.files = files
        self.label = label or f"archived session {getattr(files, 'uuid', '')}".strip()
        self._sizes: dict[str, int] | None = None
        self._hashes: dict[str, str] = {}

    def _listing(self) -> dict[str, int]:
        if self._sizes is None:
            with _archive_errors():
                entries = list(self.files.files())
            self._hashes = {str(f.name): str(getattr(f, "sha256", "") or "") for f in entries}
            self._sizes = {str(f.name): int(f.size) for f in entries}
        return self._sizes

    def names(self) -> list[str]:
        return sorted(self._listing())

    def size(self, name: str) -> int:
        return self._listing()[name]

    def open(self, name: str) -> IO[bytes]:
        if name not in self._listing():
            raise FileNotFoundError(f"{self.label} has no file {name}")
        with _archive_errors():
            stream = self.files.open(name)
        session = getattr(self.files, "uuid", "") or self.label
        checked = _CheckedReader(stream, f"the archived file {name} of session {session}", self._listing()[name],
                                 self._hashes.get(name, ""))
        return io.BufferedReader(checked)  # (the archive's own reader buffers a chunk)

    def read_bytes(self, name: str) -> bytes:
        with self.open(name) as fh:
            return fh.read()


class _CheckedReader(io.RawIOBase):
    """An archived file's bytes as they stream, hashed on the way: at its end, its size and SHA-256 are the ones the
    archive listed (or an OSError saying which file does not match)."""

    def __init__(self, stream: IO[bytes], what: str, size: int, sha256: str) -> None:
        self._stream = stream
        self._what = what
        self._size = size
        self._sha256 = sha256
        self._digest = hashlib.sha256()
        self._done = 0
        self._checked = False

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        if not len(b):
            return 0
        with _archive_errors():
            data = self._stream.read(len(b))
        n = len(data)
        if n:
            b[:n] = data
            self._digest.update(data)
            self._done += n
        elif not self._checked:
            self._checked = True
            if self._done != self._size or (self._sha256 and self._digest.hexdigest() != self._sha256):
                raise OSError(f"{self._what} does not match its SHA-256 (the archive's copy was changed or damaged: "
                              "run `linarmpp archive verify`)")
        return n

    def close(self) -> None:
        try:
            self._stream.close()
        finally:
            super().close()


@contextlib.contextmanager
def _archive_errors() -> Iterator[None]:
    """What the archive raises (app.archive.api.ArchiveError: unreachable, a file it does not hold) as an OSError with
    the same sentence: every exporter says an unreadable file of a session in one line and goes on with the others."""
    try:
        yield
    except OSError:
        raise
    except Exception as exc:
        from app.archive.api import ArchiveError

        if isinstance(exc, ArchiveError):
            raise OSError(str(exc)) from exc
        raise


def is_session_folder(folder: str | Path) -> bool:
    return (Path(folder) / recording.MANIFEST_FILE).is_file()


@dataclass(frozen=True)
class StreamInfo:
    """One recorded stream as the manifest (or the file's header) describes it."""

    name: str
    device: str
    rate_hz: float  # the nominal rate the session ran it at (manifest), 0 when unknown
    channels: tuple[Channel, ...]
    file: str  # its name in the source
    irregular: bool  # published on change, not at its rate (app.session.lsl.IRREGULAR_STREAMS)
    size: int = 0  # bytes of its file (progress)


@dataclass(frozen=True)
class LineLayout:
    """Where each line of a block of whole lines starts, its commas and its newline (byte offsets), found once with
    numpy for a block whose every line has the stream's number of fields: the fields are cut out of the lines, and
    the text formats rewrite them, without a Python step per line."""

    starts: np.ndarray  # (n,)
    commas: np.ndarray  # (n, fields − 1)
    newline: np.ndarray  # (n,)

    @property
    def first_comma(self) -> np.ndarray:
        return self.commas[:, 0]

    @property
    def last_comma(self) -> np.ndarray:
        return self.commas[:, -1]


@dataclass
class Chunk:
    """Consecutive samples of a stream: ``t`` (n,) monotonic seconds, ``values`` (n, channels) float64."""

    t: np.ndarray
    values: np.ndarray
    nbytes: int  # bytes of the file this chunk consumed (progress)
    raw: bytes | None = None  # the lines as the file holds them (when every line was read), for text formats
    arrival_column: bool = False  # the raw lines end with the t_arrival_s field
    layout: LineLayout | None = None  # of ``raw``, when the times alone were asked for (see Session.chunks)

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class StreamTally:
    """What reading a stream found: its samples and the lines it could not use."""

    samples: int = 0
    dropped_lines: int = 0
    first_t: float | None = None
    last_t: float | None = None


@dataclass
class Session:
    """A session opened for export. ``problems`` lists what is missing or wrong (as load_session says it);
    reading the streams adds to it (lines cut short, fewer samples than the manifest counted)."""

    source: SessionSource
    manifest: dict[str, Any]
    events: list[dict[str, Any]]
    streams: dict[str, StreamInfo]
    problems: list[str] = field(default_factory=list)
    tallies: dict[str, StreamTally] = field(default_factory=dict)
    block_bytes: int = BLOCK_BYTES  # how much of a stream file one read takes (memory per stream read)
    _clocks: dict[str, recording.ClockLines] | None = None

    def device_clocks(self) -> dict[str, recording.ClockLines]:
        """How each device's clock was mapped to the host's while recording (``clocks.csv``, by device; empty for a
        session recorded before it was kept, or by devices without a clock). Small: a line per estimate."""
        if self._clocks is None:
            self._clocks = {}
            if recording.CLOCK_FILE in self.source.names():
                try:
                    self._clocks, dropped = recording.parse_clock_lines(self.source.read_bytes(recording.CLOCK_FILE))
                except OSError as exc:
                    self.problems.append(f"{recording.CLOCK_FILE} cannot be read: {exc}")
                    dropped = 0
                if dropped:
                    self.problems.append(f"{recording.CLOCK_FILE}: {dropped} incomplete line(s) dropped")
        return self._clocks

    @property
    def label(self) -> str:
        return self.source.label

    @property
    def patient_id(self) -> str:
        return str(self.manifest.get("patient_id") or "unknown")

    @property
    def start_mono(self) -> float:
        """The session's time zero (monotonic s): the manifest's start, else the first time stamp found."""
        start = (self.manifest.get("start") or {}).get("t_mono_s")
        if isinstance(start, int | float):
            return float(start)
        firsts = [float(v) for v in (self.manifest.get("first_t_mono_s") or {}).values() if isinstance(v, int | float)]
        firsts += [float(e["t_mono"]) for e in self.events[:1] if isinstance(e.get("t_mono"), int | float)]
        return min(firsts) if firsts else 0.0

    @property
    def start_wall(self) -> float:
        """Epoch seconds of :attr:`start_mono`."""
        start = self.manifest.get("start") or {}
        return float(start.get("t_wall_epoch_s") or 0.0)

    @property
    def start_iso(self) -> str:
        return str((self.manifest.get("start") or {}).get("t_wall") or "")

    @property
    def end_mono(self) -> float:
        """The last moment the session knows of: its stop, else the last event or sample seen."""
        ends = [float(e["t_mono"]) for e in self.events[-1:] if isinstance(e.get("t_mono"), int | float)]
        end = (self.manifest.get("end") or {}).get("t_mono_s")
        if isinstance(end, int | float):
            ends.append(float(end))
        ends += [float(v) for v in (self.manifest.get("last_t_mono_s") or {}).values() if isinstance(v, int | float)]
        ends += [t.last_t for t in self.tallies.values() if t.last_t is not None]
        return max(ends) if ends else self.start_mono

    @property
    def total_bytes(self) -> int:
        return sum(s.size for s in self.streams.values())

    def chunks(self, stream: str, block_bytes: int | None = None, *, raw: bool = False,
               columns: list[int] | None = None) -> Iterator[Chunk]:
        """The stream's samples in file order, a block of whole lines at a time. ``raw``: each chunk also carries
        its lines as the file holds them; ``columns``: only these channels are parsed (indices; [] for the times
        alone). Counts what it reads in :attr:`tallies` (a later full pass replaces the earlier count). While the
        caller holds a chunk the generator keeps nothing but a line cut by the block's end (several streams can be
        read side by side at the cost of their chunks)."""
        info = self.streams[stream]
        tally = StreamTally()
        self.tallies[stream] = tally
        ncols = len(info.channels) + 1
        with self.source.open(info.file) as fh:
            header = fh.readline()
            if not header.endswith(b"\n"):
                return  # no complete header line: nothing to read
            names = header.decode("utf-8", errors="replace").rstrip("\n").split(",")
            keep = len(names) - 1 if names[-1] == recording.ARRIVAL_COLUMN else len(names)
            if keep != ncols:
                raise ValueError(f"{info.file}: {keep} columns where {ncols} were expected")
            wanted = None if columns is None else [0, *(c + 1 for c in columns)]
            rest = b""
            while True:
                block = fh.read(block_bytes or self.block_bytes)
                if not block:
                    break
                data = rest + block
                del block
                cut = data.rfind(b"\n") + 1
                if cut == 0:
                    rest = data
                    continue
                rest = data[cut:]
                lines = data[:cut]
                del data
                # The lines for a text format, with the times alone (BIDS): the lines' layout once, the times cut
                # out of them (the parser never sees the values), the layout kept for rewriting the lines. (For
                # other columns pandas' own column selection costs the same: measured.)
                layout = _line_layout(lines, len(names)) if raw and wanted == [0] else None
                picked = _parse_fields(lines, layout, wanted) if layout is not None and wanted is not None else None
                if picked is not None:
                    values, dropped = picked, 0
                else:
                    layout = None
                    values, dropped = _parse_lines(lines, len(names), wanted)
                tally.dropped_lines += dropped
                use = wanted
                if dropped and raw and wanted is not None:  # no raw text for this block: the caller needs values
                    values, _ = _parse_lines(lines, len(names), None)
                    use = None
                if use is None and keep != len(names):
                    values = values[:, :keep]
                if len(values):
                    tally.samples += len(values)
                    if tally.first_t is None:
                        tally.first_t = float(values[0, 0])
                    tally.last_t = float(values[-1, 0])
                    chunk = Chunk(np.ascontiguousarray(values[:, 0]), np.ascontiguousarray(values[:, 1:]), cut,
                                  lines if raw and not dropped else None, keep != len(names), layout)
                    del values, lines
                    yield chunk
                    del chunk
                else:
                    del lines
            if rest:
                tally.dropped_lines += 1  # a last line without its newline: cut short by a crash

    def read_problems(self) -> list[str]:
        """What reading the streams found (call after every stream was read through)."""
        out: list[str] = []
        for name, tally in self.tallies.items():
            if tally.dropped_lines:
                out.append(f"{name}: {tally.dropped_lines} incomplete line(s) dropped")
        counted = {n: _Len(t.samples) for n, t in self.tallies.items()}
        out += recording._count_problems(self.manifest, counted, self.events)  # type: ignore[arg-type]
        return [p for p in out if p not in self.problems]


@dataclass(frozen=True)
class _Len:
    n: int

    def __len__(self) -> int:
        return self.n


_LINE = re.compile(rb"[^\n]*\n")
COMMA, NEWLINE = ord(","), ord("\n")


def _line_layout(data: bytes, ncols: int) -> LineLayout | None:
    """The layout of whole lines ``data`` when every line has ``ncols`` fields (None otherwise: the caller reads the
    block line by line, as load_session does)."""
    if ncols < 2 or not data:
        return None
    arr = np.frombuffer(data, np.uint8)
    newline = np.flatnonzero(arr == NEWLINE)
    commas = np.flatnonzero(arr == COMMA)
    n = len(newline)
    if len(commas) != n * (ncols - 1):
        return None
    starts = np.empty_like(newline)
    starts[0] = 0
    starts[1:] = newline[:-1] + 1
    table = commas.reshape(n, ncols - 1)  # sorted: line i's commas, if each line holds ncols − 1 of them
    if np.any(table[:, 0] < starts) or np.any(table[:, -1] > newline):
        return None
    return LineLayout(starts, table, newline)


def runs_mask(lengths: np.ndarray, pattern: tuple[bool, ...]) -> np.ndarray:
    """A boolean mask made of runs: ``lengths`` is (n, len(pattern)), row i's runs taking pattern's values in
    turn (numpy's repeat: no step per line)."""
    return np.repeat(np.tile(np.array(pattern, dtype=np.bool_), len(lengths)), lengths.ravel())


def _parse_fields(data: bytes, layout: LineLayout, fields: list[int]) -> np.ndarray | None:
    """The ``fields`` (sorted column indices, 0 the time) of whole lines as float64 [n, len(fields)], parsed as
    load_session parses them: cut out of each line with numpy (the others are never read), so the parser sees
    only what is asked for. None if one cannot be parsed (the caller reads the block line by line)."""
    lay = layout
    n = len(lay.starts)
    if not fields or fields != sorted(set(fields)):
        return None
    if fields[-1] > lay.commas.shape[1]:
        return None
    # each field's first byte and its delimiter (the comma after it, or the newline)
    begins = np.column_stack([lay.starts, lay.commas + 1])
    ends = np.column_stack([lay.commas, lay.newline])
    if np.any(ends[:, fields] == begins[:, fields]):
        return None  # an empty field: line by line
    # runs per line: drop up to the field, keep it and its delimiter, …, drop to the line's end (newline included)
    keep_from = begins[:, fields]
    keep_len = ends[:, fields] - keep_from + 1
    drop_before = keep_from - np.column_stack([lay.starts, ends[:, fields[:-1]] + 1])
    tail = lay.newline + 1 - (ends[:, fields[-1]] + 1)
    runs = np.empty((n, 2 * len(fields) + 1), dtype=np.int64)
    runs[:, 0:-1:2] = drop_before
    runs[:, 1:-1:2] = keep_len
    runs[:, -1] = tail
    arr = np.frombuffer(data, np.uint8).copy()
    arr[ends[:, fields[-1]]] = NEWLINE  # the last field asked for ends its line
    picked = arr[runs_mask(runs, (False, True) * len(fields) + (False,))]
    try:
        values = recording.read_csv_numbers(picked.tobytes(), len(fields), None)
    except ValueError:
        return None
    return values if len(values) == n else None


def _parse_lines(data: bytes, ncols: int, usecols: list[int] | None = None) -> tuple[np.ndarray, int]:
    """Whole lines ``data`` as float64 [n, ncols] (or the ``usecols`` columns); lines with the wrong number of
    fields (or unparsable) are dropped and counted, as load_session does."""
    lines = data.count(b"\n")
    if data.count(b",") == lines * (ncols - 1):
        try:
            values = recording.read_csv_numbers(data, ncols, usecols)
        except ValueError:
            pass  # a garbled value: line by line below
        else:
            if len(values) == lines:  # (pandas skips a blank line: then the count differs, and line by line)
                return values, 0
    good = [ln for ln in _LINE.findall(data) if ln.count(b",") == ncols - 1 and len(ln) > 1]
    rows: list[list[float]] = []
    for ln in good:
        try:
            rows.append([float(x) for x in ln.split(b",")])
        except ValueError:
            continue
    values = np.array(rows, dtype=np.float64).reshape(len(rows), ncols)
    return (values if usecols is None else values[:, usecols]), lines - len(rows)


def _irregular(stream: str) -> bool:
    from app.session.lsl import IRREGULAR_STREAMS

    return stream in IRREGULAR_STREAMS


def open_session(source: SessionSource) -> Session:
    """Read the manifest and the events; describe the streams (no sample is read yet). Raises ValueError with a
    sentence when the source holds no readable manifest."""
    try:
        manifest = json.loads(source.read_bytes(recording.MANIFEST_FILE).decode("utf-8"))
    except FileNotFoundError as exc:
        raise ValueError(f"{source.label} is not a session (no {recording.MANIFEST_FILE})") from exc
    except (OSError, ValueError, RecursionError) as exc:
        raise ValueError(f"the manifest of {source.label} cannot be read: {exc}") from exc
    if not isinstance(manifest, dict):
        raise ValueError(f"the manifest of {source.label} is not a JSON object")
    if isinstance(source, FolderSource):
        manifest = recording._manifest_with_sidecar(source.folder, manifest)
    elif recording.FAILED_FILE in source.names():  # the archive's copy of a failed recording's sidecar
        try:
            failure = recording.failure_of_sidecar(source.read_bytes(recording.FAILED_FILE))
        except OSError as exc:
            failure = {"error": f"(unreadable: {exc})"}
        manifest = recording.manifest_with_failure(manifest, failure)
    problems: list[str] = []
    if problem := recording._status_problem(manifest):
        problems.append(problem)
    names = set(source.names())
    specs: dict[str, Any] = dict(manifest.get("streams") or {})
    known = {v.get("file") for v in specs.values() if isinstance(v, dict)}
    for name in sorted(names):
        if name.startswith(f"{recording.STREAMS_DIR}/") and name not in known:
            specs[Path(name).stem] = {"file": name, "device": "", "nominal_rate_hz": 0.0, "channels": None}
    streams: dict[str, StreamInfo] = {}
    for stream, spec in specs.items():
        if not isinstance(spec, dict) or not isinstance(spec.get("file"), str):
            problems.append(f"{stream}: the manifest names no file")
            continue
        file = spec["file"]
        if file not in names:
            problems.append(f"{stream}: file {file} is missing")
            continue
        channels = _channels(source, file, spec.get("channels"))
        if channels is None:
            problems.append(f"{stream}: file {file} has no header line; not read")
            continue
        if spec.get("channels") is not None and [c.name for c in channels] != [
                c.get("name") for c in spec["channels"] if isinstance(c, dict)]:
            problems.append(f"{stream}: file columns {[c.name for c in channels]} differ from the manifest; "
                            "using the file's")
        streams[stream] = StreamInfo(stream, str(spec.get("device") or stream.partition(".")[0]),
                                     float(spec.get("nominal_rate_hz") or 0.0), channels, file, _irregular(stream),
                                     source.size(file))
    events: list[dict[str, Any]] = []
    if recording.EVENTS_FILE in names:
        events, dropped = _read_events(source)
        if dropped:
            problems.append(f"events: {dropped} incomplete line(s) dropped")
    else:
        problems.append(f"{recording.EVENTS_FILE} is missing")
    events.sort(key=lambda e: float(e["t_mono"]))  # stable: the file's order among equal times
    return Session(source, manifest, events, streams, problems)


def _channels(source: SessionSource, file: str, declared: Any) -> tuple[Channel, ...] | None:
    """The stream's channels: the manifest's when the file's columns agree, else the file's (no units)."""
    with source.open(file) as fh:
        header = fh.readline()
    if not header.endswith(b"\n"):
        return None
    columns = header.decode("utf-8", errors="replace").rstrip("\n").split(",")
    if columns and columns[-1] == recording.ARRIVAL_COLUMN:
        columns = columns[:-1]
    names = columns[1:]
    if isinstance(declared, list):
        channels = tuple(Channel(str(c.get("name")), str(c.get("unit") or ""), str(c.get("label") or c.get("name")))
                         for c in declared if isinstance(c, dict))
        if [c.name for c in channels] == names:
            return channels
    return tuple(Channel(n, "", n) for n in names)


def _read_events(source: SessionSource) -> tuple[list[dict[str, Any]], int]:
    """The events with a numeric time (others are counted as dropped, as a damaged line is)."""
    text = source.read_bytes(recording.EVENTS_FILE).decode("utf-8", errors="replace")
    lines = text.split("\n")
    dropped = 1 if lines.pop() else 0
    out = []
    for ln in lines:
        if not ln.strip():
            continue
        try:
            record = json.loads(ln)
        except (ValueError, RecursionError):
            dropped += 1
            continue
        if isinstance(record, dict) and isinstance(record.get("t_mono"), int | float) and not isinstance(
                record.get("t_mono"), bool) and np.isfinite(record["t_mono"]):
            out.append(record)
        else:
            dropped += 1
    return out, dropped


Progress = Callable[[float, str], object]
