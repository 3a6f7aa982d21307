"""What a session delivered outside its exercise runs, read back from its record (Qt-free, no I/O): the electrode
set-ups (app/therapy/electrodes.py: per district the test bursts, each combination's response, the patient's discomfort
ratings, the proposal and the choice, by whom) and the stimulation started outside any run (the FES panel, a
script's stimulation between runs: when, which profile, the currents and pulse widths sent, how long, how it
ended). The session report prints both; the values sent are read from the stimulator's recorded stream
(``fes.channels``) where the session has it, so the record says what reached the wire, not only what was asked.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.core.runs import ExerciseRun
from app.wire.sciencemode import CHANNELS

SETUP_SOURCE = "electrode set-up"  # the source the electrode set-up's bursts start with (app/therapy/electrodes.py)


@dataclass
class TestedCombination:
    """One candidate electrode combination of a district's set-up, with its bursts in the order given."""

    channel: int
    electrodes: str
    ceiling_ma: float | None
    ceiling_set_by: str
    bursts: list[dict[str, Any]] = field(default_factory=list)  # electrode_burst data
    discomfort: int | None = None  # the patient's last rating (0–10), None = not rated
    motor_threshold_ma: float | None = None

    @property
    def currents(self) -> list[float]:
        return [float(b.get("current_ma") or 0.0) for b in self.bursts]

    @property
    def highest_ma(self) -> float | None:
        return max(self.currents, default=None)

    @property
    def best_response_n(self) -> float | None:
        return max((float(b.get("response_n") or 0.0) for b in self.bursts), default=None)


@dataclass
class ElectrodeSetupRecord:
    """One district's set-up as the record holds it."""

    district: str
    started_mono: float
    operator: str
    plan: dict[str, Any]  # ceiling_ma, start_ma, step_ma, pulse_width_us, frequency_hz
    combinations: list[TestedCombination]
    ended_mono: float | None = None
    proposed_channel: int | None = None
    proposal_reason: str = ""
    completed: bool = False
    aborted: str = ""  # why it ended early
    choice: dict[str, Any] | None = None  # electrode_choice data
    delivered: dict[int, tuple[float, float]] = field(default_factory=dict)  # channel → (max mA, max µs) sent

    @property
    def bursts(self) -> int:
        return sum(len(c.bursts) for c in self.combinations)

    @property
    def highest_ma(self) -> float | None:
        return max((c.highest_ma for c in self.combinations if c.highest_ma is not None), default=None)

    def combination(self, channel: int) -> TestedCombination | None:
        return next((c for c in self.combinations if c.channel == channel), None)


@dataclass
class StimulationRecord:
    """Stimulation started outside any exercise run (the FES panel, a script between runs)."""

    started_mono: float
    profile: str
    source: str
    current_scale: float | None = None
    ended_mono: float | None = None  # None: no end in the record (the session ended while stimulating)
    end_reason: str = ""
    end_source: str = ""
    channels: dict[int, tuple[float, float]] = field(default_factory=dict)  # channel → (max mA, max µs) sent
    frequency_hz: float | None = None

    def duration_s(self, session_end_mono: float) -> float:
        return max(0.0, (self.ended_mono if self.ended_mono is not None else session_end_mono) - self.started_mono)


def _data(e: Mapping[str, Any]) -> Mapping[str, Any]:
    d = e.get("data")
    return d if isinstance(d, Mapping) else {}


def _t(e: Mapping[str, Any]) -> float:
    t = e.get("t_mono")
    return float(t) if isinstance(t, int | float) else 0.0


def _int(value: Any) -> int | None:
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def sent_on_channels(fes: Any, t0: float, t1: float) -> dict[int, tuple[float, float]]:
    """The highest current (mA) and pulse width (µs) sent on each channel between ``t0`` and ``t1`` (monotonic),
    from the recorded ``fes.channels`` stream (``RecordedStream``: ``t``, ``data``); channels that stayed at 0 are
    left out; {} without the stream."""
    if fes is None or not len(getattr(fes, "t", ())):
        return {}
    t = np.asarray(fes.t, dtype=float)
    inside = (t >= t0) & (t <= t1)
    if not inside.any():
        return {}
    out: dict[int, tuple[float, float]] = {}
    for ch in CHANNELS:
        current = fes.data.get(f"current{ch}")
        width = fes.data.get(f"pulseWidth{ch}")
        if current is None:
            continue
        peak = float(np.nanmax(np.asarray(current, dtype=float)[inside]))
        if peak > 0:
            w = float(np.nanmax(np.asarray(width, dtype=float)[inside])) if width is not None else 0.0
            out[ch] = (peak, w)
    return out


def electrode_setups(events: Sequence[Mapping[str, Any]], fes: Any = None) -> list[ElectrodeSetupRecord]:
    """Every electrode set-up in the record, in order: each ``electrode_setup_started`` opens one for its
    district; its bursts, result or abort, the discomfort ratings and the choice that follow for that district
    are its own (a later set-up of the same district takes what follows it)."""
    setups: list[ElectrodeSetupRecord] = []
    latest: dict[str, ElectrodeSetupRecord] = {}
    for e in events:
        kind = str(e.get("kind") or "")
        if not kind.startswith("electrode_"):
            continue
        d = _data(e)
        district = str(d.get("district") or "")
        if kind == "electrode_setup_started":
            combos = [TestedCombination(int(c.get("channel") or 0), str(c.get("electrodes") or ""),
                                        c.get("ceiling_ma"), str(c.get("ceiling_set_by") or ""))
                      for c in d.get("combinations") or [] if isinstance(c, Mapping)]
            plan = {k: d.get(k) for k in ("ceiling_ma", "start_ma", "step_ma", "pulse_width_us", "frequency_hz")}
            setup = ElectrodeSetupRecord(district, _t(e), str(e.get("who") or ""), plan, combos)
            setups.append(setup)
            latest[district] = setup
            continue
        setup = latest.get(district)
        if setup is None:  # a choice without its set-up in this session (e.g. a record cut short): skipped
            continue
        channel = _int(d.get("channel"))
        if kind == "electrode_burst" and channel is not None:
            combo = setup.combination(channel)
            if combo is None:
                combo = TestedCombination(channel, str(d.get("electrodes") or ""), None, "")
                setup.combinations.append(combo)
            combo.bursts.append({**d, "t_mono": _t(e)})
            setup.ended_mono = _t(e)
        elif kind == "electrode_setup_result":
            setup.completed = True
            setup.ended_mono = _t(e)
            setup.proposed_channel = _int(d.get("proposed_channel"))
            setup.proposal_reason = str(d.get("reason") or "")
            for ch, threshold in (d.get("motor_thresholds_ma") or {}).items():
                combo = setup.combination(_int(ch) or 0)
                if combo is not None and isinstance(threshold, int | float):
                    combo.motor_threshold_ma = float(threshold)
        elif kind == "electrode_setup_aborted":
            setup.aborted = str(d.get("reason") or "ended early")
            setup.ended_mono = _t(e)
        elif kind == "electrode_discomfort" and channel is not None:
            combo = setup.combination(channel)
            if combo is not None:
                rating = d.get("discomfort")
                combo.discomfort = int(rating) if isinstance(rating, int | float) else None
        elif kind == "electrode_choice":
            setup.choice = dict(d)
    for setup in setups:
        if setup.bursts and fes is not None:
            first = min(b["t_mono"] for c in setup.combinations for b in c.bursts)
            last = setup.ended_mono if setup.ended_mono is not None else first
            setup.delivered = sent_on_channels(fes, setup.started_mono, max(first, last))
    return setups


def _inside(t: float, spans: Sequence[tuple[float, float]]) -> bool:
    return any(a <= t <= b for a, b in spans)


def stimulation_outside_runs(events: Sequence[Mapping[str, Any]], runs: Sequence[ExerciseRun], end_mono: float,
                             fes: Any = None) -> list[StimulationRecord]:
    """Each stimulation started outside every exercise run and outside the electrode set-ups (whose test bursts
    their own section reports): from its ``fes_started`` to the next ``fes_stopped`` (its cause: the Stop
    button, the profile's end, an emergency stop), with the profile loaded for it and what was sent."""
    run_spans = [(r.started_mono, r.ended_mono if r.ended_mono is not None else end_mono) for r in runs]
    setup_spans: list[tuple[float, float]] = []
    opened: float | None = None
    for e in events:
        kind = e.get("kind")
        if kind == "electrode_setup_started":
            opened = _t(e)
        elif kind in ("electrode_setup_result", "electrode_setup_aborted") and opened is not None:
            setup_spans.append((opened, _t(e)))
            opened = None
    if opened is not None:
        setup_spans.append((opened, end_mono))
    out: list[StimulationRecord] = []
    current: StimulationRecord | None = None
    frequency: float | None = None
    for e in events:
        kind = e.get("kind")
        d = _data(e)
        t = _t(e)
        if kind == "fes_profile_loaded":
            f = d.get("frequency_hz")
            frequency = float(f) if isinstance(f, int | float) else None
        elif kind == "fes_started":
            if current is not None:  # a start without a stop in between: the earlier one ended here
                current.ended_mono = t
                out.append(current)
                current = None
            source = str(d.get("source") or e.get("who") or "")
            if source == SETUP_SOURCE or _inside(t, run_spans) or _inside(t, setup_spans):
                continue
            scale = d.get("current_scale")
            current = StimulationRecord(t, str(d.get("profile") or ""), source,
                                        float(scale) if isinstance(scale, int | float) else None,
                                        frequency_hz=frequency)
        elif kind == "fes_stopped" and current is not None:
            current.ended_mono = t
            current.end_reason = str(d.get("reason") or "")
            current.end_source = str(d.get("source") or "")
            out.append(current)
            current = None
    if current is not None:
        out.append(current)
    for s in out:
        s.channels = sent_on_channels(fes, s.started_mono, s.ended_mono if s.ended_mono is not None else end_mono)
    return out
