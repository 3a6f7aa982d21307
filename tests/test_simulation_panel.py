"""The simulation panel drives the one simulated patient: its Squeeze makes the grip force measured
by the (real, simulated) physiological board rise; bad input changes nothing; fault flags reach
the board; kill / restart unplug and plug a simulated device."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from PySide6.QtCore import Qt

from app.core.config import AppConfig
from app.devices import linarm, physio
from app.devices.sim.patient import GripMode, HandleMode
from app.manager import LinarmppManager
from app.ui.simulation_panel import SimulationPanel, parse_positions
from app.wire.physio_codec import FLAG_PPG_FAULT


@pytest.fixture
def manager(qtbot) -> Iterator[LinarmppManager]:
    m = LinarmppManager(AppConfig(), factories={"linarm": linarm.create, "physio": physio.create})
    m.start()
    qtbot.waitUntil(lambda: m.all_connected() and m.bus.latest("physio.main") is not None,
                    timeout=5000)
    yield m
    m.shutdown()


def _panel(qtbot, manager: LinarmppManager) -> SimulationPanel:
    panel = SimulationPanel(manager)
    qtbot.addWidget(panel)
    panel.resize(680, 380)  # the commands frame's size in a 1366×768 window
    panel.show()
    qtbot.waitExposed(panel)
    return panel


def test_squeeze_makes_the_measured_grip_force_rise(qtbot, manager) -> None:
    panel = _panel(qtbot, manager)
    assert panel.patient is manager.patient
    assert panel.grip_force_now() < 5.0  # resting hand
    panel.squeeze_duration.setValue(2.0)
    qtbot.mouseClick(panel.squeeze_button, Qt.MouseButton.LeftButton)
    assert manager.patient.settings().gripMode is GripMode.SQUEEZE
    qtbot.waitUntil(lambda: (panel.grip_force_now() or 0.0) > 20.0, timeout=3000)
    panel.refresh()
    assert "grip force now" in panel.summary.text() and "squeeze 2.00 s" in panel.summary.text()
    qtbot.mouseClick(panel.grip_idle, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: (panel.grip_force_now() or 99.0) < 5.0, timeout=3000)


def test_periodic_targets_and_handle_behaviours_reach_the_patient(qtbot, manager) -> None:
    panel = _panel(qtbot, manager)
    panel.period.setValue(3.0)
    panel.duty.setValue(40)
    assert panel.squeeze_periodically()
    s = manager.patient.settings()
    assert s.gripMode is GripMode.PERIODIC and s.period == 3.0 and s.duty == pytest.approx(0.4)
    panel.targets.setText("0.12; 0.30 0.4")
    assert panel.squeeze_at_targets()
    assert manager.patient.settings().targets == (0.12, 0.30, 0.4)
    panel.push_target.setValue(0.3)
    panel.push_force.setValue(12.0)
    assert panel.push_to()
    s = manager.patient.settings()
    assert s.handleMode is HandleMode.PUSH and s.handleTarget == 0.3 and s.pushForce == 12.0
    panel.fraction.setValue(0.3)
    assert panel.fail_weak() and manager.patient.settings().weakFraction == pytest.approx(0.3)
    assert panel.fail_stop_early() and manager.patient.settings().handleMode is HandleMode.STOP_EARLY
    qtbot.mouseClick(panel.passive_button, Qt.MouseButton.LeftButton)
    assert manager.patient.settings().handleMode is HandleMode.PASSIVE


def test_bad_target_list_is_reported_and_nothing_changes(qtbot, manager) -> None:
    panel = _panel(qtbot, manager)
    before = manager.patient.settings()
    panel.targets.setText("0.15, abc")
    qtbot.mouseClick(panel.target_button, Qt.MouseButton.LeftButton)
    assert "not a number" in panel.message.text() and "Not applied" in panel.message.text()
    assert manager.patient.settings() == before
    with pytest.raises(ValueError, match="off the rail"):
        parse_positions("0.2, 0.9")
    with pytest.raises(ValueError):
        parse_positions(" , ")


@pytest.mark.sim_in_thread  # looks at the simulated board's core
def test_fault_flag_reaches_the_simulated_board(qtbot, manager) -> None:
    panel = _panel(qtbot, manager)
    sim = manager.devices["physio"].simulator
    panel.fault_checks[FLAG_PPG_FAULT].click()
    assert panel.fault_flags() == FLAG_PPG_FAULT
    qtbot.waitUntil(lambda: sim.with_core(lambda core: core.source.last.get("ppg")) == 0.0, timeout=2000)
    assert panel.phasic_event()


def test_kill_and_restart_a_simulated_device(qtbot, manager) -> None:
    panel = _panel(qtbot, manager)
    assert set(panel.sim_buttons) == {"linarm", "physio"}
    kill, restart, status = panel.sim_buttons["physio"]
    driver = manager.driver("physio")
    qtbot.mouseClick(kill, Qt.MouseButton.LeftButton)
    assert not manager.devices["physio"].simulator.running and "unplugged" in status.text()
    assert not kill.isEnabled()
    qtbot.waitUntil(lambda: not driver.connected or driver.silent, timeout=5000)
    count = manager.bus.total("physio.main")
    qtbot.mouseClick(restart, Qt.MouseButton.LeftButton)
    assert manager.devices["physio"].simulator.running and "running" in status.text()
    qtbot.waitUntil(lambda: driver.connected and manager.bus.total("physio.main") > count + 20, timeout=10000)


def test_the_panel_refreshes_only_while_it_is_shown(qtbot, manager) -> None:
    """A hidden panel (another tab, a closed window) asks the simulator nothing: a window a failed test left alive
    kept refreshing into later tests after its simulator process had ended."""
    panel = _panel(qtbot, manager)
    assert panel.timer.isActive()
    panel.hide()
    assert not panel.timer.isActive()
    panel.show()
    qtbot.waitExposed(panel)
    assert panel.timer.isActive()
