"""What the consumers of the devices use of the application, said as types (issue #29).

The recorder, the LSL outlets, the script API, its bridge and runner, the headless runner and the exercises'
start were handed "the manager" (``manager: Any``) and reached into it for whatever they needed. Each now
names what it really uses, as a :class:`typing.Protocol` here: the stream bus, the safety supervisor, the
configuration, the devices' names and simulated flags, the run log and progress. ``LinarmppManager`` fulfils
all of them (structurally: nothing here imports it, so none of these modules can form an import circle with
the composition root); a test hands a small object with just these members.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

from app.core.bus import StreamBus
from app.core.config import AppConfig
from app.core.ownership import Composition
from app.core.progress import ExerciseProgress
from app.core.runs import RunLog, RunSource
from app.safety.supervisor import SafetySupervisor

__all__ = ["DeviceEntry", "DeviceLink", "EventHost", "ExerciseRunner", "LslHost", "RecordingFailureHandler",
           "ScriptHost", "SessionHost"]


class DeviceLink(Protocol):
    """A device's driver as a consumer reads it: whether its link is up (its samples come from the bus)."""

    @property
    def connected(self) -> bool: ...


class DeviceEntry(Protocol):
    """One configured device (``app.devices.registry.DeviceHandle``): its driver and whether it is simulated.
    A driver's version facts (``firmware_version``, ``protocol_version``, …) go into the session's manifest
    when it has them."""

    @property
    def driver(self) -> DeviceLink: ...

    @property
    def simulated(self) -> bool: ...


class RecordingFailureHandler(Protocol):
    """The fault policy's answer to a recording that can no longer write (a STOP alarm naming the folder)."""

    def recording_failed(self, folder: str, error: str) -> None: ...


class SessionHost(Protocol):
    """What :meth:`app.session.recording.SessionRecorder.start` uses: the configuration (manifest, flush interval,
    free-space limits), the bus (every stream and the device events), the supervisor (its events; the
    low-disk warning), the devices (names, simulated flags, versions), the fault policy (a write failure)
    and a shutdown hook (a session is closed with the application)."""

    config: AppConfig
    bus: StreamBus
    supervisor: SafetySupervisor

    @property
    def fault_policy(self) -> RecordingFailureHandler: ...  # read only: the manager's FaultPolicy is one

    @property
    def devices(self) -> Mapping[str, DeviceEntry]: ...

    def add_shutdown_hook(self, fn: Callable[[], None]) -> None: ...


class LslHost(Protocol):
    """What :class:`app.session.lsl.LslBridge` uses: the configuration (``recording.lsl``, the streams' rates), the
    bus (the streams it declares, their samples, the journal's records) and the session's operator (whose the runs'
    records are, as the session record says)."""

    config: AppConfig
    bus: StreamBus
    operator: str


class EventHost(Protocol):
    """What starting an exercise uses: the session record when one runs, the supervisor's events otherwise."""

    supervisor: SafetySupervisor

    @property
    def recorder(self) -> object | None: ...

    def record_event(self, kind: str, who: str = "", **data: Any) -> None: ...


class ScriptHost(Protocol):
    """What the script API, its bridge and the runner use: the bus (latest samples, the wake-up of a
    ``waitCondition``, the subscriptions a kernel's callbacks read), the supervisor (commands' checks, the
    e-stop and the run's stop action, events), the configuration, the drivers by name (their commands), the run
    log and the progress marks, the operator's name, the session's patient profile (the electrode set-up saves
    its choice on it), and a shutdown hook (no kernel outlives the devices). The runner uses exactly these
    members, none probed."""

    config: AppConfig
    bus: StreamBus
    supervisor: SafetySupervisor
    progress: ExerciseProgress
    runs: RunLog
    operator: str
    recorder: Any  # app.session.recording.SessionRecorder while a session runs, else None
    patient_profile: Any  # app.therapy.patients.PatientProfile of the running session, else None (the electrode set-up)
    patient_version: int  # the archive's version of that profile (an accepted electrode choice is written on it)

    def driver(self, name: str) -> Any: ...  # the device's own driver class (its commands), None when absent

    def update_session_profile(self, profile: Any, version: int | None = None) -> list[str]: ...

    def record_event(self, kind: str, who: str = "", **data: Any) -> None: ...

    def add_shutdown_hook(self, fn: Callable[[], None]) -> None: ...


class ExerciseRunner(Protocol):
    """What starting an exercise needs of the script runner (``app.scripting.runner.ScriptRunner``)."""

    @property
    def running(self) -> bool: ...

    def start(self, source: str, filename: str = "<script>", params: dict[str, Any] | None = None, *,
              program: Any = None, parameters: Any = (), run_source: RunSource = "script_tab",
              restart_of: str | None = None, continues: str | None = None,
              holds: tuple[str, ...] = ("robot", "stimulator"), compose: tuple[Composition, ...] = ()) -> Any: ...


PathLike = str | Path
