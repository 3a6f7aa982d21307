"""The suite's own machinery (issue #38): the homed start of the simulated LINarm, and the shared rig's reset,
which must put a rig a test left in any state back in its known state, or fail."""

from __future__ import annotations

import threading

import pytest

from app.devices.sim.adapters import LinarmSimAdapter
from app.devices.sim.base import HOMED_ENV
from app.safety.supervisor import AlarmLevel
from app.wire.linarm_constants import K
from app.wire.linarm_protocol import ControlMode, ControlState, HomeState
from tests.rigs import OWNED, RigSpec, SharedRig


def test_the_simulated_linarm_starts_homed_only_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(HOMED_ENV, raising=False)
    core = LinarmSimAdapter(None).core
    assert not core.initialized and core.home_state is HomeState.HOME_NOT_DONE
    monkeypatch.setenv(HOMED_ENV, "1")
    core = LinarmSimAdapter(None).core
    assert core.initialized and core.home_state is HomeState.HOME_DONE
    assert core.ctrl_state is ControlState.IDLE_CTRL_STATE  # as after a homing and IDLE: motors off
    assert core.h == pytest.approx(K["HOME_CENTRE"]) and core.centre_ref == pytest.approx(K["HOME_CENTRE"])
    assert core.delta_ref == pytest.approx(K["HOME_DELTA"])
    explicit = LinarmSimAdapter(None, start_homed=False).core  # an explicit choice wins
    assert not explicit.initialized


@pytest.mark.sim_homed
def test_the_marker_gives_a_homed_start(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    assert os.environ.get(HOMED_ENV) == "1"
    assert LinarmSimAdapter(None).core.initialized


@pytest.fixture
def rig(qtbot):  # type: ignore[no-untyped-def]
    rig = SharedRig(RigSpec(devices=("linarm", "fes"), host="thread"))
    try:
        yield rig
    finally:
        rig.close()
    assert not OWNED.thread_idents() & {t.ident for t in rig.owned.threads}  # no longer the suite's


def test_a_reset_puts_a_rig_left_in_any_state_back(rig: SharedRig, qtbot, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from app.core.fes_profile import ChannelProfile, FesProfile, Trapezoid

    m = rig.manager
    assert rig.problems() == []
    robot, fes = m.driver("linarm"), m.driver("fes")
    # what a test may leave behind: the robot ON and away, stimulation on, a session, an alarm, the e-stop,
    # a subscription and an event subscriber, the patient squeezing
    m.start_session("RIG01", "tester", root=tmp_path / "sessions")
    robot.command("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS), source="test")
    robot.command("setCtrlState", int(ControlState.ON_CTRL_STATE), source="test")
    robot.command("moveCentreTo", 0.30, 0.2, 0.5, 0, False, source="test")
    qtbot.waitUntil(lambda: abs(m.bus.latest("linarm.vsa").equilibriumPos - 0.30) < 1e-3, timeout=5000)
    fes.load_profile(FesProfile("rig test", "time", {1: ChannelProfile(Trapezoid(8.0, (0.0, 0.2), (50.0, 51.0)),
                                                                        Trapezoid(150.0, (0.0, 0.2), (50.0, 51.0)))}))
    fes.start_stimulation("test")
    qtbot.waitUntil(lambda: fes.stimulating, timeout=3000)
    m.supervisor.raise_alarm(AlarmLevel.WARNING, "test", "left open by a test")
    m.bus.subscribe("a test's subscription", ["linarm.vsa"])
    seen: list[str] = []
    m.bus.listen("a test's listener", lambda r: seen.append(r.kind))
    m.patient.squeeze(30.0)
    m.supervisor.emergency_stop("test", "left latched by a test")
    assert len(rig.problems()) >= 6, rig.problems()

    rig.reset()
    assert rig.problems() == []
    state, vsa = robot.latest("linarm.state"), m.bus.latest("linarm.vsa")
    assert state.controlState == ControlState.IDLE_CTRL_STATE and state.homeState == HomeState.HOME_DONE
    assert vsa.equilibriumPos == pytest.approx(K["HOME_CENTRE"], abs=1e-3)
    assert not fes.stimulating and m.recorder is None and not m.supervisor.estop_latched
    assert m.supervisor.alarms() == []  # the next test counts its own
    n = len(seen)
    m.supervisor.record("after the reset")
    assert len(seen) == n  # the test's event subscriber is gone
    assert "a test's subscription" not in [s.name for s in m.bus.subscriptions()]


def test_a_reset_that_cannot_reach_the_known_state_fails(rig: SharedRig, qtbot) -> None:  # type: ignore[no-untyped-def]
    rig.manager.devices["linarm"].simulator.kill()  # the robot gone: nothing can bring it home
    qtbot.waitUntil(lambda: not rig.manager.driver("linarm").connected, timeout=3000)
    with pytest.raises(AssertionError, match="could not be put back in its known state: a device is not connected"):
        rig.reset()


def test_the_rigs_threads_are_the_suites_and_a_tests_own_are_not(rig: SharedRig) -> None:
    assert {t.ident for t in rig.owned.threads} and {t.ident for t in rig.owned.threads} <= OWNED.thread_idents()
    stop = threading.Event()
    mine = threading.Thread(target=stop.wait, name="a test's own thread")
    mine.start()
    try:
        assert mine.ident not in OWNED.thread_idents()  # the leftover check (tests/conftest.py) still sees it
    finally:
        stop.set()
        mine.join()
