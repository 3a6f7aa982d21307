"""The sessions browser reads the archive (issue #39): on station room-B of a clinic sharing one archive it lists the
patient's sessions of every station with the station shown, this station's own not yet uploaded as "waiting for the
archive", each session once; the list is read off the GUI thread; a replay of a session recorded on room-A (no
folder of it on room-B) opens, its files copied from the archive in the worker process."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from app.archive import reads, station
from tests.test_archive_reads import PATIENT, Clinic, make_two_stations
from tests.waits import WORKER_TASK_MS


def test_the_sessions_browser_lists_every_stations_sessions_and_replays_one_from_another_station(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.ui.replay_window import ReplayWindow
    from app.ui.sessions_browser import COLUMNS, SessionsBrowser

    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    make_two_stations(clinic)  # Monday on room-A, Wednesday on room-B (archived), Friday on room-B (waiting)
    monkeypatch.setenv("LINARMPP_HOME", str(clinic.home("room-B")))
    listed_on: list[str] = []
    real = getattr(reads, "session_blocks", None)

    def spy(*args: Any, **kwargs: Any) -> Any:
        listed_on.append(threading.current_thread().name)
        return real(*args, **kwargs)  # type: ignore[misc]

    monkeypatch.setattr(reads, "session_blocks", spy, raising=False)
    archive = clinic.archive("room-B")
    station.install(archive)
    browser = None
    try:
        browser = SessionsBrowser(clinic.home("room-B") / "sessions")
        qtbot.addWidget(browser)
        browser.set_patient(PATIENT)
        qtbot.waitUntil(lambda: not getattr(browser, "loading", False) and browser.table.rowCount() > 0,
                        timeout=30_000)
        col = COLUMNS.index("Station") if "Station" in COLUMNS else 4
        rows = [(browser.table.item(r, 0).text()[:10], browser.table.item(r, col).text())
                for r in range(browser.table.rowCount())]
        assert rows == [("2026-03-06", "room-B (waiting for the archive)"), ("2026-03-04", "room-B"),
                        ("2026-03-02", "room-A")]
        assert listed_on and set(listed_on) == {"sessions-loader"}  # never on the GUI thread
        assert [browser.table.item(r, 3).text() for r in range(3)] == ["0", "0", "0"]  # alarms, from the archive
        assert [browser.table.item(r, 5).text() for r in range(3)] == ["complete"] * 3
        browser.table.selectRow(2)  # Monday, recorded on room-A: room-B has no folder of it
        assert browser.selected_folder() is None and browser.replay_button.isEnabled()
        with qtbot.waitSignal(browser.opened, timeout=WORKER_TASK_MS) as opened:
            assert browser.replay() is not None
        replay = opened.args[0]
        assert isinstance(replay, ReplayWindow)
        cache = browser._cache
        assert cache is not None and list(cache.glob(f"*/{PATIENT}/20260302-100000/manifest.json"))
        replay.close()
        # its summary (the run's metrics) and a CSV export: from the copy made once
        with qtbot.waitSignal(browser.opened, timeout=WORKER_TASK_MS) as opened:
            assert browser.open_summary() is not None
        assert [len(r.repetitions) for r in opened.args[0].summary.runs] == [3]
        opened.args[0].close()
        done: list[tuple[bool, str]] = []
        listed = browser.selected_session()
        assert listed is not None and listed.station == "room-A"
        browser.export(listed, "csv", tmp_path / "csv", on_done=lambda ok, message: done.append((ok, message)))
        qtbot.waitUntil(lambda: bool(done), timeout=WORKER_TASK_MS)
        assert done[0][0], done
        assert (tmp_path / "csv" / "manifest.json").is_file() and (tmp_path / "csv" / "events.csv").is_file()
        research: list[Any] = []  # a research export of this session and of one of room-B's own folders
        both = [listed, browser.summaries[1].folder]
        (tmp_path / "xdf").mkdir()
        assert browser.research_export(both, "xdf", tmp_path / "xdf", on_done=research.append) is not None
        qtbot.waitUntil(lambda: bool(research), timeout=WORKER_TASK_MS)
        assert research[0].ok, research[0].error
        assert len(list((tmp_path / "xdf").rglob("*.xdf"))) == 2
        assert len(list(cache.glob("*/.copied"))) == 1  # one copy, read four times
        browser.close()
        assert not cache.exists()  # the copies go with the browser
    finally:
        if browser is not None:
            browser.close()
        station.uninstall()
        archive.close()


def test_with_the_archive_unreachable_the_browser_lists_this_stations_sessions_as_waiting_and_says_why(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.ui.sessions_browser import COLUMNS, SessionsBrowser

    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    make_two_stations(clinic)
    monkeypatch.setenv("LINARMPP_HOME", str(clinic.home("room-B")))
    station.install(None, "the archive at sqlite:///share/archive.sqlite3 cannot be reached (not mounted)")
    try:
        browser = SessionsBrowser(clinic.home("room-B") / "sessions")
        qtbot.addWidget(browser)
        browser.set_patient(PATIENT)
        qtbot.waitUntil(lambda: not browser.loading and browser.table.rowCount() > 0, timeout=30_000)
        col = COLUMNS.index("Station")
        assert [browser.table.item(r, col).text() for r in range(browser.table.rowCount())] == \
            ["this station (waiting for the archive)", "this station"]  # room-B's folders (Wednesday's archived)
        assert browser.status.text().startswith("The archive at sqlite:///share/archive.sqlite3 cannot be reached "
                                                "(not mounted). Only this station's sessions are listed")
        browser.close()
    finally:
        station.uninstall()
