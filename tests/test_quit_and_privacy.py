"""Issue #17 points 4, 6 and 7: Quit from any window ends the app with devices safe, F12 works in every
top-level window; patient data is private (0700 folders, 0600 files); the e-stop reset names the
session's operator; the manifest's rates are the configured ones; headless publishes LSL outlets."""

from __future__ import annotations

import logging
import os
import stat
from dataclasses import replace
from pathlib import Path

import pytest
from PySide6.QtCore import QEvent, Qt
from PySide6.QtGui import QKeyEvent
from PySide6.QtWidgets import QApplication

from app.core.config import AppConfig
from app.manager import LinarmppManager
from tests.fakes import counter_factory


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture
def manager(tmp_path, qtbot):
    cfg = AppConfig()
    cfg = replace(cfg, ui=replace(cfg.ui, ask_session_on_start=False))
    m = LinarmppManager(cfg, factories={"physio": counter_factory(tmp_path, "physio")})
    m.start()
    qtbot.waitUntil(m.all_connected, timeout=10000)
    yield m
    m.shutdown()


def test_quit_from_the_sessions_window_ends_the_app_with_devices_safe(tmp_path, qtbot, manager, monkeypatch) -> None:
    from app.ui.main_window import MainWindow
    from app.ui.sessions_browser import SessionsBrowser

    safe: list[str] = []
    manager.supervisor.register_estop_action("probe", safe.append)
    quits: list[bool] = []
    monkeypatch.setattr(QApplication, "quit", staticmethod(lambda: quits.append(True)))
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    browser = SessionsBrowser(tmp_path / "sessions")
    qtbot.addWidget(browser)
    browser.show()
    # F12 in the Sessions window stops everything
    QApplication.sendEvent(browser, QKeyEvent(QEvent.Type.KeyPress, Qt.Key.Key_F12, Qt.KeyboardModifier.NoModifier))
    assert manager.supervisor.estop_latched
    manager.supervisor.reset_emergency_stop("tester")
    safe.clear()
    quit_action = next(a for a in window.findChildren(type(window.menuBar().actions()[0]))
                       if a.text().replace("&", "") == "Quit")
    assert quit_action.shortcutContext() == Qt.ShortcutContext.ApplicationShortcut  # Ctrl+Q from any window
    from PySide6.QtCore import QEventLoop, QTimer

    loop = QEventLoop()  # as in the running app: Quit is triggered from inside the event loop
    QTimer.singleShot(0, quit_action.trigger)
    QTimer.singleShot(0, loop.quit)
    loop.exec()
    assert not window.isVisible() and not browser.isVisible()
    assert quits and safe == ["main window closed"]


def test_the_estop_reset_names_the_sessions_operator(tmp_path, qtbot, manager, monkeypatch) -> None:
    from PySide6.QtWidgets import QMessageBox

    from app.ui.main_window import MainWindow

    monkeypatch.setattr(QMessageBox, "question", staticmethod(lambda *a, **k: QMessageBox.StandardButton.Yes))
    window = MainWindow(manager)
    qtbot.addWidget(window)
    manager.start_session("OPS01", "Dr Rossi", root=tmp_path / "sessions")
    events: list[tuple[str, dict]] = []
    manager.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    manager.supervisor.emergency_stop("test")
    window._reset_estop()
    assert ("emergency_stop_reset", {"operator": "Dr Rossi"}) in events
    manager.end_session()


def test_session_files_and_folders_are_private(tmp_path, qtbot, manager, monkeypatch) -> None:
    old = os.umask(0o022)  # a typical login umask: the app must not depend on it
    try:
        monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
        from app.core import paths

        assert mode(paths.data_dir()) == 0o700 and mode(paths.sessions_dir()) == 0o700
        folder = manager.start_session("PRIV01", "tester", root=paths.sessions_dir())
        manager.end_session()
        for p in [folder, folder.parent, folder / "streams"]:
            assert mode(p) == 0o700, p
        files = [p for p in folder.rglob("*") if p.is_file()]
        assert files and all(mode(p) == 0o600 for p in files), [(p.name, oct(mode(p))) for p in files]
        from app.core import logging_setup

        monkeypatch.setattr(logging_setup, "_configured", None)
        root = logging.getLogger()
        before = list(root.handlers)
        log_path = logging_setup.setup_logging(console=False)
        try:
            assert mode(log_path) == 0o600
        finally:
            for h in root.handlers[:]:
                if h not in before:
                    root.removeHandler(h)
                    h.close()
    finally:
        os.umask(old)


def test_manifest_rates_are_the_configured_ones(tmp_path) -> None:
    from app.devices.physio import PHYSIO_STREAM
    from app.session.recording import configured_rate_hz

    cfg = AppConfig()
    cfg = replace(cfg, devices=replace(cfg.devices, physio=replace(cfg.devices.physio, rate_hz=250.0)))
    assert configured_rate_hz(cfg, "physio", PHYSIO_STREAM) == 250.0


def test_fes_channels_declared_irregular_to_lsl() -> None:
    from app.devices.rehastim import FES_STREAM
    from app.session.lsl import lsl_rate_hz

    assert lsl_rate_hz(AppConfig(), "fes", FES_STREAM) == 0.0


def test_headless_with_recording_lsl_publishes_outlets(tmp_path, qtbot, monkeypatch) -> None:
    from app.devices import registry
    from app.scripting import headless
    from app.session import lsl

    started: list[object] = []

    class Bridge:
        def __init__(self, manager) -> None:
            self.outlets = {s.name: object() for h in manager.devices.values() for s in h.driver.streams}
            started.append(self)

        def marker(self, record) -> None:
            pass

        def stop(self) -> None:
            self.stopped = True

    monkeypatch.setattr(lsl, "start_lsl", lambda manager, force=False: Bridge(manager)
                        if manager.config.recording.lsl else None)
    monkeypatch.setattr(registry, "default_factories", lambda config: {"physio": counter_factory(tmp_path, "physio")})
    monkeypatch.setattr(headless, "_let_the_record_show_the_safe_state", lambda manager, app: None)
    script = tmp_path / "s.py"
    script.write_text("x = 1\n", encoding="utf-8")
    cfg = AppConfig()
    cfg = replace(cfg, recording=replace(cfg.recording, lsl=True))
    code = headless.run_headless(cfg, str(script), home_first=False, output=lambda s, t: None)
    # the run ended well, with one bridge whose outlets are the devices' streams (the counter's, named "physio")
    assert code == 0 and started and set(started[0].outlets) == {"counter.main"}, (code, started)
    assert started and started[0].outlets and getattr(started[0], "stopped", False)
