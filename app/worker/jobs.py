"""The jobs the worker process runs (issue #37), by name. Each is ``fn(ctx, *args, **kwargs)``; ``ctx`` reports
progress and answers a cancel (app/worker/process.py's JobContext). Results must pickle and stay small: a
session's samples go back as column files (app/worker/session_data.py), never in the message.

Other packages add their own without editing this file: a kind of the form ``"package.module:function"`` is
imported and called the same way.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.worker.context import JobContext, JobError
from app.worker.session_data import SessionData, SessionOverview, overview_of, session_data

Job = Callable[..., Any]
JOBS: dict[str, Job] = {}


def job(name: str) -> Callable[[Job], Job]:
    def register(fn: Job) -> Job:
        JOBS[name] = fn
        return fn
    return register


def resolve(kind: str) -> Job:
    if kind in JOBS:
        return JOBS[kind]
    module, sep, name = kind.partition(":")
    if not sep:
        raise JobError(f"the worker has no task called {kind!r}.")
    fn = getattr(importlib.import_module(module), name, None)
    if not callable(fn):
        raise JobError(f"the worker has no task called {kind!r}.")
    return fn  # type: ignore[no-any-return]


def preload() -> None:
    """What most tasks need, imported before the worker says it is ready (a warm worker answers at once)."""
    import numpy  # noqa: F401

    import app.session.export
    import app.session.metrics
    import app.session.recording
    import app.session.reports  # noqa: F401


def import_result_types() -> None:
    """On the app's side: the modules whose classes the results are made of (a run's report, its metrics, the
    session's overview). Unpickling a result imports what it names, holding the interpreter lock: the first
    summary shown during a therapy held the window's thread 70 ms (and the drivers' interpreter) importing
    app.session.reports. The window calls this when it is built, before any therapy runs."""
    import app.core.runs
    import app.session.metrics
    import app.session.reports
    import app.worker.session_data  # noqa: F401


# ---------------------------------------------------------------------------------------------- reading
def _load(ctx: JobContext, folder: str | Path, share: float) -> Any:
    """The session, its side-file written first when it has none (the next load is fast); progress up to
    ``share``."""
    from app.session.recording import index_session, load_session

    ctx.step(0.0, "Reading the session")
    index_session(folder, progress=lambda f: ctx.step(share * 0.9 * f, "Reading the session's files"))
    ctx.step(share * 0.9, "Reading the session")
    session = load_session(folder, mmap=True)
    ctx.step(share)
    return session


@job("index_session")
def index(ctx: JobContext, folder: str | Path) -> str:
    """Write a session's columnar side-file (at its end: the next open is fast); '' or why not."""
    from app.session.recording import index_session

    return index_session(folder, progress=ctx.step)


@job("session_data")
def load_data(ctx: JobContext, folder: str | Path) -> SessionData:
    """A session for the replay: manifest, events, problems, its samples as column files to map."""
    session = _load(ctx, folder, 0.85)
    return session_data(session)


@job("session_overview")
def overview(ctx: JobContext, folder: str | Path) -> SessionOverview:
    return overview_of(_load(ctx, folder, 0.95))


@dataclass
class SummaryData:
    """What the run summary shows: every run's report (app.session.reports.run_reports), the patient, the problems."""

    folder: Path
    patient_id: str
    runs: list[Any]
    problems: list[str]


@job("session_summary")
def summary(ctx: JobContext, folder: str | Path) -> SummaryData:
    from app.session.reports import run_reports

    session = _load(ctx, folder, 0.5)
    ctx.step(0.5, "Computing the metrics")
    runs = run_reports(session)
    patient = str(session.manifest.get("patient_id") or Path(folder).parent.name)
    return SummaryData(Path(folder), patient, runs, list(session.problems))


@job("progress_rows")
def progress(ctx: JobContext, patient_id: str, root: str | Path | None = None) -> list[Any]:
    from app.session.reports import progress_rows

    return progress_rows(patient_id, Path(root) if root is not None else None,
                         lambda f: ctx.step(f, "Reading the patient's sessions"))


# ---------------------------------------------------------------------------------------------- writing
@job("export_hdf5")
def export_hdf5(ctx: JobContext, folder: str | Path, dest: str | Path) -> str:
    from app.core.outputs import OutputError
    from app.session import export

    session = _load(ctx, folder, 0.3)
    try:
        export.export_hdf5(session, dest, lambda f: ctx.progress(0.3 + 0.7 * f, "Writing the HDF5 file"))
    except OutputError:
        ctx.retire = True  # HDF5's own state may be damaged by a failed write: the next task gets a new worker
        raise
    return f"Exported to {dest} (HDF5, verified)."


@job("export_csv")
def export_csv(ctx: JobContext, folder: str | Path, dest: str | Path) -> str:
    from app.session import export

    session = _load(ctx, folder, 0.3)
    export.export_csv(session, dest, lambda f: ctx.progress(0.3 + 0.7 * f, "Writing the CSV files"))
    return f"Exported to {dest} (CSV files, verified)."


@job("session_report")
def session_report(ctx: JobContext, folder: str | Path, dest: str | Path) -> int:
    """The session's PDF, verified; returns its pages."""
    from app.session.reports import save_session_report

    ctx.step(0.05, "Drawing the session report")
    return save_session_report(folder, dest)


@job("progress_report")
def progress_report(ctx: JobContext, patient_id: str, dest: str | Path, root: str | Path | None = None,
                    rows: list[Any] | None = None, profile: Any = None) -> int:
    """The patient's progress PDF, verified; returns its pages (``rows`` as the progress view read them, else
    read here)."""
    from app.session.reports import progress_rows, save_progress_report

    if rows is None:
        rows = progress_rows(patient_id, Path(root) if root is not None else None,
                             lambda f: ctx.step(0.8 * f, "Reading the patient's sessions"))
    ctx.step(0.8, "Drawing the progress report")
    return save_progress_report(patient_id, dest, rows, profile)
