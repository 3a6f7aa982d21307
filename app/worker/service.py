"""The task service: heavy work in a worker process, never in the real-time process's interpreter (issue #37).

The application (drivers, command queues, supervisor, recorder, GUI thread) lives in one process whose interpreter
must stay free: parsing a long session, computing its metrics, drawing a PDF or writing HDF5 would hold the
interpreter lock for seconds, starve the LINarm heartbeat and the FES thread, and a crash inside HDF5 would end the
therapy. So those run here, in one warm worker process (app/worker/process.py), one task at a time:

    service = TaskService()
    service.warm()                                     # start the worker now, off the caller's thread
    task = service.submit("session_summary", folder, title="Summary of 20260301-100000", on_update=callback)
    task.cancel()                                      # or wait: task.wait(); task.status / result / error

Contract:

* ``submit`` never blocks: it queues the task (and starts the worker when none runs). ``on_update(task)`` is called
  on the service's link thread for every change (progress, end); the window's adapter (app/ui/tasks.py) hands it
  to the GUI thread.
* A task ends exactly once: DONE with its ``result``; FAILED with ``error``, one plain sentence (``detail`` holds
  the worker's traceback, for the log); or CANCELLED.
* Cancel: a queued task is dropped at once; a running one is asked to stop (its progress checks raise) and, when
  it does not within ``cancel_grace_s`` (stuck in native code), the worker is killed.
* A crash of the worker (SIGSEGV inside HDF5 on a full disk, SIGKILL, an exit) fails the task it was running with
  a sentence saying so (and, for an output on a full disk, that the disk is full); the temporaries of its outputs
  are removed; the next task gets a new worker. Nothing of the application's own state is touched.
* The worker runs at a lower priority (``nice``), so on a busy machine the real-time process keeps its cores.

Qt-free: the window's side is app/ui/tasks.py.
"""

from __future__ import annotations

import collections
import contextlib
import enum
import itertools
import logging
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import IO, Any

from app.core.priority import group_nice
from app.worker.protocol import LinkClosed, Sender, recv

log = logging.getLogger(__name__)

# The worker yields the CPU to the real-time process on a busy machine (LINARMPP_WORKER_NICE overrides it: a test
# machine running two suites side by side may want its tasks to keep pace).
WORKER_NICE = int(os.environ.get("LINARMPP_WORKER_NICE", "10"))
CANCEL_GRACE_S = 2.0  # a running task asked to cancel has this long before its worker is killed
LOW_SPACE_MIB = 16.0  # an output's disk with less than this free after a crash: "the disk is full"
_POLL_S = 0.1
_WORKER_LOG_MAX = 5 * 1024 * 1024
_BOOT = ("import sys; sys.path.insert(0, sys.argv[2]); from app.worker.process import main; "
         "main(int(sys.argv[1]))")


class TaskStatus(enum.Enum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


class TaskFailed(Exception):
    """A task that failed (``str()``: its one sentence) or was cancelled (``cancelled``)."""

    def __init__(self, sentence: str, cancelled: bool = False) -> None:
        super().__init__(sentence)
        self.cancelled = cancelled


Update = Callable[["Task"], None]


class Task:
    """One piece of work for the worker: what to run, how far it is, how it ended."""

    def __init__(self, service: TaskService, tid: int, kind: str, args: tuple[Any, ...], kwargs: dict[str, Any],
                 title: str, on_update: Update | None, outputs: Sequence[Path]) -> None:
        self.service = service
        self.id = tid
        self.kind = kind
        self.args = args
        self.kwargs = kwargs
        self.title = title or kind
        self.outputs = tuple(Path(p) for p in outputs)  # files or folders it writes (temporaries cleaned on a crash)
        self.status = TaskStatus.QUEUED
        self.fraction = 0.0
        self.text = ""
        self.result: Any = None
        self.error = ""  # one sentence when FAILED
        self.detail = ""  # the worker's traceback, for the log
        self.submitted = time.monotonic()
        self.started: float | None = None
        self.finished: float | None = None
        self.cancel_requested = False
        self.worker: Any = None  # the worker process running it (service side)
        self._on_update = on_update
        self._ended = threading.Event()

    @property
    def done(self) -> bool:
        return self._ended.is_set()

    @property
    def ok(self) -> bool:
        return self.status is TaskStatus.DONE

    def cancel(self) -> None:
        self.service._cancel(self)

    def wait(self, timeout: float | None = None) -> bool:
        return self._ended.wait(timeout)

    def value(self, timeout: float | None = None) -> Any:
        """The result, waiting for it; raises TaskFailed (its sentence) when it failed or was cancelled."""
        if not self.wait(timeout):
            raise TaskFailed(f"{self.title} did not finish within {timeout:g} s.")
        if self.status is TaskStatus.DONE:
            return self.result
        raise TaskFailed(self.error or f"{self.title} was cancelled.", self.status is TaskStatus.CANCELLED)

    def __repr__(self) -> str:
        return f"<Task {self.id} {self.kind} {self.status.value}>"


class _Worker:
    """One worker process and its link; the link thread reads it and reports to the service."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.sender = Sender(sock)
        self.proc: subprocess.Popen[bytes] | None = None
        self.t_spawn = time.perf_counter()
        self.ready_s: float | None = None
        self.thread: threading.Thread | None = None
        self.kill_at: float | None = None  # a cancel not honoured: kill the process then
        self.quitting = False


class TaskService:
    """Runs tasks in one warm worker process (see the module's docstring for the contract)."""

    def __init__(self, *, nice: int | None = None, cancel_grace_s: float = CANCEL_GRACE_S,
                 env: dict[str, str] | None = None) -> None:
        self.nice = WORKER_NICE if nice is None else nice
        self.cancel_grace_s = cancel_grace_s
        self.env = env
        self.spawns = 0
        self.crashes = 0
        self.last_start_s: float | None = None  # spawn → ready of the last worker (what "warm" saves)
        self._lock = threading.RLock()
        self._ids = itertools.count(1)
        self._queue: collections.deque[Task] = collections.deque()
        self._current: Task | None = None
        self._worker: _Worker | None = None
        self._closed = False
        self._keep_warm = False
        self._pending: list[Task] = []  # tasks whose callbacks are due once the lock is released

    # ------------------------------------------------------------------ public
    def warm(self) -> None:
        """Start the worker now (off the caller's thread) and keep one running, so the first task does not wait
        for it."""
        with self._lock:
            self._keep_warm = True
            if not self._closed and self._worker is None:
                self._worker = self._start_worker()

    @property
    def worker_pid(self) -> int | None:
        w = self._worker
        return w.proc.pid if w is not None and w.proc is not None else None

    @property
    def busy(self) -> bool:
        return self._current is not None or bool(self._queue)

    def submit(self, kind: str, *args: Any, title: str = "", on_update: Update | None = None,
               outputs: Iterable[str | Path] = (), **kwargs: Any) -> Task:
        """Queue ``kind`` (a job of app/worker/jobs.py, or ``"module:function"``) with its arguments."""
        task = Task(self, next(self._ids), kind, args, kwargs, title, on_update, [Path(p) for p in outputs])
        with self._lock:
            if self._closed:
                self._end(task, TaskStatus.CANCELLED, error=f"{task.title} was not run: the application is closing.")
            else:
                self._queue.append(task)
                self._pump()
        self._flush()
        return task

    def run(self, kind: str, *args: Any, timeout: float | None = None, **kwargs: Any) -> Any:
        """Submit and wait: the result, or TaskFailed with the sentence."""
        return self.submit(kind, *args, **kwargs).value(timeout)

    def close(self, timeout: float = 3.0) -> None:
        """Cancel what is queued, end the worker (killed if it does not go within ``timeout``) and its link."""
        with self._lock:
            if self._closed:
                worker = None
            else:
                self._closed = True
                while self._queue:
                    task = self._queue.popleft()
                    self._end(task, TaskStatus.CANCELLED, error=f"{task.title} was cancelled: the application closed.")
                worker = self._worker
                if worker is not None:
                    worker.quitting = True
                    with contextlib.suppress(LinkClosed):
                        worker.sender.send("quit")
        self._flush()
        if worker is not None and worker.thread is not None and worker.thread is not threading.current_thread():
            worker.thread.join(timeout)
            if worker.thread.is_alive():
                if worker.proc is not None:
                    with contextlib.suppress(OSError):
                        worker.proc.kill()
                worker.thread.join(timeout)

    # ------------------------------------------------------------------ queue (under the lock)
    def _pump(self) -> None:
        if self._closed or self._current is not None or not self._queue:
            return
        if self._worker is None:
            self._worker = self._start_worker()
        task = self._queue.popleft()
        self._current = task
        task.worker = self._worker
        task.status, task.started = TaskStatus.RUNNING, time.monotonic()
        self._pending.append(task)
        try:
            self._worker.sender.send("run", task.id, task.kind, task.args, task.kwargs)
        except LinkClosed:
            pass  # the link thread sees the worker gone and fails the task
        except Exception as exc:  # arguments that cannot be sent (not picklable): this task only
            self._current = None
            self._end(task, TaskStatus.FAILED, error=f"{task.title} could not be started: {exc}.")
            self._pump()

    def _end(self, task: Task, status: TaskStatus, result: Any = None, error: str = "", detail: str = "") -> None:
        if task.done:
            return
        task.status, task.result, task.error, task.detail = status, result, error, detail
        task.finished = time.monotonic()
        if status is TaskStatus.DONE:
            task.fraction = 1.0
        task._ended.set()
        self._pending.append(task)
        if status is TaskStatus.FAILED:
            log.error("task %s failed: %s%s", task.title, error, f"\n{detail}" if detail else "")

    def _flush(self) -> None:
        """Call the callbacks due, outside the lock (a callback may submit or cancel)."""
        with self._lock:
            pending, self._pending = self._pending, []
        for task in pending:
            if task._on_update is not None:
                try:
                    task._on_update(task)
                except Exception:
                    log.exception("a task's update callback failed")

    def _cancel(self, task: Task) -> None:
        with self._lock:
            if task.done:
                return
            task.cancel_requested = True
            if task in self._queue:
                self._queue.remove(task)
                self._end(task, TaskStatus.CANCELLED, error=f"{task.title} was cancelled.")
            elif task is self._current and self._worker is not None:
                self._worker.kill_at = time.monotonic() + self.cancel_grace_s
                with contextlib.suppress(LinkClosed):
                    self._worker.sender.send("cancel", task.id)
        self._flush()

    # ------------------------------------------------------------------ the worker process
    def _start_worker(self) -> _Worker:
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        worker = _Worker(parent)
        self.spawns += 1
        # Queued in the socket before the process exists; it reads them once it runs.
        # Its scheduling group (a session of its own) sits as far below the application's group as its nice says:
        # the application's group may be raised (app/core/priority.py).
        app_group = group_nice() or 0
        worker.sender.send("init", {"sys_path": list(sys.path), "nice": self.nice,
                                    "group_nice": max(-20, min(19, app_group + self.nice))})
        worker.thread = threading.Thread(target=self._link, args=(worker, child), name="task-worker-link",
                                         daemon=True)
        worker.thread.start()
        return worker

    def _environment(self) -> dict[str, str]:
        env = dict(os.environ if self.env is None else self.env)
        env["QT_QPA_PLATFORM"] = "offscreen"  # the reports draw with Qt: fonts, no screen
        env["LINARMPP_WORKER"] = "1"
        return env

    @staticmethod
    def _stderr() -> IO[bytes] | int:
        """The worker's stderr: a file beside the application's log (its tracebacks, a crash's stack), never the
        console a command-line user reads."""
        try:
            from app.core.paths import log_dir

            path = log_dir() / "worker.log"
            if path.exists() and path.stat().st_size > _WORKER_LOG_MAX:
                path.unlink()
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            return os.fdopen(fd, "ab")
        except OSError:
            return subprocess.DEVNULL

    def _link(self, worker: _Worker, child: socket.socket) -> None:
        """The link thread: start the process, read its messages until it is gone."""
        import app

        stderr = self._stderr()
        try:
            worker.proc = subprocess.Popen(
                [sys.executable, "-I", "-c", _BOOT, str(child.fileno()), str(Path(app.__file__).resolve().parents[1])],
                pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr,
                start_new_session=True, env=self._environment(), close_fds=True)
        except OSError as exc:
            child.close()
            self._gone(worker, None, f"the worker process could not be started ({exc.strerror or exc})")
            return
        finally:
            if not isinstance(stderr, int):
                stderr.close()
        child.close()
        try:
            while True:
                if worker.kill_at is not None and time.monotonic() >= worker.kill_at:
                    worker.kill_at = None
                    log.warning("the worker did not stop its task when asked: killed")
                    with contextlib.suppress(OSError):
                        worker.proc.kill()
                readable, _, _ = select.select([worker.sock], [], [], _POLL_S)
                if readable:
                    self._handle(worker, recv(worker.sock))
        except LinkClosed:
            pass
        except Exception:
            log.exception("the worker link failed")
            with contextlib.suppress(OSError):
                worker.proc.kill()
        code = worker.proc.wait()
        worker.sock.close()
        self._gone(worker, code, "")

    def _handle(self, worker: _Worker, msg: tuple[Any, ...]) -> None:
        what = msg[0]
        with self._lock:
            task = self._current
            if what == "ready":
                worker.ready_s = time.perf_counter() - worker.t_spawn
                self.last_start_s = worker.ready_s
                log.debug("worker process %s ready in %.2f s", msg[1], worker.ready_s)
            elif task is None or msg[1] != task.id:
                pass  # a message of a task already ended (cancelled, then finished anyway)
            elif what == "progress":
                task.fraction, task.text = float(msg[2]), str(msg[3])
                self._pending.append(task)
            elif what in ("done", "failed", "cancelled"):
                worker.kill_at = None
                self._current = None
                retire = len(msg) == {"done": 4, "failed": 5, "cancelled": 5}[what] and msg[-1] == "retire"
                if retire and self._worker is worker:  # it ends after this answer: the next task gets a new one
                    worker.quitting = True
                    self._worker = None
                if what == "done":
                    self._end(task, TaskStatus.DONE, result=msg[2])
                elif what == "failed":
                    self._end(task, TaskStatus.FAILED, error=str(msg[2]), detail=str(msg[3]))
                else:
                    self._end(task, TaskStatus.CANCELLED, error=f"{task.title} was cancelled.")
                self._pump()
        self._flush()

    def _gone(self, worker: _Worker, code: int | None, why: str) -> None:
        """The worker has ended: the task it ran fails (or is cancelled, if that was asked), a new worker takes
        the queue."""
        with self._lock:
            if self._worker is worker:
                self._worker = None
            task = self._current if self._current is not None and self._current.worker is worker else None
            if task is not None:
                self._current = None
                for dest in task.outputs:
                    _remove_temporaries(dest)
                if task.cancel_requested:
                    self._end(task, TaskStatus.CANCELLED, error=f"{task.title} was cancelled.")
                elif worker.quitting:
                    self._end(task, TaskStatus.CANCELLED, error=f"{task.title} was cancelled: the application closed.")
                else:
                    self.crashes += 1
                    self._end(task, TaskStatus.FAILED, error=_crash_sentence(task, code, why))
            elif code not in (0, None) and not worker.quitting:
                self.crashes += 1
                log.warning("the worker process ended between tasks (%s)", _how(code))
            if not self._closed and (self._queue or (self._keep_warm and worker.ready_s is not None)):
                if self._worker is None:
                    self._worker = self._start_worker()
                self._pump()
        self._flush()


def _how(code: int | None) -> str:
    if code is None:
        return "not started"
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit status {code}"


def _remove_temporaries(dest: Path) -> None:
    from app.core.outputs import remove_quietly, temporaries_of

    for tmp in temporaries_of(dest):
        remove_quietly(tmp)


def _crash_sentence(task: Task, code: int | None, why: str) -> str:
    """What the user reads when the worker died under a task: what failed, why if it can be told (a full disk),
    that nothing was written."""
    text = f"{task.title} failed: {why or f'the worker process stopped unexpectedly ({_how(code)})'}."
    for dest in task.outputs:
        try:
            free = shutil.disk_usage(dest.parent).free / (1 << 20)
            read_only = bool(os.statvfs(dest.parent).f_flag & os.ST_RDONLY)
        except OSError:
            continue
        if read_only:
            text += f" The folder {dest.parent} is read-only."
            break
        if free < LOW_SPACE_MIB:
            text += f" The disk is full ({free:.1f} MiB free in {dest.parent})."
            break
    if task.outputs:
        text += " Nothing was written."
    return text
