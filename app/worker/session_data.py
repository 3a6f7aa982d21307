"""A loaded session handed from the worker process to the window without copying its samples (issue #37).

The worker reads the session (app.session.recording.load_session) and returns a :class:`SessionData`: the manifest, the
events, the problems and, for each stream, a column file -- the session's own columnar side-file when it matches
the stream, otherwise a private temporary the worker wrote. :meth:`SessionData.open` maps those files (read-only,
``numpy.load(mmap_mode="r")``): a 30-minute session's 115 MB of samples cost the window's interpreter a few
milliseconds, not the seconds of pickling them across.

:class:`SessionOverview` is the same without samples: what the session details show.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.core.bus import Channel
from app.session.recording import (
    STREAMS_DIR,
    RecordedSession,
    RecordedStream,
    columns_path,
    stream_file_name,
)


@dataclass
class StreamColumns:
    """One stream's shape, and the file holding its columns [t, channels..., (arrival)]."""

    name: str
    channels: tuple[Channel, ...]
    nominal_rate_hz: float
    device: str
    dropped_lines: int
    path: str
    has_arrival: bool
    temporary: bool  # a file the worker wrote for this hand-over: removed once mapped


@dataclass
class SessionData:
    folder: Path
    manifest: dict[str, Any]
    events: list[dict[str, Any]]
    problems: list[str]
    streams: list[StreamColumns] = field(default_factory=list)

    def open(self) -> RecordedSession:
        """The session, its samples mapped from the column files (read-only arrays); the temporaries are removed
        once mapped (the mapping keeps them readable until the arrays are gone)."""
        streams: dict[str, RecordedStream] = {}
        try:
            for s in self.streams:
                table = np.load(s.path, mmap_mode="r", allow_pickle=False)
                rows = 1 + len(s.channels) + (1 if s.has_arrival else 0)
                if table.ndim != 2 or table.shape[0] != rows:
                    raise ValueError(f"{s.path}: {table.shape} is not {rows} columns")
                streams[s.name] = RecordedStream(
                    s.name, s.channels, s.nominal_rate_hz, table[0],
                    {c.name: table[i + 1] for i, c in enumerate(s.channels)}, device=s.device,
                    dropped_lines=s.dropped_lines, arrival=table[-1] if s.has_arrival else None)
        finally:
            self.discard()
        return RecordedSession(self.folder, self.manifest, streams, self.events, list(self.problems))

    def discard(self) -> None:
        """Remove the temporaries (after mapping them, or when the session is not shown after all)."""
        folders = set()
        for s in self.streams:
            if s.temporary:
                folders.add(Path(s.path).parent)
                try:
                    os.unlink(s.path)
                except OSError:
                    pass
        for folder in folders:
            try:
                folder.rmdir()
            except OSError:
                pass


@dataclass
class SessionOverview:
    """A session without its samples: the manifest, the events, the problems, each stream's sample count."""

    folder: Path
    manifest: dict[str, Any]
    events: list[dict[str, Any]]
    problems: list[str]
    samples: dict[str, int]
    duration_s: float


def overview_of(session: RecordedSession) -> SessionOverview:
    return SessionOverview(session.folder, session.manifest, session.events, list(session.problems),
                           {name: len(s) for name, s in session.streams.items()}, session.duration_s)


def _private_temp_dir() -> Path:
    """RAM-backed where there is one (/dev/shm), private to the user (0700)."""
    shm = Path("/dev/shm")
    base = str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None
    return Path(tempfile.mkdtemp(prefix="linarmpp-session-", dir=base))


def session_data(session: RecordedSession) -> SessionData:
    """(Worker side.) The hand-over of ``session``: each stream's columnar side-file when it holds exactly what was
    loaded, else a temporary column file."""
    out = SessionData(session.folder, session.manifest, session.events, list(session.problems))
    temp: Path | None = None
    try:
        for name, stream in session.streams.items():
            has_arrival = stream.arrival is not None
            rel = f"{STREAMS_DIR}/{stream_file_name(name)}"
            side = columns_path(session.folder, rel) if (session.folder / rel).is_file() else None
            usable = False
            if side is not None:
                table = np.load(side, mmap_mode="r", allow_pickle=False)
                header_rows = 1 + len(stream.channels) + (1 if has_arrival else 0)
                usable = table.shape == (header_rows, len(stream)) and (
                    not len(stream) or np.array_equal(np.asarray(table[0, [0, -1]]), stream.t[[0, -1]]))
            if usable and side is not None:
                path, temporary = str(side), False
            else:
                if temp is None:
                    temp = _private_temp_dir()
                rows = [stream.t, *(stream.data[c.name] for c in stream.channels)]
                if has_arrival:
                    rows.append(stream.arrival)  # type: ignore[arg-type]
                path, temporary = str(temp / f"{len(out.streams)}.npy"), True
                with open(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb") as fh:
                    np.save(fh, np.vstack(rows) if rows[0].size else np.zeros((len(rows), 0)), allow_pickle=False)
            out.streams.append(StreamColumns(name, stream.channels, stream.nominal_rate_hz, stream.device,
                                             stream.dropped_lines, path, has_arrival, temporary))
    except BaseException:
        out.discard()
        raise
    return out
