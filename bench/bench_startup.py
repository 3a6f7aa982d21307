"""Start-up: launch → window shown with every simulated device connected. Target ≤ 2 s.

    .venv/bin/python bench/bench_startup.py [--runs N]

Each run starts a fresh interpreter (t0 = time.monotonic_ns() in this process just before the spawn; the
monotonic clock is system-wide) that does what ``main.py`` does for the window (run_gui: QApplication,
palette, LinarmppManager(config).start(), MainWindow, show) with the default configuration (every device
simulated, the patient model and VR stand-in as helper processes), then reports when the window was first
exposed and when the last device connected. The figure is the later of the two.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

TIMEOUT_S = 30.0


def child() -> int:
    """The launched application: prints one JSON line of monotonic_ns stamps."""
    stamps: dict[str, int] = {}
    from PySide6.QtCore import QEvent, QObject, QTimer
    from PySide6.QtWidgets import QApplication

    stamps["imported_qt"] = time.monotonic_ns()
    from app.application import configure_qt_identity, install_safety_nets
    from app.core.config import load_config
    from app.manager import LinarmppManager
    from app.ui.main_window import MainWindow
    from app.ui.theme import apply_palette

    stamps["imported_app"] = time.monotonic_ns()
    app = QApplication.instance() or QApplication([sys.argv[0]])
    configure_qt_identity()
    config = load_config(None)
    apply_palette(app, config.ui.palette)
    manager = LinarmppManager(config)
    remove = install_safety_nets(manager)
    manager.start()
    stamps["devices_started"] = time.monotonic_ns()
    window = MainWindow(manager)

    class Exposed(QObject):
        def eventFilter(self, obj: QObject, event: QEvent) -> bool:
            if event.type() == QEvent.Type.Paint and "window_shown" not in stamps:
                stamps["window_shown"] = time.monotonic_ns()
            return False

    exposed = Exposed()
    window.installEventFilter(exposed)
    window.show()

    def check() -> None:
        if "all_connected" not in stamps and manager.all_connected():
            stamps["all_connected"] = time.monotonic_ns()
        if "all_connected" in stamps and "window_shown" in stamps:
            app.quit()

    timer = QTimer()
    timer.timeout.connect(check)
    timer.start(2)
    QTimer.singleShot(int(TIMEOUT_S * 1000), app.quit)
    app.exec()
    stamps["devices"] = len(manager.devices)  # type: ignore[assignment]
    print("STAMPS " + json.dumps(stamps), flush=True)
    window.close()
    manager.shutdown()
    remove()
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=5, help="launches (README figures: 20)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child()
    common.print_machine("start-up: launch → window shown, every simulated device connected")
    env = dict(os.environ, QT_QPA_PLATFORM=os.environ.get("QT_QPA_PLATFORM", "offscreen"))
    figures: dict[str, list[float]] = {}
    for _ in range(args.runs):
        t0 = time.monotonic_ns()
        proc = subprocess.run([sys.executable, __file__, "--child"], capture_output=True, text=True, env=env,
                              timeout=TIMEOUT_S + 15)
        line = next((x for x in proc.stdout.splitlines() if x.startswith("STAMPS ")), None)
        if line is None:
            print(f"  a launch reported nothing (exit {proc.returncode}): {proc.stderr[-800:]}")
            continue
        stamps = json.loads(line[len("STAMPS "):])
        for key in ("imported_qt", "imported_app", "devices_started", "window_shown", "all_connected"):
            if key in stamps:
                figures.setdefault(key, []).append((stamps[key] - t0) / 1e6)
        if "window_shown" in stamps and "all_connected" in stamps:
            figures.setdefault("ready", []).append((max(stamps["window_shown"], stamps["all_connected"]) - t0) / 1e6)
    print()
    names = {"imported_qt": "launch → PySide6 imported", "imported_app": "launch → application imported",
             "devices_started": "launch → devices started", "window_shown": "launch → window painted",
             "all_connected": "launch → every device connected",
             "ready": "launch → window shown AND every device connected"}
    for key, label in names.items():
        if key in figures:
            common.report(label, figures[key], 2000.0 if key == "ready" else None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
