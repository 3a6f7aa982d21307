"""``python main.py --headless --script FILE [--duration S] [--record DIR]``: a script without a window.

Starts the configured devices (simulated by default), waits for them, homes the LINarm when the
controller says it is not homed (as the seed's scripts assume), runs the script, prints its output,
records the session when asked (app.session.recording.SessionRecorder, into ``DIR/<patient>/<date-time>/``),
brings the devices to a safe state and exits:

* 0 — the script finished, or was stopped because ``--duration`` was reached (counted from the start of
  the script's own code, after any homing);
* 1 — the script raised an error (its traceback is printed), could not be read or compiled, or its
  process (the script kernel) ended by itself — a segfault, ``os._exit``, out of memory;
* 3 — a safety stop: a command refused by the safety supervisor, an emergency stop, or an alarm of
  level STOP (e.g. the LINarm latched an error, a device lost, the recording failed) during the run —
  the fault policy (app.safety.fault_policy, the same as the window's) has already stopped FES, the robot and
  the script;
* 4 — the session cannot be recorded (``--record`` folder unwritable, or too little free space): one line
  on stderr, nothing was started;
* 128 + the signal's number — ended by SIGINT (130, Ctrl-C), SIGTERM (143) or SIGHUP (129): the devices were
  brought to a safe state at once (app.core.signal_events: on a thread of its own, once however many signals
  arrive), then the script was stopped, the recording closed and the devices shut down as on any other end.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from app.core import streams
from app.core.config import AppConfig

if TYPE_CHECKING:
    from PySide6.QtCore import QCoreApplication

    from app.core.signal_events import SignalEvents
    from app.manager import LinarmppManager
    from app.safety.supervisor import AlarmLevel

log = logging.getLogger(__name__)

EXIT_OK, EXIT_ERROR, EXIT_SAFETY, EXIT_RECORDING, EXIT_INTERRUPTED = 0, 1, 3, 4, 130
CONNECT_TIMEOUT_S = 10.0
HEADLESS_PATIENT = "headless"


def run_headless(config: AppConfig, script_path: str, duration_s: float | None = None,
                 record_dir: str | None = None, *, home_first: bool = True,
                 prepare: Callable[[LinarmppManager], None] | None = None,
                 output: Callable[[str, str], None] | None = None, patient: str | None = None,
                 operator: str = "") -> int:
    """Run ``script_path`` against the devices of ``config``; returns the process exit code.

    ``prepare(manager)`` runs once the devices are connected, before the script (tests use it to set the
    simulated patient's behaviour); ``output(stream, text)`` replaces printing to stdout/stderr. ``patient`` and
    ``operator``: the run is that patient's session (``LinarmppManager.start_session``, as the window starts one:
    their profile's limits and caps apply), recorded into ``record_dir`` or the station's sessions folder."""
    from PySide6.QtCore import QCoreApplication

    from app.manager import LinarmppManager
    from app.safety.supervisor import AlarmLevel
    from app.scripting.runner import ScriptRunner

    path = Path(script_path)
    try:
        source = path.read_text(encoding="utf-8")
        compile(source, str(path), "exec")
    except (OSError, SyntaxError, ValueError) as exc:
        print(f"Cannot run {script_path}: {exc}", file=sys.stderr)
        return EXIT_ERROR
    app = QCoreApplication.instance() or QCoreApplication([sys.argv[0] if sys.argv else "linarmpp"])
    if patient and not record_dir:  # a patient's session goes where the window's go: the station's outbox
        from app.session.recording import sessions_root

        record_dir = str(sessions_root(config))
    if record_dir:
        problem = _record_dir_problem(Path(record_dir), config)
        if problem:
            print(f"Cannot record: {problem}", file=sys.stderr)
            return EXIT_RECORDING
    manager = LinarmppManager(config)
    recorder = None
    lsl = None
    runner = None
    code = EXIT_OK
    from app.core.signal_events import SignalEvents, exit_code_for, signal_name

    def on_signal(signum: int) -> None:  # the signal thread, once: the run loops below see `signals.received`
        manager.supervisor.bring_to_safe_state(f"{signal_name(signum)} received")

    signals = SignalEvents(on_signal, last_resort=on_signal).install()
    try:
        manager.start()
        _wait_connected(manager, app, signals)
        if signals.received is not None:
            return exit_code_for(signals.received)
        if prepare is not None:
            prepare(manager)
        if record_dir:
            from app.session.recording import RecordingError, SessionRecorder
            from app.therapy.patients import PatientError

            recorder = SessionRecorder()
            try:
                if patient:
                    folder = manager.start_session(patient, operator, note=f"script {path.name}",
                                                   root=Path(record_dir))
                    recorder = manager.recorder
                else:
                    folder = recorder.start(manager, HEADLESS_PATIENT, "headless runner", note=f"script {path.name}",
                                            root=Path(record_dir))
            except PatientError as exc:
                recorder = None
                _emit(output, "stderr", f"The session was not started: {exc}\n")
                return EXIT_ERROR
            except (RecordingError, OSError) as exc:
                recorder = None
                _emit(output, "stderr", f"Cannot record: {exc.strerror if isinstance(exc, RecordingError) else exc}\n")
                return EXIT_RECORDING
            _emit(output, "info", f"Recording the session in {folder}\n")
        lsl = manager.start_lsl()  # the manager's outlets: one set, shared with a session the run starts (#41)
        if lsl is not None and recorder is not None:
            recorder.add_event_tap(lsl.marker)
        alarms_before = {a.ident for a in manager.supervisor.alarms()}
        runner = ScriptRunner(manager, output or _print_sink, home_first=home_first)
        runner.start(source, str(path.resolve()), run_source="headless")  # a run of the session record
        safety_stop = ""
        try:
            while not runner.wait(0.02):
                app.processEvents()
                if signals.received is not None and not runner.stop_reason:
                    runner.request_stop(f"{signal_name(signals.received)} received")
                t0 = runner.body_started_at  # the duration is the script's own: homing first does not count
                if (duration_s is not None and t0 is not None and time.monotonic() - t0 >= duration_s
                        and not runner.stop_reason):
                    runner.request_stop(f"the duration of {duration_s:g} s was reached")
                if not safety_stop:
                    safety_stop = _safety_stop(manager, alarms_before, AlarmLevel.STOP)
                    if safety_stop:
                        runner.request_stop(f"safety stop: {safety_stop}", cause="safety_stop")
        except KeyboardInterrupt:
            runner.stop("interrupted (Ctrl-C)")
            runner.wait(5.0)
            return EXIT_INTERRUPTED
        _let_the_record_show_the_safe_state(manager, app)
        if signals.received is not None:
            signals.wait(2.0)  # the safe state it started
            return exit_code_for(signals.received)
        result = runner.result
        safety_stop = safety_stop or _safety_stop(manager, alarms_before, AlarmLevel.STOP)
        if result is None or result.status == "error":
            code = EXIT_ERROR
        elif result.status == "refused" or safety_stop:
            code = EXIT_SAFETY
            if safety_stop:
                _emit(output, "stderr", f"Safety stop: {safety_stop}\n")
    finally:
        try:
            if runner is not None:
                runner.close()  # its kernel processes end with the run
            if recorder is not None and manager.recorder is recorder:
                manager.end_session("headless run ended")  # the patient's session, ended as the window ends one
            elif recorder is not None:
                recorder.stop("headless run ended")  # never raises: a write failure is in the manifest and the log
            if lsl is not None:
                lsl.stop()
            manager.shutdown()
            app.processEvents()
        finally:
            signals.remove()
    line = _archive_line(config, Path(record_dir)) if recorder is not None and record_dir else ""
    if line:
        _emit(output, "stdout", line + "\n")
    return code


def _archive_line(config: AppConfig, root: Path) -> str:
    """The run's last line ('' without an archive): its session (and any left over under ``root``) uploaded to
    the station's archive now — "Session archived." or "1 session waiting for the archive (…)." (issue #39: the
    station keeps working offline; the next start or run uploads it)."""
    from app.archive import station

    if not station.in_use():  # a library use of the runner: no archive
        return ""
    from app.archive.outbox import headless_pass

    try:
        return headless_pass(config, root)
    except Exception as exc:  # never a traceback at the end of a run that went well
        log.exception("archiving the session failed")
        return f"1 session waiting for the archive (it could not be uploaded: {exc})."


def _record_dir_problem(root: Path, config: AppConfig) -> str:
    """Why sessions cannot be recorded under ``root`` ('' when they can): checked before anything starts."""
    import os

    from app.session.recording import RecordingError, check_free_space

    try:
        root.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as exc:
        return f"cannot create {root}: {exc.strerror or exc}"
    if not root.is_dir() or not os.access(root, os.W_OK | os.X_OK):
        return f"{root} is not a writable folder"
    try:
        warning = check_free_space(root, config.recording.warn_free_mib, config.recording.min_free_mib)
    except RecordingError as exc:
        return str(exc.strerror)
    if warning:
        log.warning("%s", warning)
    return ""


def _wait_connected(manager: LinarmppManager, app: QCoreApplication, signals: SignalEvents | None = None) -> None:
    deadline = time.monotonic() + CONNECT_TIMEOUT_S
    while not manager.all_ready() and time.monotonic() < deadline:
        if signals is not None and signals.received is not None:
            return
        app.processEvents()
        time.sleep(0.02)
    missing = [name for name, h in manager.devices.items()
               if not h.driver.connected or not getattr(h.driver, "device_ready", True)]
    if missing:
        log.warning("headless: not connected and ready after %.0f s: %s (the script may fail on them)",
                    CONNECT_TIMEOUT_S, ", ".join(missing))


def _let_the_record_show_the_safe_state(manager: LinarmppManager, app: QCoreApplication,
                                        timeout_s: float = 0.5) -> None:
    """The LINarm reports its state at 20 Hz: wait for a state sample taken after the safe state, so that a
    recording ends with it (IDLE, or still ON when holding)."""
    driver = manager.driver(streams.LINARM)
    if driver is None or not driver.connected:
        return
    bus = manager.bus
    before = bus.total(streams.LINARM_STATE)
    deadline = time.monotonic() + timeout_s
    while bus.total(streams.LINARM_STATE) < before + 2 and time.monotonic() < deadline:
        app.processEvents()
        time.sleep(0.01)


def _safety_stop(manager: LinarmppManager, before: set[int], level: AlarmLevel) -> str:
    sup = manager.supervisor
    if sup.estop_latched:
        return "the emergency stop is latched"
    for alarm in sup.alarms():
        if alarm.ident not in before and alarm.level >= level:
            return alarm.text
    return ""


def _emit(output: Callable[[str, str], None] | None, stream: str, text: str) -> None:
    (output or _print_sink)(stream, text)


def _print_sink(stream: str, text: str) -> None:
    target = sys.stderr if stream == "stderr" else sys.stdout
    target.write(text)
    target.flush()
