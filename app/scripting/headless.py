"""``python main.py --headless --script FILE [--duration S] [--record DIR]``: a script without a window, and
``--headless --exercise NAME [--param NAME=VALUE …]``: a library exercise by its form's values.

Starts the configured devices (simulated by default), waits for them, homes the LINarm when the
controller says it is not homed (as the seed's scripts assume), runs the script, prints its output,
records the session when asked (app.session.recording.SessionRecorder, into ``DIR/<patient>/<date-time>/``),
brings the devices to a safe state and exits. An exercise starts as the Exercises tab starts one
(app.therapy.exercises.start_exercise: its values checked by its form's rule and against the limits and caps in
force, ``exercise_start`` recorded, a run of kind "exercise" holding the robot — and the stimulator when it
stimulates — with the source "headless"); its name and values are checked before anything starts
(:func:`library_exercise`, :func:`exercise_values`, :func:`prescription_refusal`). Exit codes:

* 0 — the script finished, or was stopped because ``--duration`` was reached (counted from the start of
  the script's own code, after any homing);
* 1 — the script raised an error (its traceback is printed), could not be read or compiled, or its
  process (the script kernel) ended by itself — a segfault, ``os._exit``, out of memory;
* 2 — the exercise was refused when it was to start: the patient's limits, caps or electrode choices in force
  refuse its values (one sentence on stderr; nothing moved);
* 3 — a safety stop: a command refused by the safety supervisor, an emergency stop, or an alarm of
  level STOP (e.g. the LINarm latched an error, a device lost, the recording failed) during the run —
  the fault policy (app.safety.fault_policy, the same as the window's) has already stopped FES, the robot and
  the script; or an exercise that could not start because a STOP holds the robot;
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
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.core import streams
from app.core.config import AppConfig

if TYPE_CHECKING:
    from PySide6.QtCore import QCoreApplication

    from app.core.signal_events import SignalEvents
    from app.manager import LinarmppManager
    from app.safety.supervisor import AlarmLevel
    from app.scripting.runner import ScriptRunner
    from app.therapy.exercises import Exercise, Parameter
    from app.therapy.patients import PatientProfile

log = logging.getLogger(__name__)

EXIT_OK, EXIT_ERROR, EXIT_REFUSED, EXIT_SAFETY, EXIT_RECORDING, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130
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
    path = Path(script_path)
    try:
        source = path.read_text(encoding="utf-8")
        compile(source, str(path), "exec")
    except (OSError, SyntaxError, ValueError) as exc:
        print(f"Cannot run {script_path}: {exc}", file=sys.stderr)
        return EXIT_ERROR

    def start(runner: ScriptRunner, _manager: LinarmppManager) -> None:
        runner.start(source, str(path.resolve()), run_source="headless")  # a run of the session record

    return _run(config, start, f"script {path.name}", duration_s, record_dir, home_first=home_first,
                prepare=prepare, output=output, patient=patient, operator=operator)


def run_headless_exercise(config: AppConfig, exercise: Exercise, values: Mapping[str, Any],
                          duration_s: float | None = None, record_dir: str | None = None, *, home_first: bool = True,
                          prepare: Callable[[LinarmppManager], None] | None = None,
                          output: Callable[[str, str], None] | None = None, patient: str | None = None,
                          operator: str = "") -> int:
    """Run the library exercise ``exercise`` with its form's ``values`` as :func:`run_headless` runs a script
    (the same devices, session, duration, safety stops and exit codes), started as the Exercises tab starts it:
    app.therapy.exercises.start_exercise on the run's ScriptRunner, with the source "headless". Values the
    patient's limits, caps or electrode choices in force refuse: one sentence on stderr, exit 2, nothing moved."""
    from app.therapy.exercises import start_exercise

    def start(runner: ScriptRunner, manager: LinarmppManager) -> None:
        try:
            checked = start_exercise(runner, manager, exercise, values, source="headless")
        except RuntimeError as exc:  # a STOP or the emergency stop holds the robot: nothing recorded, nothing moved
            raise _NotStarted(EXIT_SAFETY, f"The exercise was not started: {exc}.") from exc
        except (SyntaxError, OSError) as exc:  # its script cannot be read or compiled
            raise _NotStarted(EXIT_ERROR, f"The exercise was not started: its script {exercise.script} cannot be "
                                          f"run ({exc}).") from exc
        if not checked.ok:
            raise _NotStarted(EXIT_REFUSED, f"The exercise was not started: {checked.message(exercise)}.")

    return _run(config, start, f"exercise {exercise.ident}", duration_s, record_dir, home_first=home_first,
                prepare=prepare, output=output, patient=patient, operator=operator)


class _NotStarted(Exception):
    """The run was refused at its start: ``code`` is the exit code, ``sentence`` says why."""

    def __init__(self, code: int, sentence: str) -> None:
        super().__init__(sentence)
        self.code = code
        self.sentence = sentence


class ExerciseRefused(ValueError):
    """``--exercise NAME --param NAME=VALUE`` refused before anything starts: the text is the one sentence that
    says why (without its final stop), naming the parameter and what it accepts."""


def library_exercise(name: str, library: Sequence[Exercise] | None = None,
                     problems: Sequence[str] | None = None) -> Exercise:
    """The exercise of the library (app.therapy.exercises.load_library, as the Exercises tab lists it) whose
    ident — its file's name without ``.yaml`` — or title is ``name``, case and surrounding spaces ignored.
    ``problems``: the library's lines for files it could not load (one of them may be the one named)."""
    from app.therapy.exercises import load_library

    if library is None:
        loaded, problems = load_library()
        library = loaded
    wanted = name.strip().casefold()
    for exercise in library:
        if wanted in (exercise.ident.casefold(), exercise.title.strip().casefold()):
            return exercise
    for line in problems or ():  # "<folder>/<ident>.yaml[:line]: why"
        if Path(line.split(":", 1)[0]).stem.casefold() == wanted:
            raise ExerciseRefused(f"the exercise {name} cannot be loaded ({line})")
    idents = ", ".join(e.ident for e in library) or "none"
    raise ExerciseRefused(f"there is no exercise {name!r} in the library (its exercises: {idents})")


def exercise_values(exercise: Exercise, assignments: Sequence[str]) -> dict[str, Any]:
    """The form's values from ``--param NAME=VALUE`` items (the others keep their defaults), each converted to its
    parameter's type and checked against its range by the form's own rule (app.therapy.exercises.validate, which
    the Exercises tab runs on what was typed). Raises ExerciseRefused naming the first parameter refused and
    what it accepts."""
    from app.therapy.exercises import validate

    given: dict[str, str] = {}
    for item in assignments:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            example = exercise.parameters[0].name if exercise.parameters else "NAME"
            raise ExerciseRefused(f"--param {item} is not NAME=VALUE (e.g. --param {example}=…)")
        if name in given:
            raise ExerciseRefused(f"--param {name} is given twice ({given[name]} and {value.strip()})")
        given[name] = value.strip()
    checked = validate(exercise, given)
    names = [p.name for p in exercise.parameters]
    for name in [*given, *checked.errors]:  # in the order given; a refused default (never: loading checks it) last
        why = checked.errors.get(name)
        if why is None:
            continue
        if name not in names:
            raise ExerciseRefused(f"{exercise.title} has no parameter {name!r} (its parameters: "
                                  f"{', '.join(names) or 'none'})")
        param = exercise.parameter(name)
        why = "" if param.type in ("bool", "choice") else f" ({why})"  # theirs only says what it accepts
        raise ExerciseRefused(f"--param {name}={given.get(name, param.default)} is refused, {param.label} accepts "
                              f"{_accepts(param)}{why}")
    return checked.params


def _accepts(param: Parameter) -> str:
    """What a parameter accepts, in words, from its own declaration (Parameter.describe_range)."""
    if param.type == "bool":
        return "yes or no"
    if param.type == "int":
        return f"whole numbers {param.describe_range()}"
    return param.describe_range()


def prescription_refusal(config: AppConfig, exercise: Exercise, values: Mapping[str, Any],
                         profile: PatientProfile) -> str:
    """Why this patient's prescription refuses the exercise with ``values`` ("" when it does not), checked before
    anything starts as the session's start will apply the profile (app.therapy.exercises.prescription_problems
    against their robot limits, their clinical FES caps and their chosen electrodes; the run's start checks the
    same again against what is then in force, app.therapy.exercises.run_problems)."""
    from app.safety.fes_limits import FesLimits
    from app.therapy.exercises import prescription_problems
    from app.therapy.patients import clinical_caps, effective_robot_limits

    problems = prescription_problems(exercise, values, robot=effective_robot_limits(profile, config.safety.robot),
                                     fes_limits=FesLimits.from_config(config.safety.fes, clinical_caps(profile)),
                                     district_channels=profile.fes.district_channels(), patient=profile.patient_id)
    return "; ".join(f"{exercise.parameter(name).label}: {why}" for name, why in problems.items())


def _run(config: AppConfig, start: Callable[[ScriptRunner, LinarmppManager], None], note: str,
         duration_s: float | None, record_dir: str | None, *, home_first: bool,
         prepare: Callable[[LinarmppManager], None] | None, output: Callable[[str, str], None] | None,
         patient: str | None, operator: str) -> int:
    """The devices, the session and the run for :func:`run_headless` and :func:`run_headless_exercise`:
    ``start(runner, manager)`` starts the run on ``runner`` (raises _NotStarted when it refuses)."""
    from PySide6.QtCore import QCoreApplication

    from app.manager import LinarmppManager
    from app.safety.supervisor import AlarmLevel
    from app.scripting.runner import ScriptRunner

    app = QCoreApplication.instance() or QCoreApplication([sys.argv[0] if sys.argv else "linarmpp"])
    from app.main_thread_gc import collect_on_the_main_thread

    collect_on_the_main_thread(app)  # the drivers' QObjects destroyed on their own thread (app/core/gc_policy.py)
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
                    folder = manager.start_session(patient, operator, note=note, root=Path(record_dir))
                    recorder = manager.recorder
                else:
                    folder = recorder.start(manager, HEADLESS_PATIENT, "headless runner", note=note,
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
        alarms_before = {a.ident for a in manager.supervisor.alarms()}
        runner = ScriptRunner(manager, output or _print_sink, home_first=home_first)
        try:
            start(runner, manager)
        except _NotStarted as exc:  # nothing moved; a patient's session so far is ended and archived as any other
            _emit(output, "stderr", exc.sentence + "\n")
            code = exc.code
        else:
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
