"""The driver base over a real pty with a simulator thread: data flow, batching, kill/reconnect."""

from __future__ import annotations

import itertools
import threading

import pytest

from app.devices.driver import UpdateNotifier
from app.devices.sim.base import SerialSimulator
from tests.fakes import CounterCore, CounterDriver


@pytest.fixture
def counter(tmp_path, qtbot):
    sim = SerialSimulator("counter", CounterCore, tmp_path / "counter.tty")
    sim.start()
    driver = CounterDriver(sim.url, notifier=UpdateNotifier(), silence_timeout_s=0.05)
    driver.reconnect_backoff_s = (0.05, 0.2)
    events: list[tuple[bool, str]] = []
    driver.connection_changed.connect(lambda ok, why: events.append((ok, why)))
    driver.start()
    yield sim, driver, events
    driver.stop()
    sim.stop()
    assert not driver.isRunning()


def test_samples_arrive_in_batches_in_order(counter, qtbot) -> None:
    _sim, driver, _ = counter
    batches = []
    driver.samples.connect(batches.append)
    qtbot.waitUntil(lambda: sum(len(b["counter.main"]) for b in batches) >= 300, timeout=5000)
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
        qtbot.waitUntil(lambda: any(not ok for ok, _ in events), timeout=3000)  # the queued signal
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
    sim, driver, _ = counter
    qtbot.waitUntil(lambda: driver.connected and driver.total_samples("counter.main") > 10, timeout=3000)
    with qtbot.waitSignal(driver.silence_changed, timeout=3000) as blocker:
        sim.with_core(lambda core: setattr(core, "period_s", 10.0))  # the device stops talking
    assert blocker.args == [True]


def test_stop_is_prompt(counter) -> None:
    import time

    _, driver, _ = counter
    t0 = time.monotonic()
    assert driver.stop(1.0)
    assert time.monotonic() - t0 < 0.5
