"""One command path per device (issue #29): a priority queue with one writer thread, and a status per command.

Every command of a device — the window's buttons, a script's calls, the assistance split, the connection
handshake, the heartbeat and the emergency stop — is submitted here and written to the wire by the queue's
one thread, in priority order (:class:`Priority`): the e-stop first, then the heartbeat, then the link's own
safety work (handshake, limits, envelope), then everything else in arrival order.

``submit`` returns at once with a :class:`CommandStatus` (a ``concurrent.futures.Future``): the caller may wait
on it (a script, the headless runner), attach a callback (the GUI turns it into a signal; it never waits on
the GUI thread), or ignore it (the assistance split logs a refusal). ``written`` says when the bytes left.

A command that expects an acknowledgement is **exclusive**: one is in flight at a time (the controller's
receive buffer is small, and replies are matched in order); the next exclusive one waits until the in-flight
one is done or timed out. The e-stop and heartbeats are not exclusive: they are written between, at once.

A status completes **once**, as ophyd's Status: a second ``resolve`` / ``fail`` raises :class:`StatusAlreadyDone`
(a bug: two parts of the app both think they own the command). Where two parties race for it legitimately —
the reply against its timeout, the link lost or the queue closing against the reply, a caller's ``cancel``
against the reply — each first ``claim``s it (atomic: exactly one wins) and only the winner completes it;
``settle`` is claim-then-complete in one call. The loser's outcome is dropped, never half-applied.

The supervisor still sees everything: commands are checked before they are queued (a refusal fails the status
with SafetyError and sends nothing), and the e-stop is recorded by the supervisor as it always was; the queue
only orders the wire. Qt-free: the queue's thread is a plain thread (real-time when the driver asks).
"""

from __future__ import annotations

import enum
import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


class Priority(enum.IntEnum):
    ESTOP = 0  # motors off / stimulation off: ahead of everything, never behind a command in flight
    HEARTBEAT = 1  # keeps the controller's host watchdog fed
    LINK = 2  # handshake, limits, envelope: the link's own safety work
    NORMAL = 3  # operator, script, assistance, VR task: in arrival order


class CommandQueueClosed(RuntimeError):
    """The device's command queue has stopped (the application is closing); nothing was sent."""


class StatusAlreadyDone(InvalidStateError):
    """A command's status was completed a second time, or by another thread than the one that claimed it."""


class CommandStatus(Future):
    """A submitted command: a Future holding the reply (or the error), plus when its bytes were written.
    Completed once (see the module docstring): ``resolve``/``fail`` are strict, ``claim``/``settle`` are for the
    paths that race."""

    def __init__(self, name: str, source: str, priority: Priority) -> None:
        super().__init__()
        self.name = name
        self.source = source
        self.priority = priority
        self.submitted_at = time.monotonic()
        self.written_at: float | None = None
        self.timeout_s: float | None = None  # how long its reply may take once written (exclusive commands)
        self._written = threading.Event()
        self._settled = threading.Event()  # written or done: what wait_written waits for (no polling: e-stop path)
        self._claim_lock = threading.Lock()
        self._claimed_by: int | None = None  # the thread that owns the completion (claim, resolve, fail, cancel)
        self.add_done_callback(lambda _s: self._settled.set())

    @property
    def written(self) -> bool:
        return self._written.is_set()

    def wait_written(self, timeout: float | None = None) -> bool:
        """Block until the bytes were written (True), the command failed before that (False), or ``timeout``."""
        self._settled.wait(timeout)
        return self._written.is_set()

    def mark_written(self) -> None:
        self.written_at = time.monotonic()
        self._written.set()
        self._settled.set()

    # ------------------------------------------------------------------ completion (once)
    def claim(self) -> bool:
        """Take the right to complete this status: True for exactly one caller (its thread must then resolve or
        fail it), False when it is done or another thread claimed it (that outcome stands). Atomic: the reply
        and its timeout, the link lost and the reply, a cancel and the reply, each claim before they act."""
        me = threading.get_ident()
        with self._claim_lock:
            if self._claimed_by is not None or self.done():
                return False
            self._claimed_by = me
            return True

    def _take(self) -> None:
        me = threading.get_ident()
        with self._claim_lock:
            if self.done():
                raise StatusAlreadyDone(f"{self.name}: completed twice (it was already "
                                        f"{'cancelled' if self.cancelled() else 'done'})")
            if self._claimed_by not in (None, me):
                raise StatusAlreadyDone(f"{self.name}: completed by a thread that did not claim it")
            self._claimed_by = me

    def set_result(self, result: object) -> None:
        self._take()
        super().set_result(result)

    def set_exception(self, exception: BaseException | None) -> None:
        self._take()
        super().set_exception(exception)

    def resolve(self, value: object) -> None:
        """Complete with the reply's ``value``; StatusAlreadyDone when it is done or claimed by another thread."""
        self.set_result(value)

    def fail(self, exc: BaseException) -> None:
        """Complete with ``exc``; StatusAlreadyDone when it is done or claimed by another thread."""
        self.set_exception(exc)

    def settle(self, value: object = None, exc: BaseException | None = None) -> bool:
        """Claim, then resolve with ``value`` (or fail with ``exc``): for the paths that race for a status
        (see :meth:`claim`). True when this call completed it; False when another party did or will."""
        if not self.claim():
            return False
        if exc is not None:
            self.set_exception(exc)
        else:
            self.set_result(value)
        return True

    def cancel(self) -> bool:
        """The caller gives up on it (e.g. its own wait timed out): False when it is done or being completed."""
        if not self.claim():
            return False
        return super().cancel()

    @classmethod
    def failed(cls, name: str, exc: BaseException, source: str = "",
               priority: Priority = Priority.NORMAL) -> CommandStatus:
        """A status that never reached the queue (refused, or no link): ``exc`` is why."""
        status = cls(name, source, priority)
        status.set_exception(exc)
        return status

    @classmethod
    def done_now(cls, name: str, value: object = None, source: str = "", written: bool = True,
                 priority: Priority = Priority.NORMAL) -> CommandStatus:
        """A status completed at once (a command written on the caller's thread, or nothing to do)."""
        status = cls(name, source, priority)
        if written:
            status.mark_written()
        status.set_result(value)
        return status


@dataclass(order=True)
class _Entry:
    priority: int
    seq: int
    status: CommandStatus = field(compare=False)
    write: Callable[[CommandStatus], None] = field(compare=False)  # puts the bytes on the wire (queue thread)
    exclusive: bool = field(compare=False)
    timeout_s: float = field(compare=False)


class CommandQueue:
    """See the module docstring. ``periodic`` (e.g. the heartbeat) is called by the queue's thread every
    ``period_s`` while the queue runs, ahead of every queued command but the e-stop; ``realtime_priority`` asks
    the OS for round-robin scheduling. ``on_timeout(status)`` runs on the queue's thread when an exclusive
    command's reply did not come in time (e.g. to resync the device's parser) and returns the exception the
    status fails with (None: a plain TimeoutError)."""

    def __init__(self, name: str, *, periodic: Callable[[], None] | None = None, period_s: float = 0.1,
                 realtime_priority: int | None = None,
                 on_timeout: Callable[[CommandStatus], BaseException | None] | None = None,
                 idle_exit_s: float | None = None) -> None:
        self.name = name
        # With no periodic: the thread ends after this long with nothing to do, and the next submit starts it
        # again (a device whose commands are rare, e.g. the FES start, keeps no idle thread).
        self.idle_exit_s = idle_exit_s if periodic is None else None
        self.periodic = periodic
        self.period_s = period_s
        self.realtime_priority = realtime_priority
        self.on_timeout = on_timeout
        self._heap: list[_Entry] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._in_flight: _Entry | None = None
        self._in_flight_deadline = 0.0
        self._thread: threading.Thread | None = None
        self._closed = True  # until start(): a command submitted to a queue not running fails at once
        self.written_total = 0
        self.realtime = False  # whether the OS granted realtime_priority to the queue's thread

    # ------------------------------------------------------------------ any thread
    def submit(self, name: str, write: Callable[[CommandStatus], None], *, source: str = "",
               priority: Priority = Priority.NORMAL, exclusive: bool = True, timeout_s: float = 1.0) -> CommandStatus:
        """Queue one command. ``write(status)`` runs on the queue's thread and writes its bytes; for an
        ``exclusive`` command, whoever reads the reply claims ``status`` and completes it (resolve / fail), else
        the queue claims and fails it after ``timeout_s`` (see ``on_timeout``). A non-exclusive command is done
        once written."""
        status = CommandStatus(name, source, priority)
        status.timeout_s = timeout_s if exclusive else None
        with self._cond:
            if self._closed:
                status.set_exception(CommandQueueClosed(f"{self.name}: {name} not sent, the device is not running"))
                return status
            heapq.heappush(self._heap, _Entry(int(priority), next(self._seq), status, write, exclusive, timeout_s))
            self._cond.notify()
            if self._thread is None:  # it ended while idle (idle_exit_s)
                self._spawn()
        return status

    def _spawn(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-commands", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        """Accepting commands (its thread may be resting: idle_exit_s)."""
        return not self._closed

    def start(self) -> None:
        with self._cond:
            self._closed = False
            if self._thread is None or not self._thread.is_alive():
                self._spawn()

    def close(self, reason: str = "the device is closing", error: BaseException | None = None) -> None:
        """Stop the thread; every command not yet done fails with ``error`` (default CommandQueueClosed)."""
        with self._cond:
            self._closed = True
            pending, self._heap = self._heap, []
            if self._in_flight is not None:
                pending.append(self._in_flight)
                self._in_flight = None
            self._cond.notify()
        for entry in pending:  # a reply may be completing the one in flight: whoever claims it first decides
            entry.status.settle(exc=error if error is not None
                                else CommandQueueClosed(f"{self.name}: {entry.status.name} not sent, {reason}"))
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(1.0)

    def fail_in_flight(self, exc: BaseException) -> None:
        """The link was lost: the command awaiting its reply fails now."""
        with self._cond:
            entry, self._in_flight = self._in_flight, None
            self._cond.notify()
        if entry is not None:
            entry.status.settle(exc=exc)  # its reply may be arriving on the reader's thread

    @property
    def in_flight(self) -> CommandStatus | None:
        entry = self._in_flight
        return entry.status if entry is not None else None

    def pending(self) -> int:
        return len(self._heap)

    # ------------------------------------------------------------------ the queue's thread
    def _wake(self, _status: object = None) -> None:
        with self._cond:
            self._cond.notify()

    def _run(self) -> None:
        if self.realtime_priority is not None:
            from app.devices.realtime import request_realtime

            self.realtime = request_realtime(self.realtime_priority)
        next_periodic = time.monotonic() + self.period_s
        idle_since = time.monotonic()
        while True:
            expired: _Entry | None = None
            with self._cond:
                entry = None
                run_periodic = False
                while True:
                    if self._closed:
                        return
                    now = time.monotonic()
                    if self.idle_exit_s is not None:
                        if self._heap or self._in_flight is not None:
                            idle_since = now
                        elif now - idle_since >= self.idle_exit_s:
                            if self._thread is threading.current_thread():
                                self._thread = None  # the next submit starts another
                            return
                    if self._in_flight is not None and (self._in_flight.status.done()
                                                        or now >= self._in_flight_deadline):
                        expired, self._in_flight = self._in_flight, None
                        if expired.status.done():
                            expired = None
                        else:
                            break  # its timeout is handled outside the lock (it may write a resync)
                    due = self.periodic is not None and now >= next_periodic
                    if due and not (self._heap and self._heap[0].priority < Priority.HEARTBEAT):
                        run_periodic = True  # the heartbeat goes before everything but an e-stop
                        break
                    entry = self._next_ready()
                    if entry is not None:
                        break
                    wake = next_periodic if self.periodic is not None else now + (self.idle_exit_s or 1.0)
                    if self._in_flight is not None:
                        wake = min(wake, self._in_flight_deadline)
                    self._cond.wait(max(0.0, wake - now))
                if entry is not None and entry.exclusive:
                    self._in_flight = entry
                    self._in_flight_deadline = time.monotonic() + entry.timeout_s
                    entry.status.add_done_callback(self._wake)  # the reply frees the queue at once
            if expired is not None:
                self._expire(expired)
                continue
            if run_periodic:
                next_periodic = max(next_periodic + self.period_s, time.monotonic())
                try:
                    self.periodic()  # type: ignore[misc]
                except Exception:
                    log.exception("%s: periodic command failed", self.name)
                continue
            if entry is not None:
                self._write(entry)

    def _next_ready(self) -> _Entry | None:
        """The highest-priority entry that may go now (an exclusive one waits for the one in flight)."""
        if not self._heap:
            return None
        if self._in_flight is None or not self._heap[0].exclusive:
            return heapq.heappop(self._heap)
        # Something exclusive is in flight: a non-exclusive entry behind the head (e-stop, handshake) may pass.
        for i, entry in enumerate(self._heap):
            if not entry.exclusive:
                self._heap.pop(i)
                heapq.heapify(self._heap)
                return entry
        return None

    def _expire(self, entry: _Entry) -> None:
        if not entry.status.claim():  # the reply (or the link lost, or a cancel) came first: its outcome stands
            return
        exc: BaseException | None = None
        if self.on_timeout is not None:
            try:
                exc = self.on_timeout(entry.status)
            except Exception:
                log.exception("%s: timeout handler failed", self.name)
        entry.status.fail(exc if exc is not None else TimeoutError(
            f"{self.name} did not acknowledge {entry.status.name} within {entry.timeout_s:.2f} s"))

    def _write(self, entry: _Entry) -> None:
        status = entry.status
        if status.done():  # cancelled by its caller meanwhile
            self._release(entry)
            return
        try:
            entry.write(status)
        except Exception as exc:  # the caller learns why through its status (unless it cancelled meanwhile)
            self._release(entry)
            status.settle(exc=exc)
            return
        if not status.written:
            status.mark_written()
        self.written_total += 1
        if not entry.exclusive:
            status.settle(None)  # its caller may have cancelled it meanwhile

    def _release(self, entry: _Entry) -> None:
        with self._cond:
            if self._in_flight is entry:
                self._in_flight = None
