#!/usr/bin/env python3
"""LINarm++ Manager. With no arguments: every device simulated, on its real wire protocol.

    python main.py [--config FILE]                 the clinician window
    python main.py --headless --script FILE [--duration S] [--record DIR]
"""

from __future__ import annotations

import argparse
import os
import sys


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="main.py", description="LINarm++ Manager")
    parser.add_argument("--config", help="YAML configuration (defaults: every device simulated)")
    parser.add_argument("--headless", action="store_true", help="no window: run --script and exit")
    parser.add_argument("--script", help="exercise script to run (with --headless)")
    parser.add_argument("--duration", type=float, help="stop the script after this many seconds")
    parser.add_argument("--record", help="record the session into this folder")
    parser.add_argument("--screenshot", help="save the window to this PNG once every device is connected, then quit")
    parser.add_argument("--quit-after", type=float, help="close the window after this many seconds")
    parser.add_argument("--verbose", action="store_true")
    return parser.parse_args(argv)


def _show_config_error(text: str) -> None:
    """The window's form of exit 2: a dialog naming the file and line (nothing else starts)."""
    try:
        from PySide6.QtWidgets import QApplication, QMessageBox

        app = QApplication.instance() or QApplication(sys.argv[:1])
        QMessageBox.critical(None, "Configuration refused", f"Nothing was started.\n\n{text}")
        del app
    except Exception:
        pass  # no display: the message is on stderr


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    from app.paths import set_private_umask

    set_private_umask()  # patient data: files 0600, folders 0700, whatever the login's umask
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") and sys.platform.startswith("linux"):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import logging

    from app.config import ConfigError, load_config
    from app.logging_setup import setup_logging

    setup_logging(logging.DEBUG if args.verbose else logging.INFO)
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"Configuration refused, nothing was started:\n  {exc}", file=sys.stderr)
        if not args.headless and os.environ.get("QT_QPA_PLATFORM") != "offscreen":
            _show_config_error(str(exc))
        return 2
    if args.headless:
        if not args.script:
            print("--headless needs --script FILE", file=sys.stderr)
            return 2
        from app.scripting.headless import run_headless

        return run_headless(config, args.script, duration_s=args.duration, record_dir=args.record)
    from app.application import run_gui

    return run_gui(config, screenshot=args.screenshot, quit_after_s=args.quit_after)


if __name__ == "__main__":
    sys.exit(main())
