"""The script API's bridge (one job: the API, not the process): answers a script kernel's requests with the
in-app API (app/scripting/api.py) and streams it the samples it reads.

:class:`ApiBridge` serves one kernel (app/scripting/kernel_process.py runs the process and hands its messages
over): ``subscribe`` (every sample of the stream from then on, in order: the bridge's subscription to the stream
bus, app/core/bus.py, drained and sent to the kernel by a thread of the bridge's own), ``peek`` (completion), and
``call`` — only the API's own methods (:data:`ALLOWED_CALLS`: the robot's command table and the methods of the
API's definition, app/scripting/api_spec.py), executed by the in-app API objects, in the order the kernel sent
them, on the bridge's call thread: never on the thread that reads the kernel's requests, so a command waiting for
its acknowledgement holds up neither the reading nor the kernel's next requests. The script's e-stop
(``linarmppManager.emergencyStop``) is never queued behind a command nor held by the rate limit: it runs as soon
as it is read, off the reading lead. Every call passes through the drivers' single command path and the safety
supervisor. Anything else is refused and recorded (supervisor event ``script_request_refused``); calls over
the rate limit are refused, and a flood of refused requests ends the kernel. :func:`hello_message` is what a
new kernel gets first (the robot's command table and enums, the streams' names and labels).

What the kernel sends is JSON only (a hostile script controls those bytes): every field is checked before use.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.core import journal
from app.core.bus import SampleItem, Subscription
from app.scripting import api, api_spec
from app.scripting.api import (
    DeviceUnavailable,
    ScriptContext,
    ScriptError,
    ScriptStopped,
)
from app.scripting.kernel_process import KernelProcess, encode
from app.wire import linarm_protocol as proto

if TYPE_CHECKING:
    from app.therapy.services import ScriptHost

log = logging.getLogger(__name__)

REFUSALS_RECORDED = 20  # per kernel; a flood of bad requests is counted, not recorded one by one
REFUSALS_LOGGED = 10  # per kernel, line by line; then one summary line per REFUSAL_SUMMARY_S at most
REFUSAL_SUMMARY_S = 5.0
# Calls a kernel may make: CALL_RATE a second on average, CALL_BURST at once. A call over the rate waits its
# turn (a script polling ``fes.stimulating`` in a loop is only slowed down) as long as no more than
# CALL_QUEUE_S of calls are queued; beyond that — a flood, calls written without waiting for answers — it is
# refused at once and counted. Measured (tests/test_kernel_hostile.py): a script's own call loop makes
# ~3000 round trips a second on this machine; the robot's and the FES's commands wait for an ACK anyway.
CALL_RATE = 2000.0
CALL_BURST = 200
CALL_QUEUE_S = 0.05
# Refused requests a kernel may send: a script through the API is never refused (its proxies send only API
# calls and wait for each answer), so refusals come from a script writing to its socket itself. Past
# REFUSAL_BURST in a row (REFUSAL_RATE a second refill it) the kernel is ended like one that sent a bad line:
# each refusal costs the application a parse and an answer, and a flood of them would cost it a core.
REFUSAL_RATE = 100.0
REFUSAL_BURST = 1000

STREAMS = api.SCRIPT_STREAMS  # stream -> (device, label): the streams a script may subscribe to
SAMPLE_QUEUE = 65536  # samples waiting to be sent to a kernel (oldest dropped and counted beyond)
ESTOP_CALL = ("linarmppManager", "emergencyStop")  # never queued behind a command

# What a kernel may call: object -> methods of the in-app API objects (the robot's commands and the API's methods,
# app/scripting/api_spec.py), and the attributes it may read.
ALLOWED_CALLS: dict[str, frozenset[str]] = {
    shape.name: frozenset(shape.methods) | (api.SCRIPT_COMMAND_NAMES if shape is api_spec.LINARM else frozenset())
    for shape in api_spec.OBJECTS.values() if shape.methods
}
ALLOWED_ATTRIBUTES: dict[str, frozenset[str]] = {
    shape.name: frozenset(shape.attributes) for shape in api_spec.OBJECTS.values() if shape.attributes
}


def hello_message() -> dict[str, Any]:
    """What a new kernel gets of the application before anything else (data only): the robot's command table and
    enums, the streams' names the API's definition refers to, and the streams' labels."""
    commands = [{"name": c.name, "args": [a.name for a in c.args], "doc": api._command_doc(c)}
                for c in api.SCRIPT_COMMANDS]
    enums = {name: {m.name: int(m.value) for m in getattr(proto, name)}
             for name in ("CONTROL_STATES", "CONTROL_MODES", "HOME_STATES", "ERROR_STATES", "TRIGGER_MODES",
                          "TRAJECTORY_TYPES")}
    return {"op": "hello", "commands": commands, "enums": enums, "streams": api.SPEC_STREAMS,
            "labels": {s: label for s, (_d, label) in STREAMS.items()}}


# ---------------------------------------------------------------------------------------------- samples
def _plain(value: Any) -> Any:
    """``value`` as plain data for the kernel: None, bool, str, int, float, and lists and dicts of them (keys as
    strings); anything else as its text. Dicts inside lists stay dicts (#37: the electrode set-up's combinations
    reached scripts as strings)."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    item = getattr(value, "item", None)  # numpy scalars
    if callable(item):
        try:
            return _plain(item())
        except (TypeError, ValueError):
            pass
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return str(value)


def _fields(sample: Any) -> tuple[str, ...]:
    if dataclasses.is_dataclass(sample):
        return tuple(f.name for f in dataclasses.fields(sample))
    named = getattr(sample, "_fields", None)
    if named is not None:
        return tuple(named)
    return tuple(k for k in vars(sample) if not k.startswith("_"))


class SampleEncoder:
    """Samples as ``schema`` (once per stream and type) + ``sample`` (values in field order) messages."""

    def __init__(self) -> None:
        self._fields: dict[type, tuple[str, ...]] = {}

    def fields(self, sample: Any) -> tuple[str, ...]:
        cls = type(sample)
        fields = self._fields.get(cls)
        if fields is None:
            fields = self._fields[cls] = _fields(sample)
        return fields

    def values(self, sample: Any, fields: tuple[str, ...]) -> list[Any]:
        return [_plain(getattr(sample, f, None)) for f in fields]

    def snapshot(self, sample: Any) -> dict[str, Any] | None:
        if sample is None:
            return None
        fields = self.fields(sample)
        return {"type": type(sample).__name__, "fields": list(fields), "v": self.values(sample, fields)}


# ---------------------------------------------------------------------------------------------- the gate
class Gate:
    """Whether the kernel's calls pass: open, held (paused: calls wait) or closed (stopping: refused)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.state = "open"

    def set(self, state: str) -> None:
        with self._cond:
            self.state = state
            self._cond.notify_all()

    def enter(self) -> bool:
        with self._cond:
            while self.state == "paused":
                self._cond.wait(0.05)
            return self.state == "open"


class _InlineContext(ScriptContext):
    """The in-app API's context for a kernel's requests: the bridge's call thread already runs off every
    script thread (and off the kernel's readers), so a command runs here directly (one thread hop less on
    the trigger path)."""

    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        return fn(*args, **kwargs)


# ---------------------------------------------------------------------------------------------- limits
class CallLimiter:
    """A kernel's call budget (a virtual-time bucket): :meth:`admit` says how long a call waits for its turn,
    or None when it is refused (more than ``queue_s`` of calls already waiting)."""

    def __init__(self, rate: float = CALL_RATE, burst: int = CALL_BURST, queue_s: float = CALL_QUEUE_S) -> None:
        self.interval = 1.0 / rate
        self.burst_s = burst * self.interval
        self.queue_s = queue_s
        self._lock = threading.Lock()
        self._tat = time.monotonic()  # when the calls admitted so far would be done at the steady rate

    def admit(self) -> float | None:
        with self._lock:
            now = time.monotonic()
            tat = max(self._tat, now) + self.interval
            wait = tat - now - self.burst_s
            if wait > self.queue_s:
                return None
            self._tat = tat
            return max(0.0, wait)


class RefusalLog:
    """Refused requests of one kernel: counted by kind; the first REFUSALS_LOGGED logged one by one, then one
    summary line (and supervisor event) per REFUSAL_SUMMARY_S while they go on, and one at the end. A flood
    of refusals used to write ~88 000 log lines a second and rotate the application's logs away."""

    def __init__(self, kernel_pid: int, event: Callable[..., None] | None) -> None:
        self.kernel_pid = kernel_pid
        self.event = event
        self.total = 0
        self.by_kind: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._unreported = 0
        self._last_reason = ""
        self._last_summary = time.monotonic()

    def note(self, kind: str, reason: str) -> bool:
        """Count one refusal; True when it is one of the first (logged and recorded one by one)."""
        with self._lock:
            self.total += 1
            self.by_kind[kind] += 1
            if self.total <= REFUSALS_LOGGED:
                log.warning("script kernel %s: refused %s", self.kernel_pid, reason)
                if self.total == REFUSALS_LOGGED:
                    log.warning("script kernel %s: further refusals are counted and summarised every %.0f s",
                                self.kernel_pid, REFUSAL_SUMMARY_S)
                return self.total <= REFUSALS_RECORDED
            self._unreported += 1
            self._last_reason = reason
            now = time.monotonic()
            if now - self._last_summary >= REFUSAL_SUMMARY_S:
                self._summary_locked(now)
            return self.total <= REFUSALS_RECORDED

    def flush(self) -> None:
        with self._lock:
            if self._unreported:
                self._summary_locked(time.monotonic())

    def _summary_locked(self, now: float) -> None:
        kinds = ", ".join(f"{n} {k}" for k, n in sorted(self.by_kind.items()))
        log.warning("script kernel %s: %d more requests refused since the last report (%d in all: %s); "
                    "the last: %s", self.kernel_pid, self._unreported, self.total, kinds, self._last_reason)
        if self.event is not None:
            self.event(journal.SCRIPT_REQUESTS_REFUSED, count=self._unreported, total=self.total,
                       by_kind=dict(self.by_kind), last=self._last_reason, kernel_pid=self.kernel_pid)
        self._unreported = 0
        self._last_summary = now


# ---------------------------------------------------------------------------------------------- the bridge
class ApiBridge:
    """Answers one kernel's requests with the in-app API objects; streams the samples it subscribed to."""

    def __init__(self, host: ScriptHost, kernel: KernelProcess, gate: Gate, *, source: str = "script",
                 base_dir: Path | None = None) -> None:
        self.host = host
        self.kernel = kernel
        self.gate = gate
        self.context = _InlineContext(host, source=source, base_dir=base_dir)
        self.objects = api.build_api(self.context)
        self.encoder = SampleEncoder()
        self.limiter = CallLimiter()
        self.refusal_budget = CallLimiter(REFUSAL_RATE, REFUSAL_BURST, 0.0)
        self.refusal_log = RefusalLog(kernel.warden_pid, host.supervisor.record)
        self._sub_lock = threading.Lock()
        self._subscribed: set[str] = set()
        self._schema_sent: dict[str, type] = {}
        self._samples: Subscription | None = None  # every stream a kernel may subscribe to, from the bus
        self._pump: threading.Thread | None = None  # drains it into the kernel's link
        self._calls: queue.SimpleQueue[tuple[float, dict[str, Any]] | None] = queue.SimpleQueue()
        self._caller: threading.Thread | None = None  # runs the kernel's calls in order (started at the first)
        self._caller_lock = threading.Lock()
        self._profiles: dict[int, Any] = {}
        self._profile_ids = itertools.count(1)
        self._closed = False

    # ------------------------------------------------------------------ requests (reader thread)
    def handle(self, msg: dict[str, Any]) -> bool | Callable[[], None]:
        """Serve ``msg`` if it is a request (True; the e-stop: the work to run at once, off the reading lead);
        False if it is not one of the bridge's. A call is queued for the bridge's call thread."""
        op = msg.get("op")
        if op == "call":
            rid = msg.get("id")
            if not isinstance(rid, int):
                self.refuse(msg, "a call without an id")
                return True
            if not self._is_api_call(msg):  # refused before it costs any of the call budget
                obj, name = msg.get("obj"), msg.get("name")
                self.refuse(msg, f"{obj!s:.40}.{name!s:.60} is not a script API call")
                self.reply(rid, error=ScriptError(f"{obj!s:.40}.{name!s:.60}: not a script API call (refused)"))
                return True
            if (msg["obj"], msg["name"]) == ESTOP_CALL:
                return lambda: self._call(msg)  # never behind a command waiting for its ACK, nor the rate
            wait = self.limiter.admit()
            if wait is None:  # a flood: refused at once, counted, answered (the script's call raises)
                self.refuse(msg, f"a call over the rate limit ({CALL_RATE:.0f} calls a second)", kind="over rate")
                self.reply(rid, error=ScriptError(f"too many API calls: more than {CALL_RATE:.0f} a second "
                                                  "(refused)"))
                return True
            self._queue_call(time.monotonic() + wait, msg)
            return True
        if op in ("subscribe", "peek"):
            rid = msg.get("id")
            stream = msg.get("stream")
            if not isinstance(rid, int) or not isinstance(stream, str) or stream not in STREAMS:
                self.refuse(msg, f"{op} of an unknown stream")
                if isinstance(rid, int):
                    self.reply(rid, error=ScriptError(f"no such data stream: {stream!r}"))
                return True
            try:
                value = self._subscribe(stream) if op == "subscribe" else self._peek(stream)
            except BaseException as exc:
                self.reply(rid, error=exc)
            else:
                self.reply(rid, value=value)
            return True
        return False

    @staticmethod
    def _is_api_call(msg: dict[str, Any]) -> bool:
        obj, name, args = msg.get("obj"), msg.get("name"), msg.get("args")
        allowed = ALLOWED_CALLS.get(obj, frozenset()) if isinstance(obj, str) else frozenset()
        attributes = ALLOWED_ATTRIBUTES.get(obj, frozenset()) if isinstance(obj, str) else frozenset()
        return isinstance(name, str) and (name in allowed or name in attributes) and isinstance(args, list) \
            and len(args) <= 16 and all(_is_plain_arg(a) for a in args)

    # ------------------------------------------------------------------ the call thread
    def _queue_call(self, due: float, msg: dict[str, Any]) -> None:
        with self._caller_lock:
            if self._closed:
                self.reply(msg["id"], error=ScriptStopped("the script has ended"))
                return
            self._calls.put((due, msg))
            if self._caller is None:
                self._caller = threading.Thread(target=self._caller_main, name=f"kernel-{self.kernel.warden_pid}-calls",
                                                daemon=True)
                self._caller.start()

    def _caller_main(self) -> None:
        """The kernel's calls, one after the other in the order they were read (a call over the rate waits its
        turn here, not on a reader)."""
        while True:
            entry = self._calls.get()
            if entry is None:
                return
            due, msg = entry
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            try:
                self._call(msg)
            except Exception:  # a bug serving one call must not end the thread serving the others
                log.exception("script kernel %s: a call failed", self.kernel.warden_pid)

    def _call(self, msg: dict[str, Any]) -> None:
        rid = msg["id"]
        obj, name, args = msg["obj"], msg["name"], msg["args"]
        attributes = ALLOWED_ATTRIBUTES.get(obj, frozenset())
        # The e-stop passes whatever the gate says: paused or stopping, stopping the devices is always welcome.
        if (obj, name) != ESTOP_CALL and not self.gate.enter():
            self.reply(rid, error=ScriptStopped("the script is being stopped"))
            return
        try:
            target = self.objects[obj]
            if name in attributes:
                value = getattr(target, name)
            else:
                value = getattr(target, name)(*[self._arg(a) for a in args])
        except BaseException as exc:
            self.reply(rid, error=exc)
            return
        self.reply(rid, value=self._result(value))

    def _arg(self, value: Any) -> Any:
        if isinstance(value, dict):  # {"profile": token}: a profile the application holds
            profile = self._profiles.get(value.get("profile"))  # type: ignore[arg-type]
            if profile is None:
                raise TypeError("unknown FES profile")
            return profile
        return value

    def _result(self, value: Any) -> Any:
        from app.core.fes_profile import FesProfile

        if isinstance(value, FesProfile):
            token = next(self._profile_ids)
            self._profiles[token] = value
            return {"token": token, "name": getattr(value, "name", None), "axis": getattr(value, "axis", None),
                    "channels": [str(c) for c in getattr(value, "channels", {})]}
        if isinstance(value, dict):
            return {str(k): self._result(v) for k, v in value.items()}
        if isinstance(value, list):
            return [self._result(v) for v in value]
        return _plain(value) if not isinstance(value, tuple) else value

    def reply(self, rid: int, value: Any = None, error: BaseException | None = None) -> None:
        msg: dict[str, Any] = {"op": "reply", "id": rid}
        if error is not None:
            kind = api_spec.wire_error_name(error)
            text = str(error) if kind != "ScriptError" or isinstance(error, ScriptError) \
                else f"{type(error).__name__}: {error}"
            if isinstance(error, KeyError) and error.args:
                text = str(error.args[0])
            msg["error"] = {"type": kind, "message": text}
        elif isinstance(value, tuple):
            msg["value"] = [_plain(v) for v in value]
            msg["tuple"] = True
        else:
            msg["value"] = value
        self.kernel.send(msg)

    @property
    def refusals(self) -> int:
        return self.refusal_log.total

    def refuse(self, msg: dict[str, Any], reason: str, kind: str = "not an API call") -> None:
        """Count a refused request; the first REFUSALS_RECORDED are recorded one by one (supervisor event
        ``script_request_refused``), the rest in periodic summaries (``script_requests_refused``)."""
        reason = str(reason)[:200]
        if kind != "bad line" and self.refusal_budget.admit() is None:
            self.kernel.end_for_violation(f"a flood of requests (more than {REFUSAL_BURST} refused in a row)")
        if self.refusal_log.note(kind, reason):
            self.host.supervisor.record(journal.SCRIPT_REQUEST_REFUSED, reason=reason, op=str(msg.get("op"))[:40],
                                       kernel_pid=self.kernel.warden_pid)

    # ------------------------------------------------------------------ samples
    def _driver(self, stream: str) -> tuple[Any, str]:
        device, label = STREAMS[stream]
        driver = self.host.driver(device)
        if driver is None:
            raise DeviceUnavailable(f"{label} is not available: it is switched off in the configuration "
                                    "or its driver is missing from this build")
        return driver, label

    def _peek(self, stream: str) -> Any:
        self._driver(stream)
        return self.encoder.snapshot(self.host.bus.latest(stream))

    def _subscribe(self, stream: str) -> dict[str, Any]:
        driver, label = self._driver(stream)
        bus = self.host.bus
        with self._sub_lock:
            if self._closed:
                raise ScriptStopped("the script has ended")
            self._subscribed.add(stream)
            if self._samples is None:
                # One queue for the streams the kernel subscribed to, so their samples reach it in the order they
                # were published; only those streams wake the pump (not every driver's every read).
                self._samples = bus.subscribe(f"script:{self.kernel.warden_pid}", tuple(self._subscribed),
                                              maxlen=SAMPLE_QUEUE)
                self._pump = threading.Thread(target=self._pump_main, args=(self._samples,),
                                              name=f"kernel-{self.kernel.warden_pid}-samples", daemon=True)
                self._pump.start()
            else:
                bus.resubscribe(self._samples, tuple(self._subscribed))
            sample = bus.latest(stream)
        return {"label": label, "connected": bool(driver.connected), "sample": self.encoder.snapshot(sample)}

    def _pump_main(self, sub: Subscription) -> None:
        """The subscribed streams' samples to the kernel, as the bus delivers them (woken once per driver
        read); never blocks on the kernel (what its link does not take waits in the link's backlog)."""
        subscribed = self._subscribed
        schema_sent = self._schema_sent
        encoder = self.encoder
        kernel = self.kernel
        while not sub.closed:
            sub.wait(0.05)  # woken by the bus; the timeout only bounds how long a closed queue keeps it
            for item in sub.drain():
                if not isinstance(item, SampleItem) or item.stream not in subscribed:
                    continue
                stream, sample = item.stream, item.sample
                fields = encoder.fields(sample)
                head = b""
                if schema_sent.get(stream) is not type(sample):
                    schema_sent[stream] = type(sample)
                    head = encode({"op": "schema", "s": stream, "type": type(sample).__name__,
                                    "fields": list(fields)})
                kernel.send_bytes(head + encode({"op": "sample", "s": stream, "v": encoder.values(sample, fields)}),
                                  droppable=not head)

    @property
    def samples_dropped(self) -> int:
        """Samples the bridge's subscription lost because its pump fell behind (the link's own: the kernel's)."""
        sub = self._samples
        return sub.dropped if sub is not None else 0

    def unsubscribe_all(self) -> None:
        with self._sub_lock:
            self._subscribed.clear()
            self._schema_sent.clear()
            sub, self._samples = self._samples, None
            pump, self._pump = self._pump, None
        if sub is not None:
            sub.close()  # the pump sees it within 50 ms and ends (never waited for here: Start may be waiting)
        del pump

    def close(self) -> None:
        self.unsubscribe_all()
        with self._sub_lock:
            self._closed = True
        with self._caller_lock:
            self._closed = True
            caller, self._caller = self._caller, None
        if caller is not None:
            self._calls.put(None)  # after the calls queued before it: each is answered (refused: the gate)
            if caller is not threading.current_thread():
                caller.join(0.05)  # a call waiting for its ACK ends on its own; never hold the closing thread
        self.context.close()
        self.refusal_log.flush()


def _is_plain_arg(value: Any) -> bool:
    if value is None or isinstance(value, bool | int | float | str):
        return True
    return isinstance(value, dict) and set(value) == {"profile"} and isinstance(value["profile"], int)
