"""Export to HDF5 and CSV round-trips the recorded values exactly; the graphs' CSV writer."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from app.core.bus import Channel, StreamSpec
from app.core.config import AppConfig
from app.session.export import (
    ExportCancelled,
    export_csv,
    export_hdf5,
    load_csv_export,
    load_hdf5,
    read_aligned_csv,
    write_aligned_csv,
)
from app.session.recording import RecordedSession, SessionRecorder, load_session
from tests.fakes import ListenerDriver
from tests.recorder_host import recorder_host


def _Driver() -> ListenerDriver:
    return ListenerDriver(
        StreamSpec("robot.state", (Channel("centre", "m", "Centre"), Channel("force", "N", "Force")), 200.0),
        StreamSpec("physio.main", (Channel("heartRate", "bpm", "Heart rate"),), 100.0))



@pytest.fixture
def session(tmp_path) -> RecordedSession:
    driver = _Driver()
    config = AppConfig()
    manager = recorder_host(config, {"dev": driver})
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P010", "op", root=tmp_path / "sessions")
    rng = np.random.default_rng(11)
    t = 5000.0 + np.cumsum(rng.random(3000) * 0.005)
    for i, ti in enumerate(t):
        for fn in driver.listeners:
            fn("robot.state", float(ti), SimpleNamespace(centre=float(rng.standard_normal() * 0.1),
                                                         force=float(rng.standard_normal() * 1e3)))
            if i % 2 == 0:
                fn("physio.main", float(ti), SimpleNamespace(heartRate=float(60 + rng.random() * 1e-9)))
    recorder.event("script_start", "op", name="reach.py", text="print('héllo, \"world\"')\n")
    recorder.event("parameter_change", "op", name="k_r", old=0.1, new=1 / 3)
    recorder.stop()
    return load_session(folder)


def assert_same(a: RecordedSession, b: RecordedSession) -> None:
    assert set(a.streams) == set(b.streams)
    for name, sa in a.streams.items():
        sb = b.streams[name]
        assert sa.channels == sb.channels and sa.nominal_rate_hz == sb.nominal_rate_hz
        assert sa.t.dtype == sb.t.dtype == np.float64 and np.array_equal(sa.t, sb.t)
        for ch in sa.channels:
            assert np.array_equal(sa.data[ch.name], sb.data[ch.name]), (name, ch.name)
    assert a.events == b.events
    assert a.manifest == b.manifest


def test_hdf5_round_trip_is_exact(session, tmp_path) -> None:
    assert len(session.streams["robot.state"]) == 3000 and len(session.streams["physio.main"]) == 1500
    seen: list[float] = []
    path = export_hdf5(session, tmp_path / "s.h5", progress=lambda f: seen.append(f) or True)
    assert seen[-1] == 1.0
    assert_same(session, load_hdf5(path))


def test_csv_round_trip_is_exact(session, tmp_path) -> None:
    files = export_csv(session, tmp_path / "csv")
    assert {f.name for f in files} == {"robot.state.csv", "physio.main.csv", "events.csv", "manifest.json"}
    lines = [line for line in (tmp_path / "csv" / "robot.state.csv").read_text(encoding="utf-8").splitlines()
             if not line.startswith("#")]
    assert lines[:2] == ["time,centre,force", "s,m,N"]
    assert_same(session, load_csv_export(tmp_path / "csv"))


def test_cancelled_export_leaves_nothing(session, tmp_path) -> None:
    with pytest.raises(ExportCancelled):
        export_hdf5(session, tmp_path / "s.h5", progress=lambda f: f < 0.3)
    assert list(tmp_path.glob("*.h5*")) == [] and list(tmp_path.glob(".*")) == []
    with pytest.raises(ExportCancelled):
        export_csv(session, tmp_path / "csv", progress=lambda f: f < 0.5)
    assert not (tmp_path / "csv").exists() and list(tmp_path.glob(".*")) == []  # no partial folder (#37)


def test_one_writer_aligns_streams_of_different_rates(tmp_path) -> None:
    """write_aligned_csv is what both the graphs' Save and the session export write with."""
    t1, t2 = np.array([0.1, 0.2, 0.3]), np.array([0.15, 0.2])
    path = tmp_path / "g.csv"
    rows = write_aligned_csv(path, [(t1, [("centre", "m", [1.0, 2.0, 1 / 3]), ("force", "N", [4, 5, 6])]),
                                    (t2, [("hr", "bpm", [70.5, 71.0])])], ["a comment"])
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == "# a comment" and lines[1:3] == ["time,centre,force,hr", "s,m,N,bpm"]
    # Nothing interpolated or repeated: a stream's cells are empty where it has no sample.
    assert lines[3:] == ["0.1,1.0,4.0,", "0.15,,,70.5", "0.2,2.0,5.0,71.0", f"0.3,{1 / 3!r},6.0,"]
    assert rows == 4
    names, units, table = read_aligned_csv(path)
    assert names == ["time", "centre", "force", "hr"] and units == ["s", "m", "N", "bpm"]
    assert table[0, 1] == 1.0 and np.isnan(table[0, 3]) and table[3, 1] == 1 / 3


def test_graphs_save_and_session_export_share_the_writer(monkeypatch, session, tmp_path) -> None:
    import app.session.export

    calls: list[str] = []
    real = app.session.export.write_aligned_csv
    monkeypatch.setattr(app.session.export, "write_aligned_csv", lambda path, *a, **k: calls.append(str(path)) or real(
        path, *a, **k))
    export_csv(session, tmp_path / "csv")
    from app.ui.signal_store import SignalStore

    store = SignalStore(10.0)
    from app.core.bus import Channel, SampleBatch, StreamSpec

    spec = StreamSpec("dev.main", (Channel("x", "m", "X"),), 100.0)
    store.add_stream(spec, "dev")
    store.feed({"dev.main": SampleBatch(spec, np.array([1.0, 2.0]), {"x": np.array([0.5, 0.25])})})
    store.export_csv(tmp_path / "graphs.csv", ["dev.main.x"])
    assert str(tmp_path / "graphs.csv") in calls and any(c.endswith("robot.state.csv") for c in calls)
