"""Research export (issue #41): the command line's answers, cancel, the XDF writer against pyxdf's clock
synchronisation with real offsets, and memory that does not grow with the session's length."""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.research_export.command import main as export_main
from app.research_export.common import ExportCancelled
from app.research_export.source import FolderSource, open_session
from app.research_export.xdf import StreamDescription, XdfWriter, export_xdf, footer_xml, header_xml, scan_xdf
from tests.research_export_data import synth_session

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli")
    synth_session(root, "PC-001", 30.0)
    synth_session(root, "PC-002", 20.0, folder_name="20260302-100000", start_iso="2026-03-02T10:00:00+01:00")
    return root


def test_exit_codes_of_the_command(sessions, tmp_path, capsys) -> None:
    one = next((sessions / "PC-001").iterdir())
    # 0: written and read back; the files on stdout
    assert export_main(["--format", "xdf", str(sessions), "--out", str(tmp_path / "x"), "--quiet"]) == 0
    out = capsys.readouterr().out.split()
    assert sorted(Path(p).name for p in out) == ["PC-001_20260301-100000.xdf", "PC-002_20260302-100000.xdf"]
    # 2: wrong arguments, nothing read
    assert export_main(["--format", "xdf", str(tmp_path / "nowhere"), "--out", str(tmp_path / "y")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert export_main(["--format", "bids", str(one), "--out", str(tmp_path / "x")]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert export_main(["--format", "mat", str(one), "--out", str(tmp_path / "z")]) == 2
    capsys.readouterr()
    # 1: nothing could be written (the only session's manifest is damaged), one sentence
    broken = tmp_path / "broken" / "P" / "20260101-000000"
    broken.mkdir(parents=True)
    (broken / "manifest.json").write_text("{not json")
    assert export_main(["--format", "edf", str(broken), "--out", str(tmp_path / "e"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("Nothing was written") and "manifest" in err[0]


def test_an_incomplete_session_is_written_and_what_is_missing_listed(sessions, tmp_path, capsys) -> None:
    import shutil

    crashed = tmp_path / "crashed" / "PC-001" / "20260301-100000"
    shutil.copytree(next((sessions / "PC-001").iterdir()), crashed)
    manifest = json.loads((crashed / "manifest.json").read_text())
    manifest["status"] = "recording"  # never stopped: a crash
    (crashed / "manifest.json").write_text(json.dumps(manifest))
    with open(crashed / "streams" / "linarm.vsa.csv", "ab") as fh:
        fh.write(b"20100.0,0.1,0.2")  # a last line cut short
    for fmt in ("xdf", "edf", "bids"):
        assert export_main(["--format", fmt, str(crashed), "--out", str(tmp_path / f"o-{fmt}"), "--quiet"]) == 3, fmt
        captured = capsys.readouterr()
        assert captured.out.strip(), "the written file is listed"
        assert "not stopped normally" in captured.err and "linarm.vsa: 1 incomplete line(s) dropped" in captured.err


def test_the_installed_command_runs_the_export(sessions, tmp_path) -> None:
    proc = subprocess.run([sys.executable, str(ROOT / "main.py"), "export", "--format", "edf",
                           str(sessions / "PC-002"), "--out", str(tmp_path / "edf")], capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    (path,) = (tmp_path / "edf").glob("*.edf")
    assert path.stat().st_mode & 0o777 == 0o600  # health data: the user's only


def test_cancel_leaves_nothing(sessions, tmp_path) -> None:
    from app.research_export.bids import export_bids
    from app.research_export.edf import export_edf

    session = open_session(FolderSource(next((sessions / "PC-001").iterdir())))
    calls = {"n": 0}

    def cancel() -> bool:
        calls["n"] += 1
        return calls["n"] > 3

    with pytest.raises(ExportCancelled):
        export_xdf(session, tmp_path / "a.xdf", cancel=cancel)
    calls["n"] = 0
    with pytest.raises(ExportCancelled):
        export_edf(session, tmp_path / "a.edf", cancel=cancel)
    calls["n"] = 0
    with pytest.raises(ExportCancelled):
        export_bids([session], tmp_path / "ds", cancel=cancel)
    assert list(tmp_path.iterdir()) == []


def test_xdf_clock_offsets_are_applied_by_pyxdf_as_recorded(tmp_path) -> None:
    """A stream stamped on a device's clock, with the offsets to the host's clock in ClockOffset chunks (every 5 s,
    as LabRecorder writes them): pyxdf's synchronised times are the host times within 1 µs."""
    pyxdf = pytest.importorskip("pyxdf")
    host = 8000.0 + np.arange(0, 60.0, 0.01)
    offset = lambda t: -1234.5 + 20e-6 * (t - 8000.0)  # noqa: E731 - a device clock 20 ppm slow, far from the host
    device = host - offset(host)  # what the device's clock said
    values = np.column_stack([np.sin(host), np.cos(host)])
    buf = io.BytesIO()
    w = XdfWriter(buf)
    w.stream_header(7, header_xml(StreamDescription("dev", "Position", 2, 100.0, "double64", "dev.1", 0.0, "u",
                                                    channels=[{"label": "a", "unit": "m", "type": "Position"},
                                                              {"label": "b", "unit": "m", "type": "Position"}])))
    w.stream_header(8, header_xml(StreamDescription("marks", "Markers", 1, 0.0, "string", "dev.2", 0.0, "v")))
    offsets = []
    for k in range(0, len(host), 500):
        w.samples(7, device[k:k + 500], values[k:k + 500])
        t_dev = float(device[k])
        w.clock_offset(7, t_dev, offset(host[k]))  # measured at a time on the stream's clock
        offsets.append((t_dev, offset(host[k])))
    w.string_samples(8, [8001.5, 8030.25], ["start", "ünïcode ✓"])
    w.boundary()
    w.stream_footer(7, footer_xml(device[0], device[-1], len(device), offsets))
    w.stream_footer(8, footer_xml(8001.5, 8030.25, 2, []))
    path = tmp_path / "o.xdf"
    path.write_bytes(buf.getvalue())
    streams, _ = pyxdf.load_xdf(str(path), dejitter_timestamps=False)
    by_name = {s["info"]["name"][0]: s for s in streams}
    assert np.max(np.abs(by_name["dev"]["time_stamps"] - host)) <= 1e-6
    assert np.array_equal(by_name["dev"]["time_series"], values)
    assert [x[0] for x in by_name["marks"]["time_series"]] == ["start", "ünïcode ✓"]
    scan = scan_xdf(path)
    assert scan.streams[7].samples == len(host) and scan.streams[7].offsets == len(offsets) and scan.boundaries == 1


def test_a_chunk_longer_than_four_gigabytes_would_use_eight_length_bytes() -> None:
    from app.research_export.xdf import _varlen

    assert _varlen(200) == b"\x01\xc8" and _varlen(70000) == b"\x04" + struct.pack("<I", 70000)
    assert _varlen(1 << 33) == b"\x08" + struct.pack("<Q", 1 << 33)


def test_memory_does_not_grow_with_the_sessions_length(tmp_path) -> None:
    """The same exports of a session four times longer need no more memory: peak RSS growth of each format in a
    child process (bench/bench_export.py; the 2-hour figures are in bench/README.md, "Session 6 (#41)"). Blocks of
    64 KiB, so that the short session fills them as the long one does (the command line reads 4 MiB)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_export import measure_all

    only = ("linarm.vsa", "physio.main")
    short = synth_session(tmp_path / "s", "PM-001", 1 * 60.0, only=only, run_s=30.0)  # BIDS metrics hold one run:
    long = synth_session(tmp_path / "l", "PM-001", 4 * 60.0, only=only, run_s=30.0)  # runs of the same length
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = measure_all(short, tmp_path / "a", block_bytes=64 * 1024)
    b = measure_all(long, tmp_path / "b", block_bytes=64 * 1024)
    figures = {fmt: (round(a[fmt]["growth_mb"], 1), round(b[fmt]["growth_mb"], 1)) for fmt in a}
    print("peak RSS growth (MB), 1 min vs 4 min:", figures)
    for fmt in a:
        assert b[fmt]["growth_mb"] <= a[fmt]["growth_mb"] + 5.0, figures


def test_an_archived_session_exports_as_its_folder_does(sessions, tmp_path) -> None:
    """The archive's SessionFiles (files, open, read_bytes: app/archive/api.py, #39) is a session source: the same
    XDF bytes as from the folder (a stand-in over the folder's files here; stage 2 uses the archive's)."""
    import io as _io
    from types import SimpleNamespace

    from app.research_export.source import ArchivedSource

    folder = next((sessions / "PC-002").iterdir())

    class Files:  # what app.archive's SessionFiles offers
        uuid = "3f1c"

        def files(self):
            return [SimpleNamespace(name=str(p.relative_to(folder)), size=p.stat().st_size, sha256="")
                    for p in folder.rglob("*") if p.is_file()]

        def open(self, name):
            return _io.BytesIO((folder / name).read_bytes())

        def read_bytes(self, name):
            return (folder / name).read_bytes()

    a = export_xdf(open_session(FolderSource(folder)), tmp_path / "folder.xdf")
    b = export_xdf(open_session(ArchivedSource(Files())), tmp_path / "archive.xdf")
    assert a.written and b.written
    assert (tmp_path / "folder.xdf").read_bytes() == (tmp_path / "archive.xdf").read_bytes()
