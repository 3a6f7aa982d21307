"""The FES dead man's switch (issue #25): a small process that sends the stimulator Stop when the application
stops serving it — frozen, stopped (SIGSTOP), deadlocked or killed.

ScienceMode 1 has no watchdog: a RehaStim 1 keeps running its channel list until it receives Stop, whatever
happens to the PC. ScienceMode 2 has one, but it waits 1.2 s without a valid packet. So the FES driver
(app.devices.rehastim) runs this guardian for both versions, as its own process, started with the driver
(in a session of its own: a Ctrl-C or a stop of the app's process group does not reach it):

* while stimulating, the driver *arms* it: it hands over a duplicate of the link's file descriptor (the
  serial port, or the simulator's loopback socket; SCM_RIGHTS over a Unix socket pair) and the bytes of
  that protocol's Stop;
* the driver's own thread — the one that writes every update to the stimulator — sends a heartbeat every
  ``HEARTBEAT_PERIOD_S``; stopping stimulation *disarms* it (the duplicate descriptor is closed at once, so
  the link closes when the driver closes it);
* armed, the guardian writes Stop (three times, ``STOP_REPEAT_GAP_S`` apart) to the link when no heartbeat
  came for ``TRIP_AFTER_S``, or at once when the application's end of the socket pair closes (the process
  died, however) or it is told to end (SIGTERM) — then tells the driver, which raises the fault when it runs
  again.

* the window's thread beats too (``WINDOW_BEAT``, app.gui_watch, #37): armed, the guardian also trips when the
  window falls silent for the bound the beats carry (0.9 s) — a frozen window, or a GUI watch unable to act;
* the guardian is itself watched (#37): its end of the socket pair closing while the application did not close
  its own is its death, which the driver sees with ``tripped``/``dead``/``death`` (Stop, an alarm) and repairs
  with ``restart``.

The bound: Stop leaves the guardian at most ``TRIP_AFTER_S`` + ``POLL_S`` after the application's last
heartbeat, i.e. 0.31 s; with the guardian's own scheduling on a loaded machine, stimulation ends within
0.5 s (docs/fes.md, "Dead man's switch"). 0.3 s is six missed heartbeats. The driver's thread runs real-time
(``FesDriver.realtime_priority``, where the OS grants it): at normal priority, with the cores busy, it was measured
runnable and not run for 155-511 ms, which tripped the guardian (#38, session 12); real-time, its longest gap was
97 ms.

This file runs as a script (``python -I -S fes_guardian.py FD PARENT_PID TRIP_AFTER_S``) and imports only the
standard library, so it starts in a few milliseconds and depends on nothing of the application.
"""

from __future__ import annotations

import array
import contextlib
import logging
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time

TRIP_AFTER_S = 0.3
HEARTBEAT_PERIOD_S = 0.05
POLL_S = 0.01
STOP_REPEATS = 3
STOP_REPEAT_GAP_S = 0.02
WRITE_TIMEOUT_S = 0.2

# Messages on the socket pair (SOCK_SEQPACKET: one send, one message)
ARM, HEARTBEAT, DISARM, QUIT, TRIPPED, READY = b"A", b"H", b"D", b"Q", b"T", b"R"
# The window's heartbeat (#37, app.gui_watch): W + its bound in seconds (ASCII) watches the window from then on;
# w stops watching it (the window closed). Armed and watching, a window silent for its bound trips the guardian.
WINDOW_BEAT, WINDOW_OFF = b"W", b"w"
START_TIMEOUT_S = 5.0

log = logging.getLogger(__name__)


# ================================================================================ the guardian process
def _write_all(fd: int, data: bytes) -> None:
    """Write ``data`` to ``fd`` (non-blocking or not; the descriptor's flags are shared with the app's)."""
    deadline = time.monotonic() + WRITE_TIMEOUT_S
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise
            select.select([], [fd], [], 0.01)


def send_stop(fd: int, stop: bytes) -> str:
    """Stop, repeated; '' when it was written, else why not."""
    problem = ""
    for i in range(STOP_REPEATS):
        if i:
            time.sleep(STOP_REPEAT_GAP_S)
        try:
            _write_all(fd, stop)
            problem = ""
        except OSError as exc:
            problem = str(exc)
    return problem


def _receive(control: socket.socket) -> tuple[bytes, list[int]]:
    """One message and the descriptors it carries, without waiting (socket.recv_fds ignores its flags)."""
    fds = array.array("i")
    data, ancillary, _flags, _addr = control.recvmsg(4096, socket.CMSG_SPACE(4 * fds.itemsize), socket.MSG_DONTWAIT)
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            fds.frombytes(payload[:len(payload) - len(payload) % fds.itemsize])
    return data, list(fds)


def guard(control: socket.socket, trip_after_s: float = TRIP_AFTER_S) -> int:
    """The guardian's loop; returns when the application closed its end (or said QUIT, or SIGTERM)."""
    link_fd: int | None = None
    stop = b""
    last_heartbeat = time.monotonic()
    window_bound = 0.0  # 0: the window is not watched (no window, or it closed)
    last_window = time.monotonic()
    ending = [False]

    def on_sigterm(*_args: object) -> None:
        ending[0] = True  # a flag only: the loop acts on it within POLL_S

    signal.signal(signal.SIGTERM, on_sigterm)
    for name in ("SIGINT", "SIGHUP"):  # the app's terminal and session are not ours to end with
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)

    def disarm() -> None:
        nonlocal link_fd
        if link_fd is not None:
            with contextlib.suppress(OSError):
                os.close(link_fd)
            link_fd = None

    def trip(why: str) -> None:
        if link_fd is None:
            return
        problem = send_stop(link_fd, stop)
        with contextlib.suppress(OSError):
            control.send(TRIPPED + (f"{why}; Stop could not be written: {problem}" if problem else why).encode())
        disarm()

    while True:
        try:
            ready = select.select([control], [], [], POLL_S)[0]
        except InterruptedError:
            ready = []
        gone = False
        while ready:  # every message waiting, before judging the heartbeat's age (we may have been descheduled)
            try:
                data, fds = _receive(control)
            except BlockingIOError:
                break
            except OSError:
                data, fds = b"", []
            if not data:
                gone = True
                break
            kind, payload = data[:1], data[1:]
            if kind == HEARTBEAT:
                last_heartbeat = time.monotonic()
            elif kind == WINDOW_BEAT:
                last_window = time.monotonic()
                with contextlib.suppress(ValueError):
                    window_bound = max(0.0, float(payload.decode("ascii", "replace")))
            elif kind == WINDOW_OFF:
                window_bound = 0.0
            elif kind == ARM and fds:
                disarm()
                link_fd, stop, last_heartbeat = fds[0], payload, time.monotonic()
                last_window = max(last_window, last_heartbeat)  # a window frozen before the start gets its bound
                fds = fds[1:]
            elif kind == DISARM:
                disarm()
            elif kind == QUIT:
                disarm()
                return 0
            for extra in fds:
                os.close(extra)
        if gone or ending[0]:
            trip("the application ended while stimulating" if gone else "the guardian was told to end while armed")
            disarm()
            return 0
        silent = time.monotonic() - last_heartbeat
        if link_fd is not None and silent > trip_after_s:
            trip(f"no heartbeat from the application for {silent:.2f} s")
        window_silent = time.monotonic() - last_window
        if link_fd is not None and window_bound > 0 and window_silent > window_bound:
            trip(f"the window did not respond for {window_silent:.2f} s")


def main(argv: list[str]) -> int:
    fd, parent = int(argv[1]), int(argv[2])
    trip_after_s = float(argv[3]) if len(argv) > 3 else TRIP_AFTER_S
    del parent  # in the command line so that `ps` shows whose guardian this is
    control = socket.socket(fileno=fd)
    try:
        control.send(READY)
        return guard(control, trip_after_s)
    finally:
        control.close()


# ================================================================================ the application's side
class GuardianError(RuntimeError):
    pass


def available() -> bool:
    """Whether this platform can run the guardian (it passes the link's descriptor over a Unix socket)."""
    return all(hasattr(socket, name) for name in ("AF_UNIX", "SOCK_SEQPACKET", "send_fds", "CMSG_SPACE"))


class FesGuardian:
    """The driver's handle on its guardian process. ``arm``/``disarm`` from any thread; ``heartbeat`` from the
    driver's thread. Duck-types the little of ``subprocess.Popen`` that the manager's shutdown calls."""

    def __init__(self, trip_after_s: float = TRIP_AFTER_S) -> None:
        self.trip_after_s = trip_after_s
        self.proc: subprocess.Popen[bytes] | None = None
        self._control: socket.socket | None = None
        self._lock = threading.Lock()  # arm/disarm/close; the heartbeat takes no lock
        self._last_heartbeat = 0.0
        self._last_window_beat = 0.0
        self._last_look = 0.0
        self.armed = False
        # Watched like every other helper (#37): the guardian's end of the socket pair closing while we did not
        # close ours means it died (killed, crashed). ``death()`` says so once; ``restart()`` starts another.
        self._closing = False
        self._dead = ""
        self._death_reported = True  # nothing to report until it has died

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def alive(self) -> bool:
        return (self.proc is not None and not self._dead and self.proc.poll() is None
                and self._control is not None)

    def start(self) -> FesGuardian:
        self._closing = False
        self._dead = ""
        self._death_reported = True
        if not available():
            raise GuardianError("the FES guardian needs Unix sockets that pass descriptors (Linux, macOS)")
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-I", "-S", os.path.abspath(__file__), str(theirs.fileno()), str(os.getpid()),
                 repr(self.trip_after_s)],
                pass_fds=(theirs.fileno(),), start_new_session=True, stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, close_fds=True)
        except OSError as exc:
            ours.close()
            raise GuardianError(f"the FES guardian could not be started: {exc}") from exc
        finally:
            theirs.close()
        ready = select.select([ours], [], [], START_TIMEOUT_S)[0] and ours.recv(16) == READY
        if not ready:
            ours.close()
            self.proc.kill()
            self.proc.wait()
            raise GuardianError(f"the FES guardian did not start within {START_TIMEOUT_S:g} s")
        ours.setblocking(False)
        self._control = ours
        return self

    def arm(self, link_fd: int, stop: bytes) -> None:
        """From now on a silent driver (or a dead app) makes the guardian write ``stop`` to ``link_fd``."""
        with self._lock:
            control = self._control
            if control is None or self.proc is None or self.proc.poll() is not None:
                raise GuardianError("the FES guardian is not running")
            try:  # the socket stays non-blocking: a guardian that stopped reading must never stall the driver
                socket.send_fds(control, [ARM + stop], [link_fd])
            except OSError as exc:
                raise GuardianError(f"the FES guardian could not be armed: {exc}") from exc
            self.armed = True
            self._last_heartbeat = time.monotonic()

    def heartbeat(self, now: float | None = None) -> None:
        """Cheap, at most every HEARTBEAT_PERIOD_S; never blocks."""
        now = time.monotonic() if now is None else now
        control = self._control
        if not self.armed or control is None or now - self._last_heartbeat < HEARTBEAT_PERIOD_S:
            return
        self._last_heartbeat = now
        with contextlib.suppress(OSError):
            control.send(HEARTBEAT)

    def window_beat(self, bound_s: float, now: float | None = None) -> None:
        """The window's thread is alive (app.gui_watch, from that thread): armed, the guardian trips when these
        stop for ``bound_s``. At most every HEARTBEAT_PERIOD_S; never blocks."""
        now = time.monotonic() if now is None else now
        control = self._control
        if control is None or now - self._last_window_beat < HEARTBEAT_PERIOD_S * 0.8:
            return
        self._last_window_beat = now
        with contextlib.suppress(OSError):
            control.send(WINDOW_BEAT + f"{bound_s:.3f}".encode("ascii"))

    def window_off(self) -> None:
        """The window closed: its silence no longer trips the guardian."""
        control = self._control
        if control is not None:
            with contextlib.suppress(OSError):
                control.send(WINDOW_OFF)

    def disarm(self) -> None:
        with self._lock:
            self.armed = False
            control = self._control
            if control is not None:
                with contextlib.suppress(OSError):
                    control.send(DISARM)

    def tripped(self, now: float | None = None) -> str:
        """Why the guardian sent Stop since the last call ('' when it did not). Looks at most every
        HEARTBEAT_PERIOD_S (the driver calls it on every loop pass)."""
        now = time.monotonic() if now is None else now
        control = self._control
        if control is None or now - self._last_look < HEARTBEAT_PERIOD_S:
            return ""
        self._last_look = now
        why = ""
        while True:
            try:
                data = control.recv(4096)
            except BlockingIOError:
                return why
            except OSError as exc:  # ECONNRESET: the guardian died with messages unread
                self._died(f"its link to the application failed: {exc.strerror or exc}")
                return why
            if not data:  # its end closed: the guardian process ended
                self._died("")
                return why
            if data[:1] == TRIPPED:
                why = data[1:].decode(errors="replace")
                self.armed = False

    def _died(self, detail: str) -> None:
        """The guardian ended without being told to (``tripped`` saw its end of the socket pair close)."""
        if self._closing or self._dead:
            return
        self._dead = detail or "its end of the link to the application closed"
        self._death_reported = False
        self.armed = False

    @property
    def dead(self) -> bool:
        """It died (seen by :meth:`tripped`) and has not been restarted since."""
        return bool(self._dead)

    def death(self) -> str:
        """Why the guardian died, once ('' when it is alive, or its death was already reported). :meth:`tripped`
        is what notices the death; the driver sends Stop first and then asks this, which may wait up to 50 ms
        for the process's exit code."""
        if not self._dead or self._death_reported:
            return ""
        self._death_reported = True
        code = self.proc.poll() if self.proc is not None else None
        if code is None and self.proc is not None:  # its socket closes as it exits: reaped a moment later
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = self.proc.wait(0.05)
        how = (f"killed by signal {-code}" if code is not None and code < 0
               else f"exit code {code}" if code is not None else self._dead)
        return f"the FES guardian process (pid {self.pid}) ended unexpectedly ({how})"

    def restart(self) -> FesGuardian:
        """A new guardian process in place of one that died (or never started): the old one reaped, its socket
        closed. Raises GuardianError when the new one cannot start."""
        with self._lock:
            self.armed = False
            control, self._control = self._control, None
            if control is not None:
                control.close()
        old = self.proc
        if old is not None and old.poll() is None:
            old.kill()
        if old is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                old.wait(1.0)
        return self.start()

    def close(self, timeout_s: float = 1.0) -> None:
        """Disarm and end the guardian (the app's orderly end: stimulation was stopped before)."""
        self._closing = True  # its end closing from now on is no death
        with self._lock:
            self.armed = False
            control, self._control = self._control, None
            if control is not None:
                with contextlib.suppress(OSError):
                    control.send(QUIT)
                control.close()
        if self.proc is not None:
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout_s)

    # what app.manager's shutdown calls on a device's helper processes
    def terminate(self) -> None:
        self.close()

    def wait(self, timeout: float | None = None) -> int | None:
        return self.proc.wait(timeout) if self.proc is not None else None

    def poll(self) -> int | None:
        """As ``Popen.poll``: None while the guardian runs (a never-started guardian reads as ended, 0)."""
        return self.proc.poll() if self.proc is not None else 0

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()


if __name__ == "__main__":
    sys.exit(main(sys.argv))
