"""The LINarm viewer: every state quantity with its enum name and colour, both motors and the VSA,
from the real simulated LINarm; greyed 'last known' values when the link is down; colours for an
error state from a stub driver."""

from __future__ import annotations

import pytest

from app.core.bus import StreamBus
from app.core.config import AppConfig
from app.devices import linarm
from app.devices.linarm import LinarmDriver, LinarmStateSample, MotorSample, VsaSample
from app.manager import DeviceHandle, LinarmppManager
from app.ui.linarm_viewer import DASH, STATE_ROWS, LinarmViewer
from app.ui.theme import colours


def _colour(viewer: LinarmViewer, key: str) -> str:
    return viewer.values[key].styleSheet()


def test_shows_every_quantity_of_the_simulated_linarm(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create})
    manager.start()
    try:
        driver = manager.driver("linarm")
        bus = manager.bus
        viewer = LinarmViewer(manager)
        qtbot.addWidget(viewer)
        qtbot.waitUntil(lambda: driver.connected and bus.latest("linarm.vsa") is not None
                        and bus.latest("linarm.motor1") is not None
                        and bus.latest("linarm.state") is not None, timeout=5000)
        viewer.refresh()
        assert viewer.text_of("state.controlState") == "IDLE_CTRL_STATE (0)"
        assert viewer.text_of("state.errorState") == "NO_ERROR (0)"
        assert viewer.text_of("state.homeState") == "HOME_NOT_DONE (0)"
        assert viewer.text_of("state.controlMode") == "POS_REF_BY_VEL (0)"
        assert viewer.text_of("state.initialized") == "no"
        assert colours().ok in _colour(viewer, "state.errorState")
        assert colours().idle in _colour(viewer, "state.controlState")
        for key in viewer.values:
            # Before homing the interaction force (read from the spring elongations) is unknown: "—".
            assert (viewer.text_of(key) == DASH) == (key == "vsa.interactionForce"), key
        vsa = bus.latest("linarm.vsa")
        assert float(viewer.text_of("vsa.stiffness")) == pytest.approx(vsa.stiffness, abs=50)
        assert float(viewer.text_of("vsa.equilibriumPos")) == pytest.approx(vsa.equilibriumPos, abs=0.002)
        m1 = bus.latest("linarm.motor1")
        assert float(viewer.text_of("motor1.position")) == pytest.approx(m1.position, abs=0.002)
        assert "connected" in viewer.header.text() and "Hz" in viewer.header.text()

        driver.stop()
        viewer.refresh()
        assert "disconnected" in viewer.header.text()
        assert viewer.text_of("state.controlState") == "IDLE_CTRL_STATE (0)"  # last known, greyed
        assert colours().idle in _colour(viewer, "state.errorState")
    finally:
        manager.shutdown()


class _FakeLinarm:
    """Duck-typed driver: connected, fixed latest samples (published on the manager's bus)."""

    def __init__(self, samples: dict[str, object]) -> None:
        self.samples = samples
        self.connected = True
        self.silent = False
        self.firmware_version = "test"

    def publish(self, bus: StreamBus) -> None:
        bus.declare(LinarmDriver.streams)
        bus.event("linarm", "connected", "fake link")
        for stream, sample in self.samples.items():
            bus.publish(stream, 12.5, sample)

    def rates(self) -> dict[str, float]:
        return {"linarm.vsa": 200.0}


def test_error_and_homing_colours_and_flags(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    state = LinarmStateSample(controlState=1, controlMode=4, homeState=2, errorState=1, triggerMode=0,
                              initialized=False, trajectoryType=1, demo=True, virtualVsa=False,
                              endstrokesDisabled=True, controllerTime=12.5)
    fake = _FakeLinarm({
        "linarm.state": state,
        "linarm.vsa": VsaSample(0.25, 0.02, 903.0, 0.2312, -0.0425, 3.27, 12.5),
        "linarm.motor0": MotorSample(0, 0.2, 0.0, 0.5, 0.2, 12.5),
        "linarm.motor1": MotorSample(1, 0.3, 0.0, -0.25, 0.3, 12.5),
    })
    manager.devices["linarm"] = DeviceHandle("linarm", fake)  # type: ignore[arg-type]
    fake.publish(manager.bus)
    viewer = LinarmViewer(manager)
    qtbot.addWidget(viewer)
    viewer.refresh()
    c = colours()
    assert viewer.text_of("state.errorState") == "TRACKING_ERROR (1)" and c.bad in _colour(viewer, "state.errorState")
    assert viewer.text_of("state.controlState") == "HOME_CTRL_STATE (1)"
    assert c.warn in _colour(viewer, "state.controlState")
    assert viewer.text_of("state.homeState") == "HOME_SEEK_MAX (2)" and c.warn in _colour(viewer, "state.homeState")
    assert viewer.text_of("state.controlMode") == "POS_REF_BY_ASSISTANCE (4)"
    assert viewer.text_of("state.trajectoryType") == "CYCLOIDAL (1)"
    assert viewer.text_of("state.demo") == "yes" and viewer.text_of("state.endstrokesDisabled") == "yes"
    assert c.bad in _colour(viewer, "state.endstrokesDisabled")
    assert viewer.text_of("vsa.handlePos") == "0.2312" and viewer.text_of("vsa.interactionForce") == "3.27"
    assert viewer.text_of("motor1.current") == "-0.25" and viewer.text_of("state.controllerTime") == "12.500 s"
    assert {f"state.{k}" for k, _l, _e in STATE_ROWS} <= set(viewer.values)


def test_off_shows_dashes(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    viewer = LinarmViewer(manager)
    qtbot.addWidget(viewer)
    assert all(viewer.text_of(k) == DASH for k in viewer.values)
    assert "off" in viewer.header.text()
