"""Session summary: what each exercise run of a session (or of one exercise's end) did — per run a table of its
repetitions (numbered within the run), plots of the metrics across them, its alarms — so runs of different
exercises are never drawn as one line. Shown at the end of an exercise and from the sessions browser; "Save
PDF…" writes the printable report (app/session/reports.py), which reads the same
:func:`app.session.reports.run_reports`."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pyqtgraph as pg
from pyqtgraph.graphicsItems.ViewBox.ViewBoxMenu import ViewBoxMenu
from PySide6.QtCore import QSize, Qt, QTimer, Signal
from PySide6.QtWidgets import (
    QAbstractItemView,
    QDialog,
    QFileDialog,
    QFrame,
    QGridLayout,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QTableWidget,
    QTableWidgetItem,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from app.session.reports import (
    REPETITION_COLUMNS,
    SOURCE_TEXT,
    RunReport,
    alarm_text,
    fmt,
    parameters_text,
    y_range,
)
from app.ui.plots_frame import prepare_axis
from app.ui.staged import Steps
from app.ui.tasks import QtTasks

log = logging.getLogger(__name__)

# (title, [(key, name)], unit) — the plots across one run's repetitions
SUMMARY_PLOTS: tuple[tuple[str, tuple[tuple[str, str], ...], str], ...] = (
    ("Peak speed", (("peak_speed_m_s", "peak"), ("mean_speed_m_s", "mean")), "m/s"),
    ("Smoothness (SPARC)", (("sparc", "SPARC"),), ""),
    ("Range of motion", (("range_m", "range"),), "m"),
    ("Interaction force", (("peak_force_n", "peak"), ("mean_force_n", "mean")), "N"),
)
PLOT_PENS = ("#1f77b4", "#d62728")
_ROWS_PER_STEP = 25  # repetition-table rows filled per turn of the event loop (a staged summary: ~4 ms; 80 took 15)
_NUMBER_ALIGNMENT = Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter  # (once: an enum's | is slow)


class _LazyMenuViewBox(pg.ViewBox):
    """A plot's view whose context menu (pyqtgraph's: View All, the axes, Export) is built at its first right click,
    not with the plot: building it was ~8 ms of the turn that makes the plot (#37)."""

    def __init__(self) -> None:
        super().__init__(enableMenu=False)
        self.state["enableMenu"] = True  # offered, built when first asked for

    def getMenu(self, ev: Any) -> Any:
        if self.menu is None and self.menuEnabled():
            self.menu = ViewBoxMenu(self)
        return self.menu

    def getContextMenus(self, event: Any) -> Any:
        return self.getMenu(event).actions() if self.menuEnabled() else []


class _Cell(QWidget):
    """A plot's place in a run's grid: the same size whether the plot is in it yet or not (a staged summary adds the
    plots one by one: a placeholder then a plot changed every cell's size hint, and each plot added re-laid out and
    re-drew the plots before it, #37). Its one child fills it."""

    def __init__(self) -> None:
        super().__init__()
        self.setMinimumHeight(110)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.child: QWidget | None = None

    def sizeHint(self) -> QSize:
        return QSize(300, 200)

    def set_child(self, child: QWidget) -> None:
        child.setParent(self)
        child.setGeometry(self.rect())
        self.child = child
        if not self.isHidden():
            child.show()

    def resizeEvent(self, event: Any) -> None:
        super().resizeEvent(event)
        if self.child is not None:
            self.child.setGeometry(self.rect())


def _table(headers: Sequence[str], name: str) -> QTableWidget:
    table = QTableWidget(0, len(headers))
    table.setHorizontalHeaderLabels(list(headers))
    table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
    table.verticalHeader().setVisible(False)
    table.setAccessibleName(name)
    table.setWordWrap(True)
    return table


class RunSummary(QWidget):
    """One run: what ran, how it ended, its parameters, its repetitions and their plots, its alarms."""

    def __init__(self, report: RunReport, parent: QWidget | None = None, staged: bool = False,
                 start: bool = True) -> None:
        """``staged``: the repetition table is filled and the plots are built a piece per turn of the event loop
        (app.ui.staged): a block of rows, a plot's frame, its data (a plot cost ~40 ms and a run's table 20-40 ms;
        the four plots at once held the window 0.25 s, 0.7 s on a loaded PC: the GUI watch stopped the next
        exercise; one per posted call still made 60-190 ms turns, #37). ``complete()`` finishes at once. Staged
        and not ``start``: the pieces begin with ``start_build()`` (once the run's tab shows it)."""
        super().__init__(parent)
        self.report = report
        run, summary, reps = report.run, report.summary, report.repetitions
        self.header = QLabel()
        self.header.setWordWrap(True)
        self.header.setTextFormat(Qt.TextFormat.RichText)
        self.header.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        how = "marked by the exercise" if summary.get("source") == "marks" else "found from the handle's speed"
        counted = (f"<b>{len(reps)}</b> repetitions ({report.completed} completed, {how})" if reps
                   else f"<b>{report.reps_text()}</b>")
        for key, label, unit in (("peak_speed_m_s", "peak speed", "m/s"), ("range_m", "range", "m"),
                                 ("sparc", "SPARC", ""), ("reaction_time_s", "reaction time", "s")):
            entry = summary.get(key)
            if isinstance(entry, dict) and reps:
                counted += f" · mean {label} <b>{fmt(entry['mean'])}</b> {unit}"
        params = ", ".join(f"{label} {value}" for label, value in parameters_text(run)) or "—"
        origin = SOURCE_TEXT.get(run.source, run.source) + (f" by {run.operator}" if run.operator else "")
        restart = " · restart of an interrupted run" if run.restart_of else ""
        self.header.setText(f"<b>Run {report.number}: {report.title}</b> — from the {origin}{restart}<br>"
                            f"Ended: <b>{run.end_text()}</b><br>Parameters: {params}<br>{counted}")

        self.table = _table([h for _, h, _ in REPETITION_COLUMNS], f"Repetitions of run {report.number}")
        self.table.setRowCount(len(reps))
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
        staged = staged and bool(reps)

        self.plots: dict[str, pg.PlotWidget] = {}
        grid = QGridLayout()
        self._cells = [_Cell() for _ in SUMMARY_PLOTS]
        for k, cell in enumerate(self._cells):
            grid.addWidget(cell, k // 2, k % 2)
        self._steps: Steps | None = None
        if staged:
            self._pieces_left = self._pieces(reps)
            self._steps = Steps(self._pieces_left, self)
            if start:
                self._steps.start()
        else:
            self._fill_rows(0, len(reps))
            for k in range(len(SUMMARY_PLOTS)):
                self._add_plot(k)

        self.alarms = _alarm_table(report.alarms, f"Alarms and interruptions of run {report.number}")
        # up to six repetitions visible without scrolling; the plots take the rest
        row_h = self.table.verticalHeader().defaultSectionSize()
        self.table.setMinimumHeight(self.table.horizontalHeader().sizeHint().height() + row_h * min(6, len(reps))
                                    + 6)
        lay = QVBoxLayout(self)
        lay.addWidget(self.header)
        if reps:
            lay.addWidget(self.table, 2)
            lay.addLayout(grid, 3)
        else:  # nothing to tabulate or plot: say so instead of empty axes
            self.table.hide()
            for cell in self._cells:
                cell.hide()
            none = QLabel("No repetition in this run" + (": it ended before its first movement."
                                                          if report.interrupted else "."))
            none.setWordWrap(True)
            lay.addWidget(none)
            lay.addStretch(1)
        # The run's number of alarms as every view counts them (app/session/alarm_count.py); the list also has the
        # interruptions (a program's end, a data gap), which are not alarms.
        alarms = int(report.summary.get("alarms") or 0)
        lay.addWidget(QLabel(f"<b>Alarms of this run</b>: {alarms or 'none'}"
                             + (" — listed below with the interruptions" if report.alarms else "")))
        lay.addWidget(self.alarms)


    def start_build(self) -> None:
        """The staged pieces from the next turn of the event loop on (made with ``start=False``)."""
        if self._steps is not None:
            self._steps.start()

    @property
    def plots_built(self) -> bool:
        """Complete: every row in the table, every plot drawn with its data."""
        return self._steps is None or not self._steps.running

    def complete(self) -> None:
        """What is left of a staged build, now (a caller that reads the table or the plots)."""
        if self._steps is not None and self._steps.running:
            self._steps.stop()
            for _ in self._pieces_left:
                pass

    def _pieces(self, reps: Sequence[dict[str, Any]]) -> Iterator[None]:
        for start in range(0, len(reps), _ROWS_PER_STEP):
            self._fill_rows(start, min(len(reps), start + _ROWS_PER_STEP))
            yield
        # A plot a few pieces at a time (a pyqtgraph plot cost 20-25 ms to make, its paint 8-12 ms): its view and
        # axes, its frame, its widget -- not drawn until its data are in --, each curve, its ranges; drawn once.
        for k in range(len(SUMMARY_PLOTS)):
            parts = _plot_parts()
            yield
            bare = _bare_plot(*parts)  # pyqtgraph's plot (its options menu's widgets: ~half its cost)
            yield
            item = self._plot_item(k, *parts, bare=bare)
            yield
            plot = self._new_plot(k, item)
            plot.setUpdatesEnabled(False)
            yield
            yield from self._plot_data(k, plot, staged=True)
            # Its first paint comes with the scene's next update, a turn or two later: those turns carry no piece
            # (a plot's frame made in the turn of the previous plot's paint held the window 40-85 ms beside a
            # therapy).
            yield
            yield

    def _fill_rows(self, start: int, end: int) -> None:
        """Rows [start, end) of the repetition table."""
        reps = self.report.repetitions
        for row in range(start, end):
            r = reps[row]
            for col, (key, _, spec) in enumerate(REPETITION_COLUMNS):
                item = QTableWidgetItem(fmt(r.get(key), spec))
                item.setTextAlignment(_NUMBER_ALIGNMENT)
                if key == "completed" and not r.get("completed"):
                    item.setForeground(pg.mkColor("#c62828"))
                self.table.setItem(row, col, item)

    def _add_plot(self, k: int) -> None:
        """The ``k``-th of SUMMARY_PLOTS across the run's repetitions, in its place in the grid."""
        for _ in self._plot_data(k, self._new_plot(k, self._plot_item(k, *_plot_parts()))):
            pass

    def _plot_item(self, k: int, view: pg.ViewBox, axes: dict[str, pg.AxisItem],
                   bare: pg.PlotItem | None = None) -> pg.PlotItem:
        """The ``k``-th plot's frame (title, axes, grid, legend) on ``view`` and ``axes`` (_plot_parts), or on
        ``bare`` (_bare_plot of them)."""
        title_, keys, unit = SUMMARY_PLOTS[k]
        item = bare if bare is not None else _bare_plot(view, axes)
        item.setTitle(title_ + (f" [{unit}]" if unit else ""))
        item.showGrid(x=True, y=True, alpha=0.3)
        item.setLabel("bottom", f"repetition of run {self.report.number}")
        if len(keys) > 1:
            item.addLegend(offset=(-5, 5), colCount=len(keys))
        return item

    def _new_plot(self, k: int, item: pg.PlotItem) -> pg.PlotWidget:
        """The ``k``-th plot's widget around its frame ``item``, in its place in the grid; its data: _plot_data."""
        plot = pg.PlotWidget(plotItem=item, background="w")
        self.plots[SUMMARY_PLOTS[k][0]] = plot
        self._cells[k].set_child(plot)
        return plot

    def _plot_data(self, k: int, plot: pg.PlotWidget, staged: bool = False) -> Iterator[None]:
        """The ``k``-th plot's curves, a step each, then its ranges (``staged``: then its axes' pictures, a step of
        their own, and its first paint in the turn after)."""
        reps = self.report.repetitions
        _title, keys, _unit = SUMMARY_PLOTS[k]
        x = [r["index"] for r in reps]
        values: list[float] = []
        for j, (key, name) in enumerate(keys):
            pts = [(a, b) for a, b in zip(x, [r.get(key) for r in reps], strict=True) if b is not None]
            if pts:
                values += [b for _, b in pts]
                plot.plot([a for a, _ in pts], [b for _, b in pts], name=name,
                          pen=pg.mkPen(PLOT_PENS[j % 2], width=2), symbol="o", symbolSize=6,
                          symbolBrush=PLOT_PENS[j % 2])
                yield
        if values:
            plot.setYRange(*y_range(values), padding=0)
        if x:
            plot.getAxis("bottom").setTicks([[(i, str(i)) for i in x]] if len(x) <= 20 else None)
        if staged:
            yield
            plot.getPlotItem().vb.prepareForPaint()  # its range now (a pending autorange), then its axes for it
            for side in ("left", "bottom"):
                prepare_axis(plot.getAxis(side))
            yield  # drawn in a turn of its own (~5 ms: its symbols)
        plot.setUpdatesEnabled(True)  # drawn once, complete (staged)
        yield

    def showEvent(self, event: Any) -> None:
        super().showEvent(event)
        self.alarms.resizeRowsToContents()  # the columns have their final widths now: wrap the sentences in full


def _bare_plot(view: pg.ViewBox, axes: dict[str, pg.AxisItem]) -> pg.PlotItem:
    """pyqtgraph's PlotItem on ``view`` and ``axes``, before its title, grid and legend (_plot_item)."""
    return pg.PlotItem(viewBox=view, axisItems=axes)


def _plot_parts() -> tuple[pg.ViewBox, dict[str, pg.AxisItem]]:
    """A summary plot's view (its menu made at the first right click) and axes, made apart from its frame: the frame
    on parts made before costs half of one that makes them (#37)."""
    return _LazyMenuViewBox(), {side: pg.AxisItem(side) for side in ("left", "bottom")}  # (top, right: hidden)


def _alarm_table(alarms: Sequence[dict[str, Any]], name: str) -> QTableWidget:
    table = _table(["Time s", "Event", "Details"], name)
    table.setRowCount(len(alarms))
    table.horizontalHeader().setSectionResizeMode(2, QHeaderView.ResizeMode.Stretch)
    for row, a in enumerate(alarms):
        details = alarm_text(a.get("data") or {})
        for col, text in enumerate((f"{a['t_s']:.1f}", str(a["kind"]).replace("_", " "), details)):
            item = QTableWidgetItem(text)
            item.setToolTip(text)  # the whole sentence, however narrow the column
            table.setItem(row, col, item)
    table.resizeRowsToContents()
    # wrapped sentences need the row height of the column's final width
    table.horizontalHeader().sectionResized.connect(lambda *_a: table.resizeRowsToContents())
    table.setMaximumHeight(60 + 24 * min(len(alarms), 4))
    return table


class SessionSummary(QWidget):
    """The summary of ``runs`` (app.session.reports.run_reports): one tab per run, and an overview of the runs when
    there are several. ``staged``: a run's tab is built when it is first shown, on a turn of the event loop of its
    own (a run's plots and table cost ~120 ms on the reference machine: opening a long session's summary shows
    its overview at once and builds no run it does not show); ``ready`` once the tab shown is built."""

    ready = Signal()

    def __init__(self, runs: Sequence[RunReport], title: str = "", folder: Path | None = None,
                 parent: QWidget | None = None, tasks: QtTasks | None = None, staged: bool = False) -> None:
        super().__init__(parent)
        self._to_build: list[RunReport] = []
        self._made: dict[str, tuple[RunSummary, QScrollArea]] = {}  # a run's tab made, not in its place yet
        self.runs = list(runs)
        self.folder = folder
        self.tasks = tasks  # the worker process that draws the PDF (issue #37); None: drawn here
        self.header = QLabel((f"<h3>{title}</h3>" if title else "")
                             + (f"{len(self.runs)} exercise run(s)" if self.runs else "No exercise run."))
        self.header.setTextFormat(Qt.TextFormat.RichText)
        self.header.setWordWrap(True)
        self.run_views: dict[str, RunSummary] = {}
        self.tabs = QTabWidget()
        self.tabs.setAccessibleName("Runs")
        self.overview: QTableWidget | None = None
        if len(self.runs) > 1:
            self.overview = _table(["Run", "Exercise", "Repetitions", "Ended"], "Runs of the session")
            self.overview.setRowCount(len(self.runs))
            self.overview.horizontalHeader().setSectionResizeMode(1, QHeaderView.ResizeMode.Stretch)
            self.overview.horizontalHeader().setSectionResizeMode(3, QHeaderView.ResizeMode.Stretch)
            numbers = {r.run.run_id: r.number for r in self.runs}
            restarted_as = {r.run.restart_of: r.number for r in self.runs if r.run.restart_of}
            for row, r in enumerate(self.runs):
                ended = r.run.end_text()
                if r.run.restart_of:
                    ended += f"; restart of run {numbers.get(r.run.restart_of, '?')}"
                if r.run.run_id in restarted_as:
                    ended += f"; restarted as run {restarted_as[r.run.run_id]}"
                for col, text in enumerate((str(r.number), r.title, r.reps_text(), ended)):
                    item = QTableWidgetItem(text)
                    item.setToolTip(text)
                    self.overview.setItem(row, col, item)
            self.overview.resizeRowsToContents()
            self.overview.cellDoubleClicked.connect(lambda row, _col: self.tabs.setCurrentIndex(row + 1))
            self.tabs.addTab(self.overview, "All runs")
        for r in self.runs:
            if staged:
                view: QWidget = QLabel("…")  # this run's tab is built on a later turn (see _build_next)
                self._to_build.append(r)
            else:
                summary = RunSummary(r, self)
                self.run_views[r.run.run_id] = summary
                view = _scrolled(summary)
            self.tabs.addTab(view, f"{r.number}. {_short(r.title)}")
            self.tabs.setTabToolTip(self.tabs.count() - 1, f"Run {r.number}: {r.title} — {r.run.end_text()}")
        self.tabs.setCurrentIndex(0)  # several runs: their overview first
        if self._to_build:
            self.tabs.currentChanged.connect(lambda _i: QTimer.singleShot(0, self, self._build_shown))
            QTimer.singleShot(0, self, self._build_shown)
        self.tabs.tabBar().setVisible(len(self.runs) > 1)

        self.pdf_button = QPushButton("Save PDF &report…")
        self.pdf_button.setEnabled(folder is not None)
        self.pdf_button.clicked.connect(self.ask_pdf)
        self.status = QLabel("")
        self.status.setWordWrap(True)
        buttons = QHBoxLayout()
        buttons.addWidget(self.status, 1)
        buttons.addWidget(self.pdf_button)
        lay = QVBoxLayout(self)
        lay.addWidget(self.header)
        lay.addWidget(self.tabs, 1)
        lay.addLayout(buttons)

    @property
    def is_ready(self) -> bool:
        """The tab shown is built (a staged summary builds the others when they are shown)."""
        shown = self._run_at(self.tabs.currentIndex())
        view = self.run_views.get(shown.run.run_id) if shown is not None else None
        return not any(x is shown for x in self._to_build) and (view is None or view.plots_built)

    def _run_at(self, index: int) -> RunReport | None:
        k = index - (1 if self.overview is not None else 0)
        return self.runs[k] if 0 <= k < len(self.runs) else None

    def _build_shown(self) -> None:
        """The run's tab shown, in two turns of the event loop: its widgets made, then put in the tab (drawn and
        laid out) -- the two in one turn took ~15 ms, #37; then its pieces (RunSummary)."""
        r = self._run_at(self.tabs.currentIndex())
        if r is not None and any(x is r for x in self._to_build) and r.run.run_id not in self._made:
            summary = RunSummary(r, self, staged=True, start=False)
            self._made[r.run.run_id] = summary, _scrolled(summary)
            QTimer.singleShot(0, self, self._build_shown)
            return
        self._build(r)
        self.ready.emit()

    def _build(self, r: RunReport | None) -> None:
        """Build ``r``'s tab now if it is still a placeholder (when shown, or when a caller asks for it)."""
        if r is not None and any(x is r for x in self._to_build):
            index = next(k for k, x in enumerate(self.runs) if x is r) + (1 if self.overview is not None else 0)
            shown = self.tabs.currentIndex()
            self._to_build = [x for x in self._to_build if x is not r]
            made = self._made.pop(r.run.run_id, None)
            if made is None:
                summary = RunSummary(r, self, staged=True, start=False)
                made = summary, _scrolled(summary)
            summary, view = made
            self.run_views[r.run.run_id] = summary
            summary.start_build()
            placeholder = self.tabs.widget(index)
            self.tabs.blockSignals(True)  # the tab shown stays shown while it is swapped
            self.tabs.removeTab(index)
            self.tabs.insertTab(index, view, f"{r.number}. {_short(r.title)}")
            self.tabs.setTabToolTip(index, f"Run {r.number}: {r.title} — {r.run.end_text()}")
            self.tabs.setCurrentIndex(shown)
            self.tabs.blockSignals(False)
            placeholder.deleteLater()

    def _complete(self, r: RunReport) -> RunSummary:
        """``r``'s tab, built and complete now (a caller reads it)."""
        self._build(r)
        view = self.run_views[r.run.run_id]
        view.complete()
        return view

    @property
    def tables(self) -> dict[str, QTableWidget]:
        """Each run's repetition table, by run id (a tab not built yet is built now)."""
        return {r.run.run_id: self._complete(r).table for r in self.runs}

    @property
    def table(self) -> QTableWidget | None:
        """The last run's repetition table (the one an exercise's end shows)."""
        if not self.runs:
            return None
        return self._complete(self.runs[-1]).table

    @property
    def plots(self) -> dict[str, pg.PlotWidget]:
        """The last run's plots."""
        if not self.runs:
            return {}
        return self._complete(self.runs[-1]).plots

    @property
    def metrics(self) -> dict[str, Any]:
        """The metrics shown, in app.session.metrics.metrics_of_session's shape: one run's own, or for several runs
        their
        repetitions one after the other and the counts (never means pooled across different exercises)."""
        if len(self.runs) == 1:
            r = self.runs[0]
            return {"repetitions": r.repetitions, "summary": r.summary, "alarms": r.alarms}
        reps = [rep for r in self.runs for rep in r.repetitions]
        return {"repetitions": reps, "alarms": [a for r in self.runs for a in r.alarms],
                "summary": {"repetitions": len(reps), "completed": sum(1 for rep in reps if rep.get("completed")),
                            "runs": len(self.runs)}}

    def ask_pdf(self) -> None:
        if self.folder is None:
            return
        default = Path.home() / f"{self.folder.parent.name}_{self.folder.name}.pdf"
        path, _ = QFileDialog.getSaveFileName(self, "Save session report", str(default), "PDF files (*.pdf)")
        if path:
            if self.tasks is not None:
                self.save_pdf_in_worker(Path(path))
            else:
                self.save_pdf(Path(path))

    def save_pdf(self, path: Path) -> bool:
        """Draw and write the report here (verified before "written" is said)."""
        from app.core.outputs import OutputError
        from app.session.reports import save_session_report

        try:
            pages = save_session_report(self.folder, path)  # type: ignore[arg-type]
        except OutputError as exc:  # a full disk, a folder not writable: one sentence, the summary stays
            self.status.setText(str(exc))
            return False
        except Exception as exc:
            log.exception("session report failed")
            self.status.setText(f"The session report {path} was not written: {exc}")
            return False
        self.status.setText(f"Report written: {path} ({pages} pages)")
        return True

    def save_pdf_in_worker(self, path: Path) -> Any:
        """Draw and write the report in the worker process (a progress dialog, Cancel); the status line says how
        it ended. Returns the task."""
        assert self.tasks is not None and self.folder is not None

        def done(task: Any) -> None:
            if task.ok:
                self.status.setText(f"Report written: {path} ({task.result} pages)")
            else:
                self.status.setText(task.error if task.error else "The session report was not written.")

        self.status.setText(f"Writing the report to {path}…")
        return self.tasks.run("session_report", str(self.folder), str(path), title="Session report", parent=self,
                              outputs=(path,), on_done=done)


def _short(title: str, n: int = 28) -> str:
    return title if len(title) <= n else title[: n - 1] + "…"


def runs_between(reports: Sequence[RunReport], since_mono: float | None, until_mono: float | None
                 ) -> list[RunReport]:
    """The runs that started within [since, until] (one exercise's end: its run, and a restart of it)."""
    lo = -float("inf") if since_mono is None else since_mono - 0.5
    hi = float("inf") if until_mono is None else until_mono
    return [r for r in reports if lo <= r.run.started_mono <= hi]


class SessionSummaryDialog(QDialog):
    """A session's (or one exercise's) summary in its own window, run by run. ``data``: what the worker process
    read (app.worker.jobs.SummaryData: the sessions browser); without it the session is read here."""

    def __init__(self, folder: Path, since_mono: float | None = None, until_mono: float | None = None,
                 title: str = "", parent: QWidget | None = None, *, data: Any = None,
                 tasks: QtTasks | None = None, staged: bool = False) -> None:
        super().__init__(parent)
        if data is not None:
            reports, patient = data.runs, data.patient_id
        else:
            from app.session.recording import load_session
            from app.session.reports import run_reports

            session = load_session(folder)
            reports = run_reports(session)
            patient = session.manifest.get("patient_id", folder.parent.name)
        runs = runs_between(reports, since_mono, until_mono)
        self.setWindowTitle(f"Summary — {patient} — {folder.name}")
        self.summary = SessionSummary(runs, title or f"Session {folder.name} — {patient}", folder, self, tasks,
                                      staged)
        close = QPushButton("&Close")
        close.clicked.connect(self.accept)
        lay = QVBoxLayout(self)
        lay.addWidget(self.summary, 1)
        row = QHBoxLayout()
        row.addStretch(1)
        row.addWidget(close)
        lay.addLayout(row)
        self.fit_to_screen()

    # Room the window manager takes around a dialog (title bar and borders), kept free when sizing it.
    FRAME_ROOM = (16, 48)

    def fit_to_screen(self) -> None:
        """900×700, or less on a smaller screen: the whole dialog — its Close button too — on the screen the
        dialog opens on (1366×768: 740 px below the panel, the title bar above the dialog)."""
        screen = self.screen()
        area = screen.availableGeometry() if screen is not None else None
        width, height = 900, 700
        if area is not None:
            width = min(width, area.width() - self.FRAME_ROOM[0])
            height = min(height, area.height() - self.FRAME_ROOM[1])
            self.setMaximumSize(area.width() - self.FRAME_ROOM[0], area.height() - self.FRAME_ROOM[1])
        self.resize(width, height)


def _scrolled(view: QWidget) -> QScrollArea:
    """A run's summary scrolled within its tab: a run with many repetitions and alarms is taller than a 1366×768
    screen, and the window (its Close button) must stay on the screen (#36)."""
    scroll = QScrollArea()
    scroll.setWidgetResizable(True)
    scroll.setFrameShape(QFrame.Shape.NoFrame)
    scroll.setWidget(view)
    return scroll
