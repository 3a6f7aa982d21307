"""The readers of sessions on the archive (issue #39, "everything reads the archive"): the progress report, the
``--metrics`` / ``--report`` commands and the sessions browser see every station's sessions, and this station's own
that are still in its outbox, each session once (by its UUID).

* :func:`progress_rows` — the progress report's rows (``app.reports.ProgressRow``): the archive's sessions of the
  patient built from its rows alone (the runs and repetitions with their metrics computed at upload: no stream is
  read), then this station's folders whose UUID the archive does not hold (computed from the files, as before).
* :func:`session_listing` — the sessions browser's list: the archive's sessions (every station's) and the local
  folders not archived yet ("waiting for the archive"), newest first.
* :func:`open_for_reading` — the configured archive for a command that only reads (``--progress``, ``--report``,
  ``--metrics``, the worker's jobs): nothing is created, and an archive that cannot be read is a sentence, never
  a traceback (the station's own folders still answer).

Qt-free. An archived session that must be read whole (``--report``, a replay) is materialised into a private
temporary folder (``Archive.materialised``): every reader of a session reads a folder, and one reader of the
recorder's format stays one.
"""

from __future__ import annotations

import datetime as _dt
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.archive.api import Archive, ArchiveError, ProgressSession

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- opening
def open_for_reading(config: Any) -> tuple[Archive | None, str]:
    """(the configured archive, '') or (None, why it cannot be read). With nothing configured and no embedded
    archive file in ``<data>`` yet there is nothing archived: (None, '') and no file is made."""
    from app import paths
    from app.archive.store import ARCHIVE_FILE, open_archive

    url = getattr(getattr(config, "archive", None), "url", "") or ""
    if not url and not (paths.data_dir() / ARCHIVE_FILE).exists():
        return None, ""
    logging.getLogger("alembic").setLevel(logging.WARNING)
    try:
        return open_archive(config, create=False), ""
    except (ArchiveError, OSError) as exc:
        log.warning("archive: %s", exc)
        return None, str(exc)


def archive_args(config: Any) -> tuple[str, str, str]:
    """(url, password_file, station) of the configured archive, for a job of the worker process to open it."""
    from app.archive.outbox import archive_settings

    return archive_settings(config)


def open_by_args(url: str, password_file: str, station: str) -> tuple[Archive | None, str]:
    """:func:`open_for_reading` from :func:`archive_args` (in the worker process)."""
    from types import SimpleNamespace

    return open_for_reading(SimpleNamespace(archive=SimpleNamespace(url=url, password_file=password_file),
                                            station=station))


# ---------------------------------------------------------------------------------------------- local folders
@dataclass(frozen=True)
class LocalSession:
    """A session folder of this station with its UUID (the manifest's, or the one derived for an old folder)."""

    folder: Path
    uuid: str
    start_epoch_s: float
    archived: bool  # its .archived marker is there (the archive committed it)


def local_sessions(root: Path, patient_id: str | None = None) -> list[LocalSession]:
    """The station's session folders (one patient's, or all), each with its UUID; reads manifests only."""
    from app.archive.derive import _start_epoch
    from app.archive.folders import is_archived, read_manifest, session_folders, session_uuid
    from app.recording import MANIFEST_FILE, safe_name

    if patient_id is not None:
        base = Path(root) / safe_name(patient_id)
        found = sorted(f for f in base.iterdir() if f.is_dir() and (f / MANIFEST_FILE).is_file()) \
            if base.is_dir() else []
    else:
        found = session_folders(Path(root))
    out = []
    for folder in found:
        manifest = read_manifest(folder)
        start = manifest.get("start") if isinstance(manifest.get("start"), dict) else {}
        out.append(LocalSession(folder, session_uuid(folder, manifest), _start_epoch(start), is_archived(folder)))
    return out


# ---------------------------------------------------------------------------------------------- the progress report
def progress_row(ps: ProgressSession) -> Any:
    """An archived session as a row of the progress report (``app.reports.ProgressRow``), from its rows alone: the
    same summary, scores and per-exercise trends as :func:`app.reports.progress_rows` computes from the folder
    (the repetitions are the run-aware metrics stored at upload, ``app.metrics.metrics_by_run``)."""
    from app.reports import ProgressRow, RunReport, exercise_trends
    from app.runs import ExerciseRun, Program, RunParameter

    reps_by_run: dict[str, list[dict[str, Any]]] = {}
    for rep in ps.repetitions:
        reps_by_run.setdefault(rep.run_id, []).append(dict(rep.metrics))
    reports = []
    for run in ps.runs:
        params = tuple(RunParameter(str(p.get("name", "")), str(p.get("label", "")), p.get("value"),
                                    str(p.get("unit", ""))) for p in run.parameters)
        er = ExerciseRun(run.run_id, Program.from_dict(run.program), params, run.source,  # type: ignore[arg-type]
                         run.operator, run.started_s, 0.0, restart_of=run.restart_of,
                         ended_mono=run.ended_s, end_reason=run.end_reason, end_detail=run.end_detail,
                         state="stopped" if run.end_reason not in (None, "finished") else "finished")
        reports.append(RunReport(er, run.position, reps_by_run.get(run.run_id, []), dict(run.summary)))
    info = ps.info
    titles = tuple(dict.fromkeys(r.exercise for r in reports)) or tuple(info.exercises)
    return ProgressRow(Path(info.folder_name), info.start, titles, dict(ps.summary), dict(ps.scores), info.complete,
                       exercise_trends(reports), uuid=info.uuid, station=info.station)


def _epoch(iso: str) -> float:
    try:
        return _dt.datetime.fromisoformat(iso).timestamp()
    except ValueError:
        return 0.0


def progress_rows(patient_id: str, root: Path | None, archive: Archive | None,
                  progress: Callable[[float], None] | None = None) -> list[Any]:
    """The patient's sessions for the progress report, oldest first: every archived one (every station's), then
    this station's folders under ``root`` whose UUID the archive does not hold (not yet uploaded), read from
    their files. ``archive=None``: the folders alone (:func:`app.reports.progress_rows`)."""
    from app import paths
    from app.reports import progress_rows as folder_rows

    if archive is None:
        return folder_rows(patient_id, root, progress)
    archived = archive.progress_sessions(patient_id)
    keyed: list[tuple[float, Any]] = [(ps.info.start_epoch_s or _epoch(ps.info.start), progress_row(ps))
                                      for ps in archived]
    known = {ps.info.uuid for ps in archived}
    local = [s for s in local_sessions(root or paths.sessions_dir(), patient_id) if s.uuid not in known]
    if local:
        rows = _folder_rows([s.folder for s in local], progress)
        keyed += [(s.start_epoch_s, row) for s, row in zip(local, rows, strict=True)]
    if progress is not None:
        progress(1.0)
    keyed.sort(key=lambda kr: kr[0])
    return [row for _, row in keyed]


def _folder_rows(folder_list: list[Path], progress: Callable[[float], None] | None) -> list[Any]:
    """Rows of these folders, computed from their files (:func:`app.reports.folder_progress_row`)."""
    from app.recording import summarize_session
    from app.reports import folder_progress_row

    rows = []
    for k, folder in enumerate(folder_list):
        if progress is not None:
            progress(k / max(1, len(folder_list)))
        rows.append(folder_progress_row(summarize_session(folder)))
    return rows
