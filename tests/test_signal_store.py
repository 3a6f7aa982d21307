"""The GUI ring buffers: exact snapshots across wrap-around, envelopes that keep every extreme,
growth when a device runs faster than nominal, CSV export bit-exact with units, and feeding from a
real driver over a pty through the bus and its Qt adapter."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from app.core.bus import Channel, SampleBatch, StreamBus, StreamSpec
from app.ui.qt_bus import QtBus
from app.ui.signal_store import BLOCK, SignalStore
from tests.fakes import CounterDriver, make_counter_device

FAST = StreamSpec("dev.fast", (Channel("a", "m", "A"), Channel("b", "N", "B")), 1000.0)
SLOW = StreamSpec("dev.slow", (Channel("c", "bpm", "C"),), 100.0)


def feed_random(store: SignalStore, spec: StreamSpec, sizes: list[int], seed: int = 0, t0: float = 0.0,
                dt: float = 0.001) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    ts, cols = [], {c.name: [] for c in spec.channels}
    n_done = 0
    for n in sizes:
        t = t0 + (n_done + np.arange(n)) * dt
        data = {c.name: rng.normal(size=n) for c in spec.channels}
        store.feed({spec.name: SampleBatch(spec, t, data)})
        ts.append(t)
        for k, v in data.items():
            cols[k].append(v)
        n_done += n
    return np.concatenate(ts) if ts else np.zeros(0), {k: np.concatenate(v) if v else np.zeros(0)
                                                       for k, v in cols.items()}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 700), max_size=40))
def test_snapshot_is_exactly_the_newest_samples(sizes: list[int]) -> None:
    store = SignalStore(history_s=1.0)  # 1 kHz → capacity ~1.5 k: many wrap-arounds
    store.add_stream(FAST)
    t, cols = feed_random(store, FAST, sizes)
    cap = store.capacity("dev.fast")
    st_t, st_a = store.snapshot("dev.fast.a")
    assert np.array_equal(st_t, t[-cap:]) and np.array_equal(st_a, cols["a"][-cap:])
    if len(t) > 10:
        lo, hi = t[-min(len(t), cap) + 3], t[-4]
        w_t, w_b = store.snapshot("dev.fast.b", lo, hi)
        mask = (t >= lo) & (t <= hi)
        assert np.array_equal(w_t, t[mask]) and np.array_equal(w_b, cols["b"][mask])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(1, 900), min_size=1, max_size=30), st.integers(8, 400), st.floats(0.0, 0.9))
def test_envelope_keeps_extremes_and_point_budget(sizes: list[int], max_points: int, start_frac: float) -> None:
    store = SignalStore(history_s=2.0)
    store.add_stream(FAST)
    feed_random(store, FAST, sizes, seed=len(sizes))
    held_t, held_a = store.snapshot("dev.fast.a")
    lo = held_t[0] + start_frac * (held_t[-1] - held_t[0])
    et, ea = store.envelope("dev.fast.a", lo, None, max_points=max_points)
    mask = held_t >= lo
    assert ea.max() == held_a[mask].max() and ea.min() == held_a[mask].min()
    assert len(et) <= max_points + 4  # two partial buckets at most beyond the budget
    assert np.all(np.diff(et) >= 0) and et[0] >= lo


def test_envelope_is_raw_when_few_samples() -> None:
    store = SignalStore(history_s=10.0)
    store.add_stream(SLOW)
    t, cols = feed_random(store, SLOW, [50, 30], dt=0.01)
    et, ec = store.envelope("dev.slow.c", None, None, max_points=1000)
    assert np.array_equal(et, t) and np.array_equal(ec, cols["c"])


def test_ring_grows_when_device_is_faster_than_nominal() -> None:
    store = SignalStore(history_s=2.0)
    store.add_stream(SLOW)  # says 100 Hz ...
    _t, cols = feed_random(store, SLOW, [100] * 40, dt=0.001)  # ... delivers 1 kHz for 4 s
    held_t, held_c = store.snapshot("dev.slow.c")
    assert held_t[-1] - held_t[0] >= 2.0 * 0.95  # the whole history is still there
    assert np.array_equal(held_c, cols["c"][-len(held_c):])
    _et, ec = store.envelope("dev.slow.c", held_t[0], None, max_points=100)
    assert ec.max() == held_c.max() and ec.min() == held_c.min()


def test_value_at_picks_nearest_sample() -> None:
    store = SignalStore(history_s=10.0)
    store.add_stream(SLOW)
    store.feed({"dev.slow": SampleBatch(SLOW, np.array([1.0, 2.0, 3.0]), {"c": np.array([10.0, 20.0, 30.0])})})
    assert store.value_at("dev.slow.c", 2.4) == (2.0, 20.0)
    assert store.value_at("dev.slow.c", 2.6) == (3.0, 30.0)
    assert store.value_at("dev.slow.c", -5) == (1.0, 10.0)


def read_export(path: Path) -> tuple[list[str], list[str], list[list[str]]]:
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith("#")]
    rows = list(csv.reader(lines))
    return rows[0], rows[1], rows[2:]


def test_csv_export_is_exact_with_names_units_and_shared_time(tmp_path: Path) -> None:
    store = SignalStore(history_s=10.0)
    store.add_stream(FAST)
    store.add_stream(SLOW)
    # Fast stream at 1 kHz with repeated timestamps (several frames decoded from one read).
    t_fast = np.repeat(np.arange(0, 0.05, 0.01), 3)
    a = np.random.default_rng(3).normal(size=len(t_fast))
    store.feed({"dev.fast": SampleBatch(FAST, t_fast, {"a": a, "b": a * 2})})
    t_slow = np.array([0.0, 0.02, 0.025, 0.04])
    c = np.array([60.1, 61.0 / 3, 62.5, 63.0])
    store.feed({"dev.slow": SampleBatch(SLOW, t_slow, {"c": c})})
    path = tmp_path / "out.csv"
    rows = store.export_csv(path, ["dev.fast.a", "dev.slow.c"])
    names, units, data = read_export(path)
    assert names == ["time", "dev.fast.a", "dev.slow.c"]
    assert units == ["s", "m", "bpm"]
    assert rows == len(data)
    got_a = [(float(r[0]), float(r[1])) for r in data if r[1]]
    got_c = [(float(r[0]), float(r[2])) for r in data if r[2]]
    assert got_a == list(zip(t_fast.tolist(), a.tolist(), strict=True))  # every sample, bit-exact, in order
    assert got_c == list(zip(t_slow.tolist(), c.tolist(), strict=True))
    # Coinciding instants share a row; the slow stream's 0.025 s sample has a row of its own.
    assert rows == len(t_fast) + 1
    times = [float(r[0]) for r in data]
    assert times == sorted(times)


def test_csv_export_of_a_time_window(tmp_path: Path) -> None:
    store = SignalStore(history_s=10.0)
    store.add_stream(FAST)
    t, cols = feed_random(store, FAST, [500])
    path = tmp_path / "w.csv"
    store.export_csv(path, ["dev.fast.b"], t_from=t[100], t_to=t[199])
    _n, _u, data = read_export(path)
    assert [float(r[1]) for r in data] == cols["b"][100:200].tolist()


def test_attach_feeds_from_a_real_driver_over_a_pty(qtbot, tmp_path: Path) -> None:
    sim = make_counter_device(tmp_path)
    sim.start()
    bus = StreamBus()
    driver = CounterDriver(sim.url, bus=bus)
    qt_bus = QtBus(bus)
    store = SignalStore(history_s=5.0)
    store.attach_bus(qt_bus)
    store.attach_bus(qt_bus)  # idempotent: one connection, no double samples
    assert [i.key for i in store.signals()] == ["counter.main.count"]
    driver.start()
    try:
        qtbot.waitUntil(lambda: store.count("counter.main.count") > 200, timeout=5000)
    finally:
        driver.stop()
        sim.stop()
        qt_bus.close()
    _t, counts = store.snapshot("counter.main.count")
    # The counter increments by one per frame: nothing lost, nothing duplicated.
    assert np.all(np.diff(counts) == 1)
    assert BLOCK > 1


def test_the_store_follows_one_adapter_at_a_time(qtbot) -> None:
    """Two adapters on one bus (a window's and a frame's own): attached to the second, the store lets go of
    the first, so no sample is stored twice."""
    bus = StreamBus()
    bus.declare([SLOW])
    first, second = QtBus(bus), QtBus(bus)
    store = SignalStore(history_s=5.0)
    store.attach_bus(first)
    store.attach_bus(second)
    for k in range(10):
        bus.publish(SLOW.name, k * 0.01, type("S", (), {"c": float(k)})())
    first.tick()
    second.tick()
    _t, values = store.snapshot("dev.slow.c")
    assert values.tolist() == [float(k) for k in range(10)]
    first.close()
    second.close()


def test_on_screen_is_false_on_a_hidden_tab_a_minimised_window_or_scrolled_away(qtbot) -> None:
    from PySide6.QtWidgets import QLabel, QScrollArea, QTabWidget, QVBoxLayout, QWidget

    from app.ui.widgets import on_screen

    tabs = QTabWidget()
    shown, hidden = QLabel("shown"), QLabel("hidden")
    tabs.addTab(shown, "a")
    tabs.addTab(hidden, "b")
    qtbot.addWidget(tabs)
    tabs.resize(300, 200)
    assert not on_screen(shown)  # the window is not shown yet
    tabs.show()
    qtbot.waitExposed(tabs)
    assert on_screen(shown) and not on_screen(hidden)
    tabs.setCurrentWidget(hidden)
    assert on_screen(hidden) and not on_screen(shown)
    tabs.showMinimized()
    assert not on_screen(hidden)

    scroll = QScrollArea()
    body = QWidget()
    lay = QVBoxLayout(body)
    top, bottom = QLabel("top"), QLabel("bottom")
    lay.addWidget(top)
    lay.addSpacing(2000)
    lay.addWidget(bottom)
    scroll.setWidget(body)
    qtbot.addWidget(scroll)
    scroll.resize(200, 150)
    scroll.show()
    qtbot.waitExposed(scroll)
    assert on_screen(top) and not on_screen(bottom)
