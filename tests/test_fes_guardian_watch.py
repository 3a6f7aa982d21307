"""The FES guardian is watched like every other helper (issue #37): its death while stimulating is an alarm at
once and Stop on the stimulator's wire within BOUND_S; a death while idle is an alarm too; either way a new
guardian is started before the next start (docs/fes.md, "The guardian is watched").

The driver and the simulated stimulator over a real pty (tests/test_rehastim_driver.py's rig), the guardian a
real process killed with SIGKILL: what reached the device is read from the simulator's side of the wire."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable

import pytest

from app.devices.fes_guardian import FesGuardian
from app.safety.supervisor import Alarm, AlarmLevel
from tests.app_process import first_fes_stop_after
from tests.test_rehastim_driver import make_rig, time_profile

BOUND_S = 0.5  # issue #37, acceptance 2: kill -9 of the guardian while stimulating -> Stop within 0.5 s


def _guarded(rig) -> tuple[FesGuardian, Callable[[], list[Alarm]]]:  # type: ignore[no-untyped-def]
    guardian = FesGuardian().start()
    rig.driver.guardian = guardian
    rig.driver.require_guardian = True
    return guardian, rig.supervisor.alarms


def _kill(guardian: FesGuardian) -> int:
    pid = guardian.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    return pid


@pytest.mark.realtime
@pytest.mark.parametrize("protocol", ["sm1", "sm2"])
def test_kill_9_of_the_guardian_while_stimulating_stops_at_once(tmp_path, qtbot, protocol: str) -> None:  # type: ignore[no-untyped-def]
    with make_rig(protocol, tmp_path, qtbot) as rig:
        guardian, alarms = _guarded(rig)
        try:
            rig.driver.load_profile(time_profile())
            rig.driver.start_stimulation("test")
            assert guardian.armed
            qtbot.waitUntil(lambda: bool(rig.core(lambda c: c.channel_state())), timeout=3000)
            t0 = time.monotonic()
            old_pid = _kill(guardian)
            qtbot.waitUntil(lambda: first_fes_stop_after(rig.sim, protocol, t0) is not None, timeout=3000)
            stop = first_fes_stop_after(rig.sim, protocol, t0)
            assert stop is not None
            delay = stop - t0
            print(f"{protocol}: Stop on the wire {delay * 1000:.0f} ms after kill -9 of the guardian")
            assert delay <= BOUND_S, f"Stop {delay * 1000:.0f} ms after the guardian was killed"
            assert not rig.driver.stimulating
            qtbot.waitUntil(lambda: not rig.core(lambda c: c.channel_state()), timeout=2000)
            qtbot.waitUntil(lambda: bool(alarms()), timeout=2000)
            alarm = alarms()[0]
            assert alarm.level == AlarmLevel.STOP and "dead man's switch stopped working" in alarm.text
            assert "killed by signal 9" in alarm.text, alarm.text
            # restarted before the next start: a new process, and the next start arms it
            qtbot.waitUntil(lambda: guardian.alive and guardian.pid != old_pid, timeout=5000)
            rig.supervisor.acknowledge(alarm.ident, "test")
            rig.driver.start_stimulation("again")
            assert rig.driver.stimulating and guardian.armed
        finally:
            rig.driver.stop_stimulation("test end")
            guardian.close()


@pytest.mark.realtime
def test_a_guardian_dead_while_idle_is_an_alarm_and_is_restarted_at_the_next_start(tmp_path, qtbot) -> None:  # type: ignore[no-untyped-def]
    with make_rig("sm1", tmp_path, qtbot) as rig:
        guardian, alarms = _guarded(rig)
        try:
            old_pid = _kill(guardian)
            qtbot.waitUntil(lambda: bool(alarms()), timeout=2000)
            alarm = alarms()[0]
            assert alarm.level == AlarmLevel.WARNING and "restarted before stimulation" in alarm.text, alarm.text
            qtbot.waitUntil(lambda: guardian.alive and guardian.pid != old_pid, timeout=5000)
            # killed again, gone before the driver looked: the start itself starts a new one before arming it
            proc = guardian.proc
            assert proc is not None
            second = _kill(guardian)
            qtbot.waitUntil(lambda: proc.poll() is not None, timeout=2000)
            rig.driver.load_profile(time_profile())
            rig.driver.start_stimulation("test")
            assert rig.driver.stimulating and guardian.armed and guardian.pid not in (old_pid, second)
        finally:
            rig.driver.stop_stimulation("test end")
            guardian.close()


def test_an_orderly_close_is_no_death() -> None:
    guardian = FesGuardian().start()
    guardian.close()
    assert guardian.tripped(time.monotonic() + 1.0) == "" and guardian.death() == "" and not guardian.dead
