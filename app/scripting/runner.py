"""Runs an exercise script on its own thread, never the GUI thread, and stops it on request.

Stopping (qt-stack.md §6): the stop flag is set first; every API wait (``time.sleep``, ``wait``,
``waitCondition``, a command waiting for its ACK, a device-value read) checks it at least every 20 ms
and raises :class:`ScriptStopped`. A script that is in none of those — a pure-Python busy loop such as
the seed's ``while eval(cond) == False: pass`` — gets ScriptStopped delivered asynchronously
(``PyThreadState_SetAsyncExc``) after a short cooperative grace, re-sent while the script keeps running
(a bare ``except:`` cannot keep it alive). Asynchronous exceptions are only ever sent to a thread while
it runs user code, and a pending one is cleared when user code ends, so the runner's own clean-up is
never hit by one.

The script sees a ``time`` module whose ``sleep`` is interruptible (through its own ``__import__``, so
``import time`` inside callbacks defined by the script gets it too), ``print`` captured to the output,
``waitCondition`` / ``wait``, and the API objects of :mod:`app.scripting.api`.

Callbacks registered by the script run on one callback thread per run, in arrival order; an exception in
one is reported with its line and the others keep running. They stop with the script.

At the end of every run (finished, stopped, failed) the devices go to a safe state: FES stopped, robot
IDLE (or holding where it is, ``safety.robot_safe_state: hold``).
"""

from __future__ import annotations

import builtins
import collections
import contextlib
import ctypes
import enum
import linecache
import logging
import re
import sys
import threading
import time
import traceback
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.devices.linarm_protocol import ControlMode, ControlState, HomeState
from app.resources import RESOURCES
from app.scripting.api import (
    CommandRefused,
    ScriptContext,
    ScriptStopped,
    build_api,
    make_wait_condition,
)

log = logging.getLogger(__name__)

OutputSink = Callable[[str, str], None]  # (stream: "stdout" | "stderr" | "info", text)
COOPERATIVE_GRACE_S = 0.03  # API waits notice the stop flag within 20 ms; only then interrupt by force
ASYNC_RESEND_S = 0.05
CALLBACK_QUEUE_LIMIT = 1000  # samples waiting for the callback thread before the oldest are dropped
HOME_TIMEOUT_S = 60.0


_gil_lock = threading.Lock()
_gil_users = 0
_gil_previous = 0.005
SCRIPT_SWITCH_INTERVAL_S = 0.001


@contextlib.contextmanager
def _responsive_gil() -> Iterator[None]:
    """While a script runs, hand the GIL over every 1 ms instead of 5: a busy-waiting script (the seed's
    own ``waitCondition``) otherwise makes every GUI and driver slot wait up to 5 ms for the GIL, and with
    a few dozen Python slots a second the window stalls for seconds."""
    global _gil_users, _gil_previous
    with _gil_lock:
        if _gil_users == 0:
            _gil_previous = sys.getswitchinterval()
            sys.setswitchinterval(min(_gil_previous, SCRIPT_SWITCH_INTERVAL_S))
        _gil_users += 1
    try:
        yield
    finally:
        with _gil_lock:
            _gil_users -= 1
            if _gil_users == 0:
                sys.setswitchinterval(_gil_previous)


@dataclass
class ScriptResult:
    status: str  # "finished" | "stopped" | "error" | "refused" (a command refused by the safety supervisor)
    message: str = ""
    filename: str = ""
    line: int | None = None
    traceback: str = ""
    duration_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status in ("finished", "stopped")


# ---------------------------------------------------------------------------------------------- helpers
def _async_raise(thread_id: int, exc_type: type[BaseException] | None) -> None:
    """Deliver ``exc_type`` in ``thread_id`` at its next bytecode (None clears a pending one)."""
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id),
                                               ctypes.py_object(exc_type) if exc_type is not None else None)


class ScriptTime(types.ModuleType):
    """The ``time`` module as scripts see it: the same, but ``sleep`` ends when the script is stopped."""

    def __init__(self, context: ScriptContext) -> None:
        super().__init__("time", time.__doc__)
        for name in dir(time):
            if not name.startswith("__"):
                setattr(self, name, getattr(time, name))
        self.sleep = context.sleep


def _no_input(*_args: Any) -> str:
    raise RuntimeError("input() is not available in exercise scripts: nobody types at the patient's side")


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

    def busy(self) -> bool:
        with self._lock:
            return bool(self._in_user)


# ---------------------------------------------------------------------------------------------- runner
class ScriptRunner:
    """One script at a time (plus interactive statements in the same namespace), each on its own thread.

    ``output(stream, text)`` is called from script threads: it must be quick and thread-safe (the console
    appends to a deque it drains on a timer). ``on_finished(result)`` is called on the script thread after
    the safe state."""

    def __init__(self, manager: Any, output: OutputSink | None = None, *, safe_state: str | None = None,
                 home_first: bool = True, home_timeout_s: float = HOME_TIMEOUT_S,
                 on_finished: Callable[[ScriptResult], None] | None = None) -> None:
        self.manager = manager
        self.output: OutputSink = output or _stdout_sink
        config = getattr(manager, "config", None)
        self.safe_state = safe_state or (config.safety.robot_safe_state if config is not None else "idle")
        self.home_first = home_first
        self.home_timeout_s = home_timeout_s
        self.on_finished = on_finished
        self.context = ScriptContext(manager)
        self.context.run_program = self._run_program
        self.context.post_callback = self._post_callback
        self.namespace: dict[str, Any] = {}
        self.filename = "<script>"
        self.result: ScriptResult | None = None
        self.stop_reason = ""
        self.body_started_at: float | None = None  # monotonic time the script's own code began (after homing)
        self.callback_errors: dict[tuple[str, int, str], int] = {}
        self.callbacks_dropped = 0
        self._users = _UserThreads()
        self._thread: threading.Thread | None = None
        self._callback_thread: threading.Thread | None = None
        self._interactive: list[threading.Thread] = []
        self._callbacks: collections.deque[tuple[str, list[Callable[[Any], Any]], Any]] = collections.deque()
        self._callback_wake = threading.Event()
        self._done = threading.Event()
        self._done.set()
        self._run_lock = threading.Lock()
        self._stopper: threading.Thread | None = None
        self._new_namespace("<console>")

    # ------------------------------------------------------------------ public
    @property
    def running(self) -> bool:
        return not self._done.is_set()

    def start(self, source: str, filename: str = "<script>", params: dict[str, Any] | None = None) -> None:
        """Run ``source`` (the script's text) on a new thread; ``filename`` names it in tracebacks.
        ``params`` (plain data: an exercise form's values) is the script's global ``exerciseParams``."""
        with self._run_lock:
            if self.running:
                raise RuntimeError("a script is already running: stop it first")
            code = compile(source, filename, "exec")  # a SyntaxError reaches the caller before anything runs
            _remember_source(filename, source)
            self._done.clear()
            self.result = None
            self.body_started_at = None
            self.stop_reason = ""
            self.callback_errors.clear()
            self.callbacks_dropped = 0
            self._callbacks.clear()
            self.context.stop_event.clear()
            base = Path(filename).resolve().parent if not filename.startswith("<") else None
            self.context.base_dir = base
            self._new_namespace(filename)
            self.namespace["exerciseParams"] = dict(params or {})
            self._thread = threading.Thread(target=self._script_main, args=(code, filename, source),
                                            name="script", daemon=True)
            self._callback_thread = threading.Thread(target=self._callback_main, name="script-callbacks",
                                                     daemon=True)
            self._callback_thread.start()
            self._thread.start()

    def start_file(self, path: str | Path, params: dict[str, Any] | None = None) -> None:
        path = Path(path)
        self.start(path.read_text(encoding="utf-8"), str(path), params)

    def request_stop(self, reason: str = "stopped by the operator") -> None:
        """Ask every script thread (main, callbacks, interactive) to stop; returns at once."""
        if not self.stop_reason:
            self.stop_reason = reason
        self.context.stop_event.set()
        self._callback_wake.set()
        if self._stopper is None or not self._stopper.is_alive():
            self._stopper = threading.Thread(target=self._escalate, name="script-stopper", daemon=True)
            self._stopper.start()

    def stop(self, reason: str = "stopped by the operator", wait_s: float = 1.0) -> bool:
        """Stop and wait up to ``wait_s`` for user code to end (not for the safe state that follows)."""
        self.request_stop(reason)
        deadline = time.monotonic() + wait_s
        while self._users.busy() or self._callbacks_alive() or self._interactive_alive():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        return True

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the run (including its safe state) has ended; True when it has."""
        return self._done.wait(timeout)

    def execute(self, source: str, symbol: str = "single") -> threading.Thread | None:
        """Run one interactive statement in the script's namespace on its own thread (the prompt).
        Returns the thread, or None when ``source`` is incomplete (more lines needed). Raises SyntaxError."""
        import codeop

        if codeop.compile_command(source, "<console>", symbol) is None:
            return None
        if not self.running:
            self.context.stop_event.clear()  # the prompt works between runs, too
        thread = threading.Thread(target=self._interactive_main, args=(source,), name="script-console", daemon=True)
        self._interactive = [t for t in self._interactive if t.is_alive()] + [thread]
        thread.start()
        return thread

    def completions(self, text: str) -> list[str]:
        """Names completing ``text`` (``linarm.mo`` → ``linarm.moveCentreTo``, …) in the script's namespace.
        Walks attributes without calling anything: device values are peeked (latest sample or nothing)."""
        import keyword

        if not re.fullmatch(r"[A-Za-z_][\w]*(\.[A-Za-z_]?[\w]*)*", text or ""):
            return []
        if "." not in text:
            names = set(self.namespace) | set(self.namespace["__builtins__"]) | set(keyword.kwlist)
            return sorted(n for n in names if n.startswith(text) and (text.startswith("_") or not n.startswith("_")))
        expr, prefix = text.rsplit(".", 1)
        head, *rest = expr.split(".")
        if head in self.namespace:
            obj = self.namespace[head]
        elif head in self.namespace["__builtins__"]:
            obj = self.namespace["__builtins__"][head]
        else:
            return []
        for name in rest:
            try:
                obj = self.context.peek(obj, name)
            except BaseException:  # a device that is not there: nothing to offer
                return []
            if obj is None:
                return []
        names = set(dir(obj))
        if isinstance(obj, type) and issubclass(obj, enum.Enum):
            names |= set(obj.__members__)
        return sorted(f"{expr}.{n}" for n in names
                      if n.startswith(prefix) and (prefix.startswith("_") or not n.startswith("_")))

    # ------------------------------------------------------------------ namespace
    def _new_namespace(self, filename: str) -> None:
        self.filename = filename
        ctx = self.context
        script_time = ScriptTime(ctx)
        real_import = builtins.__import__

        def script_import(name: str, globals_: Any = None, locals_: Any = None, fromlist: Any = (),
                          level: int = 0) -> Any:
            if name == "time" and level == 0:
                return script_time
            return real_import(name, globals_, locals_, fromlist, level)

        def script_print(*args: Any, sep: str | None = " ", end: str | None = "\n", file: Any = None,
                         flush: bool = False) -> None:
            if file is not None and file not in (sys.stdout, sys.stderr):
                builtins.print(*args, sep=sep, end=end, file=file, flush=flush)
                return
            text = (" " if sep is None else sep).join(str(a) for a in args) + ("\n" if end is None else end)
            self.output("stderr" if file is sys.stderr else "stdout", text)

        script_builtins = dict(builtins.__dict__)
        script_builtins.update(__import__=script_import, print=script_print, input=_no_input)
        namespace: dict[str, Any] = {"__name__": "__main__", "__file__": filename, "__builtins__": script_builtins}
        namespace.update(build_api(ctx))
        namespace["waitCondition"] = make_wait_condition(ctx, namespace)
        namespace["wait"] = ctx.sleep
        namespace["time"] = script_time
        self.namespace = namespace

    def _run_program(self, path: str) -> None:
        """LinarmppManager.startProgram: run another script file here, in a namespace of its own."""
        source = Path(path).read_text(encoding="utf-8")
        _remember_source(path, source)
        namespace = dict(self.namespace)
        namespace["__file__"] = path
        exec(compile(source, path, "exec"), namespace)

    # ------------------------------------------------------------------ threads
    def _script_main(self, code: types.CodeType, filename: str, source: str) -> None:
        with _responsive_gil():
            self._script_body(code, filename, source)

    def _script_body(self, code: types.CodeType, filename: str, source: str) -> None:
        t0 = time.monotonic()
        sup = getattr(self.manager, "supervisor", None)
        name = Path(filename).name
        if sup is not None:
            sup.event("script_start", name=name, text=source)
        progress = getattr(self.manager, "progress", None)
        if progress is not None:
            progress.begin(name)
        result = ScriptResult("finished", filename=filename)
        self._users.enter()
        try:
            try:
                if self.home_first:
                    self._home_if_needed()
                self.body_started_at = time.monotonic()
                exec(code, self.namespace)
            finally:
                self._users.leave()
        except ScriptStopped:
            result = ScriptResult("stopped", self.stop_reason or "stopped", filename)
        except SystemExit as exc:
            if exc.code not in (None, 0):
                result = ScriptResult("error", f"exit({exc.code!r})", filename)
        except BaseException as exc:
            result = self._describe(exc, filename, "refused" if _refused(exc) else "error")
        result.duration_s = time.monotonic() - t0
        self.context.stop_event.set()  # callbacks and prompt statements end with the script
        self._callback_wake.set()
        self._join_helpers()
        self.context.close()
        self._report(result)
        self._bring_to_safe_state(result)
        if sup is not None:
            sup.event("script_stop", name=name, reason=result.message or result.status, status=result.status)
        if progress is not None:
            progress.finish(result.status)
        self.result = result
        self._done.set()
        if self.on_finished is not None:
            try:
                self.on_finished(result)
            except Exception:
                log.exception("on_finished failed")

    def _callback_main(self) -> None:
        ctx = self.context
        while not ctx.stop_event.is_set():
            try:
                _stream, funs, sample = self._callbacks.popleft()
            except IndexError:
                self._callback_wake.wait(0.02)
                self._callback_wake.clear()
                continue
            for fn in list(funs):
                if ctx.stop_event.is_set():
                    return
                self._users.enter()
                try:
                    try:
                        fn(sample)
                    finally:
                        self._users.leave()
                except ScriptStopped:
                    return
                except SystemExit:
                    self.request_stop("a callback called exit()")
                    return
                except BaseException as exc:
                    self._report_callback_error(fn, exc, "refused" if _refused(exc) else "error")

    def _interactive_main(self, source: str) -> None:
        self._users.enter()
        try:
            try:
                self._exec_interactive(source)
            finally:
                self._users.leave()
        except ScriptStopped:
            self.output("info", "(interrupted)\n")
        except SystemExit:
            self.output("info", "exit() ignored at the prompt\n")
        except BaseException as exc:
            result = self._describe(exc, "<console>", "error")
            self.output("stderr", result.traceback)

    def _exec_interactive(self, source: str) -> None:
        """Run a prompt entry; a final expression's value is shown (as the Python prompt does) and kept in ``_``."""
        import ast

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

    def _post_callback(self, stream: str, funs: list[Callable[[Any], Any]], sample: Any) -> None:
        # driver thread: append (atomic) and wake; never user code here
        if len(self._callbacks) >= CALLBACK_QUEUE_LIMIT:
            try:
                self._callbacks.popleft()
                self.callbacks_dropped += 1
            except IndexError:
                pass
        self._callbacks.append((stream, funs, sample))
        self._callback_wake.set()

    def _escalate(self) -> None:
        """After the cooperative grace, interrupt whatever still runs user code, until it ends."""
        time.sleep(COOPERATIVE_GRACE_S)
        while self._users.interrupt_all():
            time.sleep(ASYNC_RESEND_S)

    def _join_helpers(self) -> None:
        deadline = time.monotonic() + 1.0
        for thread in [self._callback_thread, *self._interactive]:
            if thread is not None and thread is not threading.current_thread():
                thread.join(max(0.0, deadline - time.monotonic()))
                if thread.is_alive():
                    self._users.interrupt_all()
                    thread.join(0.2)

    def _callbacks_alive(self) -> bool:
        return self._callback_thread is not None and self._callback_thread.is_alive() and self._users.busy()

    def _interactive_alive(self) -> bool:
        return any(t.is_alive() for t in self._interactive)

    # ------------------------------------------------------------------ homing and safe state
    def _home_if_needed(self) -> None:
        """The seed's scripts assume a homed robot: home it first when the controller says it is not."""
        linarm = self.manager.driver("linarm") if self.manager is not None else None
        if linarm is None or not linarm.connected:
            return
        ctx = self.context
        reply = ctx.call("linarm.getIsInitialized()", linarm.command, "getIsInitialized", source="script runner",
                         timeout_s=3.0)
        if reply.get("initialized"):
            return
        self.output("info", "The LINarm is not homed: homing it before the script starts…\n")
        log.info("script runner: homing the LINarm before %s", self.filename)
        ctx.call("linarm.setCtrlState(HOME)", linarm.command, "setCtrlState", int(ControlState.HOME_CTRL_STATE),
                 source="script runner", timeout_s=3.0)

        def homed() -> bool:
            state = linarm.latest("linarm.state")
            return state is not None and bool(state.initialized) and state.homeState == HomeState.HOME_DONE

        if not ctx.wait_until(homed, self.home_timeout_s):
            raise RuntimeError(f"the LINarm did not finish homing within {self.home_timeout_s:.0f} s")
        self.output("info", "LINarm homed.\n")

    def _bring_to_safe_state(self, result: ScriptResult) -> None:
        """FES stopped; robot IDLE (or holding). Direct driver calls: the script's context is closed."""
        reason = f"script {result.status}"
        done: list[str] = []
        fes = self.manager.driver("fes") if self.manager is not None else None
        if fes is not None:
            try:
                stop = getattr(fes, "stop_stimulation", None)
                if stop is not None:
                    stop(reason, "script runner")
                else:
                    fes.stop(reason, "script runner")  # the contract's stop(reason: str, source)
                done.append("FES stopped")
            except Exception as exc:
                log.warning("script end: FES stop failed: %s", exc)
                self.output("stderr", f"Could not stop the FES: {exc}\n")
        linarm = self.manager.driver("linarm") if self.manager is not None else None
        if linarm is not None and linarm.connected:
            state = linarm.latest("linarm.state")
            active = state is None or state.controlState != ControlState.IDLE_CTRL_STATE
            try:
                if self.safe_state == "hold" and state is not None and state.controlState == ControlState.ON_CTRL_STATE:
                    # a mode change clears any motion: the centre holds where it is
                    linarm.command("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS), source="script runner")
                    done.append("robot holding")
                elif active:
                    linarm.command("setCtrlState", int(ControlState.IDLE_CTRL_STATE), source="script runner")
                    done.append("robot IDLE")
            except Exception as exc:
                log.warning("script end: robot safe state by command failed (%s); motors off directly", exc)
                try:
                    linarm.emergency_idle(reason)
                    done.append("robot IDLE")
                except Exception as exc2:
                    self.output("stderr", f"Could not bring the robot to IDLE: {exc2}\n")
        sup = getattr(self.manager, "supervisor", None)
        if sup is not None:
            sup.event("script_safe_state", reason=reason, actions=done)
        if done:
            self.output("info", f"Safe state: {', '.join(done)}.\n")

    # ------------------------------------------------------------------ reporting
    def _report(self, result: ScriptResult) -> None:
        if result.status == "finished":
            self.output("info", f"Script finished ({result.duration_s:.1f} s).\n")
        elif result.status == "stopped":
            self.output("info", f"Script stopped: {result.message} ({result.duration_s:.1f} s).\n")
        else:
            self.output("stderr", result.traceback)
            where = f" at line {result.line}" if result.line else ""
            self.output("info", f"Script ended by an error{where}: {result.message}\n")
        if self.callbacks_dropped:
            self.output("info", f"{self.callbacks_dropped} samples were skipped because the callbacks were "
                                "slower than the data.\n")

    def _report_callback_error(self, fn: Callable[..., Any], exc: BaseException, status: str) -> None:
        described = self._describe(exc, self.filename, status)
        key = (getattr(fn, "__name__", "?"), described.line or 0, type(exc).__name__)
        count = self.callback_errors.get(key, 0) + 1
        self.callback_errors[key] = count
        if count == 1:  # a callback at 100 Hz would flood the console: report each error once
            self.output("stderr", f"Error in callback {key[0]} (reported once; the callbacks keep running):\n"
                                  + described.traceback)

    def _describe(self, exc: BaseException, filename: str, status: str) -> ScriptResult:
        frames = traceback.extract_tb(exc.__traceback__)
        user = [f for f in frames if not _is_app_file(f.filename)]
        line = user[-1].lineno if user else None
        if isinstance(exc, SyntaxError) and exc.filename and not _is_app_file(exc.filename):
            line = exc.lineno
        lines = ["Traceback (most recent call last):\n", *traceback.format_list(user or frames)]
        lines += traceback.format_exception_only(type(exc), exc)
        message = f"{type(exc).__name__}: {exc}"
        return ScriptResult(status, message, filename, line, "".join(lines))


def _refused(exc: BaseException) -> bool:
    from app.safety import SafetyError

    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, CommandRefused | SafetyError):
            return True
        seen = seen.__cause__
    return False


_APP_DIR = str(Path(__file__).resolve().parent.parent)


def _is_app_file(filename: str) -> bool:
    """Frames of the application itself are hidden from script tracebacks (not the user's code)."""
    if filename.startswith(str(RESOURCES)):  # installed, the example scripts lie inside app/ (app/_resources)
        return False
    return filename.startswith(_APP_DIR) or filename.startswith("<frozen") or "concurrent/futures" in filename


def _remember_source(filename: str, source: str) -> None:
    """Tracebacks show the lines of the text that ran, even an unsaved editor buffer."""
    lines = source.splitlines(keepends=True)
    linecache.cache[filename] = (len(source), None, lines, filename)


def _stdout_sink(stream: str, text: str) -> None:
    target = sys.stderr if stream == "stderr" else sys.stdout
    target.write(text)
    target.flush()
