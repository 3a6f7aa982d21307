"""An exercise's progress as the clinician sees it: which repetition of how many, since when, what it says.

The script API (``linarmppManager.startRepetition / endRepetition / reportProgress``) feeds it, whoever
runs the script (the console, the Exercises tab, the headless runner); the window listens through its adapter
(``QtBus.watch_progress``: ``progress_changed`` on the GUI thread); every mark is also a journal record
(``repetition_start``, ``repetition_end``, ``progress``), so the per-repetition metrics can find the repetitions in
a recording. Qt-free and thread-safe: marks arrive from the script bridge's thread, and :meth:`subscribe`'s
listeners are called on it (they must be quick: the adapter queues the state for its next tick).

The run it belongs to is followed through the journal: :meth:`follow_runs` listens on the bus for the run log's
records (origin ``run``: its state, its end on the run log's clock) of the run it shows — that run's id in that
run's log, since each session's log numbers its runs from run-1.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from app.core import journal
from app.core.bus import RecordListener, StreamBus
from app.core.journal import Record
from app.core.runs import PROGRAM_STATES, run_state_text

EventRecorder = Callable[..., None]  # SafetySupervisor.record(kind, **data)
Listener = Callable[["ProgressState"], None]
log = logging.getLogger(__name__)


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
    run_id: str = ""  # the run (app/core/runs.py) these marks belong to
    run_log: str = ""  # the run log that run is in (its records' ``log``)
    run_state: str = ""  # the run's state (app.core.runs.RUN_STATES), "" without a run
    state_text: str = ""  # the run's state in words: "waiting for the grip", "stopped: emergency stop"
    ended_monotonic: float | None = None  # when the run ended: the elapsed time stops there

    def elapsed_s(self, now: float | None = None) -> float:
        if self.started_monotonic is None:
            return 0.0
        now = time.monotonic() if now is None else now
        if self.ended_monotonic is not None:
            now = min(now, self.ended_monotonic)
        paused = self.paused_s + ((now - self.paused_since) if self.paused_since is not None else 0.0)
        return max(0.0, now - self.started_monotonic - paused)

    def label(self) -> str:
        if not self.exercise and not self.repetition:
            return ""
        if self.repetition == 0:
            return self.state_text or ("starting" if self.running else "")
        return f"repetition {self.repetition} of {self.total}" if self.total else f"repetition {self.repetition}"


class ExerciseProgress:
    def __init__(self, record_event: EventRecorder | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self._listeners: tuple[Listener, ...] = ()
        self._record = record_event
        self._clock = clock
        self._lock = threading.Lock()
        self._state = ProgressState()
        self._runs: Any = None  # app.core.runs.RunLog: the session's runs (the manager attaches each new one)
        self._run_log: Any = None  # the RunLog of the run the state shows (it stays there when a session starts)
        self._listener: RecordListener | None = None

    def subscribe(self, fn: Listener) -> Callable[[], None]:
        """``fn(state)`` after every change, on the thread that made it; returns the unsubscribe."""
        self._listeners = (*self._listeners, fn)

        def unsubscribe() -> None:
            self._listeners = tuple(f for f in self._listeners if f is not fn)

        return unsubscribe

    def attach_runs(self, runs: Any) -> None:
        """The session's runs (a RunLog): a run begun from now on is looked up there, and marks made while no run
        has begun go to its current run. The run already shown stays in the log it began in."""
        self._runs = runs

    def follow_runs(self, bus: StreamBus) -> None:
        """Hear the run log's records on ``bus`` (the run shown: its state, its end)."""
        self.stop_following_runs()
        self._listener = bus.listen("progress", self.run_record)

    def stop_following_runs(self) -> None:
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.close()

    def run_record(self, record: Record) -> None:
        """A journal record (on the publishing thread): the run shown changed state or ended."""
        if record.origin != journal.RUN or record.kind not in (journal.RUN_STATE, journal.RUN_END):
            return
        data = record.data
        with self._lock:
            state = self._state
        if not state.run_id or data.get("run_id") != state.run_id or data.get("log") != state.run_log:
            return
        if record.kind == journal.RUN_STATE:
            run_state = str(data.get("state", state.run_state))
            self._set(replace(state, run_state=run_state,
                              state_text=run_state_text(run_state, str(data.get("detail", "")))))
            return
        reason = str(data.get("reason", ""))
        ended = data.get("ended_mono")
        self._set(replace(state, run_state="finished" if reason == "finished" else "stopped",
                          state_text=run_state_text("", "", reason),
                          ended_monotonic=float(ended) if ended is not None else state.ended_monotonic))

    def _current_run(self, state: ProgressState) -> tuple[str, Any]:
        """The run the marks belong to: its id and its RunLog (("", None) without one)."""
        if state.run_id and state.running:
            return state.run_id, self._run_log
        current = self._runs.current() if self._runs is not None else None
        return (current.run_id, self._runs) if current is not None else ("", None)

    @staticmethod
    def _run_fields(run_id: str, runs: Any) -> dict[str, Any]:
        """The fields naming a mark's run in its record: its id and its log."""
        if not run_id:
            return {}
        return {"run_id": run_id, "log": runs.log_id} if runs is not None else {"run_id": run_id}

    @property
    def state(self) -> ProgressState:
        with self._lock:
            return self._state

    # ------------------------------------------------------------------ called by the script host
    def begin(self, exercise: str, total: int | None = None, run_id: str = "") -> None:
        runs = self._runs if run_id else None
        self._run_log = runs
        run = runs.get(run_id) if runs is not None else None
        started = run.started_mono if run is not None else self._clock()
        self._set(ProgressState(exercise=exercise, total=_total(total), started_monotonic=started, running=True,
                                run_id=run_id, run_log=runs.log_id if runs is not None else "",
                                run_state=run.state if run is not None else "",
                                state_text=run.state_text() if run is not None else ""))

    def finish(self, status: str = "finished") -> None:
        with self._lock:
            state = self._state
        if not state.running:
            return
        runs = self._run_log
        if state.in_repetition:
            self._event(journal.REPETITION_END, index=state.repetition, ok=False, status=status,
                        **self._run_fields(state.run_id, runs))
            if state.run_id and runs is not None:
                runs.repetition_ended(state.run_id, state.repetition, False, interrupted=True)
        now = self._clock()
        paused_s = state.paused_s + ((now - state.paused_since) if state.paused_since is not None else 0.0)
        run = runs.get(state.run_id) if (state.run_id and runs is not None) else None
        text = run.state_text() if run is not None and not run.running else (state.state_text or status)
        ended = run.ended_mono if run is not None and run.ended_mono is not None else now
        # The exercise's last message ("moving to 0.30 m") is not true after a stop: only a finished run keeps it.
        end_reason = run.end_reason if run is not None and not run.running else status
        last_text = state.text if end_reason == "finished" else ""
        self._set(replace(state, running=False, in_repetition=False, paused_since=None, paused_s=paused_s,
                          ended_monotonic=ended, state_text=text, text=last_text,
                          run_state=run.state if run is not None else state.run_state))

    def pause(self) -> None:
        with self._lock:
            state = self._state
        if state.running and state.paused_since is None:
            self._event(journal.EXERCISE_PAUSED, exercise=state.exercise)
            self._set(replace(state, paused_since=self._clock()))

    def resume(self) -> None:
        with self._lock:
            state = self._state
        if state.paused_since is not None:
            self._event(journal.EXERCISE_RESUMED, exercise=state.exercise)
            self._set(replace(state, paused_s=state.paused_s + self._clock() - state.paused_since, paused_since=None))

    # ------------------------------------------------------------------ called by the script API
    def start_repetition(self, index: int, total: int | None = None) -> None:
        index = int(index)
        if index < 1:
            raise ValueError(f"repetitions are counted from 1, got {index}")
        with self._lock:
            state = self._state
        total = _total(total) if total is not None else state.total
        run_id, runs = self._current_run(state)
        self._event(journal.REPETITION_START, index=index, total=total, **self._run_fields(run_id, runs))
        if run_id and runs is not None:
            runs.repetition_started(run_id, index)
        started = state.started_monotonic if state.started_monotonic is not None else self._clock()
        self._set(replace(state, repetition=index, total=total, in_repetition=True, started_monotonic=started,
                          running=True))

    def end_repetition(self, index: int | None = None, ok: bool = True) -> None:
        with self._lock:
            state = self._state
        index = state.repetition if index is None else int(index)
        run_id, runs = self._current_run(state)
        self._event(journal.REPETITION_END, index=index, ok=bool(ok), **self._run_fields(run_id, runs))
        if run_id and runs is not None:
            runs.repetition_ended(run_id, index, bool(ok))
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
        run_id, runs = self._current_run(state)
        data.update(self._run_fields(run_id, runs))  # the run it belongs to (app/core/runs.py: prompt events)
        self._event(journal.PROMPT, **data)

    def set_run_state(self, state: str, detail: str = "") -> None:
        """The program says what its run does now (linarmppManager.setRunState): "waiting_for_grip", "moving",
        "resting" or "running". The runner owns the others (homing, paused, stopped, finished)."""
        state = str(state)
        if state not in PROGRAM_STATES:
            raise ValueError(f"a run state is one of {', '.join(PROGRAM_STATES)}, got {state!r}")
        with self._lock:
            current = self._state
        run_id, runs = self._current_run(current)
        if run_id and runs is not None:
            runs.set_state(run_id, state, str(detail)[:120])

    def report(self, text: str) -> None:
        text = str(text)[:200]
        self._event(journal.PROGRESS_TEXT, text=text)
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
        for fn in self._listeners:
            try:
                fn(state)
            except Exception:  # a listener's bug must not stop the exercise
                log.exception("progress listener failed")


def _total(total: int | None) -> int | None:
    if total is None:
        return None
    total = int(total)
    if total < 1:
        raise ValueError(f"an exercise has at least one repetition, got {total}")
    return total
