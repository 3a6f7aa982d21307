"""Every way out of a stimulation puts Stop on the wire within 50 ms, seen from the simulated device's side.

Exit paths: the stop button, the emergency stop, script end and script error (the runner calls
``bring_to_safe_state``), app close, driver errors (error ack, missing ack, an exception in the driver),
loss of the FES link (SM1: Stop on reconnect; SM2: the device's watchdog), and loss of the LINarm or
physiological link while stimulating.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from types import SimpleNamespace

import pytest

from app.core.config import AppConfig
from app.core.fes_profile import ChannelProfile, FesProfile, Trapezoid
from app.core.journal import Record
from app.devices import rehastim
from app.manager import LinarmppManager
from app.wire.sciencemode import (
    Sm1CommandDecoder,
    Sm1Stop,
    Sm1Update,
    Sm2Decoder,
    Sm2StartChannelListMode,
    Sm2StopChannelListMode,
)
from tests.fakes import counter_factory

WITHIN_S = 0.05
# Stimulates from the first second on and runs far longer than any test.
PROFILE = FesProfile("exit-path profile", "time",
                     {1: ChannelProfile(Trapezoid(10.0, (0.0, 0.25), (100.0, 101.0)),
                                        Trapezoid(150.0, (0.0, 0.25), (100.0, 101.0)))})


def wire(sim, protocol: str) -> list[tuple[float, object]]:
    """(time the device read it, command) for everything the driver sent, decoded as the device does."""
    decoder = Sm1CommandDecoder() if protocol == "sm1" else Sm2Decoder()
    out: list[tuple[float, object]] = []
    for t, data in list(sim.host_bytes_log):
        out += [(t, msg) for msg in decoder.feed(data)]
    return out


def is_stop(msg: object) -> bool:
    return isinstance(msg, Sm1Stop | Sm2StopChannelListMode)


def is_update(msg: object) -> bool:
    return isinstance(msg, Sm1Update | Sm2StartChannelListMode)


def first_stop_after(sim, protocol: str, t0: float) -> float | None:
    return next((t for t, msg in wire(sim, protocol) if t >= t0 and is_stop(msg)), None)


class Setup(SimpleNamespace):
    manager: LinarmppManager
    driver: rehastim.FesDriver


@contextmanager
def stimulating(tmp_path, qtbot, protocol: str = "sm1", links: bool = False) -> Iterator[Setup]:
    config = AppConfig()
    config = replace(config, devices=replace(config.devices, fes=replace(config.devices.fes, protocol=protocol)))
    stamps: dict[tuple[str, str], float] = {}
    factories = {}
    if links:  # stand-ins for the LINarm and the physiological board: real drivers on real ptys
        for name in ("linarm", "physio"):
            base = counter_factory(tmp_path, name)

            def factory(manager, base=base, name=name):  # type: ignore[no-untyped-def]
                handle = base(manager)
                handle.driver.silence_timeout_s = 0.3
                return handle
            factories[name] = factory
    factories["fes"] = rehastim.create
    manager = LinarmppManager(config, factories=factories)
    # When each link event happened (Record.t_mono: stamped as the driver published it, before any consumer).
    link_events = manager.bus.subscribe("test-link-events", [], events=True)

    def stamp(link: str, event: str) -> float | None:
        for item in link_events.drain():
            if isinstance(item, Record):
                stamps.setdefault((item.origin, item.kind), item.t_mono)
        return stamps.get((link, event))

    manager.start()
    try:
        driver = manager.driver("fes")
        sim = manager.devices["fes"].simulator
        assert isinstance(driver, rehastim.FesDriver) and sim is not None
        sim.keep_host_log = True
        faults: list[str] = []
        driver.fault.connect(faults.append)
        qtbot.waitUntil(lambda: driver.device_ready, timeout=3000)
        driver.load_profile(PROFILE)
        driver.start_stimulation("test")
        qtbot.waitUntil(lambda: bool(sim.with_core(lambda c: c.channel_state())), timeout=2000)
        yield Setup(manager=manager, driver=driver, sim=sim, protocol=protocol, faults=faults, stamps=stamps,
                    stamp=stamp)
    finally:
        manager.shutdown()


def assert_stopped_within(s: Setup, qtbot, t0: float, within: float = WITHIN_S) -> None:
    qtbot.waitUntil(lambda: first_stop_after(s.sim, s.protocol, t0) is not None, timeout=2000)
    delay = first_stop_after(s.sim, s.protocol, t0) - t0  # type: ignore[operator]
    assert delay <= within, f"Stop reached the device {delay * 1000:.1f} ms after the exit path"
    assert not s.driver.stimulating
    assert not s.sim.with_core(lambda c: c.channel_state())  # the device delivers nothing


PROTOCOLS = pytest.mark.parametrize("protocol", ["sm1", "sm2"])


@PROTOCOLS
def test_stop_button(tmp_path, qtbot, protocol: str) -> None:
    from app.ui.fes_panel import FesPanel

    with stimulating(tmp_path, qtbot, protocol) as s:
        panel = FesPanel(s.manager)
        qtbot.addWidget(panel)
        assert panel.stop_button.isEnabled()
        t0 = time.monotonic()
        panel.stop_button.click()
        assert_stopped_within(s, qtbot, t0)


@PROTOCOLS
def test_emergency_stop(tmp_path, qtbot, protocol: str) -> None:
    with stimulating(tmp_path, qtbot, protocol) as s:
        t0 = time.monotonic()
        s.manager.supervisor.emergency_stop("test", "pressed")
        assert_stopped_within(s, qtbot, t0)
        with pytest.raises(Exception, match="emergency stop is latched"):
            s.driver.start_stimulation("test")


@pytest.mark.parametrize("reason", ["script finished", "script error: ZeroDivisionError"])
def test_script_end_and_script_error(tmp_path, qtbot, reason: str) -> None:
    with stimulating(tmp_path, qtbot) as s:
        t0 = time.monotonic()
        s.manager.supervisor.bring_to_safe_state(reason)  # what the script runner calls
        assert_stopped_within(s, qtbot, t0)


@PROTOCOLS
def test_app_close(tmp_path, qtbot, protocol: str) -> None:
    with stimulating(tmp_path, qtbot, protocol) as s:
        t0 = time.monotonic()
        s.manager.shutdown()
        delay = first_stop_after(s.sim, protocol, t0)
        assert delay is not None and delay - t0 <= WITHIN_S
        assert not s.sim.with_core(lambda c: c.channel_state())


@PROTOCOLS
def test_driver_error_ack(tmp_path, qtbot, protocol: str) -> None:
    with stimulating(tmp_path, qtbot, protocol) as s:
        t_inject = time.monotonic()
        s.sim.with_core(lambda c: c.inject_error_ack(1))
        qtbot.waitUntil(lambda: bool(s.faults), timeout=1000)
        refused = next(t for t, msg in wire(s.sim, protocol) if t >= t_inject and is_update(msg))
        assert_stopped_within(s, qtbot, refused)
        assert "refused the update" in s.faults[0]


@PROTOCOLS
def test_driver_missing_ack(tmp_path, qtbot, protocol: str) -> None:
    with stimulating(tmp_path, qtbot, protocol) as s:
        t_inject = time.monotonic()
        s.sim.with_core(lambda c: c.inject_no_ack(1))
        qtbot.waitUntil(lambda: bool(s.faults), timeout=2000)
        lost = next(t for t, msg in wire(s.sim, protocol) if t >= t_inject and is_update(msg))
        assert_stopped_within(s, qtbot, lost + s.driver.ack_timeout_s)
        assert "did not acknowledge the update" in s.faults[0]


def test_driver_failure(tmp_path, qtbot, monkeypatch) -> None:
    with stimulating(tmp_path, qtbot) as s:
        failed: list[float] = []

        def broken_update(now: float) -> None:
            failed.append(time.monotonic())
            raise RuntimeError("a bug in the update loop")

        monkeypatch.setattr(s.driver, "_update", broken_update)
        qtbot.waitUntil(lambda: bool(failed), timeout=1000)
        assert_stopped_within(s, qtbot, failed[0])
        qtbot.waitUntil(lambda: bool(s.faults), timeout=1000)
        assert "link was lost" in s.faults[0]


def test_sm1_link_loss_stops_on_reconnect(tmp_path, qtbot) -> None:
    """SM1 has no watchdog: a device that kept stimulating after the cable was pulled is stopped as soon
    as the link is back, before anything else is sent."""
    with stimulating(tmp_path, qtbot, "sm1") as s:
        s.sim.kill()
        qtbot.waitUntil(lambda: bool(s.faults), timeout=2000)
        assert "FES link was lost while stimulating" in s.faults[0]
        assert s.sim.with_core(lambda c: c.running)  # the device does not know
        t_restart = time.monotonic()
        s.sim.restart(fresh_state=False)
        qtbot.waitUntil(lambda: not s.sim.with_core(lambda c: c.running), timeout=4000)
        after = [msg for t, msg in wire(s.sim, "sm1") if t >= t_restart]
        assert is_stop(after[0])  # the first thing the driver sends on the new link
        assert not s.sim.with_core(lambda c: c.channel_state())


def test_sm2_link_loss_the_device_watchdog_stops(tmp_path, qtbot, monkeypatch) -> None:
    with stimulating(tmp_path, qtbot, "sm2") as s:
        def lost(data: bytes) -> None:
            raise OSError("the USB cable was pulled")

        monkeypatch.setattr(s.driver.transport, "write", lost)
        t0 = time.monotonic()
        qtbot.waitUntil(lambda: not s.sim.with_core(lambda c: c.running), timeout=2000)
        assert time.monotonic() - t0 <= 1.2 + 0.1  # SM2_WATCHDOG_TIMEOUT_S + one device tick
        assert s.sim.with_core(lambda c: c.watchdog_expiries) == 1


@pytest.mark.parametrize(("link", "event"), [("linarm", "disconnected"), ("physio", "silent")])
def test_losing_the_linarm_or_physio_link_stops(tmp_path, qtbot, link: str, event: str) -> None:
    with stimulating(tmp_path, qtbot, links=True) as s:
        handle = s.manager.devices[link]
        if event == "disconnected":
            handle.simulator.kill()
        else:  # the board stops streaming but the link stays up
            handle.simulator.with_core(lambda c: setattr(c, "period_s", 1e6))
        qtbot.waitUntil(lambda: s.stamp(link, event) is not None, timeout=2000)
        assert_stopped_within(s, qtbot, s.stamps[(link, event)])
        # Either the FES driver's own link watch or, first, the fault policy (a lost LINarm is a STOP alarm,
        # issue #17) stopped it; either way the cause is on record.
        policy = s.manager.fault_policy
        qtbot.waitUntil(lambda: bool(s.faults) or bool(policy.faults), timeout=1000)
        assert (s.faults and "while stimulating" in s.faults[0]) or link in policy.last_cause
