"""Acceptance 3 for the other devices (tests/test_device_loss.py covers the LINarm and the physiological
board): the FES stimulator, the patient model and the VR renderer die mid-session and come back — an
alarm, the safe state (stimulation stopped; no α from before the loss applied to the robot), a gap marker
in the recording, automatic reconnection, and no exception escaping a thread."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pytest

from app.core.config import AppConfig
from app.devices import linarm, patient_model, rehastim, vr
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.session.recording import load_session
from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import ArduinoReceiver
from app.wire.linarm_protocol import ControlMode, ControlState, HomeState
from tests.test_fes_exit_paths import PROFILE, is_stop, is_update, wire

pytestmark = pytest.mark.sim_homed  # a homed LINarm from the start: the homing is tested on its own


@dataclass
class Running:
    manager: LinarmppManager
    folder: Path
    escaped: list[BaseException] = field(default_factory=list)

    def alarms(self, level: AlarmLevel, *words: str) -> list[Any]:
        return [a for a in self.manager.supervisor.alarms()
                if a.level == level and all(w in a.text for w in words)]

    def gap_events(self, device: str) -> list[str]:
        """The session record's gap markers for ``device``, in order (call after end_session)."""
        return [e["kind"] for e in load_session(self.folder).events
                if e["kind"] in ("gap_start", "gap_end") and (e.get("device") or e.get("who")) == device]


@pytest.fixture
def running(tmp_path, qtbot, request) -> Iterator[Running]:
    """A manager with the devices ``request.param`` (name -> factory, or (config, factories)) in a session."""
    config, factories = request.param if isinstance(request.param, tuple) else (AppConfig(), request.param)
    escaped: list[BaseException] = []
    old_hook = threading.excepthook
    threading.excepthook = lambda args: escaped.append(args.exc_value)
    manager = LinarmppManager(config, factories=factories)
    manager.start()
    try:
        for handle in manager.devices.values():
            handle.driver.reconnect_backoff_s = (0.05, 0.2)
        qtbot.waitUntil(manager.all_connected, timeout=10000)
        folder = manager.start_session("LOSS02", "tester", root=tmp_path / "sessions")
        yield Running(manager, folder, escaped)
    finally:
        manager.shutdown()
        threading.excepthook = old_hook
    assert escaped == []


# ── FES ──────────────────────────────────────────────────────────────────────────────────────────────


def fes_config(protocol: str) -> tuple[AppConfig, dict[str, Any]]:
    config = AppConfig()
    config = replace(config, devices=replace(config.devices, fes=replace(config.devices.fes, protocol=protocol)))
    return config, {"fes": rehastim.create}


@pytest.mark.parametrize(("running", "protocol", "fresh"), [
    # SM1 has no watchdog: the device kept stimulating while the cable was out; the driver must stop it.
    pytest.param(fes_config("sm1"), "sm1", False, id="sm1-device-kept-running"),
    pytest.param(fes_config("sm2"), "sm2", True, id="sm2-device-power-cycled"),
], indirect=["running"])
def test_fes_lost_mid_stimulation_stops_alarms_marks_a_gap_and_reconnects(running: Running, qtbot, protocol: str,
                                                                            fresh: bool) -> None:
    manager = running.manager
    driver = manager.driver("fes")
    sim = manager.devices["fes"].simulator
    sim.keep_host_log = True
    qtbot.waitUntil(lambda: driver.device_ready, timeout=3000)
    driver.load_profile(PROFILE)
    driver.start_stimulation("test")
    qtbot.waitUntil(lambda: bool(sim.with_core(lambda c: c.channel_state())), timeout=3000)

    sim.kill()
    qtbot.waitUntil(lambda: not driver.connected, timeout=3000)
    assert not driver.stimulating  # the driver gave up at once: nothing more is sent
    qtbot.waitUntil(lambda: bool(running.alarms(AlarmLevel.STOP, "fes", "lost")
                                 and running.alarms(AlarmLevel.STOP, "FES link was lost while stimulating")),
                    timeout=3000)

    t_restart = time.monotonic()
    sim.restart(fresh_state=fresh)
    qtbot.waitUntil(lambda: driver.connected and driver.device_ready, timeout=5000)
    qtbot.waitUntil(lambda: not sim.with_core(lambda c: c.running), timeout=3000)  # nothing is delivered
    assert not sim.with_core(lambda c: c.channel_state())
    after = [msg for t, msg in wire(sim, protocol) if t >= t_restart]
    if protocol == "sm1":
        assert after and is_stop(after[0])  # the first thing on the new link: Stop
    # The link is up again and the driver runs: still no stimulation until an operator starts it.
    published = driver.total_samples("fes.channels")
    qtbot.waitUntil(lambda: driver.total_samples("fes.channels") > published + 3, timeout=3000)
    assert not driver.stimulating
    assert not [msg for t, msg in wire(sim, protocol) if t >= t_restart and is_update(msg)]
    assert running.alarms(AlarmLevel.INFO, "fes reconnected")
    manager.end_session()
    assert running.gap_events("fes")[:2] == ["gap_start", "gap_end"]


# ── patient model ────────────────────────────────────────────────────────────────────────────────────

MODEL_AND_ROBOT = {"linarm": linarm.create, "patient_model": patient_model.create}
ASSISTANCE_COMMANDS = {"setAdmittanceParameter", "setAssistanceParameter", "setStiffness"}


def robot_on_in_assistance(manager: LinarmppManager, qtbot) -> None:
    robot = manager.driver("linarm")
    robot.command("setCtrlState", int(ControlState.HOME_CTRL_STATE), source="test")
    qtbot.waitUntil(lambda: robot.latest("linarm.state").controlState == ControlState.HOME_CTRL_STATE
                    and robot.latest("linarm.state").homeState == HomeState.HOME_DONE
                    and robot.latest("linarm.state").initialized, timeout=25000)
    robot.command("setCtrlMode", int(ControlMode.POS_REF_BY_ASSISTANCE), source="test")
    robot.command("setCtrlState", int(ControlState.ON_CTRL_STATE), source="test")
    qtbot.waitUntil(lambda: robot.latest("linarm.state").controlState == ControlState.ON_CTRL_STATE, timeout=2000)


def assistance_on_wire(sim: Any, since: float) -> list[tuple[float, str, dict[str, Any]]]:
    """The assistance parameters the robot received from ``since`` on, decoded as the controller does."""
    receiver = ArduinoReceiver()
    out = []
    for t, data in list(sim.host_bytes_log):
        for msg in receiver.feed(data):
            if not msg.id_arg_ok:
                continue
            try:
                cmd = proto.read_host_message(msg)
            except proto.CommandRejected:
                continue
            if t >= since and cmd.name in ASSISTANCE_COMMANDS:
                out.append((t, cmd.name, cmd.args))
    return out


def alpha_driven(manager: LinarmppManager, commands: list[tuple[float, str, dict[str, Any]]]) -> list[Any]:
    """The commands that carry an α-derived value: losing α sends the split at α = 0 (the non-α values,
    issue #17), which is not a stale α."""
    neutral = manager.assistance.preview(0.0)
    value = {"setAdmittanceParameter": neutral.k_a, "setAssistanceParameter": neutral.k_t,
             "setStiffness": neutral.k_m}
    return [c for c in commands
            if not abs(float(next(iter(c[2].values()))) - value[c[1]]) <= 1e-6 * max(1.0, abs(value[c[1]]))]


def model_process(manager: LinarmppManager) -> Any:
    return manager.devices["patient_model"].extras["processes"][0]


@contextmanager
def hung(process: Any) -> Iterator[None]:
    """The helper process freezes (alive, so not restarted, but silent) until the block ends."""
    os.kill(process.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(process.pid, signal.SIGCONT)


def assisting(manager: LinarmppManager, qtbot) -> Any:
    """The robot ON in assistance mode with α from the embedded model reaching it; returns its simulator."""
    sim = manager.devices["linarm"].simulator
    sim.keep_host_log = True
    t_on = time.monotonic()
    robot_on_in_assistance(manager, qtbot)
    qtbot.waitUntil(lambda: bool(assistance_on_wire(sim, t_on)), timeout=5000)  # α does drive the robot
    return sim


@pytest.mark.parametrize("running", [MODEL_AND_ROBOT], indirect=True)
def test_patient_model_silent_alarms_holds_no_stale_alpha_marks_a_gap_and_reconnects(running: Running,
                                                                                       qtbot) -> None:
    manager = running.manager
    model = manager.driver("patient_model")
    sim = assisting(manager, qtbot)
    with hung(model_process(manager)):
        qtbot.waitUntil(lambda: not model.connected, timeout=3000)
        t_lost = time.monotonic()
        qtbot.waitUntil(lambda: bool(running.alarms(AlarmLevel.STOP, "patient_model", "lost")), timeout=3000)
        writes = len(sim.host_bytes_log)  # the robot link stays busy (heartbeats) while α is missing
        qtbot.waitUntil(lambda: len(sim.host_bytes_log) > writes + 5, timeout=3000)
        # Nothing was applied to the robot while α was missing (a command already in flight when the link
        # was judged lost may land within the first few ms).
        assert alpha_driven(manager, assistance_on_wire(sim, t_lost + 0.05)) == []
    qtbot.waitUntil(lambda: model.connected, timeout=5000)
    received = model.total_samples("patient_model.main")
    qtbot.waitUntil(lambda: model.total_samples("patient_model.main") > received + 50, timeout=3000)  # α flows
    assert running.alarms(AlarmLevel.INFO, "patient_model reconnected")
    manager.end_session()
    assert running.gap_events("patient_model")[:2] == ["gap_start", "gap_end"]


@pytest.mark.parametrize("running", [MODEL_AND_ROBOT], indirect=True)
def test_patient_model_killed_is_restarted_and_alpha_flows_again(running: Running, qtbot) -> None:
    manager = running.manager
    model = manager.driver("patient_model")
    process = model_process(manager)
    sim = assisting(manager, qtbot)
    pid = process.pid
    t_kill = time.monotonic()
    process.kill()
    qtbot.waitUntil(lambda: process.pid != pid, timeout=5000)  # the driver restarts its helper (0.5 s checks)
    assert process.starts == 2
    last = model.latest("patient_model.main")
    qtbot.waitUntil(lambda: model.connected and model.latest("patient_model.main") is not last, timeout=5000)
    t_fresh = time.monotonic()
    received = model.total_samples("patient_model.main")
    qtbot.waitUntil(lambda: model.total_samples("patient_model.main") > received + 50, timeout=3000)
    # Between the kill and the new model's first α nothing reached the robot from the assistance split.
    assert alpha_driven(manager, [c for c in assistance_on_wire(sim, t_kill + 0.05) if c[0] < t_fresh - 0.05]) == []


@pytest.mark.parametrize(("running", "device", "stream"), [
    pytest.param({"patient_model": patient_model.create}, "patient_model", "patient_model.main", id="model"),
    pytest.param({"vr": vr.create}, "vr", "vr.main", id="vr"),
], indirect=["running"])
def test_a_killed_helper_raises_an_alarm_and_marks_a_gap(running: Running, qtbot, device: str, stream: str) -> None:
    manager = running.manager
    driver = manager.driver(device)
    # A link that tolerates 5 s of silence (as a slow external renderer would need): the restart always wins.
    driver.alive_timeout_s = 5.0
    process = manager.devices[device].extras["processes"][0]
    qtbot.waitUntil(lambda: driver.datagrams_received > 5, timeout=5000)
    pid = process.pid
    process.kill()
    qtbot.waitUntil(lambda: process.pid != pid, timeout=5000)
    received = driver.datagrams_received
    qtbot.waitUntil(lambda: driver.datagrams_received > received, timeout=5000)  # the new helper answers
    manager.end_session()
    assert [a for a in manager.supervisor.alarms() if a.level >= AlarmLevel.WARNING and device in a.source]
    assert "gap_start" in running.gap_events(device)


@pytest.mark.parametrize("running", [MODEL_AND_ROBOT], indirect=True)
def test_a_gain_change_while_the_model_is_lost_applies_no_stale_alpha(running: Running, qtbot) -> None:
    """The therapist moves k_r (assistance panel) while α is missing: the α from before the loss must not
    be re-applied to the robot with the new gain."""
    manager = running.manager
    model = manager.driver("patient_model")
    sim = assisting(manager, qtbot)
    with hung(model_process(manager)):
        qtbot.waitUntil(lambda: not model.connected, timeout=3000)
        assistance = manager.assistance
        t_change = time.monotonic()
        assistance.set_gains(1.0 if assistance.k_r < 1.0 else 0.2, assistance.k_f)
        # A stale update would be on the wire within milliseconds (the assistance thread sends at once);
        # give it every chance: wait for five more writes of the driver (heartbeats every 100 ms).
        writes = len(sim.host_bytes_log)
        qtbot.waitUntil(lambda: len(sim.host_bytes_log) > writes + 5, timeout=3000)
        assert not model.connected
        assert alpha_driven(manager, assistance_on_wire(sim, t_change)) == []


# ── VR ──────────────────────────────────────────────────────────────────────────────────────────────


@pytest.mark.parametrize("running", [{"vr": vr.create}], indirect=True)
def test_vr_silent_alarms_marks_a_gap_and_reconnects(running: Running, qtbot) -> None:
    manager = running.manager
    driver = manager.driver("vr")
    process = manager.devices["vr"].extras["processes"][0]
    qtbot.waitUntil(lambda: driver.events_received > 0, timeout=5000)
    with hung(process):
        qtbot.waitUntil(lambda: not driver.connected, timeout=5000)  # no event for 2.5 s
        # No FES, no robot: the VR task drives nothing, so its loss is a warning (app/safety/fault_policy.py)
        qtbot.waitUntil(lambda: bool(running.alarms(AlarmLevel.WARNING, "vr", "lost")), timeout=3000)
    qtbot.waitUntil(lambda: driver.connected, timeout=5000)
    events, sent = driver.events_received, driver.datagrams_sent
    qtbot.waitUntil(lambda: driver.events_received > events and driver.datagrams_sent > sent + 50, timeout=5000)
    assert running.alarms(AlarmLevel.INFO, "vr reconnected")
    manager.end_session()
    assert running.gap_events("vr")[:2] == ["gap_start", "gap_end"]


@pytest.mark.parametrize("running", [{"vr": vr.create}], indirect=True)
def test_vr_killed_is_restarted_and_events_flow_again(running: Running, qtbot) -> None:
    manager = running.manager
    driver = manager.driver("vr")
    process = manager.devices["vr"].extras["processes"][0]
    qtbot.waitUntil(lambda: driver.events_received > 0, timeout=5000)
    pid = process.pid
    process.kill()
    qtbot.waitUntil(lambda: process.pid != pid, timeout=5000)
    assert process.starts == 2
    events, sent = driver.events_received, driver.datagrams_sent
    qtbot.waitUntil(lambda: driver.events_received > events and driver.datagrams_sent > sent + 50, timeout=5000)
    assert driver.connected
