"""Real-time scheduling for the threads that keep a device's link alive (Qt-free)."""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

REALTIME_ENV = "LINARMPP_REALTIME"  # "0": never ask for real-time scheduling
_realtime_refused_logged = False


def request_realtime(priority: int) -> bool:
    """Ask the OS to run the calling thread round-robin real-time at ``priority`` (Linux: needs root,
    CAP_SYS_NICE or an RLIMIT_RTPRIO, e.g. ``@linarmpp - rtprio 20`` in /etc/security/limits.d). True when
    granted. Measured on a saturated 2-core machine: a normal thread waiting in select() for 10 ms was
    scheduled up to 170 ms late; a SCHED_RR one at most 13 ms late (docs/decisions.md, #16)."""
    global _realtime_refused_logged
    if os.environ.get(REALTIME_ENV) == "0" or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        # 0: this thread (Linux); RESET_ON_FORK: threads it starts (executors) run at normal priority
        os.sched_setscheduler(0, os.SCHED_RR | getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_param(priority))
        return True
    except (OSError, ValueError) as exc:
        if not _realtime_refused_logged:
            _realtime_refused_logged = True
            log.warning("real-time scheduling refused (%s): device links run at normal priority; grant "
                        "rtprio to the user for timing under load", exc)
        return False
