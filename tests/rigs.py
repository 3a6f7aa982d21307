"""Shared rigs (issue #38): one connected ``LinarmppManager`` — its simulators, drivers and threads — for the
tests of a module that only need "a connected, homed rig", put back in a known state before and after each
test, and checked: a reset that does not reach the known state fails the test.

How a test module uses it (tests/conftest.py has the fixtures)::

    @pytest.fixture(scope="module")
    def shared_rig_spec() -> RigSpec:          # which rig (optional: the default is linarm + fes, homed)
        return RigSpec(devices=("linarm",))

    def test_something(shared_manager): ...   # the module's rig, reset to the known state
    def test_from_power_up(fresh_manager): ...  # a manager of its own, built from the same spec

The known state (``SharedRig.reset``, checked by ``SharedRig.problems``): the e-stop not latched, every alarm
acknowledged and the alarm history empty, no session, no exercise run, no device leased (e.g. the electrode
set-up's lease), stimulation stopped (no caps, no district channels; the loaded profile stays), the robot
connected, homed, IDLE with no error at the home position in the default control mode, the simulated patient idle
and passive, and only the rig's own bus and event subscriptions (the ones a test opened are closed). What a test
changes beyond that (e.g. the controller's limits, the FES scales) it must put back itself, or ask for
``fresh_manager``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.core.config import AppConfig
from app.devices.sim.base import HOMED_ENV, SerialSimulator
from app.manager import LinarmppManager
from app.wire.linarm_constants import K
from app.wire.linarm_protocol import ControlMode, ControlState, ErrorState, HomeState

POSITION_TOLERANCE_M = 1e-3  # "at the home position"
RESET_TIMEOUT_S = 10.0
DEFAULT_MODE = ControlMode.POS_REF_BY_VEL  # the controller's mode at power-up


# ------------------------------------------------------------------------------ what runs (tests/conftest.py)
def _children() -> dict[int, str]:
    """Live (non-zombie) child processes of this process: pid → command."""
    me, out = os.getpid(), {}
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else ():
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[1]) == me and fields[0] != "Z":
                out[int(entry)] = stat[stat.index("(") + 1:stat.rindex(")")]
        except (OSError, ValueError, IndexError):
            continue
    return out


def _os_threads() -> dict[int, str]:
    """This process's OS threads: tid → name (a QThread carries its objectName, e.g. driver:linarm)."""
    out = {}
    for tid in os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task") else ():
        try:
            out[int(tid)] = Path(f"/proc/self/task/{tid}/comm").read_text().strip()
        except OSError:
            continue
    return out


def _python_threads() -> dict[int, str]:
    return {t.ident or 0: t.name for t in threading.enumerate()
            if t.is_alive() and not isinstance(t, threading._DummyThread)}  # type: ignore[attr-defined]


@dataclass
class Owned:
    """The threads (Python idents, OS thread ids) and child processes of the live shared rigs: the suite's, not
    a test's (tests/conftest.py's leftover check skips them, whichever test happened to build the rig)."""

    threads: set[threading.Thread] = field(default_factory=set)  # objects: an ended thread's ident is reused
    tids: set[int] = field(default_factory=set)
    pids: set[int] = field(default_factory=set)

    def thread_idents(self) -> set[int]:
        return {t.ident for t in self.threads if t.is_alive() and t.ident is not None}


OWNED = Owned()


@dataclass(frozen=True)
class RigSpec:
    """Which rig: its devices (app.devices.registry names), its configuration, where its simulators run
    (None: the suite's default, "process" or "thread"), and whether its LINarm powers up homed."""

    devices: tuple[str, ...] = ("linarm", "fes")
    config: AppConfig = field(default_factory=AppConfig)
    host: str | None = None
    homed: bool = True


def _factories(names: tuple[str, ...]) -> dict[str, Any]:
    import importlib

    from app.devices.registry import DEVICE_MODULES

    return {name: importlib.import_module(DEVICE_MODULES[name]).create for name in names}


def _pump(predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Wait for ``predicate`` while Qt's events are processed (queued signals of the drivers)."""
    from PySide6.QtCore import QCoreApplication

    app = QCoreApplication.instance()
    deadline = time.monotonic() + timeout_s
    while True:
        if app is not None:
            app.processEvents()
        if predicate():
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)


def build_manager(spec: RigSpec) -> LinarmppManager:
    """A started manager of ``spec``, every device connected (and the stimulator ready); its LINarm homed when
    ``spec.homed`` (a homed start, LINARMPP_SIM_HOMED)."""
    saved = {k: os.environ.get(k) for k in ("LINARMPP_SIM_HOST", HOMED_ENV)}
    if spec.host is not None:
        os.environ["LINARMPP_SIM_HOST"] = spec.host
    if spec.homed:
        os.environ[HOMED_ENV] = "1"
    try:
        manager = LinarmppManager(spec.config, factories=_factories(spec.devices))
        manager.start()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    fes = manager.driver("fes")
    if not _pump(lambda: manager.all_connected() and (fes is None or fes.device_ready), RESET_TIMEOUT_S):
        manager.shutdown()
        raise AssertionError(f"the rig's devices did not connect: {manager.devices}")
    robot = manager.driver("linarm")
    if robot is not None and not _pump(lambda: robot.latest("linarm.state") is not None, RESET_TIMEOUT_S):
        manager.shutdown()
        raise AssertionError("the rig's LINarm sends no state")
    return manager


class SharedRig:
    """A module's manager and its known state (see the module docstring)."""

    def __init__(self, spec: RigSpec) -> None:
        self.spec = spec
        before = (set(threading.enumerate()), set(_os_threads()), set(_children()))
        self.manager = build_manager(spec)
        self.owned = Owned(set(threading.enumerate()) - before[0], set(_os_threads()) - before[1],
                           set(_children()) - before[2])
        OWNED.threads |= self.owned.threads
        OWNED.tids |= self.owned.tids
        OWNED.pids |= self.owned.pids
        self.resets = 0
        # What the rig itself holds: anything else a test opened is closed by the reset.
        self._subscriptions = set(map(id, self.manager.bus.subscriptions()))

    # ------------------------------------------------------------------ the known state
    def reset(self) -> None:
        """Put the rig back in the known state; raises AssertionError naming what could not be."""
        self.resets += 1
        m = self.manager
        sup = m.supervisor
        for sub in m.bus.subscriptions():
            if id(sub) not in self._subscriptions:
                sub.close()
        if m.runs.current() is not None:
            m.runs.end_current("test ended")
        if m.recorder is not None:
            m.end_session("test ended")
        for key in {lease.key for lease in sup._leases.values()}:  # e.g. the electrode set-up's, left by a failure
            m.release_lease(key, "rig reset")
        m.patient_profile, m.operator, m.patient_version = None, "", 0
        fes = m.driver("fes")
        if fes is not None:
            if fes.stimulating:
                fes.stop_stimulation("rig reset", "test").result(RESET_TIMEOUT_S)
            fes.set_clinical_caps({})
            fes.set_district_channels({})
            fes.set_phase(None)
        sup.reset_emergency_stop("rig reset")
        for alarm in sup.alarms():
            if not alarm.acknowledged:
                sup.acknowledge(alarm.ident, "rig reset")
        self._reset_robot()
        for alarm in sup.alarms():  # the reset's own (e.g. "Emergency stop reset")
            if not alarm.acknowledged:
                sup.acknowledge(alarm.ident, "rig reset")
        with sup._lock:  # a fresh history: tests count their own alarms
            sup._alarms.clear()
            sup._alarm_by_key.clear()
            sup._open_stop = {}
            sup._repeat_recorded.clear()
        for handle in m.devices.values():  # the far end's byte log starts off and empty for each test
            sim = handle.simulator
            if sim is not None and sim.keep_host_log:
                sim.keep_host_log = False
                sim.clear_host_log()
            elif isinstance(sim, SerialSimulator):
                sim.clear_host_log()
        patient = m.patient
        if patient is not None:
            patient.idle()
            patient.passive()
        problems = self.problems()
        if problems:
            raise AssertionError("the shared rig could not be put back in its known state: " + "; ".join(problems))

    def _reset_robot(self) -> None:
        robot = self.manager.driver("linarm")
        if robot is None:
            return

        def state() -> Any:
            return robot.latest("linarm.state")

        if state() is not None and state().errorState != ErrorState.NO_ERROR:
            robot.command("resetError", source="rig reset")
        if not self._at_home() and (self.spec.homed or (state() is not None and state().initialized)):
            # HOME on a homed robot is the move to the home position (a full homing when it is not homed)
            robot.command("setCtrlState", int(ControlState.HOME_CTRL_STATE), source="rig reset")
            _pump(lambda: (s := state()) is not None and s.controlState == ControlState.HOME_CTRL_STATE
                  and s.homeState == HomeState.HOME_DONE and self._at_home(), RESET_TIMEOUT_S)
        if state().controlState != ControlState.IDLE_CTRL_STATE:
            robot.command("setCtrlState", int(ControlState.IDLE_CTRL_STATE), source="rig reset")
        if state().controlMode != DEFAULT_MODE:
            robot.command("setCtrlMode", int(DEFAULT_MODE), source="rig reset")
        _pump(lambda: (s := state()) is not None and s.controlState == ControlState.IDLE_CTRL_STATE
              and s.controlMode == DEFAULT_MODE, RESET_TIMEOUT_S)

    def _at_home(self) -> bool:
        vsa = self.manager.bus.latest("linarm.vsa")
        state = self.manager.bus.latest("linarm.state")
        return (vsa is not None and state is not None and bool(state.initialized)
                and abs(vsa.equilibriumPos - K["HOME_CENTRE"]) <= POSITION_TOLERANCE_M
                and abs(vsa.delta - K["HOME_DELTA"]) <= POSITION_TOLERANCE_M)

    def problems(self) -> list[str]:
        """What differs from the known state (empty when the rig is in it)."""
        m = self.manager
        sup = m.supervisor
        out = []
        if not m.all_connected():
            out.append("a device is not connected: " + ", ".join(n for n, h in m.devices.items()
                                                                 if not h.driver.connected))
        if sup.estop_latched:
            out.append("the e-stop is latched")
        if any(not a.acknowledged for a in sup.alarms()):
            out.append("alarms are open: " + "; ".join(a.text for a in sup.alarms() if not a.acknowledged))
        if m.recorder is not None:
            out.append("a session is running")
        if m.runs.current() is not None:
            out.append("an exercise run is running")
        extra = [s.name for s in m.bus.subscriptions() if id(s) not in self._subscriptions]
        if extra:
            out.append(f"bus subscriptions left open: {extra}")
        if sup._leases:
            out.append("devices are leased: " + ", ".join(f"{d} by {lease.holder}" for d, lease in sup._leases.items()))
        fes = m.driver("fes")
        if fes is not None and fes.stimulating:
            out.append("the FES is stimulating")
        if fes is not None and fes.district_channels:
            out.append(f"district channels are set: {fes.district_channels}")
        limiter = sup.fes_limiter
        if fes is not None and limiter is not None and limiter.limits.clinical_caps:
            out.append(f"the patient's FES caps are set: {limiter.limits.clinical_caps}")
        robot = m.driver("linarm")
        if robot is not None:
            s = robot.latest("linarm.state")
            if s is None:
                out.append("the LINarm sends no state")
            else:
                if s.controlState != ControlState.IDLE_CTRL_STATE:
                    out.append(f"the robot is not IDLE (control state {s.controlState})")
                if s.errorState != ErrorState.NO_ERROR:
                    out.append(f"the robot has an error ({s.errorState})")
                if s.controlMode != DEFAULT_MODE:
                    out.append(f"the robot is in control mode {s.controlMode}")
                if (self.spec.homed or s.initialized) and not self._at_home():
                    vsa = m.bus.latest("linarm.vsa")
                    out.append(f"the robot is not homed at the home position ({vsa})")
        return out

    def close(self) -> None:
        self.manager.shutdown()
        OWNED.threads -= self.owned.threads
        OWNED.tids -= self.owned.tids
        OWNED.pids -= self.owned.pids
