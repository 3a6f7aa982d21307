"""The LINarm heartbeat has a path of its own (issue #16): a slow consumer on the reading loop does not delay
the bytes that feed the controller's 250 ms watchdog, and a wedged reading loop stops them (so the
controller's watchdog still acts)."""

from __future__ import annotations

import itertools
import threading
import time

import pytest

from app.core import streams
from app.core.bus import BusItem, SampleItem
from app.core.config import AppConfig
from app.devices import linarm
from app.devices.linarm import HEARTBEAT_READER_GRACE_S
from app.manager import LinarmppManager

pytestmark = pytest.mark.realtime


def _gaps(log: list[tuple[float, bytes]], t0: float, t1: float) -> list[float]:
    """Silences between host writes seen by the simulator from t0 to t1 (the ends count as writes)."""
    times = [t0, *(t for t, _data in list(log) if t0 <= t <= t1), t1]
    return [b - a for a, b in itertools.pairwise(times)]


def test_a_stalled_reading_loop_does_not_delay_the_heartbeat_and_a_wedged_one_stops_it(qtbot) -> None:  # type: ignore[no-untyped-def]
    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create})
    manager.start()
    try:
        robot, sim = manager.driver("linarm"), manager.devices["linarm"].simulator
        qtbot.waitUntil(lambda: robot.connected and robot.latest("linarm.vsa") is not None, timeout=10000)
        sim.keep_host_log = True
        stall = {"s": 0.0}
        released = threading.Event()

        def slow_consumer(item: BusItem) -> None:
            if stall["s"] and isinstance(item, SampleItem) and item.stream == streams.LINARM_VSA:
                seconds, stall["s"] = stall["s"], 0.0
                time.sleep(seconds)  # a consumer that blocks the reading loop (what a starved thread looks like)
                released.set()

        # inline, on the reading loop (only a safety monitor may: what would wedge the loop is a slow one)
        manager.bus.subscribe_inline("safety", slow_consumer, (streams.LINARM_VSA,))
        # 1. the loop stalls 0.4 s (> the 0.25 s watchdog), within the grace: the beats go on
        t0 = time.monotonic()
        stall["s"] = 0.4
        qtbot.waitUntil(released.is_set, timeout=3000)
        t1 = time.monotonic()
        assert max(_gaps(sim.host_bytes_log, t0, t1)) < 0.2, "heartbeats were held up by the reading loop"
        # 2. the loop is wedged beyond the grace: the beats stop, so the controller's watchdog would act
        released.clear()
        t2 = time.monotonic()
        stall["s"] = HEARTBEAT_READER_GRACE_S + 0.6
        qtbot.waitUntil(released.is_set, timeout=5000)
        t3 = time.monotonic()
        assert max(_gaps(sim.host_bytes_log, t2, t3)) > 0.5, "heartbeats went on for a wedged reading loop"
    finally:
        manager.shutdown()
