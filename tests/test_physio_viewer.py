"""The physiological sensors viewer: values with units from the real simulated board, a squeeze in
the force value, lost / bad-CRC / discarded counters from a board that drops and corrupts frames,
fault flags in words, the calibration in use, the live traces, and the 'not connected' states."""

from __future__ import annotations

import dataclasses
import math

import pytest

from app.core.bus import StreamBus
from app.core.config import AppConfig, PhysioCalibration
from app.devices import physio
from app.devices.physio import PHYSIO_STREAM
from app.devices.sim.adapters import PhysioSimCore
from app.manager import DeviceHandle, LinarmppManager
from app.ui.physio_viewer import DASH, PULSE_SUBSCRIBER, TILE_ORDER, PhysioViewer, fault_words, format_value
from app.ui.theme import colours
from app.wire.physio_codec import (
    FLAG_ADC_OVERRUN,
    FLAG_FORCE_FAULT,
    FLAG_PPG_FAULT,
    PHYSIO_FRAME_SIZE,
    Calibration,
    PhysioSample,
)


class GlitchyBoard:
    """The simulated board's core, with a faulty cable on demand: drop whole frames, or flip a
    byte inside one (its CRC then fails)."""

    def __init__(self, core: PhysioSimCore) -> None:
        self.core = core
        self.source = core.source
        self.drop = 0
        self.corrupt = 0

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        return self.core.handle_host_bytes(data, t)

    def poll(self, t: float) -> bytes:
        out = bytearray(self.core.poll(t))  # whole frames only
        while self.drop and out:
            del out[:PHYSIO_FRAME_SIZE]
            self.drop -= 1
        if self.corrupt and out:
            out[6] ^= 0xFF  # skin-conductance byte: header intact, CRC wrong
            self.corrupt -= 1
        return bytes(out)


def _glitchy_physio(manager: LinarmppManager) -> DeviceHandle | None:
    handle = physio.create(manager)
    assert handle is not None and handle.simulator is not None
    handle.simulator.core = GlitchyBoard(handle.simulator.core)  # type: ignore[arg-type]
    return handle


def _points(viewer: PhysioViewer, trace: str) -> int:
    t, _y = viewer.curves[trace].getData()
    return 0 if t is None else len(t)


def _config(force_gain: float = 0.025) -> AppConfig:
    cfg = AppConfig()
    cal = PhysioCalibration(force_gain=force_gain)
    devices = dataclasses.replace(cfg.devices, physio=dataclasses.replace(cfg.devices.physio, calibration=cal))
    return dataclasses.replace(cfg, devices=devices)


def test_live_values_squeeze_counters_faults_and_calibration(qtbot) -> None:
    manager = LinarmppManager(_config(force_gain=0.03), factories={"physio": _glitchy_physio})
    manager.start()
    try:
        driver = manager.driver("physio")
        sim = manager.devices["physio"].simulator
        board: GlitchyBoard = sim.core  # type: ignore[assignment]
        viewer = PhysioViewer(manager)
        qtbot.addWidget(viewer)
        viewer.resize(680, 380)
        viewer.show()
        qtbot.waitUntil(lambda: viewer.text_of("force") != DASH, timeout=5000)

        # Values with their units (from the stream spec), within the simulated patient's ranges.
        assert [viewer.unit_of(n) for n in TILE_ORDER] == ["N", "bpm", "µS", "°C"]
        assert 32.0 <= float(viewer.text_of("temperature")) <= 34.5
        assert float(viewer.text_of("skinConductance")) > 0.0
        assert float(viewer.text_of("force")) < 5.0
        assert "connected" in viewer.header.text() and "not connected" not in viewer.header.text()
        assert viewer.text_of("faults") == "none" and viewer.colour_of("faults") == colours().ok
        # The calibration in use (force gain from the configuration), with units.
        assert viewer.text_of("cal.force.gain") == "0.03 N/count"
        assert viewer.text_of("cal.temperature.gain") == "0.01 °C/count"
        assert viewer.text_of("cal.temperature.offset") == "+10 °C"
        assert viewer.text_of("cal.skinConductance.offset") == "+0 µS"

        # A squeeze shows in the force value within a second (refreshed by the viewer's own timer).
        manager.sim_patient().squeeze(duration=2.0)
        qtbot.waitUntil(lambda: float(viewer.text_of("force")) > 20.0, timeout=1500)

        # Frame rate near the board's 100 Hz once the first rate window has closed.
        qtbot.waitUntil(lambda: viewer.text_of("rate") != "0.0 Hz", timeout=3000)
        assert 50.0 <= float(viewer.text_of("rate").removesuffix(" Hz")) <= 150.0
        assert int(viewer.text_of("decoded")) > 0
        assert (viewer.text_of("lost"), viewer.text_of("bad"), viewer.text_of("discarded")) == ("0", "0", "0")

        # Three frames dropped on the cable, then one corrupted: counted and shown, in amber.
        sim.with_core(lambda _c: setattr(board, "drop", 3))
        qtbot.waitUntil(lambda: viewer.text_of("lost") == "3", timeout=2000)
        sim.with_core(lambda _c: setattr(board, "corrupt", 1))
        qtbot.waitUntil(lambda: viewer.text_of("bad") == "1", timeout=2000)
        qtbot.waitUntil(lambda: viewer.text_of("lost") == "4", timeout=2000)  # the corrupted frame is lost too
        assert int(viewer.text_of("discarded")) >= PHYSIO_FRAME_SIZE
        assert viewer.colour_of("lost") == colours().warn and viewer.colour_of("bad") == colours().warn
        assert viewer.text_of("lost") == str(driver.frames_lost) and viewer.text_of("bad") == str(driver.bad_frames)

        # The heart rate locks (bpm, whole numbers) and its trace and the pulse waveform are drawn.
        qtbot.waitUntil(lambda: viewer.text_of("heartRate") != DASH, timeout=10000)
        assert 50 <= int(viewer.text_of("heartRate")) <= 110
        qtbot.waitUntil(lambda: _points(viewer, "ppg") > 100, timeout=2000)
        for name in TILE_ORDER:
            t, _y = viewer.curves[name].getData()
            assert t is not None and len(t) > 10 and -10.5 <= t[0] and t[-1] == 0.0, name

        # A fault flag set on the board is shown in words, the heart-rate value in red.
        sim.with_core(lambda c: c.source.set_fault_flags(FLAG_PPG_FAULT))
        qtbot.waitUntil(lambda: viewer.text_of("faults") == "pulse probe off", timeout=2000)
        assert viewer.colour_of("faults") == colours().bad
        assert viewer.colour_of("heartRate") == colours().bad and viewer.colour_of("force") == colours().text
        # With the probe off no beat comes: after the detector's timeout the rate is a dash.
        qtbot.waitUntil(lambda: viewer.text_of("heartRate") == DASH, timeout=6000)

        driver.stop()
        viewer.refresh()
        assert "not connected" in viewer.header.text()
        assert viewer.text_of("temperature") != DASH  # last known, greyed
        assert viewer.colour_of("temperature") == colours().idle
    finally:
        manager.shutdown()


class _FakePhysio:
    """Duck-typed driver: connected, one fixed sample (published on the manager's bus), fixed counters."""

    streams = (PHYSIO_STREAM,)

    def __init__(self, sample: PhysioSample) -> None:
        self.sample = sample
        self.connected = True
        self.silent = False
        self.calibration = Calibration()
        self.decoder = type("D", (), {"framesDecoded": 5000, "framesLost": 0, "badFrames": 2,
                                      "discardedBytes": 40, "seqDiscontinuities": 1})()

    def publish(self, bus: StreamBus) -> None:
        bus.declare(self.streams)
        bus.event("physio", "connected", "fake link")
        bus.publish("physio.main", 1.0, self.sample)

    def rates(self) -> dict[str, float]:
        return {"physio.main": 60.0}


def _pulse_subscriptions(manager: LinarmppManager) -> int:
    return sum(sub.name == PULSE_SUBSCRIBER for sub in manager.bus.subscriptions())


def test_no_lock_faults_and_slow_rate_from_a_stub(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    sample = PhysioSample(seq=7, timestamp=1.0, boardTime=0.07, force=-0.01, temperature=33.456,
                          heartRate=math.nan, skinConductance=4.5, ppg=0,
                          flags=FLAG_FORCE_FAULT | FLAG_ADC_OVERRUN | 0x80, lostBefore=0)
    fake = _FakePhysio(sample)
    manager.devices["physio"] = DeviceHandle("physio", fake)  # type: ignore[arg-type]
    fake.publish(manager.bus)
    viewer = PhysioViewer(manager)
    qtbot.addWidget(viewer)
    c = colours()
    assert viewer.text_of("heartRate") == DASH  # no beat lock yet
    assert viewer.text_of("force") == "0.0" and viewer.text_of("temperature") == "33.46"
    assert viewer.text_of("skinConductance") == "4.50"
    assert viewer.text_of("faults") == "grip sensor fault, ADC overrun, reserved bits 0x80"
    assert viewer.colour_of("force") == c.bad and viewer.colour_of("temperature") == c.text
    assert viewer.text_of("rate") == "60.0 Hz" and viewer.colour_of("rate") == c.warn  # below 100 Hz
    assert (viewer.text_of("decoded"), viewer.text_of("bad"), viewer.text_of("discarded")) == ("5000", "2", "40")
    assert viewer.text_of("discontinuities") == "1" and viewer.colour_of("lost") == c.text
    assert _pulse_subscriptions(manager) == 1  # the pulse tap
    manager.devices.clear()  # the device goes away: the viewer lets go of it
    viewer.refresh()
    assert _pulse_subscriptions(manager) == 0 and "not connected" in viewer.header.text()


def test_off_shows_not_connected_and_dashes(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    viewer = PhysioViewer(manager)
    qtbot.addWidget(viewer)
    assert "not connected" in viewer.header.text()
    assert all(viewer.text_of(k) == DASH for k in viewer.values)


@pytest.mark.parametrize(("flags", "words"), [
    (0, []), (FLAG_PPG_FAULT, ["pulse probe off"]),
    (0x1F, ["pulse probe off", "skin-conductance electrodes off", "temperature probe fault",
            "grip sensor fault", "ADC overrun"]),
    (0x20, ["reserved bits 0x20"]),
])
def test_fault_words(flags: int, words: list[str]) -> None:
    assert fault_words(flags) == words


def test_format_value() -> None:
    assert format_value(math.nan, 0) == DASH and format_value(None, 1) == DASH
    assert format_value(-0.04, 1) == "0.0" and format_value(72.6, 0) == "73"
