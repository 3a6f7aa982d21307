"""The application's side of the script kernel (app/scripting/kernel.py): the child process, its link, and
the bridge that answers the kernel's requests with the in-app API (app/scripting/api.py).

* :class:`KernelProcess` starts ``python -I kernel.py`` with one end of an AF_UNIX socket pair, reads its
  messages, its stdout/stderr (a crash report from faulthandler lands there) and notices its end — all on
  reader threads of its own (never the GUI thread). Writes never block the caller: what the socket
  does not take at once waits in a backlog a writer thread drains.
* :class:`ApiBridge` serves one kernel: ``subscribe`` (every sample of the stream from then on, in
  order: the bridge's subscription to the stream bus, app/bus.py, drained and sent to the kernel by a
  thread of the bridge's own), ``peek`` (completion), and ``call`` — only the API's own methods
  (:data:`ALLOWED_CALLS`), executed by the existing API objects, in the order the kernel sent them, on
  the bridge's call thread: never on the thread that reads the kernel's requests, so a command waiting
  for its acknowledgement holds up neither the reading nor the kernel's next requests. The script's
  e-stop (``linarmppManager.emergencyStop``) is never queued behind a command: it runs as soon as it is
  read, off the reading lead. Every call passes through the drivers' single command path and the safety
  supervisor. Anything else is refused and recorded (supervisor event ``script_request_refused``).

Kernel → application is JSON only: a hostile script controls those bytes, so they are never unpickled,
and every field is checked before use.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import json
import logging
import os
import queue
import re
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app import journal, streams
from app.bus import SampleItem, Subscription
from app.devices import linarm_protocol as proto
from app.scripting import api
from app.scripting.api import (
    CommandError,
    CommandRefused,
    DeviceUnavailable,
    ScriptContext,
    ScriptError,
    ScriptStopped,
)

if TYPE_CHECKING:
    from app.services import ScriptHost

log = logging.getLogger(__name__)

KERNEL_FILE = Path(__file__).resolve().parent / "kernel.py"
WARDEN_FILE = Path(__file__).resolve().parent / "warden.py"  # the kernel's parent: owns whatever a script starts
MEMORY_LIMIT_BYTES = 2 * 1024**3  # address space of a kernel: a runaway allocation fails as MemoryError there
MAX_MESSAGE = 4 * 1024 * 1024  # a longer line from the kernel is a protocol violation
BACKLOG_LIMIT = 16 * 1024 * 1024  # bytes waiting for a kernel that does not read: samples beyond are dropped
READERS = 3  # leader/follower threads per kernel (urgent work a handler returns, the e-stop, runs off the lead)
REFUSALS_RECORDED = 20  # per kernel; a flood of bad requests is counted, not recorded one by one
REFUSALS_LOGGED = 10  # per kernel, line by line; then one summary line per REFUSAL_SUMMARY_S at most
REFUSAL_SUMMARY_S = 5.0
PROBLEMS_LOGGED = 5  # handler failures logged with a traceback per kernel; the rest are counted
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
# Bytes read from a kernel: READ_RATE a second once READ_BURST is spent. A script is only slowed (its writes
# wait in the socket: back-pressure), never failed; the application's readers never parse more than this
# (a script printing 3 MB lines in a loop would otherwise keep a reader thread, and the GIL, busy).
READ_RATE = 8 * 1024 * 1024
READ_BURST = 16 * 1024 * 1024
CONTROL_TIMEOUT_S = 5.0  # the warden's answers (its first line comes ~20 ms after the start)

# stream -> (device, label): the streams a script may subscribe to (one place: the kernel gets it in hello)
STREAMS: dict[str, tuple[str, str]] = {
    streams.LINARM_STATE: (streams.LINARM, "the LINarm"),
    streams.LINARM_VSA: (streams.LINARM, "the LINarm"),
    streams.LINARM_MOTOR0: (streams.LINARM, "the LINarm"),
    streams.LINARM_MOTOR1: (streams.LINARM, "the LINarm"),
    streams.PHYSIO_MAIN: (streams.PHYSIO, "the physiological sensors"),
    streams.PATIENT_MODEL_MAIN: (streams.PATIENT_MODEL, "the patient model"),
    streams.VR_MAIN: (streams.VR, "the VR renderer"),
}
SAMPLE_QUEUE = 65536  # samples waiting to be sent to a kernel (oldest dropped and counted beyond)
ESTOP_CALL = ("linarmppManager", "emergencyStop")  # never queued behind a command

# The proxies' shape: state properties (name -> stream, doc) and callback setters (name -> stream, list).
OBJECT_SHAPES: dict[str, dict[str, Any]] = {
    "linarm": {
        "doc": "linarm: the LINarm2 robot. Commands block until the controller acknowledges them.",
        "properties": {
            "linarmState": (streams.LINARM_STATE, "controlState, controlMode, homeState, errorState, triggerMode, "
                                            "initialized, trajectoryType, …"),
            "linarmVsaState": (streams.LINARM_VSA, "equilibriumPos (m), delta (m), stiffness (N/m), handlePos (m), "
                                             "handleVel (m/s), interactionForce (N)."),
            "linarmMotor0State": (streams.LINARM_MOTOR0, "position (m), velocity (m/s), current (A), target (m)."),
            "linarmMotor1State": (streams.LINARM_MOTOR1, "position (m), velocity (m/s), current (A), target (m)."),
        },
        "callbacks": {
            "setLinarmDataCallbackFun": (streams.LINARM_STATE, "linarmDataCallbackList"),
            "setLinarmMotor0DataCallbackFun": (streams.LINARM_MOTOR0, "linarmMotor0DataCallbackList"),
            "setLinarmMotor1DataCallbackFun": (streams.LINARM_MOTOR1, "linarmMotor1DataCallbackList"),
            "setLinarmVsaDataCallbackFun": (streams.LINARM_VSA, "linarmVsaDataCallbackList"),
        },
    },
    "physiologicalSensors": {
        "doc": "physiologicalSensors: grip force (N), skin temperature (°C), heart rate (bpm), skin conductance (µS).",
        "properties": {"physiologicalSensorsData": (streams.PHYSIO_MAIN,
                                                    "force (N), temperature (°C), heartRate (bpm), "
                                                    "skinConductance (µS), boardTime (s), …")},
        "callbacks": {"setPhysiologicalSensorsDataCallbackFun": (streams.PHYSIO_MAIN, "physiologicalDataCallbackList")},
    },
    "patientModel": {
        "doc": "patientModel: the patient model's latest output (alpha, a_r, a_f, tpi, mpi, pti).",
        "properties": {"patientModelData": (streams.PATIENT_MODEL_MAIN, "alpha, a_r, a_f, tpi, mpi, pti")},
        "callbacks": {"setPatientModelDataCallbackFun": (streams.PATIENT_MODEL_MAIN, "patientModelDataCallbackList")},
    },
    "VRUnity": {
        "doc": "VRUnity: the VR renderer's latest frame (targetPos, score, targetsReached).",
        "properties": {"VRUnityData": (streams.VR_MAIN, "targetPos, score, targetsReached")},
        "callbacks": {"setVRUnityDataCallbackFun": (streams.VR_MAIN, "VRUnityDataCallbackList")},
    },
    "fes": {"doc": "fes: the RehaStim stimulator; every change passes the FES limiter of the safety supervisor."},
}

# What a kernel may call: object -> methods of the in-app API objects (and readable attributes).
ALLOWED_CALLS: dict[str, frozenset[str]] = {
    "linarm": frozenset({c.name for c in api.SCRIPT_COMMANDS} | {"getConfigData"}),
    "fes": frozenset({"loadFile", "writeFile", "start", "stop", "setCurrentScaleFactor", "setPWScaleFactor",
                      "setPhase", "getConfigData", "electrodeSetup"}),
    "linarmppManager": frozenset({"emergencyStop", "startRepetition", "endRepetition", "reportProgress",
                                  "prompt", "setRunState"}),
}
ALLOWED_ATTRIBUTES: dict[str, frozenset[str]] = {"fes": frozenset({"profile", "stimulating"})}
_ERROR_NAMES: tuple[tuple[type[BaseException], str], ...] = (
    (ScriptStopped, "ScriptStopped"), (CommandRefused, "CommandRefused"), (DeviceUnavailable, "DeviceUnavailable"),
    (CommandError, "CommandError"), (ScriptError, "ScriptError"), (TypeError, "TypeError"),
    (FileNotFoundError, "FileNotFoundError"), (KeyError, "KeyError"), (ValueError, "ValueError"),
    (OSError, "OSError"),
)


def hello_message() -> dict[str, Any]:
    """The API's shape for a new kernel: the command table, the enums, the objects' streams (data only)."""
    commands = [{"name": c.name, "args": [a.name for a in c.args], "doc": api._command_doc(c)}
                for c in api.SCRIPT_COMMANDS]
    enums = {name: {m.name: int(m.value) for m in getattr(proto, name)}
             for name in ("CONTROL_STATES", "CONTROL_MODES", "HOME_STATES", "ERROR_STATES", "TRIGGER_MODES",
                          "TRAJECTORY_TYPES")}
    return {"op": "hello", "commands": commands, "aliases": {"moveDeltato": "moveDeltaTo"}, "enums": enums,
            "objects": OBJECT_SHAPES, "labels": {s: label for s, (_d, label) in STREAMS.items()}}


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


# ---------------------------------------------------------------------------------------------- process
_LONE_SURROGATE = re.compile(rb"\\u[dD][89a-fA-F]", re.ASCII)


_OWN: Any = object()  # marks a violation found here (a JSON key is always text: a kernel cannot forge it)


def _violation(reason: str) -> dict[str, Any]:
    return {"op": "__violation__", "reason": reason, _OWN: True}


def _parse(line: bytes) -> dict[str, Any]:
    """One line from the kernel as a JSON object, or a ``__violation__`` saying what is wrong with it. Never
    raises: a hostile script writes these bytes (deep nesting, huge numbers, invalid UTF-8, lone surrogates)."""
    if len(line) > MAX_MESSAGE:
        return _violation(f"a message longer than {MAX_MESSAGE // (1024 * 1024)} MB")
    try:
        msg = json.loads(line)
    except RecursionError:
        return _violation("a message nested too deeply")
    except UnicodeDecodeError:
        return _violation("a message that is not UTF-8 text")
    except (ValueError, MemoryError):  # not JSON; an integer of more than 4300 digits
        return _violation("a message that is not JSON")
    except Exception:  # whatever else the decoder may raise: never a reader thread's end
        return _violation("a message that could not be read")
    if not isinstance(msg, dict):
        return _violation("a message that is not a JSON object")
    if _LONE_SURROGATE.search(line):  # "\ud800" decodes to text no file, log or console can encode
        try:
            json.dumps(msg, ensure_ascii=False).encode("utf-8")
        except (UnicodeEncodeError, RecursionError, ValueError):
            return _violation("a message with text that is not valid Unicode")
    return msg


def _encode(msg: dict[str, Any]) -> bytes:
    return (json.dumps(msg, separators=(",", ":"), default=str) + "\n").encode()


def _kernel_environment() -> dict[str, str]:
    """The kernel's environment: the application's, without anything meant for another helper."""
    from app.devices.udp_frames import LINK_KEY_ENV
    from app.patient_model.process import LINK_KEY_FD_ENV

    env = dict(os.environ)
    for name in (LINK_KEY_ENV, LINK_KEY_FD_ENV):
        env.pop(name, None)
    return env


def describe_end(returncode: int | None) -> str:
    """How a kernel process ended, in words."""
    if returncode is None:
        return "it stopped answering"
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        what = {"SIGSEGV": "a segmentation fault", "SIGABRT": "an abort", "SIGBUS": "a bus error",
                "SIGFPE": "a floating-point exception", "SIGKILL": "killed", "SIGTERM": "terminated",
                "SIGILL": "an illegal instruction"}.get(name, "killed by a signal")
        return f"{what} ({name})"
    if returncode == 4:
        return "out of memory (MemoryError)"
    return f"it exited with code {returncode}"


class KernelProcess:
    """One kernel process and its link. ``handler(msg)`` gets the kernel's messages (reader thread);
    ``on_output(stream, text)`` its raw stdout/stderr; ``on_exit(kernel)`` runs once when it has ended."""

    def __init__(self, memory_limit: int = MEMORY_LIMIT_BYTES) -> None:
        self.handler: Callable[[dict[str, Any]], Callable[[], None] | None] | None = None
        self.on_output: Callable[[str, str], None] | None = None
        self.on_exit: Callable[[KernelProcess], None] | None = None
        # called once (reader thread) when the kernel's link closes: the kernel has ended, even if its
        # warden has not yet reported how (it ends what the script started first)
        self.on_link_closed: Callable[[KernelProcess], None] | None = None
        self.used = False
        self.ready = threading.Event()
        self.ended = threading.Event()
        self.startup_s: float | None = None  # spawn → ready, measured here
        self.returncode: int | None = None
        self.stderr_tail = ""
        self.crash_report = False
        self._wlock = threading.Lock()
        self._backlog = bytearray()
        self._wake = threading.Event()
        self._closed = False
        self.samples_dropped = 0
        self._early: list[dict[str, Any]] = []
        self.violation: str | None = None  # why the application ended this kernel (a line it would not take)
        self.bytes_read = 0
        self._read_tokens = float(READ_BURST)
        self._read_t = time.monotonic()
        self.problems = 0  # messages whose handling failed (logged up to PROBLEMS_LOGGED)
        t0 = time.perf_counter()
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        for s in (parent, child):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        control, control_child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            # The warden (app/scripting/warden.py) is the kernel's parent, in a session of its own: a child
            # subreaper that ends every process the script starts at Stop, at the run's end and when the
            # application goes (its control link closes). Its exit status is the kernel's.
            self.proc = subprocess.Popen(
                [sys.executable, "-I", str(WARDEN_FILE), str(child.fileno()), str(int(memory_limit)),
                 str(control_child.fileno())],
                pass_fds=(child.fileno(), control_child.fileno()), stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True, cwd=os.getcwd(),
                env=_kernel_environment())
        except BaseException:
            control.close()
            raise
        finally:
            child.close()
            control_child.close()
        self._t_spawn = t0
        self.sock = parent
        self.sock.setblocking(False)
        self.warden_pid = self.proc.pid
        self._control = control
        self._control.settimeout(CONTROL_TIMEOUT_S)
        self._control_lock = threading.Lock()
        self._control_buf = b""
        self._kernel_pid: int | None = None
        self._lead = threading.Lock()
        self._busy_lock = threading.Lock()
        self._busy = 0
        self._inbox: collections.deque[dict[str, Any]] = collections.deque()
        self._buf = bytearray()
        self._sock_open = True
        self._finished = False
        self._overflow_pool: ThreadPoolExecutor | None = None
        assert self.proc.stdout is not None and self.proc.stderr is not None
        self._sel = selectors.DefaultSelector()
        self._sel.register(self.sock, selectors.EVENT_READ, "sock")
        for pipe, name in ((self.proc.stdout, "stdout"), (self.proc.stderr, "stderr")):
            os.set_blocking(pipe.fileno(), False)
            self._sel.register(pipe, selectors.EVENT_READ, name)
        self._writer = threading.Thread(target=self._write_main, name=f"kernel-{self.warden_pid}-writer", daemon=True)
        self._writer.start()
        for i in range(READERS):
            threading.Thread(target=self._reader_main, name=f"kernel-{self.warden_pid}-reader{i}", daemon=True).start()
        self.send(hello_message())

    # ------------------------------------------------------------------ state
    @property
    def pid(self) -> int:
        """The kernel's own process id (the warden reports it as soon as it has forked)."""
        if self._kernel_pid is None:
            line = self._control_line()
            if line is not None and line.startswith("pid "):
                try:
                    self._kernel_pid = int(line[4:])
                except ValueError:
                    pass
        return self._kernel_pid if self._kernel_pid is not None else self.warden_pid

    @property
    def alive(self) -> bool:
        return not self.ended.is_set() and self.proc.poll() is None

    def cause(self) -> str:
        if self.violation is not None:
            return f"ended by the application: it sent {self.violation}"
        return describe_end(self.returncode)

    # ------------------------------------------------------------------ the warden's control link
    def _control_line(self, timeout_s: float = CONTROL_TIMEOUT_S) -> str | None:
        """The warden's next line (None when it has not come in ``timeout_s`` or the link is closed)."""
        with self._control_lock:
            deadline = time.monotonic() + timeout_s
            while b"\n" not in self._control_buf:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                try:
                    self._control.settimeout(remaining)
                    data = self._control.recv(256)
                except (OSError, ValueError):
                    return None
                if not data:
                    return None
                self._control_buf += data
            line, self._control_buf = self._control_buf.split(b"\n", 1)
            return line.decode("ascii", "replace")

    def _control_send(self, command: str) -> bool:
        try:
            self._control.sendall(command.encode() + b"\n")
            return True
        except (OSError, ValueError):
            return False

    def sweep(self, timeout_s: float = 3.0) -> int | None:
        """End every process the script started, except the kernel itself (it serves the prompt on); the
        number ended, or None when the warden did not answer (the kernel has ended: the warden then ended
        them all already)."""
        if self.ended.is_set() or self.proc.poll() is not None:
            return None
        self.pid  # noqa: B018 - the warden's first line (the kernel's pid) is read before its answer
        if not self._control_send("sweep"):
            return None
        line = self._control_line(timeout_s)
        if line is None or not line.startswith("swept "):
            return None
        try:
            return int(line[6:])
        except ValueError:
            return None

    def bind(self, handler: Callable[[dict[str, Any]], Callable[[], None] | None],
             on_output: Callable[[str, str], None], on_exit: Callable[[KernelProcess], None]) -> None:
        with self._wlock:
            self.handler, self.on_output, self.on_exit = handler, on_output, on_exit
            early, self._early = self._early, []
        for msg in early:
            job = handler(msg)
            if job is not None:
                self._overflow().submit(job)
        if self.ended.is_set():
            on_exit(self)

    # ------------------------------------------------------------------ writing (any thread, never blocks)
    def send(self, msg: dict[str, Any], *, droppable: bool = False) -> bool:
        return self.send_bytes(_encode(msg), droppable=droppable)

    def send_bytes(self, data: bytes, *, droppable: bool = False) -> bool:
        with self._wlock:
            if self._closed:
                return False
            if self._backlog:
                if droppable and len(self._backlog) > BACKLOG_LIMIT:
                    self.samples_dropped += 1
                    return False
                self._backlog += data
                self._wake.set()
                return True
            try:
                n = self.sock.send(data)
            except BlockingIOError:
                n = 0
            except OSError:
                self._closed = True
                return False
            if n < len(data):
                self._backlog += data[n:]
                self._wake.set()
        return True

    def _write_main(self) -> None:
        sel = selectors.DefaultSelector()
        try:
            sel.register(self.sock, selectors.EVENT_WRITE)
        except (ValueError, OSError):
            return
        while not self.ended.is_set():
            self._wake.wait(0.5)
            while True:
                with self._wlock:
                    if self._closed or not self._backlog:
                        self._wake.clear()
                        break
                    try:
                        n = self.sock.send(self._backlog)
                    except BlockingIOError:
                        n = 0
                    except OSError:
                        self._closed = True
                        break
                    del self._backlog[:n]
                if n == 0:
                    sel.select(0.05)
        sel.close()

    # ------------------------------------------------------------------ reading (leader/follower threads)
    def _reader_main(self) -> None:
        """One of READERS threads. The leader reads and delivers messages in order; a message whose handler
        returns work (the script's e-stop: ApiBridge queues every other call for its call thread) is run by
        the thread that read it, after it handed the lead to another reader, so it neither waits for a
        thread hop nor holds up what the kernel sends next."""
        while True:
            job: Callable[[], None] | None = None
            with self._lead:
                while job is None:
                    if self._finished:
                        return
                    if self._inbox:
                        try:
                            job = self._deliver(self._inbox.popleft())
                        except Exception:  # a handler's bug must not cost a reader thread
                            self._problem("a message could not be handled", exc_info=True)
                        continue
                    if not self._sock_open:
                        self._finish()
                        return
                    try:
                        self._poll()
                    except Exception as exc:  # never a reader's end: the kernel is ended, the readers go on
                        self._problem(f"reading the kernel's link failed: {type(exc).__name__}: {exc}")
                        self.end_for_violation("a message that could not be read")
                if self._busy >= READERS - 1:  # keep a reader free: the overflow pool runs this one
                    self._overflow().submit(job)
                    job = None
                    continue
                with self._busy_lock:
                    self._busy += 1
            try:
                job()
            except Exception:
                self._problem("a request failed", exc_info=True)
            finally:
                with self._busy_lock:
                    self._busy -= 1

    def _overflow(self) -> ThreadPoolExecutor:
        if self._overflow_pool is None:
            self._overflow_pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix=f"kernel-{self.warden_pid}-call")
        return self._overflow_pool

    def _problem(self, what: str, exc_info: bool = False) -> None:
        """A failure while serving this kernel: logged PROBLEMS_LOGGED times, then only counted."""
        self.problems += 1
        if self.problems <= PROBLEMS_LOGGED:
            log.error("script kernel %s: %s", self.warden_pid, what, exc_info=exc_info)
            if self.problems == PROBLEMS_LOGGED:
                log.error("script kernel %s: further failures are counted, not logged", self.warden_pid)

    def end_for_violation(self, reason: str) -> None:
        """The kernel sent a line the application will not take: end it (the run ends with an error that
        says so); what it sends from now on is dropped unread."""
        if self.violation is None:
            self.violation = reason
            log.warning("script kernel %s sent %s: ending it", self.warden_pid, reason)
        self.kill()

    def _poll(self) -> None:
        """Wait (≤ 0.5 s) for the kernel's socket or pipes; parse what came into the inbox."""
        for key, _ in self._sel.select(0.5):
            if key.data == "sock":
                now = time.monotonic()
                self._read_tokens = min(float(READ_BURST), self._read_tokens + (now - self._read_t) * READ_RATE)
                self._read_t = now
                if self._read_tokens < 0:  # over the read budget: the kernel waits (its socket fills up)
                    time.sleep(min(0.05, -self._read_tokens / READ_RATE))
                    continue
                try:
                    data = self.sock.recv(1 << 16)
                except BlockingIOError:
                    continue
                except OSError:
                    data = b""
                if not data:
                    self._sel.unregister(self.sock)
                    self._sock_open = False
                    closed = self.on_link_closed
                    if closed is not None:
                        try:
                            closed(self)
                        except Exception:
                            log.exception("script kernel %s: on_link_closed failed", self.warden_pid)
                    continue
                self.bytes_read += len(data)
                self._read_tokens -= len(data)
                if self.violation is not None:
                    continue  # the kernel is being ended: nothing more of it is read
                buf = self._buf
                buf += data
                while True:
                    end = buf.find(b"\n")
                    if end < 0:
                        break
                    line = bytes(buf[:end])
                    del buf[:end + 1]
                    msg = _parse(line)
                    self._inbox.append(msg)
                    if _OWN in msg:
                        buf.clear()
                        self.end_for_violation(str(msg["reason"]))
                        break
                if len(buf) > MAX_MESSAGE:
                    msg = _violation(f"a message longer than {MAX_MESSAGE // (1024 * 1024)} MB")
                    self._inbox.append(msg)
                    buf.clear()
                    self.end_for_violation(str(msg["reason"]))
            else:
                pipe = key.fileobj
                try:
                    data = os.read(pipe.fileno(), 1 << 16)  # type: ignore[union-attr]
                except BlockingIOError:
                    continue
                except OSError:
                    data = b""
                if not data:
                    self._sel.unregister(pipe)
                    continue
                self._raw(key.data, data)

    def _raw(self, stream: str, data: bytes) -> None:
        text = data.decode("utf-8", "replace")
        if stream == "stderr":
            self.stderr_tail = (self.stderr_tail + text)[-4000:]
            self.crash_report = self.crash_report or "Fatal Python error" in self.stderr_tail
        out = self.on_output
        if out is not None and not self.crash_report:  # a crash report is summarised by the runner
            out(stream, text)

    def _finish(self) -> None:
        """The socket closed: the kernel ended (or is about to). Collect what it wrote last and its code."""
        self._finished = True
        try:
            self.returncode = self.proc.wait(0.5)
        except subprocess.TimeoutExpired:
            self.kill()
            try:  # the warden ends its sweep within 2 s
                self.returncode = self.proc.wait(3.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.returncode = self.proc.wait(1.0)
        try:
            self._control.close()
        except OSError:
            pass
        for key in list(self._sel.get_map().values()):
            if key.data in ("stdout", "stderr"):
                try:
                    data = os.read(key.fileobj.fileno(), 1 << 16)  # type: ignore[union-attr]
                except OSError:
                    data = b""
                if data:
                    self._raw(key.data, data)
        self._sel.close()
        with self._wlock:
            self._closed = True
        self.ended.set()
        self._wake.set()
        for f in (self.proc.stdout, self.proc.stderr):
            try:
                f.close()  # type: ignore[union-attr]
            except OSError:
                pass
        self.sock.close()
        if self._overflow_pool is not None:
            self._overflow_pool.shutdown(wait=False)
        with self._wlock:
            on_exit = self.on_exit
        if on_exit is not None:
            on_exit(self)

    def _deliver(self, msg: dict[str, Any]) -> Callable[[], None] | None:
        if msg.get("op") == "ready" and not self.ready.is_set():
            self.startup_s = time.perf_counter() - self._t_spawn
            self.ready.set()
            return None
        with self._wlock:
            handler = self.handler
            if handler is None:
                self._early.append(msg)
                return None
        return handler(msg)

    # ------------------------------------------------------------------ ending
    def terminate(self) -> None:
        """SIGTERM to the kernel (through its warden, which then ends whatever the script started)."""
        if self.proc.poll() is None and not self._control_send("term"):
            try:
                self.proc.terminate()
            except OSError:
                pass

    def kill(self) -> None:
        """SIGKILL to the kernel (through its warden, which then ends whatever the script started). Never
        the warden itself while it answers: killed, it could no longer end the script's processes."""
        if self.proc.poll() is None and not self._control_send("kill"):
            for pid in {self._kernel_pid, self.warden_pid}:
                if pid is not None:
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except OSError:
                        pass

    def retire(self) -> None:
        """End an idle kernel: ask, and kill it if it does not go (never blocks the caller for long)."""
        self.send({"op": "exit"})
        with self._wlock:
            self._closed = True
        try:
            self.sock.shutdown(socket.SHUT_WR)  # the kernel's reader sees the end and exits
        except OSError:
            pass

        def reap() -> None:
            if not self.ended.wait(1.0):
                self.kill()
                self.ended.wait(1.0)

        threading.Thread(target=reap, name=f"kernel-{self.warden_pid}-reaper", daemon=True).start()

    def end_now(self, polite_s: float, term_s: float) -> bool:
        """TERM after ``polite_s`` without an end, KILL ``term_s`` later; True once it has ended."""
        if self.ended.wait(polite_s):
            return True
        self.terminate()
        if self.ended.wait(term_s):
            return True
        self.kill()
        return self.ended.wait(1.0)


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
            self.event("script_requests_refused", count=self._unreported, total=self.total,
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
        from app.fes_profile import FesProfile

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
            kind = next((n for t, n in _ERROR_NAMES if isinstance(error, t)), "ScriptError")
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
                    head = _encode({"op": "schema", "s": stream, "type": type(sample).__name__,
                                    "fields": list(fields)})
                kernel.send_bytes(head + _encode({"op": "sample", "s": stream, "v": encoder.values(sample, fields)}),
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
