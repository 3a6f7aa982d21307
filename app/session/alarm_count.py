"""What "the number of alarms" of a session (or of one run) is: one definition, used by the session report, the
progress report, the on-screen run summary and the sessions browser (Qt-free, no I/O).

An alarm is counted **once, when it is raised, if it is a warning, a stop or a fatal alarm**: an ``alarm`` event
of level WARNING, STOP or FATAL (an older recording's alarm without a level counts too). Not counted:

- information messages (level INFO: "Emergency stop reset", "fes reconnected"): they say that something is
  fine again;
- repeats of an alarm still open (``alarm_repeated``): the supervisor merges them into that alarm;
- acknowledgements (``alarm_acknowledged``) and the Recover steps: they answer an alarm, they are not one;
- the emergency stop's own ``emergency_stop`` event: pressing STOP raises one STOP alarm ("Emergency stop: …"),
  which is the one counted; pressing it again while it is latched raises none and counts none. Only a recording
  whose stop has no such alarm (made before the supervisor raised one) counts the stop itself, once per latch;
- program ends and data gaps (``script_stop``, ``gap_start``): interruptions, listed in the reports, not alarms.

Before this definition the sessions browser counted every ``alarm`` event (INFO included) and the reports counted
``alarm`` + ``emergency_stop`` events (each STOP twice): 8 and 11 for one session with three STOPs (docs/sessions.md).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

COUNTED_LEVELS: tuple[str, ...] = ("WARNING", "STOP", "FATAL")
ESTOP_ALARM_PREFIX = "Emergency stop"  # the supervisor's STOP alarm for a press: "Emergency stop: <reason>"
_ESTOP_MATCH_S = 1.0  # an emergency_stop event and the STOP alarm it raised are this close in time, at most


def _time(e: Mapping[str, Any]) -> float:
    t = e.get("t_mono", e.get("t_s", 0.0))
    return float(t) if isinstance(t, int | float) else 0.0


def _data(e: Mapping[str, Any]) -> Mapping[str, Any]:
    data = e.get("data")
    return data if isinstance(data, Mapping) else {}


def is_counted_alarm(e: Mapping[str, Any]) -> bool:
    """An ``alarm`` event that counts: a warning, a stop or a fatal alarm (no level: an older record, counted)."""
    if e.get("kind") != "alarm":
        return False
    level = _data(e).get("level")
    return level is None or str(level).upper() in COUNTED_LEVELS


def _is_estop_alarm(e: Mapping[str, Any]) -> bool:
    return e.get("kind") == "alarm" and str(_data(e).get("text") or "").startswith(ESTOP_ALARM_PREFIX)


def counted_alarms(events: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The events that count as alarms, in the record's order (see the module's definition). ``events`` are the
    session's events (``kind``, ``data``, ``t_mono``) or the reports' alarm list (``t_s`` instead of ``t_mono``)."""
    events = list(events)
    estop_alarm_times = [_time(e) for e in events if _is_estop_alarm(e)]
    out: list[Mapping[str, Any]] = []
    latched = False
    for e in events:
        kind = e.get("kind")
        if kind == "emergency_stop_reset":
            latched = False
        elif kind == "emergency_stop":
            first = not latched
            latched = True
            t = _time(e)
            has_alarm = any(abs(t - ta) <= _ESTOP_MATCH_S for ta in estop_alarm_times)
            if first and not has_alarm:
                out.append(e)
        elif is_counted_alarm(e):
            out.append(e)
    return out


def alarm_count(events: Iterable[Mapping[str, Any]]) -> int:
    """How many alarms ``events`` hold: the one number every view shows (:func:`counted_alarms`)."""
    return len(counted_alarms(events))
