"""Drivers take their transport as an argument (#16): here they run on an in-memory link whose far end is a
simulator core on the test's own clock — no pty, no socket, no simulator thread, so what is tested is the
driver's logic, not the machine's timing."""

from __future__ import annotations

from typing import Any

import pytest

from app.core.config import SafetyConfig
from app.devices.linarm import LinarmDriver
from app.devices.physio import PhysioDriver
from app.devices.sim.linarm_model import LinarmSimCore
from app.devices.sim.patient import SimulatedPatient
from app.devices.sim.physio_signals import PhysioSimSource
from app.safety.supervisor import SafetyError, SafetySupervisor
from app.wire.physio_codec import Calibration
from tests.memory_link import MemoryLink


@pytest.fixture
def stopped() -> Any:
    drivers: list[Any] = []
    yield drivers.append
    for d in drivers:
        assert d.stop(5.0)


def test_physio_driver_decodes_ten_virtual_seconds_delivered_at_once(qtbot, stopped) -> None:  # type: ignore[no-untyped-def]
    cal = Calibration()
    source = PhysioSimSource(SimulatedPatient(), seed=3, rate_hz=100.0, calibration=cal, start_time=0.0)
    link = MemoryLink()
    driver = PhysioDriver(link, cal)
    stopped(driver)
    driver.start()
    qtbot.waitUntil(lambda: driver.connected, timeout=5000)
    stream = source.frames_until(10.0)  # the board's 10 s, on the test's clock
    frames = len(stream) // 20
    assert frames >= 1000 and len(stream) == 20 * frames
    for i in range(0, len(stream), 777):  # arbitrary chunking, as a USB-serial adapter delivers it
        link.push(stream[i:i + 777])
    qtbot.waitUntil(lambda: driver.total_samples("physio.main") == frames, timeout=5000)
    assert driver.frames_lost == 0 and driver.bad_frames == 0
    last = driver.latest("physio.main")
    assert last.boardTime == pytest.approx(source_board_time(last.seq), abs=0.002)


def source_board_time(seq: int) -> float:
    return seq * 0.010  # 100 Hz: the board's tick advances 10 ms per frame


def test_linarm_driver_identifies_and_commands_through_an_in_memory_link(qtbot, stopped) -> None:  # type: ignore[no-untyped-def]
    core = LinarmSimCore(start_homed=True, initial_centre=0.10)
    clock = [0.0]
    link = MemoryLink(lambda data: core.handle_host_bytes(data, clock[0]))
    supervisor = SafetySupervisor(SafetyConfig())
    driver = LinarmDriver(link, supervisor, command_timeout_s=2.0)
    stopped(driver)
    driver.start()
    qtbot.waitUntil(lambda: driver.connected and driver.firmware_version != "", timeout=5000)
    assert link.written[0].startswith(b";0,")  # parser flush, then identify (command 0)

    before = len(link.written)
    with pytest.raises(SafetyError):  # far outside the rail: refused by the supervisor, nothing written
        driver.command("moveCentreTo", 5.0, 0.2, 0.2, 0.0, False, source="test")
    assert not any(w.startswith(b"9,") for w in link.written[before:])

    reply = driver.command("getIsInitialized", source="test")  # an ACK through the link, decoded
    assert reply["initialized"] is True
    clock[0] = 0.005
    link.push(core.stream_bytes(clock[0]))  # the controller's stream, on the test's clock
    qtbot.waitUntil(lambda: driver.latest("linarm.vsa") is not None, timeout=5000)
    assert driver.latest("linarm.vsa").equilibriumPos == pytest.approx(0.10, abs=1e-3)
