"""Runs an exercise script in the script kernel — a child Python process (app/scripting/kernel.py) — and
stops it on request, whatever it does.

The runner starts a kernel with itself (the console's prompt and the first script use it) and, from the
first Start on, keeps a spare started ahead, so Start only hands the script to a warm process. A script
runs in a fresh kernel (its own namespace); the prompt then works in that namespace until the next Start.
The kernel's process and link are :class:`app.scripting.kernel_process.KernelProcess`'s; the kernel reaches the
devices only through :class:`app.scripting.bridge.ApiBridge`: the API's calls, answered on bridge threads by the
in-app API objects (the safety supervisor on every command), and the samples of the streams it uses. The runner
is handed what it uses of the application, typed (app.therapy.services.ScriptHost: the supervisor, the run log, the
progress marks, the drivers…), and uses exactly that.

Stop (:meth:`request_stop`): calls from the kernel are refused from then on, FES and robot go to the safe
state at once (on a thread of their own), the kernel is asked to stop (every wait there notices within
20 ms; a busy loop gets ScriptStopped asynchronously), and a kernel that has not ended its script within
50 ms is terminated, then killed 40 ms later. A kernel that ends by itself while a script runs (a
segfault, ``os._exit``, out of memory) ends the run as an error, "the script's process ended: <cause>".
Either way the devices go to the safe state, the run is recorded, and a fresh kernel serves the next
Start. The application's own interpreter is untouched: no switch-interval change, no asynchronous
exceptions in its threads.

At the end of every run (finished, stopped, failed) the devices go to a safe state: FES stopped, robot
IDLE (or holding where it is, ``safety.robot_safe_state: hold``).
"""

from __future__ import annotations

import json
import linecache
import logging
import re
import sys
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.core import journal, streams
from app.core.ownership import Composition, start_problem
from app.core.resources import RESOURCES
from app.core.runs import ExerciseRun, Program, RunLog, RunParameter, RunSource, text_hash
from app.safety.supervisor import SafetyError, SafetySupervisor
from app.scripting.api import CommandRefused, ScriptContext, ScriptStopped
from app.scripting.bridge import ApiBridge, Gate, hello_message
from app.scripting.kernel_process import KernelProcess
from app.wire.linarm_constants import PRETENSION_MOVE, K
from app.wire.linarm_protocol import ControlMode, ControlState, HomeState

if TYPE_CHECKING:
    from app.therapy.services import ScriptHost

log = logging.getLogger(__name__)

OutputSink = Callable[[str, str], None]  # (stream: "stdout" | "stderr" | "info", text)
HOME_TIMEOUT_S = 60.0
POLITE_STOP_S = 0.05  # the kernel's own stop (every wait notices within 20 ms) before SIGTERM
TERMINATE_S = 0.04  # SIGTERM before SIGKILL
ANSWER_TIMEOUT_S = 0.5  # completion and namespace reads from the GUI thread
DEFAULT_DELTA_TOLERANCE_M = 0.001  # pretension this close to the homed one: the default stiffness already
# Script output passed on to the console, in characters: OUTPUT_RATE a second once OUTPUT_BURST is spent.
# The console appends on the GUI thread; a script printing megabytes in a loop would otherwise keep it busy
# (and its queue growing) for as long as it runs. What is over is dropped and counted, never queued.
OUTPUT_RATE = 512 * 1024
OUTPUT_BURST = 4 * 1024 * 1024


class _OutputBudget:
    def __init__(self, rate: float = OUTPUT_RATE, burst: float = OUTPUT_BURST) -> None:
        self.rate = rate
        self.burst = burst
        self.tokens = burst
        self.t = time.monotonic()
        self.dropped = 0
        self._lock = threading.Lock()

    def take(self, n: int) -> bool:
        """True if ``n`` characters may go on; otherwise they are counted as dropped."""
        with self._lock:
            now = time.monotonic()
            self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
            self.t = now
            if self.tokens >= n:
                self.tokens -= n
                return True
            self.dropped += n
            return False


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


class PromptRun:
    """One prompt entry running in the kernel (what :meth:`ScriptRunner.execute` returns)."""

    def __init__(self, kernel: KernelProcess | None = None) -> None:
        self.kernel = kernel  # the kernel it runs in: its end (not another's) ends the entry
        self._done = threading.Event()

    def join(self, timeout: float | None = None) -> None:
        self._done.wait(timeout)

    def is_alive(self) -> bool:
        return not self._done.is_set()


class _Answer:
    """A read of one kernel's namespace: released by that kernel's answer, or by that kernel's end."""

    def __init__(self, kernel: KernelProcess) -> None:
        self.kernel = kernel
        self.event = threading.Event()
        self.value: Any = None


# ---------------------------------------------------------------------------------------------- runner
class ScriptRunner:
    """One script at a time (plus interactive statements in the same namespace), in a kernel process.

    ``output(stream, text)`` is called from bridge threads: it must be quick and thread-safe (the console
    appends to a deque it drains on a timer). ``on_finished(result)`` is called on the run's control thread
    after the safe state."""

    def __init__(self, manager: ScriptHost, output: OutputSink | None = None, *, safe_state: str | None = None,
                 home_first: bool = True, home_timeout_s: float = HOME_TIMEOUT_S,
                 on_finished: Callable[[ScriptResult], None] | None = None) -> None:
        self.manager = manager
        self.output: OutputSink = output or _stdout_sink
        self.safe_state = safe_state or manager.config.safety.robot_safe_state
        self.home_first = home_first
        self.home_timeout_s = home_timeout_s
        self.on_finished = on_finished
        self.context = ScriptContext(manager, source="script runner")  # homing; its stop_event follows Stop
        self.filename = "<script>"
        self.result: ScriptResult | None = None
        self.stop_reason = ""
        self.body_started_at: float | None = None  # monotonic time the script's own code began (after homing)
        self.callback_errors: dict[tuple[str, int, str], int] = {}
        self.callbacks_dropped = 0
        self._output_budget = _OutputBudget()
        self.kernel_start_s: float | None = None  # Start → the kernel has the script (the last run)
        self.run: ExerciseRun | None = None  # the run of the last Start, as it was opened
        self.stop_cause = ""  # why the run stopped (app.core.runs.END_REASONS): emergency_stop, safety_stop, …
        self._console_run: ExerciseRun | None = None  # the console entry's run while one runs (no script running)
        self._run_log: RunLog | None = None  # the run log the last run was opened in
        self.gate = Gate()
        manager.add_shutdown_hook(self.close)  # no kernel outlives the devices it was driving
        self.paused = False
        self._state_before_pause: tuple[str, str] = ("running", "")  # the run's state a resume goes back to
        self._console_rid: int | None = None  # the prompt entry the console run was opened for
        self._done = threading.Event()
        self._done.set()
        self._user_ended = threading.Event()
        self._user_ended.set()
        self._wake = threading.Event()
        self._stop_requested = threading.Event()
        self._run_lock = threading.Lock()
        self._kernel_lock = threading.Lock()
        self._kernel: KernelProcess | None = None
        self._spare: KernelProcess | None = None
        self._bridge: ApiBridge | None = None
        self._done_msg: dict[str, Any] | None = None
        self._prompts: dict[int, PromptRun] = {}
        self._answers: dict[int, _Answer] = {}
        self._ids = iter(range(1, 1 << 62))
        self._safe_thread: threading.Thread | None = None
        self._safe_lock = threading.Lock()
        self._exit_report: dict[str, Any] | None = None
        self._closed = False
        self._kernels: list[KernelProcess] = []
        self._finalizer = weakref.finalize(self, _kill_all, self._kernels)
        self._register_stop_action()
        try:
            self._next_kernel()  # started with the runner: the prompt and the first Start find it warm
        except OSError as exc:  # the window still opens; Start then says why scripts cannot run
            log.error("the script kernel could not be started: %s", exc)

    # ------------------------------------------------------------------ kernels
    def _spawn(self) -> KernelProcess:
        kernel = KernelProcess(hello_message())
        self._kernels[:] = [k for k in self._kernels if not k.ended.is_set()] + [kernel]
        return kernel

    def _replace_ended(self, ended: KernelProcess) -> None:
        """A fresh kernel for the prompt and the next Start, if ``ended`` is still the current one. Both the
        run's control thread and the kernel's exit report come here: whichever is second must not retire
        the fresh kernel the first installed (a Start may already be running in it)."""
        self._next_kernel(replacing=ended)

    def _next_kernel(self, replacing: KernelProcess | None = None) -> KernelProcess:
        """Make the spare the current kernel (retiring the old one) and start a new spare."""
        with self._kernel_lock:
            if replacing is not None and self._kernel is not replacing and self._kernel is not None:
                return self._kernel
            old = self._kernel
            kernel = self._spare if self._spare is not None and self._spare.alive else self._spawn()
            self._spare = None
            self._kernel = kernel
            bridge = ApiBridge(self.manager, kernel, self.gate)
            old_bridge, self._bridge = self._bridge, bridge
            kernel.on_link_closed = self._on_link_closed

            def handler(msg: dict[str, Any]) -> Callable[[], None] | None:  # this kernel's, through its bridge
                return self._on_message(kernel, bridge, msg)

            kernel.bind(handler, self._raw_output, self._on_kernel_exit)
        if old_bridge is not None:
            old_bridge.close()
        if old is not None and old is not kernel:
            old.retire()
        return kernel

    def _ensure_spare(self) -> None:
        """A spare kernel starting in the background (the next Start finds it warm)."""
        if not self._closed:
            threading.Thread(target=self._start_spare, name="script-kernel-spare", daemon=True).start()

    def _start_spare(self) -> None:
        with self._kernel_lock:
            if self._closed or (self._spare is not None and self._spare.alive):
                return
        spare = self._spawn()
        with self._kernel_lock:
            if self._closed or (self._spare is not None and self._spare.alive):
                spare.retire()
                return
            self._spare = spare

    def _prompt_kernel(self) -> KernelProcess | None:
        kernel = self._kernel
        if kernel is None or kernel.ended.is_set():
            try:
                kernel = self._next_kernel()
            except OSError as exc:
                log.error("the script kernel could not be started: %s", exc)
                return None
        return kernel

    def close(self) -> None:
        """Stop what runs and end the kernels (the window closes)."""
        if self.running:
            self.stop("the application is closing", wait_s=0.5, cause="app_exit")
            self.wait(2.0)
        self._end_console_run(None, "app_exit")
        self._closed = True
        with self._kernel_lock:
            kernels = [k for k in (self._kernel, self._spare) if k is not None]
            self._kernel = self._spare = None
            bridge, self._bridge = self._bridge, None
        if bridge is not None:
            bridge.close()
        for kernel in kernels:
            kernel.retire()
        self.context.close()

    def ready(self, timeout: float | None = None) -> bool:
        """True once the current kernel has started (it is started with the runner; Start then only hands
        it the script)."""
        kernel = self._kernel
        return kernel is not None and kernel.ready.wait(timeout)

    def spare_ready(self, timeout: float = 5.0) -> bool:
        """True once the spare kernel (started at a Start, for the next one) has started."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            spare = self._spare
            if spare is not None and spare.ready.wait(max(0.0, deadline - time.monotonic())):
                return True
            time.sleep(0.01)
        return False

    @property
    def kernel_pid(self) -> int | None:
        return self._kernel.pid if self._kernel is not None else None

    # ------------------------------------------------------------------ public
    @property
    def running(self) -> bool:
        return not self._done.is_set()

    def start(self, source: str, filename: str = "<script>", params: dict[str, Any] | None = None, *,
              program: Any = None, parameters: Any = (), run_source: RunSource = "script_tab",
              restart_of: str | None = None, continues: str | None = None,
              holds: tuple[str, ...] = ("robot", "stimulator"), compose: tuple[Composition, ...] = ()) -> Any:
        """Run ``source`` (the script's text) in a fresh kernel; ``filename`` names it in tracebacks.
        ``params`` (plain data: an exercise form's values) is the script's global ``exerciseParams``.

        Opens the run (app/core/runs.py) in the manager's run log: ``program`` (a Program; by default the script file
        with its exact text), ``parameters`` (RunParameters), ``run_source`` (who started it) and ``restart_of``
        (the run Recover restarts; ``continues``: the interrupted run a continuation carries on). The run holds
        ``holds`` (the robot, the stimulator: one owner during a run, app/core/ownership.py) and lets ``compose``
        (app.core.ownership.Composition) in. Returns the run (None without a run log); the run ends with the script.
        Raises RuntimeError, nothing started and no run recorded, while another holds the devices."""
        t0 = time.monotonic()
        with self._run_lock:
            if self.running:
                raise RuntimeError("a script is already running: stop it first")
            problem = start_problem(self.manager, holds, stop=False)  # the tabs disable Start under a STOP
            if problem:
                raise RuntimeError(problem)
            compile(source, filename, "exec")  # a SyntaxError reaches the caller before anything runs
            params = json.loads(json.dumps(dict(params or {})))  # plain data only
            _remember_source(filename, source)
            self._done.clear()
            self._user_ended.clear()
            self._stop_requested.clear()
            self._wake.clear()
            self._done_msg = None
            self._exit_report = None
            self.result = None
            self.body_started_at = None
            self.stop_reason = ""
            self.paused = False
            self.callback_errors = {}
            self.callbacks_dropped = 0
            self._output_budget = _OutputBudget()
            self.filename = filename
            self.context.stop_event.clear()
            self.gate.set("open")
            kernel = self._kernel
            if kernel is None or kernel.used or not kernel.alive:
                try:
                    kernel = self._next_kernel()
                except OSError as exc:
                    self._done.set()
                    self._user_ended.set()
                    raise RuntimeError(f"the script kernel (a Python process) could not be started: {exc}") from exc
            kernel.used = True
            self._ensure_spare()
            bridge = self._bridge
            assert bridge is not None
            self.stop_cause = ""
            self.run = self._open_run(source, filename, params, program, parameters, run_source, restart_of,
                                      continues, holds, compose)
            base = Path(filename).resolve().parent if not filename.startswith("<") else None
            bridge.context.base_dir = base
            self.context.base_dir = base
            thread = threading.Thread(target=self._control_main,
                                      args=(kernel, bridge, source, filename, params, t0),
                                      name="script-control", daemon=True)
            thread.start()
            return self.run

    def _open_run(self, source: str, filename: str, params: dict[str, Any], program: Any, parameters: Any,
                  run_source: RunSource, restart_of: str | None, continues: str | None = None,
                  holds: tuple[str, ...] = ("robot", "stimulator"),
                  compose: tuple[Composition, ...] = ()) -> ExerciseRun:
        runs = self.manager.runs

        if program is None:
            path = "" if filename.startswith("<") else filename
            try:  # the file as it is on disk now: Recover tells a file changed since from an editor's unsaved text
                on_disk = text_hash(Path(path).read_text(encoding="utf-8")) if path else ""
            except (OSError, UnicodeDecodeError):
                on_disk = ""
            program = Program("script_file", path or filename, Path(filename).name if path else "the editor's script",
                              text_hash(source), path=path, text=source, file_sha256=on_disk)
        if not parameters and params:
            parameters = tuple(RunParameter(str(k), str(k), v) for k, v in params.items())
        operator = str(self.manager.operator or "")
        self._run_log = runs
        return runs.start(program, tuple(parameters), run_source, operator, restart_of=restart_of,
                          continues=continues, holds=holds,
                          compose=[c.as_dict() for c in compose])

    def _end_run(self, result: ScriptResult) -> None:
        """The run's end from what happened: the script's result and the cause of a stop."""
        run = self.run
        # a run may live in an earlier log (a session started meanwhile): end it where it began
        runs = self._run_log if self._run_log is not None else self.manager.runs
        if run is None:
            return
        if result.status == "finished":
            reason, detail = "finished", ""
        elif result.status == "stopped":
            reason, detail = self.stop_cause or "stopped_by_operator", result.message
        elif result.status == "refused":
            live = runs.get(run.run_id)
            started = live is not None and bool(live.repetitions)
            # refused before its first movement (a limit such as the patient's FES cap): "not started"
            reason, detail = ("safety_stop" if started else "refused"), result.message
        else:
            where = f" (line {result.line})" if result.line else ""
            reason, detail = "script_error", f"{result.message}{where}"
        runs.end(run.run_id, reason, detail[:300])

    def _set_run_state(self, state: str, detail: str = "") -> None:
        run, runs = self.run, self._run_log
        if run is not None and runs is not None:
            runs.set_state(run.run_id, state, detail)

    def start_file(self, path: str | Path, params: dict[str, Any] | None = None) -> None:
        path = Path(path)
        self.start(path.read_text(encoding="utf-8"), str(path), params)

    def request_stop(self, reason: str = "stopped by the operator", cause: str = "stopped_by_operator") -> None:
        """Stop the script (and prompt entries); returns at once, never blocks (the supervisor's "script"
        stop action). FES and robot go to the safe state at once; the kernel ends within 200 ms.
        ``cause`` is the run's end reason (app.core.runs.END_REASONS); the first stop's reason and cause are kept."""
        running = self.running
        if not running and not any(p.is_alive() for p in list(self._prompts.values())):
            return
        if not self.stop_reason and running:
            self.stop_reason = reason
            self.stop_cause = cause
        elif running and self.stop_cause == "stopped_by_operator" and cause in ("emergency_stop", "safety_stop"):
            # A STOP that comes while a plain stop is on its way is the truer cause of the run's end (#36: a run
            # ended by a safety stop was recorded as stopped by the operator).
            self.stop_reason, self.stop_cause = reason, cause
        if not running:
            self._end_console_run(None, cause, reason[:300])
        self.context.stop_event.set()
        kernel = self._kernel
        if running:
            self.gate.set("closed")
        if kernel is not None:
            kernel.send({"op": "stop", "reason": reason})
        if running:
            self._stop_requested.set()
            self._wake.set()
            with self._safe_lock:
                if self._safe_thread is None or not self._safe_thread.is_alive():
                    thread = threading.Thread(target=self._safe_state_now, args=(reason,),
                                              name="script-safe-state", daemon=True)
                    thread.start()
                    self._safe_thread = thread

    def stop(self, reason: str = "stopped by the operator", wait_s: float = 1.0,
             cause: str = "stopped_by_operator") -> bool:
        """Stop and wait up to ``wait_s`` for user code to end; True when it has. Then, within what is left
        of ``wait_s``, wait for the run to finish its safe state too, so that a Start right after works."""
        self.request_stop(reason, cause)
        deadline = time.monotonic() + wait_s
        if self.running and not self._user_ended.wait(wait_s):
            return False
        while any(p.is_alive() for p in list(self._prompts.values())):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        self._done.wait(max(0.0, deadline - time.monotonic()))
        return True

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the run (including its safe state) has ended; True when it has."""
        return self._done.wait(timeout)

    def pause(self) -> None:
        """Hold the script: its calls wait (here and in the kernel), FES stops; :meth:`resume` lets it go on."""
        if not self.running or self.paused:
            return
        self.paused = True
        self.gate.set("paused")
        kernel = self._kernel
        if kernel is not None:
            kernel.send({"op": "pause"})
        self._stop_fes("script paused")
        run = self._run_log.get(self.run.run_id) if (self.run is not None and self._run_log is not None) else None
        self._state_before_pause = (run.state, run.state_detail) if run is not None else ("running", "")
        self._set_run_state("paused")
        self.manager.progress.pause()
        self.output("info", "Script paused (FES stopped).\n")

    def resume(self) -> None:
        if not self.running or not self.paused:
            return
        self.paused = False
        if self.gate.state == "paused":
            self.gate.set("open")
        kernel = self._kernel
        if kernel is not None:
            kernel.send({"op": "resume"})
        self._set_run_state(*self._state_before_pause)
        self.manager.progress.resume()
        self.output("info", "Script resumed.\n")

    def execute(self, source: str, symbol: str = "single") -> PromptRun | None:
        """Run one interactive statement in the kernel's namespace (the prompt). Returns a handle with
        ``join``/``is_alive``, or None when ``source`` is incomplete (more lines needed). Raises SyntaxError."""
        import codeop

        if codeop.compile_command(source, "<console>", symbol) is None:
            return None
        kernel = self._prompt_kernel()
        run = PromptRun(kernel)
        if kernel is None:
            self.output("stderr", "The script kernel could not be started: see the log.\n")
            run._done.set()
            return run
        kernel.used = True
        if not self.running:
            self.context.stop_event.clear()
        rid = next(self._ids)
        self._prompts = {k: p for k, p in self._prompts.items() if p.is_alive()}
        self._prompts[rid] = run
        self._open_console_run(rid, source)
        if not kernel.send({"op": "exec", "id": rid, "source": source}):
            run._done.set()
            self._end_console_run(rid, "script_error", "the script kernel did not take the entry")
        return run

    def _open_console_run(self, rid: int, source: str) -> None:
        """Code typed at the prompt while no script runs is a run of its own (kind "console"): a STOP during it
        is recorded against it, and Recover says it cannot be restarted. During a script it belongs to the
        script's run."""
        runs = self.manager.runs
        if self.running or self._console_run is not None:
            return
        self._run_log = runs
        program = Program("console", "<console>", "Console code", text_hash(source), text=source)
        self._console_run = runs.start(program, (), "console", str(self.manager.operator or ""))
        self._console_rid = rid

    def _end_console_run(self, rid: int | None, reason: str, detail: str = "") -> None:
        run, runs = self._console_run, self._run_log
        if run is None or runs is None or (rid is not None and rid != self._console_rid):
            return
        self._console_run = None
        runs.end(run.run_id, reason, detail)

    def completions(self, text: str) -> list[str]:
        """Names completing ``text`` (``linarm.mo`` → ``linarm.moveCentreTo``, …) in the kernel's live
        namespace. Device values are peeked (latest sample or nothing), never waited for."""
        if not re.fullmatch(r"[A-Za-z_][\w]*(\.[A-Za-z_]?[\w]*)*", text or ""):
            return []
        kernel = self._prompt_kernel()
        if kernel is None:
            return []
        value = self._ask(kernel, {"op": "complete", "text": text})
        if not isinstance(value, list):
            return []
        return [v for v in value[:2000] if isinstance(v, str) and v.startswith(text.rsplit(".", 1)[0])]

    def namespace_value(self, name: str, timeout: float = ANSWER_TIMEOUT_S) -> Any:
        """A variable of the kernel's namespace, as plain data (lists, dicts, numbers, text; others as repr)."""
        kernel = self._prompt_kernel()
        return None if kernel is None else self._ask(kernel, {"op": "get", "name": name}, timeout)

    def _ask(self, kernel: KernelProcess, msg: dict[str, Any], timeout: float = ANSWER_TIMEOUT_S) -> Any:
        rid = next(self._ids)
        answer = _Answer(kernel)
        self._answers[rid] = answer
        try:
            if kernel.send({**msg, "id": rid}):
                answer.event.wait(timeout)
            return answer.value
        finally:
            self._answers.pop(rid, None)

    # ------------------------------------------------------------------ kernel messages (reader thread)
    def _on_message(self, kernel: KernelProcess, bridge: ApiBridge,
                    msg: dict[str, Any]) -> Callable[[], None] | None:
        served = bridge.handle(msg)
        if callable(served):
            return served  # the script's e-stop: run at once by the reader that read it, off the lead
        if served:
            return None
        op = msg.get("op")
        if op == "out":
            stream, text = msg.get("stream"), msg.get("text")
            if stream in ("stdout", "stderr", "info") and isinstance(text, str):
                self._pass_output(stream, text[:1_000_000])
                return None
        elif op == "done":
            if kernel is self._kernel and self.running and self._done_msg is None:
                self._done_msg = msg
                self._user_ended.set()
                self._wake.set()
                return None
        elif op == "exiting":  # the script called os._exit: where, before the process is gone
            if kernel is self._kernel and self.running:
                self._exit_report = msg
            return None
        elif op == "exec_done":
            run = self._prompts.get(msg.get("id"))  # type: ignore[arg-type]
            if run is not None:
                run._done.set()
            rid = msg.get("id")
            self._end_console_run(rid if isinstance(rid, int) else None, "finished")
            return None
        elif op == "answer":
            answer = self._answers.get(msg.get("id"))  # type: ignore[arg-type]
            if answer is not None:
                answer.value = msg.get("value")
                answer.event.set()
            return None
        elif op == "__violation__":  # a line the bridge would not take: the kernel is being ended for it
            bridge.refuse(msg, str(msg.get("reason")), kind="bad line")
            return None
        bridge.refuse(msg, f"an unknown request {str(op)[:40]!r}")
        return None

    def _raw_output(self, stream: str, text: str) -> None:
        """What the kernel wrote to its own stdout/stderr (C extensions, a crash report)."""
        self._pass_output("stderr" if stream == "stderr" else "stdout", text)

    def _pass_output(self, stream: str, text: str) -> None:
        budget = self._output_budget
        first_drop = budget.dropped == 0
        if budget.take(len(text)):
            self.output(stream, text)
        elif first_drop:
            self.output("info", f"The script writes more than the console takes ({OUTPUT_RATE // 1024} KB a second "
                                "after the first 4 MB): the rest of its output is dropped and counted.\n")

    def _on_link_closed(self, kernel: KernelProcess) -> None:
        """The running script's kernel has gone (crash, os._exit, killed): FES and robot to the safe state at
        once, as on Stop, without waiting for the process's status (its warden first ends whatever the script
        started; on a loaded machine that took it past the 200 ms budget)."""
        if kernel is not self._kernel or not self.running or self._done_msg is not None:
            return
        with self._safe_lock:
            if self._safe_thread is None or not self._safe_thread.is_alive():
                thread = threading.Thread(target=self._safe_state_now, args=("the script's process ended",),
                                          name="script-safe-state", daemon=True)
                thread.start()
                self._safe_thread = thread

    def _on_kernel_exit(self, kernel: KernelProcess) -> None:
        for run in list(self._prompts.values()):
            if run.kernel is kernel:
                run._done.set()
        if kernel is self._kernel:
            self._end_console_run(None, "script_error", f"the script's process ended: {kernel.cause()}")
        for answer in list(self._answers.values()):
            if answer.kernel is kernel:  # not a read of the prompt's kernel when a retired one ends (#38)
                answer.event.set()
        if kernel is self._kernel:
            self._wake.set()
            if not self.running and kernel.used and not self._closed:
                self.output("info", f"The script kernel ended ({kernel.cause()}); a fresh one is ready.\n")
                threading.Thread(target=self._replace_ended, args=(kernel,), name="script-kernel-next",
                                 daemon=True).start()

    # ------------------------------------------------------------------ the run (control thread)
    def _control_main(self, kernel: KernelProcess, bridge: ApiBridge, source: str, filename: str,
                      params: dict[str, Any], t_start: float) -> None:
        t0 = time.monotonic()
        sup = self.manager.supervisor
        name = Path(filename).name
        sup.record(journal.SCRIPT_START, name=name, text=source, kernel_pid=kernel.pid)
        progress = self.manager.progress
        run = self.run
        if run is not None:
            progress.begin(run.title, run_id=run.run_id)
        else:
            progress.begin(name)
        result: ScriptResult | None = None
        try:
            if self.home_first:  # "prepare the robot": homed, and the controller's default settings
                self._home_if_needed()
                self._try_run_defaults()
        except ScriptStopped:
            result = ScriptResult("stopped", self.stop_reason or "stopped", filename)
        except BaseException as exc:
            if self._stop_requested.is_set() and self.stop_reason:  # homing ended by the stop
                result = ScriptResult("stopped", self.stop_reason, filename)
            else:
                status = "refused" if _refused(exc) else "error"
                result = ScriptResult(status, f"{type(exc).__name__}: {exc}", filename)
        if result is None and self._stop_requested.is_set():
            result = ScriptResult("stopped", self.stop_reason or "stopped", filename)
        if result is None:
            self.body_started_at = time.monotonic()
            self._set_run_state("running")  # until the program says what it does (setRunState)
            kernel.send({"op": "run", "source": source, "filename": filename, "params": params})
            self.kernel_start_s = time.monotonic() - t_start
            result = self._supervise(kernel, filename)
        self._user_ended.set()
        result.duration_s = time.monotonic() - t0
        self.gate.set("closed")
        bridge.unsubscribe_all()
        self._end_script_processes(kernel)
        bridge.refusal_log.flush()  # the run's refusals are in its record before it ends
        self._report(result)
        if bridge.refusals:
            self.output("info", f"{bridge.refusals} requests of the script were refused "
                                f"({', '.join(f'{n} {k}' for k, n in sorted(bridge.refusal_log.by_kind.items()))}).\n")
        with self._safe_lock:
            safe_thread, self._safe_thread = self._safe_thread, None
        if safe_thread is not None:
            safe_thread.join(2.0)
        self._bring_to_safe_state(result)
        self.context.close()  # the homing helper's thread and listeners end with the run
        sup.record(journal.SCRIPT_STOP, name=name, reason=result.message or result.status, status=result.status)
        progress.finish(result.status)  # an open repetition ends (not completed) before its run does
        self._end_run(result)
        self.gate.set("open")
        self.paused = False
        self.result = result
        self._done.set()
        if not kernel.alive and kernel is self._kernel and not self._closed:
            try:  # a fresh kernel for the prompt and the next Start (which would start one itself)
                self._replace_ended(kernel)
                self._ensure_spare()
            except OSError as exc:
                log.error("the script kernel could not be started: %s", exc)
        if self.on_finished is not None:
            try:
                self.on_finished(result)
            except Exception:
                log.exception("on_finished failed")

    def _supervise(self, kernel: KernelProcess, filename: str) -> ScriptResult:
        """Wait for the kernel's end of the run, its death, or Stop (then escalate)."""
        while True:
            msg = self._done_msg
            if msg is not None:
                return self._result_from(msg, filename)
            if kernel.ended.is_set():
                return self._ended_result(kernel, filename)
            if self._stop_requested.is_set():
                t_stop = time.monotonic()
                if self._wait_done(kernel, POLITE_STOP_S):
                    continue
                log.info("script kernel %s did not stop politely: terminating it", kernel.pid)
                kernel.terminate()
                if not self._wait_done(kernel, TERMINATE_S):
                    kernel.kill()
                    kernel.ended.wait(1.0)
                self._user_ended.set()
                msg = self._done_msg
                if msg is not None:
                    return self._result_from(msg, filename)
                log.info("script kernel %s ended %.0f ms after Stop (%s)", kernel.pid,
                         (time.monotonic() - t_stop) * 1000, kernel.cause())
                return ScriptResult("stopped", self.stop_reason or "stopped", filename)
            self._wake.wait(0.1)
            self._wake.clear()

    def _wait_done(self, kernel: KernelProcess, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while self._done_msg is None and not kernel.ended.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            kernel.ended.wait(min(remaining, 0.005))
        return True

    def _result_from(self, msg: dict[str, Any], filename: str) -> ScriptResult:
        status = msg.get("status")
        if status not in ("finished", "stopped", "error", "refused"):
            status = "error"
        message = str(msg.get("message") or "")[:2000]
        if status == "stopped":
            message = self.stop_reason or message or "stopped"
        line = msg.get("line")
        result = ScriptResult(str(status), message, filename, line if isinstance(line, int) else None,
                              str(msg.get("traceback") or "")[:100_000])
        if status in ("error", "refused") and self._stop_requested.is_set() and self.stop_reason:
            # a command failed because of the stop (robot IDLE, FES off, calls refused): the stop's cause
            result = ScriptResult("stopped", self.stop_reason, filename)
        try:
            self.callbacks_dropped = int(msg.get("callbacks_dropped") or 0)
            self.callback_errors = {(str(a), int(b), str(c)): int(n)
                                    for a, b, c, n in msg.get("callback_errors") or []}
        except (TypeError, ValueError):
            pass
        return result

    def _ended_result(self, kernel: KernelProcess, filename: str) -> ScriptResult:
        if self._stop_requested.is_set():
            return ScriptResult("stopped", self.stop_reason or "stopped", filename)
        if kernel.violation is not None:
            return ScriptResult("error", f"the script was ended: its process sent the application {kernel.violation}",
                                filename)
        cause = kernel.cause()
        where = _last_script_line(kernel.stderr_tail, filename)
        result = ScriptResult("error", f"the script's process ended: {cause}", filename, where)
        result.traceback = _crash_summary(kernel.stderr_tail, filename)
        report = self._exit_report
        if report is not None:
            line = report.get("line")
            result.line = line if isinstance(line, int) else result.line
            result.traceback = str(report.get("traceback") or "")[:100_000]
        return result

    def _end_script_processes(self, kernel: KernelProcess) -> None:
        """No process a script started outlives its run: the kernel's warden ends them all (setsid and
        double-forked ones too); the kernel itself stays for the prompt. A kernel that has ended took them
        with it (its warden ends everything before it exits)."""
        ended = kernel.sweep()
        if ended:
            log.info("script kernel %s: %d processes the script started were ended with its run", kernel.pid, ended)
            self.output("info", f"{ended} process{'es' if ended > 1 else ''} the script started "
                                f"{'were' if ended > 1 else 'was'} ended with it.\n")

    # ------------------------------------------------------------------ homing and safe state
    def _home_if_needed(self) -> None:
        """The seed's scripts assume a homed robot: home it first when the controller says it is not."""
        linarm = self.manager.driver(streams.LINARM)
        if linarm is None or not linarm.connected:
            return
        ctx = self.context
        reply = ctx.call(linarm.command, "getIsInitialized", source="script runner")
        if reply.get("initialized"):
            return
        self._set_run_state("homing")
        self.output("info", "The LINarm is not homed: homing it before the script starts…\n")
        log.info("script runner: homing the LINarm before %s", self.filename)
        ctx.call(linarm.command, "setCtrlState", int(ControlState.HOME_CTRL_STATE), source="script runner")

        def homed() -> bool:
            state = linarm.latest(streams.LINARM_STATE)
            return state is not None and bool(state.initialized) and state.homeState == HomeState.HOME_DONE

        if not ctx.wait_until(homed, self.home_timeout_s):
            raise RuntimeError(f"the LINarm did not finish homing within {self.home_timeout_s:.0f} s")
        self.output("info", "LINarm homed.\n")

    def _try_run_defaults(self) -> None:
        """The defaults are a courtesy to the program, not a condition of it: refused (the e-stop latched, a
        robot error) they are reported and the program still starts — its own commands meet the same refusal."""
        try:
            self._apply_run_defaults()
        except ScriptStopped:
            raise
        except Exception as exc:
            if self._stop_requested.is_set():
                raise
            log.info("robot defaults not restored before %s: %s", self.filename, exc)
            self.output("info", f"The robot's default settings were not restored: {exc}\n")

    def _apply_run_defaults(self) -> None:
        """Each run starts from the controller's own settings, not from what the previous run left (issue #26:
        a stiffness set by one exercise carried into the next): admittance Ka and assistance Kt back to their
        defaults, and the springs' pretension back to the homed one (a slow move of the carriages only: the
        centre holds). Done here, by the runner, so that every program — library exercise, a clinic's own
        script, console code run as a script — gets it without having to reset what others may have set; an
        exercise then sets what it needs itself. Skipped when the robot is not connected or not homed, and with
        ``home_first`` off (the operator prepares the robot himself: the Script tab's "Home the robot first")."""
        linarm = self.manager.driver(streams.LINARM)
        if linarm is None or not linarm.connected:
            return
        state = linarm.latest(streams.LINARM_STATE)
        if state is None or not state.initialized:
            return

        ctx, src = self.context, "script runner"
        ctx.call(linarm.command, "setAdmittanceParameter", K["ADMITTANCE_KA"], source=src)
        ctx.call(linarm.command, "setAssistanceParameter", K["ASSISTANCE_KT"], source=src)
        vsa = linarm.latest(streams.LINARM_VSA)
        home_delta = float(K["HOME_DELTA"])
        if vsa is None or abs(float(vsa.delta) - home_delta) <= DEFAULT_DELTA_TOLERANCE_M:
            return
        self._set_run_state("starting", "the robot's default stiffness")
        self.output("info", f"Robot stiffness back to its default (pretension {home_delta * 1000:.0f} mm)…\n")
        ctx.call(linarm.command, "setCtrlState", int(ControlState.IDLE_CTRL_STATE), source=src)
        ctx.call(linarm.command, "setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS), source=src)
        ctx.call(linarm.command, "setCtrlState", int(ControlState.ON_CTRL_STATE), source=src)
        ctx.call(linarm.command, "moveDeltaTo", home_delta, *PRETENSION_MOVE, False, source=src)

        def settled() -> bool:
            v = linarm.latest(streams.LINARM_VSA)
            return v is not None and abs(float(v.delta) - home_delta) <= DEFAULT_DELTA_TOLERANCE_M / 2

        ctx.wait_until(settled, 5.0)
        ctx.call(linarm.command, "setCtrlState", int(ControlState.IDLE_CTRL_STATE), source=src)
        self._set_run_state("starting")

    def _safe_state_now(self, reason: str) -> None:
        """On Stop: FES and robot to the safe state at once, before the kernel has even ended."""
        try:
            self._bring_to_safe_state(ScriptResult("stopped", reason), quiet=True)
        except Exception:
            log.exception("immediate safe state failed")

    def _stop_fes(self, reason: str) -> bool:
        fes = self.manager.driver(streams.FES)
        if fes is None:
            return False
        try:
            fes.stop_stimulation(reason, "script runner")
            return True
        except Exception as exc:
            log.warning("script: FES stop failed: %s", exc)
            self.output("stderr", f"Could not stop the FES: {exc}\n")
            return False

    def _bring_to_safe_state(self, result: ScriptResult, quiet: bool = False) -> None:
        """FES stopped; robot IDLE (or holding). Direct driver calls, never through the kernel."""
        reason = f"script {result.status}"
        done: list[str] = []
        if self._stop_fes(reason):
            done.append("FES stopped")
        linarm = self.manager.driver(streams.LINARM)
        if linarm is not None and linarm.connected:
            state = linarm.latest(streams.LINARM_STATE)
            # IDLE is sent even when the last state sample says IDLE: it is up to 50 ms old, and a command
            # acknowledged since (setCtrlState ON from the script) may not be in it yet.
            try:
                if self.safe_state == "hold" and state is not None and state.controlState == ControlState.ON_CTRL_STATE:
                    # a mode change clears any motion: the centre holds where it is
                    linarm.command("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS), source="script runner")
                    done.append("robot holding")
                else:
                    linarm.command("setCtrlState", int(ControlState.IDLE_CTRL_STATE), source="script runner")
                    done.append("robot IDLE")
            except Exception as exc:
                log.warning("script end: robot safe state by command failed (%s); motors off directly", exc)
                try:
                    linarm.emergency_idle(reason)
                    done.append("robot IDLE")
                except Exception as exc2:
                    self.output("stderr", f"Could not bring the robot to IDLE: {exc2}\n")
        self.manager.supervisor.record(journal.SCRIPT_SAFE_STATE, reason=reason, actions=done)
        if done and not quiet:
            self.output("info", f"Safe state: {', '.join(done)}.\n")

    def _register_stop_action(self) -> None:
        """Contract 3: the supervisor's e-stop and safe state stop the running script ("script")."""
        sup = self.manager.supervisor
        ref = weakref.ref(self)

        def stop_script(reason: str) -> None:
            runner = ref()
            if runner is None:
                return
            cause = _stop_cause(sup, reason)
            console_run, runs = runner._console_run, runner._run_log
            if console_run is not None and runs is not None:  # a console entry commanding the devices
                runs.end(console_run.run_id, cause, reason[:300])
            if runner.running:
                runner.request_stop(reason, cause)

        sup.register_estop_action("script", stop_script)

    # ------------------------------------------------------------------ reporting
    def _report(self, result: ScriptResult) -> None:
        if result.status == "finished":
            self.output("info", f"Script finished ({result.duration_s:.1f} s).\n")
        elif result.status == "stopped":
            self.output("info", f"Script stopped: {result.message} ({result.duration_s:.1f} s).\n")
        else:
            if result.traceback:
                self.output("stderr", result.traceback)
            where = f" at line {result.line}" if result.line else ""
            self.output("info", f"Script ended by an error{where}: {result.message}\n")
        if self.callbacks_dropped:
            self.output("info", f"{self.callbacks_dropped} samples were skipped because the callbacks were "
                                "slower than the data.\n")
        if self._output_budget.dropped:
            self.output("info", f"{self._output_budget.dropped} characters of the script's output were dropped.\n")


def _stop_cause(sup: SafetySupervisor, reason: str) -> str:
    """The supervisor's stop, as a run's end reason: the e-stop (latched before its actions run), the end of
    the session, the application closing, or a safety stop (a fault: device lost, robot error, …)."""
    if sup.estop_latched:
        return "emergency_stop"
    if reason == "session ended":
        return "session_ended"
    if reason in ("application closing", "main window closed"):
        return "app_exit"
    return "safety_stop"


def _kill_all(kernels: list[KernelProcess]) -> None:
    for kernel in kernels:
        kernel.kill()


def _refused(exc: BaseException) -> bool:
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, CommandRefused | SafetyError):
            return True
        seen = seen.__cause__
    return False


def _last_script_line(report: str, filename: str) -> int | None:
    """The script's line in a faulthandler report ('File "x.py", line 3 in <module>')."""
    lines = re.findall(r'File "([^"]+)", line (\d+)', report)
    for name, line in lines:  # faulthandler lists the most recent call first
        if name == filename:
            return int(line)
    return None


_APP_DIR = str(Path(__file__).resolve().parent.parent)


def _is_app_file(filename: str) -> bool:
    """Frames of the application itself are hidden from script tracebacks (not the user's code)."""
    if filename.startswith(str(RESOURCES)):  # installed, the example scripts lie inside app/ (app/_resources)
        return False
    return filename.startswith(_APP_DIR) or filename.startswith("<frozen") or "concurrent/futures" in filename


def _crash_summary(report: str, filename: str) -> str:
    """faulthandler's report reduced to what a script's author needs: the error and the script's frames."""
    if "Fatal Python error" not in report:
        return report.strip()[-2000:] + "\n" if report.strip() else ""
    head = report[report.index("Fatal Python error"):].splitlines()
    out = [head[0]]
    frames = [m for ln in head[1:] if (m := re.search(r'File "([^"]+)", line (\d+)', ln))]
    out += [f'  File "{m.group(1)}", line {m.group(2)}' for m in frames
            if not _is_app_file(m.group(1)) and "/lib/python" not in m.group(1)]
    return "\n".join(out) + "\n"


def _remember_source(filename: str, source: str) -> None:
    """Tracebacks show the lines of the text that ran, even an unsaved editor buffer."""
    lines = source.splitlines(keepends=True)
    linecache.cache[filename] = (len(source), None, lines, filename)


def _stdout_sink(stream: str, text: str) -> None:
    target = sys.stderr if stream == "stderr" else sys.stdout
    target.write(text)
    target.flush()
