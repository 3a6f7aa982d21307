"""The real-time process's CPU priority (#37, #38).

The process that drives the devices — the window's GUI thread (the e-stop button, F12, the GUI watch's heartbeat),
the drivers' threads, the bus, the therapy thread, the simulators it starts — asks Linux for a higher priority
than an ordinary program's (nice ``REALTIME_NICE``) when it starts driving, where the system allows it: as root,
with CAP_SYS_NICE, or with an ``RLIMIT_NICE`` the site grants (docs/decisions.md "The real-time process's
priority": one line in ``/etc/security/limits.d/``). Why: on a busy PC (an antivirus scan, a second program
using both cores) the window's turns and the drivers' heartbeats otherwise share the CPU equally with every busy
thread; measured on the 2-core machine with two CPU hogs beside a second test worker, the window then missed its
heartbeat for 0.5-1.2 s, which the GUI watch rightly answers by stopping the therapy (0.7 s). The heavy work's
worker process sets its own, lower priority (``app/worker``: nice 10), whatever it inherits.

Linux schedules each session as a group of its own (autogroup, on by default where the process is not in a cgroup
of its own), and a thread's nice value then only counts against the threads of its own group: against a program
started in another session — a second terminal's job, the script's kernel, the heavy work's worker — the window's
threads at nice -5 got no more CPU than at 0 (measured with four CPU hogs in other sessions on the 2-core machine: a
thread working 3 ms of every 5 completed its period in 9.1 ms at p50 either way; 5.1 ms with its group at -5). So the
process's group is raised too (``/proc/self/autogroup``); the other processes of the session it was started from
(the shell that started it) share that group.

Where the system does not allow it, nothing else changes: the process runs at its normal priority, the log says
so once, and the GUI watch still stops the therapy safely if the window is starved. Linux's nice value is a
per-thread attribute: every thread the process has is raised, and threads made later inherit their creator's.
Qt-free."""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

REALTIME_NICE = -5  # a quarter of the range towards the top: ahead of ordinary programs (0), far from the kernel's own
SCRIPT_NICE = 0  # a script's processes: an ordinary program's, below the real-time process (app/scripting/warden.py)
_TASKS = Path("/proc/self/task")
_AUTOGROUP = Path("/proc/self/autogroup")  # "/autogroup-123 nice 0" (Linux, CONFIG_SCHED_AUTOGROUP)


@dataclass(frozen=True)
class PriorityOutcome:
    raised: bool
    nice: int  # the calling thread's nice value after the attempt
    sentence: str  # for the log (and whoever asks why the window was starved)


_lock = threading.Lock()
_outcome: PriorityOutcome | None = None


def _thread_ids() -> list[int]:
    try:
        return [int(p.name) for p in _TASKS.iterdir() if p.name.isdigit()]
    except OSError:  # not Linux: the calling thread only
        return [0]


def group_nice() -> int | None:
    """This process's scheduling group's nice value (Linux's autogroup), None where the system has none."""
    try:
        words = _AUTOGROUP.read_text(encoding="ascii").split()
        return int(words[words.index("nice") + 1])
    except (OSError, ValueError, IndexError):
        return None


def _raise_group(nice: int) -> bool | None:
    """Raise this process's scheduling group to ``nice`` (never lower it). None: no group here; False: refused."""
    current = group_nice()
    if current is None:
        return None
    if current <= nice:
        return True
    try:
        _AUTOGROUP.write_text(str(nice), encoding="ascii")
    except OSError:  # EPERM without CAP_SYS_NICE / RLIMIT_NICE
        return False
    return group_nice() == nice


def raise_for_real_time(nice: int = REALTIME_NICE) -> PriorityOutcome:
    """Raise every thread of this process to ``nice`` (never lower one already higher). Once per process: later
    calls return the first outcome (threads made since inherit it from their creator)."""
    global _outcome
    with _lock:
        if _outcome is not None:
            return _outcome
        if not hasattr(os, "setpriority"):
            _outcome = PriorityOutcome(False, 0, "the real-time process runs at normal priority (not supported here)")
            log.info(_outcome.sentence)
            return _outcome
        raised = denied = 0
        for tid in _thread_ids():
            try:
                if os.getpriority(os.PRIO_PROCESS, tid) > nice:
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
                    raised += 1
            except PermissionError:
                denied += 1
                break  # the same answer for every thread
            except OSError:  # the thread ended meanwhile
                continue
        current = os.getpriority(os.PRIO_PROCESS, 0)
        if denied:
            sentence = (f"the real-time process runs at normal priority (nice {current}): this user may not raise "
                        f"it to {nice}; on a busy PC the window may then be starved and the GUI watch stop the "
                        "therapy (see the set-up notes: RLIMIT_NICE)")
            _outcome = PriorityOutcome(False, current, sentence)
        else:
            group = _raise_group(nice)
            where = {None: "", True: ", its scheduling group too",
                     False: f", but not its scheduling group (nice {group_nice()}): programs of other sessions "
                            "share the CPU equally with it"}[group]
            _outcome = PriorityOutcome(current <= nice, current,
                                       f"the real-time process runs at raised priority (nice {current}{where})")
        log.info(_outcome.sentence)
        return _outcome


def no_thread_below_this_one() -> None:
    """Every thread of this process at the calling thread's CPU priority at least, before it ends (Linux; where the
    system allows it, as the raise above). Whichever thread ends last unmaps the process's memory, at its own
    priority: a library's helper at nice 19 (Mesa's shader-cache writers) made the window's end take 1.5-3 s on a busy
    2-core machine. The helpers have nothing left to do: the process is ending."""
    if not hasattr(os, "sched_setscheduler"):
        return
    own = os.getpriority(os.PRIO_PROCESS, 0)
    low_policies = {getattr(os, name) for name in ("SCHED_BATCH", "SCHED_IDLE") if hasattr(os, name)}
    for tid in _thread_ids():
        try:
            if os.sched_getscheduler(tid) in low_policies:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            if os.getpriority(os.PRIO_PROCESS, tid) > own:
                os.setpriority(os.PRIO_PROCESS, tid, own)
        except OSError:  # not allowed (no CAP_SYS_NICE / RLIMIT_NICE), or the thread ended meanwhile
            continue


def _reset_for_tests() -> None:
    global _outcome
    with _lock:
        _outcome = None


__all__ = ["REALTIME_NICE", "SCRIPT_NICE", "PriorityOutcome", "group_nice", "no_thread_below_this_one",
           "raise_for_real_time"]
