"""The journal: one typed record for everything that *happens* (not sampled), on the stream bus beside the samples.

Qt-free (floor: core). Alarms, emergency stops, refusals, leases, faults, run changes and the devices' own events
(``connected``, ``silent``, ``controller_error``, …) are each one :class:`Record` published on the
:class:`app.core.bus.StreamBus`: the supervisor, the fault policy and the application's code through
``SafetySupervisor.record(kind, **data)`` (origin :data:`SAFETY`), the drivers through their one publishing call
(``DeviceDriver._fire_event``: origin the device's id), the run log and the exercise's progress (:data:`RUN`,
:data:`PROGRESS`), and what the application records for the session (``manager.record_event``: :data:`APP`, with
who did it). The recorder, the LSL marker outlet and the window's adapter (``app/ui/qt_bus.py``) subscribe
to the bus once and get them in the order they were published; bluesky's documents are the model.

The kinds are the constants below: one place, so a reader finds every kind the session record can hold, and a
typo is a NameError rather than an event nobody listens to.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

# ---------------------------------------------------------------------------------------------- origins
SAFETY: Final = "safety"  # the supervisor, the fault policy, and what the application records through them
RUN: Final = "run"  # the run log (app/core/runs.py)
PROGRESS: Final = "progress"  # the running exercise's repetitions (app/core/progress.py)
APP: Final = "app"  # what the application records for the session: the exercise chosen, the electrode set-up, …
# Every other origin is a device's id (app.core.streams.LINARM, FES, …): that record is one of the device's events.
JOURNAL_ORIGINS: Final = frozenset({SAFETY, RUN, PROGRESS, APP})

# ---------------------------------------------------------------------------------------------- kinds
# The devices' own events (published by the drivers; ``data["detail"]`` a sentence or a number as text).
CONNECTED: Final = "connected"
DISCONNECTED: Final = "disconnected"
SILENT: Final = "silent"
ALIVE: Final = "alive"
CONTROLLER_ERROR: Final = "controller_error"  # an ERROR_EVENT from the LINarm's controller, as a sentence
DEVICE_ERROR_EVENT: Final = "error"  # a driver's own error (a helper process restarting, …)
HELPER_FAILED: Final = "helper_failed"  # a helper process cannot run (its port is taken): a device loss
FES_FAULT: Final = "fes_fault"  # a fault stopped (or prevented) stimulation
STIMULATION_CHANGED: Final = "stimulation_changed"  # data: on (bool)
SCALE_CLAMPED: Final = "scale_clamped"  # data: knob, applied, text
LINK_KINDS: Final = (CONNECTED, DISCONNECTED, SILENT, ALIVE, CONTROLLER_ERROR)

# Alarms and the emergency stop (the supervisor).
ALARM: Final = "alarm"
ALARM_REPEATED: Final = "alarm_repeated"
ALARM_ACKNOWLEDGED: Final = "alarm_acknowledged"
EMERGENCY_STOP: Final = "emergency_stop"
EMERGENCY_STOP_RESET: Final = "emergency_stop_reset"
ESTOP_ACTION: Final = "estop_action"
SAFE_STATE_ACTION: Final = "safe_state_action"
FAULT: Final = "fault"  # the fault policy handled a STOP/FATAL alarm
ROBOT_HELD_IDLE: Final = "robot_held_idle"
ROBOT_IDLE_ON_CONNECT: Final = "robot_idle_on_connect"
STREAM_RESUMED: Final = "stream_resumed"
# Refusals, clamps and the one owner of each device during a run.
COMMAND_REFUSED: Final = "command_refused"
CLAMPED: Final = "clamped"
LEASE_TAKEN: Final = "lease_taken"
LEASE_RELEASED: Final = "lease_released"
LEASE_REFUSED: Final = "lease_refused"
# The devices, as the application records them.
DEVICE_ERROR: Final = "device_error"
DEVICE_TOGGLED: Final = "device_toggled"
ROBOT_COMMAND: Final = "robot_command"
LINK_GARBAGE: Final = "link_garbage"
FES_STARTED: Final = "fes_started"
FES_STOPPED: Final = "fes_stopped"
FES_START_FAILED: Final = "fes_start_failed"
FES_SCALE: Final = "fes_scale"
FES_PROFILE_LOADED: Final = "fes_profile_loaded"
FES_DISTRICT_CHANNELS: Final = "fes_district_channels"
FES_PULSE_WIDTH_OVERRIDE: Final = "fes_pulse_width_override"
FES_CLINICAL_CAPS: Final = "fes_clinical_caps"
FES_GUARDIAN_DIED: Final = "fes_guardian_died"
FES_GUARDIAN_RESTARTED: Final = "fes_guardian_restarted"
# The GUI thread's watch (app/gui_watch.py).
GUI_STALL: Final = "gui_stall"
GUI_STALL_SAFE_STATE: Final = "gui_stall_safe_state"
GUI_RESUMED: Final = "gui_resumed"
# The patient and the session.
PATIENT_PROFILE_APPLIED: Final = "patient_profile_applied"
PATIENT_LIMITS_APPLIED: Final = "patient_limits_applied"
# The session's patient record is the station's offline copy: stimulation withheld (app.manager, #39).
STIMULATION_WITHHELD: Final = "stimulation_withheld"
RECOVERY: Final = "recovery"
SIMULATION: Final = "simulation"
# Scripts and exercises.
SCRIPT_START: Final = "script_start"
SCRIPT_STOP: Final = "script_stop"
SCRIPT_SAFE_STATE: Final = "script_safe_state"
SCRIPT_REQUEST_REFUSED: Final = "script_request_refused"
SCRIPT_REQUESTS_REFUSED: Final = "script_requests_refused"
EXERCISE_START: Final = "exercise_start"
EXERCISE_PAUSED: Final = "exercise_paused"
EXERCISE_RESUMED: Final = "exercise_resumed"
REPETITION_START: Final = "repetition_start"
REPETITION_END: Final = "repetition_end"
PROMPT: Final = "prompt"
PROGRESS_TEXT: Final = "progress"
RUN_START: Final = "run_start"
RUN_STATE: Final = "run_state"
RUN_END: Final = "run_end"
PROGRESS_CHANGED: Final = "progress_changed"  # the exercise's progress state (not written to the session record)


@dataclass(frozen=True, slots=True)
class Record:
    """One thing that happened: who published it (``origin``: :data:`SAFETY`, :data:`RUN`, :data:`PROGRESS`,
    :data:`APP` or a device's id), what (``kind``, a constant above), its data, when (host monotonic and
    wall-clock s, taken as it was published) and, for an application record, who did it. ``data`` is shared with
    every subscriber: read it, never change it."""

    origin: str
    kind: str
    data: Mapping[str, Any] = field(default_factory=dict)
    t_mono: float = field(default_factory=time.monotonic)
    t_wall: float = field(default_factory=time.time)
    who: str = ""  # who did it, for an application record (origin APP): the operator, a script, "keyboard", …

    @property
    def from_device(self) -> bool:
        """A device's own event (its link, its controller), not a journal entry of the application."""
        return self.origin not in JOURNAL_ORIGINS

    # A device event's words: the device is the origin, its sentence data["detail"], its time t_mono.
    @property
    def device(self) -> str:
        return self.origin

    @property
    def detail(self) -> str:
        return str(self.data.get("detail", ""))

    @property
    def t(self) -> float:
        return self.t_mono


def device_event(device: str, kind: str, detail: str = "", t_mono: float | None = None, **data: Any) -> Record:
    """A device's event as a record (``detail`` a sentence or a number as text)."""
    return Record(device, kind, {"detail": detail, **data}, time.monotonic() if t_mono is None else t_mono)


RecordSink = Callable[[Record], None]  # a journal listener: called on the publishing thread, must be quick
