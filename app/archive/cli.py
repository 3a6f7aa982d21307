"""``linarmpp archive …``: the archive's own commands (app/cli.py hands them over).

    linarmpp archive [--config FILE] status               where the archive is, its schema, what it holds
    linarmpp archive [--config FILE] upgrade              migrate the archive to this version's schema
    linarmpp archive [--config FILE] import DATA_FOLDER   today's patients/*.yaml and sessions/ into the archive
    linarmpp archive [--config FILE] export OUT_FOLDER [--patient ID …]   profiles back to YAML
    linarmpp archive [--config FILE] upload               this station's waiting sessions (the outbox), once
    linarmpp archive [--config FILE] verify               re-hash files and chains; name the first mismatch
    linarmpp archive grants ROLE                          the SQL that gives a PostgreSQL role the app's rights

Exit codes: 0 done, 1 refused or failed (one sentence on stderr), 2 wrong arguments, 3 ``verify`` found a
mismatch (named on stderr), 4 ``upload`` left sessions waiting (the archive cannot be reached).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_MISMATCH, EXIT_WAITING = 0, 1, 2, 3, 4


def build_parser(prog: str = "linarmpp archive") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="The clinic's archive (docs/archive.md)")
    parser.add_argument("--config", help="YAML configuration (archive.url, archive.password_file, station)")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("status", help="where the archive is and what it holds")
    sub.add_parser("upgrade", help="migrate the archive to this version's schema")
    imp = sub.add_parser("import", help="a data folder's patients and sessions into the archive")
    imp.add_argument("data", help="the data folder (with patients/ and sessions/)")
    imp.add_argument("--operator", default="import", help="who imports (recorded in each patient's history)")
    exp = sub.add_parser("export", help="patient profiles back to YAML files")
    exp.add_argument("out", help="the folder to write <id>.yaml into")
    exp.add_argument("--patient", action="append", help="only this patient (repeatable)")
    sub.add_parser("upload", help="upload this station's waiting sessions once")
    sub.add_parser("verify", help="re-hash every file and chain")
    grants = sub.add_parser("grants", help="print the SQL granting a PostgreSQL role the application's rights")
    grants.add_argument("role")
    return parser


def archive_main(argv: list[str], prog: str = "linarmpp archive") -> int:
    try:
        args = build_parser(prog).parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0) and EXIT_USAGE
    if args.command == "grants":
        from app.archive.schema import grant_statements

        print(";\n".join(grant_statements(args.role)) + ";")
        return EXIT_OK
    from app.archive.api import ArchiveError
    from app.core.config import ConfigError, load_config

    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"Configuration refused: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        return _run(args, config)
    except ArchiveError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_FAILED
    except OSError as exc:
        print(f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": "), file=sys.stderr)
        return EXIT_FAILED


def _run(args: argparse.Namespace, config: object) -> int:
    from app.archive.store import open_archive, upgrade_archive

    if args.command == "upgrade":
        before, after = upgrade_archive(config)
        print(f"archive schema {before or '(new)'} -> {after}" if before != after else f"archive schema {after}: "
              "already up to date")
        return EXIT_OK
    if args.command == "upload":
        return _upload(config)
    with open_archive(config) as archive:
        if args.command == "status":
            print(f"archive: {archive.url}\nstation: {archive.station}\nschema: {archive.schema_revision()}\n"
                  f"patients: {len(archive.list_patients(limit=1_000_000))}\nsessions: {archive.count_sessions()}")
            return EXIT_OK
        if args.command == "import":
            from app.archive.transfer import import_data_folder

            report = import_data_folder(archive, Path(args.data), operator=args.operator)
            print("\n".join(report.lines()))
            return EXIT_FAILED if report.failed else EXIT_OK
        if args.command == "export":
            from app.archive.transfer import export_profiles

            for path in export_profiles(archive, Path(args.out), args.patient):
                print(path)
            return EXIT_OK
        if args.command == "verify":
            report = archive.verify()
            if report.ok:
                print(f"archive verified: {report.files} files ({report.bytes} bytes) and {report.rows} chained rows "
                      "match")
                return EXIT_OK
            for problem in report.problems:
                print(f"MISMATCH {problem}", file=sys.stderr)
            return EXIT_MISMATCH
    return EXIT_USAGE


def _upload(config: object) -> int:
    from app.archive.outbox import Outbox
    from app.archive.store import open_archive
    from app.session.recording import sessions_root

    outbox = Outbox(sessions_root(config), lambda: open_archive(config))  # type: ignore[arg-type]
    status = outbox.run_once(force=True)
    print(f"{status.uploaded} session(s) archived")
    if status.waiting:
        print(status.text(), file=sys.stderr)
        return EXIT_WAITING
    return EXIT_OK
