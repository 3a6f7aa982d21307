"""The script API's one definition, shared by the application and the script kernel (standard library only).

The seed's script API (D2.2 §3.6, §4 and the Appendix) is served twice: in the application by the objects of
:mod:`app.scripting.api` (they command the drivers, through the safety supervisor), and in the script kernel
(app/scripting/kernel.py, a ``python -I`` child process) by proxies that send each call to the application.
What both must agree on is written here, once:

* the errors a script sees (:class:`ScriptError` and its kinds, :class:`ScriptStopped`), the names they travel
  under between the two processes (:data:`WIRE_ERRORS`) and the names a script's namespace gives them
  (:data:`SCRIPT_ERRORS`);
* the callback plumbing of the ``set…CallbackFun`` methods (:func:`set_callbacks`), a script's interruptible
  sleep (:func:`interruptible_sleep`, its WAIT_SLICE_S bounding the Stop latency), how long a state attribute
  waits for a first sample, and where a script's file names resolve (:func:`resolve_path`);
* the objects' shapes (:data:`OBJECTS`): class names, the latest-sample properties and the callback setters
  with their streams, the methods and attributes a kernel may call beyond the robot's command table (which is
  the wire's, app/wire/linarm_protocol.py), with the docstrings a script's ``help()`` shows;
  :func:`apply_shape` puts a shape on a class and checks that the class implements it;
* ``linarmppManager`` (:class:`LinarmppManager`), the same class on both sides: what differs — where a file
  name resolves, how a program runs, where the e-stop and the progress marks go — is its :class:`ManagerPort`.

It imports nothing of the application: the kernel must not (its isolation: it reaches the devices only through
the application), so it loads this file by its path, under a name outside ``app`` (kernel.py,
``_load_api_spec``). Streams are named here by their constant's name in app/core/streams.py (``"LINARM_VSA"``), the
one place their names are spelled; the application resolves them and tells the kernel (its hello message).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple, Protocol


# ---------------------------------------------------------------------------------------------- errors
class ScriptStopped(BaseException):
    """Raised inside a script when it is stopped. A BaseException, so that a script's own
    ``except Exception:`` cannot swallow the Stop button."""


class ScriptError(RuntimeError):
    """A script API call failed; the message is a sentence a therapist can read."""


class DeviceUnavailable(ScriptError):
    """The device is not configured, not connected, or has not sent anything yet."""


NotInitializedError = DeviceUnavailable  # the seed's name (linarm_user.NotInitializedError)


class CommandError(ScriptError):
    """The device refused the command, reported an error, or did not answer in time."""


class CommandRefused(CommandError):
    """The safety supervisor refused the command (nothing was sent). Ends a headless run as a safety stop."""


# The errors a call's answer may carry from the application to the kernel, by name: the most specific first
# (the application names an error by the first kind it is; the kernel raises the kind the name says).
WIRE_ERRORS: tuple[tuple[type[BaseException], str], ...] = (
    (ScriptStopped, "ScriptStopped"), (CommandRefused, "CommandRefused"), (DeviceUnavailable, "DeviceUnavailable"),
    (CommandError, "CommandError"), (ScriptError, "ScriptError"), (TypeError, "TypeError"),
    (FileNotFoundError, "FileNotFoundError"), (KeyError, "KeyError"), (ValueError, "ValueError"),
    (OSError, "OSError"),
)
_WIRE_CLASSES: dict[str, type[BaseException]] = {name: kind for kind, name in WIRE_ERRORS}

# The error classes a script's namespace holds, by name (``except CommandRefused:``).
SCRIPT_ERRORS: dict[str, type[BaseException]] = {
    "ScriptError": ScriptError, "CommandError": CommandError, "CommandRefused": CommandRefused,
    "DeviceUnavailable": DeviceUnavailable, "NotInitializedError": NotInitializedError,
}


def wire_error_name(error: BaseException) -> str:
    """The name ``error`` travels under (an error of no listed kind: "ScriptError")."""
    return next((name for kind, name in WIRE_ERRORS if isinstance(error, kind)), "ScriptError")


def wire_error_class(name: object) -> type[BaseException]:
    """The class a travelling error's name stands for (an unknown name: ScriptError)."""
    return _WIRE_CLASSES.get(str(name), ScriptError)


def refused(error: BaseException) -> bool:
    """True when ``error``, or an error it was raised from, is a refusal of the safety supervisor."""
    seen: BaseException | None = error
    while seen is not None:
        if isinstance(seen, CommandRefused):
            return True
        seen = seen.__cause__
    return False


# ---------------------------------------------------------------------------------------------- waiting, files
WAIT_SLICE_S = 0.02  # longest uninterrupted wait of a script's thread: bounds the Stop latency
FIRST_SAMPLE_TIMEOUT_S = 2.0  # how long a state attribute waits for a device's first sample


def interruptible_sleep(seconds: float, stop_event: threading.Event, check: Callable[[], None]) -> None:
    """``time.sleep`` for scripts: waits in slices of WAIT_SLICE_S and ends early through ``check`` (which raises
    ScriptStopped) once ``stop_event`` is set."""
    seconds = float(seconds)
    if seconds < 0:
        raise ValueError("sleep length must be non-negative")
    deadline = time.monotonic() + seconds
    while True:
        check()
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return
        stop_event.wait(min(remaining, WAIT_SLICE_S))


def resolve_path(file_name: str, base_dir: Path | None, *extra_dirs: Path) -> Path:
    """A file name from a script: as given when absolute; else the first of the script's folder, the working
    folder and ``extra_dirs`` that holds it; else in the script's folder (or the working folder)."""
    path = Path(file_name).expanduser()
    if path.is_absolute():
        return path
    for folder in (base_dir, Path.cwd(), *extra_dirs):
        if folder is not None and (folder / path).exists():
            return folder / path
    return (base_dir or Path.cwd()) / path


# ---------------------------------------------------------------------------------------------- callbacks
Callback = Callable[[Any], Any]


def set_callbacks(target: list[Callback], fun: Any, what: str) -> None:
    """The seed's ``set…CallbackFun``: a callable is added to the list; a list replaces it; None clears it."""
    if fun is None:
        target.clear()
        return
    funs = list(fun) if isinstance(fun, list | tuple) else [fun]
    for f in funs:
        if not callable(f):
            raise TypeError(f"{what} expects a function taking one argument (the new data), got {f!r}")
    if isinstance(fun, list | tuple):
        target[:] = funs
    else:
        target.append(fun)


# ---------------------------------------------------------------------------------------------- shapes
class Property(NamedTuple):
    """A state attribute: the latest sample of ``stream`` (a constant's name in app/core/streams.py)."""

    stream: str
    doc: str


class CallbackSetter(NamedTuple):
    """``set…CallbackFun``: the script's ``list_name`` of functions, called on every ``stream`` sample."""

    stream: str
    list_name: str
    doc: str


class ObjectShape(NamedTuple):
    """One script-visible object: what a script sees of it on either side."""

    name: str  # its name in a script's namespace
    class_string: str  # the seed's class name (``classString``)
    label: str  # the device in a sentence ("the LINarm"): what an error names
    doc: str
    text: str  # its repr's words
    properties: Mapping[str, Property] = {}
    callbacks: Mapping[str, CallbackSetter] = {}
    methods: Mapping[str, str] = {}  # name -> doc: the calls a kernel may make (besides the robot's commands)
    attributes: Mapping[str, str] = {}  # name -> doc: values a kernel may read

    def callback_lists(self) -> tuple[str, ...]:
        return tuple(c.list_name for c in self.callbacks.values())


_MOTOR = "position (m), velocity (m/s), current (A), target (m) of motor {}."

LINARM = ObjectShape(
    "linarm", "LinarmUser", "the LINarm",
    "``linarm``: the LINarm2 robot. Commands are the controller's (docs/linarm-protocol.md) and block until it "
    "acknowledges them; state attributes are the latest samples of its streams, with the seed's field names "
    "(``equilibriumPos``…).",
    "LINarm2 robot",
    properties={
        "linarmState": Property("LINARM_STATE", "controlState, controlMode, homeState, errorState, triggerMode, "
                                                "initialized, trajectoryType, …"),
        "linarmVsaState": Property("LINARM_VSA", "equilibriumPos (m), delta (m), stiffness (N/m), handlePos (m), "
                                                 "handleVel (m/s), interactionForce (N)."),
        "linarmMotor0State": Property("LINARM_MOTOR0", _MOTOR.format(0)),
        "linarmMotor1State": Property("LINARM_MOTOR1", _MOTOR.format(1)),
    },
    callbacks={
        "setLinarmDataCallbackFun": CallbackSetter(
            "LINARM_STATE", "linarmDataCallbackList",
            "Call ``fun(linarmState)`` on every LINarm state sample (on the script's callback thread)."),
        "setLinarmMotor0DataCallbackFun": CallbackSetter(
            "LINARM_MOTOR0", "linarmMotor0DataCallbackList",
            "Call ``fun(linarmMotor0State)`` on every sample of motor 0 (on the script's callback thread)."),
        "setLinarmMotor1DataCallbackFun": CallbackSetter(
            "LINARM_MOTOR1", "linarmMotor1DataCallbackList",
            "Call ``fun(linarmMotor1State)`` on every sample of motor 1 (on the script's callback thread)."),
        "setLinarmVsaDataCallbackFun": CallbackSetter(
            "LINARM_VSA", "linarmVsaDataCallbackList",
            "Call ``fun(linarmVsaState)`` on every VSA sample (200 Hz: keep it short)."),
    },
    methods={"getConfigData": "The robot's configuration and safety limits as the application holds them."},
)

PHYSIOLOGICAL_SENSORS = ObjectShape(
    "physiologicalSensors", "PhysiologicalSensorsUser", "the physiological sensors",
    "``physiologicalSensors``: grip force (N), skin temperature (°C), heart rate (bpm), skin conductance (µS).",
    "grip force, temperature, heart rate, skin conductance",
    properties={"physiologicalSensorsData": Property(
        "PHYSIO_MAIN", "force (N), temperature (°C), heartRate (bpm), skinConductance (µS), boardTime (s), …")},
    callbacks={"setPhysiologicalSensorsDataCallbackFun": CallbackSetter(
        "PHYSIO_MAIN", "physiologicalDataCallbackList",
        "Call ``fun(physiologicalSensorsData)`` on every sample (100 Hz), on the script's callback thread.")},
)

PATIENT_MODEL = ObjectShape(
    "patientModel", "PatientModelUser", "the patient model",
    "``patientModel``: the patient model's latest output (alpha, a_r, a_f, tpi, mpi, pti).",
    "assistance levels and performance indices",
    properties={"patientModelData": Property("PATIENT_MODEL_MAIN", "alpha, a_r, a_f, tpi, mpi, pti")},
    callbacks={"setPatientModelDataCallbackFun": CallbackSetter(
        "PATIENT_MODEL_MAIN", "patientModelDataCallbackList",
        "Call ``fun(patientModelData)`` on every output of the patient model, on the script's callback thread.")},
)

VR_UNITY = ObjectShape(
    "VRUnity", "VRUnityUser", "the VR renderer",
    "``VRUnity``: the VR renderer's latest frame (targetPos, score, targetsReached).",
    "the virtual-reality scene",
    properties={"VRUnityData": Property("VR_MAIN", "targetPos, score, targetsReached")},
    callbacks={"setVRUnityDataCallbackFun": CallbackSetter(
        "VR_MAIN", "VRUnityDataCallbackList",
        "Call ``fun(VRUnityData)`` on every frame of the VR renderer, on the script's callback thread.")},
)

FES = ObjectShape(
    "fes", "FESUser", "the FES stimulator",
    "``fes``: the RehaStim stimulator. ``loadFile`` a profile (YAML, docs/fes.md), ``start``, ``stop``, and the "
    "live scale factors. Every change passes the FES limiter of the safety supervisor.",
    "RehaStim stimulator",
    methods={
        "loadFile": "Load a current + pulse-width profile (YAML) into the stimulator; returns the profile.",
        "writeFile": "Save a profile (what ``fes.loadFile`` returned, or ``fes.profile``) as YAML.",
        "start": "Start stimulating with the loaded profile.",
        "stop": "Stop stimulating.",
        "setCurrentScaleFactor": "Scale the current profile (0..2); returns the factor applied.",
        "setPWScaleFactor": "Scale the pulse-width profile (0..2); returns the factor applied.",
        "setPhase": "Not in the seed: the movement phase 0..1 that a ``phase`` profile follows (0 = start of the "
                    "reach, 0.5 = target, 1 = back at the start); None = at rest. Cheap: call it from a LINarm "
                    "callback.",
        "getConfigData": "Device, profile, scale factors and limits.",
        "electrodeSetup": "Not in the seed (issue #32): test every electrode combination of ``district``'s array "
                          "with ramped bursts from ``start_mA`` to ``ceiling_mA`` (never above the patient's caps) "
                          "while the robot holds the arm; returns the responses and the proposal (the largest "
                          "response per mA). ``accept``: save the proposal as the patient's choice (docs/fes.md "
                          "\"Electrode set-up\").",
    },
    attributes={"profile": "The loaded profile (None before ``loadFile``).",
                "stimulating": "True while the stimulator stimulates."},
)
FES_ALIASES: Mapping[str, str] = {"saveFile": "writeFile"}  # the Appendix lists both names

LINARMPP_MANAGER = ObjectShape(
    "linarmppManager", "LinarmppManager", "the application",
    "``linarmppManager``: every module in one object, and a program (script file) to run.",
    "linarm, physiologicalSensors, fes, patientModel, VRUnity",
    # Progress marks (an addition to the Appendix): the window shows "repetition 3 of 8", and the marks are
    # session events from which the per-repetition metrics find the repetitions.
    methods={
        "emergencyStop": "FES Stop and robot IDLE at once, latched until an operator resets it; the script is "
                         "stopped.",
        "startRepetition": "Mark the start of repetition ``index`` (from 1), optionally of ``total``.",
        "endRepetition": "Mark the end of repetition ``index`` (the current one when omitted); ``ok=False`` if it "
                         "failed.",
        "reportProgress": "A short message for the clinician (shown beside the repetition count, recorded as an "
                          "event).",
        "prompt": "Mark the cue to the patient, now (\"squeeze\" the handle, ``threshold`` N; or \"move\"): the "
                  "patient's reaction time is measured from it (docs/metrics.md).",
        "setRunState": "Say what the run does now, for the progress area and the record: \"waiting_for_grip\", "
                       "\"moving\", \"resting\" or \"running\" (homing, paused, stopped and finished are set by the "
                       "application).",
    },
)

OBJECTS: Mapping[str, ObjectShape] = {s.name: s for s in (LINARM, PHYSIOLOGICAL_SENSORS, FES, PATIENT_MODEL,
                                                           VR_UNITY, LINARMPP_MANAGER)}
API_NAMES = tuple(OBJECTS)  # the seed's names, in a script's namespace
DEVICE_OBJECTS = tuple(name for name in API_NAMES if name != LINARMPP_MANAGER.name)
LINARM_ALIASES: Mapping[str, str] = {"moveDeltato": "moveDeltaTo"}  # the seed's service list spells it so
ESTOP_REASON = "emergency stop from a script"


def apply_shape(cls: type, shape: ObjectShape, make_property: Callable[[ObjectShape, Property], property] | None = None,
                make_setter: Callable[[ObjectShape, str, CallbackSetter], Callable[..., None]] | None = None) -> type:
    """Give ``cls`` the shape's class string, docstring, repr, properties and callback setters (made by the
    side's own ``make_property(shape, property)`` / ``make_setter(shape, method, setter)``), and the shape's
    docstrings on its methods. Raises TypeError when ``cls`` lacks a method or attribute of the shape."""
    setattr(cls, "classString", shape.class_string)  # noqa: B010 - the seed's class name, on the class
    cls.__doc__ = shape.doc
    text = f"<{shape.name}: {shape.text} ({shape.class_string})>"

    def shown(self: object) -> str:
        return text

    setattr(cls, "__repr__", shown)  # noqa: B010 - a method put on a class, not an attribute probed
    if (shape.properties and make_property is None) or (shape.callbacks and make_setter is None):
        raise TypeError(f"{shape.name}'s state attributes and callback setters need the side's makers")
    for name, prop in shape.properties.items():
        made = make_property(shape, prop)  # type: ignore[misc]
        setattr(cls, name, property(made.fget, doc=prop.doc))
    for method, setter in shape.callbacks.items():
        fn = make_setter(shape, method, setter)  # type: ignore[misc]
        fn.__name__ = fn.__qualname__ = method
        fn.__doc__ = setter.doc
        setattr(cls, method, fn)
    missing = [n for n in (*shape.methods, *shape.attributes) if not hasattr(cls, n)]
    if missing:
        raise TypeError(f"{cls.__name__} does not implement {shape.name}'s {', '.join(missing)}")
    for name, doc in shape.methods.items():
        fn = getattr(cls, name)
        if callable(fn) and hasattr(fn, "__doc__") and not isinstance(fn, type):
            try:
                fn.__doc__ = doc
            except AttributeError:  # a builtin's docstring stays its own
                pass
    return cls


def init_callback_lists(obj: object, shape: ObjectShape) -> None:
    """The object's callback lists, empty (the seed's ``…CallbackList`` attributes)."""
    for list_name in shape.callback_lists():
        setattr(obj, list_name, [])


# ---------------------------------------------------------------------------------------------- linarmppManager
class ManagerPort(Protocol):
    """What ``linarmppManager`` needs of its side: in the application the host's supervisor and progress, in
    the kernel a call to the application."""

    def resolve_path(self, file_name: str) -> Path: ...

    def run_program(self, path: str) -> None: ...

    def emergency_stop(self, reason: str) -> None: ...

    def start_repetition(self, index: int, total: int | None) -> None: ...

    def end_repetition(self, index: int | None, ok: bool) -> None: ...

    def report_progress(self, text: str) -> None: ...

    def prompt(self, index: int | None, cue: str, threshold: float | None) -> None: ...

    def set_run_state(self, state: str, detail: str) -> None: ...


class LinarmppManager:
    """``linarmppManager``: every module in one object, and a program (script file) to run."""

    def __init__(self, port: ManagerPort, linarm: Any, physiologicalSensors: Any, fes: Any, patientModel: Any,
                 VRUnity: Any) -> None:
        self._port = port
        self.linarm = linarm
        self.physiologicalSensors = physiologicalSensors
        self.fes = fes
        self.patientModel = patientModel
        self.VRUnity = VRUnity
        self.fileName: str | None = None

    def emergencyStop(self, reason: str = ESTOP_REASON) -> None:
        self._port.emergency_stop(str(reason))
        raise ScriptStopped(reason)  # the script must not go on moving

    def setProgram(self, fileName: str) -> None:
        """Choose the script file that ``startProgram`` runs."""
        path = self._port.resolve_path(str(fileName))
        if not path.is_file():
            raise FileNotFoundError(f"no script file {path}")
        self.fileName = str(path)

    def startProgram(self) -> None:
        """Run the chosen script here, to its end (it shares this run's Stop button and devices)."""
        if self.fileName is None:
            raise ScriptError("call linarmppManager.setProgram(fileName) first")
        self._port.run_program(self.fileName)

    internalExec = startProgram

    def startRepetition(self, index: int, total: int | None = None) -> None:
        self._port.start_repetition(index, total)

    def endRepetition(self, index: int | None = None, ok: bool = True) -> None:
        self._port.end_repetition(index, ok)

    def reportProgress(self, text: str) -> None:
        self._port.report_progress(str(text))

    def prompt(self, index: int | None = None, cue: str = "squeeze", threshold: float | None = None) -> None:
        self._port.prompt(index, str(cue), threshold)

    def setRunState(self, state: str, detail: str = "") -> None:
        self._port.set_run_state(str(state), str(detail))


apply_shape(LinarmppManager, LINARMPP_MANAGER)
