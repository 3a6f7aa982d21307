"""Printable reports for the medical record: a PDF per session and a progress PDF per patient.

Drawn with Qt's own PDF writer (QPdfWriter + QPainter: no new dependency). The session's unit is the
exercise run (app/core/runs.py): the session report lists every run (interrupted and restarted ones with their
causes), then per run its title, its parameters in words with units, its repetitions numbered within the run
and its own summary, with the values the on-screen summary shows (app/ui/session_summary.py reads the same
:func:`run_reports`). The progress report trends each exercise across sessions; a session whose runs of
that exercise were all interrupted is marked, not drawn as a decline. Also the command line's ``--metrics`` /
``--report`` / ``--progress``.
"""

from __future__ import annotations

import datetime as _dt
import errno
import functools
import json
import math
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from app.core import streams
from app.core.runs import ExerciseRun, Program, RunParameter, runs_from_events
from app.session.alarm_count import counted_alarms
from app.session.clinical_words import event_words, is_technical, plain, source_words
from app.session.delivered import ElectrodeSetupRecord, StimulationRecord, electrode_setups, stimulation_outside_runs
from app.session.metrics import SUMMARY_METRICS, metrics_of_session

# Session metrics shown as trends across sessions (key in the summary → label, unit)
TREND_METRICS: tuple[tuple[str, str, str], ...] = (
    ("peak_speed_m_s", "Peak speed", "m/s"),
    ("sparc", "Smoothness (SPARC)", ""),
    ("range_m", "Range of motion", "m"),
    ("movement_time_s", "Movement time", "s"),
    ("reaction_time_s", "Reaction time", "s"),
    ("speed_peaks", "Speed peaks", ""),
    ("mean_force_n", "Mean interaction force", "N"),
    ("mean_alpha", "Assistance α", ""),
    ("mean_a_r", "Robot assistance a_r", ""),
)
SCORES: tuple[tuple[str, str], ...] = (
    ("fugl_meyer_ue", "Fugl-Meyer UE (0–66)"),
    ("action_research_arm_test", "ARAT (0–57)"),
    ("box_and_block", "Box and Block (blocks/min)"),
    ("modified_ashworth", "Modified Ashworth (0–4)"),
)
# Repetition table of the session report and of the on-screen summary: (key, header, format)
REPETITION_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("index", "#", "{:d}"),
    ("start_s", "Start s", "{:.1f}"),
    ("movement_time_s", "Move s", "{:.2f}"),
    ("range_m", "Range m", "{:.3f}"),
    ("peak_speed_m_s", "Peak m/s", "{:.3f}"),
    ("mean_speed_m_s", "Mean m/s", "{:.3f}"),
    ("sparc", "SPARC", "{:.2f}"),
    ("speed_peaks", "Peaks", "{:d}"),
    ("peak_force_n", "Force N", "{:.1f}"),
    ("grip_at_start_n", "Grip N", "{:.1f}"),
    ("reaction_time_s", "RT s", "{:.2f}"),
    ("completed", "Done", "{}"),
)
SOURCE_TEXT: dict[str, str] = {
    "exercises_tab": "Exercises tab", "script_tab": "Script tab", "console": "script console",
    "headless": "headless (command line)", "recover": "Recover", "plan": "therapy plan",
    "recording": "the recording (no program was run)",
}
# Short definitions printed at the end of the session report (docs/metrics.md has the full ones).
DEFINITIONS: tuple[tuple[str, str], ...] = (
    ("Repetition", "One movement the exercise marked (start → end). \"Done\" = completed: the handle covered "
                   "the movement (criterion in docs/metrics.md), not only the command."),
    ("Move s", "Movement time: from the handle's onset to its end (speed above 5 % of the repetition's peak "
               "speed and at least 5 mm/s)."),
    ("Range m", "Range of motion: the distance between the handle's extreme positions within the repetition."),
    ("Peak / Mean m/s", "The handle's highest speed, and its mean speed over the movement itself."),
    ("SPARC", "Spectral arc length of the speed profile: smoothness, always negative; closer to 0 is smoother "
              "(a minimum-jerk reach ≈ −1.4)."),
    ("Peaks", "Number of speed peaks within the movement: 1 for a smooth reach; more = sub-movements."),
    ("Force N", "Peak interaction force between the patient and the handle."),
    ("Grip N", "Grip force measured in the 100 ms before the repetition started."),
    ("RT s", "Reaction time: how long the patient took to respond to the exercise's cue (exact definition: "
             "docs/metrics.md, \"Reaction time\")."),
    ("α, a_r, a_f", "α: the patient model's assistance level (0 = none … 1 = full); a_r: the robot's share of "
                    "the assistance; a_f: the stimulation's share."),
    ("FES charge", "Charge delivered per stimulator channel over the repetitions (current × pulse width × "
                   "pulses), in mC."),
    ("Alarms", "Warnings, stop and fatal alarms raised, each once (an emergency stop is one stop alarm). Not "
               "counted: information messages (\"Emergency stop reset\", \"reconnected\"), repeats of an open "
               "alarm, acknowledgements, data gaps."),
    ("Response, N", "Electrode set-up: the change of the force on the handle during a test burst, in the "
                    "district's direction, minus the force just before it."),
    ("Motor threshold", "Electrode set-up: the lowest test current whose response reached the detection level "
                        "(0.5 N unless set otherwise)."),
    ("Discomfort", "The patient's rating of a combination's test bursts: 0 = none … 10 = the worst imaginable."),
)


def fmt(value: Any, spec: str | None = None) -> str:
    """A value as the reports and the on-screen summary show it: "—" when unknown, never an exponent."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if spec is None:
        return number_text(value)
    try:
        text = spec.format(value)
        if text.startswith("-") and not any(c in "123456789" for c in text):
            return text[1:]  # a negative value that rounds to zero reads "0.00", not "-0.00"
        return text
    except (ValueError, TypeError):
        return str(value)


def number_text(value: Any, digits: int = 3) -> str:
    """``digits`` significant digits in plain notation (0.000123 → "0.000123", 9240.4 → "9240")."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return str(value)
    if isinstance(value, int):
        return str(value)
    if not math.isfinite(value):
        return "—"
    if abs(value) < 1e-9:  # a spread of rounding noise (identical repetitions) is no spread
        return "0"
    decimals = min(6, max(0, digits - 1 - math.floor(math.log10(abs(value)))))
    text = f"{value:.{decimals}f}"
    return "0" if float(text) == 0 else text


def charge_text(microcoulomb: float) -> str:
    """FES charge in the unit that reads best: µC below 1 mC, mC above (never "9.24e+03 µC")."""
    if microcoulomb is None or not math.isfinite(float(microcoulomb)):
        return "—"
    if abs(microcoulomb) >= 1000.0:
        return f"{number_text(microcoulomb / 1000.0)} mC"
    return f"{number_text(float(microcoulomb))} µC"


# ------------------------------------------------------------------------------------------- runs
def legacy_runs(events: Sequence[Mapping[str, Any]], t_end: float) -> list[ExerciseRun]:
    """Runs of a recording made before the run record existed (no ``run_start``): each ``script_start`` opens
    one (its ``exercise_start`` just before gives the title and parameters), ``script_stop`` closes it."""
    runs: list[ExerciseRun] = []
    pending_exercise: dict[str, Any] | None = None
    current: ExerciseRun | None = None

    def close(run: ExerciseRun, t: float, status: str, detail: str) -> ExerciseRun:
        reason = {"finished": "finished", "stopped": "stopped_by_operator", "error": "script_error",
                  "emergency_stop": "emergency_stop"}.get(status, "crashed" if status == "crashed" else "finished")
        return replace(run, ended_mono=t, end_reason=reason, end_detail=detail,
                       state="finished" if reason == "finished" else "stopped")

    for e in events:
        kind = e.get("kind")
        data = e.get("data") if isinstance(e.get("data"), dict) else {}
        t_mono = e.get("t_mono", 0.0)
        if not isinstance(t_mono, int | float) or isinstance(t_mono, bool) or not math.isfinite(t_mono):
            continue  # a malformed time (app.session.recording lists it among the problems): no place on the time line
        t = float(t_mono)
        if kind == "exercise_start":
            pending_exercise = {**data, "_t": t}
        elif kind == "script_start":
            if current is not None:
                runs.append(close(current, t, "crashed", ""))
            name = str(data.get("name") or "script")
            if pending_exercise is not None:
                ident = str(pending_exercise.get("exercise") or name)
                title = str(pending_exercise.get("title") or "") or _library_title(ident) or ident
                program = Program("exercise", ident, title, "", path=str(pending_exercise.get("script") or ""))
                params = _parameters_in_words(ident, pending_exercise.get("params") or {})
                source = "exercises_tab"
            else:
                program = Program("script_file", name, name, "", path=name)
                params, source = (), "script_tab"
            # the run starts with its form's exercise_start (its parameters belong to it), else its script
            began = float(pending_exercise["_t"]) if pending_exercise is not None else t
            current = ExerciseRun(f"run-{len(runs) + 1}", program, params, source, str(e.get("who") or ""),  # type: ignore[arg-type]
                                  began, 0.0)
            pending_exercise = None
        elif kind == "script_stop" and current is not None:
            runs.append(close(current, t, str(data.get("status") or "finished"),
                              str(data.get("message") or data.get("reason") or "")))
            current = None
    if current is not None:
        runs.append(close(current, t_end, "crashed", ""))
    return runs


def _library_title(ident: str) -> str:
    try:
        from app.therapy.exercises import find_exercise

        return find_exercise(ident).title
    except Exception:  # an exercise since removed from the library: its id is its name
        return ""


def _parameters_in_words(ident: str, params: Mapping[str, Any]) -> tuple[RunParameter, ...]:
    """Raw ``{name: value}`` with the library's labels and units where the exercise is still known."""
    try:
        from app.therapy.exercises import find_exercise

        exercise = find_exercise(ident)
        known = {p.name: p for p in exercise.parameters}
    except Exception:
        known = {}
    out = []
    for name, value in params.items():
        p = known.get(name)
        out.append(RunParameter(name, p.label if p else name.replace("_", " "), value, p.unit if p else ""))
    return tuple(out)


def session_runs(session: Any) -> list[ExerciseRun]:
    """The session's runs: from the run record, or rebuilt from an older recording's script events. Each run's
    wall-clock start is filled from the manifest (the record keeps monotonic times)."""
    events = list(session.events)
    if any(e.get("kind") == "run_start" for e in events):
        runs = runs_from_events(events, t_end=session.end_mono)
    else:
        runs = legacy_runs(events, session.end_mono)
    if not runs:  # a recording with no program at all: its movements (segmented from the speed) as one block
        runs = [ExerciseRun("session", Program("console", "", "Movements without an exercise run", ""), (),
                            "recording", "", session.start_mono, 0.0, ended_mono=session.end_mono,  # type: ignore[arg-type]
                            end_reason="session_ended", state="stopped")]
    start = (session.manifest.get("start") or {})
    epoch = start.get("t_wall_epoch_s")
    wall0 = None
    try:
        wall0 = _dt.datetime.fromisoformat(str(start.get("t_wall"))).timestamp()
    except ValueError:
        wall0 = float(epoch) if isinstance(epoch, int | float) and epoch else None
    if wall0 is None:
        return runs
    return [replace(r, started_wall=wall0 + (r.started_mono - session.start_mono)) if not r.started_wall else r
            for r in runs]


END_GRACE_S = 0.5  # what the record writes just after a run's end (the script's stop) still belongs to it


def run_at(runs: Sequence[ExerciseRun], t_mono: float) -> ExerciseRun | None:
    """The run an event at ``t_mono`` belongs to: the one running then (start < t ≤ end; an event at a
    restart's very start is the previous run's end), else the one that ended just before (0.5 s)."""
    for r in runs:
        end = r.ended_mono if r.ended_mono is not None else math.inf
        if r.started_mono < t_mono <= end:
            return r
    for r in runs:
        if r.ended_mono is not None and r.ended_mono < t_mono <= r.ended_mono + END_GRACE_S:
            return r
    return None


def run_titles(folder: Path) -> tuple[str, ...]:
    """The exercises of a session's runs in order (:func:`exercise_identity`: one exercise, one name, whatever
    started it), from its events alone (no streams: the sessions list stays fast); empty for a recording made
    before the run record."""
    from app.session.recording import EVENTS_FILE, read_events

    events, _ = read_events(Path(folder) / EVENTS_FILE)
    return tuple(exercise_identity(Program.from_dict((e.get("data") or {}).get("program") or {}))[1]
                 for e in events if e.get("kind") == "run_start")


# ------------------------------------------------------------------------------------------- one exercise, one name
# The app's example scripts (resources/scripts) that are the library exercise of another name: the seed's own text
# of the trigger exercise (resources/exercises/trigger_reaching.yaml says so). The others share the exercise's id.
EXAMPLE_SCRIPT_EXERCISE: dict[str, str] = {"trigger_exercise.py": "trigger_reaching"}


@dataclass(frozen=True)
class _Library:
    titles: dict[str, str]  # exercise id → title
    by_hash: dict[str, str]  # text hash of a script (the library's or an example's) → exercise id
    by_path: dict[str, str]  # resolved path of such a script → exercise id


@functools.lru_cache(maxsize=1)
def _library() -> _Library:
    """The library's exercises and the example scripts that are the same exercises (read once per process)."""
    from app.core.resources import resource_path
    from app.core.runs import text_hash
    from app.therapy.exercises import load_library

    titles: dict[str, str] = {}
    by_hash: dict[str, str] = {}
    by_path: dict[str, str] = {}

    def add(path: Path, ident: str) -> None:
        try:
            by_hash[text_hash(path.read_text(encoding="utf-8"))] = ident
            by_path[str(path.resolve())] = ident
        except (OSError, UnicodeDecodeError):
            pass

    try:
        exercises = load_library()[0]
    except Exception:  # no library (a broken install): every run keeps its own name
        exercises = []
    for e in exercises:
        titles[e.ident] = e.title
        add(e.script, e.ident)
    try:
        examples = sorted(resource_path("scripts").glob("*.py"))
    except OSError:
        examples = []
    for path in examples:
        ident = EXAMPLE_SCRIPT_EXERCISE.get(path.name, path.stem)
        if ident in titles:
            add(path, ident)
    return _Library(titles, by_hash, by_path)


def exercise_identity(program: Program) -> tuple[str, str]:
    """(key, name) under which a run's program is counted across sessions (the progress report, the sessions
    browser). The rule (docs/sessions.md, "One exercise, one name"): a run is the library exercise E when its
    program is E (Exercises tab, plan, Recover: kind "exercise", E's id), or when it ran E's script or one of the
    app's example scripts of E (resources/scripts/<id>.py; the seed's trigger_exercise.py for trigger reaching),
    recognised by the text's hash or by the file's path — from the Script tab, the console or headless alike. Its
    name is then E's title as the library has it now. Any other program is its own: a script by its file name,
    console code as "Console code"."""
    lib = _library()
    ident = ""
    if program.kind == "exercise" and program.ident:
        ident = program.ident
    elif program.kind in ("script_file", "console"):
        ident = lib.by_hash.get(program.text_sha256, "")
        if not ident and program.path:
            try:
                ident = lib.by_path.get(str(Path(program.path).resolve()), "")
            except (OSError, ValueError):
                ident = ""
    if ident:
        return f"exercise:{ident}", lib.titles.get(ident) or program.title or _library_title(ident) or ident
    if program.kind == "console":
        return "console", program.title or "Console code"
    name = Path(program.path).name if program.path else (program.title or program.ident or "program")
    return f"script:{name}", program.title or name


@dataclass
class RunReport:
    """One run with its metrics, as the reports and the on-screen summary show it."""

    run: ExerciseRun
    number: int  # the run's number in the session, from 1
    repetitions: list[dict[str, Any]]  # numbered within the run, from 1
    summary: dict[str, Any]
    positioning: list[dict[str, Any]] = field(default_factory=list)  # robot positioning moves, not repetitions
    alarms: list[dict[str, Any]] = field(default_factory=list)

    @property
    def title(self) -> str:
        return self.run.title or self.run.program.ident or "program"

    @property
    def exercise(self) -> str:
        """The exercise's one name across tabs and sessions (:func:`exercise_identity`)."""
        if self.run.program.kind == "console" and not self.run.program.ident:  # movements without a program
            return self.title
        return exercise_identity(self.run.program)[1]

    @property
    def completed(self) -> int:
        return sum(1 for r in self.repetitions if r.get("completed"))

    @property
    def interrupted(self) -> bool:
        return self.run.end_reason not in ("finished", None)

    def reps_text(self) -> str:
        if not self.repetitions:
            return "not started" if self.run.end_reason not in ("finished", None) else "none"
        return f"{self.completed} of {len(self.repetitions)} completed"


def run_reports(session: Any, runs: Sequence[ExerciseRun] | None = None) -> list[RunReport]:
    """Per run: its repetitions (numbered within it), its own summary, its alarms.

    The one adapter to the metrics: :func:`app.session.metrics.metrics_by_run` where it exists (the run-aware metrics:
    repetitions decided from the handle, positioning moves apart), otherwise today's
    :func:`app.session.metrics.metrics_of_session` sliced to each run's [start, end]. After the metrics branch is merged
    the fallback can go."""
    from app.session import metrics

    runs = list(runs) if runs is not None else session_runs(session)
    by_run = getattr(metrics, "metrics_by_run", None)
    numbers = {r.run_id: k + 1 for k, r in enumerate(runs)}
    all_alarms = alarms_of_session(session)
    t0 = session.start_mono

    def alarms_of(run: ExerciseRun) -> list[dict[str, Any]]:
        return [a for a in all_alarms if run_at(runs, a["t_s"] + t0) is run]

    out: list[RunReport] = []
    if by_run is not None and any(e.get("kind") == "run_start" for e in session.events):
        for ref in by_run(session):
            run = next((r for r in runs if r.run_id == ref.run.run_id), ref.run)
            out.append(RunReport(run, numbers.get(run.run_id, len(out) + 1), list(ref.repetitions),
                                 dict(ref.summary), list(getattr(ref, "positioning", []) or []), alarms_of(run)))
        return out
    for run in runs:
        end = run.ended_mono if run.ended_mono is not None else session.end_mono
        m = metrics_of_session(session, run.started_mono, end)
        reps = [dict(r, index=k + 1) for k, r in enumerate(m["repetitions"])]
        out.append(RunReport(run, numbers[run.run_id], reps, m["summary"], [], alarms_of(run)))
    return out


@dataclass
class SessionReportData:
    folder: Path
    manifest: dict[str, Any]
    metrics: dict[str, Any]  # the whole session's (alarms, the handle's position)
    runs: list[RunReport]
    position: tuple[list[float], list[float]]  # (t s from the start, handle position m), decimated
    problems: list[str]
    profile: Any = None  # the patient's profile (app.therapy.patients) as it is now, when it can be read
    events: list[dict[str, Any]] = field(default_factory=list)  # the record's events (acknowledgements, ids)
    setups: list[ElectrodeSetupRecord] = field(default_factory=list)  # the electrode set-ups, in order
    stimulation: list[StimulationRecord] = field(default_factory=list)  # FES started outside every run
    end_mono: float = 0.0
    origin: str = ""  # where the session was read from when not its station's folder (an archived session's copy)

    @property
    def patient_id(self) -> str:
        return str(self.manifest.get("patient_id") or self.folder.parent.name)

    @property
    def started(self) -> str:
        return str((self.manifest.get("start") or {}).get("t_wall", ""))

    @property
    def exercises(self) -> list[str]:
        return [r.title for r in self.runs]


def session_report_data(folder: str | Path, profile: Any = None, origin: str = "") -> SessionReportData:
    """What the session's report shows, read from ``folder``; ``origin``: what the folder is when it is not the
    station's own (an archived session materialised into a temporary folder: "archived session <uuid> …")."""
    from app.session.recording import load_session

    session = load_session(folder)
    metrics = metrics_of_session(session)
    runs = run_reports(session)
    t: list[float] = []
    x: list[float] = []
    vsa = session.streams.get(streams.LINARM_VSA)
    if vsa is not None and len(vsa.t) and "handlePos" in vsa.data:
        step = max(1, len(vsa.t) // 2000)
        t = [float(v) - session.start_mono for v in vsa.t[::step]]
        x = [float(v) for v in vsa.data["handlePos"][::step]]
    if profile is None:
        profile = _profile_of(session.manifest.get("patient_id") or Path(folder).parent.name)
    events = [dict(e) for e in session.events]
    fes = session.streams.get(streams.FES_CHANNELS)
    return SessionReportData(Path(folder), session.manifest, metrics, runs, (t, x), list(session.problems), profile,
                             events, electrode_setups(events, fes),
                             stimulation_outside_runs(events, [r.run for r in runs], session.end_mono, fes),
                             float(session.end_mono), origin)


def _profile_of(patient_id: str) -> Any:
    from app.therapy.patients import load_patient

    try:
        return load_patient(str(patient_id))
    except Exception:  # no profile (a pseudonymous recording moved elsewhere): the manifest's copy is used
        return None


@dataclass
class ExerciseTrend:
    """One exercise within one session: its runs pooled (same exercise, same measures)."""

    title: str
    repetitions: int
    completed: int
    values: dict[str, float]  # trend metric → mean over the exercise's repetitions
    interrupted: bool  # none of the exercise's runs in that session finished


@dataclass
class ProgressRow:
    """One session of a patient, as a point of the trends."""

    folder: Path
    started: str  # ISO
    exercises: tuple[str, ...]
    summary: dict[str, Any]
    scores: dict[str, Any]  # the clinical scores in the profile at that session
    complete: bool
    per_exercise: dict[str, ExerciseTrend] = field(default_factory=dict)
    uuid: str = ""  # the session's UUID when it was read from the archive (app.archive.reads)
    station: str = ""  # the station that recorded it, when read from the archive

    def value(self, key: str) -> float | None:
        entry = self.summary.get(key)
        if isinstance(entry, dict):
            return entry.get("mean")
        return entry if isinstance(entry, int | float) else None

    @property
    def date(self) -> str:
        """Date and time (two sessions on one day stay apart)."""
        try:
            return _dt.datetime.fromisoformat(self.started).strftime("%Y-%m-%d %H:%M")
        except ValueError:
            name = self.folder.name  # YYYYMMDD-HHMMSS
            return f"{name[:4]}-{name[4:6]}-{name[6:8]} {name[9:11]}:{name[11:13]}" if len(name) >= 13 else name

    @property
    def interrupted(self) -> bool:
        return not self.complete or (bool(self.per_exercise)
                                     and all(e.interrupted for e in self.per_exercise.values()))


def shows_stations(rows: Iterable[ProgressRow]) -> bool:
    """Whether a progress table has a Station column (the report's and the window's). Read from the clinic's
    archive, the sessions come from several stations: each row says which (a session still waiting in this
    station's outbox says so). A station's own folders alone: no column."""
    return any(r.station for r in rows)


def exercise_trends(reports: Iterable[RunReport]) -> dict[str, ExerciseTrend]:
    """Per exercise (:func:`exercise_identity`: its runs from any tab under one name), its runs pooled."""
    groups: dict[str, list[RunReport]] = {}
    for r in reports:
        groups.setdefault(r.exercise, []).append(r)
    out = {}
    for title, group in groups.items():
        reps = [rep for r in group for rep in r.repetitions]
        values = {}
        for key, _label, _unit in TREND_METRICS:
            xs = [float(v) for rep in reps if isinstance(v := rep.get(key), int | float) and not isinstance(v, bool)
                  and math.isfinite(float(v))]
            if xs:
                values[key] = sum(xs) / len(xs)
        out[title] = ExerciseTrend(title, len(reps), sum(1 for rep in reps if rep.get("completed")), values,
                                   all(r.interrupted for r in group))
    return out


def progress_rows(patient_id: str, root: Path | None = None,
                  progress: Callable[[float], None] | None = None) -> list[ProgressRow]:
    """Every session of the patient in the station's folders, oldest first, with its metrics summary (reads every
    stream). With the clinic's archive, :func:`app.archive.reads.progress_rows` adds every station's."""
    from app.session.recording import list_sessions

    sessions = list(reversed(list_sessions(patient_id, root)))
    rows = []
    for k, s in enumerate(sessions):
        if progress is not None:
            progress(k / max(1, len(sessions)))
        rows.append(folder_progress_row(s))
    if progress is not None:
        progress(1.0)
    return rows


def folder_progress_row(s: Any) -> ProgressRow:
    """One session folder (its ``app.session.recording.SessionSummary``) as a row of the progress report, from its
    files."""
    from app.session.recording import load_session

    session = load_session(s.folder)
    m = metrics_of_session(session)
    reports = run_reports(session)
    scores = dict(((session.manifest.get("patient") or {}).get("scores")) or {})
    titles = tuple(dict.fromkeys(r.exercise for r in reports)) or s.exercises
    return ProgressRow(s.folder, s.start, titles, m["summary"], scores, s.complete, exercise_trends(reports))


def alarms_of_session(session: Any) -> list[dict[str, Any]]:
    """Alarms and interruptions of a session, times from its start: the metrics' list (one definition)."""
    from app.session.metrics import session_alarms

    return session_alarms(session)


# ------------------------------------------------------------------------------------------- drawing
def _ensure_gui_app() -> Any:
    from PySide6.QtCore import QCoreApplication
    from PySide6.QtGui import QGuiApplication

    app = QCoreApplication.instance()
    if app is None:
        import os

        if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # a PDF needs fonts, not a screen
        app = QGuiApplication([sys.argv[0] if sys.argv else "linarmpp"])
    return app


PLOT_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")
_WRAP = 0x1000  # Qt.TextFlag.TextWordWrap
_ZWSP = "\u200b"  # a break opportunity that prints nothing


class _Pdf:
    """A4 pages drawn top to bottom with a cursor; a new page when the next block does not fit. Every text is
    measured before it is drawn and wrapped in its own box, so no text runs into another or off the page."""

    DPI = 96
    MARGIN = 48

    def __init__(self, path: Path, title: str, footer: str) -> None:
        from PySide6.QtCore import QMarginsF
        from PySide6.QtGui import QPageLayout, QPageSize, QPainter, QPdfWriter

        self.writer = QPdfWriter(str(path))
        self.writer.setResolution(self.DPI)
        self.writer.setTitle(title)
        self.writer.setCreator("LINarm++ Manager")
        self.writer.setPageLayout(QPageLayout(QPageSize(QPageSize.PageSizeId.A4), QPageLayout.Orientation.Portrait,
                                              QMarginsF(0, 0, 0, 0)))
        self.painter = QPainter()
        if not self.painter.begin(self.writer):
            raise OSError(f"cannot write {path}")
        self.width = self.writer.width()
        self.height = self.writer.height()
        self.footer = footer
        self.page = 1
        self.y = float(self.MARGIN)

    @property
    def inner_width(self) -> float:
        return self.width - 2 * self.MARGIN

    @property
    def bottom(self) -> float:
        return self.height - self.MARGIN - 20

    def font(self, size: float, bold: bool = False) -> None:
        from PySide6.QtGui import QFont

        f = QFont("DejaVu Sans")
        f.setPointSizeF(size)
        f.setBold(bold)
        self.painter.setFont(f)

    def measure(self, text: str, width: float) -> float:
        """The height ``text`` takes wrapped in ``width`` with the current font."""
        rect = self.painter.fontMetrics().boundingRect(0, 0, max(1, int(width)), 100000, _WRAP, text)
        return float(rect.height())

    def breakable(self, text: str, width: float) -> str:
        """``text`` with break opportunities inside the words wider than ``width`` (a path, an id): Qt wraps at
        spaces only and would let such a word run past its box. Words that fit are left whole."""
        metrics = self.painter.fontMetrics()
        out = []
        for word in text.split(" "):
            if metrics.horizontalAdvance(word) <= width:
                out.append(word)
                continue
            pieces, piece = [], ""
            for ch in word:
                if piece and metrics.horizontalAdvance(piece + ch) > width - 2:
                    pieces.append(piece)
                    piece = ""
                piece += ch
            out.append(_ZWSP.join([*pieces, piece]))
        return " ".join(out)

    def text_width(self, text: str) -> float:
        return float(self.painter.fontMetrics().horizontalAdvance(text))

    def ensure(self, h: float) -> None:
        if self.y + h > self.bottom:
            self.new_page()

    def new_page(self) -> None:
        self._draw_footer()
        self.writer.newPage()
        self.page += 1
        self.y = float(self.MARGIN)

    def _draw_footer(self) -> None:
        from PySide6.QtCore import QRectF, Qt

        self.font(7)
        self.painter.setPen(self._colour("#555555"))
        number = f"page {self.page}"
        w = self.text_width(number) + 8
        self.painter.drawText(QRectF(self.MARGIN, self.height - self.MARGIN, self.inner_width - w - 10, 16),
                              int(Qt.AlignmentFlag.AlignLeft) | _WRAP, self.footer)
        self.painter.drawText(QRectF(self.MARGIN + self.inner_width - w, self.height - self.MARGIN, w, 16),
                              int(Qt.AlignmentFlag.AlignRight), number)

    @staticmethod
    def _colour(name: str) -> Any:
        from PySide6.QtGui import QColor

        return QColor(name)

    def text(self, text: str, size: float = 9, bold: bool = False, colour: str = "#000000", gap: float = 4,
             indent: float = 0.0) -> None:
        from PySide6.QtCore import QRectF

        self.font(size, bold)
        width = self.inner_width - indent
        text = self.breakable(text, width)
        h = self.measure(text, width)
        self.ensure(h + gap)
        self.painter.setPen(self._colour(colour))
        self.painter.drawText(QRectF(self.MARGIN + indent, self.y, width, h + 2), _WRAP, text)
        self.y += h + gap

    def heading(self, text: str, size: float = 12, keep: float = 60) -> None:
        self.ensure(keep)
        self.y += 6
        self.text(text, size, True, "#1a3d6d", gap=6)

    def subheading(self, text: str, keep: float = 70) -> None:
        """A block's title, kept on one page with the first ``keep`` px of what follows it."""
        self.ensure(keep)
        self.text(text, 9.5, True, "#1a3d6d", gap=3)

    def fields(self, pairs: Sequence[tuple[str, str]], label_width: float = 150) -> None:
        """Label / value rows; both wrap in their own column (a long label never runs into its value)."""
        from PySide6.QtCore import QRectF

        self.font(9, True)
        widest = max((self.text_width(label) for label, _ in pairs), default=0.0) + 12
        label_width = max(label_width, min(widest, 0.4 * self.inner_width))  # a label on one line if it can
        value_width = self.inner_width - label_width
        for label, value in pairs:
            self.font(9, True)
            label = self.breakable(label, label_width - 8)
            lh = self.measure(label, label_width - 8)
            self.font(9)
            value = self.breakable(value, value_width)
            vh = self.measure(value, value_width)
            h = max(lh, vh)
            self.ensure(h + 3)
            self.font(9, True)
            self.painter.setPen(self._colour("#333333"))
            self.painter.drawText(QRectF(self.MARGIN, self.y, label_width - 8, h + 2), _WRAP, label)
            self.font(9)
            self.painter.setPen(self._colour("#000000"))
            self.painter.drawText(QRectF(self.MARGIN + label_width, self.y, value_width, h + 2),
                                  _WRAP, value)
            self.y += h + 3

    def table(self, headers: Sequence[str], rows: Sequence[Sequence[str]], widths: Sequence[float] | None = None,
              size: float = 7.5, align_right: Sequence[int] = ()) -> None:
        """A table whose cells wrap: each row is as tall as its tallest cell; headers repeat on a new page."""
        from PySide6.QtCore import QRectF, Qt

        widths = list(widths or [1.0] * len(headers))
        scale = self.inner_width / sum(widths)
        widths = [w * scale for w in widths]
        pad = 3.0

        def breakable(cells: Sequence[str], bold: bool) -> list[str]:
            self.font(size, bold)
            return [self.breakable(c, w - 2 * pad) for c, w in zip(cells, widths, strict=False)]

        def height_of(cells: Sequence[str], bold: bool) -> float:
            self.font(size, bold)
            return max(self.measure(c, w - 2 * pad) for c, w in zip(cells, widths, strict=False)) + 5

        headers = breakable(headers, True)
        rows = [breakable(row, False) for row in rows]

        def draw_row(cells: Sequence[str], bold: bool, shade: bool, h: float) -> None:
            if shade:
                self.painter.fillRect(QRectF(self.MARGIN, self.y, self.inner_width, h), self._colour("#eef2f7"))
            self.font(size, bold)
            self.painter.setPen(self._colour("#000000"))
            x = float(self.MARGIN)
            for k, (cell, w) in enumerate(zip(cells, widths, strict=False)):
                right = k in align_right  # headers over their numbers
                horizontal = Qt.AlignmentFlag.AlignRight if right else Qt.AlignmentFlag.AlignLeft
                self.painter.drawText(QRectF(x + pad, self.y + 2.5, w - 2 * pad, h - 2.5),
                                      int(horizontal | Qt.AlignmentFlag.AlignTop) | _WRAP, cell)
                x += w
            self.y += h

        def header() -> None:
            h = height_of(headers, True)
            draw_row(headers, True, True, h)
            self.painter.setPen(self._colour("#1a3d6d"))
            self.painter.drawLine(int(self.MARGIN), int(self.y), int(self.MARGIN + self.inner_width), int(self.y))

        first_h = height_of(rows[0], False) if rows else 0.0
        self.ensure(height_of(headers, True) + first_h)
        header()
        for k, row in enumerate(rows):
            h = height_of(row, False)
            if self.y + h > self.bottom:
                self.new_page()
                header()
            draw_row(row, False, k % 2 == 1, h)
        self.y += 6

    def rule_line(self, label: str, width: float, left: float) -> None:
        """A line to write on, its label under it (the sign-off block)."""
        from PySide6.QtCore import QPointF, QRectF

        self.painter.setPen(self._colour("#000000"))
        self.painter.drawLine(QPointF(left, self.y + 26), QPointF(left + width, self.y + 26))
        self.font(7.5)
        self.painter.setPen(self._colour("#444444"))
        self.painter.drawText(QRectF(left, self.y + 29, width, 12), 0, label)

    def plot(self, title: str, series: Sequence[tuple[str, Sequence[float], Sequence[float | None]]],
             unit: str = "", x_label: str = "", width: float | None = None, height: float = 150,
             x_ticks: Sequence[tuple[float, str]] | None = None, shade: Sequence[tuple[float, float]] = (),
             markers: bool = True, left: float | None = None, advance: bool = True,
             hollow: Sequence[tuple[float, float]] = (), connect: bool = True) -> None:
        """A line plot: ``series`` = [(name, x, y)] (None values skipped); ``hollow`` points are drawn as open
        circles outside the lines (interrupted sessions)."""
        from PySide6.QtCore import QPointF, QRectF, Qt
        from PySide6.QtGui import QPen, QPolygonF

        width = width or self.inner_width
        if advance:
            self.ensure(height + 10)
        p = self.painter
        x0 = self.MARGIN if left is None else left
        self.font(8.5, True)
        p.setPen(self._colour("#1a3d6d"))
        full_title = title + (f" [{unit}]" if unit else "")
        p.drawText(QRectF(x0, self.y, width, 14), 0, self._elide(full_title, width))
        box = QRectF(x0 + 46, self.y + 18, width - 56, height - 42)
        p.setPen(self._colour("#888888"))
        p.drawRect(box)
        pts = [(float(x), float(y)) for _, xs, ys in series for x, y in zip(xs, ys, strict=False)
               if y is not None and math.isfinite(float(y))] + [(float(x), float(y)) for x, y in hollow]
        if not pts:
            self.font(8)
            p.drawText(box, int(Qt.AlignmentFlag.AlignCenter), "no data")
        else:
            xmin = min(x for x, _ in pts)
            xmax = max(x for x, _ in pts)
            if x_ticks:
                xmin, xmax = min(xmin, min(x for x, _ in x_ticks)), max(xmax, max(x for x, _ in x_ticks))
            if xmax == xmin:
                xmin, xmax = xmin - 1, xmax + 1
            span = xmax - xmin
            xmin, xmax = xmin - 0.04 * span, xmax + 0.04 * span  # end markers and labels stay inside
            ymin, ymax = y_range([y for _, y in pts])

            def to_px(x: float, y: float) -> QPointF:
                return QPointF(box.left() + (x - xmin) / (xmax - xmin) * box.width(),
                               box.bottom() - (y - ymin) / (ymax - ymin) * box.height())

            for k, (a, b) in enumerate(shade):
                left_px = to_px(max(a, xmin), ymin).x()
                right_px = to_px(min(b, xmax), ymin).x()
                p.fillRect(QRectF(left_px, box.top(), max(0.5, right_px - left_px), box.height()),
                           self._colour("#dde9cf" if k % 2 == 0 else "#eef4e6"))
            self.font(7)
            yticks, ydec = _nice_ticks(ymin, ymax)
            row_h = p.fontMetrics().height()
            if len(yticks) > 1 and (to_px(xmin, yticks[0]).y() - to_px(xmin, yticks[1]).y()) < row_h + 1:
                yticks = yticks[::2]  # labels closer than their height would touch
            for y in yticks:
                py = to_px(xmin, y).y()
                p.setPen(self._colour("#e0e0e0"))
                p.drawLine(QPointF(box.left(), py), QPointF(box.right(), py))
                p.setPen(self._colour("#444444"))
                p.drawText(QRectF(x0, py - row_h / 2, 42, row_h), int(Qt.AlignmentFlag.AlignRight), f"{y:.{ydec}f}")
            if x_ticks is None:
                xt, xdec = _nice_ticks(xmin, xmax)
                x_ticks = [(x, f"{x:.{xdec}f}") for x in xt]
            widest = max((self.text_width(label) for _, label in x_ticks), default=0.0) + 6
            stride = 1
            while len(x_ticks) > 1 and stride < len(x_ticks) and \
                    (to_px(x_ticks[stride][0], ymin).x() - to_px(x_ticks[0][0], ymin).x()) < widest:
                stride += 1
            for x, label in list(x_ticks)[::stride]:
                px = to_px(x, ymin).x()
                p.drawText(QRectF(px - widest / 2, box.bottom() + 2, widest, row_h), int(Qt.AlignmentFlag.AlignHCenter),
                           label)
            if x_label:
                p.drawText(QRectF(box.left(), box.bottom() + 4 + row_h, box.width(), row_h),
                           int(Qt.AlignmentFlag.AlignHCenter), x_label)
            for k, (_name, xs, ys) in enumerate(series):
                colour = self._colour(PLOT_COLOURS[k % len(PLOT_COLOURS)])
                pen = QPen(colour)
                pen.setWidthF(1.4)
                p.setPen(pen)
                line = [to_px(float(x), float(y)) for x, y in zip(xs, ys, strict=False)
                        if y is not None and math.isfinite(float(y))]
                if connect and len(line) > 1:
                    p.drawPolyline(QPolygonF(line))
                if markers and len(line) < 200:
                    p.setBrush(colour)
                    for q in line:
                        p.drawEllipse(q, 2.2, 2.2)
                    p.setBrush(Qt.BrushStyle.NoBrush)
            if hollow:
                pen = QPen(self._colour("#c62828"))
                pen.setWidthF(1.2)
                p.setPen(pen)
                p.setBrush(Qt.BrushStyle.NoBrush)
                for x, y in hollow:
                    p.drawEllipse(to_px(x, y), 3.5, 3.5)
            if len(series) > 1:  # the legend, inside the plot's top right corner, one name a line
                self.font(7, True)
                names = [name for name, _, _ in series]
                w = max(self.text_width(n) for n in names) + 8
                h = p.fontMetrics().height()
                p.fillRect(QRectF(box.right() - w - 2, box.top() + 2, w, h * len(names) + 2), self._colour("#ffffff"))
                for k, name in enumerate(names):
                    p.setPen(self._colour(PLOT_COLOURS[k % len(PLOT_COLOURS)]))
                    p.drawText(QRectF(box.right() - w, box.top() + 2 + k * h, w - 4, h),
                               int(Qt.AlignmentFlag.AlignRight), name)
        if advance:
            self.y += height + 6

    def _elide(self, text: str, width: float) -> str:
        from PySide6.QtCore import Qt

        return self.painter.fontMetrics().elidedText(text, Qt.TextElideMode.ElideRight, int(width))

    def plot_grid(self, plots: Sequence[dict[str, Any]], columns: int = 2, height: float = 150) -> None:
        w = self.inner_width / columns
        for k in range(0, len(plots), columns):
            self.ensure(height + 10)
            for j, spec in enumerate(plots[k:k + columns]):
                self.plot(**{"height": height, **spec}, width=w - 6, left=self.MARGIN + j * w, advance=False)
            self.y += height + 6

    def finish(self) -> int:
        self._draw_footer()
        if not self.painter.end():  # the writer could not finish the file (issue #37: it was ignored)
            raise OSError(errno.EIO, "the PDF writer could not finish the file")
        return self.page


def y_range(values: Sequence[float]) -> tuple[float, float]:
    """The y axis: the data with a margin, and at least 10 % of the largest magnitude tall, so that
    differences at the level of noise do not fill the plot."""
    lo, hi = min(values), max(values)
    span = max(hi - lo, 0.1 * max(abs(lo), abs(hi)), 1e-6)
    mid = (lo + hi) / 2
    lo, hi = min(lo, mid - span / 2), max(hi, mid + span / 2)
    pad = (hi - lo) * 0.08
    return lo - pad, hi + pad


def _nice_ticks(lo: float, hi: float, target: int = 5) -> tuple[list[float], int]:
    """Ticks at 1, 2 or 5 × 10^k inside [lo, hi], and the decimals that show them."""
    raw = (hi - lo) / target
    if raw <= 0 or not math.isfinite(raw):
        return [lo], 2
    exp = math.floor(math.log10(raw))
    step = next(m * 10 ** exp for m in (1, 2, 5, 10) if m * 10 ** exp >= raw)
    first = math.ceil(lo / step) * step
    ticks = [first + k * step for k in range(int((hi - first) / step + 1e-9) + 1)]
    return ticks, max(0, -math.floor(math.log10(step)))


def _footer(what: str) -> str:
    from app.session.recording import app_version

    now = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return f"LINarm++ Manager {app_version()} — {what} — printed {now}"


def _when(iso: str) -> str:
    try:
        return _dt.datetime.fromisoformat(iso).strftime("%Y-%m-%d %H:%M:%S (UTC%z)")
    except ValueError:
        return iso or "unknown"


def _clock(epoch: float) -> str:
    return _dt.datetime.fromtimestamp(epoch).astimezone().strftime("%H:%M:%S") if epoch else "—"


def _duration(seconds: Any) -> str:
    if not isinstance(seconds, int | float):
        return "—"
    m, s = divmod(round(seconds), 60)
    return f"{m} min {s:02d} s"


# ------------------------------------------------------------------------------------------- session PDF
def program_text(run: ExerciseRun) -> str:
    """What ran, in the clinician's words (ids, paths, versions and hashes are in the technical appendix)."""
    prog = run.program
    if prog.kind == "exercise":
        return "library exercise"
    if prog.kind == "console":
        if not prog.ident:
            return "none (the handle's movements, found from its speed)"
        return "code typed in the script console"
    name = Path(prog.path).name if prog.path else plain(prog.ident or prog.title)
    key, exercise = exercise_identity(prog)
    if key.startswith("exercise:"):
        return f"script file {name}, the exercise “{exercise}” run as a script"
    return f"script file {name}"


def program_technical(run: ExerciseRun) -> str:
    """What ran, for the engineer: the run's id, the program's kind, id, file, version and text hash."""
    prog = run.program
    parts = [f"run id {run.run_id}", f"kind {prog.kind}"]
    if prog.ident:
        parts.append(f"id {prog.ident}")
    if prog.path:
        parts.append(f"file {prog.path}")
    if prog.version:
        parts.append(f"version {prog.version}")
    if prog.text_sha256:
        parts.append(f"text sha256 {prog.text_sha256}")
    parts.append(f"end {run.end_reason or 'running'}" + (f": {run.end_detail}" if run.end_detail else ""))
    return "; ".join(parts)


def run_heading(report: RunReport) -> str:
    """A run's name in the session report: its exercise's one name (:func:`exercise_identity`), and the script's
    file when the exercise ran as a script ("Trigger reaching (…) — script trigger_exercise.py")."""
    if report.exercise == report.title:
        return report.title
    return f"{report.exercise} — script {report.title}"


def end_words(run: ExerciseRun) -> str:
    """How a run ended, in the clinician's words (its cause as recorded: technical appendix)."""
    return plain(run.end_text())


def parameters_text(run: ExerciseRun) -> list[tuple[str, str]]:
    """The parameters in words with their units: (label, "value unit"). A script's own names (no label) are said
    as words."""
    out = []
    for p in run.parameters:
        number = isinstance(p.value, int | float) and not isinstance(p.value, bool)
        value = fmt(p.value) if number else plain(fmt(p.value, "{}"))
        label = p.label if p.label and p.label != p.name else plain(p.name)
        out.append((label, value + (f" {p.unit}" if p.unit else "")))
    return out


def summary_rows(summary: Mapping[str, Any]) -> list[list[str]]:
    rows = []
    for key, (unit, label) in SUMMARY_METRICS.items():
        entry = summary.get(key)
        if isinstance(entry, dict):
            rows.append([label + (f" [{unit}]" if unit else ""), fmt(entry.get("mean")), fmt(entry.get("sd")),
                         fmt(entry.get("first")), fmt(entry.get("last")), str(entry.get("n", ""))])
    for ch, q in (summary.get("fes_charge_uc") or {}).items():
        rows.append([f"FES charge, channel {ch}", charge_text(q), "", "", "", "total"])
    return rows


def repetition_row(r: Mapping[str, Any]) -> list[str]:
    return [fmt(r.get(k), f) for k, _, f in REPETITION_COLUMNS]


def alarm_text(data: Mapping[str, Any]) -> str:
    """An alarm's or interruption's own sentence in the clinician's words, and who raised it (the record's own
    wording is in the report's technical appendix: :func:`alarm_technical`)."""
    said = plain(data.get("text") or data.get("reason") or data.get("message") or "")
    device = data.get("device")
    if not said and device:  # a data gap: the device and why
        said = f"{source_words(device)}: {plain(data.get('detail') or data.get('cause') or 'no data')}"
    who = data.get("source")
    if who and data.get("level") is not None:
        name = source_words(who)
        if name.lower() not in said.lower():
            said = f"{said} ({name})" if said else name
    return said


def alarm_technical(kind: str, data: Mapping[str, Any]) -> str:
    """An alarm's or interruption's record as written: its kind and every field."""
    return kind + ": " + ", ".join(f"{k}={v}" for k, v in data.items())


@dataclass(frozen=True)
class AlarmRow:
    """One line of the report's alarms table: when, in which run, what, the details, and its acknowledgement."""

    t_s: float  # from the session's start
    run: str  # the run's number, "—" outside every run
    what: str
    details: str
    acknowledged: str
    counted: bool  # counted in the session's number of alarms (app/session/alarm_count.py)
    technical: str  # the record's own words


def alarm_rows(data: SessionReportData) -> list[AlarmRow]:
    """The session's alarms and interruptions as the report lists them: each stop once (the supervisor's STOP
    alarm; its own ``emergency_stop`` event only where no alarm came with it), no line for a program's end (the
    runs' table says how each ended), and who acknowledged each alarm, when."""
    t0 = float((data.manifest.get("start") or {}).get("t_mono_s") or 0.0)
    counted_ids = {id(e) for e in counted_alarms(data.events)}
    acks: dict[Any, tuple[str, float]] = {}
    for e in data.events:
        if e.get("kind") == "alarm_acknowledged":
            d = e.get("data") or {}
            acks.setdefault(d.get("ident"), (str(d.get("operator") or e.get("who") or ""), float(e.get("t_mono", t0))))
    estop_alarms = [float(e.get("t_mono", t0)) for e in data.events if e.get("kind") == "alarm"
                    and str((e.get("data") or {}).get("text") or "").startswith("Emergency stop")]
    runs = [r.run for r in data.runs]
    number_of = {r.run.run_id: str(r.number) for r in data.runs}
    rows: list[AlarmRow] = []
    kinds = ("alarm", "emergency_stop", "exercise_paused", "exercise_resumed", "gap_start", "command_refused")
    for e in data.events:
        kind = str(e.get("kind") or "")
        if kind not in kinds:
            continue
        d = dict(e.get("data") or {})
        t = float(e.get("t_mono", t0))
        if kind == "emergency_stop" and (any(abs(t - ta) <= 1.0 for ta in estop_alarms)
                                         or id(e) not in counted_ids):
            continue  # the STOP alarm it raised is the line (a press while latched adds nothing)
        run = run_at(runs, t)
        ack = ""
        if kind == "alarm":
            who, when = acks.get(d.get("ident"), ("", 0.0))
            if who or when:
                ack = f"{who or 'operator'}, {_clock_of(data, when)}"
        what = event_words(kind, d)
        rows.append(AlarmRow(t - t0, number_of.get(run.run_id, "—") if run is not None else "—", what,
                             alarm_text(d), ack, id(e) in counted_ids, alarm_technical(kind, d)))
    return rows


def _clock_of(data: SessionReportData, t_mono: float | None) -> str:
    """A monotonic time of the session as the clock showed it (HH:MM:SS), or seconds from the start."""
    start = data.manifest.get("start") or {}
    start_mono = float(start.get("t_mono_s") or 0.0)
    if t_mono is None:
        return "—"
    try:
        start_dt = _dt.datetime.fromisoformat(str(start.get("t_wall")))
    except ValueError:
        return f"{t_mono - start_mono:.0f} s"
    return (start_dt + _dt.timedelta(seconds=t_mono - start_mono)).strftime("%H:%M:%S")


def alarms_summary(data: SessionReportData) -> str:
    """"7 (4 stop alarms, 3 warnings)": the session's alarm count (app/session/alarm_count.py) and its levels."""
    counted = counted_alarms(data.events)
    if not counted:
        return "none"
    levels: dict[str, int] = {}
    for e in counted:
        level = str((e.get("data") or {}).get("level") or ("STOP" if e.get("kind") == "emergency_stop" else ""))
        name = {"STOP": "stop alarm", "FATAL": "fatal alarm", "WARNING": "warning"}.get(level, "alarm")
        levels[name] = levels.get(name, 0) + 1
    parts = [f"{n} {name}{'s' if n > 1 else ''}" for name, n in levels.items()]
    return f"{len(counted)} ({', '.join(parts)})"


def _g(value: Any) -> str:
    """A setting as typed: 8 mA, 12.5 mA, 250 µs (no trailing zeros)."""
    return f"{float(value):g}" if isinstance(value, int | float) else "—"


def _newton(value: Any) -> str:
    """A test burst's response to 0.01 N (below that: 0; a negative response is no response in that direction)."""
    v = round(float(value), 2) if isinstance(value, int | float) else 0.0
    return "0" if v == 0 else f"{v:.2f}"


def _ma(value: float | None) -> str:
    return "—" if value is None else f"{_g(value)} mA"


def _currents_text(currents: Sequence[float]) -> str:
    """"8, 10 … 30 mA" (a ladder said by its first two steps and its end)."""
    if not currents:
        return "none"
    values = [_g(c) for c in currents]
    if len(values) <= 4:
        return ", ".join(values) + " mA"
    return f"{values[0]}, {values[1]} … {values[-1]} mA"


def setup_summary(setup: ElectrodeSetupRecord) -> str:
    """One district's set-up in a sentence: bursts, currents up to the highest, pulse width, and the choice."""
    plan = setup.plan
    width = plan.get("pulse_width_us")
    text = (f"{setup.district}: {setup.bursts} test burst{'s' if setup.bursts != 1 else ''} on "
            f"{len(setup.combinations)} combinations, up to {_ma(setup.highest_ma)}"
            + (f" at {_g(width)} µs" if isinstance(width, int | float) else ""))
    if setup.aborted:
        text += f"; ended early: {plain(setup.aborted)}"
    choice = setup.choice
    if choice:
        text += (f"; channel {choice.get('channel')} (electrodes {choice.get('electrodes')}) chosen by "
                 f"{choice.get('chosen_by') or 'the operator'}"
                 + (" (the proposal)" if choice.get("accepted_proposal") else
                    f" (proposed: channel {choice.get('proposed_channel')})"))
    elif not setup.aborted:
        text += "; no combination chosen"
    return text


def stimulation_summary(data: SessionReportData) -> str:
    stims = data.stimulation
    if not stims:
        return "none"
    total = sum(s.duration_s(data.end_mono) for s in stims)
    profiles = ", ".join(dict.fromkeys(s.profile or "a profile" for s in stims))
    return f"{len(stims)} time{'s' if len(stims) > 1 else ''}, {_duration(total)} in all ({profiles})"


def stimulation_end_words(s: StimulationRecord) -> str:
    if s.ended_mono is None:
        return "no end in the record (the session ended while stimulating)"
    reason, source = s.end_reason, s.end_source
    if source == "fes profile" or reason == "the time profile finished":
        return "the profile ran to its end"
    if reason == "stop button":
        return f"Stop pressed in the {source or 'FES panel'}"
    said = plain(reason) or "stopped"
    return said if not source or source.lower() in said.lower() else f"{said} ({source_words(source)})"


def _channels_text(channels: Mapping[int, tuple[float, float]]) -> str:
    if not channels:
        return "not recorded"
    return "; ".join(f"channel {ch}: up to {_g(ma)} mA, {_g(us)} µs"
                     for ch, (ma, us) in sorted(channels.items()))


def _restart_links(run: ExerciseRun, runs: Sequence[RunReport], numbers: Mapping[str, int]) -> list[tuple[str, Any]]:
    """How ``run`` is linked to the runs Recover made of it, or it of them: a continuation (the remaining
    repetitions, #36) is said as one, a restart from the beginning as a restart."""
    links: list[tuple[str, Any]] = []
    if run.restart_of:
        links.append(("continues" if run.continues else "restart of", numbers.get(run.restart_of, "?")))
    for other in runs:
        if other.run.restart_of == run.run_id:
            links.append(("continued as" if other.run.continues else "restarted as", other.number))
    return links


def _started_from(run: ExerciseRun) -> str:
    """"Exercises tab, by Dr Rossi", "Recover, by Dr Rossi"."""
    return SOURCE_TEXT.get(run.source, run.source) + (f", by {run.operator}" if run.operator else "")


TECHNICAL_APPENDIX = "Technical appendix (for the engineer)"


def save_session_report(folder: str | Path, out: str | Path, data: SessionReportData | None = None) -> int:
    """The session's report at ``out``, verified (app/core/outputs.py: drawn under a temporary name, read back, its
    pages
    counted, then renamed into place); returns the number of pages. Raises :class:`app.core.outputs.OutputError` (one
    sentence, nothing left at ``out``) when it cannot be written."""
    from app.core.outputs import verify_pdf, write_verified

    return write_verified(Path(out), lambda tmp: write_session_report(folder, tmp, data), verify_pdf,
                          what="the session report")


def save_progress_report(patient_id: str, out: str | Path, rows: Sequence[ProgressRow], profile: Any = None) -> int:
    """The progress report at ``out``, verified as :func:`save_session_report`; returns the number of pages."""
    from app.core.outputs import verify_pdf, write_verified

    return write_verified(Path(out), lambda tmp: write_progress_report(patient_id, tmp, rows, profile), verify_pdf,
                          what="the progress report")


def write_session_report(folder: str | Path, out: str | Path, data: SessionReportData | None = None) -> int:
    """Draw the session's report into ``out``; returns the number of pages. Reading the session
    (:func:`session_report_data`), drawing it (:func:`render_session_report`) and finishing the file are apart;
    what the user saves goes through :func:`save_session_report`, which writes aside, reads the file back and
    only then moves it into place."""
    _ensure_gui_app()
    data = data or session_report_data(folder)
    pdf = _Pdf(Path(out), f"Session {data.patient_id} {data.started}", _footer(f"session {data.folder.name}"))
    render_session_report(pdf, data)
    return pdf.finish()


def render_session_report(pdf: _Pdf, data: SessionReportData) -> None:
    """The session's report, in the clinician's words first: page 1 the patient, the session, its runs, what
    was delivered besides them and the alarms, with the sign-off; then each run, the electrode set-ups, the
    stimulation outside the exercises, the whole session's alarms and the definitions; last a technical
    appendix with what the record says in the engineer's words (paths, ids, hashes, raw messages)."""
    m = data.metrics
    manifest = data.manifest
    patient = manifest.get("patient") or {}
    start = manifest.get("start") or {}
    start_mono = float(start.get("t_mono_s") or 0.0)

    def clock(t_mono: float | None) -> str:
        return _clock_of(data, t_mono)

    pdf.text("Therapy session report", 17, True, "#1a3d6d", gap=8)
    status = "complete" if manifest.get("status") == "complete" else "INTERRUPTED (the application did not end it)"
    runs = data.runs
    duration = manifest.get("duration_s")
    if duration is None:
        duration = m["summary"].get("session_duration_s")
    pdf.fields([
        *identification(data.patient_id, data.profile, patient),
        ("Operator", str(manifest.get("operator") or "—")),
        ("Date", _when(data.started)),
        ("Duration", f"{_duration(duration)}   ({status})"),
        ("Note", str(manifest.get("note") or "—")),
    ])

    numbers = {r.run.run_id: r.number for r in runs}
    pdf.heading("Session overview")
    if runs:
        rows = []
        for r in runs:
            notes = [f"{what} run {number}" for what, number in _restart_links(r.run, runs, numbers)]
            rows.append([str(r.number), run_heading(r), SOURCE_TEXT.get(r.run.source, r.run.source) + (
                f", {r.run.operator}" if r.run.operator else ""), clock(r.run.started_mono),
                _duration(r.run.elapsed_s()), r.reps_text(), "; ".join([end_words(r.run), *notes])])
        pdf.table(["Run", "Exercise", "Started from, by", "Start", "Duration", "Repetitions", "Ended"], rows,
                  [0.4, 2.2, 1.5, 0.8, 0.9, 1.2, 2.3])
    else:
        pdf.text("No exercise was run in this session.", colour="#555555")
    delivered = [("Electrode set-up", "; ".join(setup_summary(s) for s in data.setups) if data.setups else "none"),
                 ("Stimulation outside the exercises", stimulation_summary(data)),
                 ("Alarms", alarms_summary(data))]
    pdf.heading("Also in this session", keep=90)
    pdf.fields(delivered, label_width=150)
    # The sign-off belongs with the summary it signs: it follows it on its page (never alone on the last one).
    sign_off(pdf, str(manifest.get("operator") or ""))

    pdf.new_page()
    for r in runs:
        run = r.run
        pdf.heading(f"Run {r.number} — {run_heading(r)}", 11.5, keep=140)
        info = [("Program", program_text(run)),
                ("Started", f"{clock(run.started_mono)} — {_started_from(run)}"),
                ("Ended", f"{clock(run.ended_mono)} — {end_words(run)}")]
        info += [(what[:1].upper() + what[1:], f"run {number}") for what, number in _restart_links(run, runs, numbers)]
        pdf.fields(info, label_width=110)
        params = parameters_text(run)
        pdf.subheading("Parameters")
        if params:
            pdf.fields(params, label_width=190)
        else:
            pdf.text("none (a script's own values; its text is kept in the session's record)", colour="#555555")
        summary = r.summary
        how = "marked by the exercise" if summary.get("source") == "marks" else "segmented from the handle speed"
        pdf.subheading("Summary of this run")
        counted = (f"{len(r.repetitions)} ({r.completed} completed; {how})" if r.repetitions
                   else r.reps_text())
        summary_fields = [("Repetitions", counted), ("Alarms", str(summary.get("alarms", 0)))]
        if r.positioning:
            summary_fields.append(("Positioning moves", f"{len(r.positioning)} (the robot placing the handle; not "
                                                        "repetitions)"))
        pdf.fields(summary_fields, label_width=110)
        rows = summary_rows(summary)
        if rows and r.repetitions:
            pdf.table(["Measure", "Mean", "SD", "First", "Last", "n"], rows, [3.2, 1, 1, 1, 1, 0.6],
                      align_right=(1, 2, 3, 4, 5))
        if r.repetitions:
            pdf.subheading(f"Repetitions of run {r.number} (numbered within the run)")
            pdf.table([h for _, h, _ in REPETITION_COLUMNS], [repetition_row(rep) for rep in r.repetitions],
                      [0.5, 0.8, 0.8, 0.9, 0.9, 0.9, 0.8, 0.6, 0.8, 0.8, 0.7, 0.6],
                      align_right=tuple(range(len(REPETITION_COLUMNS))))
            idx = [rep["index"] for rep in r.repetitions]
            ticks = [(float(i), str(i)) for i in idx] if len(idx) <= 30 else None
            pdf.plot_grid([
                {"title": f"Run {r.number}: peak and mean speed", "unit": "m/s", "x_label": "repetition",
                 "x_ticks": ticks, "series": [("peak", idx, [rep.get("peak_speed_m_s") for rep in r.repetitions]),
                                              ("mean", idx, [rep.get("mean_speed_m_s") for rep in r.repetitions])]},
                {"title": f"Run {r.number}: range of motion", "unit": "m", "x_label": "repetition",
                 "x_ticks": ticks, "series": [("range", idx, [rep.get("range_m") for rep in r.repetitions])]},
            ], height=130)
        mine = [a for a in alarm_rows(data) if a.run == str(r.number)]
        if mine:
            pdf.subheading(f"Alarms and interruptions during run {r.number}")
            pdf.table(["Time", "What", "Details", "Acknowledged by"],
                      [[clock(a.t_s + start_mono), a.what, a.details, a.acknowledged] for a in mine],
                      [0.8, 1.1, 4.8, 1.5])

    if data.setups:
        pdf.heading("Electrode set-up", keep=200)
        pdf.text("Test bursts given with the robot holding the arm still; the response is the change of the force "
                 "on the handle during each burst (definitions at the end).", 8, colour="#444444")
        for setup in data.setups:
            _draw_setup(pdf, data, setup)

    pdf.heading("Stimulation outside the exercises", keep=90)
    if data.stimulation:
        pdf.table(["Start", "Profile", "Started from", "Sent (highest)", "Duration", "How it ended"],
                  [[clock(s.started_mono), s.profile or "—", source_words(s.source) or "—",
                    _channels_text(s.channels), _duration(s.duration_s(data.end_mono)), stimulation_end_words(s)]
                   for s in data.stimulation], [0.8, 2.0, 1.1, 2.2, 0.9, 1.8])
    else:
        pdf.text("None: every stimulation of this session was part of an exercise or of the electrode set-up.",
                 colour="#555555")

    pdf.heading("The whole session", keep=200)
    t, x = data.position
    pdf.plot("Handle position over the session (runs shaded)", [("position", t, x)], "m", "s from the start",
             shade=[(r.run.started_mono - start_mono, (r.run.ended_mono or start_mono) - start_mono) for r in runs],
             markers=False, height=170)
    pdf.heading("Alarms and interruptions (whole session)")
    rows_all = alarm_rows(data)
    if rows_all:
        pdf.text(f"Alarms counted: {alarms_summary(data)}. Information messages and data gaps are listed but not "
                 "counted (definitions at the end).", 8, colour="#444444")
        pdf.table(["Time", "Run", "What", "Details", "Acknowledged by"],
                  [[clock(a.t_s + start_mono), a.run, a.what, a.details, a.acknowledged] for a in rows_all],
                  [0.8, 0.45, 1.1, 4.4, 1.5])
    else:
        pdf.text("None.")
    if data.problems:
        pdf.heading("Recording problems")
        for p in data.problems:
            pdf.text("• " + plain(p))

    pdf.heading("Definitions", keep=120)
    pdf.fields(list(DEFINITIONS), label_width=110)
    pdf.text("Full definitions and sources: the metrics and sessions documents of LINarm++ Manager.", 8,
             colour="#555555")

    _draw_technical_appendix(pdf, data)


def _draw_setup(pdf: _Pdf, data: SessionReportData, setup: ElectrodeSetupRecord) -> None:
    plan = setup.plan

    def num(key: str, unit: str) -> str:
        value = plan.get(key)
        return f"{_g(value)} {unit}" if isinstance(value, int | float) else "—"

    pdf.subheading(f"{setup.district[:1].upper()}{setup.district[1:]} — {_clock_of(data, setup.started_mono)}"
                   + (f", {setup.operator}" if setup.operator else ""), keep=160)
    fields = [("Test bursts", f"{setup.bursts} on {len(setup.combinations)} combinations, up to "
                              f"{_ma(setup.highest_ma)}"),
              ("Settings", f"from {num('start_ma', 'mA')} in steps of {num('step_ma', 'mA')} up to "
                           f"{num('ceiling_ma', 'mA')} (or the channel's cap), pulse width "
                           f"{num('pulse_width_us', 'µs')}, {num('frequency_hz', 'Hz')}")]
    planned = plan.get("pulse_width_us")
    sent = [us for _ma_, us in setup.delivered.values()]
    if sent and isinstance(planned, int | float) and abs(max(sent) - float(planned)) > 0.5:
        fields.append(("Pulse width sent", f"up to {_g(max(sent))} µs, not the {_g(planned)} µs set (an override was "
                                           "active: see the stimulator's record)"))
    pdf.fields(fields, label_width=110)
    rows = []
    for c in setup.combinations:
        responses = ", ".join(f"{_g(b.get('current_ma') or 0)}: {_newton(b.get('response_n'))}"
                              for b in c.bursts) or "—"
        widths = {_g(b.get("pulse_width_us") or 0) for b in c.bursts}
        chosen = setup.choice is not None and setup.choice.get("channel") == c.channel
        rows.append([str(c.channel) + (" ✓" if chosen else ""), c.electrodes or "—", str(len(c.bursts)),
                     _currents_text(c.currents) + (f" at {', '.join(sorted(widths))} µs" if widths else ""),
                     responses, _ma(c.motor_threshold_ma),
                     "not rated" if c.discomfort is None else f"{c.discomfort}/10"])
    pdf.table(["Ch.", "Electrodes", "Bursts", "Currents tested", "Response, N (at mA)", "Motor threshold",
               "Discomfort"], rows, [0.4, 0.95, 0.6, 1.6, 2.7, 0.95, 1.0])
    outcome = []
    if setup.aborted:
        outcome.append(("Ended early", plain(setup.aborted)))
    if setup.proposed_channel is not None or setup.proposal_reason:
        outcome.append(("Proposed", plain(setup.proposal_reason) or f"channel {setup.proposed_channel}"))
    choice = setup.choice
    if choice:
        when = str(choice.get("chosen_at") or "")
        try:
            when = _dt.datetime.fromisoformat(when).strftime("%H:%M:%S")
        except ValueError:
            pass
        outcome.append(("Chosen", f"channel {choice.get('channel')} (electrodes {choice.get('electrodes')}) by "
                                  f"{choice.get('chosen_by') or 'the operator'}" + (f" at {when}" if when else "")
                                  + (", the proposal" if choice.get("accepted_proposal") else
                                     f", not the proposal (channel {choice.get('proposed_channel')})")
                                  + ("; saved in the patient's profile" if choice.get("saved") else
                                     "; not saved (no profile file)")))
    elif not setup.aborted:
        outcome.append(("Chosen", "no combination was chosen"))
    pdf.fields(outcome, label_width=110)


def _draw_technical_appendix(pdf: _Pdf, data: SessionReportData) -> None:
    """What the record says in the engineer's words: where it is, what exactly ran, and every alarm and
    interruption as written (the pages before say them in the clinician's words)."""
    from app.session.recording import app_version

    pdf.new_page()
    pdf.heading(TECHNICAL_APPENDIX, 13)
    pdf.text("For the engineer: the record's own identifiers and messages. The clinical pages before this one say "
             "the same in words.", 8, colour="#444444")
    fields = [("Session", data.origin) if data.origin else ("Session folder", str(data.folder)),
              ("Printed by", f"LINarm++ Manager {app_version()}")]
    recorded = data.manifest.get("app_version") or data.manifest.get("version")
    if recorded:
        fields.append(("Recorded by", str(recorded)))
    pdf.fields(fields, label_width=120)
    if data.runs:
        pdf.subheading("Programs")
        pdf.fields([(f"Run {r.number}", program_technical(r.run)) for r in data.runs], label_width=60)
    rows = alarm_rows(data)
    if rows:
        pdf.subheading("Alarms and interruptions as recorded")
        pdf.table(["Time s", "Record"], [[f"{a.t_s:.1f}", a.technical] for a in rows], [0.7, 8])
    stims = [s for s in data.stimulation if s.end_reason or s.end_source]
    if stims:
        pdf.subheading("Stimulation outside the exercises as recorded")
        pdf.table(["Start", "Record"], [[_clock_of(data, s.started_mono),
                                         f"source={s.source}; profile={s.profile}; end reason={s.end_reason}; "
                                         f"end source={s.end_source}; current scale={s.current_scale}"]
                                        for s in stims], [0.7, 8])
    technical = [p for p in data.problems if is_technical(p)]
    if technical:
        pdf.subheading("Recording problems as recorded")
        for p in technical:
            pdf.text("• " + p, 8)


def identification(patient_id: str, profile: Any, snapshot: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The patient's identification: the profile's as it is now where it can be read, else the copy in the
    session's manifest. A pseudonymous profile says so (the clinic's key links it to the person)."""
    def get(name: str) -> str:
        value = getattr(profile, name, None) if profile is not None else None
        if value in (None, ""):
            value = snapshot.get(name)
        return str(value or "")

    name, born, record = get("full_name"), get("birth_date"), get("record_number")
    side = get("affected_side") or "unknown"
    out = [("Patient ID", patient_id + ("" if (name or record) else "   (pseudonym: the clinic's key identifies "
                                                                      "the patient)"))]
    if name:
        out.append(("Name", name))
    if born:
        out.append(("Date of birth", born))
    if record:
        out.append(("Medical record no.", record))
    out.append(("Affected side", side))
    return out


SIGN_OFF_HEIGHT = 150.0  # the sign-off block: its heading, the operator, three lines to write on


def sign_off(pdf: _Pdf, operator: str) -> None:
    pdf.heading("Sign-off", keep=SIGN_OFF_HEIGHT)
    pdf.fields([("Operator (recorded)", operator or "—")], label_width=130)
    pdf.ensure(60)
    third = (pdf.inner_width - 40) / 3
    pdf.y += 4
    for k, label in enumerate(("Clinician (name)", "Date", "Signature")):
        pdf.rule_line(label, third, pdf.MARGIN + k * (third + 20))
    pdf.y += 48


# ------------------------------------------------------------------------------------------- progress PDF
def write_progress_report(patient_id: str, out: str | Path, rows: Sequence[ProgressRow],
                          profile: Any = None) -> int:
    """Write the patient's progress report from :func:`progress_rows`; returns the number of pages. Without
    ``profile`` the patient's saved profile is read (their identification is never dropped for lack of it)."""
    _ensure_gui_app()
    if profile is None:
        profile = _profile_of(patient_id)
    pdf = _Pdf(Path(out), f"Progress {patient_id}", _footer(f"progress of {patient_id}"))
    render_progress_report(pdf, patient_id, rows, profile)
    return pdf.finish()


def render_progress_report(pdf: _Pdf, patient_id: str, rows: Sequence[ProgressRow], profile: Any) -> None:
    """The progress report's pages (:func:`write_progress_report` writes them): the patient, the sessions, one
    trend section per exercise (its one name, :func:`exercise_identity`), the clinical scores."""
    pdf.text("Patient progress report", 17, True, "#1a3d6d", gap=8)
    first = rows[0].date if rows else "—"
    last = rows[-1].date if rows else "—"
    interrupted = [k + 1 for k, r in enumerate(rows) if r.interrupted]
    pairs = [
        *identification(patient_id, profile, {}),
        ("Sessions", f"{len(rows)}   ({first} … {last})"
                     + (f"; interrupted: #{', #'.join(map(str, interrupted))}" if interrupted else "")),
        ("Repetitions", str(sum(int(r.summary.get("repetitions") or 0) for r in rows))),
    ]
    if profile is not None:
        scores = profile.scores
        pairs += [(label, fmt(getattr(scores, key, None), "{}")) for key, label in SCORES]
        pairs.append(("Assessed on", scores.assessed_on or "—"))
    pdf.fields(pairs, label_width=190)

    pdf.heading("Sessions")
    stations = shows_stations(rows)
    headers = ["#", "Date and time", "Exercises", "Reps (done)", "Peak m/s", "SPARC", "Range m", "α", "Alarms",
               "Session"]
    widths = [0.3, 1.45, 2.0, 0.85, 0.75, 0.65, 0.8, 0.65, 0.65, 0.95]
    if stations:
        headers.insert(2, "Station")
        widths[2:3] = [1.05, 1.45]
    table = []
    for k, r in enumerate(rows):
        line = [str(k + 1), r.date, "; ".join(r.exercises) or "—",
                f"{fmt(r.summary.get('repetitions'), '{}')} ({fmt(r.summary.get('completed'), '{}')})",
                fmt(r.value("peak_speed_m_s")), fmt(r.value("sparc")), fmt(r.value("range_m")),
                # α to two decimals, as the window shows it (0 … 1): three significant digits of a level near 0
                # ("-0.00501") did not fit the column and wrapped into "-0.005" over "01".
                fmt(r.value("mean_alpha"), "{:.2f}"), fmt(r.summary.get("alarms"), "{}"),
                "interrupted" if r.interrupted else "complete"]
        if stations:
            line.insert(2, r.station or "—")
        table.append(line)
    right = (3, 4, 5, 6, 7, 8)
    pdf.table(headers, table, widths, align_right=tuple(c + 1 for c in right) if stations else right)

    n = len(rows)
    ticks = [(float(i), f"#{i}") for i in range(1, n + 1)]
    titles = list(dict.fromkeys(t for r in rows for t in r.per_exercise))
    if not titles:
        titles = [""]
    for title in titles:
        pdf.heading(f"Trends: {title}" if title else "Trends across sessions (session means)", keep=200)
        pdf.text("Session means of this exercise's repetitions, by session number (dates in the table above). "
                 "○ = a session whose runs of this exercise were all interrupted: shown, but not joined to the "
                 "trend line.", 8, colour="#444444")
        plots = []
        for key, label, unit in TREND_METRICS:
            xs, ys, hollow = trend_points(rows, title, key)
            if xs or hollow:
                plots.append({"title": label, "series": [(label, xs, ys)], "unit": unit, "x_label": "session",
                              "x_ticks": ticks, "hollow": hollow})
        if plots:
            pdf.plot_grid(plots)
        else:
            pdf.text("No repetition of this exercise has metrics yet.", colour="#555555")
    scored = [(key, label) for key, label in SCORES if any(r.scores.get(key) is not None for r in rows)]
    if scored:
        pdf.heading("Clinical scores (as in the profile at each session)", keep=200)
        pdf.plot_grid([{"title": label, "series": [(label, [k + 1.0 for k in range(n)],
                                                    [_score(r.scores.get(key)) for r in rows])],
                        "x_label": "session", "x_ticks": ticks} for key, label in scored])


def trend_points(rows: Sequence[ProgressRow], title: str, key: str
                 ) -> tuple[list[float], list[float], list[tuple[float, float]]]:
    """One exercise's trend of ``key`` by session number: the points joined by the line (x, y), and apart the
    sessions whose runs of that exercise were all interrupted (drawn as open circles, never as a decline).
    ``title`` "" = the whole session's means (recordings without exercises)."""
    xs: list[float] = []
    ys: list[float] = []
    hollow: list[tuple[float, float]] = []
    for k, r in enumerate(rows):
        trend = r.per_exercise.get(title) if title else None
        if title and trend is None:
            continue
        value = trend.values.get(key) if trend is not None else r.value(key)
        if value is None:
            continue
        if (trend.interrupted if trend is not None else r.interrupted):
            hollow.append((k + 1.0, float(value)))
        else:
            xs.append(k + 1.0)
            ys.append(float(value))
    return xs, ys, hollow


def _score(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


# ------------------------------------------------------------------------------------------- command line
def run_report_command(config: Any, *, metrics: str | None = None, report: str | None = None,
                       progress: str | None = None, out: str | None = None,
                       rows_of: Callable[[str, Path], list[ProgressRow]] | None = None, archive_read: bool = False,
                       report_origin: str = "") -> int:
    """``--metrics`` prints JSON to stdout; ``--report`` / ``--progress`` write ``--out``. Exit 0, or 2 with a
    message on stderr when the input is wrong. ``rows_of(patient, sessions root)``: the progress report's rows
    (the command line's: every station's from the archive, ``archive_read``, and this station's not yet archived;
    default: this station's folders);
    ``report_origin``: what ``report`` is when it is an archived session's copy (said in the report)."""
    from app.session.recording import MANIFEST_FILE, sessions_root

    if (report or progress) and not out:
        print("--report and --progress need --out FILE.pdf", file=sys.stderr)
        return 2
    for folder in (metrics, report):
        if folder and not (Path(folder) / MANIFEST_FILE).is_file():
            print(f"{folder} is not a session folder (no {MANIFEST_FILE})", file=sys.stderr)
            return 2
    if metrics:
        print(json.dumps(_metrics_json(metrics), indent=1, ensure_ascii=False))
    if report:
        data = session_report_data(report, origin=report_origin) if report_origin else None
        pages = save_session_report(report, out, data)  # type: ignore[arg-type]
        print(f"Session report written: {out} ({pages} page{'s' if pages > 1 else ''})", file=sys.stderr)
    if progress:
        from app.therapy.patients import PatientError, load_patient

        rows = (rows_of or progress_rows)(progress, sessions_root(config))
        if not rows:
            where = f"under {sessions_root(config)}" + (" nor in the archive" if archive_read else "")
            print(f"no session of patient {progress} {where}", file=sys.stderr)
            return 2
        try:
            profile = load_patient(progress, config.safety)
        except (PatientError, OSError):
            profile = None
        pages = save_progress_report(progress, out, rows, profile)  # type: ignore[arg-type]
        print(f"Progress report written: {out} ({pages} page{'s' if pages > 1 else ''})", file=sys.stderr)
    return 0


def _metrics_json(folder: str) -> dict[str, Any]:
    from app.session.metrics import session_metrics

    return session_metrics(folder)
