"""The driver base over a real pty with a simulator thread: data flow, batching, kill/reconnect. The driver
publishes on its stream bus; the tests read it as consumers do (a queued subscription, display-rate batches)."""

from __future__ import annotations

import itertools
import threading

import numpy as np
import pytest
from PySide6.QtCore import QTimer

from app.core.bus import Channel, SampleItem, StreamBus, StreamSpec, UpdateNotifier
from app.core.journal import Record
from app.devices.driver import DeviceDriver
from app.devices.sim.base import SerialSimulator
from tests.fakes import CounterCore, CounterDriver
from tests.memory_link import MemoryLink


class ConnectionLog:
    """The driver's connection changes as (connected, reason), read from a queued bus subscription (what the Qt
    adapter's connection_changed carries)."""

    def __init__(self, bus: StreamBus) -> None:
        self.sub = bus.subscribe("test connection log", (), events=True)
        self.items: list[tuple[bool, str]] = []
        self.silence: list[bool] = []  # True: went silent, False: alive again

    def _take(self) -> None:
        for item in self.sub.drain():
            if isinstance(item, Record):
                if item.kind in ("connected", "disconnected"):
                    self.items.append((item.kind == "connected", item.detail))
                elif item.kind in ("silent", "alive"):
                    self.silence.append(item.kind == "silent")

    def __iter__(self):
        self._take()
        return iter(list(self.items))

    def silence_changes(self) -> list[bool]:
        self._take()
        return list(self.silence)


class Batches(list):
    """Display-rate column batches, taken from the bus at 30 Hz like the Qt adapter's timer."""

    def __init__(self, bus: StreamBus) -> None:
        super().__init__()
        self.sub = bus.subscribe_batches("test batches")
        self.timer = QTimer()
        self.timer.timeout.connect(self._take)
        self.timer.start(33)

    def _take(self) -> None:
        batch = self.sub.take()
        if batch:
            self.append(batch)

    def close(self) -> None:
        self.timer.stop()
        self._take()
        self.sub.close()


@pytest.fixture
def counter(tmp_path, qtbot):
    sim = SerialSimulator("counter", CounterCore, tmp_path / "counter.tty")
    sim.start()
    driver = CounterDriver(sim.url, bus=StreamBus(UpdateNotifier()), silence_timeout_s=0.05)
    driver.reconnect_backoff_s = (0.05, 0.2)
    events = ConnectionLog(driver.bus)
    driver.start()
    yield sim, driver, events
    driver.stop()
    sim.stop()
    assert not driver.isRunning()


def test_samples_arrive_in_batches_in_order(counter, qtbot) -> None:
    _sim, driver, _ = counter
    batches = Batches(driver.bus)
    try:
        qtbot.waitUntil(lambda: sum(len(b["counter.main"]) for b in batches) >= 300, timeout=5000)
    finally:
        batches.timer.stop()
    counts = [c for b in batches for c in b["counter.main"].data["count"]]
    diffs = {b - a for a, b in itertools.pairwise(counts)}
    assert diffs == {1.0}, "samples must arrive complete and in order"
    # Batched at display rate: far fewer signals than samples.
    assert len(batches) < len(counts) / 5
    qtbot.waitUntil(lambda: driver.rates().get("counter.main", 0) > 500, timeout=3000)


def test_killed_simulator_is_reported_then_reconnected(counter, qtbot) -> None:
    sim, driver, events = counter
    escaped: list[BaseException] = []
    old_hook = threading.excepthook
    threading.excepthook = lambda args: escaped.append(args.exc_value)
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=3000)
        sim.kill()
        qtbot.waitUntil(lambda: not driver.connected, timeout=3000)
        qtbot.waitUntil(lambda: any(not ok for ok, _ in events), timeout=3000)  # the queued event
        down = [why for ok, why in events if not ok]
        assert down and down[-1], "the disconnection carries a reason"
        assert "lost" in down[-1] or "cannot open" in down[-1]
        sim.restart()
        qtbot.waitUntil(lambda: driver.connected, timeout=5000)
        before = driver.total_samples("counter.main")
        qtbot.waitUntil(lambda: driver.total_samples("counter.main") > before + 50, timeout=3000)
    finally:
        threading.excepthook = old_hook
    assert escaped == []
    assert [ok for ok, _ in events][-1] is True


def test_silence_is_detected_while_connected(counter, qtbot) -> None:
    sim, driver, events = counter
    qtbot.waitUntil(lambda: driver.connected and driver.total_samples("counter.main") > 10, timeout=3000)
    before = len(events.silence_changes())
    sim.with_core(lambda core: setattr(core, "period_s", 10.0))  # the device stops talking
    qtbot.waitUntil(lambda: len(events.silence_changes()) > before, timeout=3000)
    assert events.silence_changes()[before:before + 1] == [True]


def test_stop_is_prompt(counter) -> None:
    import time

    _, driver, _ = counter
    t0 = time.monotonic()
    assert driver.stop(1.0)
    assert time.monotonic() - t0 < 0.5


# -- the per-sample path without a link: an in-memory transport ----------------------------------------

class _CountingNotifier(UpdateNotifier):
    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def notify(self) -> None:
        self.calls += 1
        super().notify()


def _two_stream_driver(reads: list[bytes], notifier: UpdateNotifier) -> DeviceDriver:
    """A driver on a private bus whose notifier counts the wake-ups."""
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Pair:
        a: float
        ok: bool

    class PairDriver(DeviceDriver):
        streams = (StreamSpec("pair.x", (Channel("a", "", "A"), Channel("ok", "", "OK")), 100.0),
                   StreamSpec("pair.y", (Channel("a", "", "A"),), 100.0))

        def on_bytes(self, data: bytes, t_ns: int) -> None:
            for b in data:  # one sample per byte: odd bytes to x, even to y
                self.publish("pair.x" if b % 2 else "pair.y", t_ns / 1e9, Pair(float(b), b > 100))

    link = MemoryLink()
    for data in reads:
        link.push(data)
    return PairDriver("pair", link, bus=StreamBus(notifier))


def test_every_sample_reaches_subscribers_latest_and_batches_with_one_wake_up_per_read(qtbot) -> None:
    reads = [bytes(range(i, i + 7)) for i in range(0, 210, 7)]  # 30 reads, 210 samples
    notifier = _CountingNotifier()
    driver = _two_stream_driver(reads, notifier)
    seen: list[tuple[str, float]] = []
    queue = driver.bus.subscribe("test", ("pair.x", "pair.y"))

    def subscriber_took_all() -> bool:
        seen.extend((item.stream, item.sample.a) for item in queue.drain() if isinstance(item, SampleItem))
        return len(seen) == 210

    batches = Batches(driver.bus)
    driver.start()
    try:
        qtbot.waitUntil(lambda: subscriber_took_all() and driver.total_samples("pair.y") == 105, timeout=5000)
        qtbot.waitUntil(lambda: sum(len(b.get("pair.x", ())) for b in batches) == 105, timeout=5000)
        qtbot.waitUntil(lambda: notifier.calls >= 31, timeout=5000)
        notified = notifier.calls
    finally:
        driver.stop()
        batches.close()
        queue.close()
    assert queue.dropped == 0
    assert [a for _s, a in seen] == [float(b) for b in range(210)]
    assert notified == 1 + 30  # connected, then once per read (not once per sample)
    assert driver.latest("pair.x").a == 209.0 and driver.latest("pair.y").a == 208.0
    x = [b["pair.x"] for b in batches if "pair.x" in b]
    a = np.concatenate([b.data["a"] for b in x])
    ok = np.concatenate([b.data["ok"] for b in x])
    assert a.tolist() == [float(b) for b in range(1, 210, 2)]
    assert ok.tolist() == [1.0 if b > 100 else 0.0 for b in range(1, 210, 2)]
    assert all(b.data["a"].flags.c_contiguous and b.t.shape == b.data["a"].shape for b in x)
    y = np.concatenate([b["pair.y"].data["a"] for b in batches if "pair.y" in b])
    assert y.tolist() == [float(b) for b in range(0, 210, 2)]


def test_publish_outside_a_read_notifies_at_once() -> None:
    notifier = _CountingNotifier()
    driver = _two_stream_driver([], notifier)
    driver.publish("pair.y", 1.0, type("S", (), {"a": 3.0})())
    assert notifier.calls == 1


def test_notifier_wakes_every_waiter_promptly_and_counts_without_waiters() -> None:
    import time

    notifier = UpdateNotifier()
    for _ in range(1000):  # nobody waiting: just the count
        notifier.notify()
    assert notifier.generation == 1000 and notifier._waiting == 0
    rounds, woken = 200, []

    def waiter() -> None:
        g = notifier.generation
        for _ in range(rounds):
            if give_up.is_set():
                return
            t0 = time.monotonic()
            g = notifier.wait_after(g, 2.0)
            woken.append(time.monotonic() - t0)
            if woken[-1] >= 1.5:
                return  # missed: no point waiting for the rest

    give_up = threading.Event()
    thread = threading.Thread(target=waiter)
    thread.start()
    try:
        for i in range(rounds):
            deadline = time.monotonic() + 5.0
            # until the waiter took the previous notification and waits again
            while (len(woken) < i or notifier._waiting == 0) and thread.is_alive() and time.monotonic() < deadline:
                time.sleep(0)
            notifier.notify()
    finally:
        give_up.set()
        thread.join(5.0)
    assert not thread.is_alive()
    assert len(woken) == rounds and max(woken) < 1.5, "a notification was missed (the wait timed out)"
    assert notifier.generation == 1000 + rounds
