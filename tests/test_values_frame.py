"""Frame 1: values with units from the bus's latest samples, "—" when absent, state colours,
active FES channels only, device indicators. Also home of the stub devices the other frame
tests use (devices with the real stream names that publish synthetic samples on the manager's bus on demand)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from app.core.bus import Channel, StreamBus, StreamSpec
from app.core.config import AppConfig
from app.manager import DeviceHandle, LinarmppManager
from app.ui.theme import colours
from app.ui.values_frame import DASH, ValuesFrame, enum_name

STREAMS: dict[str, StreamSpec] = {
    "linarm.state": StreamSpec("linarm.state", tuple(Channel(n, "", n) for n in (
        "controlState", "controlMode", "homeState", "errorState", "triggerMode", "initialized")), 200.0),
    "linarm.vsa": StreamSpec("linarm.vsa", (
        Channel("equilibriumPos", "m", "Centre"), Channel("delta", "m", "Delta"),
        Channel("stiffness", "N/m", "Stiffness"), Channel("handlePos", "m", "Handle position"),
        Channel("handleVel", "m/s", "Handle velocity"), Channel("interactionForce", "N", "Interaction force")),
        200.0),
    "linarm.motor0": StreamSpec("linarm.motor0", (
        Channel("position", "m", "Motor 0 position"), Channel("velocity", "m/s", "Motor 0 velocity"),
        Channel("current", "A", "Motor 0 current"), Channel("target", "m", "Motor 0 target")), 200.0),
    "linarm.motor1": StreamSpec("linarm.motor1", (
        Channel("position", "m", "Motor 1 position"), Channel("velocity", "m/s", "Motor 1 velocity"),
        Channel("current", "A", "Motor 1 current"), Channel("target", "m", "Motor 1 target")), 200.0),
    "physio.main": StreamSpec("physio.main", (
        Channel("heartRate", "bpm", "Heart rate"), Channel("skinConductance", "µS", "Skin conductance"),
        Channel("temperature", "°C", "Skin temperature"), Channel("force", "N", "Grip force")), 100.0),
    "fes.channels": StreamSpec("fes.channels", tuple(
        [Channel(f"current{i}", "mA", f"Current {i}") for i in range(1, 9)]
        + [Channel(f"pulseWidth{i}", "µs", f"Pulse width {i}") for i in range(1, 9)]), 40.0),
    "patient_model.main": StreamSpec("patient_model.main", tuple(
        Channel(n, "", n) for n in ("alpha", "a_r", "a_f", "tpi", "mpi", "pti")), 100.0),
    "vr.main": StreamSpec("vr.main", (
        Channel("targetPos", "m", "Target position"), Channel("score", "", "Score"),
        Channel("targetsReached", "", "Targets reached")), 50.0),
}


class StubDriver:
    """A device without a thread or a link: tests publish its samples and link events on the bus by hand. It
    answers what the window still asks a driver (rates, whether its thread runs)."""

    def __init__(self, name: str, streams: tuple[StreamSpec, ...], bus: StreamBus) -> None:
        self.name = name
        self.streams = streams
        self.bus = bus
        bus.declare(streams)
        self.set_connected(True)

    def set_connected(self, connected: bool, reason: str = "") -> None:
        self.connected = connected
        self.bus.event(self.name, "connected" if connected else "disconnected",
                       reason or ("stub link" if connected else "stub unplugged"))

    def put(self, stream: str, t: float, **values: float) -> None:
        spec = next(s for s in self.streams if s.name == stream)
        full = {c.name: values.get(c.name, 0.0) for c in spec.channels}
        self.bus.publish(stream, t, SimpleNamespace(**full))

    def rates(self) -> dict[str, float]:
        return {s.name: s.nominal_rate_hz for s in self.streams}

    def isRunning(self) -> bool:
        return False


def make_stub_manager(devices: tuple[str, ...] = ("linarm", "physio", "fes", "patient_model", "vr"),
                      ) -> tuple[LinarmppManager, dict[str, StubDriver]]:
    manager = LinarmppManager(AppConfig(), factories={})
    drivers: dict[str, StubDriver] = {}
    for dev in devices:
        specs = tuple(s for name, s in STREAMS.items() if name.split(".")[0] == dev)
        drivers[dev] = StubDriver(dev, specs, manager.bus)
        manager.devices[dev] = DeviceHandle(dev, drivers[dev], extras={"simulated": True})
    return manager, drivers


def publish_scene(drivers: dict[str, Any], t: float = 1.0) -> None:
    """A plausible instant: handle at 0.231 m, two FES channels on, an error latched."""
    d = drivers
    d["linarm"].put("linarm.vsa", t, equilibriumPos=0.25, delta=0.012, stiffness=850.0, handlePos=0.231,
                    handleVel=-0.0425, interactionForce=3.27)
    d["linarm"].put("linarm.motor0", t, position=0.16)
    d["linarm"].put("linarm.motor1", t, position=0.34)
    d["linarm"].put("linarm.state", t, controlState=2, controlMode=2, errorState=3)
    d["physio"].put("physio.main", t, heartRate=72.4, skinConductance=4.567, temperature=33.21, force=12.34)
    d["fes"].put("fes.channels", t, current1=12.0, pulseWidth1=200.0, current3=8.5, pulseWidth3=0.0,
                 current5=20.0, pulseWidth5=250.0)
    d["patient_model"].put("patient_model.main", t, alpha=0.5, a_r=0.25, a_f=0.75)
    d["vr"].put("vr.main", t, targetPos=0.3)


def test_values_show_units_states_and_active_fes_channels(qtbot) -> None:
    manager, drivers = make_stub_manager()
    frame = ValuesFrame(manager)
    qtbot.addWidget(frame)
    assert frame.text_of("linarm.vsa", "handlePos") == DASH  # nothing published yet
    publish_scene(drivers)
    frame.refresh()
    assert frame.text_of("linarm.vsa", "handlePos") == "0.231 m"
    assert frame.text_of("linarm.vsa", "handleVel") == "-0.043 m/s"
    assert frame.text_of("linarm.vsa", "interactionForce") == "3.3 N"
    assert frame.text_of("linarm.vsa", "stiffness") == "850 N/m"
    assert frame.text_of("physio.main", "heartRate") == "72 bpm"
    assert frame.text_of("physio.main", "skinConductance") == "4.57 µS"
    assert frame.text_of("physio.main", "temperature") == "33.2 °C"
    assert frame.text_of("physio.main", "force") == "12.3 N"
    assert frame.text_of("patient_model.main", "a_f") == "0.75"
    # Only channels with current AND pulse width > 0 are listed.
    assert frame.active_fes_texts() == ["Ch 1:  12.0 mA · 200 µs", "Ch 5:  20.0 mA · 250 µs"]
    assert frame.state_text("controlState").startswith("On")
    assert frame.state_text("controlMode").startswith("Impedance")
    assert "Over force" in frame.state_text("errorState")
    assert colours().bad in frame.state_tiles["errorState"].value.styleSheet()
    assert colours().ok in frame.state_tiles["controlState"].value.styleSheet()
    device_text = frame.device_labels["linarm"].text()
    assert "linarm" in device_text and "Hz" in device_text and colours().ok in device_text


def test_absent_and_disconnected_devices_show_dashes(qtbot) -> None:
    manager, drivers = make_stub_manager(("linarm",))
    publish_scene_subset = drivers["linarm"]
    publish_scene_subset.put("linarm.vsa", 1.0, handlePos=0.2)
    frame = ValuesFrame(manager)
    qtbot.addWidget(frame)
    assert frame.text_of("linarm.vsa", "handlePos") == "0.200 m"
    assert frame.text_of("physio.main", "heartRate") == DASH  # no physio device at all
    assert frame.active_fes_texts() == []
    drivers["linarm"].set_connected(False)
    frame.refresh()
    assert frame.text_of("linarm.vsa", "handlePos") == DASH  # stale values are not shown
    assert "disconnected" in frame.device_labels["linarm"].text()


def test_enum_names_fall_back_to_numbers() -> None:
    assert enum_name("CONTROL_STATES", 0).startswith("Idle")
    assert enum_name("CONTROL_STATES", 99) == "99"
    assert enum_name("NO_SUCH_ENUM", 2) == "2"
    assert enum_name("ERROR_STATES", None) == DASH


def test_values_frame_renders_readably(qtbot, tmp_path) -> None:
    manager, drivers = make_stub_manager()
    publish_scene(drivers)
    frame = ValuesFrame(manager)
    qtbot.addWidget(frame)
    frame.resize(560, 700)
    frame.show()
    qtbot.waitExposed(frame)
    image = frame.grab().toImage()
    pixels = np.array([image.pixel(x, y) for x in range(0, image.width(), 7) for y in range(0, image.height(), 7)])
    assert len(np.unique(pixels)) > 10
    # Values are large: at least 20 px tall text for the main quantities.
    assert frame.tiles[("linarm.vsa", "handlePos")].value.fontMetrics().height() >= 20


def test_the_values_follow_at_10_hz_when_shown_and_not_at_all_when_hidden(qtbot) -> None:
    from PySide6.QtCore import Qt
    from PySide6.QtWidgets import QDockWidget, QMainWindow

    manager, drivers = make_stub_manager()
    window = QMainWindow()
    frame = ValuesFrame(manager)
    dock = QDockWidget("Values")
    dock.setWidget(frame)
    window.addDockWidget(Qt.DockWidgetArea.LeftDockWidgetArea, dock)
    qtbot.addWidget(window)
    window.resize(900, 700)
    window.show()
    qtbot.waitExposed(window)
    publish_scene(drivers)
    qtbot.waitUntil(lambda: frame.text_of("linarm.vsa", "handlePos") == "0.231 m", timeout=1000)  # by its timer
    dock.hide()  # a closed dock: its values are not refreshed
    drivers["linarm"].put("linarm.vsa", 2.0, handlePos=0.3, handleVel=0.0, interactionForce=0.0, stiffness=0.0,
                          equilibriumPos=0.3, delta=0.0)
    qtbot.wait(3 * frame.timer.interval())
    frame._tick()
    assert frame.text_of("linarm.vsa", "handlePos") == "0.231 m"
    dock.show()  # shown again: up to date at once
    assert frame.text_of("linarm.vsa", "handlePos") == "0.300 m"
