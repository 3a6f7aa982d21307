"""``linarmpp export --format bids|xdf|edf SESSION… --out DIR [--config FILE]``: recorded sessions for research tools.

Exit codes (as the report commands'): 0 every file written and read back; 1 nothing written (one sentence on
stderr: no session could be read, the archive cannot be reached); 2 wrong arguments (a configuration refused
among them); 3 written, but something is missing (a session that could not be read, an archived session's UUID the
archive does not hold, a session recorded incompletely, a file that could not be written): stderr lists what.

A SESSION is a session folder; a patient's folder (its sessions) or the sessions folder (every patient's) may be
named instead; or an archived session's UUID (issue #39), read from the clinic's archive as it streams (never copied
into a folder first): the archive of ``--config FILE`` (default: the user's configuration, the embedded archive in
``<data>``), opened only when a UUID is named and closed at the end, whatever happens. Folders and UUIDs may be
mixed; a session named twice (its folder and its UUID) is exported once. Progress goes to stderr; the written files
are listed on stdout.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import logging
import sys
import uuid as _uuid
from pathlib import Path
from typing import Any

from app.research_export.common import ExportCancelled, ExportError, ExportResult, release_memory_promptly
from app.research_export.source import ArchivedSource, FolderSource, Session, is_session_folder, open_session
from app.session.recording import MANIFEST_FILE, is_session_uuid, safe_name

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INCOMPLETE = 0, 1, 2, 3
FORMATS = ("bids", "xdf", "edf")
log = logging.getLogger(__name__)


def build_parser(prog: str = "linarmpp export") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="Export recorded sessions for research tools: a BIDS "
                                     "dataset, one XDF file or one EDF+ file per session (docs/export.md).")
    parser.add_argument("--format", required=True, choices=FORMATS, help="bids, xdf or edf")
    parser.add_argument("sessions", nargs="+", metavar="SESSION",
                        help="session folders (or a patient's folder, or the sessions folder), or archived sessions' "
                        "UUIDs")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="bids: the dataset's folder (new or empty); xdf, edf: the folder for the files")
    parser.add_argument("--include-names", action="store_true",
                        help="write the patients' full names (participants.tsv, EDF header); default: pseudonyms")
    parser.add_argument("--shift-days", type=int, default=0, metavar="N",
                        help="move every date back by N days (de-identification; BIDS recommends it)")
    parser.add_argument("--name", default="LINarm++ Manager sessions", help="the BIDS dataset's name")
    parser.add_argument("--no-metrics", action="store_true", help="bids: leave out derivatives/linarmpp-metrics")
    parser.add_argument("--xdf-clock", choices=("host", "device"), default="host",
                        help="xdf: the time stamps of the devices' streams: host (default: every sample at its "
                        "recorded time, clock offsets 0, each device's clock in the stream's header) or device "
                        "(on the device's own clock, the measured map to the host's as clock offsets)")
    parser.add_argument("--config", metavar="FILE", help="the configuration naming the clinic's archive, read when a "
                        "SESSION is a UUID (default: the user's configuration: the archive in the data folder)")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return parser


class _Usage(Exception):
    pass


def _expand(paths: list[str]) -> list[Path | str]:
    """Session folders named, or found one or two levels below a folder named; and archived sessions' UUIDs (a text
    that names nothing on disk and is a UUID, as the report commands take it), in the form the archive keys them by."""
    out: list[Path | str] = []
    for text in paths:
        path = Path(text)
        if not path.exists():
            if is_session_uuid(text):
                out.append(str(_uuid.UUID(text)))
                continue
            raise _Usage(f"{text} does not exist (and is not an archived session's UUID)")
        if is_session_folder(path):
            out.append(path)
            continue
        if not path.is_dir():
            raise _Usage(f"{text} is not a session folder (no {MANIFEST_FILE})")
        found = sorted(p for p in path.iterdir() if is_session_folder(p))
        if not found:
            found = sorted(q for p in path.iterdir() if p.is_dir() for q in p.iterdir() if is_session_folder(q))
        if not found:
            raise _Usage(f"{text} is not a session folder and holds none (no {MANIFEST_FILE})")
        out += found
    return list(dict.fromkeys(p.resolve() if isinstance(p, Path) else p for p in out))


class _Unreadable(Exception):
    """The archive cannot be read (unreachable, refused, none): one sentence, nothing written."""


def _open_archive(config_file: str | None, uuids: list[str], stack: contextlib.ExitStack) -> Any:
    """The archive the UUIDs are read from, closed with ``stack``; nothing is made where there is no archive yet.
    Raises _Usage (the configuration refused) or _Unreadable."""
    from app.archive.reads import open_for_reading
    from app.core.config import ConfigError, load_config

    try:
        config = load_config(config_file)
    except ConfigError as exc:
        raise _Usage(f"the configuration was refused, nothing was exported: {' '.join(str(exc).split())}") from exc
    archive, problem = open_for_reading(config)
    if archive is None:
        named = ", ".join(uuids)
        raise _Unreadable(f"{problem}; the session{'s' if len(uuids) > 1 else ''} {named} would be read from it"
                          if problem else f"{named} {'is' if len(uuids) == 1 else 'are'} not a session folder, and "
                          "this station has no archive (none is configured, and its data folder holds none)")
    stack.callback(archive.close)
    return archive


def _open_sessions(named: list[Path | str], archive: Any) -> tuple[list[Session], list[str]]:
    """The sessions in the order named (each once: an archived session also named by its folder is read from the
    folder), and what could not be opened."""
    missing: list[str] = []
    opened: dict[int, Session] = {}
    local: set[str] = set()
    for k, item in enumerate(named):
        if isinstance(item, Path):
            try:
                opened[k] = open_session(FolderSource(item))
            except ValueError as exc:
                missing.append(f"{item}: not exported: {exc}")
                continue
            if archive is not None:
                from app.archive.folders import session_uuid

                local.add(session_uuid(item, opened[k].manifest))
    for k, item in enumerate(named):
        if isinstance(item, Path) or item in local:
            continue
        try:
            opened[k] = _open_archived(archive, item)
        except _NotArchived as exc:
            missing.append(f"{item}: not exported: {exc}")
    return [opened[k] for k in sorted(opened)], missing


class _NotArchived(Exception):
    pass


def _open_archived(archive: Any, session_uuid: str) -> Session:
    from app.archive.api import ArchiveError, NotFound
    from app.archive.reads import archived_label

    try:
        info = archive.get_session(session_uuid).info
        files = archive.session_files(session_uuid)
        return open_session(ArchivedSource(files, archived_label(info, archive.url)))
    except NotFound as exc:
        raise _NotArchived(f"the archive has no session {session_uuid}") from exc
    except (ArchiveError, OSError, ValueError) as exc:  # the archive gone away meanwhile, a manifest unreadable
        raise _NotArchived(str(exc)) from exc


class _Terminal:
    """Progress on stderr: one line redrawn on a terminal, a line per tenth elsewhere."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.last = -1

    def __call__(self, fraction: float, text: str) -> None:
        if self.quiet:
            return
        percent = int(fraction * 100)
        if self.tty:
            sys.stderr.write(f"\r{percent:3d}% {text[:70]:<70}")
            sys.stderr.flush()
        elif percent // 10 != self.last // 10:
            print(f"{percent:3d}% {text}", file=sys.stderr)
        self.last = percent

    def done(self) -> None:
        if self.tty and not self.quiet and self.last >= 0:
            sys.stderr.write("\n")


def main(argv: list[str], prog: str = "linarmpp export") -> int:
    parser = build_parser(prog)
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return EXIT_USAGE if stop.code not in (0, None) else EXIT_OK
    try:
        named = _expand(args.sessions)
        out = Path(args.out)
        _check_out(out, args.format)
        if args.shift_days < 0:
            raise _Usage("--shift-days takes a number of days to move dates back (0 or more)")
    except _Usage as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    uuids = [item for item in named if isinstance(item, str)]
    with contextlib.ExitStack() as stack:  # the archive stays open while its sessions stream, and is closed after
        archive = None
        if uuids:
            try:
                archive = _open_archive(args.config, uuids, stack)
            except _Usage as exc:
                print(f"{prog}: {exc}", file=sys.stderr)
                return EXIT_USAGE
            except _Unreadable as exc:
                print(f"Nothing was written: {exc}", file=sys.stderr)
                return EXIT_FAILED
        return _export(named, archive, out, args)


def _export(named: list[Path | str], archive: Any, out: Path, args: argparse.Namespace) -> int:
    sessions, missing = _open_sessions(named, archive)
    if not sessions:
        print(f"Nothing was written: {missing[0] if len(missing) == 1 else 'no session could be read'}",
              file=sys.stderr)
        for line in missing[1:] if len(missing) > 1 else []:
            print(f"  - {line}", file=sys.stderr)
        return EXIT_FAILED
    terminal = _Terminal(args.quiet)
    release_memory_promptly()
    try:
        if args.format == "bids":
            result = _bids(sessions, out, args, terminal)
        else:
            result = _per_session(sessions, out, args, terminal)
    except KeyboardInterrupt:
        terminal.done()
        print("Export interrupted: nothing of it was kept", file=sys.stderr)
        return 130
    except (ExportError, OSError) as exc:
        terminal.done()
        log.exception("the export failed")
        print(f"Nothing was written: {_sentence(exc)}", file=sys.stderr)
        return EXIT_FAILED
    terminal.done()
    missing += result.missing
    for session in sessions:
        for problem in session.problems + session.read_problems():
            missing.append(f"{session.label}: {problem}")
    for note in result.notes:
        print(f"Note: {note}", file=sys.stderr)
    for path in result.written:
        print(path)
    if not result.written:
        print(f"Nothing was written: {missing[0] if missing else 'no session could be exported'}", file=sys.stderr)
        return EXIT_FAILED
    if missing:
        print("Written, but incomplete:", file=sys.stderr)
        for line in dict.fromkeys(missing):
            print(f"  - {line}", file=sys.stderr)
        return EXIT_INCOMPLETE
    return EXIT_OK


def _sentence(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename or ''}{': ' if exc.filename else ''}{exc.strerror}"
    return str(exc)


def _check_out(out: Path, fmt: str) -> None:
    """The output can be made where it is asked for (checked before anything is read)."""
    import tempfile

    if fmt == "bids":
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise _Usage(f"{out} already exists and is not an empty folder: name a new folder for the dataset")
        parent = out.parent if str(out.parent) else Path(".")
    else:
        if out.exists() and not out.is_dir():
            raise _Usage(f"{out} is not a folder")
        parent = out if out.is_dir() else out.parent
    if not parent.is_dir():
        raise _Usage(f"the folder {parent} does not exist")
    try:
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".linarmpp-probe-"):
            pass
    except OSError as exc:
        raise _Usage(f"the folder {parent} is not writable ({exc.strerror or exc})") from exc


def _bids(sessions: list[Session], out: Path, args: argparse.Namespace, terminal: _Terminal) -> ExportResult:
    from app.research_export.bids import BidsOptions, export_bids

    options = BidsOptions(name=args.name, include_names=args.include_names, shift_days=args.shift_days,
                          metrics=not args.no_metrics)
    return export_bids(sessions, out, options, progress=terminal)


def output_name(session: Session, shift_days: int, suffix: str) -> str:
    """``<patient>_<YYYYmmdd-HHMMSS>.<suffix>`` (the session's start, dates shifted when asked)."""
    try:
        start = _dt.datetime.fromisoformat(session.start_iso).replace(tzinfo=None)
    except ValueError:
        start = _dt.datetime.fromtimestamp(session.start_wall or 0.0)
    start -= _dt.timedelta(days=shift_days)
    return f"{safe_name(session.patient_id)}_{start:%Y%m%d-%H%M%S}.{suffix}"


def _per_session(sessions: list[Session], out: Path, args: argparse.Namespace, terminal: _Terminal) -> ExportResult:
    from app.research_export.edf import export_edf
    from app.research_export.xdf import export_xdf

    out.mkdir(exist_ok=True, mode=0o700)
    total = ExportResult()
    used: set[str] = set()
    for k, session in enumerate(sessions):
        name = output_name(session, args.shift_days, args.format)
        stem, n = name.rsplit(".", 1)[0], 2
        while name in used or (out / name).exists():
            name = f"{stem}-{n}.{args.format}"
            n += 1
        used.add(name)
        share = 1.0 / len(sessions)

        def progress(fraction: float, text: str, k: int = k, share: float = share) -> None:
            terminal((k + fraction) * share, f"{k + 1}/{len(sessions)} {text}")

        try:
            if args.format == "xdf":
                result = export_xdf(session, out / name, progress=progress, shift_days=args.shift_days,
                                    clock=args.xdf_clock)
            else:
                result = export_edf(session, out / name, include_names=args.include_names,
                                    shift_days=args.shift_days, progress=progress)
        except ExportCancelled:
            raise
        except (ExportError, OSError, ValueError) as exc:
            log.exception("exporting %s failed", session.label)
            total.missing.append(f"{session.label}: not written: {_sentence(exc)}")
            continue
        total.merge(result)
    return total
