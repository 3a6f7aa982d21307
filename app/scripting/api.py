"""The objects an exercise script sees: the seed's script API (D2.2 §3.6, §4 and the Appendix).

``linarm`` (:class:`LinarmUser`), ``physiologicalSensors`` (:class:`PhysiologicalSensorsUser`),
``fes`` (:class:`FESUser`), ``patientModel`` (:class:`PatientModelUser`), ``VRUnity``
(:class:`VRUnityUser`) and ``linarmppManager`` (:class:`LinarmppManager`), with the Appendix's
camelCase names, so the seed's scripts run unchanged.

Rules every object follows:

* attribute reads (``linarm.linarmVsaState``, ``physiologicalSensors.physiologicalSensorsData``…)
  return the stream's latest sample on the bus (app/bus.py); before the first sample they wait briefly for
  it (on the bus's notifier), then raise
  :class:`DeviceUnavailable`. Each read also releases the GIL for a moment, so a script busy-waiting
  on a device value (the seed's own ``waitCondition``) leaves the devices and the GUI their share;
* commands block until the device acknowledges them and raise a :class:`ScriptError` with a plain
  sentence on refusal, error or timeout (the driver's own ACK timeout). They run on a helper thread
  while the script waits in short slices, so Stop interrupts a script even while it waits for an
  acknowledgement. They all pass through the drivers' single command path, hence through the safety
  supervisor;
* callbacks registered with the ``set…CallbackFun`` methods never run on a driver thread: the stream's
  samples come from a bus subscription, and ``(callbacks, sample)`` is posted to the script's callback
  thread (``post_callback``) by a thread of the context's own.

The context is handed what it uses of the application (app.services.ScriptHost), not the manager.
"""

from __future__ import annotations

import inspect
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app import streams
from app.bus import SampleItem, Subscription
from app.devices import linarm_protocol as proto
from app.devices.transport import TransportError
from app.safety import SafetyError

if TYPE_CHECKING:
    from app.services import ScriptHost

log = logging.getLogger(__name__)

WAIT_SLICE_S = 0.02  # longest uninterrupted wait of a script thread: bounds the Stop latency
FIRST_SAMPLE_TIMEOUT_S = 2.0  # how long an attribute read waits for a device's first sample
CALLBACK_QUEUE = 4096  # samples of one callback stream waiting to be posted (oldest dropped, counted)


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


# ---------------------------------------------------------------------------------------------- context
CallbackPoster = Callable[[str, list[Callable[[Any], Any]], Any], None]


class ScriptContext:
    """What the API objects share for one script run: the application's services (``host``), the stop flag,
    the command helper thread and the callback subscriptions (``post_callback`` receives their samples)."""

    def __init__(self, host: ScriptHost, *, source: str = "script", base_dir: Path | None = None) -> None:
        self.host = host
        self.source = source
        self.base_dir = base_dir  # relative file names in scripts (fes.loadFile) resolve here first
        self.stop_event = threading.Event()
        self.post_callback: CallbackPoster | None = None
        self.run_program: Callable[[str], None] | None = None  # LinarmppManager.startProgram
        self._executor: ThreadPoolExecutor | None = None
        self._executor_lock = threading.Lock()
        self._callbacks: dict[str, list[Callable[[Any], Any]]] = {}  # stream -> the script's callback list
        self._callback_sub: Subscription | None = None
        self._callback_thread: threading.Thread | None = None
        self._listener_lock = threading.Lock()
        self._peeking = threading.local()  # completion reads attributes without waiting or stopping

    # ------------------------------------------------------------------ stop-aware waiting
    @property
    def stopped(self) -> bool:
        return self.stop_event.is_set()

    def check(self) -> None:
        if self.stop_event.is_set():
            raise ScriptStopped()

    def sleep(self, seconds: float) -> None:
        """``time.sleep`` for scripts: returns early (raising ScriptStopped) when the script is stopped."""
        seconds = float(seconds)
        if seconds < 0:
            raise ValueError("sleep length must be non-negative")
        deadline = time.monotonic() + seconds
        while True:
            self.check()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            self.stop_event.wait(min(remaining, WAIT_SLICE_S))

    def wait_until(self, predicate: Callable[[], Any], timeout: float | None) -> bool:
        """Evaluate ``predicate`` now and again on every new device sample (at least every 50 ms) until it
        is true (True) or ``timeout`` s pass (False). Stop interrupts it."""
        notifier = self.host.bus.notifier
        deadline = None if timeout is None else time.monotonic() + float(timeout)
        while True:
            self.check()
            generation = notifier.generation
            if predicate():
                return True
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return False
            slice_s = WAIT_SLICE_S if deadline is None else min(WAIT_SLICE_S, max(0.0, deadline - now))
            notifier.wait_after(generation, slice_s)

    # ------------------------------------------------------------------ commands off the script thread
    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Run ``fn`` on the command helper thread and wait for it in short, interruptible slices. How long
        is the command's own business (the driver's ACK timeout raises LinarmTimeout, a TimeoutError)."""
        self.check()
        future = self._submit(fn, *args, **kwargs)
        while True:
            try:
                return future.result(WAIT_SLICE_S)
            except TimeoutError:
                if future.done():
                    raise  # the command's own timeout
            self.check()  # the command itself finishes on the helper thread; the script stops now

    def _submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Future:
        with self._executor_lock:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="script-cmd")
            return self._executor.submit(fn, *args, **kwargs)

    # ------------------------------------------------------------------ samples
    def driver(self, name: str, label: str) -> Any:
        driver = self.host.driver(name)
        if driver is None:
            raise DeviceUnavailable(f"{label} is not available: it is switched off in the configuration "
                                    "or its driver is missing from this build")
        return driver

    def latest(self, device: str, stream: str, label: str) -> Any:
        """The latest sample of ``stream``, waiting up to FIRST_SAMPLE_TIMEOUT_S for a first one."""
        bus = self.host.bus
        if getattr(self._peeking, "on", False):
            self.driver(device, label)
            return bus.latest(stream)
        self.check()  # a busy-wait on a device value stops here, without an asynchronous exception
        driver = self.driver(device, label)
        sample = bus.latest(stream)
        if sample is None:
            if not self.wait_until(lambda: bus.latest(stream) is not None, FIRST_SAMPLE_TIMEOUT_S):
                state = "connected" if driver.connected else "not connected"
                raise DeviceUnavailable(f"{label}: no data received yet (the device is {state})")
            sample = bus.latest(stream)
        time.sleep(0)  # release the GIL: busy-waiting scripts read a device value on every pass
        return sample

    def peek(self, obj: Any, name: str) -> Any:
        """``getattr(obj, name)`` for completion on the GUI thread: a device value is the latest sample or
        None, never a wait."""
        self._peeking.on = True
        try:
            return getattr(obj, name)
        finally:
            self._peeking.on = False

    def subscribe(self, device: str, stream: str, label: str, callbacks: list[Callable[[Any], Any]]) -> None:
        """Post ``(stream, callbacks, sample)`` for the callback thread on every ``stream`` sample (once per
        list). The samples come from one bus subscription of the context, drained by a thread of its own:
        never a driver's thread."""
        self.driver(device, label)
        with self._listener_lock:
            if stream in self._callbacks:
                return
            self._callbacks[stream] = callbacks
            old = self._callback_sub
            # one queue for every callback stream, so their samples keep the order they were published in
            self._callback_sub = self.host.bus.subscribe(f"script-callbacks:{self.source}", tuple(self._callbacks),
                                                         maxlen=CALLBACK_QUEUE)
            if old is not None:
                old.close()
            if self._callback_thread is None or not self._callback_thread.is_alive():
                self._callback_thread = threading.Thread(target=self._post_callbacks, name="script-callbacks",
                                                         daemon=True)
                self._callback_thread.start()

    def _post_callbacks(self) -> None:
        while True:
            sub = self._callback_sub
            if sub is None:
                return
            sub.wait(0.1)
            for item in sub.drain():
                if isinstance(item, SampleItem) and not self.stop_event.is_set():
                    callbacks, post = self._callbacks.get(item.stream), self.post_callback
                    if callbacks and post is not None:
                        post(item.stream, callbacks, item.sample)

    def close(self) -> None:
        """Close the callback subscription and let the command helper thread end (the script run is over)."""
        with self._listener_lock:
            sub, self._callback_sub = self._callback_sub, None
            self._callbacks.clear()
            thread, self._callback_thread = self._callback_thread, None
        if sub is not None:
            sub.close()
        if thread is not None and thread is not threading.current_thread():
            thread.join(1.0)
        with self._executor_lock:
            if self._executor is not None:
                self._executor.shutdown(wait=False, cancel_futures=True)
                self._executor = None

    def resolve_path(self, file_name: str, *extra_dirs: Path) -> Path:
        path = Path(file_name).expanduser()
        if path.is_absolute():
            return path
        for folder in (self.base_dir, Path.cwd(), *extra_dirs):
            if folder is not None and (folder / path).exists():
                return folder / path
        return (self.base_dir or Path.cwd()) / path


def _set_callbacks(target: list[Callable[[Any], Any]], fun: Any, what: str) -> None:
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


# ---------------------------------------------------------------------------------------------- LINarm
# The driver owns the data stream, the heartbeat and the identification; scripts do not get those.
_HIDDEN_COMMANDS = frozenset({"identify", "heartbeat", "startDataStream", "stopDataStream", "getState"})
SCRIPT_COMMANDS: tuple[proto.Command, ...] = tuple(c for c in proto.HOST_COMMANDS if c.name not in _HIDDEN_COMMANDS)


def _coerce(command: str, arg: proto.Arg, value: Any) -> Any:
    """A script value as the wire expects it: 0 → 0.0 for a float, an enum member → int."""
    where = f"linarm.{command}: argument {arg.name}"
    if arg.kind is proto.BOOL:
        if isinstance(value, bool) or (isinstance(value, int) and value in (0, 1)):
            return bool(value)
        raise TypeError(f"{where} must be True or False, got {value!r}")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"{where} must be a number, got {value!r}")
    if arg.kind is proto.INT:
        if isinstance(value, float) and not value.is_integer():
            raise TypeError(f"{where} must be a whole number, got {value!r}")
        return int(value)
    return float(value)


def _command_doc(spec: proto.Command) -> str:
    args = ", ".join(f"{a.name}{f' ({a.unit})' if a.unit else ''}" for a in spec.args) or "no arguments"
    returns = ", ".join(a.name for a in spec.returns)
    text = f"{spec.name}({args})"
    if returns:
        text += f" -> {returns}"
    if spec.doc:
        text += f"\n\n{spec.doc}"
    return text + "\n\nBlocks until the LINarm acknowledges; raises CommandError / CommandRefused otherwise."


def _make_command(spec: proto.Command) -> Callable[..., Any]:
    def command(self: LinarmUser, *args: Any) -> Any:
        return self._command(spec.name, args)

    command.__name__ = command.__qualname__ = spec.name
    command.__doc__ = _command_doc(spec)
    params = [inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY)]
    params += [inspect.Parameter(a.name, inspect.Parameter.POSITIONAL_ONLY) for a in spec.args]
    command.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
    return command


class LinarmUser:
    """``linarm``: the LINarm2 robot. Commands are the controller's (docs/linarm-protocol.md); state
    attributes are the latest samples of its streams, with the seed's field names (``equilibriumPos``…)."""

    classString = "LinarmUser"
    CONTROL_STATES = proto.CONTROL_STATES
    CONTROL_MODES = proto.CONTROL_MODES
    HOME_STATES = proto.HOME_STATES
    ERROR_STATES = proto.ERROR_STATES
    TRIGGER_MODES = proto.TRIGGER_MODES
    TRAJECTORY_TYPES = proto.TRAJECTORY_TYPES

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context
        self.linarmDataCallbackList: list[Callable[[Any], Any]] = []
        self.linarmMotor0DataCallbackList: list[Callable[[Any], Any]] = []
        self.linarmMotor1DataCallbackList: list[Callable[[Any], Any]] = []
        self.linarmVsaDataCallbackList: list[Callable[[Any], Any]] = []

    def __repr__(self) -> str:
        return "<linarm: LINarm2 robot (LinarmUser)>"

    # ------------------------------------------------------------------ state (latest samples)
    @property
    def linarmState(self) -> Any:
        """controlState, controlMode, homeState, errorState, triggerMode, initialized, trajectoryType, …"""
        return self._ctx.latest(streams.LINARM, streams.LINARM_STATE, "the LINarm")

    @property
    def linarmVsaState(self) -> Any:
        """equilibriumPos (m), delta (m), stiffness (N/m), handlePos (m), handleVel (m/s), interactionForce (N)."""
        return self._ctx.latest(streams.LINARM, streams.LINARM_VSA, "the LINarm")

    @property
    def linarmMotor0State(self) -> Any:
        """position (m), velocity (m/s), current (A), target (m) of motor 0."""
        return self._ctx.latest(streams.LINARM, streams.LINARM_MOTOR0, "the LINarm")

    @property
    def linarmMotor1State(self) -> Any:
        """position (m), velocity (m/s), current (A), target (m) of motor 1."""
        return self._ctx.latest(streams.LINARM, streams.LINARM_MOTOR1, "the LINarm")

    # ------------------------------------------------------------------ callbacks
    def setLinarmDataCallbackFun(self, fun: Any) -> None:
        """Call ``fun(linarmState)`` on every LINarm state sample (on the script's callback thread)."""
        self._callbacks(streams.LINARM_STATE, self.linarmDataCallbackList, fun, "setLinarmDataCallbackFun")

    def setLinarmMotor0DataCallbackFun(self, fun: Any) -> None:
        self._callbacks(streams.LINARM_MOTOR0, self.linarmMotor0DataCallbackList, fun, "setLinarmMotor0DataCallbackFun")

    def setLinarmMotor1DataCallbackFun(self, fun: Any) -> None:
        self._callbacks(streams.LINARM_MOTOR1, self.linarmMotor1DataCallbackList, fun, "setLinarmMotor1DataCallbackFun")

    def setLinarmVsaDataCallbackFun(self, fun: Any) -> None:
        """Call ``fun(linarmVsaState)`` on every VSA sample (200 Hz: keep it short)."""
        self._callbacks(streams.LINARM_VSA, self.linarmVsaDataCallbackList, fun, "setLinarmVsaDataCallbackFun")

    def _callbacks(self, stream: str, target: list[Callable[[Any], Any]], fun: Any, what: str) -> None:
        _set_callbacks(target, fun, f"linarm.{what}")
        self._ctx.subscribe(streams.LINARM, stream, "the LINarm", target)

    def getConfigData(self) -> dict[str, Any]:
        """The robot's configuration and safety limits as the application holds them."""
        cfg = self._ctx.host.config
        from app.yamlschema import to_plain

        return {"device": to_plain(cfg.devices.linarm), "limits": to_plain(cfg.safety.robot)}

    # ------------------------------------------------------------------ commands
    def _command(self, name: str, args: tuple[Any, ...]) -> Any:
        spec = proto.COMMANDS_BY_NAME[name]
        if len(args) != len(spec.args):
            names = ", ".join(a.name for a in spec.args) or "no arguments"
            raise TypeError(f"linarm.{name} takes {len(spec.args)} argument(s) ({names}), got {len(args)}")
        values = tuple(_coerce(name, a, v) for a, v in zip(spec.args, args, strict=True))
        driver = self._ctx.driver(streams.LINARM, "the LINarm")
        shown = f"linarm.{name}({', '.join(_show(v) for v in values)})"
        try:
            reply = self._ctx.call(driver.command, name, *values, source=self._ctx.source)
        except SafetyError as exc:
            raise CommandRefused(f"{shown}: {exc.reason}") from exc
        except TransportError as exc:
            raise DeviceUnavailable(f"{shown} could not be sent: {exc}") from exc
        except (ScriptError, TypeError, ValueError):
            raise
        except Exception as exc:  # LinarmCommandError, LinarmTimeout: the driver's sentences
            raise CommandError(f"{shown} failed: {exc}") from exc
        values_out = [reply.get(a.name) for a in spec.returns]
        if name == "getPidTunings":
            values_out = values_out[1:]  # the seed returns (P, I, D); the index echo is the wire's check
        if not values_out:
            return None
        return values_out[0] if len(values_out) == 1 else tuple(values_out)


def _show(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else repr(value)


for _spec in SCRIPT_COMMANDS:
    setattr(LinarmUser, _spec.name, _make_command(_spec))
LinarmUser.moveDeltato = LinarmUser.moveDeltaTo  # type: ignore[attr-defined]  # the seed's service list spells it so


# ---------------------------------------------------------------------------------------------- sensors
class PhysiologicalSensorsUser:
    """``physiologicalSensors``: grip force (N), skin temperature (°C), heart rate (bpm), skin conductance (µS)."""

    classString = "PhysiologicalSensorsUser"

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context
        self.physiologicalDataCallbackList: list[Callable[[Any], Any]] = []

    def __repr__(self) -> str:
        return "<physiologicalSensors: grip force, temperature, heart rate, skin conductance>"

    @property
    def physiologicalSensorsData(self) -> Any:
        """force (N), temperature (°C), heartRate (bpm), skinConductance (µS), boardTime (s), …"""
        return self._ctx.latest(streams.PHYSIO, streams.PHYSIO_MAIN, "the physiological sensors")

    def setPhysiologicalSensorsDataCallbackFun(self, fun: Any) -> None:
        """Call ``fun(physiologicalSensorsData)`` on every sample (100 Hz), on the script's callback thread."""
        funs = self.physiologicalDataCallbackList
        _set_callbacks(funs, fun, "physiologicalSensors.setPhysiologicalSensorsDataCallbackFun")
        self._ctx.subscribe(streams.PHYSIO, streams.PHYSIO_MAIN, "the physiological sensors", funs)


class PatientModelUser:
    """``patientModel``: the patient model's latest output (alpha, a_r, a_f, tpi, mpi, pti)."""

    classString = "PatientModelUser"

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context
        self.patientModelDataCallbackList: list[Callable[[Any], Any]] = []

    def __repr__(self) -> str:
        return "<patientModel: assistance levels and performance indices>"

    @property
    def patientModelData(self) -> Any:
        return self._ctx.latest(streams.PATIENT_MODEL, streams.PATIENT_MODEL_MAIN, "the patient model")

    def setPatientModelDataCallbackFun(self, fun: Any) -> None:
        funs = self.patientModelDataCallbackList
        _set_callbacks(funs, fun, "patientModel.setPatientModelDataCallbackFun")
        self._ctx.subscribe(streams.PATIENT_MODEL, streams.PATIENT_MODEL_MAIN, "the patient model", funs)


class VRUnityUser:
    """``VRUnity``: the VR renderer's latest frame (targetPos, score, targetsReached)."""

    classString = "VRUnityUser"

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context
        self.VRUnityDataCallbackList: list[Callable[[Any], Any]] = []

    def __repr__(self) -> str:
        return "<VRUnity: the virtual-reality scene>"

    @property
    def VRUnityData(self) -> Any:
        return self._ctx.latest(streams.VR, streams.VR_MAIN, "the VR renderer")

    def setVRUnityDataCallbackFun(self, fun: Any) -> None:
        _set_callbacks(self.VRUnityDataCallbackList, fun, "VRUnity.setVRUnityDataCallbackFun")
        self._ctx.subscribe(streams.VR, streams.VR_MAIN, "the VR renderer", self.VRUnityDataCallbackList)


# ---------------------------------------------------------------------------------------------- FES
class FESUser:
    """``fes``: the RehaStim stimulator. ``loadFile`` a profile (YAML, docs/fes.md), ``start``, ``stop``, and
    the live scale factors. Every change passes the FES limiter of the safety supervisor."""

    classString = "FESUser"

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context

    def __repr__(self) -> str:
        return "<fes: RehaStim stimulator (FESUser)>"

    def _driver(self) -> Any:
        return self._ctx.driver(streams.FES, "the FES stimulator")

    def _call(self, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        try:
            return self._ctx.call(fn, *args, **kwargs)
        except SafetyError as exc:
            raise CommandRefused(f"{what} was refused: {exc.reason}") from exc
        except TransportError as exc:
            raise DeviceUnavailable(f"{what} could not be sent: {exc}") from exc
        except (ScriptError, TypeError, ValueError):
            raise
        except Exception as exc:
            raise CommandError(f"{what} failed: {exc}") from exc

    def loadFile(self, fileName: str) -> Any:
        """Load a current + pulse-width profile (YAML) into the stimulator; returns the profile."""
        from app.config import RESOURCES
        from app.fes_profile import load_profile

        path = self._ctx.resolve_path(str(fileName), RESOURCES / "fes_profiles")
        profile = load_profile(path)  # FesProfileError names the file, line and key
        driver = self._driver()
        self._call(f"fes.loadFile({str(fileName)!r})", driver.load_profile, profile, self._ctx.source)
        return profile

    def writeFile(self, data: Any, fileName: str) -> None:
        """Save a profile (an ``FesProfile``, e.g. ``fes.profile``) as YAML."""
        from app.fes_profile import FesProfile, save_profile
        from app.safe_files import check_writable_target

        if not isinstance(data, FesProfile):
            raise TypeError(f"fes.writeFile expects a profile (e.g. fes.profile), got {type(data).__name__}")
        path = self._ctx.resolve_path(str(fileName))
        check_writable_target(path)  # never replace a device node, a pipe or a folder (the app may run as root)
        save_profile(data, path)

    saveFile = writeFile  # the Appendix lists both names

    def start(self) -> None:
        """Start stimulating with the loaded profile."""
        driver = self._driver()
        start = getattr(driver, "start_stimulation", None) or driver.start  # start(str) is the contract's alias
        self._call("fes.start()", start, self._ctx.source)

    def stop(self) -> None:
        """Stop stimulating."""
        driver = self._driver()
        stop = getattr(driver, "stop_stimulation", None) or driver.stop  # stop(str, str) is the contract's alias
        self._call("fes.stop()", stop, "stopped by the script", self._ctx.source)

    def setCurrentScaleFactor(self, factor: float) -> float:
        """Scale the current profile (0..2); returns the factor applied."""
        driver = self._driver()
        return float(self._call(f"fes.setCurrentScaleFactor({factor!r})", driver.set_current_scale,
                                float(factor), self._ctx.source))

    def setPWScaleFactor(self, factor: float) -> float:
        """Scale the pulse-width profile (0..2); returns the factor applied."""
        driver = self._driver()
        return float(self._call(f"fes.setPWScaleFactor({factor!r})", driver.set_pulse_width_scale,
                                float(factor), self._ctx.source))

    def setPhase(self, phase: float | None) -> None:
        """Not in the seed: the movement phase 0..1 that a ``phase`` profile follows (0 = start of the reach,
        0.5 = target, 1 = back at the start); None = at rest. Cheap: call it from a LINarm callback."""
        driver = self._driver()
        set_phase = getattr(driver, "set_phase", None)
        if set_phase is None:
            raise DeviceUnavailable("this FES driver does not follow a movement phase")
        set_phase(None if phase is None else float(phase))

    def electrodeSetup(self, district: str, ceiling_mA: float, start_mA: float = 6.0, step_mA: float = 2.0,
                       pulseWidth_us: float = 250.0, accept: bool = False) -> dict[str, Any]:
        """Not in the seed (issue #32): test every electrode combination of ``district``'s array with ramped
        bursts from ``start_mA`` to ``ceiling_mA`` (never above the patient's caps) while the robot holds the arm;
        returns the responses and the proposal (the largest response per mA). ``accept``: save the proposal as the
        patient's choice (docs/fes.md "Electrode set-up")."""
        from app import electrodes

        manager = self._ctx.host
        fes, robot = self._driver(), self._ctx.driver("linarm", "the LINarm")
        districts = electrodes.districts_from_config(manager.config.devices.fes.electrodes)
        if district not in districts:
            raise ScriptError(f"no district {district!r} in the configuration (devices.fes.electrodes): "
                              f"{', '.join(districts) or 'none'}")
        plan = electrodes.SetupPlan(ceiling_ma=float(ceiling_mA), start_ma=float(start_mA), step_ma=float(step_mA),
                                    pulse_width_us=float(pulseWidth_us),
                                    frequency_hz=manager.config.safety.fes.frequency_hz)
        bus = manager.bus
        source = f"{self._ctx.source}: fes.electrodeSetup"

        def record(kind: str, data: dict[str, Any]) -> None:
            if manager.recorder is not None:
                manager.record_event(kind, **data)
            else:
                manager.supervisor.record(kind, **data)

        try:
            result = electrodes.run_district_setup(fes, robot, manager.supervisor,
                                                   bus.latest, record,
                                                   districts[district], plan, lambda: self._ctx.stopped,
                                                   source=source)
        except electrodes.SetupAborted as exc:
            raise CommandRefused(f"fes.electrodeSetup({district!r}) was refused: {exc.reason}") from exc
        self._ctx.check()
        summary = electrodes.result_summary(result)
        channel = result.proposal.channel if result.proposal is not None else None
        if accept and channel is not None and not result.aborted:
            profile = manager.patient_profile
            if profile is None:
                raise ScriptError("the proposal cannot be saved: this session's patient has no profile")
            # only this district's choice is written, onto the archive's record as it is now (#39): a cap lowered
            # since the session started stays lowered, and what changed meanwhile applies here too (#36)
            saved = electrodes.save_choice_record(result, channel, profile, manager.operator or self._ctx.source,
                                                  "", manager.config.safety,
                                                  expected_version=getattr(manager, "patient_version", 0))
            profile = saved.profile
            update = getattr(manager, "update_session_profile", None)
            if not (callable(update) and update(profile, saved.version)):
                manager.patient_profile = profile
                manager.patient_version = saved.version
            fes.set_district_channels(profile.fes.district_channels())
            record("electrode_choice", electrodes.choice_event(result, profile.fes.electrodes[district]))
            summary["accepted"] = channel
        return summary

    @property
    def profile(self) -> Any:
        return getattr(self._driver(), "profile", None)

    @property
    def stimulating(self) -> bool:
        return bool(getattr(self._driver(), "stimulating", False))

    def getConfigData(self) -> dict[str, Any]:
        """Device, profile, scale factors and limits."""
        driver = self._driver()
        config_data = getattr(driver, "config_data", None)
        if callable(config_data):
            return dict(config_data())
        profile = getattr(driver, "profile", None)
        return {"profile": getattr(profile, "name", None), "stimulating": bool(getattr(driver, "stimulating", False)),
                "currentScale": getattr(profile, "current_scale", None),
                "pulseWidthScale": getattr(profile, "pulse_width_scale", None)}


# ---------------------------------------------------------------------------------------------- manager
class LinarmppManager:
    """``linarmppManager``: every module in one object, and a program (script file) to run."""

    classString = "LinarmppManager"

    def __init__(self, context: ScriptContext, linarm: LinarmUser, physiologicalSensors: PhysiologicalSensorsUser,
                 fes: FESUser, patientModel: PatientModelUser, VRUnity: VRUnityUser) -> None:
        self._ctx = context
        self.linarm = linarm
        self.physiologicalSensors = physiologicalSensors
        self.fes = fes
        self.patientModel = patientModel
        self.VRUnity = VRUnity
        self.fileName: str | None = None

    def __repr__(self) -> str:
        return "<linarmppManager: linarm, physiologicalSensors, fes, patientModel, VRUnity>"

    def emergencyStop(self, reason: str = "emergency stop from a script") -> None:
        """FES Stop and robot IDLE at once, latched until an operator resets it; the script is stopped."""
        emergency_stop(self._ctx, reason)

    def setProgram(self, fileName: str) -> None:
        """Choose the script file that ``startProgram`` runs."""
        path = self._ctx.resolve_path(str(fileName))
        if not path.is_file():
            raise FileNotFoundError(f"no script file {path}")
        self.fileName = str(path)

    def startProgram(self) -> None:
        """Run the chosen script here, to its end (it shares this run's Stop button and devices)."""
        if self.fileName is None:
            raise ScriptError("call linarmppManager.setProgram(fileName) first")
        if self._ctx.run_program is None:
            raise ScriptError("programs can only be started from a running script")
        self._ctx.run_program(self.fileName)

    internalExec = startProgram

    # Progress marks (an addition to the Appendix): the window shows "repetition 3 of 8", and the
    # marks are session events from which the per-repetition metrics find the repetitions.
    def startRepetition(self, index: int, total: int | None = None) -> None:
        """Mark the start of repetition ``index`` (from 1), optionally of ``total``."""
        self._ctx.host.progress.start_repetition(index, total)

    def endRepetition(self, index: int | None = None, ok: bool = True) -> None:
        """Mark the end of repetition ``index`` (the current one when omitted); ``ok=False`` if it failed."""
        self._ctx.host.progress.end_repetition(index, ok)

    def reportProgress(self, text: str) -> None:
        """A short message for the clinician (shown beside the repetition count, recorded as an event)."""
        self._ctx.host.progress.report(text)

    def prompt(self, index: int | None = None, cue: str = "squeeze", threshold: float | None = None) -> None:
        """Mark the cue to the patient, now ("squeeze" the handle, ``threshold`` N; or "move"): the patient's
        reaction time is measured from it (docs/metrics.md)."""
        self._ctx.host.progress.prompt(index, cue, threshold)

    def setRunState(self, state: str, detail: str = "") -> None:
        """Say what the run does now, for the progress area and the record: "waiting_for_grip", "moving",
        "resting" or "running" (homing, paused, stopped and finished are set by the application)."""
        self._ctx.host.progress.set_run_state(state, detail)


# ---------------------------------------------------------------------------------------------- namespace
API_NAMES = ("linarm", "physiologicalSensors", "fes", "patientModel", "VRUnity", "linarmppManager")


def emergency_stop(context: ScriptContext, reason: str = "emergency stop from a script") -> None:
    """The script API's e-stop: the supervisor's, then this script ends (it must not go on moving)."""
    context.host.supervisor.emergency_stop(context.source, reason)
    raise ScriptStopped(reason)


def build_api(context: ScriptContext) -> dict[str, Any]:
    """The script-visible objects of one run, by their seed names (plus ``manager`` for linarmppManager)."""
    linarm = LinarmUser(context)
    physio = PhysiologicalSensorsUser(context)
    fes = FESUser(context)
    patient_model = PatientModelUser(context)
    vr = VRUnityUser(context)
    mgr = LinarmppManager(context, linarm, physio, fes, patient_model, vr)
    return {
        "linarm": linarm, "physiologicalSensors": physio, "fes": fes, "patientModel": patient_model,
        "VRUnity": vr, "linarmppManager": mgr, "manager": mgr,
        "emergencyStop": lambda reason="emergency stop from a script": emergency_stop(context, reason),
        "ScriptError": ScriptError, "CommandError": CommandError, "CommandRefused": CommandRefused,
        "DeviceUnavailable": DeviceUnavailable, "NotInitializedError": NotInitializedError,
    }
