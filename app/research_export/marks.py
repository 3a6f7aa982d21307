"""The session's events as every export names them: one row per recorded event (its kind, a short value), the
spans an analysis wants with their duration (a repetition, an exercise run, a device's data gap), and the FES
channels switching on and off (from the stimulator's stream). BIDS ``_events.tsv``, the XDF marker stream and the
EDF+ annotations are all made from these, so an event has the same name and time in the three.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass
from typing import Any

import numpy as np

# What a clinical viewer shows as annotations (EDF+): the course of the session, not every command and
# acknowledgement (those stay in the XDF event stream and in BIDS _events.tsv).
CLINICAL_KINDS = frozenset({
    "session_start", "session_stop", "run", "exercise_start", "exercise_paused", "exercise_resumed", "script_start",
    "script_stop", "repetition", "prompt", "alarm", "emergency_stop", "emergency_stop_reset", "device_gap",
    "recording_failed", "samples_dropped", "fes_on", "fes_off",
})
SPAN_KINDS = {"repetition": ("repetition_start", "repetition_end"), "run": ("run_start", "run_end"),
              "device_gap": ("gap_start", "gap_end")}
VALUE_CHARS = 200  # a value longer than this (an alarm's whole text) is cut with an ellipsis in a marker


@dataclass(frozen=True)
class Mark:
    """An event at ``t`` (monotonic s) lasting ``duration`` s (0: an instant). ``record`` is the recorded event
    (None for a derived span or an FES switch)."""

    t: float
    duration: float
    kind: str
    value: str
    record: dict[str, Any] | None = None

    @property
    def label(self) -> str:
        """``kind`` and ``value`` in one short text (a marker, an annotation)."""
        value = self.value if len(self.value) <= VALUE_CHARS else self.value[: VALUE_CHARS - 1] + "…"
        return f"{self.kind} {value}".strip()


def _data(event: dict[str, Any]) -> dict[str, Any]:
    data = event.get("data")
    return data if isinstance(data, dict) else {}


def event_value(event: dict[str, Any]) -> str:
    """The one thing a reader of a marker wants to know about an event, as short text."""
    kind = str(event.get("kind") or "")
    d = _data(event)
    if kind in ("repetition_start", "repetition_end"):
        ok = "" if kind == "repetition_start" or d.get("ok", True) else " not completed"
        return f"{d.get('index', '')}{ok}"
    if kind == "prompt":
        return str(d.get("cue") or d.get("text") or d.get("index") or "")
    if kind in ("alarm", "alarm_repeated"):
        return f"{d.get('level', '')}: {d.get('text', '')}".strip(": ")
    if kind == "emergency_stop":
        return str(d.get("reason") or d.get("source") or "")
    if kind == "run_start":
        program = d.get("program") if isinstance(d.get("program"), dict) else {}
        return str(program.get("title") or program.get("ident") or d.get("run_id") or "")
    if kind == "run_end":
        return str(d.get("reason") or "")
    if kind == "exercise_start":
        return str(d.get("title") or d.get("exercise") or "")
    if kind == "script_start":
        return str(d.get("name") or "")
    if kind == "script_stop":
        return str(d.get("status") or d.get("reason") or "")
    if kind in ("gap_start", "gap_end", "device_connected", "device_disconnected"):
        return f"{d.get('device', event.get('who', ''))} {d.get('cause', '')}".strip()
    if kind == "command":
        return f"{d.get('device', '')} {d.get('name', '')}".strip()
    if kind == "parameter_change":
        return f"{d.get('name', '')} {d.get('old', '')} -> {d.get('new', '')}"
    if kind == "progress":
        return str(d.get("text") or "")
    return ""


def event_marks(events: list[dict[str, Any]], t_end: float) -> list[Mark]:
    """Every recorded event (instant), then the spans with their durations; sorted by time (stable)."""
    out = [Mark(float(e["t_mono"]), 0.0, str(e.get("kind") or ""), event_value(e), e) for e in events]
    open_spans: dict[tuple[str, str], dict[str, Any]] = {}
    for e in events:
        kind = str(e.get("kind") or "")
        d = _data(e)
        for span, (start, end) in SPAN_KINDS.items():
            if kind not in (start, end):
                continue
            key = (span, _span_key(span, e, d))
            if kind == start:
                open_spans.setdefault(key, e)
            elif key in open_spans:
                first = open_spans.pop(key)
                out.append(_span(span, first, float(e["t_mono"])))
    for (span, _), first in open_spans.items():  # never ended (a crash): up to the session's end
        out.append(_span(span, first, max(t_end, float(first["t_mono"]))))
    return sorted(out, key=lambda m: m.t)


def _span_key(span: str, event: dict[str, Any], d: dict[str, Any]) -> str:
    # A run is its id in its run log (app/core/runs.py: each session's log numbers from run-1, and an earlier
    # log's run may end inside this session); records from before the ``log`` field have one log.
    if span == "repetition":
        return f"{d.get('log', '')}/{d.get('run_id', '')}/{d.get('index', '')}"
    if span == "run":
        return f"{d.get('log', '')}/{d.get('run_id', '')}"
    return str(d.get("device") or event.get("who") or "")


def _span(span: str, first: dict[str, Any], t_end: float) -> Mark:
    t = float(first["t_mono"])
    return Mark(t, max(0.0, t_end - t), span, event_value(first), None)


class FesSwitches:
    """FES channels switching on (current above zero) and off, from the stimulator's stream read in chunks."""

    def __init__(self, channel_names: list[str]) -> None:
        self.columns = [(i, name.removeprefix("current")) for i, name in enumerate(channel_names)
                        if name.startswith("current")]
        self.on = np.zeros(len(self.columns), dtype=bool)
        self.marks: list[Mark] = []

    def feed(self, t: np.ndarray, values: np.ndarray) -> None:
        if not self.columns or not len(t):
            return
        cols = np.array([i for i, _ in self.columns])
        active = np.nan_to_num(values[:, cols]) > 0.0
        previous = np.vstack([self.on[None, :], active[:-1]])
        rows, chans = np.nonzero(active != previous)
        for r, c in sorted(zip(rows.tolist(), chans.tolist(), strict=True)):
            kind = "fes_on" if active[r, c] else "fes_off"
            self.marks.append(Mark(float(t[r]), 0.0, kind, f"channel {self.columns[c][1]}", None))
        self.on = active[-1]


def exported(record: dict[str, Any], shift_days: int = 0) -> dict[str, Any]:
    """An event as it leaves the application. With dates shifted (de-identification), its wall time moves back as
    every date does, and the session folder's path (named after the real date and time) is left out."""
    if not shift_days:
        return record
    out = dict(record)
    if isinstance(out.get("t_wall"), str) and out["t_wall"]:
        try:
            moment = _dt.datetime.fromisoformat(out["t_wall"]) - _dt.timedelta(days=shift_days)
            out["t_wall"] = moment.isoformat(timespec="microseconds")
        except ValueError:
            out["t_wall"] = ""
    data = out.get("data")
    if isinstance(data, dict) and "folder" in data:
        out["data"] = {k: v for k, v in data.items() if k != "folder"}
    return out


def record_json(record: dict[str, Any]) -> str:
    """An event as the session's ``events.jsonl`` line holds it (and as the live LSL marker carries it)."""
    return json.dumps(record, ensure_ascii=False, default=str)
