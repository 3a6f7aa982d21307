"""Session summary: what an exercise (or a whole session) did — a table of repetitions, plots of the metrics
across the repetitions, the alarms and interruptions. Shown at the end of an exercise and from the sessions
browser; "Save PDF…" writes the printable report (app/reports.py)."""

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
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.metrics import metrics_of_session
from app.reports import REPETITION_COLUMNS, fmt, y_range

log = logging.getLogger(__name__)

# (title, [(key, name)], unit) — the plots across repetitions
SUMMARY_PLOTS: tuple[tuple[str, tuple[tuple[str, str], ...], str], ...] = (
    ("Peak speed", (("peak_speed_m_s", "peak"), ("mean_speed_m_s", "mean")), "m/s"),
    ("Smoothness (SPARC)", (("sparc", "SPARC"),), ""),
    ("Range of motion", (("range_m", "range"),), "m"),
    ("Interaction force", (("peak_force_n", "peak"), ("mean_force_n", "mean")), "N"),
)
PLOT_PENS = ("#1f77b4", "#d62728")


class SessionSummary(QWidget):
    """The summary of ``metrics`` (app.metrics.metrics_of_session's result)."""

    def __init__(self, metrics: dict[str, Any], title: str = "", folder: Path | None = None,
                 parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.metrics = metrics
        self.folder = folder
        reps = metrics["repetitions"]
        summary = metrics["summary"]

        self.header = QLabel()
        self.header.setWordWrap(True)
        self.header.setTextFormat(Qt.TextFormat.RichText)
        how = "marked by the exercise" if summary.get("source") == "marks" else "found from the handle's speed"
        line = (f"<b>{summary.get('repetitions', 0)}</b> repetitions ({summary.get('completed', 0)} completed, "
                f"{how})")
        for key, label, unit in (("peak_speed_m_s", "peak speed", "m/s"), ("range_m", "range", "m"),
                                 ("sparc", "SPARC", "")):
            entry = summary.get(key)
            if isinstance(entry, dict):
                line += f" · mean {label} <b>{fmt(entry['mean'])}</b> {unit}"
        self.header.setText((f"<h3>{title}</h3>" if title else "") + line)

        self.table = QTableWidget(len(reps), len(REPETITION_COLUMNS))
        self.table.setHorizontalHeaderLabels([h for _, h, _ in REPETITION_COLUMNS])
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().setVisible(False)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
        self.table.setAccessibleName("Repetitions")
        for row, r in enumerate(reps):
            for col, (key, _, spec) in enumerate(REPETITION_COLUMNS):
                item = QTableWidgetItem(fmt(r.get(key), spec))
                item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                if key == "completed" and not r.get("completed"):
                    item.setForeground(pg.mkColor("#c62828"))
                self.table.setItem(row, col, item)

        self.plots: dict[str, pg.PlotWidget] = {}
        grid = QGridLayout()
        x = [r["index"] for r in reps]
        for k, (title_, keys, unit) in enumerate(SUMMARY_PLOTS):
            plot = pg.PlotWidget(title=title_ + (f" [{unit}]" if unit else ""))
            plot.setBackground("w")
            plot.showGrid(x=True, y=True, alpha=0.3)
            plot.setLabel("bottom", "repetition")
            plot.setMinimumHeight(150)
            if len(keys) > 1:
                plot.addLegend(offset=(-5, 5))
            values: list[float] = []
            for j, (key, name) in enumerate(keys):
                ys = [r.get(key) for r in reps]
                pts = [(a, b) for a, b in zip(x, ys, strict=True) if b is not None]
                if pts:
                    values += [b for _, b in pts]
                    plot.plot([a for a, _ in pts], [b for _, b in pts], name=name,
                              pen=pg.mkPen(PLOT_PENS[j % 2], width=2), symbol="o", symbolSize=6,
                              symbolBrush=PLOT_PENS[j % 2])
            if values:
                plot.setYRange(*y_range(values), padding=0)
            self.plots[title_] = plot
            grid.addWidget(plot, k // 2, k % 2)

        alarms = metrics.get("alarms") or []
        self.alarms = QTableWidget(len(alarms), 3)
        self.alarms.setHorizontalHeaderLabels(["Time s", "Event", "Details"])
        self.alarms.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.alarms.verticalHeader().setVisible(False)
        self.alarms.horizontalHeader().setSectionResizeMode(2, QHeaderView.ResizeMode.Stretch)
        self.alarms.setAccessibleName("Alarms and interruptions")
        for row, a in enumerate(alarms):
            data = a.get("data") or {}
            details = data.get("text") or data.get("reason") or ", ".join(f"{k}: {v}" for k, v in data.items())
            for col, text in enumerate((f"{a['t_s']:.1f}", a["kind"], str(details))):
                self.alarms.setItem(row, col, QTableWidgetItem(text))
        self.alarms.setMaximumHeight(60 + 24 * min(len(alarms), 4))
        alarms_label = QLabel(f"<b>Alarms and interruptions</b>: {len(alarms) or 'none'}")

        self.pdf_button = QPushButton("Save PDF &report…")
        self.pdf_button.setEnabled(folder is not None)
        self.pdf_button.clicked.connect(self.ask_pdf)
        self.status = QLabel("")
        buttons = QHBoxLayout()
        buttons.addWidget(self.status, 1)
        buttons.addWidget(self.pdf_button)

        lay = QVBoxLayout(self)
        lay.addWidget(self.header)
        lay.addWidget(self.table, 2)
        lay.addLayout(grid, 3)
        lay.addWidget(alarms_label)
        lay.addWidget(self.alarms)
        lay.addLayout(buttons)

    def ask_pdf(self) -> None:
        if self.folder is None:
            return
        default = Path.home() / f"{self.folder.parent.name}_{self.folder.name}.pdf"
        path, _ = QFileDialog.getSaveFileName(self, "Save session report", str(default), "PDF files (*.pdf)")
        if path:
            self.save_pdf(Path(path))

    def save_pdf(self, path: Path) -> bool:
        from app.reports import write_session_report

        try:
            pages = write_session_report(self.folder, path)  # type: ignore[arg-type]
        except Exception as exc:  # a full disk, a folder not writable: say so, the summary stays
            log.exception("session report failed")
            self.status.setText(f"Report not written: {exc}")
            return False
        self.status.setText(f"Report written: {path} ({pages} pages)")
        return True


class SessionSummaryDialog(QDialog):
    """A session's (or one exercise's) summary in its own window."""

    def __init__(self, folder: Path, since_mono: float | None = None, until_mono: float | None = None,
                 title: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        from app.recording import load_session

        session = load_session(folder)
        metrics = metrics_of_session(session, since_mono, until_mono)
        patient = session.manifest.get("patient_id", folder.parent.name)
        self.setWindowTitle(f"Summary — {patient} — {folder.name}")
        self.summary = SessionSummary(metrics, title or f"Session {folder.name} — {patient}", folder, self)
        close = QPushButton("&Close")
        close.clicked.connect(self.accept)
        lay = QVBoxLayout(self)
        lay.addWidget(self.summary, 1)
        row = QHBoxLayout()
        row.addStretch(1)
        row.addWidget(close)
        lay.addLayout(row)
        self.resize(900, 760)
