"""The script kernel's process and its link, on the application's side (one job: the process, not the API).

:class:`KernelProcess` starts the kernel's warden (app/scripting/warden.py, ``python -I warden.py SOCK_FD
MEMORY_LIMIT CONTROL_FD``), which execs the kernel (app/scripting/kernel.py) with one end of an AF_UNIX socket
pair and ends whatever a script starts. It sends the kernel its first message (the ``hello`` it is given), reads
the kernel's messages, its stdout/stderr (a crash report from faulthandler lands there) and notices its end —
all on reader threads of its own (never the GUI thread). Writes never block the caller: what the socket does
not take at once waits in a backlog a writer thread drains. What the messages mean is its ``handler``'s
business (the runner's, which passes the API's requests to app/scripting/bridge.py).

Kernel → application is JSON only: a hostile script controls those bytes, so they are never unpickled, a line
that is not a JSON object (or too long, or not text) ends the kernel, and reading is rate-limited.
"""

from __future__ import annotations

import collections
import json
import logging
import os
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
from typing import Any

from app.core.priority import SCRIPT_NICE

log = logging.getLogger(__name__)

WARDEN_FILE = Path(__file__).resolve().parent / "warden.py"  # the kernel's parent: owns whatever a script starts
MEMORY_LIMIT_BYTES = 2 * 1024**3  # address space of a kernel: a runaway allocation fails as MemoryError there
MAX_MESSAGE = 4 * 1024 * 1024  # a longer line from the kernel is a protocol violation
BACKLOG_LIMIT = 16 * 1024 * 1024  # bytes waiting for a kernel that does not read: samples beyond are dropped
READERS = 3  # leader/follower threads per kernel (urgent work a handler returns, the e-stop, runs off the lead)
PROBLEMS_LOGGED = 5  # handler failures logged with a traceback per kernel; the rest are counted
# Bytes read from a kernel: READ_RATE a second once READ_BURST is spent. A script is only slowed (its writes
# wait in the socket: back-pressure), never failed; the application's readers never parse more than this
# (a script printing 3 MB lines in a loop would otherwise keep a reader thread, and the GIL, busy).
READ_RATE = 8 * 1024 * 1024
READ_BURST = 16 * 1024 * 1024
CONTROL_TIMEOUT_S = 5.0  # the warden's answers (its first line comes ~20 ms after the start)
# Ending: a retired kernel is asked to exit, killed (through its warden) after RETIRE_WAIT_S, given RETIRE_WAIT_S
# more; once its link has closed, the warden gets FINISH_WAIT_S to end by itself, SWEEP_WAIT_S after a kill (it ends
# what the script started within 2 s), KILLED_WAIT_S after a kill of its own. END_BOUND_S: the most all of it takes.
RETIRE_WAIT_S = 1.0
FINISH_WAIT_S = 0.5
SWEEP_WAIT_S = 3.0
KILLED_WAIT_S = 1.0
END_BOUND_S = 2 * RETIRE_WAIT_S + FINISH_WAIT_S + SWEEP_WAIT_S + KILLED_WAIT_S
THREAD_PREFIX = "kernel-"  # the names of a kernel's threads here: kernel-<warden pid>-writer, -reader0, …


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


def encode(msg: dict[str, Any]) -> bytes:
    """One message for the kernel: a line of JSON."""
    return (json.dumps(msg, separators=(",", ":"), default=str) + "\n").encode()


def _kernel_environment() -> dict[str, str]:
    """The kernel's environment: the application's, without anything meant for another helper."""
    from app.devices.sim.patient_model.process import LINK_KEY_FD_ENV
    from app.wire.udp_frames import LINK_KEY_ENV

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

    def __init__(self, hello: dict[str, Any], memory_limit: int = MEMORY_LIMIT_BYTES) -> None:
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
                 str(control_child.fileno()), str(SCRIPT_NICE)],
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
        named = f"{THREAD_PREFIX}{self.warden_pid}"
        self._writer = threading.Thread(target=self._write_main, name=f"{named}-writer", daemon=True)
        self._writer.start()
        for i in range(READERS):
            threading.Thread(target=self._reader_main, name=f"{named}-reader{i}", daemon=True).start()
        self.send(hello)  # the kernel's first message: it builds its namespace from it while it waits for a script

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
        return self.send_bytes(encode(msg), droppable=droppable)

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
            self._overflow_pool = ThreadPoolExecutor(max_workers=4,
                                                     thread_name_prefix=f"{THREAD_PREFIX}{self.warden_pid}-call")
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
            self.returncode = self.proc.wait(FINISH_WAIT_S)
        except subprocess.TimeoutExpired:
            self.kill()
            try:  # the warden ends its sweep within 2 s
                self.returncode = self.proc.wait(SWEEP_WAIT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.returncode = self.proc.wait(KILLED_WAIT_S)
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
            if not self.ended.wait(RETIRE_WAIT_S):
                self.kill()
                self.ended.wait(RETIRE_WAIT_S)

        threading.Thread(target=reap, name=f"{THREAD_PREFIX}{self.warden_pid}-reaper", daemon=True).start()

    def end_now(self, polite_s: float, term_s: float) -> bool:
        """TERM after ``polite_s`` without an end, KILL ``term_s`` later; True once it has ended."""
        if self.ended.wait(polite_s):
            return True
        self.terminate()
        if self.ended.wait(term_s):
            return True
        self.kill()
        return self.ended.wait(1.0)
