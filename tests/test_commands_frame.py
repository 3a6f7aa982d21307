"""Frame 4: a connect/disconnect toggle per device that really stops and restarts its driver (over
a pty), confirmation before disconnecting, and the panels loaded as tabs when present."""

from __future__ import annotations

import sys
import types

from PySide6.QtWidgets import QLabel

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui import commands_frame
from app.ui.commands_frame import CommandsFrame
from tests.fakes import counter_factory


def test_toggle_disconnects_and_reconnects_a_device(qtbot, tmp_path) -> None:
    manager = LinarmppManager(AppConfig(), factories={"alpha": counter_factory(tmp_path, "alpha")})
    manager.start()
    try:
        frame = CommandsFrame(manager)
        qtbot.addWidget(frame)
        driver = manager.devices["alpha"].driver
        qtbot.waitUntil(lambda: driver.connected, timeout=5000)
        frame.refresh()
        toggle = frame.toggles["alpha"]
        assert toggle.isChecked() and "connected" in toggle.toolTip()
        asked: list[str] = []
        frame.confirm = lambda name: asked.append(name) or False  # operator says no
        toggle.click()
        assert asked == ["alpha"] and driver.isRunning() and toggle.isChecked()
        frame.confirm = lambda name: True
        toggle.click()
        assert not driver.isRunning() and not toggle.isChecked() and "disconnected" in toggle.toolTip()
        count = driver.total_samples("counter.main")
        toggle.click()  # connect again
        qtbot.waitUntil(lambda: driver.connected and driver.total_samples("counter.main") > count + 50,
                        timeout=5000)
        assert toggle.isChecked()
    finally:
        manager.shutdown()


def test_panels_load_when_present_and_simulation_only_when_simulated(qtbot, monkeypatch) -> None:
    class FakePanel(QLabel):
        def __init__(self, manager) -> None:
            super().__init__("panel")
            self.manager = manager

    for mod, cls in (("app.ui.fes_panel", "FesPanel"), ("app.ui.simulation_panel", "SimulationPanel")):
        module = types.ModuleType(mod)
        setattr(module, cls, FakePanel)
        monkeypatch.setitem(sys.modules, mod, module)
    manager = LinarmppManager(AppConfig(), factories={})  # no device: nothing is simulated
    frame = CommandsFrame(manager)
    qtbot.addWidget(frame)
    titles = [frame.tabs.tabText(i) for i in range(frame.tabs.count())]
    assert "FES" in titles and "Simulation" not in titles
    assert isinstance(frame.panels["FesPanel"], FakePanel) and frame.no_devices.isVisibleTo(frame)
    assert commands_frame.set_device_running(manager, "nope", True) is False
    manager.shutdown()  # ends the script console's kernel


def test_a_viewer_is_built_when_its_tab_is_first_shown(qtbot) -> None:
    """The viewers (BUILT_WHEN_SHOWN) cost the window's start about a second of CPU for tabs a session may never
    open: each is built on its tab's first showing, once, in the tab, with the window's bus; the panels that act
    are built with the frame."""
    manager = LinarmppManager(AppConfig(), factories={})
    frame = CommandsFrame(manager)
    qtbot.addWidget(frame)
    try:
        titles = [frame.tabs.tabText(i) for i in range(frame.tabs.count())]
        assert {"FesPanel", "ExercisesPanel", "ScriptConsole", "AlarmsPanel"} <= set(frame.panels)
        assert not set(frame.panels) & commands_frame.BUILT_WHEN_SHOWN, sorted(frame.panels)
        frame.tabs.setCurrentIndex(titles.index("Sensors"))
        physio = frame.panels["PhysioViewer"]
        assert frame.tabs.widget(titles.index("Sensors")).isAncestorOf(physio)
        assert physio.qt_bus is frame.qt_bus
        frame.tabs.setCurrentIndex(0)
        frame.tabs.setCurrentIndex(titles.index("Sensors"))
        assert frame.panels["PhysioViewer"] is physio  # once
        frame.build_all_panels()
        assert commands_frame.BUILT_WHEN_SHOWN <= set(frame.panels)
    finally:
        manager.shutdown()
