"""The progress of a patient treated on two stations names each session's station (issue #39): the progress view
(app/ui/progress_view.py: the browser's Progress… window) and the progress report (``--progress``) have a Station
column when the rows come from the clinic's archive; a station's own folders alone keep the old table.

Two stations of one SQLite archive (tests/test_archive_reads.py's clinic): Monday on room-A, Wednesday on room-B
(both archived), Friday on room-B still waiting in B's outbox."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from app.archive.reads import progress_rows as archive_rows
from app.session.reports import progress_rows
from tests.pdf_layout import pdf_text
from tests.test_archive_reads import PATIENT, Clinic, make_two_stations, progress_of

STATIONS = ["room-A", "room-B", "room-B (not archived yet)"]
DATES = ["2026-03-02 10:00", "2026-03-04 10:00", "2026-03-06 10:00"]


def two_stations(tmp_path: Path) -> Clinic:
    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    make_two_stations(clinic)
    return clinic


def table_cells(view: Any) -> tuple[list[str], list[list[str]]]:
    table = view.table
    headers = [table.horizontalHeaderItem(c).text() for c in range(table.columnCount())]
    cells = [[table.item(r, c).text() for c in range(table.columnCount())] for r in range(table.rowCount())]
    return headers, cells


def test_the_progress_view_names_the_station_of_each_session(qtbot: Any, tmp_path: Path) -> None:
    from app.ui.progress_view import ProgressView

    clinic = two_stations(tmp_path)
    with clinic.archive("room-B") as archive:
        rows = archive_rows(PATIENT, clinic.home("room-B") / "sessions", archive)
    view = ProgressView(PATIENT, rows)
    qtbot.addWidget(view)
    headers, cells = table_cells(view)
    assert "Station" in headers, f"the progress view has no Station column: {headers}"
    station, date = headers.index("Station"), headers.index("Date")
    assert [c[date] for c in cells] == DATES
    assert [c[station] for c in cells] == STATIONS
    # the rest of the row is where it was: the exercises and the repetitions of each session
    assert [c[headers.index("Reps")] for c in cells] == ["3", "4", "2"]
    assert all(c[headers.index("Exercises")].startswith("Trigger reaching") for c in cells)


def test_a_stations_own_folders_keep_the_table_without_a_station_column(qtbot: Any, tmp_path: Path) -> None:
    from app.ui.progress_view import ProgressView

    clinic = two_stations(tmp_path)
    rows = progress_rows(PATIENT, clinic.home("room-B") / "sessions")  # no archive: the folders alone
    view = ProgressView(PATIENT, rows)
    qtbot.addWidget(view)
    headers, cells = table_cells(view)
    assert headers == ["Date", "Exercises", "Reps", "Peak m/s", "SPARC", "Range m", "α"]
    assert [c[0] for c in cells] == DATES[1:]


def test_the_progress_report_puts_each_sessions_station_on_its_row(tmp_path: Path, monkeypatch: Any) -> None:
    """``--progress`` on room-B: each session's line of the Sessions table has its date and its station (not only
    the station names somewhere in the text)."""
    clinic = two_stations(tmp_path)
    code, rows, _text = progress_of(clinic, "room-B", monkeypatch, tmp_path)
    assert code == 0 and [r.station for r in rows] == STATIONS
    lines = pdf_text(tmp_path / "progress-room-B.pdf", layout=True).splitlines()
    for k, (date, station) in enumerate(zip(DATES, STATIONS, strict=True)):
        line = next((ln for ln in lines if ln.split()[:3] == [str(k + 1), *date.split()]), "")
        words = line.split()
        assert words, f"no row {k + 1} of {date} in the Sessions table"
        assert words[3] == station.split()[0], line  # the Station column, after the date
