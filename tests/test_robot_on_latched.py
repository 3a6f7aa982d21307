"""A robot switched ON behind the app's back while it must stay IDLE (#25), and the LINarm link's record rows.

A second controller (here: commands injected straight into the simulated controller, which the app never sees)
switches the robot ON or starts homing while the e-stop is latched or a STOP alarm is open: the app sends IDLE at
the first state sample that shows it, within one state period, and raises one alarm for the cause however often
it happens. A safe-state action that could not be sent is recorded ``ok: false`` with why. Garbage on the link
is counted in the session record; a forged frame repeated many times raises one alarm, not one per frame."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from PySide6.QtCore import QCoreApplication

from app.core import journal
from app.core.config import AppConfig
from app.devices import linarm
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel, SafetySupervisor
from app.session.recording import load_session
from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import ControlState, ErrorState, HomeState

pytestmark = [pytest.mark.sim_in_thread, pytest.mark.realtime]

IDLE, HOME, ON = (int(s) for s in (ControlState.IDLE_CTRL_STATE, ControlState.HOME_CTRL_STATE,
                                   ControlState.ON_CTRL_STATE))
STATE_PERIOD_S = 1.0 / AppConfig().devices.linarm.state_rate_hz


@dataclass
class Rig:
    manager: LinarmppManager
    events: list[tuple[str, dict[str, Any]]]
    folder: Any

    @property
    def driver(self) -> Any:
        return self.manager.driver("linarm")

    @property
    def sim(self) -> Any:
        return self.manager.devices["linarm"].simulator

    def core(self) -> Any:
        return self.sim.core.core  # LinarmSimAdapter -> LinarmSimCore

    def inject(self, command: str, *args: Any) -> float:
        """A second controller's command, executed by the simulated controller; its reply goes nowhere."""
        frame = proto.encode_command(command, 77, *args)
        t = time.monotonic()
        self.sim.with_core(lambda adapter: adapter.core.handle_host_bytes(frame))
        return t

    def switch_on_behind_the_apps_back(self) -> float:
        def homed_and_on(adapter: Any) -> None:
            core = adapter.core
            core._reference_encoders()
            core.initialized, core.home_state = True, HomeState.HOME_DONE
            core._meas = core._measure()  # as a finished homing leaves it: the motors hold where they are
            core.handle_host_bytes(proto.encode_command("setCtrlState", 78, ON))
        t = time.monotonic()
        self.sim.with_core(homed_and_on)
        return t

    def host_idles_after(self, t0: float) -> list[float]:
        """When the simulated controller received setCtrlState IDLE from the app, after ``t0``."""
        decoder, times = CmdMessengerDecoder(), []
        for t, data in self.sim.host_bytes_log:
            for frame in decoder.feed(data):
                try:
                    cmd = proto.decode_host_frame(frame)
                except proto.ProtocolError:
                    continue
                if t >= t0 and cmd.name == "setCtrlState" and int(cmd.args.get("controlState", -1)) == IDLE:
                    times.append(t)
        return times

    def latch_and_wait(self, hold: Any) -> None:
        """Hold the robot (e-stop or STOP alarm) and wait until the IDLE that sends has reached the controller:
        an injection made before it arrives would be undone by it, not by the state monitor."""
        t = time.monotonic()
        hold()
        deadline = time.monotonic() + 3.0
        while not self.host_idles_after(t):
            assert time.monotonic() < deadline, "the safe state's IDLE did not reach the controller"
            QCoreApplication.processEvents()
            threading.Event().wait(0.005)

    def alarms(self, text: str) -> list[Any]:
        return [a for a in self.manager.supervisor.alarms() if text in a.text]


@pytest.fixture
def rig(qtbot, tmp_path) -> Iterator[Rig]:
    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create})
    events: list[tuple[str, dict[str, Any]]] = []
    manager.bus.listen("test", lambda r: events.append((r.kind, dict(r.data))))
    manager.start()
    manager.driver("linarm").reconnect_backoff_s = (0.05, 0.2)
    qtbot.waitUntil(lambda: manager.driver("linarm").connected
                    and manager.driver("linarm").latest("linarm.state") is not None, timeout=10000)
    folder = manager.start_session("PORT01", "tester", root=tmp_path / "sessions")
    rig = Rig(manager, events, folder)
    rig.sim.keep_host_log = True
    yield rig
    manager.shutdown()


def _state(rig: Rig) -> int:
    return int(rig.core().linarm_state().control_state)


# ------------------------------------------------------------------------------------------ ON while held
def test_a_robot_switched_on_while_the_estop_is_latched_is_idled_within_a_state_period(rig: Rig, qtbot) -> None:
    rig.latch_and_wait(lambda: rig.manager.supervisor.emergency_stop("test", "F12"))
    t_on = rig.switch_on_behind_the_apps_back()
    assert _state(rig) == ON
    qtbot.waitUntil(lambda: rig.host_idles_after(t_on) != [], timeout=2000)
    qtbot.waitUntil(lambda: _state(rig) == IDLE, timeout=2000)
    delay = rig.host_idles_after(t_on)[0] - t_on
    # The IDLE follows the first state sample that shows ON (sent at the next 5 ms stream tick); the rest is
    # scheduling on a shared machine. Printed for the report.
    print(f"ON behind the app's back -> IDLE on the wire after {delay * 1000:.1f} ms "
          f"(state period {STATE_PERIOD_S * 1000:.0f} ms)")
    assert delay < STATE_PERIOD_S + 0.1, delay
    held = rig.alarms("Robot found ON while the emergency stop is latched")
    assert len(held) == 1 and held[0].level == AlarmLevel.STOP and "sent IDLE" in held[0].text, \
        [a.text for a in rig.manager.supervisor.alarms()]
    # Again and again (a second controller that keeps trying): IDLE every time, still one alarm for the cause.
    for _ in range(3):
        t_again = rig.switch_on_behind_the_apps_back()
        qtbot.waitUntil(lambda t=t_again: rig.host_idles_after(t) != [] and _state(rig) == IDLE, timeout=2000)
    held = rig.alarms("Robot found ON while the emergency stop is latched")
    assert len(held) == 1 and held[0].repeats >= 3, [(a.text, getattr(a, "repeats", None)) for a in held]


def test_a_robot_homing_behind_the_apps_back_while_a_stop_alarm_is_open_is_idled(rig: Rig, qtbot) -> None:
    rig.latch_and_wait(lambda: rig.manager.supervisor.raise_alarm(AlarmLevel.STOP, "physio", "physio lost: test"))
    t_home = rig.inject("goToHome")
    qtbot.waitUntil(lambda: rig.host_idles_after(t_home) != [] and _state(rig) == IDLE, timeout=2000)
    assert rig.host_idles_after(t_home)[0] - t_home < STATE_PERIOD_S + 0.1
    assert len(rig.alarms("Robot found homing while a STOP alarm is open")) == 1
    # The front door says the same before anything is sent: ON / homing are refused while the alarm is open.
    with pytest.raises(Exception, match="STOP alarm is open"):
        rig.driver.command("goToHome", source="test")
    # Acknowledged (Recover): the robot may home again.
    for alarm in rig.manager.supervisor.alarms():
        rig.manager.supervisor.acknowledge(alarm.ident, "tester")
    rig.driver.command("goToHome", source="test")
    qtbot.waitUntil(lambda: _state(rig) == HOME, timeout=2000)
    samples = rig.driver.total_samples("linarm.state")
    qtbot.waitUntil(lambda: rig.driver.total_samples("linarm.state") > samples + 3, timeout=2000)
    assert _state(rig) == HOME  # several state samples later: nothing holds it any more


def test_a_reconnect_while_latched_sends_idle_first(rig: Rig, qtbot) -> None:
    """The robot was switched ON while the app's link was down (the controller's own watchdog is the only
    guard then); the app's reconnect sends IDLE before anything else and says so in the record."""
    sup = rig.manager.supervisor
    sup.emergency_stop("test", "F12")
    rig.manager.set_device_running("linarm", False)
    qtbot.waitUntil(lambda: not rig.driver.connected, timeout=3000)
    rig.inject("resetError")  # the controller's host watchdog may have latched while the link was down
    rig.switch_on_behind_the_apps_back()
    assert _state(rig) == ON
    t_reconnect = time.monotonic()
    rig.manager.set_device_running("linarm", True)
    qtbot.waitUntil(lambda: rig.driver.connected, timeout=5000)
    qtbot.waitUntil(lambda: _state(rig) == IDLE, timeout=2000)
    assert rig.host_idles_after(t_reconnect)
    assert any(k == "robot_idle_on_connect" and d["ok"] for k, d in rig.events), rig.events


# ------------------------------------------------------------------------------------------ ok: false
def test_emergency_idle_while_disconnected_is_recorded_not_ok(rig: Rig, qtbot) -> None:
    sup = rig.manager.supervisor
    rig.manager.set_device_running("linarm", False)
    qtbot.waitUntil(lambda: not rig.driver.connected, timeout=3000)
    sup.bring_to_safe_state("test: link down")
    sup.emergency_stop("test", "F12 with the robot's link down")
    safe = [d for k, d in rig.events if k == "safe_state_action" and d["action"] == "robot IDLE"
            and d["reason"] == "test: link down"]
    estop = [d for k, d in rig.events if k == "estop_action" and d["action"] == "robot IDLE"]
    assert safe and not safe[-1]["ok"] and "not open" in safe[-1]["error"], safe
    assert estop and not estop[-1]["ok"] and "not open" in estop[-1]["error"], estop
    rig.manager.end_session()
    recorded = [e["data"] for e in load_session(rig.folder).events
                if e["kind"] in ("safe_state_action", "estop_action") and e["data"].get("action") == "robot IDLE"]
    assert recorded and not any(e["ok"] for e in recorded), recorded  # the link was down for every one


# ------------------------------------------------------------------------------------------ the link's record
def test_garbage_on_the_link_is_counted_in_the_session_record(rig: Rig, qtbot) -> None:
    driver = rig.driver
    before = driver.garbage["bytes_discarded"] if hasattr(driver, "garbage") else 0
    junk = bytes(range(256)).replace(b";", b"").replace(b"/", b"") * 4  # no frame ends inside a chunk
    for _ in range(200):  # ~200 KB of noise between genuine frames
        rig.sim.link.write(junk + b";")
    # Every chunk counted in a record (the driver records the counts at most every GARBAGE_RECORD_PERIOD_S while
    # frames arrive): waiting for half the bytes let the session end before the last chunks' record (199 < 200).
    qtbot.waitUntil(lambda: any(k == "link_garbage" and d["bytes_discarded"] - before >= 200 * len(junk)
                                and d["bad_frames"] >= 200 for k, d in rig.events), timeout=10_000)
    assert driver.connected
    rig.manager.end_session()
    garbage = [e["data"] for e in load_session(rig.folder).events if e["kind"] == "link_garbage"]
    assert garbage and garbage[-1]["device"] == "linarm" and garbage[-1]["bad_frames"] >= 200, garbage
    assert len(garbage) <= 10  # counted, not one record per frame


def test_the_session_record_has_every_garbage_frame_dropped_before_its_end(rig: Rig, qtbot, monkeypatch) -> None:
    """The driver records its garbage counts at most every GARBAGE_RECORD_PERIOD_S while garbage comes: a session
    that ends between two records must still hold the frames dropped since the last one (the record said 199 of
    200 once). Here the period is longer than the test, so only the end's record can hold them all."""
    from app.devices import linarm

    monkeypatch.setattr(linarm, "GARBAGE_RECORD_PERIOD_S", 3600.0)
    driver = rig.driver
    before = driver.garbage["bad_frames"]
    junk = bytes(range(256)).replace(b";", b"").replace(b"/", b"") * 4
    for _ in range(50):
        rig.sim.link.write(junk + b";")
    qtbot.waitUntil(lambda: driver.garbage["bad_frames"] - before >= 50, timeout=10_000)
    dropped = driver.garbage["bad_frames"]
    rig.manager.end_session()
    garbage = [e["data"] for e in load_session(rig.folder).events if e["kind"] == "link_garbage"]
    assert garbage and garbage[-1]["bad_frames"] >= dropped, (dropped, garbage)


def test_a_forged_frame_repeated_raises_one_alarm_per_cause(rig: Rig, qtbot) -> None:
    """12 forged frames in 0.1 s between genuine ones: a controller error event and an over-speed state sample.
    Each is stopped, but each cause is one alarm (with its repeats counted), not twelve."""
    core = rig.core()
    forged_error = proto.encode_error_event(
        proto.ErrorEvent(1, ErrorState.TRACKING_ERROR, ControlState.IDLE_CTRL_STATE, "forged"))
    vsa = core.vsa_state()
    forged_vsa = proto.encode_vsa_state(proto.VsaState(**{**{f: getattr(vsa, f) for f in vsa.__slots__},
                                                          "handle_vel": 5.0}))
    for _ in range(12):
        rig.sim.link.write(forged_error + forged_vsa)
        qtbot.wait(8)  # genuine state samples in between, as from a second writer on the link
    qtbot.waitUntil(lambda: len(rig.alarms("forged")) >= 1 and len(rig.alarms("handle speed")) >= 1, timeout=3000)
    qtbot.wait(200)
    errors, speeds = rig.alarms("forged"), rig.alarms("handle speed")
    assert len(errors) == 1 and len(speeds) == 1, [(a.text, getattr(a, "repeats", None)) for a in errors + speeds]
    assert errors[0].repeats >= 6 and speeds[0].repeats >= 1  # (a frame split by the sim's own writes is lost)


# ------------------------------------------------------------------------------------------ the rule itself
def test_check_robot_state_idles_on_the_first_sample_and_raises_one_alarm_per_cause() -> None:
    sup = SafetySupervisor(AppConfig().safety)
    sent: list[str] = []

    @dataclass
    class Sample:
        controlState: int

    assert not sup.check_robot_state(Sample(ON), sent.append)  # nothing holds it: ON is fine
    sup.emergency_stop("test")
    assert sup.check_robot_state(Sample(IDLE), sent.append) is False and sent == []
    for _ in range(12):
        assert sup.check_robot_state(Sample(ON), sent.append)
    assert len(sent) == 12  # IDLE at every sample that shows ON
    held = [a for a in sup.alarms() if "Robot found ON" in a.text]
    assert len(held) == 1 and held[0].repeats == 11

    def unreachable(_reason: str) -> None:
        raise OSError("IDLE not sent: the LINarm link is not open")

    sup.check_robot_state(Sample(HOME), unreachable)
    failed = [a for a in sup.alarms() if "Robot found homing" in a.text]
    assert len(failed) == 1 and "could not be sent" in failed[0].text


def test_repeats_of_a_cause_are_counted_on_its_open_alarm_until_acknowledged(monkeypatch, qtbot) -> None:
    import app.safety.supervisor as safety

    sup = SafetySupervisor(AppConfig().safety)
    raised: list[Any] = []
    sup.bus.listen("test", lambda r: raised.append(r) if r.kind == journal.ALARM else None)
    first = sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: TRACKING_ERROR (forged)")
    for _ in range(11):
        assert sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: TRACKING_ERROR (forged)") is first
    assert first.repeats == 11 and len(raised) == 1  # one signal: the fault policy's safe state ran once
    assert sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: OVER_FORCE") is not first  # another cause
    sup.acknowledge(first.ident, "tester")
    again = sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: TRACKING_ERROR (forged)")
    assert again is not first and again.repeats == 0  # acknowledged: the next occurrence is a new alarm
    monkeypatch.setattr(safety, "ALARM_REPEAT_HOLD_S", 0.05)
    qtbot.wait(100)
    assert sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: TRACKING_ERROR (forged)") is not again
