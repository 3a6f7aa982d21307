"""The readers of sessions on the archive (issue #39, "everything reads the archive"): the progress report, the
``--metrics`` / ``--report`` commands and the sessions browser see every station's sessions, and this station's own
that are still in its outbox, each session once (by its UUID).

* :func:`progress_rows` — the progress report's rows (``app.session.reports.ProgressRow``): the archive's sessions of
  the
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
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.archive.api import Archive, ArchiveError, ProgressSession

if TYPE_CHECKING:
    from app.worker.context import JobContext

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- opening
def open_for_reading(config: Any) -> tuple[Archive | None, str]:
    """(the configured archive, '') or (None, why it cannot be read). With nothing configured and no embedded
    archive file in ``<data>`` yet there is nothing archived: (None, '') and no file is made."""
    from app.archive.store import ARCHIVE_FILE, open_archive
    from app.core import paths

    url = getattr(getattr(config, "archive", None), "url", "") or ""
    if not url and not (paths.data_dir() / ARCHIVE_FILE).exists():
        return None, ""
    logging.getLogger("alembic").setLevel(logging.WARNING)
    try:
        return open_archive(config, create=False), ""
    except ArchiveError as exc:
        log.warning("archive: %s", exc)
        return None, str(exc)
    except OSError as exc:  # the archive's folder (a share, a disk) is not there, as the outbox says it
        log.warning("archive: %s", exc)
        return None, f"the archive at {url or 'the data folder'} cannot be reached ({exc})"


def archived_label(info: Any, url: str) -> str:
    """An archived session in messages and reports (``info``: its SessionInfo; ``url``: the archive's, without a
    password): the report commands and the research export name it alike."""
    return (f"archived session {info.uuid} (recorded on station {info.station or '?'} as {info.folder_name}; "
            f"read from the archive at {url})")


def archive_args(config: Any) -> tuple[str, str, str]:
    """(url, password_file, station) of the configured archive, for a job of the worker process to open it."""
    from app.archive.outbox import archive_settings

    return archive_settings(config)


def args_of(archive: Archive) -> tuple[str, str, str]:
    """(url, password_file, station) of an open archive, for a job of the worker process to open it too."""
    return archive.url, str(getattr(archive, "password_file", "") or ""), archive.station


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
    from app.session.recording import MANIFEST_FILE, safe_name

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
    """An archived session as a row of the progress report (``app.session.reports.ProgressRow``), from its rows alone:
    the
    same summary, scores and per-exercise trends as :func:`app.session.reports.progress_rows` computes from the folder
    (the repetitions are the run-aware metrics stored at upload, ``app.session.metrics.metrics_by_run``)."""
    from app.core.runs import ExerciseRun, Program, RunParameter
    from app.session.reports import ProgressRow, RunReport, exercise_trends

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
    their files. ``archive=None``: the folders alone (:func:`app.session.reports.progress_rows`)."""
    from app.core import paths
    from app.session.reports import progress_rows as folder_rows

    if archive is None:
        return folder_rows(patient_id, root, progress)
    archived = archive.progress_sessions(patient_id)
    keyed: list[tuple[float, Any]] = [(ps.info.start_epoch_s or _epoch(ps.info.start), progress_row(ps))
                                      for ps in archived]
    known = {ps.info.uuid for ps in archived}
    local = [s for s in local_sessions(root or paths.sessions_dir(), patient_id) if s.uuid not in known]
    if local:
        rows = _folder_rows([s.folder for s in local], progress)
        for row in rows:  # recorded here, where the report is made, and waiting in this station's outbox
            row.station = f"{archive.station} (not archived yet)"
        keyed += [(s.start_epoch_s, row) for s, row in zip(local, rows, strict=True)]
    if progress is not None:
        progress(1.0)
    keyed.sort(key=lambda kr: kr[0])
    return [row for _, row in keyed]


def _folder_rows(folder_list: list[Path], progress: Callable[[float], None] | None) -> list[Any]:
    """Rows of these folders, computed from their files (:func:`app.session.reports.folder_progress_row`)."""
    from app.session.recording import summarize_session
    from app.session.reports import folder_progress_row

    rows = []
    for k, folder in enumerate(folder_list):
        if progress is not None:
            progress(k / max(1, len(folder_list)))
        rows.append(folder_progress_row(summarize_session(folder)))
    return rows


# ---------------------------------------------------------------------------------------------- the sessions browser
STOP_LEVELS = ("STOP", "FATAL")
STATUS_KINDS = ("script_stop", "alarm")  # the events a session's status is decided from


@dataclass(frozen=True)
class SessionStatus:
    """What the sessions browser's Status column says, and why (its tooltip)."""

    text: str
    tooltip: str
    ok: bool


IN_PROGRESS = SessionStatus("in progress", "This session is being recorded now.", True)


def status_of(complete: bool, events: list[dict[str, Any]]) -> SessionStatus:
    """``interrupted`` (the app never ended it), else ``complete`` only when every exercise finished and no STOP
    alarm was raised -- otherwise what went wrong (issue #19: 5 aborted exercises and 12 alarms showed as
    "complete"). ``events``: the session's ``script_stop`` and ``alarm`` events (its folder's or the archive's)."""
    if not complete:
        return SessionStatus("interrupted", "The session was not stopped normally (crash or power loss); "
                             "its data end at the last flush.", False)
    ends = [e.get("data", {}) for e in events if e.get("kind") == "script_stop"]
    aborted = [d for d in ends if str(d.get("status", "finished")) != "finished"]
    stops = [e for e in events if e.get("kind") == "alarm" and e.get("data", {}).get("level") in STOP_LEVELS]
    problems = []
    if aborted:
        problems.append(f"{len(aborted)} of {len(ends)} exercise(s) aborted")
    if stops:
        problems.append(f"{len(stops)} stop alarm(s)")
    if not problems:
        return SessionStatus("complete", "Ended normally; every exercise finished, no stop alarm.", True)
    reasons = "; ".join(sorted({str(d.get("reason", d.get("status", ""))) for d in aborted})[:5])
    return SessionStatus("ended: " + ", ".join(problems),
                         "Ended normally, but " + " and ".join(problems) + (f". Causes: {reasons}" if reasons else ""),
                         False)


# Where a listed session is, for the Station column: in the archive, or only in this station's outbox.
ARCHIVED, WAITING, REFUSED, LOCAL = "archived", "waiting", "refused", "local"


@dataclass(frozen=True)
class ListedSession:
    """One row of the sessions browser: an archived session (any station's) or a folder of this station."""

    uuid: str
    patient_id: str
    folder: Path | None  # this station's folder of it (None: only in the archive: materialised to be read)
    folder_name: str  # "<patient>/<stamp>" as recorded on its station
    start: str  # ISO
    duration_s: float
    exercises: tuple[str, ...]
    alarms: int
    operator: str
    station: str  # the station that recorded it ('' for a folder of this station not archived)
    status: SessionStatus
    where: str  # ARCHIVED, WAITING (in the outbox), REFUSED (by the archive), LOCAL (no archive in use)

    def station_text(self, here: str) -> str:
        """The Station column: the recording station, and whether the session is still only here."""
        if self.where == WAITING:
            return f"{here or 'this station'} (waiting for the archive)"
        if self.where == REFUSED:
            return f"{here or 'this station'} (refused by the archive)"
        return self.station or here or "this station"


def _folder_row(folder: Path, uuid: str, where: str, active: Path | None) -> ListedSession:
    """A row from a folder of this station (its manifest and events: no stream read)."""
    from app.session.recording import EVENTS_FILE, read_events, summarize_session
    from app.session.reports import run_titles

    s = summarize_session(folder)
    titles = run_titles(folder) or s.exercises  # the runs' titles, not file names (older: scripts)
    if active is not None and folder.resolve() == active.resolve():
        status = IN_PROGRESS
    else:
        events, _dropped = read_events(folder / EVENTS_FILE) if s.complete else ([], 0)
        status = status_of(s.complete, [e for e in events if e.get("kind") in STATUS_KINDS])
    return ListedSession(uuid, s.patient_id, folder, f"{folder.parent.name}/{folder.name}", s.start, s.duration_s,
                         tuple(titles), s.alarms, s.operator, "", status, where)


BLOCK = 200  # sessions per block of the sessions browser's list (one page of the archive)


def session_listing(patient_id: str, root: Path, archive: Archive | None, in_use: bool = False,
                    active: Path | None = None) -> list[ListedSession]:
    """The sessions browser's rows for ``patient_id``, newest first, all at once (:func:`session_blocks`)."""
    return [row for block in session_blocks(patient_id, root, archive, in_use, active) for row in block]


def session_blocks(patient_id: str, root: Path, archive: Archive | None, in_use: bool = False,
                   active: Path | None = None, block: int = BLOCK) -> Iterator[list[ListedSession]]:
    """The sessions browser's rows for ``patient_id``, newest first, in blocks of about ``block``: every archived
    session (every station's; the folder of this station attached when it has one, so reading it needs no copy)
    and this station's folders the archive does not hold ("waiting for the archive", or refused), each in its
    place by start time. The first block comes after one page of the archive (and this station's manifests), so a
    patient's newest sessions are listed before the thousands behind them are read. ``in_use``: an archive is in
    use (even if it cannot be reached now: the local folders are then all "waiting"); without one the folders are
    listed as before (LOCAL). ``active``: the folder being recorded now ("in progress"). Raises ArchiveError
    (the caller lists the folders alone and says why). Slow on a server or with many sessions: call it off the
    GUI thread."""
    from app.archive.folders import REFUSED_MARKER

    local = local_sessions(root, patient_id)
    here = {s.uuid: s.folder for s in local}
    held = archive.held_sessions(list(here)) if archive is not None and here else set()
    # this station's folders the archive does not hold, newest first; each is read when its place comes
    waiting = sorted((s for s in local if s.uuid not in held), key=lambda s: (s.start_epoch_s, str(s.folder)),
                     reverse=True)

    def folder_row(s: LocalSession) -> tuple[float, ListedSession]:
        # the outbox's markers say what the archive (unreadable now, or another one) did with it
        where = (LOCAL if not in_use else ARCHIVED if s.archived else
                 REFUSED if (s.folder / REFUSED_MARKER).is_file() else WAITING)
        return s.start_epoch_s, _folder_row(s.folder, s.uuid, where, active)

    def ordered(rows: list[tuple[float, ListedSession]]) -> list[ListedSession]:
        rows.sort(key=lambda r: (r[0], r[1].folder_name), reverse=True)
        return [r for _, r in rows]

    after: tuple[float, str] | None = None
    while archive is not None:
        infos = archive.list_sessions(patient_id, limit=block, after=after)
        if not infos:
            break
        journals = archive.journals([i.uuid for i in infos], STATUS_KINDS)
        rows: list[tuple[float, ListedSession]] = []
        for info in infos:
            folder = here.get(info.uuid)
            if folder is not None and active is not None and folder.resolve() == active.resolve():
                status = IN_PROGRESS
            else:
                events = [{"kind": j.kind, "data": j.data} for j in journals.get(info.uuid, [])]
                status = status_of(info.status == "complete", events)
            rows.append((info.start_epoch_s or _epoch(info.start), ListedSession(
                info.uuid, info.patient_id, folder, info.folder_name, info.start, info.duration_s,
                tuple(info.exercises), info.alarms, info.operator, info.station, status, ARCHIVED)))
        last = infos[-1]
        after = (last.start_epoch_s, last.uuid)
        full = len(infos) == block
        # this station's waiting folders that belong in this page: newer than its last session (all, at the end)
        while waiting and (not full or waiting[0].start_epoch_s >= last.start_epoch_s):
            rows.append(folder_row(waiting.pop(0)))
        yield ordered(rows)
        if not full:
            break
    for k in range(0, len(waiting), block):
        yield ordered([folder_row(s) for s in waiting[k:k + block]])


def patient_ids(root: Path, archive: Archive | None, in_use: bool = False) -> list[str]:
    """The patients the browser offers: the archive's (no profile built) and those with folders on this station;
    without an archive in use (``in_use``) the station's patient files too."""
    from app.session.recording import list_patients_with_sessions

    ids = set(list_patients_with_sessions(root))
    if archive is not None:
        offset = 0
        while page := archive.list_patients(limit=1000, offset=offset):
            ids |= {p.patient_id for p in page}
            offset += len(page)
    elif not in_use:
        from app.therapy.patients import list_patients

        ids |= {e.patient_id for e in list_patients()}
    return sorted(ids, key=str.lower)


# ---------------------------------------------------------------------------------------------- the worker's jobs
class _Share:
    """A job's context reporting into [start, start + span] of the task's progress (a job run after a copy)."""

    def __init__(self, ctx: JobContext, start: float, span: float) -> None:
        self._ctx, self._start, self._span = ctx, start, span

    def progress(self, fraction: float, text: str = "") -> bool:
        return bool(self._ctx.progress(self._start + self._span * max(0.0, min(1.0, fraction)), text))

    def step(self, fraction: float, text: str = "") -> None:
        self._ctx.step(self._start + self._span * max(0.0, min(1.0, fraction)), text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ctx, name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name.startswith("_"):
            object.__setattr__(self, name, value)
        else:
            setattr(self._ctx, name, value)  # ctx.retire


COPIED = ".copied"  # written in a materialised copy once every file is there and checked


def copy_of(archive: Archive, uuid: str, cache: Path, progress: Callable[[float], bool | None] | None = None
            ) -> Path:
    """The archived session ``uuid`` as a folder under ``cache`` (``<cache>/<uuid>/<patient>/<stamp>``), written
    once (each file checked against its SHA-256) and reused while the cache lives."""
    import shutil

    from app.archive.store import folders_safe

    files = archive.session_files(uuid)
    patient, _, stamp = str(getattr(files, "folder_name", "")).partition("/")
    base = Path(cache) / uuid
    folder = base / (folders_safe(patient) or "patient") / (folders_safe(stamp) or uuid)
    if (base / COPIED).is_file() and folder.is_dir():
        return folder
    shutil.rmtree(base, ignore_errors=True)  # a copy interrupted earlier
    files.materialise(folder, progress)
    (base / COPIED).touch()
    return folder


def archived_job(ctx: JobContext, kind: str, archive: tuple[str, str, str], uuids: list[str], cache: str, *args: Any,
                 many: bool = False, also: list[str] | None = None, at: int = 0, **kwargs: Any) -> Any:
    """A worker job (kind ``"app.archive.reads:archived_job"``) on archived sessions this station has no folder
    of: each copied from the archive into ``cache`` (the sessions browser's private folder; progress shown), then
    the job ``kind`` run with the folder (``many``: the list of folders, ``also``'s local folders first) put at
    position ``at`` of ``args``."""
    from app.worker.jobs import resolve

    opened, problem = open_by_args(*archive)
    if opened is None:
        raise ArchiveError(f"{problem[:1].upper()}{problem[1:]}: the session cannot be read from it."
                           if problem else "This station has no archive to read the session from.")
    copy_share = 0.4
    try:
        found = []
        for k, uuid in enumerate(uuids):
            def step(f: float, k: int = k) -> bool:
                return bool(ctx.progress(copy_share * (k + f) / len(uuids), "Copying the session from the archive"))
            found.append(str(copy_of(opened, uuid, Path(cache), step)))
    finally:
        opened.close()
    job = resolve(kind)
    call = list(args)
    call.insert(at, [*(also or []), *found] if many else found[0])
    return job(_Share(ctx, copy_share, 1.0 - copy_share), *call, **kwargs)


def progress_job(ctx: JobContext, patient_id: str, root: str, archive: tuple[str, str, str] | None) -> list[Any]:
    """A worker job (kind ``"app.archive.reads:progress_job"``): the progress report's rows of every station (the
    sessions browser's Progress…); the station's folders alone, said in the log, when the archive cannot be read
    (``archive=None``: none is in use)."""
    opened, problem = open_by_args(*archive) if archive is not None else (None, "")
    if problem:
        log.warning("progress of %s: %s; this station's sessions only", patient_id, problem)
    try:
        return progress_rows(patient_id, Path(root), opened, lambda f: ctx.step(f, "Reading the patient's sessions"))
    finally:
        if opened is not None:
            opened.close()
