"""The command line: ``linarmpp`` (installed), ``linarmpp-gui`` (Windows, no console) and ``python main.py``
all run :func:`main`. With no arguments: the clinician window, every device simulated.

    linarmpp [--config FILE]                                the clinician window
    linarmpp --headless --script FILE [--duration S] [--record DIR]
    linarmpp --version
    linarmpp --install-desktop-entry                       the application menu entry (Linux)
    linarmpp --metrics SESSION_FOLDER                      per-repetition metrics as JSON (docs/metrics.md)
    linarmpp --report SESSION_FOLDER --out FILE.pdf        the session's PDF report
    linarmpp --progress PATIENT_ID --out FILE.pdf          the patient's progress PDF
    linarmpp export --format bids|xdf|edf SESSION… --out DIR   sessions for research tools (docs/export.md)
                      (exit 0 done, 1 nothing written: why on stderr, 2 wrong arguments,
                       3 done from an incomplete session: what is missing on stderr)

SIGTERM, SIGINT (Ctrl-C) and SIGHUP end the window or a headless run the same way: the devices are brought to
a safe state at once (FES Stop, robot IDLE; app/signal_events.py), the session is closed, and the process
exits with 128 + the signal's number (143, 130, 129).

The parser is built in one place, :func:`build_parser`: a new option is one ``add_argument`` line there.
"""

from __future__ import annotations

import argparse
import os
import sys

from app import __version__


def build_parser(prog: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="LINarm++ Manager")
    parser.add_argument("--version", action="version", version=f"LINarm++ Manager {__version__}")
    parser.add_argument("--config", help="YAML configuration (defaults: every device simulated)")
    parser.add_argument("--headless", action="store_true", help="no window: run --script and exit")
    parser.add_argument("--script", help="exercise script to run (with --headless)")
    parser.add_argument("--duration", type=float, help="stop the script after this many seconds")
    parser.add_argument("--record", help="record the session into this folder")
    parser.add_argument("--screenshot", help="save the window to this PNG once every device is connected, then quit")
    parser.add_argument("--quit-after", type=float, help="close the window after this many seconds")
    parser.add_argument("--metrics", metavar="SESSION_FOLDER", help="print the session's per-repetition metrics (JSON)")
    parser.add_argument("--report", metavar="SESSION_FOLDER", help="write the session's PDF report to --out")
    parser.add_argument("--progress", metavar="PATIENT_ID", help="write the patient's progress PDF to --out")
    parser.add_argument("--out", metavar="FILE", help="output file of --report / --progress")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument("--install-desktop-entry", action="store_true",
                        help="add LINarm++ Manager to this user's application menu (Linux), then exit")
    return parser


def parse_args(argv: list[str], prog: str | None = None) -> argparse.Namespace:
    return build_parser(prog).parse_args(argv)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["export"]:
        return _export_command(argv[1:], prog)
    args = parse_args(argv, prog)
    from app.paths import set_private_umask

    set_private_umask()  # patient data: files 0600, folders 0700, whatever the login's umask (issue #17)
    if args.install_desktop_entry:
        return _install_desktop_entry()
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") and sys.platform.startswith("linux"):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import logging

    from app.config import ConfigError, load_config
    from app.logging_setup import setup_logging

    setup_logging(logging.DEBUG if args.verbose else logging.INFO)
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        # Headless: exit 2 and the message; the window: also a dialog naming the file and line.
        _report_error(f"Configuration refused, nothing was started:\n  {exc}",
                      window=not args.headless and os.environ.get("QT_QPA_PLATFORM") != "offscreen")
        return 2
    if args.metrics or args.report or args.progress:
        return _report_command(config, args)
    if args.headless:
        if not args.script:
            _report_error("--headless needs --script FILE")
            return 2
        from app.scripting.headless import run_headless

        code = run_headless(config, args.script, duration_s=args.duration, record_dir=args.record)
        if code > 128:  # ended by a signal, devices safe and session closed: no slow interpreter teardown
            _exit_now(code)
        return code
    from app.application import run_gui

    return run_gui(config, screenshot=args.screenshot, quit_after_s=args.quit_after)


EXIT_REPORT_OK, EXIT_REPORT_FAILED, EXIT_REPORT_USAGE, EXIT_REPORT_INCOMPLETE = 0, 1, 2, 3


def _report_command(config: object, args: argparse.Namespace) -> int:
    """``--metrics`` / ``--report`` / ``--progress``, with the answers a caller can act on (docs/sessions.md):
    0 done; 1 nothing written (the output cannot be written, the session cannot be read) with one line
    saying why; 2 wrong arguments; 3 done from what was recorded, but the session is incomplete, and
    stderr lists what is missing (a failed or crashed recording, samples or events the files lack)."""
    import logging
    from pathlib import Path

    from app.recording import MANIFEST_FILE, session_problems
    from app.reports import run_report_command

    if args.out and (args.report or args.progress):
        problem = _unwritable(Path(args.out))
        if problem:
            print(f"Cannot write {args.out}: {problem}; nothing was written", file=sys.stderr)
            return EXIT_REPORT_FAILED
    incomplete = False
    for folder in dict.fromkeys(f for f in (args.metrics, args.report) if f):
        if not (Path(folder) / MANIFEST_FILE).is_file():
            continue  # run_report_command says it is not a session folder (exit 2)
        problems = session_problems(folder)
        if problems:
            incomplete = True
            print(f"Incomplete session {folder}: the output covers only what was recorded.", file=sys.stderr)
            for line in problems:
                print(f"  - {line}", file=sys.stderr)
    try:
        code = run_report_command(config, metrics=args.metrics, report=args.report, progress=args.progress,
                                  out=args.out)
    except OSError as exc:
        where = exc.filename or args.out or args.metrics or args.report
        print(f"Cannot write {where}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_REPORT_FAILED
    except Exception as exc:  # a damaged session no reader expected: one line here, the traceback in the log
        logging.getLogger(__name__).exception("the report command failed")
        print(f"Cannot read the session {args.metrics or args.report or args.progress}: "
              f"{type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_REPORT_FAILED
    if code == EXIT_REPORT_OK and incomplete:
        return EXIT_REPORT_INCOMPLETE
    return code


def _export_command(argv: list[str], prog: str | None) -> int:
    """``linarmpp export --format bids|xdf|edf SESSION… --out DIR`` (issue #41; app/research_export/command.py)."""
    import logging

    from app.logging_setup import setup_logging
    from app.paths import set_private_umask
    from app.research_export.command import main as export_main

    set_private_umask()  # exports hold health data: files 0600, folders 0700
    try:
        setup_logging(logging.INFO, console=False)  # the terminal shows progress; details go to the log
    except OSError:
        pass  # no log folder: the export still runs and says what it did on the terminal
    return export_main(argv, prog=f"{prog or 'linarmpp'} export")


def _unwritable(out: object) -> str:
    """Why a file cannot be created at ``out`` ('' when it can): tried with a real file in its folder,
    since permission bits say nothing of a read-only mount or of root."""
    import tempfile
    from pathlib import Path

    path = Path(str(out))
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
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
