"""Physiological driver + simulated board over a real pty."""

from __future__ import annotations

import time

import pytest

from app.core.config import AppConfig
from app.devices.physio import PhysioDriver
from app.devices.sim.adapters import PhysioSimCore
from app.devices.sim.base import SerialSimulator
from app.devices.sim.patient import SimulatedPatient
from app.devices.transport import SerialTransport
from app.wire.physio_codec import Calibration


def start_pair(tmp_path, rate_hz: float):
    patient = SimulatedPatient(seed=3)
    cal = Calibration()
    sim = SerialSimulator("physio", lambda: PhysioSimCore(patient, rate_hz, cal), tmp_path / "physio.tty",
                          tick_s=min(0.005, 0.5 / rate_hz))
    driver = PhysioDriver(SerialTransport(sim.url), cal, silence_timeout_s=0.1)
    driver.start()  # open the port before the board streams (qt-stack.md §3)
    return patient, sim, driver


@pytest.mark.slow
@pytest.mark.parametrize(("rate_hz", "seconds"), [(100.0, 10.0), (1000.0, 5.0)])
def test_frames_arrive_complete_at_rate(tmp_path, qtbot, rate_hz: float, seconds: float) -> None:
    _patient, sim, driver = start_pair(tmp_path, rate_hz)
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=3000)
        sim.start()
        qtbot.waitUntil(lambda: driver.decoder.framesDecoded > 0, timeout=3000)
        first = driver.decoder.framesDecoded
        t0 = time.monotonic()
        qtbot.waitUntil(lambda: time.monotonic() - t0 >= seconds, timeout=int(seconds * 1000) + 2000)
        received = driver.decoder.framesDecoded - first
        expected = rate_hz * seconds
        assert abs(received - expected) <= max(2, 0.01 * expected), (received, expected)
        assert driver.frames_lost == 0
        assert driver.bad_frames == 0
    finally:
        driver.stop()
        sim.stop()


def test_squeeze_crosses_20_newtons_within_half_a_second(tmp_path, qtbot) -> None:
    patient, sim, driver = start_pair(tmp_path, 100.0)
    sim.start()
    try:
        qtbot.waitUntil(lambda: driver.latest("physio.main") is not None, timeout=3000)
        assert driver.latest("physio.main").force < 5.0
        t0 = time.monotonic()
        patient.squeeze(duration=2.0)
        qtbot.waitUntil(lambda: driver.latest("physio.main").force > 20.0, timeout=500)
        assert time.monotonic() - t0 < 0.5
        s = driver.latest("physio.main")
        assert 30.0 <= s.temperature <= 36.0 and s.skinConductance > 0
    finally:
        driver.stop()
        sim.stop()


def test_manager_creates_simulated_physio(qtbot) -> None:
    from app.devices import physio
    from app.manager import LinarmppManager

    manager = LinarmppManager(AppConfig(), factories={"physio": physio.create})
    manager.start()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=3000)
        qtbot.waitUntil(lambda: (manager.driver("physio").latest("physio.main") or None) is not None, timeout=3000)
    finally:
        manager.shutdown()
