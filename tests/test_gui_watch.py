"""The GUI thread is watched (issue #37, app.gui_watch): the judgement on a virtual clock, the FES guardian's
window bound, and the real window blocked for 2 s (without the interpreter lock) while stimulating."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

from app import gui_watch
from app.core.bus import StreamBus
from app.core.config import AppConfig
from app.devices.fes_guardian import FesGuardian
from app.gui_watch import GuiWatch
from app.safety.fault_policy import FaultPolicy
from app.safety.supervisor import AlarmLevel, SafetySupervisor, StopAction
from app.wire.sciencemode import encode_sm1_stop


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def watched():  # type: ignore[no-untyped-def]
    """A supervisor with the fault policy (as the manager has it), a stop action that records, a virtual clock."""
    supervisor = SafetySupervisor(AppConfig().safety)
    policy = FaultPolicy(supervisor, StreamBus(), lambda _name: None)
    stops: list[str] = []
    supervisor.add_stop_action(StopAction("FES stop", stops.append))
    events: list[tuple[str, dict]] = []
    supervisor.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    clock = Clock()
    driving = {"what": "stimulation runs"}
    watch = GuiWatch(supervisor, lambda: driving["what"], clock=clock)
    watch.policy = policy  # type: ignore[attr-defined]  # kept alive: its alarm connection goes with it
    watch.start = lambda: None  # type: ignore[method-assign]  # judged here, on the virtual clock, by check()
    yield watch, supervisor, clock, stops, events, driving
    watch.close()


def test_a_stall_while_stimulating_is_an_alarm_then_the_safe_state(watched) -> None:  # type: ignore[no-untyped-def]
    watch, supervisor, clock, stops, events, _driving = watched
    watch.beat()
    clock.t += gui_watch.ALARM_AFTER_S - 0.01
    watch.check()
    assert supervisor.alarms() == [] and stops == []  # a normal stall: nothing
    clock.t += 0.02
    watch.check()
    (warning,) = supervisor.alarms()
    assert warning.level == AlarmLevel.WARNING and "The window stopped responding" in warning.text
    assert "stimulation runs" in warning.text and stops == []
    clock.t += gui_watch.SAFE_AFTER_S - gui_watch.ALARM_AFTER_S
    watch.check()
    stop_alarm = supervisor.alarms()[-1]
    assert stop_alarm.level == AlarmLevel.STOP and "emergency-stop button and F12 could not act" in stop_alarm.text
    assert len(stops) == 1 and "The window did not respond" in stops[0]  # the fault policy's safe state
    clock.t += 1.0
    watch.check()
    assert len(stops) == 1 and len(supervisor.alarms()) == 2  # one safe state per stall
    watch.beat()
    watch.check()
    kinds = [k for k, _d in events]
    assert kinds.index("gui_stall") < kinds.index("gui_stall_safe_state") < kinds.index("gui_resumed")
    resumed = dict(events)["gui_resumed"]
    assert resumed["safe_state"] is True and resumed["stalled_s"] >= 1.6
    assert not stop_alarm.acknowledged  # the safe state stays to be recovered from
    assert watch.stalls and watch.stalls[-1] >= 1.6


def test_a_short_stall_warns_and_clears_itself(watched) -> None:  # type: ignore[no-untyped-def]
    watch, supervisor, clock, stops, _events, _driving = watched
    watch.beat()
    clock.t += (gui_watch.ALARM_AFTER_S + gui_watch.SAFE_AFTER_S) / 2
    watch.check()
    watch.beat()
    watch.check()
    (warning,) = supervisor.alarms()
    assert warning.acknowledged and "responding again after" in warning.text and stops == []


def test_nothing_driving_nothing_judged(watched) -> None:  # type: ignore[no-untyped-def]
    watch, supervisor, clock, stops, _events, driving = watched
    driving["what"] = ""
    watch.beat()
    clock.t += 10.0
    watch.check()
    assert supervisor.alarms() == [] and stops == []
    driving["what"] = "the robot is ON"  # it starts driving while the window is still stalled
    watch.check()
    assert [a.level for a in supervisor.alarms()] == [AlarmLevel.WARNING, AlarmLevel.STOP] and len(stops) == 1


@pytest.mark.realtime
def test_the_watch_thread_starts_when_driving_and_rests_when_not(qtbot) -> None:  # type: ignore[no-untyped-def]
    supervisor = SafetySupervisor(AppConfig().safety)
    driving = {"what": ""}
    watch = GuiWatch(supervisor, lambda: driving["what"], idle_exit_s=0.1)
    try:
        watch.beat()
        assert not watch.running  # nothing drives: no thread
        driving["what"] = "stimulation runs"
        watch.beat()
        assert watch.running
        qtbot.waitUntil(lambda: any(a.level == AlarmLevel.STOP for a in supervisor.alarms()), timeout=3000)
        driving["what"] = ""
        watch.beat()
        qtbot.waitUntil(lambda: not watch.running, timeout=3000)
    finally:
        watch.close()


# ============================================================================ the guardian's window bound
@pytest.mark.realtime
def test_the_guardian_trips_when_the_window_falls_silent() -> None:
    app_end, device_end = socket.socketpair()
    device_end.settimeout(3.0)
    guardian = FesGuardian().start()
    try:
        guardian.arm(app_end.fileno(), encode_sm1_stop())
        bound = 0.3
        t_end = time.monotonic() + 0.6
        while time.monotonic() < t_end:  # the window and the driver alive: no Stop
            guardian.window_beat(bound)
            guardian.heartbeat()
            time.sleep(0.01)
        device_end.settimeout(0.05)
        with pytest.raises(TimeoutError):
            device_end.recv(1)
        last_window = guardian._last_window_beat
        device_end.settimeout(3.0)
        while True:  # the driver still beats, the window does not
            guardian.heartbeat()
            device_end.settimeout(0.01)
            try:
                first = device_end.recv(1)
                break
            except TimeoutError:
                if time.monotonic() - last_window > 3.0:
                    raise
        t_stop = time.monotonic()
        assert first == encode_sm1_stop()
        assert bound - 0.01 <= t_stop - last_window <= bound + 0.2
        deadline = time.monotonic() + 2.0
        why = ""
        while not why and time.monotonic() < deadline:
            guardian.heartbeat()
            why = guardian.tripped()
            time.sleep(0.01)
        assert "the window did not respond" in why
    finally:
        guardian.close()
        app_end.close()
        device_end.close()


@pytest.mark.realtime
def test_a_closed_window_no_longer_trips_the_guardian() -> None:
    app_end, device_end = socket.socketpair()
    guardian = FesGuardian().start()
    try:
        guardian.window_beat(0.2)
        guardian.window_off()
        guardian.arm(app_end.fileno(), b"STOP")
        t_end = time.monotonic() + 0.5
        while time.monotonic() < t_end:
            guardian.heartbeat()
            time.sleep(0.01)
        device_end.settimeout(0.05)
        with pytest.raises(TimeoutError):
            device_end.recv(4)
    finally:
        guardian.close()
        app_end.close()
        device_end.close()


# ============================================================================ the real window, blocked
BLOCK_LAUNCHER_TAIL = r"""
import time as _time
from PySide6.QtCore import QTimer as _QTimer
from PySide6.QtWidgets import QApplication as _QApplication


def _block_when_stimulating():
    fes = None
    for widget in _QApplication.topLevelWidgets():
        manager = getattr(widget, "manager", None)
        if manager is not None:
            fes = manager.driver("fes")
    if fes is None or not fes.stimulating:
        _QTimer.singleShot(100, _block_when_stimulating)
        return
    _QTimer.singleShot(1500, _block)


def _block():
    print(f"BLOCK {_time.monotonic():.6f}", flush=True)
    _time.sleep(2.0)  # the window's thread blocked without holding the interpreter lock
    print(f"UNBLOCK {_time.monotonic():.6f}", flush=True)


_QTimer.singleShot(0, _block_when_stimulating)
"""


@pytest.mark.realtime
def test_the_window_blocked_2_s_while_stimulating_is_stopped_within_the_bound(tmp_path: Path) -> None:
    from tests.app_process import WINDOW_LAUNCHER, AppProcess

    app = AppProcess(tmp_path, "sm1")
    try:
        head, tail = WINDOW_LAUNCHER.rsplit("from app.cli import main", 1)
        launcher = head + BLOCK_LAUNCHER_TAIL + "from app.cli import main" + tail
        app._spawn([__import__("sys").executable, "-c", launcher, str(app.script), str(app.sessions),
                    str(app.config)])
        app.wait_stimulating(60.0)
        deadline = time.monotonic() + 20.0
        while not any(line.startswith("UNBLOCK") for line in app.output) and time.monotonic() < deadline:
            time.sleep(0.05)
        text = app.text()
        block = next((float(line.split()[1]) for line in app.output if line.startswith("BLOCK")), None)
        assert block is not None, text[-3000:]
        stop = app.fes_stop_after(block)
        idle = app.robot_idle_after(block)
        assert stop is not None, f"no Stop on the stimulator's wire after the block:\n{text[-3000:]}"
        print(f"Stop on the FES wire {(stop - block) * 1000:.0f} ms after the block began; robot IDLE "
              f"{(idle - block) * 1000 if idle else float('nan'):.0f} ms")
        assert stop - block <= 1.0, f"Stop {(stop - block) * 1000:.0f} ms after the block began"
        assert idle is not None and idle - block <= 1.0
        assert "The window stopped responding" in text and "The window did not respond" in text
        assert not app.stimulating_on_the_device()
    finally:
        app.close()
