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
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from app.devices.driver import Channel
from app.recording import RecordedSession, RecordedStream, safe_name, write_json_atomic

FORMAT = "linarmpp-session"
FORMAT_VERSION = 1
Progress = Callable[[float], bool]
_ROWS_PER_CHUNK = 20_000


class ExportCancelled(Exception):
    pass


def _report(progress: Progress | None, fraction: float) -> None:
    if progress is not None and progress(min(1.0, max(0.0, fraction))) is False:
        raise ExportCancelled("export cancelled")


# ---------------------------------------------------------------------------------------------- HDF5
def export_hdf5(session: RecordedSession, path: str | Path, progress: Progress | None = None) -> Path:
    """Write the whole session to one HDF5 file (written to a temp name, renamed when complete)."""
    import h5py

    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    total = max(1, sum(len(s) for s in session.streams.values()))
    done = 0
    try:
        with h5py.File(tmp, "w") as h5:
            h5.attrs["format"] = FORMAT
            h5.attrs["format_version"] = FORMAT_VERSION
            h5.attrs["manifest"] = json.dumps(session.manifest, ensure_ascii=False, default=str)
            streams = h5.create_group("streams")
            for name, stream in session.streams.items():
                _report(progress, done / total)
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
        _report(progress, 1.0)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


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
def _header(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def _rows_text(block: np.ndarray) -> str:
    # Python's repr of a float is the shortest text that reads back to the same double.
    return "".join(",".join(map(repr, row)) + "\n" for row in block.tolist())


def export_csv(session: RecordedSession, folder: str | Path, progress: Progress | None = None) -> list[Path]:
    """One CSV per stream (header of names and units), events.csv and manifest.json in ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    total = max(1, sum(len(s) for s in session.streams.values()))
    done = 0
    try:
        for name, stream in session.streams.items():
            path = folder / f"{safe_name(name)}.csv"
            written.append(path)
            with open(path, "w", encoding="utf-8", newline="") as fh:
                fh.write(",".join(["t_mono_s [s]", *(_header(c.name, c.unit) for c in stream.channels)]) + "\n")
                table = np.column_stack([stream.t, *(stream.data[c.name] for c in stream.channels)]) \
                    if len(stream) else np.zeros((0, 1 + len(stream.channels)))
                for start in range(0, len(table), _ROWS_PER_CHUNK):
                    _report(progress, (done + start) / total)
                    fh.write(_rows_text(table[start:start + _ROWS_PER_CHUNK]))
            done += len(stream)
        path = folder / "events.csv"
        written.append(path)
        with open(path, "w", encoding="utf-8", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_wall", "t_mono_s", "kind", "who", "origin", "data"])
            for e in session.events:
                w.writerow([e.get("t_wall", ""), repr(float(e.get("t_mono", float("nan")))), e.get("kind", ""),
                            e.get("who", ""), e.get("origin", ""),
                            json.dumps(e.get("data", {}), ensure_ascii=False, default=str)])
        path = folder / "manifest.json"
        written.append(path)
        write_json_atomic(path, session.manifest)
        _report(progress, 1.0)
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        raise
    return written


def _split_header(text: str) -> tuple[str, str]:
    if text.endswith("]") and " [" in text:
        name, unit = text[:-1].rsplit(" [", 1)
        return name, unit
    return text, ""


def load_csv_export(folder: str | Path) -> RecordedSession:
    """Read a CSV export back (streams, events, manifest) — the inverse of :func:`export_csv`."""
    folder = Path(folder)
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    by_file = {safe_name(n): (n, info) for n, info in (manifest.get("streams") or {}).items()}
    streams: dict[str, RecordedStream] = {}
    for path in sorted(folder.glob("*.csv")):
        if path.name == "events.csv":
            continue
        lines = path.read_text(encoding="utf-8").splitlines()
        heads = [_split_header(h) for h in lines[0].split(",")]
        values = np.array(",".join(lines[1:]).split(","), dtype=np.float64).reshape(len(lines) - 1, len(heads)) \
            if len(lines) > 1 else np.zeros((0, len(heads)))
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


# ---------------------------------------------------------------------------------------------- graphs
Column = tuple[str, str, Sequence[float] | np.ndarray, Sequence[float] | np.ndarray]  # name, unit, t, values


def write_signals_csv(path: str | Path, columns: list[Column]) -> Path:
    """The graphs' Save: signals side by side. Columns sharing the same time stamps share one time
    column; groups of different lengths are padded with empty cells."""
    path = Path(path)
    groups: list[tuple[np.ndarray, list[tuple[str, str, np.ndarray]]]] = []
    for name, unit, t, values in columns:
        t_arr, v_arr = np.asarray(t, dtype=np.float64), np.asarray(values, dtype=np.float64)
        if len(t_arr) != len(v_arr):
            raise ValueError(f"{name}: {len(t_arr)} time stamps but {len(v_arr)} values")
        for gt, members in groups:
            if len(gt) == len(t_arr) and np.array_equal(gt, t_arr):
                members.append((name, unit, v_arr))
                break
        else:
            groups.append((t_arr, [(name, unit, v_arr)]))
    header: list[str] = []
    for _gt, members in groups:
        header.append("t [s]" if len(groups) == 1 else f"t {members[0][0]} [s]")
        header += [_header(n, u) for n, u, _ in members]
    rows = max((len(gt) for gt, _ in groups), default=0)
    tmp = path.with_name(f".{path.name}.part")
    with open(tmp, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(header) + "\n")
        for i in range(rows):
            cells: list[str] = []
            for gt, members in groups:
                if i < len(gt):
                    cells.append(repr(float(gt[i])))
                    cells += [repr(float(v[i])) for _, _, v in members]
                else:
                    cells += [""] * (1 + len(members))
            fh.write(",".join(cells) + "\n")
    os.replace(tmp, path)
    return path

