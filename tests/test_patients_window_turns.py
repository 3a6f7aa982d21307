"""The Patients window never holds the GUI thread (issues #37, #39): with a few hundred patients in the archive,
opening the window while a timer measures the GUI thread's turns gives no turn above a functional bound. The GUI
watch (app/gui_watch.py) warns at 0.35 s and stops a running therapy at 0.7 s; each record read and validated on
the GUI thread costs ~5-15 ms, so the list read there held the thread for seconds.

The archive is SQLite, filled fast for the test: every record through the store's own API in one transaction
(``SqlArchive.import_profiles``; without it, the same through ``save_patient``, one transaction each).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import pytest
from PySide6.QtCore import QTimer

from app.archive import station
from app.archive.store import open_archive
from app.core.config import AppConfig
from app.gui_watch import ALARM_AFTER_S
from tests.archive_data import full_profile

SAFETY = AppConfig().safety
PATIENTS = 200
# Functional: under the GUI watch's warning (0.35 s), an order of magnitude inside the failure (3.1 s in one turn
# for 200 patients). The loader thread shares the interpreter lock with the window: at load 2-5 its longest turn
# was 90-183 ms (150 ms failed twice in the suite's company); the figures belong to the note, not to this bound.
TURN_BOUND_S = 0.300


class TurnMeter:
    """A 1 ms timer on the GUI thread: the gap between two of its ticks is at least the longest turn between them."""

    def __init__(self) -> None:
        self.gaps: list[float] = []
        self.cpu: list[float] = []  # the GUI thread's own CPU time within each gap
        self.ends: list[float] = []  # when each gap ended (perf_counter)
        self._last = time.perf_counter()
        self._last_cpu = time.thread_time()
        self.timer = QTimer()
        self.timer.setInterval(1)
        self.timer.timeout.connect(self._tick)

    def _tick(self) -> None:
        now, cpu = time.perf_counter(), time.thread_time()
        self.gaps.append(now - self._last)
        self.cpu.append(cpu - self._last_cpu)
        self.ends.append(now)
        self._last, self._last_cpu = now, cpu

    def start(self) -> None:
        self._last, self._last_cpu = time.perf_counter(), time.thread_time()
        self.timer.start()

    def stop(self) -> None:
        """The turn still running (a window that held the thread until now) counts too."""
        if self.timer.isActive():
            self._tick()
        self.timer.stop()

    @property
    def longest(self) -> float:
        return max(self.gaps, default=0.0)

    @property
    def longest_cpu(self) -> float:
        return max(self.cpu, default=0.0)


def _fill(archive, n: int) -> None:  # type: ignore[no-untyped-def]
    profiles = [replace(full_profile(f"PZ-{k:04d}"), full_name=f"Patient {k}") for k in range(n)]
    if hasattr(archive, "import_profiles"):
        archive.import_profiles(profiles, operator="test")
    else:  # the code before it
        for p in profiles:
            archive.save_patient(p, expected_version=None, operator="test")


@pytest.mark.realtime  # the wall clock of a shared machine: one rerun
def test_opening_the_patients_window_never_holds_the_gui_thread(qtbot, tmp_path: Path) -> None:
    from app.ui.patients_window import PatientsDialog

    archive = open_archive(url=f"sqlite:///{tmp_path / 'archive.sqlite3'}", station="room-A")
    _fill(archive, PATIENTS)
    station.install(archive)
    meter = TurnMeter()
    try:
        meter.start()
        qtbot.wait(50)  # the meter's own pace first
        opened = time.perf_counter()
        dialog = PatientsDialog(SAFETY)
        qtbot.addWidget(dialog)
        dialog.show()
        qtbot.waitUntil(lambda: dialog.table.rowCount() == PATIENTS and getattr(dialog, "loaded", True),
                        timeout=120_000)
        listed_s = time.perf_counter() - opened
        meter.stop()
        assert dialog.table.item(0, 0).text() == "PZ-0000"
        assert dialog.table.item(PATIENTS - 1, 1).text() == f"Patient {PATIENTS - 1}"
        assert dialog.selected_id() == "PZ-0000"
        longest = meter.longest
        gaps = sorted(meter.gaps)
        print(f"\n{PATIENTS} patients listed in {listed_s:.2f} s; GUI thread turns: {len(gaps)} ticks, "
              f"median {gaps[len(gaps) // 2] * 1000:.1f} ms, p99 {gaps[int(len(gaps) * 0.99)] * 1000:.1f} ms, "
              f"longest {longest * 1000:.1f} ms (its own CPU at most {meter.longest_cpu * 1000:.1f} ms); "
              "above 50 ms (ms after opening: length): "
              + ", ".join(f"{(e - g - opened) * 1000:.0f}: {g * 1000:.0f}"
                          for g, e in zip(meter.gaps, meter.ends, strict=True) if g > 0.05))
        # The GUI thread's own work in a turn against the bound; the wall clock's turn (its own work, the loader's
        # hold of the interpreter lock, and a loaded machine's waits: 304 ms once with two CPU hogs) against the
        # GUI watch's warning, which is what a clinician would see.
        assert meter.longest_cpu <= TURN_BOUND_S, (
            f"the GUI thread worked {meter.longest_cpu * 1000:.0f} ms in one turn while the Patients window listed "
            f"{PATIENTS} patients (bound {TURN_BOUND_S * 1000:.0f} ms)")
        assert longest < ALARM_AFTER_S, (
            f"the GUI thread was held {longest * 1000:.0f} ms in one turn while the Patients window listed "
            f"{PATIENTS} patients (the GUI watch warns at {ALARM_AFTER_S * 1000:.0f} ms)")
        # the search works on what is loaded, at once
        dialog.search.setText("patient 17")
        assert {dialog.table.item(r, 1).text() for r in range(dialog.table.rowCount())} == {
            f"Patient {k}" for k in range(PATIENTS) if "17" in f"PZ-{k:04d} Patient {k}"}  # id or name
        dialog.close()
    finally:
        meter.stop()
        station.uninstall()
        archive.close()


def test_loading_is_said_and_rows_come_in_blocks(qtbot, tmp_path: Path) -> None:
    """While the loader reads, the window says "Loading patients…" and shows the rows that came; an archive that
    cannot be read is one sentence."""
    from app.ui.patients_window import PatientsDialog

    archive = open_archive(url=f"sqlite:///{tmp_path / 'archive.sqlite3'}", station="room-A")
    _fill(archive, 60)
    station.install(archive)
    try:
        dialog = PatientsDialog(SAFETY)
        qtbot.addWidget(dialog)
        dialog.show()
        assert dialog.loading and "Loading patients" in dialog.loading_note.text()
        qtbot.waitUntil(lambda: 0 < dialog.table.rowCount() < 60 or dialog.loaded, timeout=30_000)
        seen_partial = 0 < dialog.table.rowCount() < 60
        qtbot.waitUntil(lambda: dialog.loaded, timeout=60_000)
        assert seen_partial, "the rows came all at once, not as they were read"
        assert not dialog.loading_note.isVisibleTo(dialog) and dialog.table.rowCount() == 60
        dialog.close()
    finally:
        station.uninstall()
        archive.close()
    station.install(None, "the archive at postgresql+psycopg://x@127.0.0.1:1/linarmpp cannot be reached (refused)")
    try:
        dialog = PatientsDialog(SAFETY)
        qtbot.addWidget(dialog)
        qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
        note = dialog.archive_note.text()
        assert dialog.archive_note.isVisibleTo(dialog) and "cannot be reached" in note and "\n" not in note
        assert dialog.table.rowCount() == 0 and not dialog.new_button.isEnabled()
        dialog.close()
    finally:
        station.uninstall()
