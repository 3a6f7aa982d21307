"""Unplug and reconnect, per device: the simulator dies mid-session and comes back — an alarm, the
safe state, a gap marker in the recording, automatic reconnection, and no crash."""

from __future__ import annotations

import threading

import pytest

from app.core.config import AppConfig
from app.devices import linarm, physio
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.session.recording import load_session


@pytest.fixture
def session(tmp_path, qtbot):
    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create, "physio": physio.create})
    manager.start()
    for handle in manager.devices.values():
        handle.driver.reconnect_backoff_s = (0.05, 0.2)
    qtbot.waitUntil(manager.all_connected, timeout=5000)
    folder = manager.start_session("LOSS01", "tester", root=tmp_path / "sessions")
    escaped: list[BaseException] = []
    old_hook = threading.excepthook
    threading.excepthook = lambda args: escaped.append(args.exc_value)
    yield manager, folder
    threading.excepthook = old_hook
    manager.shutdown()
    assert escaped == []


@pytest.mark.parametrize("device", ["linarm", "physio"])
def test_device_lost_mid_session_alarms_marks_a_gap_and_reconnects(session, qtbot, device) -> None:
    manager, folder = session
    handle = manager.devices[device]
    driver = handle.driver
    stream = driver.streams[-1].name
    qtbot.waitUntil(lambda: driver.total_samples(stream) > 20, timeout=3000)
    handle.simulator.kill()
    qtbot.waitUntil(lambda: not driver.connected, timeout=3000)
    qtbot.waitUntil(lambda: any(a.level == AlarmLevel.STOP and device in a.text and "lost" in a.text
                                for a in manager.supervisor.alarms()), timeout=3000)
    handle.simulator.restart()
    qtbot.waitUntil(lambda: driver.connected, timeout=5000)
    before = driver.total_samples(stream)
    qtbot.waitUntil(lambda: driver.total_samples(stream) > before + 20, timeout=3000)
    assert any("reconnected" in a.text for a in manager.supervisor.alarms())
    manager.end_session()
    kinds = [(e["kind"], e.get("device") or e.get("who")) for e in load_session(folder).events]
    assert any(k == "gap_start" for k, _ in kinds), kinds
    assert any(k == "gap_end" for k, _ in kinds), kinds


@pytest.mark.sim_homed
def test_robot_goes_idle_when_the_host_link_dies(session, qtbot) -> None:
    """The controller's watchdog (250 ms of host silence) is the safe state when the app side is gone."""
    manager, _ = session
    handle = manager.devices["linarm"]
    driver = handle.driver
    driver.command("goToHome", source="test", timeout_s=2.0)
    qtbot.waitUntil(lambda: driver.latest("linarm.state").controlState == 1
                    and driver.latest("linarm.state").initialized, timeout=20000)
    manager.set_device_running("linarm", False)  # the host stops talking
    core = handle.simulator.core.core
    qtbot.waitUntil(lambda: int(core.linarm_state().control_state) == 0, timeout=2000)
    manager.set_device_running("linarm", True)
    qtbot.waitUntil(lambda: driver.connected, timeout=3000)
