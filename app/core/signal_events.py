"""SIGTERM, SIGINT and SIGHUP as events (issue #25), the window and the headless runner alike.

A signal handler may run between any two bytecodes of the main thread — in the middle of a write that holds a
transport's lock, or of the previous handler. So the handlers here do nothing: the interpreter's C-level
handler writes the signal's number to a wake-up socket (``signal.set_wakeup_fd``), and a dedicated thread
reading that socket runs ``on_signal(signum)`` once, for the first signal, outside any handler. Later
signals of a burst are counted and otherwise ignored. The thread acts even while the main thread is blocked
(the Qt loop in C, a long wait), and Python never raises KeyboardInterrupt at an arbitrary point (which
aborted the headless runner with "QThread destroyed" while threads still ran).

If the process has not ended ``exit_deadline_s`` after the first signal (a hang in the shutdown, or in
``on_signal`` itself), a timer thread brings the devices to a safe state once more and ends the process
with ``os._exit`` — the FES guardian (app.devices.fes_guardian) sends Stop when the process is gone, and
the robot's controller idles on its own host watchdog.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import signal
import socket
import sys
import threading
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

HANDLED_SIGNALS: tuple[int, ...] = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, name))
EXIT_DEADLINE_S = 10.0


def exit_code_for(signum: int) -> int:
    """The shell's convention for a process ended by a signal (SIGINT 130, SIGTERM 143, SIGHUP 129),
    also after a clean shutdown, so a caller can tell it was stopped from outside."""
    return 128 + int(signum)


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def _record(_signum: int, _frame: Any) -> None:
    """The Python-level handler: nothing. The wake-up socket already carries the signal to the thread."""


class SignalEvents:
    """While installed, the first of SIGTERM/SIGINT/SIGHUP calls ``on_signal(signum)`` once, on a thread
    of its own. Only from the main thread (Python's rule for signal handlers); elsewhere it does nothing."""

    def __init__(self, on_signal: Callable[[int], None], *, exit_deadline_s: float | None = EXIT_DEADLINE_S,
                 last_resort: Callable[[int], None] | None = None) -> None:
        self._on_signal = on_signal
        self._exit_deadline_s = exit_deadline_s
        self._last_resort = last_resort
        self.received: int | None = None  # the first signal's number, set as it arrives (before on_signal runs)
        self.count = 0
        self._previous: dict[int, Any] = {}
        self._previous_wakeup_fd = -1
        self._sockets: tuple[socket.socket, socket.socket] | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._handled = threading.Event()
        self._backstop: threading.Timer | None = None

    @property
    def installed(self) -> bool:
        return self._thread is not None

    def install(self) -> SignalEvents:
        if threading.current_thread() is not threading.main_thread() or self._thread is not None:
            return self
        reader, writer = socket.socketpair()
        reader.setblocking(False)
        writer.setblocking(False)
        self._sockets = (reader, writer)
        self._thread = threading.Thread(target=self._watch, name="signal events", daemon=True)
        self._thread.start()
        self._previous_wakeup_fd = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        for signum in HANDLED_SIGNALS:
            try:
                self._previous[signum] = signal.signal(signum, _record)
            except (OSError, ValueError):  # e.g. SIGHUP where the platform has none
                continue
        return self

    def remove(self) -> None:
        """Restore the previous handlers and end the thread (after ``on_signal`` returned, if it runs). Once a
        signal was handled the process is closing on it: the rest of a burst is ignored from here on (the
        default action would kill the process in the middle of its shutdown)."""
        if self._thread is None:
            return
        for signum, handler in self._previous.items():
            with contextlib.suppress(OSError, ValueError, TypeError):
                signal.signal(signum, handler if self.received is None else signal.SIG_IGN)
        self._previous = {}
        with contextlib.suppress(ValueError):
            signal.set_wakeup_fd(self._previous_wakeup_fd)
        self._closing.set()
        if self._backstop is not None:
            self._backstop.cancel()
            self._backstop.join(timeout=1.0)
            self._backstop = None
        assert self._sockets is not None
        with contextlib.suppress(OSError):
            self._sockets[1].send(b"\0")  # wakes the thread (0 is no signal)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        for sock in self._sockets:
            sock.close()
        self._thread = None
        self._sockets = None

    def __enter__(self) -> SignalEvents:
        return self.install()

    def __exit__(self, *_exc: object) -> None:
        self.remove()

    def wait(self, timeout_s: float | None = None) -> bool:
        """True once ``on_signal`` has run for the first signal."""
        return self._handled.wait(timeout_s)

    # ------------------------------------------------------------------ the thread
    def _watch(self) -> None:
        assert self._sockets is not None
        reader = self._sockets[0]
        while True:
            select.select([reader], [], [])
            try:
                data = reader.recv(4096)
            except BlockingIOError:
                continue
            except OSError:
                return
            if self._closing.is_set():  # removed: whatever else arrived, the process is handling it
                return
            signals = [b for b in data if b]
            self.count += len(signals)
            if not signals or self.received is not None:
                continue
            signum = signals[0]
            self.received = signum
            if self._exit_deadline_s is not None:  # its own thread: on_signal itself may be what hangs
                self._backstop = threading.Timer(self._exit_deadline_s, self._exit_now)
                self._backstop.name = "signal backstop"
                self._backstop.daemon = True
                self._backstop.start()
            log.warning("%s received: bringing the devices to a safe state and closing", signal_name(signum))
            try:
                self._on_signal(signum)
            except Exception:
                log.exception("closing on %s failed", signal_name(signum))
            finally:
                self._handled.set()
            if self._closing.is_set():
                return

    def _exit_now(self) -> None:
        if self._closing.is_set():
            return
        signum = self.received or signal.SIGTERM
        log.critical("the application did not end within %.0f s of %s: ending it now", self._exit_deadline_s or 0,
                     signal_name(signum))
        if self._last_resort is not None:
            try:
                self._last_resort(signum)
            except Exception:
                log.exception("last safe state before the forced exit failed")
        with contextlib.suppress(Exception):
            logging.shutdown()
            sys.stderr.flush()
        os._exit(exit_code_for(signum))
