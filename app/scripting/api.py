"""The script API in the application: the objects that do what a script asks (D2.2 §3.6, §4 and the Appendix).

``linarm`` (:class:`LinarmUser`), ``physiologicalSensors`` (:class:`PhysiologicalSensorsUser`),
``fes`` (:class:`FESUser`), ``patientModel`` (:class:`PatientModelUser`), ``VRUnity``
(:class:`VRUnityUser`) and ``linarmppManager`` (:class:`LinarmppManager`), with the Appendix's
camelCase names, so the seed's scripts run unchanged. Their shapes (state attributes, callback setters,
methods, docstrings), the errors and ``linarmppManager`` itself are the API's one definition,
app/scripting/api_spec.py, from which the script kernel's proxies are made too; this module implements them
in the application. Scripts run in the kernel (app/scripting/kernel.py): its calls reach these objects through
the bridge (app/scripting/bridge.py), with an inline context; the runner uses a context of its own for homing.

Rules every object follows:

* attribute reads (``linarm.linarmVsaState``, ``physiologicalSensors.physiologicalSensorsData``…)
  return the stream's latest sample on the bus (app/core/bus.py); before the first sample they wait briefly for
  it (on the bus's notifier), then raise :class:`DeviceUnavailable`. Each read also releases the GIL for a
  moment, so a caller busy-waiting on a device value leaves the devices and the GUI their share;
* commands block until the device acknowledges them and raise a :class:`ScriptError` with a plain
  sentence on refusal, error or timeout (the driver's own ACK timeout). They run on a helper thread
  while the caller waits in short slices, so Stop interrupts it even while it waits for an
  acknowledgement. They all pass through the drivers' single command path, hence through the safety
  supervisor;
* callbacks registered with the ``set…CallbackFun`` methods here never run on a driver thread: the stream's
  samples come from a bus subscription, and ``(callbacks, sample)`` is posted to ``post_callback`` by a
  thread of the context's own. (A script's own callbacks run in the kernel, on its callback thread: the bridge
  streams it the samples; nothing in the application sets ``post_callback`` today.)

The context is handed what it uses of the application (app.therapy.services.ScriptHost), not the manager.
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

from app.core import streams
from app.core.bus import SampleItem, Subscription
from app.devices.transport import TransportError
from app.safety.supervisor import SafetyError
from app.scripting import api_spec
from app.scripting.api_spec import (  # the one definition (re-exported: the bridge, the runner and tests use these)
    API_NAMES,
    CommandError,
    CommandRefused,
    DeviceUnavailable,
    LinarmppManager,
    NotInitializedError,
    ScriptError,
    ScriptStopped,
)
from app.wire import linarm_protocol as proto

if TYPE_CHECKING:
    from app.therapy.services import ScriptHost

__all__ = ["API_NAMES", "CommandError", "CommandRefused", "DeviceUnavailable", "FESUser", "LinarmUser",
           "LinarmppManager", "NotInitializedError", "PatientModelUser", "PhysiologicalSensorsUser", "ScriptContext",
           "ScriptError", "ScriptStopped", "VRUnityUser", "build_api", "emergency_stop"]

log = logging.getLogger(__name__)

WAIT_SLICE_S = api_spec.WAIT_SLICE_S
FIRST_SAMPLE_TIMEOUT_S = api_spec.FIRST_SAMPLE_TIMEOUT_S
CALLBACK_QUEUE = 4096  # samples of one callback stream waiting to be posted (oldest dropped, counted)


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
        api_spec.interruptible_sleep(seconds, self.stop_event, self.check)

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
        return api_spec.resolve_path(file_name, self.base_dir, *extra_dirs)


def _make_property(shape: api_spec.ObjectShape, prop: api_spec.Property) -> property:
    """A state attribute of the in-app objects: the stream's latest sample on the bus."""
    stream = getattr(streams, prop.stream)
    device, label = streams.device_of(stream), shape.label

    def get(self: _ApiObject) -> Any:
        return self._ctx.latest(device, stream, label)

    return property(get)


def _make_setter(shape: api_spec.ObjectShape, method: str, setter: api_spec.CallbackSetter) -> Callable[..., None]:
    """A ``set…CallbackFun`` of the in-app objects: the context posts the stream's samples to the list."""
    stream = getattr(streams, setter.stream)
    device, label, what = streams.device_of(stream), shape.label, f"{shape.name}.{method}"

    def set_callback(self: _ApiObject, fun: Any) -> None:
        target = getattr(self, setter.list_name)
        api_spec.set_callbacks(target, fun, what)
        self._ctx.subscribe(device, stream, label, target)

    return set_callback


class _ApiObject:
    """Base of the in-app objects: the run's context and the shape's callback lists."""

    _shape: api_spec.ObjectShape

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context
        api_spec.init_callback_lists(self, self._shape)


def _shaped(shape: api_spec.ObjectShape) -> Callable[[type], type]:
    """Class decorator: the shape's attributes, setters and docstrings on an in-app class (api_spec.py)."""

    def apply(cls: type) -> type:
        cls._shape = shape  # type: ignore[attr-defined]
        return api_spec.apply_shape(cls, shape, _make_property, _make_setter)

    return apply


# The shapes' streams by their constant's name in app/core/streams.py ("LINARM_VSA" -> "linarm.vsa"): the kernel gets it
SPEC_STREAMS: dict[str, str] = {
    key: getattr(streams, key) for shape in api_spec.OBJECTS.values()
    for key in (*(p.stream for p in shape.properties.values()), *(c.stream for c in shape.callbacks.values()))
}
# stream -> (device, label): the streams a script reads (the bridge serves these)
SCRIPT_STREAMS: dict[str, tuple[str, str]] = {
    getattr(streams, p.stream): (streams.device_of(getattr(streams, p.stream)), shape.label)
    for shape in api_spec.OBJECTS.values() for p in shape.properties.values()
}


# ---------------------------------------------------------------------------------------------- LINarm
# The driver owns the data stream, the heartbeat and the identification; scripts do not get those.
_HIDDEN_COMMANDS = frozenset({"identify", "heartbeat", "startDataStream", "stopDataStream", "getState"})
SCRIPT_COMMANDS: tuple[proto.Command, ...] = tuple(c for c in proto.HOST_COMMANDS if c.name not in _HIDDEN_COMMANDS)
SCRIPT_COMMAND_NAMES = frozenset(c.name for c in SCRIPT_COMMANDS)


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


@_shaped(api_spec.LINARM)
class LinarmUser(_ApiObject):
    """``linarm`` (its docstring, state attributes and callback setters: app/scripting/api_spec.py); the commands
    are the controller's (docs/linarm-protocol.md), added below from the wire's command table."""

    CONTROL_STATES = proto.CONTROL_STATES
    CONTROL_MODES = proto.CONTROL_MODES
    HOME_STATES = proto.HOME_STATES
    ERROR_STATES = proto.ERROR_STATES
    TRIGGER_MODES = proto.TRIGGER_MODES
    TRAJECTORY_TYPES = proto.TRAJECTORY_TYPES

    def getConfigData(self) -> dict[str, Any]:
        cfg = self._ctx.host.config
        from app.core.yamlschema import to_plain

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
for _alias, _target in api_spec.LINARM_ALIASES.items():
    setattr(LinarmUser, _alias, getattr(LinarmUser, _target))


# ---------------------------------------------------------------------------------------------- sensors
@_shaped(api_spec.PHYSIOLOGICAL_SENSORS)
class PhysiologicalSensorsUser(_ApiObject):
    """``physiologicalSensors`` (app/scripting/api_spec.py)."""


@_shaped(api_spec.PATIENT_MODEL)
class PatientModelUser(_ApiObject):
    """``patientModel`` (app/scripting/api_spec.py)."""


@_shaped(api_spec.VR_UNITY)
class VRUnityUser(_ApiObject):
    """``VRUnity`` (app/scripting/api_spec.py)."""


# ---------------------------------------------------------------------------------------------- FES
@_shaped(api_spec.FES)
class FESUser(_ApiObject):
    """``fes`` (its methods' docstrings: app/scripting/api_spec.py): every change passes the FES limiter of the
    safety supervisor."""

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
        from app.core.config import RESOURCES
        from app.core.fes_profile import load_profile

        path = self._ctx.resolve_path(str(fileName), RESOURCES / "fes_profiles")
        profile = load_profile(path)  # FesProfileError names the file, line and key
        driver = self._driver()
        self._call(f"fes.loadFile({str(fileName)!r})", driver.load_profile, profile, self._ctx.source)
        return profile

    def writeFile(self, data: Any, fileName: str) -> None:
        from app.core.fes_profile import FesProfile, save_profile
        from app.core.safe_files import check_writable_target

        if not isinstance(data, FesProfile):
            raise TypeError(f"fes.writeFile expects a profile (e.g. fes.profile), got {type(data).__name__}")
        path = self._ctx.resolve_path(str(fileName))
        check_writable_target(path)  # never replace a device node, a pipe or a folder (the app may run as root)
        save_profile(data, path)

    saveFile = writeFile  # the Appendix lists both names (api_spec.FES_ALIASES)

    def start(self) -> None:
        driver = self._driver()
        start = getattr(driver, "start_stimulation", None) or driver.start  # start(str) is the contract's alias
        self._call("fes.start()", start, self._ctx.source)

    def stop(self) -> None:
        driver = self._driver()
        stop = getattr(driver, "stop_stimulation", None) or driver.stop  # stop(str, str) is the contract's alias
        self._call("fes.stop()", stop, "stopped by the script", self._ctx.source)

    def setCurrentScaleFactor(self, factor: float) -> float:
        driver = self._driver()
        return float(self._call(f"fes.setCurrentScaleFactor({factor!r})", driver.set_current_scale,
                                float(factor), self._ctx.source))

    def setPWScaleFactor(self, factor: float) -> float:
        driver = self._driver()
        return float(self._call(f"fes.setPWScaleFactor({factor!r})", driver.set_pulse_width_scale,
                                float(factor), self._ctx.source))

    def setPhase(self, phase: float | None) -> None:
        driver = self._driver()
        set_phase = getattr(driver, "set_phase", None)
        if set_phase is None:
            raise DeviceUnavailable("this FES driver does not follow a movement phase")
        set_phase(None if phase is None else float(phase))

    def electrodeSetup(self, district: str, ceiling_mA: float, start_mA: float = 6.0, step_mA: float = 2.0,
                       pulseWidth_us: float = 250.0, accept: bool = False) -> dict[str, Any]:
        from app.therapy import electrodes

        manager = self._ctx.host
        fes, robot = self._driver(), self._ctx.driver(streams.LINARM, "the LINarm")
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
            manager.record_event(kind, **data)

        try:
            result = electrodes.run_district_setup(fes, robot, manager.supervisor,
                                                   bus.latest, record,
                                                   districts[district], plan, lambda: self._ctx.stopped,
                                                   source=source, bus=bus)
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
            from app.archive import station

            saved = station.save_choice_record(result, channel, profile, manager.operator or self._ctx.source,
                                               "", manager.config.safety, expected_version=manager.patient_version)
            profile = saved.profile
            if not manager.update_session_profile(profile, saved.version):
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
        driver = self._driver()
        config_data = getattr(driver, "config_data", None)
        if callable(config_data):
            return dict(config_data())
        profile = getattr(driver, "profile", None)
        return {"profile": getattr(profile, "name", None), "stimulating": bool(getattr(driver, "stimulating", False)),
                "currentScale": getattr(profile, "current_scale", None),
                "pulseWidthScale": getattr(profile, "pulse_width_scale", None)}


# ---------------------------------------------------------------------------------------------- manager
class _ManagerPort:
    """``linarmppManager``'s side in the application (api_spec.ManagerPort): the run's context and its host."""

    def __init__(self, context: ScriptContext) -> None:
        self._ctx = context

    def resolve_path(self, file_name: str) -> Path:
        return self._ctx.resolve_path(file_name)

    def run_program(self, path: str) -> None:
        if self._ctx.run_program is None:
            raise ScriptError("programs can only be started from a running script")
        self._ctx.run_program(path)

    def emergency_stop(self, reason: str) -> None:
        self._ctx.host.supervisor.emergency_stop(self._ctx.source, reason)

    def start_repetition(self, index: int, total: int | None) -> None:
        self._ctx.host.progress.start_repetition(index, total)

    def end_repetition(self, index: int | None, ok: bool) -> None:
        self._ctx.host.progress.end_repetition(index, ok)

    def report_progress(self, text: str) -> None:
        self._ctx.host.progress.report(text)

    def prompt(self, index: int | None, cue: str, threshold: float | None) -> None:
        self._ctx.host.progress.prompt(index, cue, threshold)

    def set_run_state(self, state: str, detail: str) -> None:
        self._ctx.host.progress.set_run_state(state, detail)


# ---------------------------------------------------------------------------------------------- namespace
def emergency_stop(context: ScriptContext, reason: str = api_spec.ESTOP_REASON) -> None:
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
    mgr = LinarmppManager(_ManagerPort(context), linarm, physio, fes, patient_model, vr)
    return {
        "linarm": linarm, "physiologicalSensors": physio, "fes": fes, "patientModel": patient_model,
        "VRUnity": vr, "linarmppManager": mgr, "manager": mgr,
        "emergencyStop": lambda reason=api_spec.ESTOP_REASON: emergency_stop(context, reason),
        **api_spec.SCRIPT_ERRORS,
    }
