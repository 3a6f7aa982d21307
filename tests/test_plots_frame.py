"""Frame 2 driven like a user: tick signals, see one plot per unit, pause, read the cursor, Save to
CSV (names, units, values equal to what was fed), export PNG, keys, settings that persist."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from PySide6.QtCore import QSettings, Qt
from PySide6.QtGui import QImage
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QFileDialog

from app.core.bus import Channel, SampleBatch, StreamSpec
from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.plots_frame import PlotsFrame
from app.ui.signal_store import SignalStore, shared_store
from tests.fakes import counter_factory

VSA = StreamSpec("linarm.vsa", (Channel("handlePos", "m", "Handle position"),
                                Channel("interactionForce", "N", "Interaction force"),
                                Channel("equilibriumPos", "m", "Centre")), 200.0)
PHYSIO = StreamSpec("physio.main", (Channel("heartRate", "bpm", "Heart rate"),), 100.0)


def synthetic_store(seconds: float = 4.0) -> tuple[SignalStore, dict[str, np.ndarray]]:
    store = SignalStore(history_s=30.0)
    store.add_stream(VSA, "linarm")
    store.add_stream(PHYSIO, "physio")
    t = np.arange(0, seconds, 1 / 200)
    pos = 0.25 + 0.1 * np.sin(t)
    force = 3.0 * np.cos(3 * t)
    t_hr = np.arange(0, seconds, 1 / 100)
    hr = 70 + np.sin(t_hr)
    for i in range(0, len(t), 7):  # batches, as drivers deliver them
        sl = slice(i, i + 7)
        store.feed({"linarm.vsa": SampleBatch(VSA, t[sl], {"handlePos": pos[sl], "interactionForce": force[sl],
                                                             "equilibriumPos": np.full(len(t[sl]), 0.25)})})
    store.feed({"physio.main": SampleBatch(PHYSIO, t_hr, {"heartRate": hr})})
    return store, {"t": t, "pos": pos, "force": force, "t_hr": t_hr, "hr": hr}


def make_frame(qtbot, store: SignalStore) -> PlotsFrame:
    QSettings().remove("plots")
    frame = PlotsFrame(None, store=store)
    qtbot.addWidget(frame)
    frame.resize(900, 600)
    frame.show()
    qtbot.waitExposed(frame)
    return frame


def tick(frame: PlotsFrame, key: str) -> None:
    item = next(it for it in frame._leaf_items() if it.data(0, Qt.ItemDataRole.UserRole) == key)
    item.setCheckState(0, Qt.CheckState.Checked)


def read_export(path: Path) -> tuple[list[str], list[str], list[list[str]]]:
    rows = list(csv.reader(ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith("#")))
    return rows[0], rows[1], rows[2:]


def test_tree_lists_every_signal_grouped_by_device(qtbot) -> None:
    store, _ = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected([])
    top = [frame.tree.topLevelItem(i).text(0) for i in range(frame.tree.topLevelItemCount())]
    assert top == ["linarm", "physio"]
    keys = {it.data(0, Qt.ItemDataRole.UserRole) for it in frame._leaf_items()}
    assert keys == {"linarm.vsa.handlePos", "linarm.vsa.interactionForce", "linarm.vsa.equilibriumPos",
                    "physio.main.heartRate"}
    assert frame.plots == {}


def test_selecting_signals_makes_one_plot_per_unit_with_shared_time(qtbot) -> None:
    store, data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected([])
    tick(frame, "linarm.vsa.handlePos")
    tick(frame, "linarm.vsa.equilibriumPos")
    tick(frame, "linarm.vsa.interactionForce")
    tick(frame, "physio.main.heartRate")
    assert list(frame.plots) == ["m", "N", "bpm"]
    qtbot.wait(50)  # let the new plots get their geometry
    frame.redraw()
    x, y = frame.curves["linarm.vsa.handlePos"].getData()
    assert len(x) > 100 and x.max() <= 0 and np.isclose(y.max(), data["pos"].max())
    ranges = {tuple(np.round(p.vb.viewRange()[0], 6)) for p in frame.plots.values()}
    assert len(ranges) == 1  # linked time axes
    image = frame.graphics.grab().toImage()
    assert len({image.pixel(px, py) for px in range(0, image.width(), 5) for py in range(0, image.height(), 5)}) > 5


def test_pause_freezes_and_save_writes_exact_values(qtbot, tmp_path: Path, monkeypatch) -> None:
    store, data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos", "physio.main.heartRate"])
    frame.redraw()
    QTest.keyClick(frame.graphics, Qt.Key.Key_Space)
    assert frame.paused and frame.pause_button.isChecked() and frame.pause_button.text() == "Resume"
    # New data while paused does not move the frozen picture.
    before = frame.curves["linarm.vsa.handlePos"].getData()[1].copy()
    store.feed({"linarm.vsa": SampleBatch(VSA, np.array([10.0]), {"handlePos": np.array([9.9]),
                                                                  "interactionForce": np.array([0.0]),
                                                                  "equilibriumPos": np.array([0.25])})})
    frame.redraw()
    assert np.array_equal(frame.curves["linarm.vsa.handlePos"].getData()[1], before)

    out = tmp_path / "signals.csv"
    monkeypatch.setattr(QFileDialog, "getSaveFileName", lambda *a, **k: (str(out), "CSV files (*.csv)"))
    frame.scope_box.setCurrentIndex(frame.scope_box.findData("all"))
    frame.save_button.click()
    names, units, rows = read_export(out)
    assert names == ["time", "linarm.vsa.handlePos", "physio.main.heartRate"]
    assert units == ["s", "m", "bpm"]
    got_pos = [float(r[1]) for r in rows if r[1]]
    got_hr = [float(r[2]) for r in rows if r[2]]
    assert got_pos == data["pos"].tolist()  # the frozen buffer: without the sample fed after pausing
    assert got_hr == data["hr"].tolist()
    assert "saved" in frame.status.text()

    # Visible range: zoom to the last second and save only that.
    frame.plots["m"].setXRange(-1.0, 0.0, padding=0)
    visible = tmp_path / "visible.csv"
    frame.save_csv(visible, "visible")
    _n, _u, rows = read_export(visible)
    t_rows = [float(r[0]) for r in rows if r[1]]
    lo, hi = frame.visible_range()
    expected = data["t"][(data["t"] >= lo) & (data["t"] <= hi)]
    assert t_rows == expected.tolist() and 150 <= len(t_rows) <= 250

    # Issue #30: two streams of different rates in one table are said to leave empty cells; "a file per
    # stream" writes each dense at its own rate.
    assert "empty cells" in frame.status.text()
    frame.save_csv(tmp_path / "split.csv", "all", "per_stream")
    _n, _u, pos_rows = read_export(tmp_path / "split-linarm.vsa.csv")
    names, _u, hr_rows = read_export(tmp_path / "split-physio.main.csv")
    assert names == ["time", "physio.main.heartRate"] and all(r[1] for r in hr_rows)
    assert [float(r[1]) for r in pos_rows] == data["pos"].tolist()
    assert [float(r[1]) for r in hr_rows] == data["hr"].tolist()
    assert "2 files" in frame.status.text()

    QTest.keyClick(frame.graphics, Qt.Key.Key_P)
    assert not frame.paused


def test_cursor_readout_and_png_export(qtbot, tmp_path: Path, monkeypatch) -> None:
    store, data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos"])
    frame.redraw()
    frame.set_cursor(-1.0)
    t_end = data["t"][-1]
    expected = data["pos"][np.argmin(np.abs(data["t"] - (t_end - 1.0)))]
    text = frame.readout_text()
    assert "t = -1.000 s" in text and f"{expected:.4g}" in text and "Handle position" in text
    assert all(line.isVisible() and line.value() == -1.0 for line in frame.vlines)
    png = tmp_path / "graphs.png"
    monkeypatch.setattr(QFileDialog, "getSaveFileName", lambda *a, **k: (str(png), "PNG images (*.png)"))
    frame.png_button.click()
    image = QImage(str(png))
    assert not image.isNull() and image.width() > 100
    assert len({image.pixel(x, y) for x in range(0, image.width(), 9) for y in range(0, image.height(), 9)}) > 5


def test_keys_history_and_autoscale(qtbot) -> None:
    store, _ = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos"])
    frame.set_history(10.0)
    frame.redraw()
    x0, x1 = frame.plots["m"].vb.viewRange()[0]
    assert np.isclose(x0, -10.0) and np.isclose(x1, 0.0)
    QTest.keyClick(frame.graphics, Qt.Key.Key_Plus)
    assert frame.history_s == 20.0
    frame.autoscale_box.setChecked(False)
    assert not frame.plots["m"].vb.autoRangeEnabled()[1]
    QTest.keyClick(frame.graphics, Qt.Key.Key_A)
    assert frame.autoscale_box.isChecked() and frame.plots["m"].vb.autoRangeEnabled()[1]


def test_settings_persist_selection_and_plot_settings(qtbot) -> None:
    store, _ = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["physio.main.heartRate", "vr.main.score"])  # vr is absent: kept for later
    frame.set_history(5.0)
    frame.autoscale_box.setChecked(False)
    frame.scope_box.setCurrentIndex(frame.scope_box.findData("all"))
    settings = QSettings()
    frame.save_settings(settings)
    settings.sync()
    again = PlotsFrame(None, store=store)
    qtbot.addWidget(again)
    assert again.selected == ["physio.main.heartRate"]
    assert again._wanted == ["vr.main.score"]
    assert again.history_s == 5.0 and not again.autoscale_box.isChecked()
    assert again.scope_box.currentData() == "all"
    QSettings().remove("plots")


def test_live_frame_from_a_counter_device_over_a_pty(qtbot, tmp_path: Path) -> None:
    QSettings().remove("plots")
    manager = LinarmppManager(AppConfig(), factories={"counter": counter_factory(tmp_path)})
    manager.start()
    try:
        frame = PlotsFrame(manager)
        qtbot.addWidget(frame)
        frame.resize(800, 500)
        frame.show()
        assert frame.qt_bus is not None and frame.store is shared_store(manager, frame.qt_bus)  # one per manager
        frame.set_selected(["counter.main.count"])
        qtbot.waitUntil(lambda: frame.store.count("counter.main.count") > 300, timeout=5000)
        frame.redraw()
        x, y = frame.curves["counter.main.count"].getData()
        assert len(x) > 0 and y.max() > 200
        QTest.keyClick(frame.graphics, Qt.Key.Key_Space)
        out = tmp_path / "counter.csv"
        frame.save_csv(out, "all")
        names, units, rows = read_export(out)
        counts = [float(r[1]) for r in rows]
        assert names == ["time", "counter.main.count"] and units == ["s", ""]
        assert counts == list(np.arange(counts[0], counts[0] + len(counts)))  # consecutive counter values
    finally:
        manager.shutdown()


def test_sticky_y_range_moves_only_when_the_data_leaves_it_or_shrinks_within_it() -> None:
    from app.ui.plots_frame import Y_FILL_MIN, sticky_y_range

    assert sticky_y_range((0.0, 10.0), 2.0, 8.0) is None  # inside, fills 60 %: kept
    lo, hi = sticky_y_range((0.0, 10.0), 2.0, 12.0)  # leaves it: a new range with headroom
    assert lo < 2.0 and hi > 12.0 and sticky_y_range((lo, hi), 2.0, 12.0) is None
    lo, hi = sticky_y_range((0.0, 10.0), 4.0, 4.0 + 0.9 * Y_FILL_MIN * 10.0)  # too small a part of it
    assert 0.0 < lo < 4.0 and hi < 10.0
    lo, hi = sticky_y_range((0.0, 10.0), 2.0, 8.0, snap=True)  # Fit: close around the data
    assert 1.5 < lo < 2.0 and 8.0 < hi < 8.5
    lo, hi = sticky_y_range(None, 5.0, 5.0)  # a flat line: a band around it
    assert lo < 5.0 < hi


def feed_vsa(store: SignalStore, t: np.ndarray, pos: np.ndarray) -> None:
    store.feed({"linarm.vsa": SampleBatch(VSA, t, {"handlePos": pos, "interactionForce": np.zeros(len(t)),
                                                   "equilibriumPos": np.full(len(t), 0.25)})})


def test_the_vertical_range_holds_still_for_small_changes_and_never_clips(qtbot) -> None:
    store, data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos"])
    vb = frame.plots["m"].vb

    def frame_now() -> tuple[float, float]:
        frame.redraw()
        frame.graphics.grab()  # paints now (the autorange is applied when painting), exposed or not
        return tuple(vb.viewRange()[1])

    first = frame_now()
    assert first[0] <= data["pos"].min() and data["pos"].max() <= first[1]
    assert first[1] - first[0] < 0.5  # fitted to the data (0.15..0.35 m), not pyqtgraph's default 0..1
    t = data["t"][-1]
    for _ in range(20):  # new samples inside the range: the axis (and its grid) is not regenerated
        t += 0.005
        feed_vsa(store, np.array([t]), np.array([0.30]))
        assert frame_now() == first
    feed_vsa(store, np.array([t + 0.005]), np.array([0.60]))  # beyond the top: the range follows at once
    lo, hi = frame_now()
    assert hi >= 0.60 and lo <= data["pos"].min()
    frame.autoscale_box.setChecked(False)  # autoscale off: the range stays whatever comes
    feed_vsa(store, np.array([t + 0.01]), np.array([5.0]))
    assert frame_now() == (lo, hi)


def test_a_hidden_frame_draws_nothing_and_an_unchanged_one_is_not_redrawn(qtbot) -> None:
    from PySide6.QtWidgets import QLabel, QTabWidget

    QSettings().remove("plots")
    store, data = synthetic_store()
    tabs = QTabWidget()
    frame = PlotsFrame(None, store=store)
    tabs.addTab(QLabel("values"), "Values")
    tabs.addTab(frame, "Graphs")
    qtbot.addWidget(tabs)
    tabs.resize(900, 600)
    tabs.show()
    qtbot.waitExposed(tabs)
    frame.set_selected(["linarm.vsa.handlePos"])
    drawn = len(frame.frame_times)
    feed_vsa(store, np.array([data["t"][-1] + 0.01]), np.array([0.3]))
    qtbot.wait(3 * frame.timer.interval())
    frame._tick()
    assert len(frame.frame_times) == drawn  # on a hidden tab: no frame
    tabs.setCurrentWidget(frame)
    qtbot.waitExposed(frame)
    frame._tick()
    assert len(frame.frame_times) == drawn + 1  # shown: the new data is drawn
    frame._tick()
    assert len(frame.frame_times) == drawn + 1  # no new sample: nothing to redraw
    feed_vsa(store, np.array([data["t"][-1] + 0.02]), np.array([0.3]))
    frame._tick()
    assert len(frame.frame_times) == drawn + 2


def test_costly_frames_slow_the_redraw_down_to_keep_the_gui_thread_free(qtbot) -> None:
    from app.ui.plots_frame import GRAPH_DUTY, MAX_INTERVAL_MS

    store, data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos"])
    frame.set_history(5.0)
    base = frame.timer.interval()
    t = data["t"][-1]
    for _ in range(30):  # frames that paint for 60 ms each
        t += 0.005
        feed_vsa(store, np.array([t]), np.array([0.3]))
        frame._tick()
        frame.graphics.last_paint_s = 0.060
    assert frame.timer.interval() >= min(MAX_INTERVAL_MS, 0.9 * 60 / GRAPH_DUTY) > base
    for _ in range(60):  # cheap again: back to the configured rate
        t += 0.005
        feed_vsa(store, np.array([t]), np.array([0.3]))
        frame._tick()
        frame.graphics.last_paint_s = 0.0
    assert frame.timer.interval() <= max(base, 1000 * 5.0 / frame.plots["m"].vb.width()) + 3


def test_fes_channels_named_by_number_and_muscle_and_exports_carry_the_session(qtbot, tmp_path: Path) -> None:
    """Issue #19: eight identical "Current c…" rows; Save CSV as "signals.csv" in raw monotonic
    seconds; PNGs of ~640×260 without patient, date or units."""
    from app.core.fes_profile import load_profile
    from app.devices import rehastim
    from app.ui.fes_panel import PROFILES_DIR

    manager = LinarmppManager(AppConfig(), factories={"fes": rehastim.create})
    manager.start()
    try:
        frame = PlotsFrame(manager)
        qtbot.addWidget(frame)
        frame.resize(700, 300)
        frame.show()
        fes = manager.driver("fes")
        qtbot.waitUntil(lambda: fes.device_ready, timeout=3000)
        fes.load_profile(load_profile(PROFILES_DIR / "wrist_extension_time.yaml"))
        qtbot.waitUntil(lambda: any(frame.tree.findItems("3 current · extensor carpi radialis",
                                                         Qt.MatchFlag.MatchExactly | Qt.MatchFlag.MatchRecursive)),
                        timeout=3000)
        names = [i.text(0) for i in frame._leaf_items() if str(i.data(0, Qt.ItemDataRole.UserRole)).startswith("fes.")]
        assert len(set(names)) == len(names) == 16 and "5 pulse width" in names
        manager.start_session("P077", "Dr Neri", root=tmp_path)
        t0 = frame.session_t0
        assert t0 is not None
        csv_default = frame.default_file("csv")
        assert csv_default.parent == manager.recorder.folder and csv_default.name.startswith("P077_")
        frame.set_selected(["fes.channels.current3"])
        qtbot.waitUntil(lambda: "fes.channels.current3" in frame.store
                        and frame.store.last_time() is not None and frame.store.last_time() > t0 + 0.3, timeout=3000)
        out = tmp_path / "x.csv"
        frame.save_csv(out, "all")
        text = out.read_text(encoding="utf-8")
        assert "seconds from the start of session P077/" in text
        _n, _u, rows = read_export(out)
        assert -60.0 < float(rows[-1][0]) < 60.0, "time from the session start, not raw monotonic seconds"
        png = tmp_path / "g.png"
        assert frame.export_png(png)
        image = QImage(str(png))
        assert image.width() >= 1600 and image.height() >= 400
        assert "P077/" in frame.export_title() and "mA: 3 current · extensor carpi radialis" in frame.export_title()
        manager.end_session()
    finally:
        manager.shutdown()


def test_the_left_axis_has_room_for_tick_labels_beside_the_unit(qtbot) -> None:
    """Issue #19: "(mm)" was overlapped by tick labels such as 317.05 (on screen and in PNGs)."""
    from PySide6.QtGui import QFontMetrics

    store, _ = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos"])
    frame.redraw()
    axis = frame.plots["m"].getAxis("left")
    fm = QFontMetrics(frame.graphics.font())
    assert axis.minimumWidth() >= fm.horizontalAdvance("-317.05") + fm.lineSpacing() + 8


def test_a_pane_ticked_above_the_kept_ones_moves_them_down(qtbot) -> None:
    """A signal whose unit comes first in the tree, ticked after one below it: its new pane takes the first row
    and the kept pane moves down (the incremental build left both in row 0, one over the other; seen when the
    replay window ticks its signals one per turn)."""
    store, _ = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["physio.main.heartRate"])
    frame.set_selected(["linarm.vsa.handlePos", "physio.main.heartRate"])
    assert list(frame.plots) == ["m", "bpm"]
    layout = frame.graphics.ci
    rows = {unit: layout.items[plot][0][0] for unit, plot in frame.plots.items()}
    assert rows == {"m": 0, "bpm": 1}
    qtbot.wait(50)
    frame.redraw()
    top = [p.sceneBoundingRect().top() for p in frame.plots.values()]
    assert top[0] < top[1]  # drawn one above the other, not over it
