"""The exercise run: the unit of therapy in a session's record (Qt-free).

Everything that starts an exercise (the Exercises tab, the Script tab, the console, headless, Recover) opens
one :class:`ExerciseRun` in the session's :class:`RunLog`; everything that ends it closes it with a reason.
The Exercises panel, the Script tab, Recover, the metrics and the reports all read runs, never file names.

Each change is a journal record (origin ``run``, :mod:`app.core.journal`) on the stream bus, published through
the log's one ``record`` call as it happens; whoever follows runs — the devices' leases (the manager), the
exercise's progress, the session's recorder — hears them on the bus. The log keeps no listener list of its own.
The record is the session's event log (``events.jsonl``), written as it happens, so a crash leaves the runs
readable: :func:`runs_from_events` rebuilds them from the events alone. The events (``data`` fields):

``run_start``   run_id, log, program {kind, ident, title, version, path, text_sha256}, parameters
                [{name, label, value, unit}], source, operator, restart_of, continues (the interrupted run a
                continuation carries on: its remaining repetitions), holds (the devices the run holds: "robot",
                "stimulator"), compose (what other sources it lets set, app/core/ownership.py), started_mono
``run_state``   run_id, log, state (a :data:`RUN_STATES` value), detail
``run_end``     run_id, log, reason (an :data:`END_REASONS` value), detail, completed, not_started, ended_mono
``prompt``      run_id, log, index, cue            the exercise's "squeeze now" cue (metrics: reaction time)
``repetition_start`` / ``repetition_end``          as before, plus ``run_id`` and ``log`` (repetitions numbered
                                                   within the run, from 1)

``log`` names the run log (:attr:`RunLog.log_id`, unique in the process): each session makes a log of its own
whose ids start again at run-1, and a run ends in the log it began in, so a run is its (log, run_id). Sessions
recorded before the field have one log: a record without it belongs to the run of its id. ``started_mono`` and
``ended_mono`` are the run log's clock (the record's own ``t_mono`` is the time it was published).

The program text itself is kept in ``run_start``'s ``program.text`` only for console code and scripts (so a
restart can run exactly what ran, and a changed file on disk is detected by its hash); library exercises
are identified by id, version (hash of their YAML + script) and text hash.
"""

from __future__ import annotations

import hashlib
import itertools
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

ProgramKind = Literal["exercise", "script_file", "console"]
RunSource = Literal["exercises_tab", "script_tab", "console", "headless", "recover", "plan"]
RunState = Literal["starting", "homing", "waiting_for_grip", "moving", "resting", "paused", "stopped", "finished",
                   "running"]
# "running": the program's own code runs and it has not said what it does (a script without setRunState).
RUN_STATES: tuple[str, ...] = ("starting", "homing", "waiting_for_grip", "moving", "resting", "paused",
                               "stopped", "finished", "running")
# What the progress area says for each state (the end's cause is added for "stopped").
STATE_TEXT: dict[str, str] = {
    "starting": "starting", "homing": "homing the robot", "waiting_for_grip": "waiting for the grip",
    "moving": "moving", "resting": "resting", "paused": "paused", "stopped": "stopped", "finished": "finished",
    "running": "running",
}
# The states a program may announce itself (linarmppManager.setRunState); the others belong to the runner.
PROGRAM_STATES: tuple[str, ...] = ("waiting_for_grip", "moving", "resting", "running")
# Why a run ended. "refused": refused before its first movement (a limit, a conflict) — never "completed".
EndReason = Literal["finished", "stopped_by_operator", "emergency_stop", "safety_stop", "script_error",
                    "refused", "session_ended", "app_exit", "crashed"]
END_REASONS: tuple[str, ...] = ("finished", "stopped_by_operator", "emergency_stop", "safety_stop", "script_error",
                                "refused", "session_ended", "app_exit", "crashed")
END_REASON_TEXT: dict[str, str] = {
    "finished": "finished",
    "stopped_by_operator": "stopped by the operator",
    "emergency_stop": "emergency stop",
    "safety_stop": "safety stop",
    "script_error": "script error",
    "refused": "refused before it started",
    "session_ended": "session ended",
    "app_exit": "application closed",
    "crashed": "interrupted (no end in the record)",
}

RUN_START, RUN_STATE, RUN_END, PROMPT = "run_start", "run_state", "run_end", "prompt"
# Ends after which Recover offers to start the run again (a finished run needs nothing; a refused one would
# be refused again until its cause is fixed).
INTERRUPTED_REASONS: tuple[str, ...] = ("stopped_by_operator", "emergency_stop", "safety_stop", "script_error",
                                        "session_ended", "app_exit", "crashed")


def text_hash(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class Program:
    """What ran. ``ident`` is the exercise id (library), the file's path (script) or ``"<console>"``."""

    kind: ProgramKind
    ident: str
    title: str
    text_sha256: str
    version: str = ""  # library exercises: hash of the YAML + script as loaded
    path: str = ""  # the file that was run (library script or Script-tab file)
    text: str = ""  # console code and script files: the exact text, so a restart runs what ran
    file_sha256: str = ""  # a Script-tab file: its text on disk when the run started (the editor's may differ)

    def as_dict(self, with_text: bool = True) -> dict[str, Any]:
        d = {"kind": self.kind, "ident": self.ident, "title": self.title, "text_sha256": self.text_sha256,
             "version": self.version, "path": self.path}
        if self.file_sha256:
            d["file_sha256"] = self.file_sha256
        if with_text and self.text:
            d["text"] = self.text
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Program:
        return cls(kind=d.get("kind", "script_file"), ident=str(d.get("ident", "")), title=str(d.get("title", "")),
                   text_sha256=str(d.get("text_sha256", "")), version=str(d.get("version", "")),
                   path=str(d.get("path", "")), text=str(d.get("text", "")),
                   file_sha256=str(d.get("file_sha256", "")))

    def file_changed(self) -> bool | None:
        """A Script-tab run's file: changed on disk since the run started (True), not (False), not known (None:
        no file, or a record from before its hash was kept)."""
        if self.kind != "script_file" or not self.path or not self.file_sha256:
            return None
        try:
            now = Path(self.path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            return True
        return text_hash(now) != self.file_sha256

    def changed_on_disk(self) -> str:
        """Why this program cannot be run again exactly ("" when it can)."""
        if self.kind == "console":
            return "code typed in the console is not kept as a program to restart"
        if self.kind == "script_file" and self.text:
            return ""  # the text that ran is in the record: a restart runs it, whatever the file says now
        if not self.path:
            return "the program's file is not known"
        try:
            now = Path(self.path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            return f"{self.path} cannot be read any more ({exc.__class__.__name__})"
        if text_hash(now) != self.text_sha256:
            return f"{Path(self.path).name} has changed on disk since the run started"
        return ""


@dataclass(frozen=True)
class RunParameter:
    name: str
    label: str
    value: Any
    unit: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "label": self.label, "value": self.value, "unit": self.unit}

    def text(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        return f"{self.label}: {self.value}{unit}"


@dataclass(frozen=True)
class RepetitionMark:
    index: int  # within the run, from 1
    start_mono: float
    end_mono: float | None = None
    ok: bool | None = None  # the exercise's own verdict; metrics decide "completed" from the handle
    prompt_mono: float | None = None
    interrupted: bool = False  # ended by the run's end (a STOP, Stop), not by the exercise: to be done again


@dataclass(frozen=True)
class ExerciseRun:
    run_id: str
    program: Program
    parameters: tuple[RunParameter, ...]
    source: RunSource
    operator: str
    started_mono: float
    started_wall: float
    restart_of: str | None = None
    continues: str | None = None  # a continuation of this interrupted run (its remaining repetitions)
    holds: tuple[str, ...] = ("robot", "stimulator")  # the devices it holds while it runs (one owner, #36)
    compose: tuple[Mapping[str, Any], ...] = ()  # what it lets another source set (app.core.ownership.Composition)
    state: str = "starting"
    state_detail: str = ""
    ended_mono: float | None = None
    end_reason: str | None = None
    end_detail: str = ""
    repetitions: tuple[RepetitionMark, ...] = ()

    @property
    def running(self) -> bool:
        return self.ended_mono is None

    @property
    def title(self) -> str:
        return self.program.title

    def params_dict(self) -> dict[str, Any]:
        return {p.name: p.value for p in self.parameters}

    def elapsed_s(self, now_mono: float | None = None, paused_s: float = 0.0) -> float:
        """Stops with the run: after its end, the run's duration."""
        end = self.ended_mono if self.ended_mono is not None else (time.monotonic() if now_mono is None else now_mono)
        return max(0.0, end - self.started_mono - paused_s)

    def end_text(self) -> str:
        if self.end_reason is None:
            return "running"
        text = END_REASON_TEXT.get(self.end_reason, self.end_reason)
        if self.end_detail.lower().startswith(text.lower()):  # "emergency stop pressed (keyboard)": said once
            return self.end_detail
        return f"{text}: {self.end_detail}" if self.end_detail else text

    def state_text(self) -> str:
        """The run's state in words: "waiting for the grip", "stopped: emergency stop", "finished"."""
        return run_state_text(self.state, self.state_detail, None if self.running else (self.end_reason or ""))

    def parameters_text(self) -> str:
        return ", ".join(p.text() for p in self.parameters)


EventRecorder = Callable[..., None]  # (kind, **data) -> None: the journal (the manager: bus.record, origin "run")
_LOG_NUMBERS = itertools.count(1)  # next() is atomic: each run log of the process gets its own number


def run_state_text(state: str, detail: str = "", end_reason: str | None = None) -> str:
    """A run's state in words: "waiting for the grip", "stopped: emergency stop", "finished" (``end_reason`` once
    it ended). The one reading of a state for :meth:`ExerciseRun.state_text` and a run record's follower."""
    if end_reason is not None:
        if end_reason == "finished":
            return "finished"
        return f"stopped: {END_REASON_TEXT.get(end_reason, end_reason)}"
    text = STATE_TEXT.get(state, state)
    return f"{text} ({detail})" if detail else text


class RunLog:
    """The session's runs, live. Thread-safe. Each change is a record published at once through ``record``
    (the journal, on the bus: see the module docstring), on the caller's thread; its followers hear it there.
    ``log_id`` names this log in its records (unique in the process; "log-1", "log-2", … when not given)."""

    def __init__(self, record: EventRecorder | None = None, clock: Callable[[], float] = time.monotonic,
                 wall_clock: Callable[[], float] = time.time, *, log_id: str = "") -> None:
        self._record = record
        self._clock = clock
        self._wall = wall_clock
        self.log_id = log_id or f"log-{next(_LOG_NUMBERS)}"
        self._lock = threading.Lock()
        self._runs: dict[str, ExerciseRun] = {}
        self._order: list[str] = []
        self._n = 0

    # ------------------------------------------------------------------ reading
    def runs(self) -> list[ExerciseRun]:
        with self._lock:
            return [self._runs[r] for r in self._order]

    def get(self, run_id: str) -> ExerciseRun | None:
        with self._lock:
            return self._runs.get(run_id)

    def current(self) -> ExerciseRun | None:
        """The running run, if any (at most one runs at a time)."""
        with self._lock:
            for r in reversed(self._order):
                if self._runs[r].running:
                    return self._runs[r]
        return None

    def last(self) -> ExerciseRun | None:
        with self._lock:
            return self._runs[self._order[-1]] if self._order else None

    # ------------------------------------------------------------------ writing
    def start(self, program: Program, parameters: Sequence[RunParameter], source: RunSource, operator: str,
              restart_of: str | None = None, *, continues: str | None = None,
              holds: Sequence[str] = ("robot", "stimulator"),
              compose: Sequence[Mapping[str, Any]] = ()) -> ExerciseRun:
        with self._lock:
            self._n += 1
            run_id = f"run-{self._n}"
            while run_id in self._runs:
                self._n += 1
                run_id = f"run-{self._n}"
            run = ExerciseRun(run_id=run_id, program=program, parameters=tuple(parameters), source=source,
                              operator=operator, started_mono=self._clock(), started_wall=self._wall(),
                              restart_of=restart_of, continues=continues, holds=tuple(holds),
                              compose=tuple(dict(c) for c in compose))
            self._runs[run_id] = run
            self._order.append(run_id)
        self._emit(RUN_START, run_id=run_id, program=program.as_dict(with_text=program.kind != "exercise"),
                   parameters=[p.as_dict() for p in parameters], source=source, operator=operator,
                   restart_of=restart_of, holds=list(holds), compose=[dict(c) for c in compose],
                   started_mono=run.started_mono, **({"continues": continues} if continues else {}))
        return run

    def set_state(self, run_id: str, state: str, detail: str = "") -> None:
        if state not in RUN_STATES:
            raise ValueError(f"unknown run state {state!r}")
        run = self._update(run_id, lambda r: replace(r, state=state, state_detail=detail) if r.running else r)
        if run is not None and run.running:
            self._emit(RUN_STATE, run_id=run_id, state=state, detail=detail)

    def repetition_started(self, run_id: str, index: int) -> None:
        now = self._clock()
        self._update(run_id, lambda r: replace(r, repetitions=(*r.repetitions, RepetitionMark(index, now))))

    def repetition_ended(self, run_id: str, index: int, ok: bool, interrupted: bool = False) -> None:
        now = self._clock()

        def close(r: ExerciseRun) -> ExerciseRun:
            reps = list(r.repetitions)
            for k in range(len(reps) - 1, -1, -1):
                if reps[k].index == index and reps[k].end_mono is None:
                    reps[k] = replace(reps[k], end_mono=now, ok=ok, interrupted=interrupted)
                    break
            return replace(r, repetitions=tuple(reps))
        self._update(run_id, close)

    def end(self, run_id: str, reason: str, detail: str = "") -> ExerciseRun | None:
        """Close a run once (a second end is ignored: the first cause is the one the record keeps)."""
        if reason not in END_REASONS:
            raise ValueError(f"unknown end reason {reason!r}")
        now = self._clock()
        with self._lock:
            run = self._runs.get(run_id)
            if run is None or not run.running:
                return run
            final_state = "finished" if reason == "finished" else "stopped"
            run = replace(run, ended_mono=now, end_reason=reason, end_detail=detail, state=final_state)
            self._runs[run_id] = run
        completed = sum(1 for m in run.repetitions if m.ok)
        # "Not started" only for a run refused before its first movement: a script that marks no repetitions
        # (the seed's Fig. 18) still moved the patient; its movements are counted from the handle (metrics).
        self._emit(RUN_END, run_id=run_id, reason=reason, detail=detail, completed=completed,
                   not_started=reason == "refused" and not run.repetitions, ended_mono=now)
        return run

    def end_current(self, reason: str, detail: str = "") -> ExerciseRun | None:
        run = self.current()
        return self.end(run.run_id, reason, detail) if run is not None else None

    def end_running(self, reason: str, detail: str = "") -> list[ExerciseRun]:
        """End every run still running (a session's end, the application closing), each with its record."""
        ended = [self.end(run.run_id, reason, detail) for run in self.runs() if run.running]
        return [run for run in ended if run is not None]

    # ------------------------------------------------------------------ internals
    def _update(self, run_id: str, fn: Callable[[ExerciseRun], ExerciseRun]) -> ExerciseRun | None:
        with self._lock:
            run = self._runs.get(run_id)
            if run is None:
                return None
            run = fn(run)
            self._runs[run_id] = run
        return run

    def _emit(self, kind: str, **data: Any) -> None:
        if self._record is not None:
            self._record(kind, log=self.log_id, **data)


def repetitions_done(run: ExerciseRun) -> int:
    """The repetitions the exercise itself ended (completed or skipped), not those its interruption cut short."""
    return sum(1 for m in run.repetitions if m.end_mono is not None and not m.interrupted)


def remaining_repetitions(run: ExerciseRun, parameter: str) -> int:
    """How many of the run's planned repetitions (its parameter ``parameter``) are still to do: what Recover's
    "continue with the remaining repetitions" runs. 0 when none (or the run does not say how many)."""
    planned = run.params_dict().get(parameter)
    try:
        total = int(planned)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return 0
    return max(0, total - repetitions_done(run))


def restart_candidate(runs: Sequence[ExerciseRun]) -> ExerciseRun | None:
    """The run Recover offers to start again: the running one (Recover stops it first), else the last run if a
    STOP, an error or the operator interrupted it. Console entries that finished (a value looked at after the
    STOP) do not hide the interrupted run before them."""
    for run in reversed(runs):
        if run.running:
            return run
        if run.program.kind == "console" and run.end_reason == "finished":
            continue
        return run if run.end_reason in INTERRUPTED_REASONS else None
    return None


def runs_from_events(events: Iterable[Mapping[str, Any]], t_end: float | None = None) -> list[ExerciseRun]:
    """Rebuild the runs from a session's events (``t_mono`` times). A run without ``run_end`` (the app crashed)
    ends at ``t_end`` (the record's last time) with reason ``crashed``."""
    runs: dict[str, ExerciseRun] = {}
    logs: dict[str, str] = {}  # run id -> the log its run_start named ("" in a record from before the field)
    order: list[str] = []
    last_t = 0.0
    for e in events:
        kind = e.get("kind")
        data = e.get("data") or {}
        t = float(e.get("t_mono", last_t))
        last_t = max(last_t, t)
        run_id: str = data.get("run_id") or ""
        if kind == RUN_START and run_id:
            params = tuple(RunParameter(str(p.get("name", "")), str(p.get("label", p.get("name", ""))),
                                        p.get("value"), str(p.get("unit", "")))
                           for p in data.get("parameters") or [])
            runs[run_id] = ExerciseRun(run_id=run_id, program=Program.from_dict(data.get("program") or {}),
                                       parameters=params, source=data.get("source", "script_tab"),
                                       operator=str(data.get("operator") or e.get("who") or ""),
                                       started_mono=t, started_wall=0.0, restart_of=data.get("restart_of"),
                                       continues=data.get("continues"),
                                       holds=tuple(data.get("holds") or ("robot", "stimulator")),
                                       compose=tuple(data.get("compose") or ()))
            logs[run_id] = str(data.get("log") or "")
            order.append(run_id)
            continue
        run = runs.get(run_id) if run_id else None
        if run is None:
            continue
        if data.get("log") and logs[run_id] and data["log"] != logs[run_id]:
            continue  # the same id in another run log (a run still open when the session began): not this run
        if kind == RUN_STATE and run.running:
            runs[run_id] = replace(run, state=str(data.get("state", run.state)),
                                   state_detail=str(data.get("detail", "")))
        elif kind == RUN_END and run.running:
            reason = str(data.get("reason", "finished"))
            runs[run_id] = replace(run, ended_mono=t, end_reason=reason, end_detail=str(data.get("detail", "")),
                                   state="finished" if reason == "finished" else "stopped")
        elif kind == PROMPT:
            pass  # prompts are read by the metrics from the events themselves
        elif kind == "repetition_start":
            idx = int(data.get("index", len(run.repetitions) + 1))
            runs[run_id] = replace(run, repetitions=(*run.repetitions, RepetitionMark(idx, t)))
        elif kind == "repetition_end":
            reps = list(run.repetitions)
            idx = int(data.get("index", 0))
            for k in range(len(reps) - 1, -1, -1):
                if reps[k].end_mono is None and (reps[k].index == idx or not idx):
                    reps[k] = replace(reps[k], end_mono=t, ok=bool(data.get("ok", True)),
                                      interrupted="status" in data)  # closed by the run's end (progress)
                    break
            runs[run_id] = replace(run, repetitions=tuple(reps))
    end = last_t if t_end is None else t_end
    out = []
    for r in order:
        run = runs[r]
        if run.running:
            run = replace(run, ended_mono=end, end_reason="crashed", state="stopped")
        out.append(run)
    return out


@dataclass(frozen=True)
class RunMetricsRef:
    """What :func:`app.session.metrics.metrics_by_run` returns per run (the reports' input); defined in
    app/session/metrics.py.

    Documented here so the reports and the metrics agree: ``run`` (ExerciseRun), ``repetitions`` (list of the
    metrics module's per-repetition dicts, numbered within the run from 1), ``summary`` (that run's own
    summary dict), ``positioning`` (robot positioning moves within the run, reported apart)."""

    run: ExerciseRun
    repetitions: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    positioning: list[dict[str, Any]] = field(default_factory=list)
