"""A session's end → the archive (issue #39): the window's outbox uploads it in the worker process, exactly once;
the status bar says what waits ("1 session waiting for the archive (…)") while the archive cannot be reached, and
nothing once it is back and the session is archived. And ``--headless``'s last line says the same.

The archive is SQLite in a folder of its own; "unreachable" is that folder gone (a file in its place, as a share
that is not mounted), "back" is the folder restored.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from app.archive import station
from app.archive.store import open_archive
from app.core.config import AppConfig, ArchiveConfig
from app.therapy.patients import PatientProfile
from tests.waits import WORKER_TASK_MS


def _archived(url: str) -> int:
    archive = open_archive(url=url, station="counter")
    try:
        return archive.count_sessions()
    finally:
        archive.close()


def test_a_session_is_archived_once_at_its_end_and_waits_while_the_archive_is_away(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.manager import LinarmppManager
    from app.ui.main_window import MainWindow
    from tests.fakes import counter_factory

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    share = tmp_path / "share"
    url = f"sqlite:///{share / 'archive.sqlite3'}"
    cfg = replace(AppConfig(), archive=ArchiveConfig(url=url), station="room-A")
    archive = open_archive(url=url, station="room-A")
    archive.save_patient(PatientProfile(patient_id="PZ-001", full_name="Anna Rossi"), expected_version=None,
                         operator="dr_rossi")
    station.install(archive)
    manager = LinarmppManager(cfg, factories={"alpha": counter_factory(tmp_path, "alpha")})
    manager.start()
    window = None
    try:
        window = MainWindow(manager)
        qtbot.addWidget(window)
        window.show()
        # 1. a session ends: archived, exactly once; nothing said in the status bar
        manager.start_session("PZ-001", "dr_verdi")
        qtbot.wait(300)
        manager.end_session()
        qtbot.waitUntil(lambda: _archived(url) == 1 and getattr(window, "_archive_task", None) is None,
                        timeout=WORKER_TASK_MS)  # the upload is a task of the worker process
        assert not window.archive_status.isVisible() and window.archive_status.text() == ""
        window.archive_pass(force=True)  # the 30 s timer's pass: nothing more
        qtbot.waitUntil(lambda: getattr(window, "_archive_task", None) is None, timeout=WORKER_TASK_MS)
        assert _archived(url) == 1
        # 2. the archive goes away during the next session: its end waits, and the status bar says so
        manager.start_session("PZ-001", "dr_verdi")
        away = tmp_path / "share-away"
        share.rename(away)
        share.write_text("not mounted\n", encoding="utf-8")
        qtbot.wait(300)
        manager.end_session()
        qtbot.waitUntil(lambda: "waiting for the archive" in window.archive_status.text(), timeout=WORKER_TASK_MS)
        text = window.archive_status.text()
        assert text.startswith("1 session waiting for the archive (") and "cannot be reached" in text, text
        assert window.archive_status.isVisible()
        # 3. the archive is back: the next pass uploads it, once
        share.unlink()
        away.rename(share)
        window.archive_pass(force=True)
        qtbot.waitUntil(lambda: window.archive_status.text() == "" and window._archive_task is None,
                        timeout=WORKER_TASK_MS)
        assert _archived(url) == 2
        window.archive_pass(force=True)
        qtbot.waitUntil(lambda: getattr(window, "_archive_task", None) is None, timeout=WORKER_TASK_MS)
        assert _archived(url) == 2 and not window.archive_status.isVisible()
    finally:
        if window is not None:
            window.close()
        manager.shutdown(timeout_s=1.0)
        station.uninstall()
        archive.close()


def test_headless_last_line_says_archived_or_waiting(tmp_path: Path, monkeypatch: Any) -> None:
    """The headless run's last line (app.scripting.headless._archive_line): archived, or waiting with why."""
    from app.scripting.headless import _archive_line
    from tests.archive_data import make_data_folder

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    make_data_folder(tmp_path / "data")
    root = tmp_path / "data" / "sessions"
    share = tmp_path / "share"
    share.write_text("not mounted\n", encoding="utf-8")
    url = f"sqlite:///{share / 'archive.sqlite3'}"
    cfg = replace(AppConfig(), archive=ArchiveConfig(url=url), station="room-A")
    station.install(None, "the archive cannot be reached (not mounted)")
    try:
        line = _archive_line(cfg, root)
        assert line.startswith("4 sessions waiting for the archive (") and "cannot be reached" in line, line
        share.unlink()
        assert _archive_line(cfg, root) == "Session archived."
        assert _archived(url) == 4
        assert _archive_line(cfg, root) == "Session archived." and _archived(url) == 4
    finally:
        station.uninstall()
