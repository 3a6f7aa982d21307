"""``linarmpp archive …``: the archive's own commands (app/cli.py hands them over).

    linarmpp archive [--config FILE] status               where the archive is, its schema, what it holds
    linarmpp archive [--config FILE] upgrade              migrate the archive to this version's schema
    linarmpp archive [--config FILE] import DATA_FOLDER   today's patients/*.yaml and sessions/ into the archive
    linarmpp archive [--config FILE] export OUT_FOLDER [--patient ID …]   profiles back to YAML
    linarmpp archive [--config FILE] upload               this station's waiting sessions (the outbox), once
    linarmpp archive [--config FILE] verify               re-hash files and chains; name the first mismatch
    linarmpp archive [--config FILE] patients [--search WORDS] [--json]   the patients: id, name, the station that
                                                          last changed each, how many sessions
    linarmpp archive [--config FILE] patient add ID [--name …] [--birth-date …] [--record-number …] [--side …]
                     [--k-r …] [--k-f …] [--fes-profile …] [--score KEY=VALUE …] [--robot KEY=VALUE …]
                     [--cap CH:KEY=VALUE …] [--notes …] [--operator NAME]
                                                          a new patient, checked as the Patients form checks one
    linarmpp archive grants ROLE                          the SQL that gives a PostgreSQL role the app's rights

Exit codes: 0 done, 1 refused or failed (one sentence on stderr), 2 wrong arguments, 3 ``verify`` found a
mismatch (named on stderr), 4 ``upload`` left sessions waiting (the archive cannot be reached).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from app.archive.patient_form import CAP_KEYS, ROBOT_KEYS, SCORE_KEYS

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
    patients = sub.add_parser("patients", help="list the patients (id, name, station of the last change, sessions)")
    patients.add_argument("--search", default="", help="only patients with every word in their id, name, record "
                          "number or notes")
    patients.add_argument("--json", action="store_true", help="one JSON array instead of the table")
    patient = sub.add_parser("patient", help="patient records: add")
    patient_sub = patient.add_subparsers(dest="patient_command", required=True)
    add = patient_sub.add_parser("add", help="a new patient, checked as the Patients form checks one")
    add.add_argument("patient_id", metavar="ID", help="identifier or pseudonym: letters, digits, - and _")
    add.add_argument("--name", default="", help="full name (optional: for the printed record)")
    add.add_argument("--birth-date", default="", help="YYYY-MM-DD (optional)")
    add.add_argument("--record-number", default="", help="the clinic's medical record number (optional)")
    add.add_argument("--side", default="unknown", help="affected side: left, right, both or unknown")
    add.add_argument("--k-r", default="", help="assistance gain k_r, the robot's share (0-1)")
    add.add_argument("--k-f", default="", help="assistance gain k_f, the FES share (0-1)")
    add.add_argument("--fes-profile", default="", help="FES profile file (a name in resources/fes_profiles or a path)")
    add.add_argument("--score", action="append", default=[], metavar="KEY=VALUE",
                     help=f"a clinical score (repeatable): {', '.join(SCORE_KEYS)}")
    add.add_argument("--robot", action="append", default=[], metavar="KEY=VALUE",
                     help=f"a robot limit, tighter than the configuration's (repeatable): {', '.join(ROBOT_KEYS)}")
    add.add_argument("--cap", action="append", default=[], metavar="CH:KEY=VALUE",
                     help=f"an FES cap of a stimulator channel (repeatable): {', '.join(CAP_KEYS)}")
    add.add_argument("--notes", default="", help="notes")
    add.add_argument("--operator", default="", help="who adds the patient (recorded); default: your login name")
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
        before, after, copy = upgrade_archive(config)
        print(f"archive schema {before or '(new)'} -> {after}" if before != after else f"archive schema {after}: "
              "already up to date")
        if copy is not None:
            print(f"the archive as it was is kept in {copy}")
        return EXIT_OK
    if args.command == "upload":
        return _upload(config)
    if args.command in ("patients", "patient"):
        return _patients(args, config)
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


# ---------------------------------------------------------------------------------------------- patients
# Each field of the form as the command names it (its messages name the option to correct).
_OPTIONS = {"patient_id": "ID", "full_name": "--name", "birth_date": "--birth-date", "record_number": "--record-number",
            "affected_side": "--side", "assistance": "--k-r/--k-f", "assistance.k_r": "--k-r",
            "assistance.k_f": "--k-f", "fes.profile": "--fes-profile", "fes": "--cap", "fes.caps": "--cap",
            "scores": "--score", "robot": "--robot", "notes": "--notes"}


class _Refused(Exception):
    """A patient the command does not add: its sentence."""


def _option_of(key: str) -> str:
    if key in _OPTIONS:
        return _OPTIONS[key]
    parts = key.split(".")
    if key.startswith("fes.caps.") and len(parts) >= 4:
        return f"--cap {parts[2]}:{parts[3]}"
    if key.startswith("fes.caps."):
        return f"--cap {parts[2]}:…"
    if parts[0] in ("scores", "robot") and len(parts) > 1:
        return f"--{'score' if parts[0] == 'scores' else 'robot'} {parts[1]}"
    return key


def _pairs(option: str, values: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise _Refused(f"{option} {item!r} is not KEY=VALUE (e.g. {option} "
                           f"{'fugl_meyer_ue=31' if option == '--score' else 'max_velocity_m_s=0.3'}).")
        out[key.strip()] = value
    return out


def _caps(values: list[str]) -> dict[Any, dict[str, str]]:
    from app.archive.patient_form import field_value

    out: dict[Any, dict[str, str]] = {}
    for item in values:
        channel, sep, rest = item.partition(":")
        key, sep2, value = rest.partition("=")
        if not sep or not sep2 or not channel.strip() or not key.strip():
            raise _Refused(f"--cap {item!r} is not CH:KEY=VALUE (e.g. --cap 1:max_current_ma=15).")
        ch = field_value(channel)  # a number, as the form's row is its channel; anything else the profile refuses
        out.setdefault(ch if isinstance(ch, int) else channel.strip(), {})[key.strip()] = value
    return out


def _patients(args: argparse.Namespace, config: Any) -> int:
    """``patients`` and ``patient add`` on the station's archive, opened as the application opens it (the embedded
    archive made now takes the data folder's patient files first, as at the application's first start)."""
    from app.archive import station

    profile = None
    if args.command == "patient":  # checked first: nothing is opened (nor made) for a patient that is refused
        try:
            texts = _texts(args)
        except _Refused as exc:
            print(f"Patient not added: {exc}", file=sys.stderr)
            return EXIT_USAGE
        profile = _checked(texts, config)
        if profile is None:
            return EXIT_FAILED
    opened = station.open_station(config)
    if opened.archive is None:
        print(f"{opened.problem[:1].upper()}{opened.problem[1:]}.", file=sys.stderr)
        return EXIT_FAILED
    for problem in opened.import_problems:
        print(problem, file=sys.stderr)
    try:
        if args.command == "patients":
            return _list(opened.archive, args)
        return _add(opened.archive, profile, args, config)
    finally:
        opened.archive.close()


def _texts(args: argparse.Namespace) -> Any:
    from app.archive.patient_form import FormTexts

    return FormTexts(patient_id=args.patient_id, full_name=args.name, birth_date=args.birth_date,
                     record_number=args.record_number, affected_side=args.side.strip(), k_r=args.k_r, k_f=args.k_f,
                     fes_profile=args.fes_profile, scores=_pairs("--score", args.score),
                     robot=_pairs("--robot", args.robot), caps=_caps(args.cap), notes=args.notes)


def _checked(texts: Any, config: Any) -> Any:
    """The form's texts as a valid profile (the Patients form's checks, the configuration's limits), or None with
    the sentence on stderr."""
    from app.archive import patient_form
    from app.therapy.patients import PatientError

    try:
        return patient_form.profile_of(patient_form.form_data(texts), getattr(config, "safety", None))
    except PatientError as exc:
        key = patient_form.error_key(exc.key, exc.problem, _OPTIONS)
        where = f" ({_option_of(key)})" if key and key != "(top level)" else ""
        print(f"Patient not added: {exc.problem.rstrip('.')}{where}.", file=sys.stderr)
        return None


def _add(archive: Any, profile: Any, args: argparse.Namespace, config: Any) -> int:
    """The Patients form's New patient, from the command line: its fields, its checks, its save."""
    from app.archive import station
    from app.archive.api import PatientExists
    from app.therapy.patients import PatientError

    safety = getattr(config, "safety", None)
    try:
        record = station.save_profile(profile, expected_version=None, operator=station.default_operator(args.operator),
                                      safety=safety, archive=archive)
    except PatientExists:
        try:
            have = archive.get_patient(profile.patient_id)
            who = (f": {have.profile.full_name or 'no name'}, last changed by {have.changed_by} on station "
                   f"{have.changed_station} at {have.changed_at}")
        except Exception:  # the refusal stands; who has it is a courtesy
            who = ""
        print(f"Patient not added: {profile.patient_id} is already in the archive at {archive.url}{who}.",
              file=sys.stderr)
        return EXIT_FAILED
    except PatientError as exc:
        print(f"Patient not added: {exc.problem.rstrip('.')} ({_option_of(exc.key)}).", file=sys.stderr)
        return EXIT_FAILED
    print(f"Patient {record.profile.patient_id} added to the archive at {archive.url} (version {record.version}, "
          f"by {record.changed_by} on station {record.changed_station}).")
    return EXIT_OK


def _list(archive: Any, args: argparse.Namespace) -> int:
    import json

    items = []
    offset = 0
    while page := archive.list_patients(args.search, limit=1000, offset=offset):
        items += page
        offset += len(page)
    if args.json:
        print(json.dumps([{"id": p.patient_id, "name": p.full_name, "record_number": p.record_number,
                           "station": p.changed_station, "changed_by": p.changed_by, "changed_at": p.changed_at,
                           "version": p.version, "sessions": p.sessions, "last_session": p.last_session}
                          for p in items], ensure_ascii=False, indent=1))
        return EXIT_OK
    rows = [("ID", "Name", "Last changed on", "Sessions")]
    rows += [(p.patient_id, p.full_name, p.changed_station, str(p.sessions)) for p in items]
    widths = [max(len(r[k]) for r in rows) for k in range(3)]
    for r in rows:
        print(f"{r[0]:<{widths[0]}}  {r[1]:<{widths[1]}}  {r[2]:<{widths[2]}}  {r[3]:>8}".rstrip())
    found = f"matching {args.search!r} " if args.search else ""
    print(f"{len(items)} patient{'' if len(items) == 1 else 's'} {found}in the archive at {archive.url}")
    return EXIT_OK
