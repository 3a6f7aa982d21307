"""Screenshots of the real window, with every device simulated and an exercise running.

    xvfb-run -a -s "-screen 0 1920x1080x24" .venv/bin/python tools/take_screenshots.py [--out docs/screenshots]

Starts a session, the seed's trigger exercise (Fig. 18) with the simulated patient squeezing every few
seconds, FES on the wrist-extension profile, and saves the window at 1366×768 and 1920×1080 once the
robot is moving: main-window*.png with the Script tab, and tab-<name>-<width>.png for every Commands tab.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("LINARMPP_HOME", tempfile.mkdtemp(prefix="linarmpp-shots-"))


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default=str(ROOT / "docs" / "screenshots"))
    parser.add_argument("--screen", action="store_true",
                        help="under a window manager: the whole screen, the window maximised then not, every tab "
                             "(<state>-tab-<name>-<screen width>.png); the screen's size is the display's")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    from app.application import configure_qt_identity, prepare_qt
    from app.core import streams

    prepare_qt()
    from PySide6.QtCore import QEventLoop, QTimer
    from PySide6.QtWidgets import QApplication

    app = QApplication(sys.argv)
    configure_qt_identity()
    from app.core.config import AppConfig
    from app.core.fes_profile import load_profile
    from app.manager import LinarmppManager
    from app.ui.main_window import MainWindow
    from app.ui.theme import apply_palette

    apply_palette(app, "light")
    manager = LinarmppManager(AppConfig())
    manager.start()
    window = MainWindow(manager)
    window.resize(1366, 768)
    window.show()

    def pump(seconds: float) -> None:
        loop = QEventLoop()
        QTimer.singleShot(int(seconds * 1000), loop.quit)
        loop.exec()

    deadline = time.monotonic() + 20
    while not manager.all_connected() and time.monotonic() < deadline:
        pump(0.2)
    manager.start_session("DEMO01", "screenshot")
    manager.sim_patient().squeeze_periodically(period=4.0, duty=0.3)
    fes = manager.driver("fes")
    fes.load_profile(load_profile(ROOT / "resources" / "fes_profiles" / "wrist_extension_time.yaml"))
    commands = window.frames["CommandsFrame"]
    for i in range(commands.tabs.count()):
        if commands.tabs.tabText(i) == "Script":
            commands.tabs.setCurrentIndex(i)
    console = commands.panels["ScriptConsole"]
    console.load_file(ROOT / "resources" / "scripts" / "trigger_exercise.py")
    console.start_script()
    runner = console.runner
    plots = window.frames["PlotsFrame"]
    plots.set_selected(["linarm.vsa.equilibriumPos", "linarm.vsa.handlePos", "physio.main.force",
                        "linarm.vsa.interactionForce", "fes.channels.current3", "fes.channels.pulseWidth3"])
    deadline = time.monotonic() + 40
    while time.monotonic() < deadline:
        vsa = manager.bus.latest(streams.LINARM_VSA)
        if vsa is not None and vsa.equilibriumPos > 0.2 and runner.running:
            break
        pump(0.2)
    try:
        fes.start_stimulation("screenshot")
    except Exception as exc:  # the screenshot is still useful without stimulation
        print("FES not started:", exc)
    pump(2.5)
    from PySide6.QtCore import Qt

    if args.screen:
        _screen_shots(app, window, commands, out, pump)
        runner.stop("screenshots taken", wait_s=2.0)
        window.close()
        manager.shutdown()
        return 0
    window.setWindowState(Qt.WindowState.WindowNoState)
    script_tab = commands.tabs.currentIndex()
    for width, height, name in ((1366, 768, "main-window.png"), (1920, 1080, "main-window-1920.png")):
        window.resize(width, height)
        window._reset_layout(short=height < 900)  # the first-run layout a screen of this size gets
        commands.tabs.setCurrentIndex(script_tab)
        pump(1.5)
        window.grab().save(str(out / name))
        print("saved", out / name, window.size().width(), "x", window.size().height())
        # Every Commands tab at this size (issue #19: each tab's primary controls on screen).
        for i in range(commands.tabs.count()):
            commands.tabs.setCurrentIndex(i)
            pump(0.8)
            slug = commands.tabs.tabText(i).lower().replace(" ", "-").replace("&", "")
            path = out / f"tab-{slug}-{width}.png"
            window.grab().save(str(path))
            print("saved", path)
    commands.tabs.setCurrentIndex(script_tab)
    # The graphs with six signals in six panes (issue #30: every ticked signal gets a readable pane; what
    # does not fit scrolls), at both sizes.
    plots.set_selected(["linarm.vsa.handlePos", "linarm.vsa.interactionForce", "physio.main.heartRate",
                        "fes.channels.current3", "fes.channels.pulseWidth3", "patient_model.main.alpha"])
    for width, height in ((1366, 768), (1920, 1080)):
        window.resize(width, height)
        window._reset_layout(short=height < 900)
        pump(1.5)
        window.grab().save(str(out / f"graphs-6-signals-{width}.png"))
        print("saved", out / f"graphs-6-signals-{width}.png")
    runner.stop("screenshots taken", wait_s=2.0)
    window.close()
    manager.shutdown()
    return 0


def _screen_shots(app: Any, window: Any, commands: Any, out: Path, pump: Any) -> None:
    """The whole screen as a person sees it (the window manager's frame included): maximised, then a normal
    window of 80 % of the screen, each Commands tab in turn."""
    from PySide6.QtCore import Qt

    screen = app.primaryScreen()
    width = screen.size().width()
    for state, tag in ((Qt.WindowState.WindowMaximized, "max"), (Qt.WindowState.WindowNoState, "normal")):
        window.setWindowState(state)
        if tag == "normal":
            window.resize(int(width * 0.8), int(screen.size().height() * 0.8))
        pump(1.5)
        for i in range(commands.tabs.count()):
            commands.tabs.setCurrentIndex(i)
            pump(0.8)
            slug = commands.tabs.tabText(i).lower().replace(" ", "-").replace("&", "")
            path = out / f"{tag}-tab-{slug}-{width}.png"
            screen.grabWindow(0).save(str(path))
            print("saved", path)


if __name__ == "__main__":
    sys.exit(main())
