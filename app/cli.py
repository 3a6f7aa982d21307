"""The command line: ``linarmpp`` (installed), ``linarmpp-gui`` (Windows, no console) and ``python main.py``
all run :func:`main`. With no arguments: the clinician window, every device simulated.

    linarmpp [--config FILE]                                the clinician window
    linarmpp --headless --script FILE [--duration S] [--record DIR] [--patient ID --operator NAME]
    linarmpp --headless --exercise NAME [--param NAME=VALUE]… [--duration S] [--record DIR] [--patient … --operator …]
                                                            a library exercise by its form's values, as its tab runs it
    linarmpp --version
    linarmpp --install-desktop-entry                       the application menu entry (Linux)
    linarmpp --metrics SESSION_FOLDER|UUID                 per-repetition metrics as JSON (docs/metrics.md)
    linarmpp --report SESSION_FOLDER|UUID --out FILE.pdf   the session's PDF report (UUID: an archived session)
    linarmpp --progress PATIENT_ID --out FILE.pdf          the patient's progress PDF (every station's sessions)
    linarmpp --export SESSION_FOLDER|UUID --out FILE.h5|FOLDER   the session as one HDF5 file, or CSV files in a folder
    linarmpp archive {status,upgrade,import,export,upload,verify,patients,patient,grants} …   the archive
                      (docs/archive.md)
    linarmpp export --format bids|xdf|edf SESSION_FOLDER|UUID… --out DIR [--config FILE]
                      sessions for research tools (docs/export.md; UUID: an archived session, read from the archive)
                      (exit 0 done, 1 nothing written: why on stderr, 2 wrong arguments,
                       3 done from an incomplete session: what is missing on stderr)

Every output is verified before it is said written (app/core/outputs.py): a full disk or a read-only folder is one
sentence on stderr and exit 1, and leaves nothing at the destination. Exports run in the worker process
(app/worker): HDF5 can crash the process that writes it on a full disk, and that is then a failed export. A data
folder that cannot be written (``LINARMPP_HOME``, a read-only disk) is one line and exit 1 (the window: a message
box too; ``--headless``: exit 4, as for a record folder that cannot be written).

SIGTERM, SIGINT (Ctrl-C) and SIGHUP end the window or a headless run the same way: the devices are brought to
a safe state at once (FES Stop, robot IDLE; app/core/signal_events.py), the session is closed, and the process
exits with 128 + the signal's number (143, 130, 129).

The parser is built in one place, :func:`build_parser`: a new option is one ``add_argument`` line there.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from typing import Any

from app import __version__


def build_parser(prog: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="LINarm++ Manager")
    parser.add_argument("--version", action="version", version=f"LINarm++ Manager {__version__}")
    parser.add_argument("--config", help="YAML configuration (defaults: every device simulated)")
    parser.add_argument("--headless", action="store_true", help="no window: run --script or --exercise and exit")
    parser.add_argument("--script", help="exercise script to run (with --headless)")
    parser.add_argument("--exercise", metavar="NAME", help="with --headless: run this exercise of the library (its "
                        "file's name, e.g. trigger_reaching, or its title) as the Exercises tab starts it")
    parser.add_argument("--param", metavar="NAME=VALUE", action="append", default=[],
                        help="with --exercise: a value of its form, checked against its range as the form checks it "
                        "(repeat for each; the others keep their defaults)")
    parser.add_argument("--duration", type=float, help="stop the script or exercise after this many seconds")
    parser.add_argument("--record", help="record the session into this folder")
    parser.add_argument("--patient", metavar="ID", help="with --headless: the session is this patient's (their "
                        "profile's limits apply), recorded with the station's sessions and archived")
    parser.add_argument("--operator", metavar="NAME", help="with --patient: who runs the session")
    parser.add_argument("--screenshot", help="save the window to this PNG once every device is connected, then quit")
    parser.add_argument("--quit-after", type=float, help="close the window after this many seconds")
    parser.add_argument("--metrics", metavar="SESSION", help="print the session's per-repetition metrics (JSON); "
                        "SESSION: its folder, or an archived session's UUID")
    parser.add_argument("--report", metavar="SESSION", help="write the session's PDF report to --out; SESSION: its "
                        "folder, or an archived session's UUID")
    parser.add_argument("--progress", metavar="PATIENT_ID", help="write the patient's progress PDF to --out (every "
                        "station's sessions in the archive, and this station's not yet archived)")
    parser.add_argument("--export", metavar="SESSION", help="export the session to --out: FILE.h5 (HDF5) or a new "
                        "FOLDER (CSV files); SESSION: its folder, or an archived session's UUID")
    parser.add_argument("--out", metavar="FILE", help="output of --report / --progress / --export")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument("--install-desktop-entry", action="store_true",
                        help="add LINarm++ Manager to this user's application menu (Linux), then exit")
    return parser


def parse_args(argv: list[str], prog: str | None = None) -> argparse.Namespace:
    return build_parser(prog).parse_args(argv)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["archive"]:
        return _archive_command(argv[1:], prog)
    if argv[:1] == ["export"]:
        return _export_command(argv[1:], prog)
    args = parse_args(argv, prog)
    refusal = _run_arguments_refusal(args)
    if refusal:
        _report_error(f"Nothing was started: {refusal}.")
        return 2
    from app.core.paths import set_private_umask

    set_private_umask()  # patient data: files 0600, folders 0700, whatever the login's umask (issue #17)
    if args.install_desktop_entry:
        return _install_desktop_entry()
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") and sys.platform.startswith("linux"):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import logging

    from app.core.config import ConfigError, load_config
    from app.core.logging_setup import setup_logging

    report_command = bool(args.metrics or args.report or args.progress or args.export)
    try:
        # A report command says what happened in its own lines on stderr; its log goes to the log file only.
        setup_logging(logging.DEBUG if args.verbose else logging.INFO, console=not report_command or args.verbose)
    except OSError as exc:  # a read-only data folder (issue #37): one line, not a traceback
        _report_error(f"LINarm++ Manager cannot use its data folder: {exc}; nothing was started. Set LINARMPP_HOME "
                      "to a folder you can write, or free the disk.",
                      window=not args.headless and os.environ.get("QT_QPA_PLATFORM") != "offscreen"
                      and not report_command)
        return 4 if args.headless else 1
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        # Headless: exit 2 and the message; the window: also a dialog naming the file and line.
        _report_error(f"Configuration refused, nothing was started:\n  {exc}",
                      window=not args.headless and os.environ.get("QT_QPA_PLATFORM") != "offscreen")
        return 2
    if report_command:
        return _report_command(config, args)
    if args.headless:
        if not args.script and not args.exercise:
            _report_error("--headless needs --script FILE or --exercise NAME")
            return 2
        from app.archive import station
        from app.scripting import headless

        if bool(args.patient) != bool(args.operator and args.operator.strip()):
            _report_error("--patient and --operator go together: a session is a patient and the person who runs it")
            return 2
        if args.exercise:  # the exercise and its values, before anything starts
            try:
                exercise = headless.library_exercise(args.exercise)
                values = headless.exercise_values(exercise, args.param)
            except headless.ExerciseRefused as exc:
                _report_error(f"Nothing was started: {exc}.")
                return 2
        opened = _open_archive_headless(config)
        if opened is None:
            return 2
        try:
            record = _headless_patient(args.patient, config) if args.patient else None
            if args.patient and record is None:
                return 2
            operator = (args.operator or "").strip()
            if args.exercise:
                refused = headless.prescription_refusal(config, exercise, values, record.profile) if record else ""
                if refused:
                    _report_error(f"Nothing was started: the limits of patient {args.patient} refuse "
                                  f"{exercise.title} with these values ({refused}).")
                    return 2
                code = headless.run_headless_exercise(config, exercise, values, duration_s=args.duration,
                                                      record_dir=args.record, patient=args.patient, operator=operator)
            else:
                code = headless.run_headless(config, args.script, duration_s=args.duration, record_dir=args.record,
                                             patient=args.patient, operator=operator)
        finally:
            archive = station.uninstall()
            if archive is not None:
                archive.close()
        if code > 128:  # ended by a signal, devices safe and session closed: no slow interpreter teardown
            _exit_now(code)
        return code
    from app.application import run_gui

    return run_gui(config, screenshot=args.screenshot, quit_after_s=args.quit_after)


def _open_archive_headless(config: object) -> object:
    """The station's archive for a headless run, installed (app.archive.station); None when it is refused (the
    sentence on stderr; exit 2). An archive that cannot be reached: said on stderr, and the run goes on."""
    from app.application import archive_refusal
    from app.archive import station

    try:
        opened = station.open_station(config)
    except Exception as exc:
        refusal = archive_refusal(exc)
        if not refusal:
            raise
        print(refusal, file=sys.stderr)
        return None
    station.install(opened.archive, opened.problem)
    if opened.message():
        print(opened.message(), file=sys.stderr)
    return opened


def _run_arguments_refusal(args: argparse.Namespace) -> str:
    """Why these options cannot go together ("" when they can), checked before anything starts."""
    if args.param and not args.exercise:
        return "--param sets a value of the exercise --exercise NAME runs; give --exercise"
    if args.exercise and args.script:
        return "--exercise and --script each say what to run; give one of them"
    if args.exercise and not args.headless:
        return "--exercise runs an exercise without the window; add --headless"
    return ""


def _headless_patient(patient_id: str, config: object) -> Any:
    """The patient's record (app.archive.api.PatientRecord) when a headless session may start for ``patient_id``:
    their record is in the archive (or, without one, their profile file). Otherwise None and one line on stderr
    (nothing is started): a mistyped identifier would record a session for nobody, without the caps of the
    patient meant."""
    from app.archive import station
    from app.archive.api import ArchiveError
    from app.therapy.patients import PatientError

    try:
        record = station.read_record(patient_id, getattr(config, "safety", None))
    except (ArchiveError, PatientError, OSError) as exc:
        print(f"The session was not started: the profile of patient {patient_id} cannot be read ({exc}).",
              file=sys.stderr)
        return None
    if record is None:
        where = "in the archive" if station.in_use() else "among this station's patients"
        print(f"The session was not started: there is no patient {patient_id} {where}. Create them in the "
              "Patients window first.", file=sys.stderr)
    return record


def _archive_command(argv: list[str], prog: str | None) -> int:
    """``linarmpp archive …`` (app/archive/cli.py): its own parser and exit codes."""
    from app.archive.cli import archive_main
    from app.core.logging_setup import setup_logging
    from app.core.paths import set_private_umask

    set_private_umask()
    setup_logging(console=False)  # the command's own sentences go to stderr; details to the log
    return archive_main(argv, f"{prog or 'linarmpp'} archive")


EXIT_REPORT_OK, EXIT_REPORT_FAILED, EXIT_REPORT_USAGE, EXIT_REPORT_INCOMPLETE = 0, 1, 2, 3


def _report_command(config: object, args: argparse.Namespace) -> int:
    """``--metrics`` / ``--report`` / ``--progress``, with the answers a caller can act on (docs/sessions.md):
    0 done; 1 nothing written (the output cannot be written, the session cannot be read) with one line
    saying why; 2 wrong arguments; 3 done from what was recorded, but the session is incomplete, and
    stderr lists what is missing (a failed or crashed recording, samples or events the files lack)."""
    from pathlib import Path

    from app.session.recording import MANIFEST_FILE

    if args.export and not args.out:
        print("--export needs --out FILE.h5 or --out FOLDER", file=sys.stderr)
        return EXIT_REPORT_USAGE
    if args.export and not (Path(args.export) / MANIFEST_FILE).is_file() and not _is_uuid(args.export):
        print(f"{args.export} is not a session folder (no {MANIFEST_FILE}) nor an archived session's UUID",
              file=sys.stderr)
        return EXIT_REPORT_USAGE
    if args.out and (args.report or args.progress or args.export):
        problem = _unwritable(Path(args.out), folder_ok=bool(args.export))
        if problem:
            print(f"Cannot write {args.out}: {problem}; nothing was written", file=sys.stderr)
            return EXIT_REPORT_FAILED
    with contextlib.ExitStack() as stack:
        archive, problem = _report_archive(config, args, stack)
        if problem and args.progress:
            print(f"{problem[:1].upper()}{problem[1:]}: the progress report holds only this station's sessions.",
                  file=sys.stderr)
        origins: dict[str, str] = {}
        try:
            given = {"metrics": args.metrics, "report": args.report, "export": args.export}
            for key, value in given.items():
                if value:
                    folder, origins[key] = _session_folder(value, archive, problem, stack)
                    setattr(args, key, folder)
        except _NoSession as exc:
            print(str(exc), file=sys.stderr)
            return EXIT_REPORT_USAGE
        named = {getattr(args, k): v for k, v in given.items() if v}
        code = _report_command_run(config, args, archive, named, origins.get("report", ""))
        if code == EXIT_REPORT_OK and problem and args.progress:
            return EXIT_REPORT_INCOMPLETE  # written, without the other stations' sessions (said above)
        return code


class _NoSession(Exception):
    """``--metrics`` / ``--report`` / ``--export`` named neither a session folder nor a session the archive holds."""


def _is_uuid(text: str) -> bool:
    from app.session.recording import is_session_uuid

    return is_session_uuid(text)


def _report_archive(config: object, args: argparse.Namespace, stack: contextlib.ExitStack) -> tuple[object, str]:
    """The station's archive for the report commands, installed for their reads of the patient (app.archive.station)
    and closed with ``stack``: only when one reads it (``--progress``, ``--report``, an archived session's UUID);
    (None, why) when it cannot be read; nothing is made where there is no archive yet."""
    from pathlib import Path

    from app.session.recording import MANIFEST_FILE

    uuids = [v for v in (args.metrics, args.report, args.export)
             if v and not (Path(v) / MANIFEST_FILE).is_file() and _is_uuid(v)]
    if not (args.progress or args.report or uuids):
        return None, ""
    from app.archive import station
    from app.archive.reads import open_for_reading

    archive, problem = open_for_reading(config)
    if archive is not None:
        station.install(archive)
        stack.callback(archive.close)
        stack.callback(station.uninstall)
    return archive, problem


def _session_folder(given: str, archive: object, problem: str, stack: contextlib.ExitStack) -> tuple[str, str]:
    """(a session folder for ``given``, what it is): the folder itself (''), or an archived session's UUID
    materialised into a private temporary folder (removed with ``stack``; "archived session <uuid> …"). Every reader
    of a session reads a folder (app.session.recording), so the metrics and the report of an archived session are those
    of
    its folder, computed by the same code, each file checked against its SHA-256 as it is written."""
    from pathlib import Path

    from app.session.recording import MANIFEST_FILE

    if (Path(given) / MANIFEST_FILE).is_file() or not _is_uuid(given):
        return given, ""  # a folder, or not a session: run_report_command says so (exit 2)
    if archive is None:
        why = f"the archive cannot be read ({problem})" if problem else "this station has no archive"
        raise _NoSession(f"{given} is not a session folder, and {why}.")
    from app.archive.api import NotFound

    try:
        info = archive.get_session(given).info  # type: ignore[attr-defined]
        folder = stack.enter_context(archive.materialised(given))  # type: ignore[attr-defined]
    except NotFound as exc:
        raise _NoSession(f"{given} is not a session folder, and the archive has no session {given}.") from exc
    from app.archive.reads import archived_label

    return str(folder), archived_label(info, archive.url)  # type: ignore[attr-defined]


def _report_command_run(config: object, args: argparse.Namespace, archive: object, named: dict[str, str],
                        report_origin: str) -> int:
    """The report commands once their sessions are folders (``named``: each folder -> what the user gave)."""
    import logging
    from pathlib import Path

    from app.core.outputs import OutputError
    from app.session.recording import MANIFEST_FILE, session_problems
    from app.session.reports import run_report_command

    incomplete = False
    for folder in dict.fromkeys(f for f in (args.metrics, args.report, args.export) if f):
        if not (Path(folder) / MANIFEST_FILE).is_file():
            continue  # run_report_command says it is not a session folder (exit 2)
        problems = session_problems(folder)
        if problems:
            incomplete = True
            print(f"Incomplete session {named.get(folder, folder)}: the output covers only what was recorded.",
                  file=sys.stderr)
            for line in problems:
                print(f"  - {line}", file=sys.stderr)
    try:
        code = EXIT_REPORT_OK
        if args.metrics or args.report or args.progress:
            from app.archive.reads import progress_rows

            code = run_report_command(config, metrics=args.metrics, report=args.report, progress=args.progress,
                                      out=args.out, report_origin=report_origin, archive_read=archive is not None,
                                      rows_of=lambda pid, root: progress_rows(pid, root, archive))  # type: ignore[arg-type]
        sys.stdout.flush()  # --metrics' JSON: a full disk under a redirected stdout shows here, not at exit
        if code == EXIT_REPORT_OK and args.export:
            code = _session_export_command(args.export, Path(args.out))
    except OutputError as exc:  # the output could not be written or verified: its one sentence
        print(exc.sentence, file=sys.stderr)
        return EXIT_REPORT_FAILED
    except OSError as exc:
        _quiet_stdout()
        where = exc.filename or args.out or "the standard output"
        print(f"Cannot write {where}: {exc.strerror or exc}; nothing was written.", file=sys.stderr)
        return EXIT_REPORT_FAILED
    except Exception as exc:  # a damaged session no reader expected: one line here, the traceback in the log
        logging.getLogger(__name__).exception("the report command failed")
        print(f"Cannot read the session {args.metrics or args.report or args.progress or args.export}: "
              f"{type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_REPORT_FAILED
    if code == EXIT_REPORT_OK and incomplete:
        return EXIT_REPORT_INCOMPLETE
    return code


def _export_command(argv: list[str], prog: str | None) -> int:
    """``linarmpp export --format bids|xdf|edf SESSION… --out DIR`` (issue #41; app/research_export/command.py)."""
    import logging

    from app.core.logging_setup import setup_logging
    from app.core.paths import set_private_umask
    from app.research_export.command import main as export_main

    set_private_umask()  # exports hold health data: files 0600, folders 0700
    try:
        setup_logging(logging.INFO, console=False)  # the terminal shows progress; details go to the log
    except OSError:
        pass  # no log folder: the export still runs and says what it did on the terminal
    return export_main(argv, prog=f"{prog or 'linarmpp'} export")


def _session_export_command(session: str, out: object) -> int:
    """``--export``: in the worker process (a crash of HDF5 there is a failed export, one sentence)."""
    from pathlib import Path

    from app.worker import TaskFailed, TaskService

    dest = Path(str(out))
    kind = "export_hdf5" if dest.suffix.lower() in (".h5", ".hdf5") else "export_csv"
    service = TaskService(nice=0)
    try:
        message = service.run(kind, str(Path(session).resolve()), str(dest.resolve()), outputs=(dest.resolve(),),
                              title=f"The export of {Path(session).name} to {dest}")
    except TaskFailed as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_REPORT_FAILED
    finally:
        service.close()
    print(message, file=sys.stderr)
    return EXIT_REPORT_OK


def _quiet_stdout() -> None:
    """After a failed write to stdout (a full disk), what its buffer still holds must not fail again at exit
    (Python would print "Exception ignored" and exit 120)."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())  # the buffered rest goes nowhere, quietly
        os.close(null)
    except (OSError, ValueError):
        pass


def _unwritable(out: object, folder_ok: bool = False) -> str:
    """Why a file cannot be created at ``out`` ('' when it can): tried with a real file in its folder,
    since permission bits say nothing of a read-only mount or of root. ``folder_ok``: ``out`` may be a folder
    (a CSV export)."""
    import tempfile
    from pathlib import Path

    path = Path(str(out))
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir() and not folder_ok:
        return "it is a folder"
    if not folder.is_dir():
        return f"the folder {folder} does not exist"
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".linarmpp-probe-"):
            pass
    except OSError as exc:
        return f"the folder {folder} is not writable ({exc.strerror or exc})"
    if path.exists() and not os.access(path, os.W_OK):
        return "the file is read-only"
    return ""


def _exit_now(code: int) -> None:
    """A process told to end by a signal ends now (issue #25: within 2 s), once its logs are written."""
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def _install_desktop_entry() -> int:
    from app.desktop_entry import install_desktop_entry

    if sys.platform in ("win32", "darwin"):
        _report_error("--install-desktop-entry is for Linux desktops (freedesktop.org menus)")
        return 2
    try:
        written = install_desktop_entry()
    except OSError as exc:
        _report_error(f"The desktop entry was not installed: {exc}")
        return 1
    print("Installed (remove these files to undo):\n  " + "\n  ".join(str(p) for p in written))
    return 0


def console_main() -> int:
    """``linarmpp``: the console script."""
    return main(prog="linarmpp")


def gui_main() -> int:
    """``linarmpp-gui``: started without a console (Windows ``pythonw``), where there is no stdout or
    stderr; output goes to the log file and a refused configuration is shown in a message box."""
    global _no_console
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w", encoding="utf-8"))  # open for the life of the process
            _no_console = True
    return main(prog="linarmpp-gui")


_no_console = False  # errors cannot be printed where anyone sees them: show them in a message box too


def _report_error(text: str, window: bool = False) -> None:
    print(text, file=sys.stderr)
    if _no_console or window:
        from PySide6.QtWidgets import QApplication, QMessageBox

        _app = QApplication.instance() or QApplication(sys.argv)
        QMessageBox.critical(None, "LINarm++ Manager", text)
