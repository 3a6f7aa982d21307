"""The GUI thread is watched (issue #37): a stall of the window's thread while the robot is ON or stimulation runs
is an alarm, and a longer one puts the devices in the safe state, because the e-stop button and F12 are read by
that thread and cannot act while it stalls.

* The window's thread *beats*: a Qt timer there (:class:`app.ui.gui_heartbeat.GuiHeartbeat`) calls
  :meth:`GuiWatch.beat` every ``BEAT_PERIOD_S``. A beat is a time stamp (and, while stimulating, a message to
  the FES guardian: :meth:`app.devices.fes_guardian.FesGuardian.window_beat`); it never waits.
* A thread of the application's own (``gui-watch``; it needs neither the window's thread nor anything that
  thread may hold) looks every ``POLL_S`` at the age of the last beat. While something drives the patient
  (:func:`what_drives`: the LINarm ON, or FES stimulating):

  - no beat for ``ALARM_AFTER_S``: a WARNING alarm, "the window stopped responding", and a ``gui_stall`` event;
  - no beat for ``SAFE_AFTER_S``: a STOP alarm that says why; the fault policy puts the devices in the safe state
    (robot IDLE, FES Stop, the script stopped) from this thread, and the record has the alarm, the fault and
    each stop action;
  - the window responding again: a ``gui_resumed`` event with the stall's length; a warning that did not reach
    the safe state is acknowledged by itself (as a device's "resumed" silence warning is).

  Nothing drives: nothing is judged (a window busy for a second while nothing moves or stimulates harms nobody),
  and the thread rests after ``IDLE_EXIT_S`` (a beat that sees something driving starts it again).
* Behind it, the FES guardian (another process) stops stimulation itself when the window's beats stop for
  ``GUARDIAN_WINDOW_TRIP_S`` while it is armed: a frozen process, or this thread unable to act, is covered too.

The bounds (docs/fes.md, "The GUI thread is watched"; the normal stalls they leave room for were measured with
bench/bench_window.py ``--stalls``): ALARM_AFTER_S and SAFE_AFTER_S below. Qt-free: the heartbeat's timer lives
in app/ui.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from app.core import journal, streams

if TYPE_CHECKING:  # the supervisor is a QObject; this module imports nothing of Qt (docs/decisions.md)
    from app.manager import LinarmppManager
    from app.safety.supervisor import Alarm, SafetySupervisor

log = logging.getLogger(__name__)

BEAT_PERIOD_S = 0.05  # the window's heartbeat timer
POLL_S = 0.02  # how often the watch looks at the last beat's age
# Longest normal stall of the window's thread measured (bench_window.py --stalls, every signal in the graphs, FES
# stimulating, the arm moving): see docs/fes.md. The alarm comes well above it, the safe state well within the
# 1 s the issue allows for Stop on the wire.
ALARM_AFTER_S = 0.35
SAFE_AFTER_S = 0.7
# The guardian's own bound on the window's silence (armed only, i.e. while stimulating): behind this watch, so
# later than SAFE_AFTER_S, still within the 1 s.
GUARDIAN_WINDOW_TRIP_S = 0.9
IDLE_EXIT_S = 1.0  # nothing driving this long: the watch's thread ends (a beat starts it again)


def what_drives(manager: LinarmppManager) -> str:
    """What a stall of the window would leave unattended: 'the robot is ON', 'stimulation runs', both, or ''."""
    parts = []
    state = manager.bus.latest(streams.LINARM_STATE) if manager.driver(streams.LINARM) is not None else None
    from app.wire.linarm_protocol import ControlState

    if state is not None and getattr(state, "controlState", None) == int(ControlState.ON_CTRL_STATE):
        parts.append("the robot is ON")
    fes = manager.driver(streams.FES)
    if fes is not None and bool(getattr(fes, "stimulating", False)):
        parts.append("stimulation runs")
    return " and ".join(parts)


class GuiWatch:
    """The watch of one window's thread (see the module docstring). ``beat`` from the window's thread; the rest
    from any thread. ``check(now)`` is the judgement (the watch thread calls it every POLL_S; tests call it on a
    virtual clock)."""

    def __init__(self, supervisor: SafetySupervisor, drives: Callable[[], str], *,
                 alarm_after_s: float = ALARM_AFTER_S, safe_after_s: float = SAFE_AFTER_S,
                 clock: Callable[[], float] = time.monotonic, poll_s: float = POLL_S,
                 idle_exit_s: float = IDLE_EXIT_S) -> None:
        if not 0 < alarm_after_s <= safe_after_s:
            raise ValueError("the alarm must come before (or with) the safe state")
        self.supervisor = supervisor
        self.drives = drives
        self.alarm_after_s = alarm_after_s
        self.safe_after_s = safe_after_s
        self.clock = clock
        self.poll_s = poll_s
        self.idle_exit_s = idle_exit_s
        self.beat_listeners: list[Callable[[float], None]] = []  # e.g. the FES guardian's window beat
        self._last_beat = clock()
        self._window_thread: int | None = None  # the beating thread: its stack is logged with a warning
        self._lock = threading.Lock()  # the thread's start and stop
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False
        # the stall being judged: its alarms, what was driving, its longest age
        self._warning: Alarm | None = None
        self._safe_state = False
        self._what = ""
        self._longest = 0.0
        self.stalls: list[float] = []  # every judged stall's length (s), for the record and tests

    # ------------------------------------------------------------------ the window's thread
    def beat(self, now: float | None = None) -> None:
        """The window's thread is alive (its timer ran). Starts the watch's thread when something drives."""
        now = self.clock() if now is None else now
        self._last_beat = now
        self._window_thread = threading.get_ident()
        for listener in self.beat_listeners:
            try:
                listener(now)
            except Exception:  # a listener must never stall the window
                log.exception("gui watch: a beat listener failed")
        if self._thread is None and not self._closed:
            try:
                driving = self.drives()
            except Exception:
                driving = ""
            if driving:
                self.start()

    @property
    def last_beat(self) -> float:
        """When the window's thread last beat (the watch's clock)."""
        return self._last_beat

    @property
    def running(self) -> bool:
        thread = self._thread
        return thread is not None and thread.is_alive()

    # ------------------------------------------------------------------ the watch
    def check(self, now: float | None = None) -> None:
        """Judge the last beat's age (any thread; see the module docstring)."""
        now = self.clock() if now is None else now
        age = now - self._last_beat
        if age < self.alarm_after_s:
            if self._warning is not None or self._safe_state:
                self._resumed()
            return
        if self._safe_state:
            self._longest = max(self._longest, age)
            return
        driving = self._drives()
        if not driving:
            return  # nothing moves or stimulates (or no longer does): a busy window harms nobody
        what = self._what = self._what or driving
        self._longest = max(self._longest, age)
        from app.safety.supervisor import AlarmLevel  # loaded with the supervisor already
        if self._warning is None:
            text = f"The window stopped responding ({age:.2f} s without its heartbeat) while {what}"
            self.supervisor.record(journal.GUI_STALL, stalled_s=round(age, 3), driving=what)
            self._warning = self.supervisor.raise_alarm(AlarmLevel.WARNING, "window", text, key="gui stall")
            self._log_window_stack()
        if age >= self.safe_after_s:
            self._safe_state = True
            text = (f"The window did not respond for {age:.2f} s while {what}: the robot was set to IDLE and "
                    "stimulation stopped, because the emergency-stop button and F12 could not act "
                    "(the script API's emergency stop still could)")
            self.supervisor.record(journal.GUI_STALL_SAFE_STATE, stalled_s=round(age, 3), driving=what)
            # The fault policy, connected directly to the alarm, runs the stop actions here, on this thread.
            self.supervisor.raise_alarm(AlarmLevel.STOP, "window", text, key="gui stall safe state")

    def _log_window_stack(self) -> None:
        """Where the window's thread is now, in the log (for whoever finds the stall's cause; not in the alarm's
        text). A thread in Qt's C++ code without the interpreter lock shows its last Python frame."""
        import sys
        import traceback

        frame = sys._current_frames().get(self._window_thread) if self._window_thread is not None else None
        if frame is not None:
            stack = "".join(traceback.format_stack(frame)[-10:])
            log.warning("gui watch: the window's thread during the stall:\n%s", stack)

    def _drives(self) -> str:
        try:
            return self.drives()
        except Exception:
            log.exception("gui watch: what drives could not be read")
            return "a device may be driving"

    def _resumed(self) -> None:
        longest, warning = self._longest, self._warning
        self.stalls.append(longest)
        self.supervisor.record(journal.GUI_RESUMED, stalled_s=round(longest, 3), safe_state=self._safe_state)
        log.warning("gui watch: the window responds again after %.2f s%s", longest,
                    " (the devices were put in the safe state)" if self._safe_state else "")
        if warning is not None and not self._safe_state:
            warning.text = f"{warning.text} (responding again after {longest:.2f} s)"
            self.supervisor.acknowledge(warning.ident, operator="window responding again")
        self._warning, self._safe_state, self._what, self._longest = None, False, "", 0.0

    # ------------------------------------------------------------------ the thread
    def start(self) -> None:
        with self._lock:
            if self._closed or (self._thread is not None and self._thread.is_alive()):
                return
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="gui-watch", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        idle_since: float | None = None
        try:
            while not self._stop.wait(self.poll_s):
                now = self.clock()
                try:
                    self.check(now)
                except Exception:  # the watch must outlive a bug in what it calls
                    log.exception("gui watch: a check failed")
                stalled = self._warning is not None or self._safe_state
                if stalled or self._drives():
                    idle_since = None
                elif idle_since is None:
                    idle_since = now
                elif now - idle_since >= self.idle_exit_s:
                    break
        finally:
            with self._lock:
                if self._thread is threading.current_thread():
                    self._thread = None

    def close(self, timeout_s: float = 1.0) -> None:
        """End the watch (the window closes, or the application ends): no judgement follows."""
        with self._lock:
            self._closed = True
            self._stop.set()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
