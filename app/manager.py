"""LinarmppManager: owns the devices (drivers and, when simulated, their simulators), the safety
supervisor, and the shared update notifier. The GUI, the script runner and the headless runner
all work through one manager; none of them touches a port.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PySide6.QtCore import QObject, Signal

from app.config import AppConfig
from app.devices.driver import DeviceDriver, UpdateNotifier
from app.devices.registry import DeviceFactory, DeviceHandle, SimulatorHosting, build_devices
from app.paths import runtime_dir
from app.safety import SafetySupervisor

log = logging.getLogger(__name__)

__all__ = ["DeviceFactory", "DeviceHandle", "LinarmppManager"]


class LinarmppManager(QObject):
    device_connection_changed = Signal(str, bool, str)  # device, connected, reason
    session_changed = Signal(object)  # the session folder (Path) or None when no session runs

    def __init__(self, config: AppConfig, factories: dict[str, DeviceFactory] | None = None) -> None:
        super().__init__()
        self.config = config
        self.notifier = UpdateNotifier()
        self.supervisor = SafetySupervisor(config.safety)
        self.runtime_dir: Path = runtime_dir()
        self.devices: dict[str, DeviceHandle] = {}
        self.simulators = SimulatorHosting(config, self.runtime_dir)
        if factories is None:
            from app.devices.registry import default_factories

            factories = default_factories(config)
        self._factories = factories
        self._started = False
        self._shutdown_hooks: list[Callable[[], None]] = []
        self.recorder: Any = None  # app.recording.SessionRecorder while a session runs
        self.patient_profile: Any = None
        self.operator = ""
        self._lsl: Any = None
        self.assistance: Any = None  # app.assistance.AssistanceController, created in start()
        from app.progress import ExerciseProgress

        self.progress = ExerciseProgress(self.supervisor.event)  # the running exercise's repetitions
        self.runs = self._new_run_log()  # the exercise runs (app/runs.py); a new log for each session
        from app.fault_policy import FaultPolicy

        self.fault_policy = FaultPolicy(self)  # every STOP alarm -> safe state (window and headless alike)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Build every configured device (app.devices.registry), start the simulators (their own
        process, or threads here), then the drivers."""
        if self._started:
            return
        self._started = True
        self.devices = build_devices(
            self._factories, self.config, notifier=self.notifier, supervisor=self.supervisor,
            runtime_dir=self.runtime_dir, simulators=self.simulators, app=self,
            on_error=lambda name, exc: self.supervisor.event("device_error", device=name, error=str(exc)))
        try:
            self.simulators.start()
        except Exception as exc:
            log.exception("the simulated devices could not be started")
            self.supervisor.event("device_error", device="simulators", error=str(exc))
        for name, handle in self.devices.items():
            self._watch_device(handle)
            handle.driver.connection_changed.connect(
                lambda ok, why, n=name: self.device_connection_changed.emit(n, ok, why))
            if handle.simulator is not None:
                handle.simulator.start()
            handle.driver.start()
        log.info("devices started: %s", ", ".join(self.devices) or "none")
        self.fault_policy.attach_devices()
        self._wire_assistance()

    # ------------------------------------------------------------------ the therapy loop
    def _wire_assistance(self) -> None:
        """α from the patient model → split → robot (k_m, k_a, k_t) and FES (pulse width), and the VR
        task's target → the robot's assistance target. Commands go through the drivers' checked paths
        on a worker thread, so a slow ack never stalls the patient-model link."""
        from concurrent.futures import ThreadPoolExecutor

        from app.assistance import AssistanceController, AssistanceInactive

        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="assistance")
        executor.submit(lambda: None)  # its thread exists from start-up, not from the first α (ends at shutdown)
        self.add_shutdown_hook(lambda: executor.shutdown(wait=False, cancel_futures=True))

        def report(future: Any) -> None:
            exc = future.exception()
            if exc is not None:
                log.warning("assistance not applied: %s", exc)

        from app.devices.linarm_protocol import ControlMode, ControlState

        assisted_modes = (int(ControlMode.POS_REF_BY_ADMITTANCE), int(ControlMode.POS_REF_BY_ASSISTANCE))

        def apply_robot(k_m: float, k_a: float, k_t: float) -> None:
            # The robot's share of α only acts in the interaction modes it parameterises (admittance,
            # assistance) while ON: a position-controlled exercise or a script's moves are never altered.
            robot = self.driver("linarm")
            if robot is None or not robot.connected:
                raise AssistanceInactive("the LINarm is not connected")
            state = robot.latest("linarm.state")
            if state is None or state.controlState != int(ControlState.ON_CTRL_STATE) \
                    or state.controlMode not in assisted_modes:
                raise AssistanceInactive("robot assistance applies only while ON in admittance or assistance mode")

            # Each parameter on its own: a refused one must not hold back the others.
            for args in (("setAdmittanceParameter", k_a), ("setAssistanceParameter", k_t),
                         ("setStiffness", k_m, 0.05, 0.2, 0.0)):
                executor.submit(robot.command, *args, source="assistance").add_done_callback(report)

        def apply_fes_pulse_width(pulse_width_us: float) -> None:
            fes = self.driver("fes")
            if fes is None or not hasattr(fes, "set_pulse_width_override"):
                raise AssistanceInactive("no FES device")
            fes.set_pulse_width_override(pulse_width_us)

        self.assistance = AssistanceController(self.config.assistance, apply_robot, apply_fes_pulse_width,
                                               supervisor=self.supervisor)
        model = self.driver("patient_model")
        if model is not None:
            model.add_listener(self.assistance.on_patient_model_sample)
            assistance = self.assistance

            def model_lost(event: str, _detail: str) -> None:
                if event in ("disconnected", "silent"):
                    assistance.invalidate()  # no stale α is ever applied, whatever the GUI changes meanwhile

            model.add_event_listener(model_lost)
        vr = self.driver("vr")
        robot = self.driver("linarm")
        if vr is not None and robot is not None:
            last = {"target": None}

            def follow_target(stream: str, t: float, sample: Any) -> None:
                target = getattr(sample, "targetPos", None)
                if target is None or target != target or target == last["target"]:
                    return
                state = robot.latest("linarm.state")
                if not robot.connected or state is None or not state.initialized:
                    return
                last["target"] = target
                executor.submit(robot.command, "setAssistanceTargetPos", float(target),
                                source="VR task").add_done_callback(report)

            vr.add_listener(follow_target)

    def apply_patient_profile(self, profile: Any) -> None:
        """The patient's clinical score feeds the embedded model; their gains the assistance split."""
        model = self.driver("patient_model")
        score = profile.scores.fugl_meyer_ue
        if model is not None and score is not None and hasattr(model, "clinical_score"):
            model.clinical_score = int(score)
        if self.assistance is not None:
            self.assistance.set_gains(profile.assistance.k_r, profile.assistance.k_f)
        fes = self.driver("fes")
        set_caps = getattr(fes, "set_clinical_caps", None)
        if callable(set_caps):
            from app.patients import clinical_caps

            set_caps(clinical_caps(profile))
        set_districts = getattr(fes, "set_district_channels", None)
        if callable(set_districts):  # district-addressed FES profiles use the patient's chosen electrodes
            set_districts(profile.fes.district_channels())
        self.supervisor.event("patient_profile_applied", patient=profile.patient_id,
                              k_r=profile.assistance.k_r, k_f=profile.assistance.k_f, clinical_score=score)

    # ------------------------------------------------------------------ sessions
    def start_session(self, patient_id: str, operator: str, note: str = "", root: Path | None = None) -> Path:
        """A session = a patient + an operator + a recording that starts now. The patient's profile
        narrows the safety limits for its duration. Raises ValueError/PatientError, nothing started."""
        from app.patients import effective_robot_limits, load_patient, patient_file
        from app.recording import SessionRecorder, sessions_root

        if self.recorder is not None:
            raise RuntimeError("a session is already running; end it first")
        profile = None
        if patient_file(patient_id).exists():
            profile = load_patient(patient_id, self.config.safety)  # a bad profile refuses the session
        else:
            log.info("patient %s has no profile: the configured limits apply", patient_id)
        recorder = SessionRecorder()
        folder = recorder.start(self, patient_id, operator, note, root=root or sessions_root(self.config),
                                profile=profile)
        self.recorder = recorder
        self.patient_profile = profile
        self.operator = operator
        self.runs = self._new_run_log()
        if profile is not None:
            self.supervisor.robot = effective_robot_limits(profile, self.config.safety.robot)
            self.supervisor.event("patient_limits_applied", patient=patient_id)
            self._apply_robot_limits()
            apply_profile = getattr(self, "apply_patient_profile", None)
            if callable(apply_profile):
                apply_profile(profile)
        if self.config.recording.lsl and self._lsl is None:
            from app.lsl import start_lsl

            self._lsl = start_lsl(self)
            if self._lsl is not None:
                recorder.add_event_tap(self._lsl.marker)
        self.session_changed.emit(folder)
        return folder

    def end_session(self, reason: str = "ended by the operator") -> None:
        recorder, self.recorder = self.recorder, None
        if recorder is None:
            return
        self.runs.end_current("session_ended" if reason != "application closing" else "app_exit")  # recorded
        self.supervisor.bring_to_safe_state("session ended")
        recorder.stop(reason)
        self.supervisor.robot = self.config.safety.robot
        self._apply_robot_limits()
        self.patient_profile = None
        set_districts = getattr(self.driver("fes"), "set_district_channels", None)
        if callable(set_districts):  # the next patient's district profiles must not use this one's electrodes
            set_districts({})
        self.session_changed.emit(None)

    def _apply_robot_limits(self) -> None:
        robot = self.driver("linarm")
        if robot is not None and robot.connected and hasattr(robot, "apply_limits"):
            robot.apply_limits(self.supervisor.robot)

    def _new_run_log(self) -> Any:
        """The runs go into the session record as they happen (record_event). Without the window's session, as
        the supervisor's events: a recorder of its own (the headless runner's) hears those."""
        from app.runs import RunLog

        def record(kind: str, **data: Any) -> None:
            if self.recorder is not None:
                self.record_event(kind, **data)
            else:
                self.supervisor.event(kind, **data)

        runs = RunLog(record)
        self.progress.attach_runs(runs)
        return runs

    def record_event(self, kind: str, who: str = "", **data: Any) -> None:
        """An event for the session record (script start/stop, parameter changes); logged without one."""
        if self.recorder is not None:
            self.recorder.event(kind, who or self.operator, **data)
        else:
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
        self.runs.end_current("app_exit")
        self.supervisor.bring_to_safe_state("application closing")
        if self.recorder is not None:
            self.end_session("application closing")
        if self._lsl is not None:
            self._lsl.stop()
            self._lsl = None
        self._run_shutdown_hooks()
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
        self.supervisor.event("device_toggled", device=name, running=running)
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

    def _watch_device(self, handle: DeviceHandle) -> None:
        """Connection loss and silence become alarms (and events in the session record)."""
        from app.safety import AlarmLevel

        name = handle.name
        state: dict[str, Any] = {"was_connected": False, "silence_alarm": None}

        def on_event(event: str, detail: str) -> None:
            if event == "connected":
                if state["was_connected"]:
                    self.supervisor.raise_alarm(AlarmLevel.INFO, name, f"{name} reconnected")
                state["was_connected"] = True
            elif event == "disconnected" and state["was_connected"] and self._started:
                self.supervisor.raise_alarm(self.fault_policy.loss_level(name), name,  # STOP unless nothing needs it
                                            f"{name} connection lost: {detail}")
            elif event == "silent" and self._started:
                state["silence_alarm"] = self.supervisor.raise_alarm(AlarmLevel.WARNING, name,
                                                                     f"{name} stopped sending data")
            elif event == "alive" and state.get("silence_alarm") is not None:
                # The stream resumed: the warning says so and leaves the banner; it stays in the alarm history.
                alarm, state["silence_alarm"] = state["silence_alarm"], None
                try:
                    gap = f" after {float(detail):.1f} s"
                except ValueError:
                    gap = ""
                alarm.text = f"{alarm.text} (resumed{gap})"
                self.supervisor.event("stream_resumed", device=name, silent_s=detail, ident=alarm.ident)
                self.supervisor.acknowledge(alarm.ident, operator=f"{name} resumed")
            elif event == "controller_error":
                self.supervisor.raise_alarm(AlarmLevel.STOP, name, detail)

        handle.driver.add_event_listener(on_event)

    # ------------------------------------------------------------------ queries
    def driver(self, name: str) -> DeviceDriver | None:
        handle = self.devices.get(name)
        return handle.driver if handle else None

    def all_connected(self) -> bool:
        return bool(self.devices) and all(h.driver.connected for h in self.devices.values())


def _stop_process(proc: Any) -> None:
    try:
        proc.terminate()
        proc.wait(timeout=1.0)
    except Exception:
        try:
            proc.kill()
        except Exception:
            log.exception("could not stop helper process")
