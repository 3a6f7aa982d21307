"""The research export as one task for the worker process (the sessions browser's Export…, issue #41).

``export_sessions`` writes the chosen sessions in one format into a folder, all or nothing: every file is made in a
staging folder beside the destination (``.<name>.part-<token>``, the name app.core.outputs gives temporaries, so the
task service removes it when a worker dies mid-export), read back there, and only once every session is written
moved out into the folder; a cancel or a failure removes the staging folder, so nothing is said written that is
not. A session that cannot be read or written is left out and said (the others are written), as the command line
does (exit 3).

The worker runs :func:`research_export` by the kind ``"app.research_export.jobs:research_export"`` (app/worker/jobs.py
resolves ``module:function``); the task's ``outputs`` is :func:`staging_target`, whose temporaries are the staging
folder. Qt-free.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import os
import secrets
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from app.archive.api import Archive, ArchiveError
from app.research_export.common import DIR_MODE, Cancel, ExportCancelled, ExportError, Progress, remove_quietly
from app.research_export.source import ArchivedSource, FolderSource, Session, SessionSource, open_session
from app.worker.context import Cancelled, JobContext, JobError

log = logging.getLogger(__name__)

JOB_KIND = "app.research_export.jobs:research_export"
FORMAT_TITLES = {"bids": "a BIDS dataset", "xdf": "XDF files", "edf": "EDF+ files"}
STAGING_STEM = "linarmpp-export"


@dataclass
class Outcome:
    """What an export left in the destination folder (moved there whole) and the sessions it left out, and why."""

    written: list[Path] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)

    def sentence(self, fmt: str, folder: Path) -> str:
        what = FORMAT_TITLES[fmt]
        if fmt == "bids":
            text = f"Exported to {self.written[0]} ({what}, read back)."
        else:
            names = ", ".join(p.name for p in self.written)
            text = f"Exported {len(self.written)} file(s) to {folder} ({what}, read back): {names}."
        if self.missing:
            text += f" Left out or incomplete: {'; '.join(self.missing)}."
        return text


def staging_target(folder: Path, stamp: str) -> Path:
    """The name an export's staging folder is a temporary of (``.linarmpp-export-<stamp>.part-<token>``)."""
    return folder / f"{STAGING_STEM}-{stamp}"


def export_sessions(fmt: str, folders: Sequence[Path | SessionSource], destination: Path, stamp: str, *,
                    include_names: bool = False, shift_days: int = 0, progress: Progress | None = None,
                    cancel: Cancel | None = None) -> Outcome:
    """Export ``folders`` (session folders, or sources such as an archived session's ``ArchivedSource``) as ``fmt``
    into the folder ``destination``: a BIDS dataset ``linarmpp-bids-<stamp>``, or a file per session. Raises
    ExportCancelled or ExportError (nothing written)."""
    if fmt not in FORMAT_TITLES:
        raise ExportError(f"there is no export format called {fmt!r}")
    destination = Path(destination)
    if not destination.is_dir():
        raise ExportError(f"the folder {destination} does not exist")
    outcome = Outcome()
    sessions: list[Session] = []
    for folder in folders:
        try:
            sessions.append(open_session(FolderSource(folder) if isinstance(folder, str | Path) else folder))
        except ValueError as exc:
            outcome.missing.append(f"{_label(folder if isinstance(folder, str | Path) else folder.label)}: {exc}")
    if not sessions:
        raise ExportError(outcome.missing[0] if len(outcome.missing) == 1 else "no session could be read")
    target = staging_target(destination, stamp)
    staging = target.with_name(f".{target.name}.part-{secrets.token_hex(4)}")
    try:
        staging.mkdir(mode=DIR_MODE)
    except OSError as exc:
        raise ExportError(f"the folder {destination} cannot be written ({exc.strerror or exc})") from exc
    try:
        made = _write(fmt, sessions, staging, stamp, include_names, shift_days, progress, cancel, outcome)
        if cancel is not None and cancel():
            raise ExportCancelled("export cancelled")
        if not made:
            raise ExportError(outcome.missing[0] if len(outcome.missing) == 1 else "no session could be written")
        outcome.written = _move_out(made, destination)
    except BaseException:
        remove_quietly(staging)
        raise
    remove_quietly(staging)
    for session in sessions:
        for problem in session.problems + session.read_problems():
            outcome.missing.append(f"{_label(session.label)}: {problem}")
    outcome.missing = list(dict.fromkeys(outcome.missing))
    return outcome


def _write(fmt: str, sessions: list[Session], staging: Path, stamp: str, include_names: bool, shift_days: int,
           progress: Progress | None, cancel: Cancel | None, outcome: Outcome) -> list[Path]:
    from app.research_export.command import output_name

    if fmt == "bids":
        from app.research_export.bids import BidsOptions, export_bids

        result = export_bids(sessions, staging / f"linarmpp-bids-{stamp}",
                             BidsOptions(include_names=include_names, shift_days=shift_days), progress, cancel)
        return list(result.written)
    from app.research_export.edf import export_edf
    from app.research_export.xdf import export_xdf

    made: list[Path] = []
    for k, session in enumerate(sessions):
        name = output_name(session, shift_days, fmt)
        stem, n = name.rsplit(".", 1)[0], 2
        while (staging / name).exists():
            name = f"{stem}-{n}.{fmt}"
            n += 1
        share = 1.0 / len(sessions)

        def step(fraction: float, text: str, k: int = k, share: float = share) -> None:
            if progress is not None:
                progress((k + fraction) * share, f"{k + 1} of {len(sessions)}: {text}")

        try:
            if fmt == "xdf":
                result = export_xdf(session, staging / name, progress=step, cancel=cancel, shift_days=shift_days)
            else:
                result = export_edf(session, staging / name, include_names=include_names, shift_days=shift_days,
                                    progress=step, cancel=cancel)
        except (ExportError, OSError, ValueError) as exc:
            log.exception("exporting %s failed", session.label)
            outcome.missing.append(f"{_label(session.label)}: not written ({_sentence(exc)})")
            continue
        made += result.written
    return made


def _move_out(made: list[Path], destination: Path) -> list[Path]:
    """Every file (or the dataset's folder) from the staging folder into ``destination``, under a name nothing there
    has; if a move fails, those already moved are taken back (so it is all or nothing)."""
    moved: list[tuple[Path, Path]] = []
    try:
        for path in made:
            final = destination / path.name
            stem, suffix, n = final.stem, final.suffix, 2
            while final.exists():
                final = destination / f"{stem}-{n}{suffix}"
                n += 1
            os.rename(path, final)  # the same file system: the staging folder is beside the destination
            moved.append((path, final))
        fd = os.open(destination, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        for path, final in reversed(moved):
            try:
                os.rename(final, path)
            except OSError:
                remove_quietly(final)
        raise ExportError(f"the export could not be moved into {destination} ({exc.strerror or exc})") from exc
    return [final for _, final in moved]


def _label(folder: str | Path) -> str:
    """A session as the browser names it: its patient's folder and its own (``PZ-017/20260301-100000``); an archived
    session by its source's label (app.archive.reads.archived_label)."""
    path = Path(folder)
    return f"{path.parent.name}/{path.name}" if path.is_absolute() else str(folder)


def _sentence(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename or ''}{': ' if exc.filename else ''}{exc.strerror}"
    return str(exc)


def new_stamp() -> str:
    return _dt.datetime.now().strftime("%Y%m%d-%H%M%S")


def research_export(ctx: JobContext, fmt: str, folders: list[str], destination: str, stamp: str,
                    include_names: bool = False, shift_days: int = 0, archived: list[str] | None = None,
                    archive: tuple[str, str, str] | None = None) -> str:
    """The worker's task: :func:`export_sessions` with the task's progress and cancel; returns the sentence the
    window shows. A failure is a JobError (its sentence); a cancel ends the task cancelled.

    ``folders`` are session folders, and the UUIDs among them named in ``archived`` sessions the clinic's archive
    holds (another station's: no folder here), read as they stream from the archive ``archive`` (its (url,
    password_file, station): app.archive.reads.args_of) — never copied into a folder first, each file checked
    against its SHA-256 as it is read (``ArchivedSource``), as ``linarmpp export UUID`` reads them. The archive is
    opened in this process and closed at the end."""
    from app.research_export.common import release_memory_promptly

    release_memory_promptly()
    ctx.step(0.0, "Reading the sessions")
    with contextlib.ExitStack() as stack:
        sources: list[Path | SessionSource] = []
        unread: list[str] = []
        uuids = set(archived or ())
        opened = _open_archive(archive, stack) if uuids else None
        for item in folders:
            if item not in uuids:
                sources.append(Path(item))
                continue
            try:
                sources.append(_archived_source(opened, item))
            except (ArchiveError, OSError) as exc:
                unread.append(f"archived session {item}: not exported ({_sentence(exc)})")
        try:
            if not sources:
                raise ExportError(unread[0] if len(unread) == 1 else "no session could be read")
            outcome = export_sessions(fmt, sources, Path(destination), stamp, include_names=include_names,
                                      shift_days=shift_days, progress=lambda f, text: ctx.progress(f, text),
                                      cancel=lambda: ctx.cancelled)
        except ExportCancelled as exc:
            raise Cancelled() from exc
        except (ExportError, OSError) as exc:
            raise JobError(f"The export was not written: {_sentence(exc)}.") from exc
    outcome.missing = unread + outcome.missing
    return outcome.sentence(fmt, Path(destination))


def _open_archive(args: tuple[str, str, str] | None, stack: contextlib.ExitStack) -> Archive:
    from app.archive.reads import open_by_args

    archive, problem = open_by_args(*args) if args is not None else (None, "")
    if archive is None:
        raise JobError(f"The export was not written: {problem[:1].upper()}{problem[1:].rstrip('.')}; the sessions of "
                       "other stations are read from it." if problem else
                       "The export was not written: this station has no archive to read other stations' sessions "
                       "from.")
    stack.callback(archive.close)
    return archive


def _archived_source(archive: Archive, session_uuid: str) -> ArchivedSource:
    from app.archive.reads import archived_label

    info = archive.get_session(session_uuid).info
    return ArchivedSource(archive.session_files(session_uuid), archived_label(info, archive.url))
