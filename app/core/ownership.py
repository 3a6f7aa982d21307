"""One owner of each device during a run (issue #36), the pure part (Qt-free).

A run (a library exercise, a script, Recover's restart or continuation) or the electrode set-up holds a **lease**
on the robot — its target, mode, gains and trajectory — and, where it stimulates, on the stimulator. While a lease
is held, a command from any other source (the VR task's target, the patient model's assistance, a panel's
button, the console outside the run) is refused with a sentence, unless the holder **composes** it: an exercise
declares in its YAML which other source may set what, within which of its parameters' range::

    composition:
      - {source: VR task, sets: assistance_target, within: [start_m, target_m]}

A composed value is clamped to the declared range and to the patient's limits before it is sent
(:func:`clamp_to`), and a composed command outside the range is refused at the supervisor like any other.

What is always let through, whoever holds the device: the e-stop and the safe state (robot IDLE, FES Stop are
never checked here), commands that only read or align the controller's limits, and the drivers' own link
traffic (sources :data:`FREE_SOURCES`).

The supervisor (app/safety/supervisor.py) keeps the leases and calls :func:`refusal` from its command checks; this
module
only decides.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

ROBOT, STIMULATOR = "robot", "stimulator"
DEVICES: tuple[str, ...] = (ROBOT, STIMULATOR)
DEVICE_WORDS = {ROBOT: "the robot", STIMULATOR: "the stimulator"}

# What a composition may let another source set, and the commands (robot) or actions (stimulator) it covers.
SETS: dict[str, tuple[str, frozenset[str]]] = {
    "assistance_target": (ROBOT, frozenset({"setAssistanceTargetPos"})),
    "robot_gains": (ROBOT, frozenset({"setAdmittanceParameter", "setAssistanceParameter", "setStiffness",
                                      "robot gains"})),
    "pulse_width": (STIMULATOR, frozenset({"pulse width override"})),
}
# The sources another holder may let in (what composes): the VR task's target and the patient model's assistance.
COMPOSABLE_SOURCES: tuple[str, ...] = ("VR task", "assistance")
# The drivers' own traffic (the controller's limits at connect, the handshake): never a competing controller.
FREE_SOURCES: frozenset[str] = frozenset({"limits", "handshake"})
# The command sources that act for a script or exercise run: the script API (its bridge), the runner itself
# (homing, the run's default settings, the safe state) and the API's electrode set-up ("script: fes.…").
RUN_SOURCES: tuple[str, ...] = ("script", "script runner")
SETUP_SOURCES: tuple[str, ...] = ("electrode set-up",)

# A command in words, for the sentences ("… refused: the robot is held by Trigger reaching").
_COMMAND_WORDS = {
    "setAssistanceTargetPos": "the assistance target", "setAdmittanceParameter": "the admittance",
    "setAssistanceParameter": "the assistance gain", "setStiffness": "the stiffness",
    "setCtrlState": "the robot's control state", "setCtrlMode": "the robot's control mode",
    "moveCentreTo": "a move", "moveDeltaTo": "a stiffness move", "goToHome": "homing",
    "setCentreVelocity": "a jog", "setDeltaVelocity": "a jog", "setTrajectory": "a trajectory",
    "pulse width override": "the pulse width", "start": "stimulation", "load profile": "a profile",
    "scale": "a scale factor", "robot gains": "the robot's gains",
}
_SOURCE_WORDS = {"VR task": "the VR task", "assistance": "the patient model's assistance", "gui": "the Robot tab",
                 "FES panel": "the FES tab", "recover": "Recover", "": "an unnamed source"}


@dataclass(frozen=True)
class Composition:
    """``source`` may set ``sets`` (a key of :data:`SETS`) while the run holds the device; a target within
    ``range_m`` (m, both ends included; None: the patient's limits only)."""

    source: str
    sets: str
    range_m: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.sets not in SETS:
            raise ValueError(f"'sets' must be one of {', '.join(SETS)}, got {self.sets!r}")
        if self.source not in COMPOSABLE_SOURCES:
            raise ValueError(f"'source' must be one of {', '.join(COMPOSABLE_SOURCES)}, got {self.source!r}")
        if self.range_m is not None:
            lo, hi = self.range_m
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"the range {lo} .. {hi} m is not a range")

    @property
    def device(self) -> str:
        return SETS[self.sets][0]

    def covers(self, source: str, command: str) -> bool:
        return source == self.source and command in SETS[self.sets][1]

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"source": self.source, "sets": self.sets}
        if self.range_m is not None:
            d["range_m"] = [self.range_m[0], self.range_m[1]]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Composition:
        rng = d.get("range_m")
        return cls(str(d.get("source", "")), str(d.get("sets", "")),
                   (float(rng[0]), float(rng[1])) if rng else None)


@dataclass(frozen=True)
class Lease:
    """``holder`` (in words: "Trigger reaching", "Electrode set-up") holds ``devices``; commands from ``sources``
    act for it; ``compose`` lets other sources in. ``key`` identifies it (the run's id)."""

    key: str
    holder: str
    devices: frozenset[str]
    sources: tuple[str, ...]
    compose: tuple[Composition, ...] = ()
    run_id: str = ""
    refused: dict[str, int] = field(default_factory=dict, compare=False)  # "source: what" -> count

    def acts_for(self, source: str) -> bool:
        """``source`` is the holder's own (exactly, or a sub-source "script: fes.electrodeSetup")."""
        return any(source == s or source.startswith(s + ":") for s in self.sources)

    def composition(self, source: str, command: str) -> Composition | None:
        return next((c for c in self.compose if c.covers(source, command)), None)

    def record(self) -> dict[str, Any]:
        """What the session record keeps of it (``lease_taken``)."""
        return {"key": self.key, "holder": self.holder, "devices": sorted(self.devices), "sources": list(self.sources),
                "compose": [c.as_dict() for c in self.compose], "run_id": self.run_id}


def command_words(command: str) -> str:
    return _COMMAND_WORDS.get(command, command)


def source_words(source: str) -> str:
    return _SOURCE_WORDS.get(source, source)


def refusal(lease: Lease | None, device: str, source: str, command: str, value: float | None = None) -> str:
    """Why ``command`` from ``source`` may not act on ``device`` now ("" when it may): held by another, not
    composed, or composed but outside the declared range."""
    if lease is None or device not in lease.devices or source in FREE_SOURCES or lease.acts_for(source):
        return ""
    comp = lease.composition(source, command)
    what = f"{command_words(command)} from {source_words(source)}"
    if comp is None:
        return f"{what} refused: {DEVICE_WORDS[device]} is held by {lease.holder}"
    if comp.range_m is not None and value is not None:
        lo, hi = comp.range_m
        if not (lo - 1e-9 <= value <= hi + 1e-9):
            return (f"{what} refused: {value:.3f} m is outside {lease.holder}'s range {lo:.3f} .. {hi:.3f} m "
                    f"({DEVICE_WORDS[device]} is held by {lease.holder})")
    return ""


def clamp_to(comp: Composition, value: float, patient_range: tuple[float, float]) -> float:
    """A composed target clamped to the run's declared range and the patient's limits (both, the narrower)."""
    lo, hi = patient_range
    if comp.range_m is not None:
        lo, hi = max(lo, comp.range_m[0]), min(hi, comp.range_m[1])
    if lo > hi:  # the run's range lies outside the patient's: the patient's limits win
        lo, hi = patient_range
    return min(max(value, lo), hi)


def compositions_from(declared: Iterable[Mapping[str, Any]], params: Mapping[str, Any]) -> tuple[Composition, ...]:
    """An exercise's declared composition (its YAML's ``composition`` list) with the run's parameter values:
    ``within: [a, b]`` names two parameters (or gives two numbers); the range is their sorted values."""
    out = []
    for d in declared:
        within = d.get("within") or ()
        rng = None
        if within:
            a, b = (float(params[w]) if isinstance(w, str) else float(w) for w in within)
            rng = (min(a, b), max(a, b))
        out.append(Composition(str(d["source"]), str(d["sets"]), rng))
    return tuple(out)


class _Holds(Protocol):
    """What :func:`start_problem` reads of the supervisor (app.safety.supervisor.SafetySupervisor)."""

    def robot_hold_reason(self) -> str: ...

    def holder(self, device: str = ROBOT) -> str: ...


class OwnershipHost(Protocol):
    """What :func:`start_problem` reads of the manager: its supervisor."""

    @property
    def supervisor(self) -> _Holds: ...


def start_problem(manager: OwnershipHost, holds: tuple[str, ...] = ("robot",), *, stop: bool = True) -> str:
    """Why a run cannot start now ("" when it can), in words, before anything is recorded or moves: a latched
    emergency stop or an open STOP alarm (Recover first; ``stop`` False: not asked — a script that only looks
    may run), or another holder of the devices it needs."""
    sup = getattr(manager, "supervisor", None)
    hold_reason = getattr(sup, "robot_hold_reason", None)
    reason = hold_reason() if stop and callable(hold_reason) else ""
    if reason:
        return f"{reason}; press Recover… in the alarm banner first"
    holder = getattr(sup, "holder", None)
    if callable(holder):
        for device in holds:
            who = holder(device)
            if who:
                return f"the {device} is held by {who}; wait until it ends or stop it first"
    return ""
