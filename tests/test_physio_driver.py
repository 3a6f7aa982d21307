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


def stop_streaming(sim: SerialSimulator) -> None:
    """The board stops making frames, every one it made written, its end of the pty left open."""
    sim.halt()
    assert not sim.running


# How far behind the board the driver may be when looked at: at 100 Hz the 10 frames the 1 % of a 10 s window
# allowed before (now measured as a lag, not as the difference of two lags), at 1000 Hz 100 frames.
KEEP_UP_S = 0.1


@pytest.mark.slow
@pytest.mark.parametrize("rate_hz", [100.0, 1000.0])
def test_frames_arrive_complete_at_rate(tmp_path, qtbot, rate_hz: float) -> None:
    """For 3 s at the board's rate: the driver keeps up (at the window's end it is within KEEP_UP_S of the frames
    the board has sent), and every frame the board sent arrives — counted exactly against the board's own count
    once it stops, none lost, none damaged. (Before: 10 s and 5 s windows whose received count had to be within
    1 % of rate × time; the board makes its frames on the wall clock, so that count only measured the driver's lag
    at both ends — asserted directly now, and completeness exactly instead of within 1 %.)"""
    seconds = 3.0
    _patient, sim, driver = start_pair(tmp_path, rate_hz)
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=3000)
        sim.start()
        qtbot.waitUntil(lambda: driver.decoder.framesDecoded > 0, timeout=3000)
        first = driver.decoder.framesDecoded
        t0 = time.monotonic()
        qtbot.waitUntil(lambda: time.monotonic() - t0 >= seconds, timeout=int(seconds * 1000) + 2000)
        sent = sim.with_core(lambda core: core.source._k)  # frames the board has made by now (on the wall clock)
        decoded = driver.decoder.framesDecoded
        assert sent - decoded <= max(2, KEEP_UP_S * rate_hz), (sent, decoded)
        assert decoded - first >= rate_hz * seconds * 0.9, (first, decoded)  # it streamed all along
        stop_streaming(sim)
        sent = sim.with_core(lambda core: core.source._k)
        drained = time.monotonic() + 3.0
        qtbot.waitUntil(lambda: driver.decoder.framesDecoded >= sent or time.monotonic() > drained, timeout=5000)
        assert driver.decoder.framesDecoded == sent, (driver.decoder.framesDecoded, sent)
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
