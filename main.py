#!/usr/bin/env python3
"""LINarm++ Manager from a checkout (installed, the same command line is ``linarmpp``; see app/cli.py).
With no arguments: every device simulated, on its real wire protocol.

    python main.py [--config FILE]                 the clinician window
    python main.py --headless --script FILE [--duration S] [--record DIR] [--patient ID --operator NAME]
    python main.py --metrics SESSION_FOLDER|UUID     per-repetition metrics as JSON
    python main.py --report SESSION_FOLDER|UUID --out FILE.pdf
    python main.py --progress PATIENT_ID --out FILE.pdf
"""

from __future__ import annotations

import sys

from app.cli import build_parser, main, parse_args  # noqa: F401 - the one parser lives in app/cli.py

if __name__ == "__main__":
    sys.exit(main())
