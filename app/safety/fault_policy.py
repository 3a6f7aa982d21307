"""One fault policy for the window and the headless runner alike (contract 5).

Which faults stop the therapy, and what stopping means, live here and nowhere else:

* a device's connection lost is a STOP (``loss_level``) — except the patient model and the VR link
  while they drive nothing (no FES stimulation, the LINarm not ON): then a warning, so a model that
  flaps while the robot homes or idles does not stop anything;
* every alarm of level STOP or FATAL — a robot error latch (``controller_error``), a device's
  connection lost, the robot monitor's excursion, the patient model or VR link lost, a recording
  failure — calls ``supervisor.bring_to_safe_state(cause)`` at once, in the thread that raised the
  alarm: the registered stop actions stop FES, put the robot in its safe state and stop the running
  script (contract 3: the script ends "stopped" with ``cause`` as its message);
* silence of a device that moves the patient or drives current (``STOP_ON_SILENCE``: the LINarm, the
  FES) that lasts ``safety.silence_stop_s`` (1 s) after the manager's silence warning is a STOP alarm
  raised here (the LINarm's own watchdog has idled the motors after 0.25 s without host bytes anyway);
* losing α (the patient-model link disconnected or silent) returns FES and robot assistance to their
  non-α values (``AssistanceController.invalidate``, wired by the manager);
* a helper process that cannot bind its port is a device loss (``process_failed``), never "reconnected".
* while the e-stop is latched or a STOP alarm is open, the robot is held IDLE: the supervisor idles a robot
  found ON or homing at every state sample and at every (re)connect (``SafetySupervisor.check_robot_state``),
  and refuses homing / ON; each cause is one alarm, its repeats counted on it (``raise_alarm``'s ``key``).

The policy is a safety monitor inline on the stream bus (the name ``"safety"``), from one subscription: the
supervisor's ``alarm`` records and the devices' events, on the thread that published them. Qt-free.

Each handled fault is recorded (``faults``; a ``fault`` event in the session record) with its cause,
so the headless runner can exit with 3 and the window shows the same alarm: docs/fault-policy.md has
the device × fault matrix that tests/test_fault_policy.py checks in both.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from app.core import journal, streams
from app.core.bus import BusItem, StreamBus
from app.core.journal import Record
from app.safety.supervisor import Alarm, AlarmLevel, SafetySupervisor

log = logging.getLogger(__name__)


class Driver(Protocol):
    """What the policy asks a device's driver (app.devices.driver.DeviceDriver, a floor above)."""

    @property
    def connected(self) -> bool: ...

    @property
    def silent(self) -> bool: ...

STOP_ON_SILENCE: frozenset[str] = frozenset({streams.LINARM, streams.FES})
# a loss matters only while they drive
DRIVING_LINKS: frozenset[str] = frozenset({streams.PATIENT_MODEL, streams.VR})

DriverLookup = Callable[[str], "Driver | None"]


@dataclass(frozen=True)
class Fault:
    source: str
    cause: str
    t_mono: float


class FaultPolicy:
    """Created once by the manager (``manager.fault_policy``); ``attach_devices`` after they start.

    What it uses: the supervisor (alarms, safe state), the bus (device events, the robot's state), the drivers
    by name (still silent? still connected? FES stimulating?), whether the application runs (``running``: no
    fault is judged while it shuts down) and how long a silence may last before it is a STOP."""

    def __init__(self, supervisor: SafetySupervisor, bus: StreamBus, drivers: DriverLookup,
                 running: Callable[[], bool] = lambda: True, silence_stop_s: float = 1.0) -> None:
        self.supervisor = supervisor
        self.bus = bus
        self.drivers = drivers
        self.running = running
        self.silence_stop_s = silence_stop_s
        self.faults: list[Fault] = []
        self._lock = threading.Lock()
        self._attached = False
        # Inline: the safe state runs in the thread that raised the alarm, not when the GUI thread gets to it. One
        # subscription for the alarms and the devices' events (the latter heard once the devices are attached).
        self._subscriptions = [self.bus.subscribe_inline("safety", self._on_item, (), events=True, records=True)]
        if supervisor.bus is not bus:  # a supervisor publishing elsewhere (a test's): its alarms too
            self._subscriptions.append(supervisor.bus.subscribe_inline("safety", self._on_item, (), records=True))

    # ------------------------------------------------------------------ inputs
    def attach_devices(self) -> None:
        """Listen to the devices' silence and helper failures: a safety monitor, inline on the bus (idempotent)."""
        self._attached = True

    def close(self) -> None:
        """Stop listening (the policy no longer acts on anything)."""
        for sub in self._subscriptions:
            sub.close()

    def _on_item(self, item: BusItem) -> None:
        if not isinstance(item, Record):
            return
        if not item.from_device:
            if item.origin == journal.SAFETY and item.kind == journal.ALARM:
                self._on_alarm_record(item)
            return
        if not self._attached or not self.running():
            return
        if item.kind == journal.SILENT and item.device in STOP_ON_SILENCE:
            self._silence_check(item.device, item.detail)
        elif item.kind == journal.HELPER_FAILED:
            self.process_failed(item.device, item.detail)

    def _silence_check(self, device: str, detail: str) -> None:
        delay = self.silence_stop_s

        def check() -> None:
            driver = self.drivers(device)
            if driver is None or not self.running():
                return
            if driver.silent and driver.connected:
                self.supervisor.raise_alarm(AlarmLevel.STOP, device, f"{device} stopped sending data for "
                                            f"{delay:g} s: {detail or 'silent'}")

        timer = threading.Timer(delay, check)
        timer.daemon = True
        timer.start()

    def recording_failed(self, folder: str, error: str) -> None:
        """The recorder could not write (any thread)."""
        self.supervisor.raise_alarm(AlarmLevel.STOP, "recording",
                                    f"Recording failed in {folder}: {error}")

    def process_failed(self, device: str, detail: str) -> None:
        """A helper process (patient model, VR stand-in) cannot run, e.g. its port is taken."""
        self.supervisor.raise_alarm(AlarmLevel.STOP, device, f"{device} helper failed: {detail}")

    # ------------------------------------------------------------------ the policy
    def drives_something(self) -> bool:
        """An actuator α or the VR task can influence is active: FES stimulating, or the LINarm ON."""
        fes = self._driver(streams.FES)
        if fes is not None and bool(getattr(fes, "stimulating", False)):  # an FesDriver
            return True
        state = self.bus.latest(streams.LINARM_STATE) if self._driver(streams.LINARM) is not None else None
        from app.wire.linarm_protocol import ControlState

        return state is not None and getattr(state, "controlState", None) == int(ControlState.ON_CTRL_STATE)

    def loss_level(self, device: str) -> AlarmLevel:
        """The level of ``device``'s connection loss (the manager raises the alarm)."""
        if device in DRIVING_LINKS and not self.drives_something():
            return AlarmLevel.WARNING
        return AlarmLevel.STOP

    def _driver(self, name: str) -> Driver | None:
        try:
            return self.drivers(name)
        except Exception:
            return None

    def _on_alarm_record(self, rec: Record) -> None:
        level = AlarmLevel.__members__.get(str(rec.data.get("level")))
        if level is None or level < AlarmLevel.STOP:
            return
        ident = int(rec.data.get("ident", 0))
        alarm = self.supervisor.alarm(ident) or Alarm(level, str(rec.data.get("source", "")),
                                                      str(rec.data.get("text", "")), ident=ident)
        self._on_alarm(alarm)

    def _on_alarm(self, alarm: Alarm) -> None:
        if alarm.level < AlarmLevel.STOP:
            return
        cause = f"{alarm.source}: {alarm.text}" if alarm.source and alarm.source not in alarm.text else alarm.text
        with self._lock:
            self.faults.append(Fault(alarm.source, cause, time.monotonic()))
        self.supervisor.record(journal.FAULT, source=alarm.source, cause=cause)
        if self.supervisor.estop_latched and alarm.text.startswith("Emergency stop"):
            return  # emergency_stop has just run every stop action itself
        try:
            self.supervisor.bring_to_safe_state(cause)
        except Exception:
            log.exception("safe state after %s failed", cause)

    def faults_since(self, t_mono: float) -> list[Fault]:
        with self._lock:
            return [f for f in self.faults if f.t_mono >= t_mono]

    @property
    def last_cause(self) -> str:
        with self._lock:
            return self.faults[-1].cause if self.faults else ""
