"""The stream bus with a real driver publishing on it (issue #29): every consumer gets a bounded queue whose
drops are counted, only the safety monitor runs on the driver's thread, waiters wake once per read, and a slow
consumer loses only its own oldest items — it never delays the driver or another consumer."""

from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass

import pytest

from app.core.bus import BusItem, Channel, SampleItem, StreamBus, StreamSpec, UpdateNotifier
from app.core.journal import Record
from app.devices.driver import DeviceDriver
from tests.memory_link import MemoryLink

TICKS = "tick.main"
PER_READ = 10  # samples in one read


@dataclass(frozen=True, slots=True)
class Tick:
    n: float


class TickDriver(DeviceDriver):
    """A device whose bytes are little-endian uint32 counters: one sample per 4 bytes."""

    streams = (StreamSpec(TICKS, (Channel("n", "", "Count"),), 1000.0),)

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        for (n,) in struct.iter_unpack("<I", data):
            self.publish(TICKS, t_ns / 1e9, Tick(float(n)))


def reads(count: int, first: int = 0) -> list[bytes]:
    """``count`` reads of PER_READ consecutive counters."""
    return [b"".join(struct.pack("<I", first + k * PER_READ + i) for i in range(PER_READ)) for k in range(count)]


class CountingNotifier(UpdateNotifier):
    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def notify(self) -> None:
        self.calls += 1
        super().notify()


def counts(items: list[BusItem]) -> list[int]:
    return [int(item.sample.n) for item in items if isinstance(item, SampleItem)]


# ---------------------------------------------------------------------------------------------- bounded queues
def test_a_queue_that_is_not_drained_keeps_its_newest_items_and_counts_the_dropped(qtbot) -> None:
    driver = TickDriver("tick", MemoryLink())
    small = driver.bus.subscribe("small", (TICKS,), maxlen=100)
    large = driver.bus.subscribe("large", (TICKS,))
    for data in reads(50):
        driver.transport.push(data)  # type: ignore[attr-defined]
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.total_samples(TICKS) == 500, timeout=5000)
    finally:
        driver.stop()
        small.close()
        large.close()
    assert (small.received, small.dropped) == (500, 400)
    assert counts(small.drain()) == list(range(400, 500)), "the newest items stay, in order"
    assert (large.received, large.dropped) == (500, 0)
    assert counts(large.drain()) == list(range(500))
    assert driver.latest(TICKS) == Tick(499.0)


def test_a_closed_subscription_gets_nothing_more() -> None:
    driver = TickDriver("tick", MemoryLink())
    sub = driver.bus.subscribe("gone", (TICKS,))
    driver.publish(TICKS, 1.0, Tick(1.0))
    sub.close()
    driver.publish(TICKS, 2.0, Tick(2.0))
    assert sub.received == 1 and counts(sub.drain()) == [1]
    assert sub not in driver.bus.subscriptions()


# ---------------------------------------------------------------------------------------------- inline: safety only
@pytest.mark.parametrize("name", ["recorder", "lsl", "script", "assistance", "therapy", "Safety"])
def test_only_the_safety_monitor_may_run_on_a_drivers_thread(name: str) -> None:
    bus = StreamBus()
    with pytest.raises(ValueError, match="may not run on a driver's thread"):
        bus.subscribe_inline(name, lambda _item: None, (TICKS,))


def test_the_safety_monitor_sees_every_sample_on_the_driver_thread_before_publish_returns(qtbot) -> None:
    driver = TickDriver("tick", MemoryLink())
    seen: list[tuple[int, bool, int]] = []  # (count, latest was this sample, thread)

    def monitor(item: BusItem) -> None:
        if isinstance(item, SampleItem):
            seen.append((int(item.sample.n), driver.bus.latest(TICKS) is item.sample, threading.get_ident()))

    driver.bus.subscribe_inline("safety", monitor, (TICKS,))
    driver.publish(TICKS, 0.0, Tick(-1.0))  # outside the loop: on the caller's thread, before publish returns
    assert seen == [(-1, True, threading.get_ident())]
    seen.clear()
    for data in reads(20):
        driver.transport.push(data)  # type: ignore[attr-defined]
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.total_samples(TICKS) == 201, timeout=5000)
    finally:
        driver.stop()
    assert [n for n, _latest, _thread in seen] == list(range(200))
    assert all(latest for _n, latest, _thread in seen)
    threads = {thread for _n, _latest, thread in seen}
    assert len(threads) == 1 and threading.get_ident() not in threads, "on the driver's thread"


def test_a_failing_safety_callback_is_counted_and_the_driver_goes_on(qtbot) -> None:
    driver = TickDriver("tick", MemoryLink())

    def broken(_item: BusItem) -> None:
        raise RuntimeError("a monitor bug")

    sub = driver.bus.subscribe_inline("safety", broken, (TICKS,))
    for data in reads(5):
        driver.transport.push(data)  # type: ignore[attr-defined]
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.total_samples(TICKS) == 50, timeout=5000)
    finally:
        driver.stop()
    assert sub.failures == 50


# ---------------------------------------------------------------------------------------------- wake-ups
def test_waiters_wake_once_per_read_after_its_last_sample() -> None:
    notifier = CountingNotifier()
    driver = TickDriver("tick", MemoryLink(), bus=StreamBus(notifier))
    sub = driver.bus.subscribe("waiter", (TICKS,))
    for k, data in enumerate(reads(30)):
        before = notifier.calls
        assert not sub.wait(0.0)
        driver._take_bytes(driver.on_bytes, data, time.monotonic_ns())  # the loop's path for one read
        assert notifier.calls == before + 1, "one wake-up per read, not one per sample"
        assert sub.wait(0.0)
        assert counts(sub.drain()) == list(range(k * PER_READ, (k + 1) * PER_READ)), "the whole read"
    driver.publish(TICKS, 0.0, Tick(0.0))  # outside a read: at once
    assert notifier.calls == 31


def test_a_device_event_reaches_the_subscribers_that_asked_for_events_and_wakes_waiters(qtbot) -> None:
    notifier = CountingNotifier()
    driver = TickDriver("tick", MemoryLink(), bus=StreamBus(notifier))
    events = driver.bus.subscribe("events", (), events=True)
    samples_only = driver.bus.subscribe("samples", (TICKS,))
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=5000)
    finally:
        driver.stop()
    kinds = [(item.origin, item.kind) for item in events.drain() if isinstance(item, Record)]
    assert kinds == [("tick", "connected"), ("tick", "disconnected")]
    assert samples_only.received == 0
    assert notifier.calls == 2
    assert driver.bus.last_event("tick").kind == "disconnected"


# ---------------------------------------------------------------------------------------------- a slow consumer
@pytest.mark.realtime
def test_a_slow_subscriber_loses_its_own_oldest_items_and_delays_nobody(qtbot) -> None:
    """A consumer that takes 5 ms per item (a stuck recorder, a slow script callback) beside one that keeps up:
    the driver decodes at its own pace, the quick consumer gets every sample, the slow one's queue drops (counted)."""
    driver = TickDriver("tick", MemoryLink())
    slow = driver.bus.subscribe("slow", (TICKS,), maxlen=50)
    quick = driver.bus.subscribe("quick", (TICKS,), maxlen=10_000)
    got_quick: list[int] = []
    got_slow: list[int] = []
    stop = threading.Event()

    def consume(sub, out: list[int], per_item_s: float) -> None:
        while not stop.is_set():
            if not sub.wait(0.05):
                continue
            for item in sub.drain(1 if per_item_s else None):
                out.append(int(item.sample.n))
                if per_item_s:
                    time.sleep(per_item_s)

    threads = [threading.Thread(target=consume, args=(slow, got_slow, 0.005)),
               threading.Thread(target=consume, args=(quick, got_quick, 0.0))]
    for thread in threads:
        thread.start()
    n_reads = 400
    for data in reads(n_reads):
        driver.transport.push(data)  # type: ignore[attr-defined]
    t0 = time.monotonic()
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.total_samples(TICKS) == n_reads * PER_READ, timeout=10000)
        decoded_s = time.monotonic() - t0
        qtbot.waitUntil(lambda: len(got_quick) == n_reads * PER_READ, timeout=5000)
    finally:
        driver.stop()
        stop.set()
        for thread in threads:
            thread.join(5.0)
        slow.close()
        quick.close()
    assert not any(thread.is_alive() for thread in threads)
    # The slow consumer alone would need 4000 × 5 ms = 20 s; the driver did not wait for it.
    assert decoded_s < 5.0, f"the driver took {decoded_s:.2f} s to decode 4000 samples"
    assert got_quick == list(range(n_reads * PER_READ)) and quick.dropped == 0
    assert slow.received == n_reads * PER_READ and slow.dropped > 0
    assert len(got_slow) + slow.dropped + slow.pending() == slow.received
    assert got_slow == sorted(got_slow), "what the slow consumer got is still in order"


def test_closing_a_subscription_wakes_its_waiter() -> None:
    """A consumer blocked in wait() returns when its subscription is closed (a thread's stop does not wait for
    its timeout)."""
    import threading
    import time as _time

    from app.core.bus import StreamBus

    bus = StreamBus()
    sub = bus.subscribe("waiter", [])
    returned: list[tuple[bool, float]] = []

    def wait() -> None:
        t0 = _time.monotonic()
        returned.append((sub.wait(5.0), _time.monotonic() - t0))

    thread = threading.Thread(target=wait)
    thread.start()
    sub.close()  # whether the thread is already waiting or not yet: it must not wait out its 5 s
    thread.join(2.0)
    assert not thread.is_alive()
    assert returned and returned[0][0] is False and returned[0][1] < 2.0
    assert sub.wait(5.0) is False  # closed: no wait at all


def test_resubscribe_changes_the_streams_and_keeps_the_queue() -> None:
    """A script that subscribes to one more stream: what its queue holds stays, in order; a stream it did not
    ask for never reaches it."""
    from types import SimpleNamespace

    from app.core.bus import Channel, StreamBus, StreamSpec

    bus = StreamBus()
    bus.declare([StreamSpec("a.main", (Channel("x", "", "x"),), 10.0),
                 StreamSpec("b.main", (Channel("x", "", "x"),), 10.0)])
    sub = bus.subscribe("script", ["a.main"])
    bus.publish("a.main", 1.0, SimpleNamespace(x=1.0))
    bus.publish("b.main", 2.0, SimpleNamespace(x=2.0))
    bus.resubscribe(sub, ["a.main", "b.main"])
    bus.publish("b.main", 3.0, SimpleNamespace(x=3.0))
    assert [(i.stream, i.t) for i in sub.drain()] == [("a.main", 1.0), ("b.main", 3.0)]
    assert sub.received == 2 and sub.dropped == 0
