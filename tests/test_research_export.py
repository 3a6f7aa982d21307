"""Research export (issue #41), acceptance 1: a session recorded by the real recorder (a grip onset and an
emergency stop at known times) exported as XDF, EDF+ and BIDS; each file read back by the format's own reader
(pyxdf, pyedflib, pybids) gives every sample of every stream with its recorded time (XDF and BIDS within 1 µs; EDF on
its grid, within its stated limits) and the known events at the same time in the three within one sample period."""

from __future__ import annotations

import gzip
import json
import math

import numpy as np
import pytest

from app.core import streams
from app.research_export.command import main as export_main
from app.session.recording import load_session
from tests.research_export_data import GRIP_THRESHOLD_N, Recorded, record_session

pyxdf = pytest.importorskip("pyxdf")
pyedflib = pytest.importorskip("pyedflib")
bids = pytest.importorskip("bids")

US = 1e-6


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("export")
    mp = pytest.MonkeyPatch()
    try:
        rec = record_session(root / "sessions", monkeypatch=mp)
    finally:
        mp.undo()
    out = {"rec": rec, "session": load_session(rec.folder)}
    for fmt in ("xdf", "edf", "bids"):
        target = root / f"out-{fmt}"
        assert export_main(["--format", fmt, str(rec.folder), "--out", str(target), "--quiet"]) == 0
        out[fmt] = target
    return out


def _truth(session, name: str) -> tuple[np.ndarray, np.ndarray]:
    s = session.streams[name]
    return s.t, np.column_stack([s.data[c.name] for c in s.channels])


def _grip_onset(t: np.ndarray, force: np.ndarray) -> float:
    k = int(np.argmax(np.nan_to_num(force) >= GRIP_THRESHOLD_N))
    return float(t[k])


def test_xdf_read_by_pyxdf_gives_every_sample_at_its_recorded_time(exported) -> None:
    rec: Recorded = exported["rec"]
    session = exported["session"]
    (path,) = exported["xdf"].glob("*.xdf")
    data, _header = pyxdf.load_xdf(str(path), dejitter_timestamps=False)  # clocks synchronised (the default)
    by_name = {s["info"]["name"][0]: s for s in data}
    assert set(session.streams) | {"linarmpp.events", "linarmpp.markers"} == set(by_name)
    for name in session.streams:
        t, values = _truth(session, name)
        s = by_name[name]
        assert len(s["time_stamps"]) == len(t) > 0, name
        assert np.max(np.abs(s["time_stamps"] - t)) <= US, name
        assert np.array_equal(s["time_series"], values, equal_nan=True), name
        chans = s["info"]["desc"][0]["channels"][0]["channel"]
        assert [c["label"][0] for c in chans] == [c.name for c in session.streams[name].channels]
        assert [(c["unit"][0] or "") for c in chans] == [c.unit for c in session.streams[name].channels]
        assert float(s["info"]["nominal_srate"][0]) == (0.0 if name == streams.FES_CHANNELS else
                                                         session.streams[name].nominal_rate_hz)
        assert len(s["clock_times"]) > 0 and set(s["clock_values"]) == {0.0}  # offsets: mapped when recorded
    events = by_name["linarmpp.events"]
    assert [json.loads(x[0]) for x in events["time_series"]] == session.events
    assert np.max(np.abs(events["time_stamps"] - [e["t_mono"] for e in session.events])) <= US
    markers = by_name["linarmpp.markers"]
    estop = [t for t, (m,) in zip(markers["time_stamps"], markers["time_series"], strict=True)
             if m.startswith("emergency_stop")]
    assert estop == [pytest.approx(rec.estop_t, abs=US)]
    physio = by_name[streams.PHYSIO_MAIN]
    grip = _grip_onset(physio["time_stamps"], physio["time_series"][:, 3])
    assert grip == pytest.approx(rec.grip_onset_t, abs=US)
    fes_on = [t for t, (m,) in zip(markers["time_stamps"], markers["time_series"], strict=True)
              if m == "fes_on channel 1"]
    assert len(fes_on) == 1


def test_edf_read_by_pyedflib_holds_every_sample_on_its_grid(exported) -> None:
    rec: Recorded = exported["rec"]
    session = exported["session"]
    (path,) = exported["edf"].glob("*.edf")
    reader = pyedflib.EdfReader(str(path))
    try:
        t0 = session.start_mono  # the file starts at the session's start (its header gives the wall time)
        start = reader.getStartdatetime()
        assert start.strftime("%Y-%m-%d %H:%M:%S") == session.manifest["start"]["t_wall"][:19].replace("T", " ")
        labels = reader.getSignalLabels()
        found = missing = 0
        for i, _label in enumerate(labels):
            stream, name = reader.getTransducer(i).split(" ")[:2]  # "linarm.vsa handlePos (Handle position)"
            s = session.streams[stream]
            ch = next(c for c in s.channels if c.name == name)
            assert reader.getPhysicalDimension(i) == ch.unit.replace("µ", "u").replace("°C", "degC")
            fs = reader.getSampleFrequency(i)
            assert fs == (40.0 if stream == streams.FES_CHANNELS else s.nominal_rate_hz)
            phys = reader.readSignal(i)
            digital = reader.readSignal(i, digital=True)
            step = (reader.getPhysicalMaximum(i) - reader.getPhysicalMinimum(i)) / 65535
            values = s.data[ch.name]
            slot = np.rint((s.t - t0) * fs).astype(int)
            for k, v in zip(slot.tolist(), values.tolist(), strict=True):
                ok = False
                for j in (k, k + 1):  # the nearest slot, or the next one when a sample took it
                    if j < len(phys) and (digital[j] == -32768 if math.isnan(v) else abs(phys[j] - v) <= step):
                        ok = True
                        break
                found += ok
                missing += not ok
        total = sum(len(s.t) * len(s.channels) for s in session.streams.values())
        # EDF's limits (docs/export.md): a few samples of the warm-up's bunched time stamps find no slot
        assert found + missing == total and missing / total < 0.01, (found, missing)
        onsets, _durations, texts = reader.readAnnotations()
    finally:
        reader.close()
    estop = [o for o, t in zip(onsets, texts, strict=True) if t.startswith("emergency_stop")]
    assert estop == [pytest.approx(rec.estop_t - t0, abs=1e-4)]  # EDF+ onsets to 100 µs
    physio = session.streams[streams.PHYSIO_MAIN]
    i = labels.index("force")
    reader = pyedflib.EdfReader(str(path))
    try:
        force = reader.readSignal(i)
    finally:
        reader.close()
    k = int(np.argmax(force >= GRIP_THRESHOLD_N))
    assert abs(t0 + k / 100.0 - rec.grip_onset_t) <= 1 / physio.nominal_rate_hz


def _bids_layout(root):
    return bids.BIDSLayout(str(root), validate=False)


def test_bids_read_by_pybids_gives_every_sample_at_its_recorded_time(exported) -> None:
    import pandas as pd

    rec: Recorded = exported["rec"]
    session = exported["session"]
    t0 = session.start_mono
    layout = _bids_layout(exported["bids"])
    assert layout.get_subjects() == ["PZ017"] and layout.get_sessions() == ["1"]
    motion = layout.get(suffix="motion", extension=".tsv")
    assert {f.entities["acquisition"] for f in motion} == {"vsa", "motor0", "motor1", "state"}
    stream_of = {"vsa": streams.LINARM_VSA, "motor0": streams.LINARM_MOTOR0, "motor1": streams.LINARM_MOTOR1,
                 "state": streams.LINARM_STATE}
    for f in motion:
        name = stream_of[f.entities["acquisition"]]
        channels = layout.get(suffix="channels", extension=".tsv", acquisition=f.entities["acquisition"])[0].get_df()
        assert f.get_metadata()["SamplingFrequency"] == session.streams[name].nominal_rate_hz
        table = pd.read_csv(f.path, sep="\t", header=None, names=list(channels["name"]), na_values="n/a")
        t, values = _truth(session, name)
        assert np.max(np.abs(table["latency"].to_numpy() + t0 - t)) <= US, name
        assert np.array_equal(table.drop(columns="latency").to_numpy(), values, equal_nan=True), name
        units = dict(zip(channels["name"], channels["units"], strict=True))
        assert units["latency"] == "s"
    for f in layout.get(extension=".tsv.gz"):
        label = f.entities["recording"]
        name = {"physio": streams.PHYSIO_MAIN, "patientmodel": streams.PATIENT_MODEL_MAIN, "vr": streams.VR_MAIN,
                "fes": streams.FES_CHANNELS}[label]
        meta = f.get_metadata()
        table = f.get_df(include_timing=False)
        t, values = _truth(session, name)
        cols = [c.name for c in session.streams[name].channels]
        if label == "fes":  # held on a grid; the updates are where the timestamp column changes
            assert meta["SamplingFrequency"] == 40.0
            first = ~table["timestamp"].duplicated().to_numpy()
            table = table[first]
        assert np.max(np.abs(table["timestamp"].to_numpy() + t0 - t)) <= US, name
        assert np.array_equal(table[cols].to_numpy(), values, equal_nan=True), name
        assert meta["StartTime"] == pytest.approx(float(t[0]) - t0, abs=US)
    events = layout.get(suffix="events", extension=".tsv")[0].get_df()
    estop = events[events["trial_type"] == "emergency_stop"]["onset"].to_numpy()
    assert estop.tolist() == [pytest.approx(rec.estop_t - t0, abs=US)]
    rep = events[events["trial_type"] == "repetition"]
    assert len(rep) == 1 and rep["duration"].iloc[0] > 2.0
    physio = layout.get(extension=".tsv.gz", recording="physio")[0].get_df(include_timing=False)
    grip = _grip_onset(physio["timestamp"].to_numpy() + t0, physio["force"].to_numpy())
    assert grip == pytest.approx(rec.grip_onset_t, abs=US)
    with gzip.open(layout.get(extension=".tsv.gz", recording="physio")[0].path, "rt") as fh:
        assert "\t" in fh.readline()  # a header-less TSV, as BIDS physio files are
    derivatives = list((exported["bids"] / "derivatives" / "linarmpp-metrics").rglob("*_metrics.tsv"))
    reps = pd.read_csv(derivatives[0], sep="\t", na_values="n/a")
    assert len(reps) == 1 and reps["index"].iloc[0] == 1


def test_the_known_events_agree_across_the_three_formats(exported) -> None:
    """The e-stop and the grip onset, read from each format, within one sample period of one another."""
    rec: Recorded = exported["rec"]
    session = exported["session"]
    t0 = session.start_mono
    (xdf_path,) = exported["xdf"].glob("*.xdf")
    data, _ = pyxdf.load_xdf(str(xdf_path), dejitter_timestamps=False)
    by_name = {s["info"]["name"][0]: s for s in data}
    mk = by_name["linarmpp.markers"]
    xdf_estop = next(t for t, (m,) in zip(mk["time_stamps"], mk["time_series"], strict=True)
                     if m.startswith("emergency_stop"))
    xdf_grip = _grip_onset(by_name[streams.PHYSIO_MAIN]["time_stamps"],
                           by_name[streams.PHYSIO_MAIN]["time_series"][:, 3])
    (edf_path,) = exported["edf"].glob("*.edf")
    reader = pyedflib.EdfReader(str(edf_path))
    try:
        onsets, _, texts = reader.readAnnotations()
        edf_estop = t0 + next(o for o, t in zip(onsets, texts, strict=True) if t.startswith("emergency_stop"))
        force = reader.readSignal(reader.getSignalLabels().index("force"))
        edf_grip = t0 + int(np.argmax(force >= GRIP_THRESHOLD_N)) / reader.getSampleFrequency(
            reader.getSignalLabels().index("force"))
    finally:
        reader.close()
    layout = _bids_layout(exported["bids"])
    events = layout.get(suffix="events", extension=".tsv")[0].get_df()
    bids_estop = t0 + float(events[events["trial_type"] == "emergency_stop"]["onset"].iloc[0])
    physio = layout.get(extension=".tsv.gz", recording="physio")[0].get_df(include_timing=False)
    bids_grip = t0 + _grip_onset(physio["timestamp"].to_numpy(), physio["force"].to_numpy())
    period = 1 / session.streams[streams.PHYSIO_MAIN].nominal_rate_hz
    for a, b in ((xdf_estop, edf_estop), (xdf_estop, bids_estop), (xdf_grip, edf_grip), (xdf_grip, bids_grip)):
        assert abs(a - b) <= period
    assert abs(xdf_estop - rec.estop_t) <= US and abs(bids_estop - rec.estop_t) <= US


def test_the_derivatives_are_the_applications_metrics(exported) -> None:
    """derivatives/linarmpp-metrics, computed one exercise run at a time, are app.session.metrics' repetitions of the
    whole session (what ``--metrics`` prints)."""
    import pandas as pd

    from app.session.metrics import metrics_of_session

    expected = metrics_of_session(exported["session"])["repetitions"]
    (path,) = (exported["bids"] / "derivatives" / "linarmpp-metrics").rglob("*_desc-repetitions_metrics.tsv")
    table = pd.read_csv(path, sep="\t", na_values="n/a")
    assert len(table) == len(expected) > 0
    for row, rep in zip(table.to_dict("records"), expected, strict=True):
        for key in ("index", "start_s", "end_s", "duration_s", "peak_speed_m_s", "range_m", "sparc",
                    "reaction_time_s", "grip_at_start_n"):
            if rep.get(key) is None:
                assert math.isnan(row[key]), key
            else:
                assert row[key] == pytest.approx(rep[key], rel=1e-9, abs=1e-12), key
