"""An exercise's progress as the clinician sees it: which repetition of how many, since when, what it says.

The script API (``linarmppManager.startRepetition / endRepetition / reportProgress``) feeds it, whoever
runs the script (the console, the Exercises tab, the headless runner); the window listens to ``changed``;
every mark is also a session event (``repetition_start``, ``repetition_end``, ``progress``), so the
per-repetition metrics can find the repetitions in a recording. Thread-safe: marks arrive from the
script bridge's thread, ``changed`` is delivered to the GUI thread by Qt's queued connections.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from PySide6.QtCore import QObject, Signal

EventRecorder = Callable[..., None]  # SafetySupervisor.event(kind, **data)


@dataclass(frozen=True)
class ProgressState:
    exercise: str = ""  # the exercise's (or script's) name; "" when nothing runs
    repetition: int = 0  # the current (or last) repetition, counted from 1; 0 before the first
    total: int | None = None  # how many repetitions the exercise plans, when it says
    in_repetition: bool = False
    text: str = ""  # the exercise's last progress message
    started_monotonic: float | None = None  # when the exercise began
    paused_s: float = 0.0  # time spent paused so far (not counted as elapsed)
    paused_since: float | None = None
    running: bool = False

    def elapsed_s(self, now: float | None = None) -> float:
        if self.started_monotonic is None:
            return 0.0
        now = time.monotonic() if now is None else now
        paused = self.paused_s + ((now - self.paused_since) if self.paused_since is not None else 0.0)
        return max(0.0, now - self.started_monotonic - paused)

    def label(self) -> str:
        if not self.exercise and not self.repetition:
            return ""
        if self.repetition == 0:
            return "starting"
        return f"repetition {self.repetition} of {self.total}" if self.total else f"repetition {self.repetition}"


class ExerciseProgress(QObject):
    changed = Signal(object)  # ProgressState

    def __init__(self, record_event: EventRecorder | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self._record = record_event
        self._clock = clock
        self._lock = threading.Lock()
        self._state = ProgressState()

    @property
    def state(self) -> ProgressState:
        with self._lock:
            return self._state

    # ------------------------------------------------------------------ called by the script host
    def begin(self, exercise: str, total: int | None = None) -> None:
        self._set(ProgressState(exercise=exercise, total=_total(total), started_monotonic=self._clock(), running=True))

    def finish(self, status: str = "finished") -> None:
        with self._lock:
            state = self._state
        if not state.running:
            return
        if state.in_repetition:
            self._event("repetition_end", index=state.repetition, ok=False, status=status)
        self._set(replace(state, running=False, in_repetition=False, paused_since=None))

    def pause(self) -> None:
        with self._lock:
            state = self._state
        if state.running and state.paused_since is None:
            self._event("exercise_paused", exercise=state.exercise)
            self._set(replace(state, paused_since=self._clock()))

    def resume(self) -> None:
        with self._lock:
            state = self._state
        if state.paused_since is not None:
            self._event("exercise_resumed", exercise=state.exercise)
            self._set(replace(state, paused_s=state.paused_s + self._clock() - state.paused_since, paused_since=None))

    # ------------------------------------------------------------------ called by the script API
    def start_repetition(self, index: int, total: int | None = None) -> None:
        index = int(index)
        if index < 1:
            raise ValueError(f"repetitions are counted from 1, got {index}")
        with self._lock:
            state = self._state
        total = _total(total) if total is not None else state.total
        self._event("repetition_start", index=index, total=total)
        started = state.started_monotonic if state.started_monotonic is not None else self._clock()
        self._set(replace(state, repetition=index, total=total, in_repetition=True, started_monotonic=started,
                          running=True))

    def end_repetition(self, index: int | None = None, ok: bool = True) -> None:
        with self._lock:
            state = self._state
        index = state.repetition if index is None else int(index)
        self._event("repetition_end", index=index, ok=bool(ok))
        self._set(replace(state, in_repetition=False))

    def prompt(self, index: int | None = None, cue: str = "squeeze", threshold_n: float | None = None) -> None:
        """The exercise cues the patient now ("squeeze": the grip trigger, ``threshold_n`` its threshold;
        "move": an active movement): the ``prompt`` event the patient's reaction time is measured from."""
        with self._lock:
            state = self._state
        index = state.repetition if index is None else int(index)
        data: dict[str, Any] = {"index": index, "cue": str(cue)[:40]}
        if threshold_n is not None:
            data["threshold_n"] = float(threshold_n)
        self._event("prompt", **data)

    def report(self, text: str) -> None:
        text = str(text)[:200]
        self._event("progress", text=text)
        with self._lock:
            state = self._state
        self._set(replace(state, text=text))

    # ------------------------------------------------------------------ internals
    def _event(self, kind: str, **data: Any) -> None:
        if self._record is not None:
            self._record(kind, **data)

    def _set(self, state: ProgressState) -> None:
        with self._lock:
            self._state = state
        self.changed.emit(state)


def _total(total: int | None) -> int | None:
    if total is None:
        return None
    total = int(total)
    if total < 1:
        raise ValueError(f"an exercise has at least one repetition, got {total}")
    return total
