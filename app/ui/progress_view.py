"""Patient progress: the session metrics and the clinical scores across a patient's sessions, as trend plots
(pyqtgraph), so a therapist sees whether speed, smoothness and range improve and assistance falls.
"Save PDF…" writes the progress report (app/session/reports.py). From the sessions browser the sessions are read, and
the PDF
drawn, in the worker process (issue #37)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (
    QAbstractItemView,
    QDialog,
    QFileDialog,
    QGridLayout,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QProgressDialog,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.session.reports import SCORES, TREND_METRICS, ProgressRow, fmt, progress_rows, shows_stations, y_range
from app.ui.tasks import QtTasks

log = logging.getLogger(__name__)


class ProgressView(QWidget):
    """Trends of ``rows`` (app.session.reports.progress_rows: one per session, oldest first)."""

    def __init__(self, patient_id: str, rows: list[ProgressRow], profile: Any = None,
                 parent: QWidget | None = None, tasks: QtTasks | None = None) -> None:
        super().__init__(parent)
        self.patient_id, self.rows, self.profile = patient_id, rows, profile
        self.tasks = tasks  # the worker process that draws the PDF (issue #37); None: drawn here
        header = QLabel(f"<h3>Progress of {patient_id}</h3>{len(rows)} session(s)"
                        + (f", {rows[0].date} … {rows[-1].date}" if rows else ""))
        header.setTextFormat(Qt.TextFormat.RichText)

        # A patient treated on several stations (read from the clinic's archive): each session names its station,
        # as the progress report does (the same rule: app.session.reports.shows_stations).
        stations = shows_stations(rows)
        headers = ["Date", *(["Station"] if stations else []), "Exercises", "Reps", "Peak m/s", "SPARC", "Range m",
                   "α"]
        self.table = QTableWidget(len(rows), len(headers))
        self.table.setHorizontalHeaderLabels(headers)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().setVisible(False)
        self.table.horizontalHeader().setSectionResizeMode(headers.index("Exercises"),
                                                           QHeaderView.ResizeMode.Stretch)
        self.table.setAccessibleName("Sessions")
        for row, r in enumerate(rows):
            cells = (r.date, *([r.station or "—"] if stations else []), ", ".join(r.exercises) or "—",
                     fmt(r.summary.get("repetitions"), "{}"), fmt(r.value("peak_speed_m_s")), fmt(r.value("sparc")),
                     fmt(r.value("range_m")), fmt(r.value("mean_alpha")))
            for col, text in enumerate(cells):
                self.table.setItem(row, col, QTableWidgetItem(text))
        if stations:
            self.table.resizeColumnToContents(headers.index("Station"))
        self.table.setMaximumHeight(70 + 24 * min(len(rows), 5))

        self.plots: dict[str, pg.PlotWidget] = {}
        grid = QGridLayout()
        n = list(range(1, len(rows) + 1))
        dates = [(i, f"#{i} {rows[i - 1].date[5:]}") for i in n]
        specs = [(key, label, unit, [r.value(key) for r in rows]) for key, label, unit in TREND_METRICS]
        specs += [(key, label, "", [_num(r.scores.get(key)) for r in rows]) for key, label in SCORES]
        for key, label, unit, values in specs:
            pts = [(i, v) for i, v in zip(n, values, strict=True) if v is not None]
            if not pts:
                continue
            plot = pg.PlotWidget(title=label + (f" [{unit}]" if unit else ""))
            plot.setBackground("w")
            plot.showGrid(x=True, y=True, alpha=0.3)
            plot.setMinimumHeight(150)
            plot.getAxis("bottom").setTicks([dates if len(dates) <= 10 else dates[::max(1, len(dates) // 10)]])
            plot.plot([a for a, _ in pts], [b for _, b in pts], pen=pg.mkPen("#1f77b4", width=2), symbol="o",
                      symbolSize=7, symbolBrush="#1f77b4")
            plot.setYRange(*y_range([b for _, b in pts]), padding=0)  # noise-level changes do not fill the plot
            plot.setXRange(0.7, len(rows) + 0.3, padding=0)
            self.plots[key] = plot
            k = len(self.plots) - 1
            grid.addWidget(plot, k // 3, k % 3)
        if not self.plots:
            grid.addWidget(QLabel("No metrics yet: the patient has no recorded repetition."), 0, 0)

        self.pdf_button = QPushButton("Save progress &PDF…")
        self.pdf_button.setEnabled(bool(rows))
        self.pdf_button.clicked.connect(self.ask_pdf)
        self.status = QLabel("")
        buttons = QHBoxLayout()
        buttons.addWidget(self.status, 1)
        buttons.addWidget(self.pdf_button)
        lay = QVBoxLayout(self)
        lay.addWidget(header)
        lay.addWidget(self.table)
        lay.addLayout(grid, 1)
        lay.addLayout(buttons)

    def ask_pdf(self) -> None:
        default = Path.home() / f"{self.patient_id}_progress.pdf"
        path, _ = QFileDialog.getSaveFileName(self, "Save progress report", str(default), "PDF files (*.pdf)")
        if path:
            if self.tasks is not None:
                self.save_pdf_in_worker(Path(path))
            else:
                self.save_pdf(Path(path))

    def save_pdf(self, path: Path) -> bool:
        """Draw and write the report here (verified before "written" is said)."""
        from app.core.outputs import OutputError
        from app.session.reports import save_progress_report

        try:
            pages = save_progress_report(self.patient_id, path, self.rows, self.profile)
        except OutputError as exc:
            self.status.setText(str(exc))
            return False
        except Exception as exc:
            log.exception("progress report failed")
            self.status.setText(f"The progress report {path} was not written: {exc}")
            return False
        self.status.setText(f"Report written: {path} ({pages} pages)")
        return True

    def save_pdf_in_worker(self, path: Path) -> Any:
        """Draw and write the report in the worker process; the status line says how it ended. Returns the task."""
        assert self.tasks is not None

        def done(task: Any) -> None:
            if task.ok:
                self.status.setText(f"Report written: {path} ({task.result} pages)")
            else:
                self.status.setText(task.error if task.error else "The progress report was not written.")

        self.status.setText(f"Writing the report to {path}…")
        return self.tasks.run("progress_report", self.patient_id, str(path), rows=self.rows, profile=self.profile,
                              title="Progress report", parent=self, outputs=(path,), on_done=done)


def _rows(patient_id: str, root: Path | None, progress: Any) -> list[ProgressRow]:
    """Every station's sessions from the station's archive when one is open (app.archive.reads), else the folders'."""
    from app.archive import station
    from app.archive.api import ArchiveError
    from app.archive.reads import progress_rows as archive_rows

    try:
        return archive_rows(patient_id, root, station.current(), progress)
    except ArchiveError as exc:
        log.warning("progress of %s from the archive: %s; this station's sessions only", patient_id, exc)
        return progress_rows(patient_id, root, progress)


def _num(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


class ProgressDialog(QDialog):
    """A patient's progress in its own window; reading every session shows a cancellable progress bar."""

    def __init__(self, patient_id: str, root: Path | None = None, profile: Any = None,
                 parent: QWidget | None = None, *, rows: list[ProgressRow] | None = None,
                 tasks: QtTasks | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle(f"Progress — {patient_id}")
        if profile is None:
            from app.therapy.patients import PatientError, load_patient

            try:
                profile = load_patient(patient_id)
            except (PatientError, OSError):
                profile = None
        if rows is None:  # read here (a caller without the worker process: the sessions browser reads them there)
            wait = QProgressDialog(f"Reading the sessions of {patient_id}…", "", 0, 100, parent)
            wait.setCancelButton(None)
            wait.setMinimumDuration(400)
            rows = _rows(patient_id, root, lambda f: wait.setValue(int(f * 100)))
            wait.close()
        self.view = ProgressView(patient_id, rows, profile, self, tasks)
        close = QPushButton("&Close")
        close.clicked.connect(self.accept)
        lay = QVBoxLayout(self)
        lay.addWidget(self.view, 1)
        row = QHBoxLayout()
        row.addStretch(1)
        row.addWidget(close)
        lay.addLayout(row)
        self.resize(1000, 760)
