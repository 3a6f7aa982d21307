"""Export a recorded session to one HDF5 file or to CSV files; the graphs' Save uses the same writer.

Values round-trip exactly: HDF5 stores float64 as is, CSV writes Python's shortest exact repr.

HDF5 layout (h5py)::

    /                       attrs: format="linarmpp-session", format_version, manifest (JSON text)
    /streams/<stream>/      attrs: device, nominal_rate_hz, channels (names in order)
        t_mono_s            float64 [n], seconds of time.monotonic() (manifest.start anchors wall time)
        <channel>           float64 [n], attrs: unit, label
    /events/json            variable-length UTF-8 strings, one JSON object per event (as events.jsonl)
    /events/t_mono_s        float64 [n]

CSV export: ``<stream>.csv`` per stream with a header of names and units (``heartRate [bpm]``),
``events.csv`` and a copy of ``manifest.json``.

Long exports report ``progress(fraction) -> bool``; returning False cancels and removes what was written.

Both are written only when right (issue #37, app/core/outputs.py): under a temporary name beside the destination, read
back and compared with the session, then renamed into place; a full disk or a read-only folder is one sentence
(:class:`app.core.outputs.OutputError`) and leaves nothing behind.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from app.core.bus import Channel
from app.core.outputs import NotRight, OutputError, write_verified
from app.session.recording import RecordedSession, RecordedStream, safe_name, write_json_atomic

FORMAT = "linarmpp-session"
FORMAT_VERSION = 1
Progress = Callable[[float], bool]


class ExportCancelled(Exception):
    pass


def _report(progress: Progress | None, fraction: float) -> None:
    if progress is not None and progress(min(1.0, max(0.0, fraction))) is False:
        raise ExportCancelled("export cancelled")


# ---------------------------------------------------------------------------------------------- HDF5
def export_hdf5(session: RecordedSession, path: str | Path, progress: Progress | None = None) -> Path:
    """Write the whole session to one HDF5 file, verified (app/core/outputs.py): written under a temporary name,
    reopened
    and compared with the session, then renamed into place. Raises :class:`app.core.outputs.OutputError` (one sentence,
    nothing at ``path``) when it cannot be written, ExportCancelled when ``progress`` says stop.

    A full disk can make HDF5 itself crash the process (SIGSEGV, issue #37): the window and the command line run
    exports in the worker process (app/worker), where that is a failed task."""
    path = Path(path)
    write_verified(path, lambda tmp: _write_hdf5(session, tmp, progress),
                   lambda tmp, _result: verify_hdf5(session, tmp), what="the HDF5 export")
    if progress is not None:
        progress(1.0)  # written and verified (too late to cancel: the file is in place)
    return path


def _write_hdf5(session: RecordedSession, tmp: Path, progress: Progress | None) -> Path:
    import h5py

    total = max(1, sum(len(s) for s in session.streams.values()))
    done = 0
    with h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = FORMAT
        h5.attrs["format_version"] = FORMAT_VERSION
        h5.attrs["manifest"] = json.dumps(session.manifest, ensure_ascii=False, default=str)
        streams = h5.create_group("streams")
        for name, stream in session.streams.items():
            _report(progress, 0.9 * done / total)
            g = streams.create_group(name.replace("/", "_"))
            g.attrs["stream"] = name
            g.attrs["device"] = stream.device
            g.attrs["nominal_rate_hz"] = stream.nominal_rate_hz
            g.attrs["channels"] = [c.name for c in stream.channels]
            g.create_dataset("t_mono_s", data=np.asarray(stream.t, dtype=np.float64), compression="gzip",
                             shuffle=True)
            for ch in stream.channels:
                ds = g.create_dataset(ch.name, data=np.asarray(stream.data[ch.name], dtype=np.float64),
                                      compression="gzip", shuffle=True)
                ds.attrs["unit"] = ch.unit
                ds.attrs["label"] = ch.label
            done += len(stream)
        ev = h5.create_group("events")
        text = [json.dumps(e, ensure_ascii=False, default=str) for e in session.events]
        ev.create_dataset("json", data=np.array(text, dtype=object), dtype=h5py.string_dtype("utf-8"))
        ev.create_dataset("t_mono_s", data=np.array([float(e.get("t_mono", np.nan)) for e in session.events],
                                                    dtype=np.float64))
    _report(progress, 0.9)
    return tmp


def verify_hdf5(session: RecordedSession, path: Path) -> None:
    """The HDF5 file at ``path`` reopens and holds every stream's every value and every event (raises NotRight)."""
    try:
        back = load_hdf5(path)
    except Exception as exc:  # h5py raises OSError, KeyError, ValueError for a damaged file
        raise NotRight(f"the file does not reopen as a session export ({type(exc).__name__}: {exc})") from exc
    if set(back.streams) != set(session.streams):
        raise NotRight(f"it holds the streams {sorted(back.streams)}, not {sorted(session.streams)}")
    for name, stream in session.streams.items():
        other = back.streams[name]
        if not np.array_equal(other.t, stream.t, equal_nan=True) or any(
                not np.array_equal(other.data.get(c.name), stream.data[c.name], equal_nan=True)
                for c in stream.channels):
            raise NotRight(f"the stream {name} read back differs from the session")
    if len(back.events) != len(session.events):
        raise NotRight(f"it holds {len(back.events)} events, not {len(session.events)}")


def load_hdf5(path: str | Path) -> RecordedSession:
    """Read an exported HDF5 file back into a RecordedSession."""
    import h5py

    path = Path(path)
    with h5py.File(path, "r") as h5:
        if h5.attrs.get("format") != FORMAT:
            raise ValueError(f"{path} is not a LINarm++ session export")
        manifest = json.loads(h5.attrs["manifest"])
        streams: dict[str, RecordedStream] = {}
        for g in h5["streams"].values():
            names = [str(n) for n in g.attrs["channels"]]
            channels = tuple(Channel(n, str(g[n].attrs["unit"]), str(g[n].attrs["label"])) for n in names)
            name = str(g.attrs["stream"])
            streams[name] = RecordedStream(name, channels, float(g.attrs["nominal_rate_hz"]), g["t_mono_s"][()],
                                           {n: g[n][()] for n in names}, device=str(g.attrs["device"]))
        events = [json.loads(s) for s in h5["events/json"].asstr()[()]]
    return RecordedSession(path, manifest, streams, events)


# ---------------------------------------------------------------------------------------------- CSV
EXPORT_FILES = ("events.csv", "manifest.json")  # besides one <stream>.csv per stream


def export_csv(session: RecordedSession, folder: str | Path, progress: Progress | None = None) -> list[Path]:
    """One CSV per stream (header of names and units), events.csv and manifest.json in ``folder``, verified (every
    file there with every row) in a temporary folder beside it and then renamed into place: a failure leaves no
    partial folder. An existing ``folder`` is replaced only when it is empty or an earlier export of this kind."""
    folder = Path(folder)
    if folder.exists() and not _replaceable(folder):
        raise OutputError(f"The CSV export {folder} was not written: that folder exists and holds other files; "
                          "choose a new folder.")
    names = write_verified(folder, lambda tmp: _write_csv(session, tmp, progress),
                           lambda tmp, _names: verify_csv(session, tmp), what="the CSV export", replace_folder=True)
    if progress is not None:
        progress(1.0)
    return [folder / n for n in names]


def _replaceable(folder: Path) -> bool:
    if not folder.is_dir():
        return False
    names = {p.name for p in folder.iterdir()}
    return not names or (set(EXPORT_FILES) <= names and all(n.endswith(".csv") or n in EXPORT_FILES for n in names))


def _stream_file(name: str) -> str:
    return f"{safe_name(name)}.csv"


def _write_csv(session: RecordedSession, folder: Path, progress: Progress | None) -> list[str]:
    folder.mkdir(mode=0o700)
    written: list[str] = []
    total = max(1, sum(len(s) for s in session.streams.values()))
    done = 0
    for name, stream in session.streams.items():
        _report(progress, 0.9 * done / total)
        written.append(_stream_file(name))
        write_aligned_csv(folder / written[-1],
                          [(stream.t, [(c.name, c.unit, stream.data[c.name]) for c in stream.channels])],
                          [f"LINarm++ Manager session export: stream {name}", "time: monotonic seconds"])
        done += len(stream)
    with open(folder / "events.csv", "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_wall", "t_mono_s", "kind", "who", "origin", "data"])
        for e in session.events:
            w.writerow([e.get("t_wall", ""), repr(float(e.get("t_mono", float("nan")))), e.get("kind", ""),
                        e.get("who", ""), e.get("origin", ""),
                        json.dumps(e.get("data", {}), ensure_ascii=False, default=str)])
    write_json_atomic(folder / "manifest.json", session.manifest)
    _report(progress, 0.9)
    return [*written, *EXPORT_FILES]


def verify_csv(session: RecordedSession, folder: Path) -> None:
    """Every stream file holds every sample (its rows counted, its last row's time compared), events.csv every
    event, manifest.json the manifest (raises NotRight)."""
    for name, stream in session.streams.items():
        path = folder / _stream_file(name)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise NotRight(f"{path.name} is missing ({exc.strerror or exc})") from exc
        lines = [ln for ln in data.split(b"\n") if ln and not ln.startswith(b"#")]
        rows = len(lines) - 2  # the names and the units
        if rows != len(stream) or (rows and float(lines[-1].split(b",", 1)[0]) != float(stream.t[-1])):
            raise NotRight(f"{path.name} holds {max(rows, 0)} of the {len(stream)} samples of {name}")
    try:
        with open(folder / "events.csv", encoding="utf-8", newline="") as fh:
            events = sum(1 for _ in csv.reader(fh)) - 1
        manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise NotRight(f"the events or the manifest are not readable ({exc})") from exc
    if events != len(session.events):
        raise NotRight(f"events.csv holds {events} of the {len(session.events)} events")
    if json.loads(json.dumps(session.manifest, default=str)) != manifest:
        raise NotRight("manifest.json differs from the session's manifest")


def load_csv_export(folder: str | Path) -> RecordedSession:
    """Read a CSV export back (streams, events, manifest) — the inverse of :func:`export_csv`."""
    folder = Path(folder)
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    by_file = {safe_name(n): (n, info) for n, info in (manifest.get("streams") or {}).items()}
    streams: dict[str, RecordedStream] = {}
    for path in sorted(folder.glob("*.csv")):
        if path.name == "events.csv":
            continue
        names, units, values = read_aligned_csv(path)
        heads = list(zip(names, units, strict=True))
        name, info = by_file.get(path.stem, (path.stem, {}))
        labels = {c["name"]: c.get("label", c["name"]) for c in info.get("channels") or []}
        channels = tuple(Channel(n, u, labels.get(n, n)) for n, u in heads[1:])
        streams[name] = RecordedStream(name, channels, float(info.get("nominal_rate_hz") or 0.0), values[:, 0].copy(),
                                       {c.name: values[:, i + 1].copy() for i, c in enumerate(channels)},
                                       device=info.get("device", ""))
    events = []
    with open(folder / "events.csv", encoding="utf-8", newline="") as fh:
        for row in csv.DictReader(fh):
            events.append({"t_wall": row["t_wall"], "t_mono": float(row["t_mono_s"]), "kind": row["kind"],
                           "who": row["who"], "origin": row["origin"], "data": json.loads(row["data"])})
    return RecordedSession(folder, manifest, streams, events)


# ---------------------------------------------------------------------------------------------- the table writer
AlignedStream = tuple[Sequence[float] | np.ndarray, Sequence[tuple[str, str, Sequence[float] | np.ndarray]]]


def write_aligned_csv(path: str | Path, streams: Sequence[AlignedStream], comments: Sequence[str] = ()) -> int:
    """The one CSV writer of the application: the graphs' Save and the session CSV export both use it.
    ``streams``: per stream its time stamps and its columns (name, unit, values). Returns the data rows.

    Layout: ``#`` comment lines, a row of names (``time`` then each column), a row of units (``s`` then
    each unit), then the data. Streams of different rates share one time column and nothing is
    interpolated, repeated or dropped: each row is one instant, a stream's cells are filled only in the
    rows of its own samples (empty otherwise); streams sampled at the same instant share rows; several
    samples of one stream with the same time stamp take consecutive rows. Values are written with
    ``repr`` so they read back bit-exact. (pandas: ``read_csv(path, comment="#", header=[0, 1])``.)
    """
    times = [np.asarray(t, dtype=np.float64) for t, _cols in streams]
    occurrences = [np.arange(len(t)) - np.searchsorted(t, t, "left") for t in times]  # repeats of one time
    cat_t = np.concatenate(times) if times else np.zeros(0)
    cat_k = np.concatenate(occurrences) if occurrences else np.zeros(0, dtype=np.int64)
    order = np.lexsort((cat_k, cat_t))
    st, sk = cat_t[order], cat_k[order]
    new_row = np.ones(len(st), dtype=bool)
    if len(st) > 1:
        new_row[1:] = (st[1:] != st[:-1]) | (sk[1:] != sk[:-1])
    row_of_sorted = np.cumsum(new_row) - 1
    nrows = int(row_of_sorted[-1] + 1) if len(st) else 0
    row_of = np.empty(len(st), dtype=np.int64)
    row_of[order] = row_of_sorted
    row_time = np.empty(nrows)
    row_time[row_of_sorted] = st
    names: list[str] = []
    units: list[str] = []
    ncols = sum(len(cols) for _t, cols in streams)
    cells = [[""] * ncols for _ in range(nrows)]
    offset = col = 0
    for (_t, cols), t in zip(streams, times, strict=True):
        rows = row_of[offset:offset + len(t)].tolist()
        offset += len(t)
        for name, unit, values in cols:
            names.append(name)
            units.append(unit)
            for r, v in zip(rows, np.asarray(values, dtype=np.float64).tolist(), strict=True):
                cells[r][col] = repr(v)
            col += 1
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    with open(tmp, "w", encoding="utf-8", newline="") as fh:
        for line in comments:
            fh.write(f"# {line}\n")
        fh.write(",".join(["time", *map(_csv_field, names)]) + "\n")
        fh.write(",".join(["s", *map(_csv_field, units)]) + "\n")
        for r in range(nrows):
            fh.write(repr(float(row_time[r])) + "," + ",".join(cells[r]) + "\n")
    os.replace(tmp, path)
    return nrows


def _csv_field(text: str) -> str:
    if any(ch in text for ch in ',"\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def read_aligned_csv(path: str | Path) -> tuple[list[str], list[str], np.ndarray]:
    """Names, units and the value table (NaN in empty cells) of a file written by write_aligned_csv."""
    with open(path, encoding="utf-8", newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    names, units, data = rows[0], rows[1], rows[2:]
    table = np.array([[float(c) if c else np.nan for c in r] for r in data], dtype=np.float64) \
        if data else np.zeros((0, len(names)))
    return names, units, table
