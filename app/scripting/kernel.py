"""The script kernel: the child interpreter in which exercise scripts run (standard library only).

Started by the application's kernel process (app/scripting/kernel_process.py) through the kernel's warden
(app/scripting/warden.py), which execs ``python -I kernel.py FD MEMORY_LIMIT`` with one end of a socket pair as
``FD``. It imports nothing of the application (``-I`` keeps the application's folder off ``sys.path``, and an
import of ``app``, PySide6 or serial is refused): the API's one definition — its errors, the objects' shapes,
the callback plumbing, ``linarmppManager`` — is app/scripting/api_spec.py (standard library only), loaded here
by its path under a name outside ``app``; what only the application knows (the robot's command table, its
enums, the streams' names) arrives as data in the first message. The objects a script sees — ``linarm``,
``physiologicalSensors``, ``fes``, ``patientModel``, ``VRUnity``, ``linarmppManager``, ``emergencyStop``,
``waitCondition``, ``wait`` — are proxies that send requests and read samples streamed by the application.
Nothing here can reach a driver, a port, the safety supervisor or the manager: they live in another process.

Wire format, both directions: one JSON object per line (data only; the application never unpickles
what comes from here). Threads: the main thread runs the script; a reader thread dispatches what the
application sends; a callback thread runs the script's callbacks in arrival order; each prompt entry
and each completion runs on a thread of its own. A state attribute is the latest sample as soon as it arrives,
while its callbacks wait their turn: on a busy computer a callback runs with a sample older than the one the
script's main thread already read. A script that judges on both must not mix them (resources/exercises/
trigger_reaching.py judges its trigger in the callback alone, on the samples in the order they were taken).

Stop: the application sends ``stop``; every wait here (``time.sleep``, ``wait``, ``waitCondition``,
a request, a repeated read) notices it within 20 ms, and a pure-Python busy loop gets ScriptStopped
asynchronously. Whatever ignores that (C code, a deadlock, a crash) is terminated by the application.
"""

from __future__ import annotations

import ast
import builtins
import collections
import ctypes
import enum
import faulthandler
import inspect
import itertools
import json
import keyword
import linecache
import os
import re
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

READ_WAIT_S = 0.1  # a read with no new sample since this thread's last read waits at most this long for one
CALLBACK_QUEUE_LIMIT = 1000
ASYNC_GRACE_S = 0.01
ASYNC_RESEND_S = 0.02
SWITCH_INTERVAL_S = 0.001  # this process only: the reader thread gets the GIL quickly from a busy script
MAX_LINE = 64 * 1024 * 1024

_real_sleep = time.sleep
_real_exit = os._exit
_KERNEL_FILE = os.path.abspath(__file__)


# ---------------------------------------------------------------------------------------------- the API's definition
API_SPEC_FILE = os.path.join(os.path.dirname(_KERNEL_FILE), "api_spec.py")
API_SPEC_MODULE = "_linarmpp_script_api"  # outside ``app``: nothing of the application is imported here


def _load_api_spec() -> Any:
    """app/scripting/api_spec.py, the API's one definition the application shares, loaded by its path."""
    import importlib.util

    module = sys.modules.get(API_SPEC_MODULE)
    if module is None:
        spec = importlib.util.spec_from_file_location(API_SPEC_MODULE, API_SPEC_FILE)
        if spec is None or spec.loader is None:
            raise ImportError(f"the script API's definition cannot be loaded from {API_SPEC_FILE}")
        module = importlib.util.module_from_spec(spec)
        sys.modules[API_SPEC_MODULE] = module
        spec.loader.exec_module(module)
    return module


_api = _load_api_spec()
for _error in (_api.ScriptStopped, *_api.SCRIPT_ERRORS.values()):
    # a script's traceback names them as its namespace does ("CommandRefused: …", as when they were defined in
    # this file, the script's __main__), not by the module name they were loaded under
    _error.__module__ = "__main__"
ScriptStopped: type[BaseException] = _api.ScriptStopped
WAIT_SLICE_S: float = _api.WAIT_SLICE_S  # longest uninterrupted wait of a script thread
FIRST_SAMPLE_TIMEOUT_S: float = _api.FIRST_SAMPLE_TIMEOUT_S
DeviceUnavailable: type[Exception] = _api.DeviceUnavailable
_OWN_FILES = frozenset({_KERNEL_FILE, os.path.abspath(API_SPEC_FILE)})  # frames a script's traceback leaves out


# ---------------------------------------------------------------------------------------------- helpers
def _async_raise(thread_id: int, exc_type: type[BaseException] | None) -> None:
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id),
                                               ctypes.py_object(exc_type) if exc_type is not None else None)


class _UserThreads:
    """Which threads run user code now (only those may receive an asynchronous ScriptStopped)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._in_user: set[int] = set()

    def enter(self) -> None:
        with self._lock:
            self._in_user.add(threading.get_ident())

    def leave(self) -> None:
        tid = threading.get_ident()
        while True:  # a ScriptStopped may still land while we get here: retry until clean
            try:
                with self._lock:
                    self._in_user.discard(tid)
                    _async_raise(tid, None)
                return
            except ScriptStopped:
                continue

    def interrupt_all(self) -> int:
        with self._lock:
            for tid in self._in_user:
                _async_raise(tid, ScriptStopped)
            return len(self._in_user)


def plain(value: Any, depth: int = 0) -> Any:
    """A JSON-able copy of ``value`` (what the prompt and ``get`` show the application)."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, int | float):
        return value if type(value) in (int, float) else (int(value) if isinstance(value, int) else float(value))
    if depth < 6:
        if isinstance(value, list | tuple):
            return [plain(v, depth + 1) for v in value[:10000]]
        if isinstance(value, dict):
            return {str(k): plain(v, depth + 1) for k, v in list(value.items())[:10000]}
    return repr(value)


class _Output:
    """``sys.stdout`` / ``sys.stderr`` of the kernel: text goes to the application's console."""

    encoding = "utf-8"
    errors = "replace"

    def __init__(self, kernel: Kernel, stream: str) -> None:
        self._kernel = kernel
        self._stream = stream

    def write(self, text: str) -> int:
        if not isinstance(text, str):
            raise TypeError(f"write() argument must be str, not {type(text).__name__}")
        if text:
            self._kernel.output(self._stream, text)
        return len(text)

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    def writable(self) -> bool:
        return True


class _Stream:
    def __init__(self, name: str, label: str) -> None:
        self.name = name
        self.label = label
        self.sample: Any = None
        self.seq = 0
        self.subscribed = False
        self.connected = True
        self.cls: Any = None


class _Slot:
    __slots__ = ("event", "reply")

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reply: dict[str, Any] = {}


# ---------------------------------------------------------------------------------------------- kernel
class Kernel:
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._send_lock = threading.Lock()
        self._ids = itertools.count(1)
        self._pending: dict[int, _Slot] = {}
        self.stop_event = threading.Event()
        self.stop_reason = ""
        self.gate = threading.Event()  # cleared while paused
        self.gate.set()
        self.changed = threading.Condition()
        self.generation = 0
        self.streams: dict[str, _Stream] = {}
        self.labels: dict[str, str] = {}
        self.hello: dict[str, Any] = {}
        self.callback_queue: collections.deque[tuple[str, Any]] = collections.deque()
        self.callback_wake = threading.Event()
        self.callback_lists: dict[str, list[list[Callable[[Any], Any]]]] = {}
        self.callbacks_dropped = 0
        self.callback_errors: dict[tuple[str, int, str], int] = {}
        self.users = _UserThreads()
        self.jobs: collections.deque[dict[str, Any]] = collections.deque()
        self.jobs_wake = threading.Event()
        self.running = False
        self.filename = "<console>"
        self.base_dir: Path | None = None
        self.namespace: dict[str, Any] = {}
        self._tls = threading.local()
        self._escalator: threading.Thread | None = None
        self._schemas: dict[tuple[str, tuple[str, ...]], Any] = {}

    # ------------------------------------------------------------------ wire
    def send(self, msg: dict[str, Any]) -> None:
        data = (json.dumps(msg, separators=(",", ":"), default=repr) + "\n").encode()
        with self._send_lock:
            try:
                self.sock.sendall(data)
            except OSError:
                _real_exit(3)  # the application is gone: nothing left to serve

    def output(self, stream: str, text: str) -> None:
        self.send({"op": "out", "stream": stream, "text": text})

    def _print(self, *args: Any, sep: str | None = " ", end: str | None = "\n", file: Any = None,
               flush: bool = False) -> None:
        """``print`` in one piece (a console line is not split into its words)."""
        if file is not None and file not in (sys.stdout, sys.stderr):
            builtins.print(*args, sep=sep, end=end, file=file, flush=flush)
            return
        text = (" " if sep is None else sep).join(str(a) for a in args) + ("\n" if end is None else end)
        if text:
            self.output("stderr" if file is sys.stderr else "stdout", text)

    def request(self, op: str, **fields: Any) -> Any:
        """Send a request and wait for its answer in short, interruptible slices."""
        self.check()
        self.wait_gate()
        rid = next(self._ids)
        slot = _Slot()
        self._pending[rid] = slot
        try:
            self.send({"op": op, "id": rid, **fields})
            while not slot.event.wait(WAIT_SLICE_S):
                self.check()
        finally:
            self._pending.pop(rid, None)
        reply = slot.reply
        error = reply.get("error")
        if error is not None:
            raise _api.wire_error_class(error.get("type"))(str(error.get("message", "")))
        value = reply.get("value")
        if reply.get("tuple") and isinstance(value, list):
            return tuple(value)
        return value

    def call(self, obj: str, name: str, *args: Any) -> Any:
        return self.request("call", obj=obj, name=name, args=[_wire_arg(obj, name, a) for a in args])

    def reader(self) -> None:
        rfile = self.sock.makefile("rb")
        while True:
            line = rfile.readline(MAX_LINE)
            if not line:
                _real_exit(0)  # the application closed the link: it is gone or it retired this kernel
            try:
                msg = json.loads(line)
                self.dispatch(msg)
            except Exception:  # a bug here must not leave the script waiting forever
                traceback.print_exc(file=sys.__stderr__)

    def dispatch(self, msg: dict[str, Any]) -> None:
        op = msg.get("op")
        if op == "sample":
            self._on_sample(msg["s"], msg["v"])
        elif op == "schema":
            st = self._stream(msg["s"])
            st.cls = self._schema(msg["type"], tuple(msg["fields"]))
        elif op == "reply":
            slot = self._pending.get(msg.get("id"))
            if slot is not None:
                slot.reply = msg
                slot.event.set()
        elif op == "hello":
            self.hello = msg
            self.labels = dict(msg.get("labels", {}))
            self._new_namespace("<console>")
        elif op in ("run", "exit"):
            self.jobs.append(msg)
            self.jobs_wake.set()
        elif op == "exec":
            if not self.running:
                self.stop_event.clear()
            threading.Thread(target=self._exec_main, args=(msg,), name="script-console", daemon=True).start()
        elif op == "complete":
            threading.Thread(target=self._complete_main, args=(msg,), name="script-complete", daemon=True).start()
        elif op == "get":
            self.send({"op": "answer", "id": msg.get("id"), "value": plain(self.namespace.get(str(msg.get("name"))))})
        elif op == "stop":
            self.stop(str(msg.get("reason") or "stopped"))
        elif op == "pause":
            self.gate.clear()
        elif op == "resume":
            self.gate.set()
        elif op == "connected":
            st = self._stream(msg["s"])
            st.connected = bool(msg.get("connected"))

    # ------------------------------------------------------------------ stop and pause
    def stop(self, reason: str) -> None:
        if not self.stop_reason:
            self.stop_reason = reason
        self.stop_event.set()
        self.gate.set()
        self.callback_wake.set()
        with self.changed:
            self.changed.notify_all()
        if self._escalator is None or not self._escalator.is_alive():
            self._escalator = threading.Thread(target=self._escalate, name="script-stopper", daemon=True)
            self._escalator.start()

    def _escalate(self) -> None:
        _real_sleep(ASYNC_GRACE_S)
        while self.stop_event.is_set() and self.users.interrupt_all():
            _real_sleep(ASYNC_RESEND_S)

    def check(self) -> None:
        if self.stop_event.is_set():
            raise ScriptStopped(self.stop_reason or "stopped")

    def wait_gate(self) -> None:
        while not self.gate.is_set():
            self.check()
            self.gate.wait(WAIT_SLICE_S)
        self.check()

    def sleep(self, seconds: float) -> None:
        """``time.sleep`` for scripts: returns early (raising ScriptStopped) when the script is stopped."""
        _api.interruptible_sleep(seconds, self.stop_event, self.check)

    # ------------------------------------------------------------------ samples
    def _stream(self, name: str) -> _Stream:
        st = self.streams.get(name)
        if st is None:
            st = self.streams[name] = _Stream(name, self.labels.get(name, name))
        return st

    def _schema(self, type_name: str, fields: tuple[str, ...]) -> Any:
        key = (type_name, fields)
        cls = self._schemas.get(key)
        if cls is None:
            safe = type_name if type_name.isidentifier() and not keyword.iskeyword(type_name) else "Sample"
            cls = self._schemas[key] = collections.namedtuple(safe, fields, rename=True)  # type: ignore[misc]
        return cls

    def _on_sample(self, stream: str, values: list[Any]) -> None:
        st = self.streams.get(stream)
        if st is None or not st.subscribed or st.cls is None:
            return
        sample = st.cls(*values)
        with self.changed:
            st.sample = sample
            st.seq += 1
            self.generation += 1
            self.changed.notify_all()
        lists = self.callback_lists.get(stream)
        if lists and any(lists) and self.running and not self.stop_event.is_set():
            if len(self.callback_queue) >= CALLBACK_QUEUE_LIMIT:
                try:
                    self.callback_queue.popleft()
                    self.callbacks_dropped += 1
                except IndexError:
                    pass
            self.callback_queue.append((stream, sample))
            self.callback_wake.set()

    def subscribe(self, stream: str) -> _Stream:
        st = self._stream(stream)
        if st.subscribed:
            return st
        reply = self.request("subscribe", stream=stream)
        with self.changed:
            st.label = str(reply.get("label", st.label))
            st.connected = bool(reply.get("connected", True))
            snapshot = reply.get("sample")
            if not st.subscribed:
                st.subscribed = True
                if snapshot is not None and st.sample is None:
                    st.cls = self._schema(snapshot["type"], tuple(snapshot["fields"]))
                    st.sample = st.cls(*snapshot["v"])
                    st.seq += 1
        return st

    def latest(self, stream: str) -> Any:
        """The stream's latest sample. A thread that already read the latest sample waits (up to
        READ_WAIT_S) for the next one: a busy-wait on a device value then costs next to nothing."""
        if getattr(self._tls, "peeking", False):
            st = self.streams.get(stream)
            if st is not None and st.sample is not None:
                return st.sample
            snapshot = self.request("peek", stream=stream)
            if snapshot is None:
                return None
            return self._schema(snapshot["type"], tuple(snapshot["fields"]))(*snapshot["v"])
        self.wait_gate()
        st = self.subscribe(stream)
        seen: dict[str, int] = self._tls.__dict__.setdefault("seen", {})
        with self.changed:
            if st.sample is None:
                deadline = time.monotonic() + FIRST_SAMPLE_TIMEOUT_S
                while st.sample is None and not self.stop_event.is_set():
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        state = "connected" if st.connected else "not connected"
                        raise DeviceUnavailable(f"{st.label}: no data received yet (the device is {state})")
                    self.changed.wait(min(remaining, WAIT_SLICE_S))
            elif seen.get(stream) == st.seq:
                self.changed.wait_for(lambda: st.seq != seen.get(stream) or self.stop_event.is_set(), READ_WAIT_S)
            sample, seq = st.sample, st.seq
        self.check()
        seen[stream] = seq
        return sample

    def wait_until(self, predicate: Callable[[], Any], timeout: float | None) -> bool:
        """Evaluate ``predicate`` now and again on every new sample (at least every 20 ms) until it is true
        (True) or ``timeout`` s pass (False)."""
        deadline = None if timeout is None else time.monotonic() + float(timeout)
        while True:
            self.check()
            generation = self.generation
            if predicate():
                return True
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return False
            slice_s = WAIT_SLICE_S if deadline is None else min(WAIT_SLICE_S, max(0.0, deadline - now))
            with self.changed:
                if self.generation == generation and not self.stop_event.is_set():
                    self.changed.wait(slice_s)

    def register_callbacks(self, stream: str, target: list[Callable[[Any], Any]]) -> None:
        lists = self.callback_lists.setdefault(stream, [])
        if not any(t is target for t in lists):
            lists.append(target)
        self.subscribe(stream)

    # ------------------------------------------------------------------ namespace
    def _new_namespace(self, filename: str) -> None:
        self.filename = filename
        self.callback_lists.clear()
        api = build_api(self)
        script_builtins = dict(builtins.__dict__)
        script_builtins.update(input=_no_input, print=self._print)
        namespace: dict[str, Any] = {"__name__": "__main__", "__file__": filename, "__builtins__": script_builtins}
        namespace.update(api)
        namespace["waitCondition"] = make_wait_condition(self, namespace)
        namespace["wait"] = self.sleep
        namespace["time"] = time
        self.namespace = namespace

    def run_program(self, path: str) -> None:
        source = Path(path).read_text(encoding="utf-8")
        _remember_source(path, source)
        namespace = dict(self.namespace)
        namespace["__file__"] = path
        exec(compile(source, path, "exec"), namespace)

    def resolve_path(self, file_name: str) -> Path:
        return _api.resolve_path(file_name, self.base_dir)

    # ------------------------------------------------------------------ the script (main thread)
    def main(self) -> None:
        while True:
            self.jobs_wake.wait()
            self.jobs_wake.clear()
            while self.jobs:
                job = self.jobs.popleft()
                if job.get("op") == "exit":
                    return
                self.run_script(job)

    def run_script(self, job: dict[str, Any]) -> None:
        filename = str(job.get("filename") or "<script>")
        source = str(job.get("source") or "")
        self.stop_event.clear()
        self.stop_reason = ""
        self.callbacks_dropped = 0
        self.callback_errors.clear()
        self.callback_queue.clear()
        self.base_dir = Path(filename).resolve().parent if not filename.startswith("<") else None
        self._new_namespace(filename)
        self.namespace["exerciseParams"] = dict(job.get("params") or {})
        self.running = True
        callbacks = threading.Thread(target=self._callback_main, name="script-callbacks", daemon=True)
        callbacks.start()
        status, message, line, text = "finished", "", None, ""
        fatal = False
        try:
            self.users.enter()
            try:
                code = compile(source, filename, "exec")
                _remember_source(filename, source)
                exec(code, self.namespace)
            finally:
                self.users.leave()
        except ScriptStopped as exc:
            status, message = "stopped", self.stop_reason or str(exc) or "stopped"
        except SystemExit as exc:
            if exc.code not in (None, 0):
                status, message = "error", f"exit({exc.code!r})"
        except BaseException as exc:
            status = "refused" if _api.refused(exc) else "error"
            message, line, text = _describe(exc)
            fatal = isinstance(exc, MemoryError)
        self.stop_event.set()  # callbacks and prompt statements end with the script
        self.callback_wake.set()
        callbacks.join(0.2)
        if callbacks.is_alive():  # a callback in a pure-Python loop
            self.users.interrupt_all()
            callbacks.join(1.0)
        for st in self.streams.values():
            st.subscribed = False
        self.running = False
        self.send({"op": "done", "status": status, "message": message, "line": line, "traceback": text,
                   "callbacks_dropped": self.callbacks_dropped,
                   "callback_errors": [[k[0], k[1], k[2], n] for k, n in self.callback_errors.items()]})
        if fatal:
            _real_exit(4)  # out of memory: give the memory back; the application starts a fresh kernel
        self.stop_event.clear()

    def _callback_main(self) -> None:
        while not self.stop_event.is_set():
            try:
                stream, sample = self.callback_queue.popleft()
            except IndexError:
                self.callback_wake.wait(WAIT_SLICE_S)
                self.callback_wake.clear()
                continue
            self.gate.wait()
            for funs in list(self.callback_lists.get(stream, ())):
                for fn in list(funs):
                    if self.stop_event.is_set():
                        return
                    try:
                        self.users.enter()
                        try:
                            fn(sample)
                        finally:
                            self.users.leave()
                    except ScriptStopped:
                        return
                    except SystemExit:
                        self.stop("a callback called exit()")
                        return
                    except BaseException as exc:
                        self._callback_error(fn, exc)

    def _callback_error(self, fn: Callable[..., Any], exc: BaseException) -> None:
        _message, line, text = _describe(exc)
        key = (str(getattr(fn, "__name__", "?")), line or 0, type(exc).__name__)
        count = self.callback_errors.get(key, 0) + 1
        self.callback_errors[key] = count
        if count == 1:  # a callback at 100 Hz would flood the console: report each error once
            self.output("stderr", f"Error in callback {key[0]} (reported once; the callbacks keep running):\n{text}")

    # ------------------------------------------------------------------ the prompt
    def _exec_main(self, msg: dict[str, Any]) -> None:
        try:
            self.users.enter()
            try:
                self._exec_interactive(str(msg.get("source", "")))
            finally:
                self.users.leave()
        except ScriptStopped:
            self.output("info", "(interrupted)\n")
        except SystemExit:
            self.output("info", "exit() ignored at the prompt\n")
        except BaseException as exc:
            self.output("stderr", _describe(exc)[2])
        self.send({"op": "exec_done", "id": msg.get("id")})

    def _exec_interactive(self, source: str) -> None:
        _remember_source("<console>", source)
        tree = ast.parse(source, "<console>", "exec")
        last = tree.body[-1] if tree.body and isinstance(tree.body[-1], ast.Expr) else None
        if last is not None:
            tree.body.pop()
        if tree.body:
            exec(compile(tree, "<console>", "exec"), self.namespace)
        if last is not None:
            value = eval(compile(ast.Expression(last.value), "<console>", "eval"), self.namespace)
            if value is not None:
                self.namespace["_"] = value
                self.output("stdout", repr(value) + "\n")

    def _complete_main(self, msg: dict[str, Any]) -> None:
        self._tls.peeking = True
        try:
            value = self.completions(str(msg.get("text", "")))
        except BaseException:
            value = []
        self.send({"op": "answer", "id": msg.get("id"), "value": value})

    def completions(self, text: str) -> list[str]:
        """Names completing ``text`` in the live namespace; device values are peeked, never waited for."""
        if not re.fullmatch(r"[A-Za-z_][\w]*(\.[A-Za-z_]?[\w]*)*", text or ""):
            return []
        names_ns = self.namespace
        bi = names_ns.get("__builtins__", {})
        if "." not in text:
            names = set(names_ns) | set(bi) | set(keyword.kwlist)
            return sorted(n for n in names if n.startswith(text) and (text.startswith("_") or not n.startswith("_")))
        expr, prefix = text.rsplit(".", 1)
        head, *rest = expr.split(".")
        if head in names_ns:
            obj = names_ns[head]
        elif head in bi:
            obj = bi[head]
        else:
            return []
        for name in rest:
            try:
                obj = getattr(obj, name)
            except BaseException:
                return []
            if obj is None:
                return []
        names = set(dir(obj))
        if isinstance(obj, type) and issubclass(obj, enum.Enum):
            names |= set(obj.__members__)
        return sorted(f"{expr}.{n}" for n in names
                      if n.startswith(prefix) and (prefix.startswith("_") or not n.startswith("_")))


def _no_input(*_args: Any) -> str:
    raise RuntimeError("input() is not available in exercise scripts: nobody types at the patient's side")


def _wire_arg(obj: str, name: str, value: Any) -> Any:
    if value is None or isinstance(value, bool | int | float | str):
        return int(value) if isinstance(value, enum.IntEnum) else value
    item = getattr(value, "item", None)  # a numpy scalar
    if callable(item):
        value = item()
        if isinstance(value, bool | int | float):
            return value
    if isinstance(value, FesProfileRef):
        return {"profile": value.token}
    raise TypeError(f"{obj}.{name}: arguments are numbers, True/False or text, got {value!r}")


def _describe(exc: BaseException) -> tuple[str, int | None, str]:
    """(message, the user's line, a traceback without the kernel's own frames)."""
    frames = traceback.extract_tb(exc.__traceback__)
    user = [f for f in frames if f.filename not in _OWN_FILES]
    line = user[-1].lineno if user else None
    if isinstance(exc, SyntaxError) and exc.filename and exc.filename not in _OWN_FILES:
        line = exc.lineno
    lines = ["Traceback (most recent call last):\n", *traceback.format_list(user or frames)]
    lines += traceback.format_exception_only(type(exc), exc)
    return f"{type(exc).__name__}: {exc}", line, "".join(lines)


def _remember_source(filename: str, source: str) -> None:
    linecache.cache[filename] = (len(source), None, source.splitlines(keepends=True), filename)


# ---------------------------------------------------------------------------------------------- the API
class FesProfileRef:
    """A stimulation profile held by the application (``fes.loadFile`` / ``fes.profile``)."""

    def __init__(self, data: Mapping[str, Any]) -> None:
        self.token = int(data.get("token", 0))
        self.name = data.get("name")
        self.axis = data.get("axis")
        self.channels = tuple(data.get("channels") or ())

    def __repr__(self) -> str:
        return f"<FES profile {self.name!r} (axis {self.axis}, channels {', '.join(map(str, self.channels))})>"


def _profile(value: Any) -> Any:
    return FesProfileRef(value) if isinstance(value, dict) and "token" in value else value


class _ApiObject:
    """Base of the proxies: their shape (app/scripting/api_spec.py) gives them their state properties, callback
    setters and docstrings; every call goes to the application."""

    _shape: Any = None

    def __init__(self, kernel: Kernel) -> None:
        self._k = kernel
        _api.init_callback_lists(self, self._shape)


def _make_call(obj: str, method: str, wrap: Callable[[Any], Any] | None = None) -> Callable[..., Any]:
    def call(self: _ApiObject, *args: Any) -> Any:
        value = self._k.call(obj, method, *args)
        return wrap(value) if wrap is not None else value

    call.__name__ = call.__qualname__ = method
    return call


def _make_command(spec: Mapping[str, Any]) -> Callable[..., Any]:
    """A robot command from the wire's table (hello ``commands``), with its arguments' names."""
    name = str(spec["name"])
    command = _make_call("linarm", name)
    command.__doc__ = str(spec.get("doc", ""))
    params = [inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY)]
    params += [inspect.Parameter(str(a), inspect.Parameter.POSITIONAL_ONLY) for a in spec.get("args", [])]
    command.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
    return command


def _write_file(self: _ApiObject, data: Any, fileName: str) -> None:
    if not isinstance(data, FesProfileRef):
        raise TypeError(f"fes.writeFile expects a profile (e.g. fes.profile), got {type(data).__name__}")
    self._k.call("fes", "writeFile", data, str(fileName))


class _ManagerPort:
    """``linarmppManager``'s side in the kernel (api_spec.ManagerPort): programs run here, the rest is a call."""

    def __init__(self, kernel: Kernel) -> None:
        self._k = kernel

    def resolve_path(self, file_name: str) -> Path:
        return self._k.resolve_path(file_name)

    def run_program(self, path: str) -> None:
        self._k.run_program(path)

    def emergency_stop(self, reason: str) -> None:
        self._k.request("call", obj="linarmppManager", name="emergencyStop", args=[reason])

    def start_repetition(self, index: int, total: int | None) -> None:
        self._k.call("linarmppManager", "startRepetition", index, total)

    def end_repetition(self, index: int | None, ok: bool) -> None:
        self._k.call("linarmppManager", "endRepetition", index, ok)

    def report_progress(self, text: str) -> None:
        self._k.call("linarmppManager", "reportProgress", text)

    def prompt(self, index: int | None, cue: str, threshold: float | None) -> None:
        self._k.call("linarmppManager", "prompt", index, cue, threshold)

    def set_run_state(self, state: str, detail: str) -> None:
        self._k.call("linarmppManager", "setRunState", state, detail)


def build_api(kernel: Kernel) -> dict[str, Any]:
    """The proxies of one namespace, made from the API's definition and the application's hello (the robot's
    command table, its enums, the streams' names)."""
    hello = kernel.hello
    stream_names: Mapping[str, str] = hello.get("streams", {})
    enums = {name: enum.IntEnum(name, dict(members)) for name, members in hello.get("enums", {}).items()}

    def make_property(shape: Any, prop: Any) -> property:
        stream = str(stream_names.get(prop.stream, prop.stream))

        def get(self: _ApiObject) -> Any:
            return self._k.latest(stream)

        return property(get)

    def make_setter(shape: Any, method: str, setter: Any) -> Callable[..., None]:
        stream, what = str(stream_names.get(setter.stream, setter.stream)), f"{shape.name}.{method}"

        def set_callback(self: _ApiObject, fun: Any) -> None:
            target = getattr(self, setter.list_name)
            _api.set_callbacks(target, fun, what)
            self._k.register_callbacks(stream, target)

        return set_callback

    def proxy(shape: Any, members: Mapping[str, Any]) -> type:
        attrs: dict[str, Any] = {"_shape": shape}
        attrs.update({m: _make_call(shape.name, m) for m in shape.methods})
        attrs.update(members)
        cls = type(shape.class_string, (_ApiObject,), attrs)
        return _api.apply_shape(cls, shape, make_property, make_setter)

    linarm_members: dict[str, Any] = dict(enums)
    for spec in hello.get("commands", []):
        linarm_members[str(spec["name"])] = _make_command(spec)
    for alias, target in _api.LINARM_ALIASES.items():
        if target in linarm_members:
            linarm_members[alias] = linarm_members[target]
    fes_members: dict[str, Any] = {
        "loadFile": _make_call("fes", "loadFile", _profile), "writeFile": _write_file,
        "profile": property(lambda self: _profile(self._k.call("fes", "profile"))),
        "stimulating": property(lambda self: self._k.call("fes", "stimulating")),
    }
    fes_members.update({alias: fes_members[target] for alias, target in _api.FES_ALIASES.items()})

    linarm = proxy(_api.LINARM, linarm_members)(kernel)
    physio = proxy(_api.PHYSIOLOGICAL_SENSORS, {})(kernel)
    fes = proxy(_api.FES, fes_members)(kernel)
    patient_model = proxy(_api.PATIENT_MODEL, {})(kernel)
    vr = proxy(_api.VR_UNITY, {})(kernel)
    mgr = _api.LinarmppManager(_ManagerPort(kernel), linarm, physio, fes, patient_model, vr)

    def emergencyStop(reason: str = _api.ESTOP_REASON) -> None:
        """FES Stop and robot IDLE at once, latched until an operator resets it; the script is stopped."""
        mgr.emergencyStop(reason)

    return {
        "linarm": linarm, "physiologicalSensors": physio, "fes": fes, "patientModel": patient_model,
        "VRUnity": vr, "linarmppManager": mgr, "manager": mgr, "emergencyStop": emergencyStop,
        **_api.SCRIPT_ERRORS,
    }


def make_wait_condition(kernel: Kernel, namespace: Mapping[str, Any]) -> Callable[..., bool]:
    """``waitCondition(condition, timeout=None)`` or the seed's ``waitCondition("expr", locals(), timeout)``:
    re-evaluated on every new device sample. True when met, False on timeout."""

    def waitCondition(condition: Any, *args: Any, timeout: float | None = None) -> bool:
        local_vars: Mapping[str, Any] | None = None
        rest = list(args)
        if rest and (isinstance(rest[0], Mapping) or rest[0] is None) and not isinstance(rest[0], int | float):
            local_vars = rest.pop(0)
        if rest:
            timeout = rest.pop(0)
        if rest:
            raise TypeError("waitCondition(condition, timeout) or waitCondition(condition, locals(), timeout)")
        if isinstance(condition, str):
            code = compile(condition, "<waitCondition>", "eval")
            globals_ = namespace if isinstance(namespace, dict) else dict(namespace)

            def predicate() -> Any:
                return eval(code, globals_, local_vars if local_vars is not None else globals_)
        elif callable(condition):
            predicate = condition
        else:
            raise TypeError(f"waitCondition needs a string expression or a function, got {condition!r}")
        return kernel.wait_until(predicate, None if timeout is None else float(timeout))

    return waitCondition


# ---------------------------------------------------------------------------------------------- entry
_APP_PACKAGES = ("app", "PySide6", "shiboken6", "serial")


class _NoApplicationModules:
    """``-I`` keeps the checkout off ``sys.path``, but an installed (or editable) application sits in
    site-packages beside the packages scripts may use (numpy, ...). A script that imports the application's
    modules would only get fresh, unconnected copies, never the application's live objects; refusing them
    makes that plain and keeps a script from opening a device behind the supervisor's back by accident. A
    barrier, not a sandbox (decisions.md, "Script kernel": a process is not a sandbox)."""

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name.split(".")[0] in _APP_PACKAGES:
            raise ImportError(f"{name} is not available to scripts: devices are reached through the script API "
                              "(linarm, physiologicalSensors, fes, patientModel, VRUnity, linarmppManager)")
        return None


def main(argv: list[str]) -> int:
    t0 = time.perf_counter()
    fd = int(argv[1])
    memory_limit = int(argv[2]) if len(argv) > 2 else 0
    if memory_limit > 0:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (memory_limit, memory_limit))
    sys.meta_path.insert(0, _NoApplicationModules())
    faulthandler.enable(file=sys.__stderr__, all_threads=False)  # a crash names the script's line
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    sock = socket.socket(fileno=fd)
    kernel = Kernel(sock)
    sys.stdout = _Output(kernel, "stdout")  # type: ignore[assignment]
    sys.stderr = _Output(kernel, "stderr")  # type: ignore[assignment]
    time.sleep = kernel.sleep  # every ``time.sleep`` of the script ends when it is stopped

    def _exit(code: int) -> None:
        """``os._exit`` from a script: say where first (the process ends without a traceback)."""
        frames = [f for f in traceback.extract_stack()[:-1] if f.filename not in _OWN_FILES]
        if frames:
            text = "Traceback (most recent call last):\n" + "".join(traceback.format_list(frames))
            kernel.send({"op": "exiting", "code": code, "line": frames[-1].lineno, "traceback": text
                         + f"os._exit({code!r})\n"})
        _real_exit(code)

    os._exit = _exit
    threading.Thread(target=kernel.reader, name="kernel-reader", daemon=True).start()
    kernel.send({"op": "ready", "pid": os.getpid(), "startup_s": time.perf_counter() - t0})
    kernel.main()
    return 0


if __name__ == "__main__":
    _real_exit(main(sys.argv))
