"""LinarmppManager: the composition root. It builds the stream bus first, then the safety supervisor, the
assistance controller and the devices (drivers and, when simulated, their simulators), and wires the consumers
to the bus: the safety monitors inline (the devices' loss and silence alarms, the fault policy), the therapy
(patient-model α → split → robot and FES, the VR task's target → the robot) on one queued "therapy" thread.
The GUI, the script runner and the headless runner all work through one manager; none of them touches a port.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

from PySide6.QtCore import QCoreApplication, QObject, QThread, Signal

from app.core import journal, streams
from app.core.bus import BusItem, SampleItem, StreamBus, Subscription
from app.core.config import AppConfig
from app.core.ownership import ROBOT, RUN_SOURCES, STIMULATOR, Composition, Lease
from app.core.paths import runtime_dir
from app.core.priority import PriorityOutcome, raise_for_real_time
from app.devices.driver import DeviceDriver
from app.devices.registry import DeviceFactory, DeviceHandle, SimulatorHosting, build_devices
from app.safety.assistance import AssistanceController, AssistanceInactive
from app.safety.fault_policy import FaultPolicy
from app.safety.supervisor import AlarmLevel, SafetyError, SafetySupervisor
from app.wire.linarm_constants import PRETENSION_MOVE

if TYPE_CHECKING:
    from app.devices.linarm import LinarmDriver

log = logging.getLogger(__name__)

__all__ = ["DeviceFactory", "DeviceHandle", "DeviceWatch", "LinarmppManager", "TherapyThread"]

# The pretension move by which the robot's share of α changes the VSA's stiffness (setStiffness's motion
# profile): the constants table's, and execTime 0 = planned from that velocity and acceleration.
STIFFNESS_MOVE = PRETENSION_MOVE


class TherapyThread:
    """The one thread the therapy's consumers run on: it drains their queued bus subscription (the patient
    model's α and link events, the VR task's frames) and applies them through the devices' command paths, so a
    command waiting for its ack never delays a driver, the safety monitor or another consumer. Within a pass
    only the newest α and the newest target count (a backlog is not replayed to the robot), in the order the
    events came: an α lost after its last sample is never applied.

    Started by ``LinarmppManager.start``, stopped (and joined) by ``shutdown``."""

    NAME = "therapy"
    MAXLEN = 1024  # ~5 s of α at 100 Hz and the VR frames at 50 Hz: more backlog than that is counted, dropped

    def __init__(self, bus: StreamBus, on_alpha: Callable[[float], None], on_alpha_lost: Callable[[str], None],
                 on_target: Callable[[float], None]) -> None:
        self.bus = bus
        self.on_alpha = on_alpha
        self.on_alpha_lost = on_alpha_lost
        self.on_target = on_target
        self.subscription: Subscription | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.passes = 0

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        if self.running:
            return
        self._stop.clear()
        self.subscription = self.bus.subscribe(self.NAME, (streams.PATIENT_MODEL_MAIN, streams.VR_MAIN), events=True,
                                               maxlen=self.MAXLEN)
        self._thread = threading.Thread(target=self._run, args=(self.subscription,), name=self.NAME, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> bool:
        """End the thread (after the command it may be waiting on) and close its subscription."""
        self._stop.set()
        sub, self.subscription = self.subscription, None
        if sub is not None:
            sub.close()  # wakes its wait at once
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
            return not thread.is_alive()
        return True

    def _run(self, sub: Subscription) -> None:
        while not self._stop.is_set():
            if not sub.wait(0.5):
                continue
            try:
                self.handle(sub.drain())
            except Exception:  # a consumer's bug must not end the therapy thread
                log.exception("therapy: a pass failed")

    def handle(self, items: list[BusItem]) -> None:
        """One pass over the queued items (the thread's body; tests call it directly)."""
        self.passes += 1
        alpha: float | None = None
        target: float | None = None
        for item in items:
            if isinstance(item, SampleItem):
                if item.stream == streams.PATIENT_MODEL_MAIN:
                    alpha = float(getattr(item.sample, "alpha", float("nan")))
                elif item.stream == streams.VR_MAIN:
                    value = getattr(item.sample, "targetPos", None)
                    if value is not None and value == value:  # not NaN
                        target = float(value)
            elif isinstance(item, journal.Record) and item.origin == streams.PATIENT_MODEL \
                    and item.kind in (journal.DISCONNECTED, journal.SILENT):
                alpha = None  # whatever came before the loss is stale
                self.on_alpha_lost(item.kind)
        if alpha is not None:
            self.on_alpha(alpha)
        if target is not None:
            self.on_target(target)


class DeviceWatch:
    """Connection loss and silence become alarms (and events in the session record). A safety monitor: the
    manager subscribes it inline on the bus (``bus.subscribe_inline("safety", watch, (), events=True)``), so the
    alarm — and the fault policy's safe state — comes on the thread that saw the event."""

    def __init__(self, supervisor: SafetySupervisor, loss_level: Callable[[str], AlarmLevel],
                 running: Callable[[], bool] = lambda: True) -> None:
        self.supervisor = supervisor
        self.loss_level = loss_level  # the fault policy's: STOP unless nothing needs the device
        self.running = running
        self._state: dict[str, dict[str, Any]] = {}  # per device: seen connected, its open silence alarm

    def watch(self, device: str) -> None:
        self._state.setdefault(device, {"was_connected": False, "silence_alarm": None})

    def __call__(self, item: BusItem) -> None:
        if not isinstance(item, journal.Record):
            return
        name, event, detail = item.origin, item.kind, item.detail
        state = self._state.get(name)
        if state is None:
            return
        if event == journal.CONNECTED:
            if state["was_connected"]:
                self.supervisor.raise_alarm(AlarmLevel.INFO, name, f"{name} reconnected")
            state["was_connected"] = True
        elif event == journal.DISCONNECTED and state["was_connected"] and self.running():
            self.supervisor.raise_alarm(self.loss_level(name), name, f"{name} connection lost: {detail}")
        elif event == journal.SILENT and self.running():
            state["silence_alarm"] = self.supervisor.raise_alarm(AlarmLevel.WARNING, name,
                                                                 f"{name} stopped sending data")
        elif event == journal.ALIVE and state.get("silence_alarm") is not None:
            # The stream resumed: the warning says so and leaves the banner; it stays in the alarm history.
            alarm, state["silence_alarm"] = state["silence_alarm"], None
            try:
                gap = f" after {float(detail):.1f} s"
            except ValueError:
                gap = ""
            alarm.text = f"{alarm.text} (resumed{gap})"
            self.supervisor.record(journal.STREAM_RESUMED, device=name, silent_s=detail, ident=alarm.ident)
            self.supervisor.acknowledge(alarm.ident, operator=f"{name} resumed")
        elif event == journal.CONTROLLER_ERROR:
            self.supervisor.raise_alarm(AlarmLevel.STOP, name, detail)


class LinarmppManager(QObject):
    session_changed = Signal(object)  # the session folder (Path) or None when no session runs
    profile_changed = Signal(object)  # the session patient's profile, saved again during the session
    # A session plan check's answer (generation, the profile it read, its problems), from the check's thread to the
    # manager's (the window's): see _check_plan_off_thread.
    _plan_checked = Signal(int, object, object)

    def __init__(self, config: AppConfig, factories: dict[str, DeviceFactory] | None = None) -> None:
        super().__init__()
        self.config = config
        self._plan_lock = threading.Lock()
        self._plan_generation = 0  # the newest plan check's: an older check's answer is dropped
        self.plan_checks_pending = 0  # checks on their thread whose answer has not been taken yet (tests)
        self._plan_checked.connect(self._take_plan_check)
        self.bus = StreamBus()  # first: every device publishes on it, every consumer subscribes to it
        self.notifier = self.bus.notifier  # what a script's waitCondition waits on (woken once per driver read)
        self.supervisor = SafetySupervisor(config.safety, bus=self.bus)  # its records: the journal, on the bus
        self.runtime_dir: Path = runtime_dir()
        self.devices: dict[str, DeviceHandle] = {}
        self.simulators = SimulatorHosting(config, self.runtime_dir)
        if factories is None:
            from app.devices.registry import default_factories

            factories = default_factories(config)
        self._factories = factories
        self._started = False
        self._shutdown_hooks: list[Callable[[], None]] = []
        self.recorder: Any = None  # app.session.recording.SessionRecorder while a session runs
        self.patient_profile: Any = None
        # The archive record's version the session's profile was read at (0: a YAML file, unversioned): a change
        # made inside the session (an electrode choice) is saved as of it, field by field (app.archive.station).
        self.patient_version = 0
        self.operator = ""
        self._lsl: Any = None
        # α from the patient model → split → robot (k_m, k_a, k_t) and FES (pulse width). Built before the
        # devices: the patient model's and the VR's frames carry its split and α.
        self.assistance = AssistanceController(config.assistance, self._apply_robot_assistance,
                                               self._apply_fes_pulse_width, supervisor=self.supervisor)
        self._last_target: float | None = None
        self._leased: set[str] = set()  # the leases of the runs holding their devices now (one owner, #36)
        # The open runs' starts (their run_start records' data), by lease key: what a run holds, for its lease.
        self._open_runs: dict[str, Mapping[str, Any]] = {}
        self._earlier_runs: list[Any] = []  # run logs a session replaced while one of their runs was open
        self._vr_targets_before: tuple[float, ...] | None = None  # the VR task's own targets, during a composed run
        self.therapy = TherapyThread(self.bus, self.assistance.update_alpha, self._alpha_lost, self._follow_target)
        from app.core.progress import ExerciseProgress

        self.progress = ExerciseProgress(self.supervisor.record)  # the running exercise's repetitions
        # Runs are followed through their journal records (origin "run"): the leases here, the progress its run.
        self.bus.listen("leases", self.hold_for_run)
        self.progress.follow_runs(self.bus)
        self.runs = self._new_run_log()  # the exercise runs (app/core/runs.py); a new log for each session
        # every STOP alarm -> safe state (window and headless alike)
        self.fault_policy = FaultPolicy(self.supervisor, self.bus, self.driver, lambda: self._started,
                                        config.safety.silence_stop_s)
        self.device_watch = DeviceWatch(self.supervisor, self.loss_level, lambda: self._started)
        self._watching = False
        self.priority: PriorityOutcome | None = None  # set at start(): app/core/priority.py

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Build every configured device (app.devices.registry), start the simulators (their own
        process, or threads here), then the drivers and the therapy thread."""
        if self._started:
            return
        self._started = True
        # Driving starts: this process's threads ahead of ordinary programs where the system allows it (the
        # simulators and drivers started below inherit it): app/core/priority.py.
        self.priority = raise_for_real_time()
        self.devices = build_devices(
            self._factories, self.config, bus=self.bus, supervisor=self.supervisor,
            runtime_dir=self.runtime_dir, simulators=self.simulators, assistance=self.assistance,
            on_error=lambda name, exc: self.supervisor.record(journal.DEVICE_ERROR, device=name, error=str(exc)))
        try:
            self.simulators.start()
        except Exception as exc:
            log.exception("the simulated devices could not be started")
            self.supervisor.record(journal.DEVICE_ERROR, device="simulators", error=str(exc))
        # The safety monitors, after the devices' own (LINarm monitor, FES link watch: subscribed by their
        # create), in the order they always ran: the device watch's alarms, then the fault policy.
        for name in self.devices:
            self.device_watch.watch(name)
        if not self._watching:
            self._watching = True
            self.bus.subscribe_inline("safety", self.device_watch, (), events=True)
        self.fault_policy.attach_devices()
        self.therapy.start()
        for handle in self.devices.values():
            if handle.simulator is not None:
                handle.simulator.start()
            handle.driver.start()
        log.info("devices started: %s", ", ".join(self.devices) or "none")

    # ------------------------------------------------------------------ the therapy (on the therapy thread)
    def _robot(self) -> LinarmDriver | None:
        """The LINarm driver when there is one (its command path runs the supervisor's checks)."""
        from app.devices.linarm import LinarmDriver

        robot = self.driver(streams.LINARM)
        return robot if isinstance(robot, LinarmDriver) else None

    def _apply_robot_assistance(self, k_m: float, k_a: float, k_t: float) -> None:
        """The robot's share of α only acts in the interaction modes it parameterises (admittance, assistance)
        while ON: a position-controlled exercise or a script's moves are never altered."""
        from app.wire.linarm_protocol import ControlMode, ControlState

        robot = self._robot()
        if robot is None or not robot.connected:
            raise AssistanceInactive("the LINarm is not connected")
        try:  # a run holding the robot keeps its own gains, unless its exercise lets the assistance set them
            self.supervisor.check_lease(ROBOT, "robot gains", "assistance")
        except SafetyError as exc:
            raise AssistanceInactive(exc.reason) from None
        state = self.bus.latest(streams.LINARM_STATE)
        assisted_modes = (int(ControlMode.POS_REF_BY_ADMITTANCE), int(ControlMode.POS_REF_BY_ASSISTANCE))
        if state is None or state.controlState != int(ControlState.ON_CTRL_STATE) \
                or state.controlMode not in assisted_modes:
            raise AssistanceInactive("robot assistance applies only while ON in admittance or assistance mode")
        # Each parameter on its own: a refused one must not hold back the others.
        for args in (("setAdmittanceParameter", k_a), ("setAssistanceParameter", k_t),
                     ("setStiffness", k_m, *STIFFNESS_MOVE)):
            _command(robot, args, "assistance")

    def _apply_fes_pulse_width(self, pulse_width_us: float | None) -> None:
        from app.devices.rehastim import FesDriver

        fes = self.driver(streams.FES)
        if not isinstance(fes, FesDriver):
            raise AssistanceInactive("no FES device")
        if pulse_width_us is not None:
            try:  # the run (or the electrode set-up) stimulates at the pulse width it shows, unless it composes
                self.supervisor.check_lease(STIMULATOR, "pulse width override", "assistance")
            except SafetyError as exc:
                raise AssistanceInactive(exc.reason) from None
        fes.set_pulse_width_override(pulse_width_us, "assistance")

    def _alpha_lost(self, _why: str) -> None:
        self.assistance.invalidate()  # no stale α is ever applied, whatever the GUI changes meanwhile

    def _follow_target(self, target: float) -> None:
        """The VR task's target becomes the robot's assistance target (once per new target) — while a run holds
        the robot, only if its exercise composes it, clamped to the run's range and the patient's limits (the
        supervisor refuses anything else, and records the refusal once per run)."""
        robot = self._robot()
        if target == self._last_target or robot is None or not robot.connected:
            return
        state = self.bus.latest(streams.LINARM_STATE)
        if state is None or not state.initialized:
            return
        if self.supervisor.robot_hold_reason():
            # A latched e-stop or an open STOP alarm holds the robot IDLE: the target would only be refused (and a
            # refusal per VR frame recorded); the next target after Recover is applied.
            self._last_target = None
            return
        self._last_target = target
        applied = self.supervisor.composed_target("VR task", target)
        if applied is None:
            return
        _command(robot, ("setAssistanceTargetPos", applied), "VR task")

    # ------------------------------------------------------------------ one owner during a run (#36)
    def loss_level(self, device: str) -> AlarmLevel:
        """The level of ``device``'s connection loss: the fault policy's (a link that drives an active actuator is a
        STOP), except that a driving link — the patient model's α, the VR task's target — drives nothing an owner
        holds without composing it and without a program that could read it: while every active actuator is held
        by such an owner (the electrode set-up), its loss is a warning. A script's or an exercise's run may read
        α through the API itself: for those it stays a STOP."""
        level = self.fault_policy.loss_level(device)
        source = {streams.PATIENT_MODEL: "assistance", streams.VR: "VR task"}.get(device)
        if level < AlarmLevel.STOP or source is None:
            return level
        from app.wire.linarm_protocol import ControlState

        fes = self.driver(streams.FES)
        state = self.bus.latest(streams.LINARM_STATE) if self.driver(streams.LINARM) is not None else None
        active = [d for d, on in ((ROBOT, state is not None
                                   and getattr(state, "controlState", None) == int(ControlState.ON_CTRL_STATE)),
                                  (STIMULATOR, bool(getattr(fes, "stimulating", False)))) if on]
        for dev in active:
            lease = self.supervisor.lease(dev)
            if lease is None or lease.acts_for(RUN_SOURCES[0]) or any(c.source == source for c in lease.compose):
                return level  # it can reach this actuator, or the program holding it can read it
        return AlarmLevel.WARNING if active else level

    def hold_for_run(self, record: journal.Record) -> None:
        """A journal listener (on the publishing thread): a run that starts holds its devices, one that ends gives
        them back. What it holds and lets in comes from its ``run_start`` record (``holds``, ``compose``,
        ``program.title``: app/core/runs.py). The lease's key is the run's id in its log (the records' ``log``):
        each session's log numbers from run-1, and a run of an earlier log may still be running. A run refused its
        devices at its start asks again at its next state."""
        if record.origin != journal.RUN or record.kind not in (journal.RUN_START, journal.RUN_STATE, journal.RUN_END):
            return
        data = record.data
        run_id = str(data.get("run_id", ""))
        key = f"{run_id}@{data.get('log', '')}"
        if record.kind == journal.RUN_END:
            self._open_runs.pop(key, None)
            if key in self._leased:
                self._leased.discard(key)
                self.release_lease(key, str(data.get("reason") or ""))
            return
        if record.kind == journal.RUN_START:
            self._open_runs[key] = data
        start = self._open_runs.get(key)
        if start is None or key in self._leased:
            return
        self._leased.add(key)
        try:
            compose = tuple(Composition.from_dict(c) for c in start.get("compose") or ())
        except (ValueError, KeyError, TypeError) as exc:
            log.error("run %s: its composition is not understood (%s); nothing composes", run_id, exc)
            compose = ()
        title = str((start.get("program") or {}).get("title", ""))
        lease = Lease(key=key, holder=title, devices=frozenset(start.get("holds") or ()), sources=RUN_SOURCES,
                      compose=compose, run_id=run_id)
        try:
            self.take_lease(lease)
        except SafetyError as exc:  # the runner checks first (start_problem): a console entry meanwhile
            log.warning("run %s does not hold its devices: %s", run_id, exc.reason)
            self._leased.discard(key)

    def take_lease(self, lease: Lease) -> None:
        """``lease.holder`` holds its devices from now on (the supervisor refuses everyone else); raises
        SafetyError when another holds them. Runs take theirs through :meth:`hold_for_run`; the electrode set-up
        its own."""
        self.supervisor.take_lease(lease)
        self._lease_taken(lease)

    def release_lease(self, key: str, reason: str = "") -> Lease | None:
        held = self.supervisor.release_lease(key, reason)
        if held is not None:
            self._lease_released(held)
        return held

    def _lease_taken(self, lease: Lease) -> None:
        """What the holder takes over: the assistance's pulse width off the stimulator (the run stimulates at
        the pulse width its profile shows, unless it composes it); a VR task it composes shows its range."""
        fes = self.driver(streams.FES)
        if STIMULATOR in lease.devices and not lease.composition("assistance", "pulse width override") \
                and getattr(fes, "pulse_width_override", None) is not None:
            try:
                fes.set_pulse_width_override(None, lease.holder)  # type: ignore[union-attr]
            except Exception:
                log.exception("the assistance's pulse width could not be taken off")
            self.assistance.forget_applied(fes=True)
        if ROBOT in lease.devices and not lease.composition("assistance", "robot gains"):
            self.assistance.forget_applied(robot=True)  # re-applied, if still wanted, once the run ends
        vr = self.driver(streams.VR)
        task = getattr(vr, "task", None)
        comp = lease.composition("VR task", "setAssistanceTargetPos")
        if task is not None and comp is not None and comp.range_m is not None:
            # The game shows the run's two ends, the start first (it alternates between them as the exercise
            # does): whatever it sends is inside the range anyway (clamped and checked).
            lo, hi = comp.range_m
            self._vr_targets_before = tuple(task.targets)
            task.set_targets((lo, hi) if task.subTask % 2 == 0 else (hi, lo))
        self._last_target = None

    def _lease_released(self, lease: Lease) -> None:
        vr = self.driver(streams.VR)
        task = getattr(vr, "task", None)
        if task is not None and self._vr_targets_before is not None:
            task.set_targets(self._vr_targets_before)
        self._vr_targets_before = None
        self._last_target = None  # the VR task's target applies again from its next frame

    def apply_patient_profile(self, profile: Any) -> None:
        """The patient's clinical score feeds the embedded model; their gains the assistance split."""
        from app.devices.patient_model import PatientModelDriver
        from app.devices.rehastim import FesDriver

        model = self.driver(streams.PATIENT_MODEL)
        score = profile.scores.fugl_meyer_ue
        if isinstance(model, PatientModelDriver) and score is not None:
            model.clinical_score = int(score)
        self.assistance.set_gains(profile.assistance.k_r, profile.assistance.k_f)
        fes = self.driver(streams.FES)
        if isinstance(fes, FesDriver):
            from app.therapy.patients import clinical_caps

            fes.set_clinical_caps(clinical_caps(profile))
            # district-addressed profiles stimulate the patient's chosen electrodes
            fes.set_district_channels(profile.fes.district_channels())
        self.supervisor.record(journal.PATIENT_PROFILE_APPLIED, patient=profile.patient_id,
                              k_r=profile.assistance.k_r, k_f=profile.assistance.k_f, clinical_score=score)

    # ------------------------------------------------------------------ sessions
    def start_session(self, patient_id: str, operator: str, note: str = "", root: Path | None = None) -> Path:
        """A session = a patient + an operator + a recording that starts now. The patient's profile
        narrows the safety limits for its duration. Raises ValueError/PatientError, nothing started."""
        from app.archive import station
        from app.archive.api import ArchiveError
        from app.session.recording import SessionRecorder, sessions_root
        from app.therapy.patients import PatientError, effective_robot_limits

        if self.recorder is not None:
            raise RuntimeError("a session is already running; end it first")
        try:  # the archive's record (or the YAML file without one); a bad profile refuses the session
            record = station.read_record(patient_id, self.config.safety)
        except ArchiveError as exc:  # never a session without the caps its patient may have
            raise PatientError(f"patient {patient_id}", None, "",
                               f"the session is not started: the patient's profile cannot be read ({exc})") from exc
        profile = record.profile if record is not None else None
        if record is None:
            log.info("patient %s has no profile: the configured limits apply", patient_id)
        copy_read_at = station.copy_in_use(patient_id) if record is not None else ""
        recorder = SessionRecorder()
        folder = recorder.start(self, patient_id, operator, note, root=root or sessions_root(self.config),
                                profile=profile)
        self.recorder = recorder
        self.patient_profile = profile
        self.patient_version = record.version if record is not None else 0
        self.operator = operator
        self.runs = self._new_run_log()
        self._withhold_stimulation_for_a_copy(patient_id, copy_read_at)
        if profile is not None:
            self.supervisor.robot = effective_robot_limits(profile, self.config.safety.robot)
            self.supervisor.record(journal.PATIENT_LIMITS_APPLIED, patient=patient_id)
            self._apply_robot_limits()
            self.apply_patient_profile(profile)
            self._check_plan(profile)
        self.start_lsl()  # its marker outlet hears the journal on the bus, as the recorder does
        self.session_changed.emit(folder)
        return folder

    def _withhold_stimulation_for_a_copy(self, patient_id: str, read_at: str) -> None:
        """A session whose patient record is this station's copy (the archive unreachable, #39) runs without
        stimulation: a cap lowered on another station since the copy was read would not be known, and a lowered cap
        is never raised again by a stale copy. Said on screen (a warning alarm) and in the record; lifted when the
        archive's own record reaches the session (``update_session_profile`` with its version)."""
        if not read_at:
            self.supervisor.stimulation_withheld = ""
            return
        why = (f"this session uses this station's copy of patient {patient_id}'s record, read at {read_at[:16]} "
               "(the archive cannot be reached): FES caps lowered on another station since would not be known")
        self.supervisor.stimulation_withheld = why
        self.supervisor.record(journal.STIMULATION_WITHHELD, patient=patient_id, copy_read_at=read_at)
        self.supervisor.raise_alarm(AlarmLevel.WARNING, "archive", f"Stimulation withheld: {why}.")

    def start_lsl(self) -> Any:
        """The LSL outlets when ``recording.lsl`` is on, opened once whatever asks (a session, a headless run):
        twice would publish every stream twice with one silent event outlet (#41). None when off or unavailable."""
        if self.config.recording.lsl and self._lsl is None:
            from app.session.lsl import start_lsl

            self._lsl = start_lsl(self)
        return self._lsl

    def update_session_profile(self, profile: Any, version: int | None = None) -> list[str]:
        """The session patient's profile was saved again (Patients window, an electrode choice): what it
        changes applies to the next command at once — the robot limits, the FES caps (a lowered cap below a
        running profile stops it), the chosen electrodes, the gains — and is recorded. ``version``: the archive
        record's version of ``profile`` (kept with the session). Returns the changes in words ([] when
        ``profile`` is not this session's patient)."""
        from app.therapy.patients import effective_robot_limits, profile_changes

        old = self.patient_profile
        if self.recorder is None or old is None or profile.patient_id != old.patient_id:
            return []
        if version is not None and version < self.patient_version:
            return []  # an older copy than the session's (a late reader): the session keeps the newer one
        changes = profile_changes(old, profile)
        self.patient_profile = profile
        if version is not None:
            self.patient_version = version
            if self.supervisor.stimulation_withheld:
                from app.archive import station

                if not station.copy_in_use(profile.patient_id):  # the archive's own record reached the session
                    self.supervisor.stimulation_withheld = ""
                    changes = [*changes, "stimulation no longer withheld (the archive's record)"]
        self.supervisor.robot = effective_robot_limits(profile, self.config.safety.robot)
        self._apply_robot_limits()
        self.apply_patient_profile(profile)
        if changes:
            self.record_event("patient_profile_updated", patient=profile.patient_id, changes=changes)
        if QThread.currentThread() is self.thread() and QCoreApplication.instance() is not None:
            self._check_plan_off_thread(profile)  # the window's thread: it does not wait for the check
        else:
            self._check_plan(profile)
        self.profile_changed.emit(profile)
        return changes

    def _next_plan_generation(self) -> int:
        with self._plan_lock:
            self._plan_generation += 1
            return self._plan_generation

    def _check_plan(self, profile: Any) -> list[str]:
        """The therapy plan against the patient's limits, caps and electrode choices now (at the session's start
        and when the profile changes): what would be refused is recorded before anything moves."""
        self._next_plan_generation()  # a check still running for an older profile is overtaken by this one
        problems = self._plan_problems(profile)
        if problems:
            self.record_event("plan_problems", patient=profile.patient_id, problems=problems)
        return problems

    def _plan_problems(self, profile: Any) -> list[str]:
        """What the plan's steps would meet as refusals (Qt-free, any thread: reads the library and the profile)."""
        from app.therapy.exercises import load_library
        from app.therapy.patients import plan_problems, prescription_problems

        try:
            library = load_library()[0]  # read once for both checks
            return [str(p) for p in plan_problems(profile.therapy_plan, library)
                    + prescription_problems(profile.therapy_plan, profile, self.config.safety, library)]
        except Exception:  # a broken library must not stop the session: the Exercises tab lists it
            log.exception("the therapy plan could not be checked")
            return []

    def _check_plan_off_thread(self, profile: Any) -> None:
        """``_check_plan`` with the reading and checking (~25 ms: the library's YAML, every step, the FES profiles)
        on a thread of its own, so the window's thread turns meanwhile (#37: it ran there after the plan form
        closed). Only the record waits for it: the limits and caps were applied before (the supervisor holds them,
        the next command meets them); the check only says what the plan would meet. Its answer comes back to this
        thread with the generation it was started with, and is recorded only if no newer check began and the
        session still holds that very profile: never an older plan's problems after a newer save, never after the
        session ended."""
        generation = self._next_plan_generation()
        self.plan_checks_pending += 1

        def check() -> None:
            problems = self._plan_problems(profile)
            try:
                self._plan_checked.emit(generation, profile, problems)  # queued to this thread
            except RuntimeError:  # the manager is gone (the application closed meanwhile): nobody to tell
                pass

        threading.Thread(target=check, name="plan-check", daemon=True).start()

    def _take_plan_check(self, generation: int, profile: Any, problems: list[str]) -> None:
        self.plan_checks_pending = max(0, self.plan_checks_pending - 1)
        with self._plan_lock:
            current = generation == self._plan_generation
        if current and problems and self.recorder is not None and self.patient_profile is profile:
            self.record_event("plan_problems", patient=profile.patient_id, problems=problems)

    def end_session(self, reason: str = "ended by the operator") -> None:
        recorder, self.recorder = self.recorder, None
        if recorder is None:
            return
        self._end_open_runs("session_ended" if reason != "application closing" else "app_exit")  # recorded
        self.supervisor.stimulation_withheld = ""  # the session's copy goes with it
        self.supervisor.bring_to_safe_state("session ended")
        for handle in list(self.devices.values()):  # counts a driver records only now and then, up to now
            record_counts = getattr(handle.driver, "record_link_counts", None)
            if callable(record_counts):
                record_counts()
        recorder.stop(reason)
        self.supervisor.robot = self.config.safety.robot
        self._apply_robot_limits()
        self.patient_profile = None
        self.patient_version = 0
        set_districts = getattr(self.driver(streams.FES), "set_district_channels", None)
        if callable(set_districts):  # the next patient's district profiles must not use this one's electrodes
            set_districts({})
        self.session_changed.emit(None)

    def _apply_robot_limits(self) -> None:
        robot = self._robot()
        if robot is not None and robot.connected:
            robot.apply_limits(self.supervisor.robot)

    def _new_run_log(self) -> Any:
        """The runs' changes are journal records (origin ``run``, naming the log) on the bus as they happen: the
        session's recorder, or the headless runner's, hears them there like any other record, and so do the leases
        (:meth:`hold_for_run`) and the progress. A run still open in the log this one replaces ends where it began
        (its runner holds that log); the session's end ends it there if it has not."""
        from app.core.runs import RunLog

        def record(kind: str, **data: Any) -> None:
            self.bus.record(journal.RUN, kind, data)

        previous = getattr(self, "runs", None)
        self._earlier_runs = [r for r in (*self._earlier_runs, previous)
                              if r is not None and r.current() is not None]
        runs = RunLog(record)
        self.progress.attach_runs(runs)
        return runs

    def _end_open_runs(self, reason: str) -> None:
        """A session's end, the application closing: every run still open ends with ``reason`` in its own log —
        the current log's and any an earlier log still holds open — and its record gives its devices back."""
        self.runs.end_running(reason)
        earlier, self._earlier_runs = self._earlier_runs, []
        for runs in earlier:
            runs.end_running(reason)

    def record_event(self, kind: str, who: str = "", **data: Any) -> None:
        """An event for the session record (the exercise chosen, parameter changes, the electrode set-up): one
        journal record of origin ``app`` on the bus, which whatever records the session writes (and the window's
        adapter shows); logged too when no session records."""
        self.bus.record(journal.APP, kind, dict(data), who=who or self.operator)
        if self.recorder is None:
            log.info("event %s by %s: %s", kind, who, data)

    def add_shutdown_hook(self, fn: Callable[[], None]) -> None:
        self._shutdown_hooks.append(fn)

    def _run_shutdown_hooks(self) -> None:
        """Each hook once, the newest first."""
        hooks, self._shutdown_hooks = self._shutdown_hooks, []
        for fn in reversed(hooks):
            try:
                fn()
            except Exception:
                log.exception("shutdown hook failed")

    def shutdown(self, timeout_s: float = 1.0) -> None:
        """Bring every device to a safe state, then stop all threads and helper processes."""
        if not self._started:
            self._run_shutdown_hooks()  # e.g. a script console's kernel, made before any device started
            return
        self._started = False
        t0 = time.monotonic()
        self._end_open_runs("app_exit")
        self.supervisor.bring_to_safe_state("application closing")
        if self.recorder is not None:
            self.end_session("application closing")
        if self._lsl is not None:
            self._lsl.stop()
            self._lsl = None
        self._run_shutdown_hooks()
        if not self.therapy.stop(timeout_s):
            log.error("the therapy thread did not stop within %.2f s", timeout_s)
        for handle in self.devices.values():
            handle.driver._stop.set()  # all at once, then wait: total time = the slowest, not the sum
        for handle in self.devices.values():
            remaining = max(0.05, timeout_s - (time.monotonic() - t0))
            if not handle.driver.stop(remaining):
                log.error("driver %s did not stop within %.2f s", handle.name, timeout_s)
        for handle in self.devices.values():
            if handle.simulator is not None:
                handle.simulator.stop()
            for proc in handle.extras.get("processes", []):
                _stop_process(proc)
        self.simulators.stop()
        shutil.rmtree(self.runtime_dir, ignore_errors=True)
        log.info("manager shut down in %.3f s", time.monotonic() - t0)

    def sim_patient(self) -> Any:
        """The one simulated patient shared by every simulator (grip and handle forces); in the simulator
        process, a proxy with the same behaviours."""
        return self.simulators.patient()

    @property
    def patient(self) -> Any:
        """The simulated patient when a device is simulated on a serial link, else None."""
        return self.simulators._patient

    def set_device_running(self, name: str, running: bool, timeout_s: float = 1.0) -> bool:
        """Connect or disconnect one device (its simulator, if any, keeps running). A device is put in
        its safe state (robot IDLE, stimulation stopped) before its link is closed."""
        handle = self.devices.get(name)
        if handle is None:
            return False
        self.supervisor.record(journal.DEVICE_TOGGLED, device=name, running=running)
        if running:
            handle.driver.resume()
            return True
        safe_stop = handle.extras.get("safe_stop")
        if callable(safe_stop):
            try:
                safe_stop(f"{name} disconnected by the operator")
            except Exception:
                log.exception("safe stop of %s failed", name)
        return handle.driver.stop(timeout_s)

    # ------------------------------------------------------------------ queries
    def driver(self, name: str) -> DeviceDriver | None:
        """The driver of device ``name`` (its commands and link state; its samples are on ``bus``)."""
        handle = self.devices.get(name)
        return handle.driver if handle else None

    def all_connected(self) -> bool:
        return bool(self.devices) and all(h.driver.connected for h in self.devices.values())

    def all_ready(self) -> bool:
        """Connected, and each device that announces itself has (a ScienceMode 2 stimulator's Init): what a
        script needs before its first command (a headless script's fes.start() came before the Init)."""
        return self.all_connected() and all(bool(getattr(h.driver, "device_ready", True))
                                            for h in self.devices.values())


def _command(robot: LinarmDriver, args: tuple[Any, ...], source: str) -> None:
    """One robot command from the therapy thread; a refusal or a failed ack is logged, never raised (the next
    α or target tries again)."""
    def report(future: Future) -> None:
        exc = future.exception()
        if exc is not None:
            log.warning("%s not applied: %s", source, exc)

    try:
        result = robot.command(*args, source=source)
    except Exception as exc:
        log.warning("%s not applied: %s", source, exc)
        return
    if isinstance(result, Future):  # a command path that returns its status instead of waiting for the ack
        result.add_done_callback(report)


def _stop_process(proc: Any) -> None:
    try:
        proc.terminate()
        proc.wait(timeout=1.0)
    except Exception:
        try:
            proc.kill()
        except Exception:
            log.exception("could not stop helper process")
