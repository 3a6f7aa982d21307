"""Sessions browser: a patient's sessions (date, duration, exercises, alarms); open, export, replay.

Opening a session (its details, summary, replay, the patient's progress) and exporting it run in the worker process
(app/worker, issue #37) behind a progress dialog with Cancel: the real-time process's interpreter never parses a
session, and a crash there (HDF5 on a full disk) is one sentence here. The window is built from the result.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import queue
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PySide6.QtCore import QStandardPaths, Qt, QTimer, Signal
from PySide6.QtGui import QCloseEvent, QColor, QKeySequence, QShortcut
from PySide6.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QComboBox,
    QDialog,
    QDialogButtonBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QMessageBox,
    QPlainTextEdit,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.archive import reads, station
from app.archive.api import ArchiveError
from app.archive.reads import STATUS_KINDS, STOP_LEVELS, ListedSession, SessionStatus, status_of
from app.core import paths
from app.session.recording import EVENTS_FILE, SessionSummary, load_session, read_events
from app.ui.tasks import QtTasks
from app.worker import Task, TaskService, TaskStatus
from app.worker.session_data import SessionOverview, overview_of

log = logging.getLogger(__name__)

COLUMNS = ("Date", "Duration", "Exercises", "Alarms", "Operator", "Status", "Station")
STATION_COLUMN = 6
FOLDER_ROLE = Qt.ItemDataRole.UserRole
SIZED_ON_ROWS = 100  # the columns fit the first rows' contents (the header's precision below)


def _date_text(iso: str) -> str:
    try:
        return _dt.datetime.fromisoformat(iso).strftime("%Y-%m-%d %H:%M")
    except ValueError:
        return iso or "?"


def _duration_text(seconds: float) -> str:
    m, s = divmod(round(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def session_status(summary: SessionSummary, active: Path | None = None) -> SessionStatus:
    """``in progress`` (the session being recorded now), ``interrupted`` (the app never ended it),
    else ``complete`` only when every exercise finished and no STOP alarm was raised -- otherwise
    what went wrong (app.archive.reads.status_of, which the archive's sessions are judged by too)."""
    if active is not None and summary.folder.resolve() == active.resolve():
        return reads.IN_PROGRESS
    events, _dropped = read_events(summary.folder / EVENTS_FILE) if summary.complete else ([], 0)
    return status_of(summary.complete, [e for e in events if e.get("kind") in STATUS_KINDS])


EXPORT_JOBS = {"hdf5": "export_hdf5", "csv": "export_csv"}


class ExportJob:
    """One export, run by the worker process; ``done``, ``ok``, ``message`` and ``fraction`` tell where it is.
    Without a service of its own it starts a worker for this export alone and ends it when done."""

    def __init__(self, folder: Path, kind: str, destination: Path, service: TaskService | None = None) -> None:
        if kind not in EXPORT_JOBS:
            raise ValueError(f"unknown export kind {kind!r}")
        self.folder, self.kind, self.destination = folder, kind, destination
        self.service = service
        self._own = service is None
        self.task: Task | None = None
        self._cancel_first = False

    def start(self, on_update: Callable[[Task], Any] | None = None) -> Task:
        if self.service is None:
            self.service = TaskService()

        def update(task: Task) -> None:
            if task.done and self._own and self.service is not None:
                self.service.close()
            if on_update is not None:
                on_update(task)

        self.task = self.service.submit(EXPORT_JOBS[self.kind], str(self.folder), str(self.destination),
                                        title=f"Export of {self.folder.name} to {self.kind.upper()}",
                                        outputs=(self.destination,), on_update=update)
        if self._cancel_first:
            self.task.cancel()
        return self.task

    def cancel(self) -> None:
        if self.task is None:
            self._cancel_first = True
        else:
            self.task.cancel()

    @property
    def fraction(self) -> float:
        return self.task.fraction if self.task is not None else 0.0

    @property
    def done(self) -> bool:
        return self.task is not None and self.task.done

    @property
    def ok(self) -> bool:
        return self.task is not None and self.task.ok

    @property
    def message(self) -> str:
        task = self.task
        if task is None or not task.done:
            return ""
        if task.status is TaskStatus.DONE:
            return str(task.result)
        if task.status is TaskStatus.CANCELLED:
            return "export cancelled"
        return task.error


RESEARCH_FORMATS = (  # (format, what the clinician reads in the list)
    ("bids", "BIDS dataset (MNE-Python, EEGLAB's bids-matlab)"),
    ("xdf", "XDF, one file per session (pyxdf, EEGLAB, MoBILAB)"),
    ("edf", "EDF+, one file per session (EDFbrowser, MNE-Python)"),
)


def documents_folder() -> Path:
    """The user's documents folder (where exports go by default), else the home folder."""
    docs = QStandardPaths.writableLocation(QStandardPaths.StandardLocation.DocumentsLocation)
    return Path(docs) if docs and Path(docs).is_dir() else Path.home()


class ResearchExportDialog(QDialog):
    """Export… for research tools: the format and the folder (docs/export.md says what goes where)."""

    def __init__(self, count: int, folder: Path, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Export for research")
        self.format_box = QComboBox()
        for fmt, text in RESEARCH_FORMATS:
            self.format_box.addItem(text, fmt)
        self.format_box.setAccessibleName("Format")
        self.folder_edit = QLineEdit(str(folder))
        self.folder_edit.setAccessibleName("Folder")
        browse = QPushButton("&Browse…")
        browse.clicked.connect(self._browse)
        self.names_box = QCheckBox("Write the patients' full &names (otherwise only their pseudonyms)")
        form = QFormLayout()
        format_label = QLabel("&Format")
        format_label.setBuddy(self.format_box)
        form.addRow(format_label, self.format_box)
        row = QHBoxLayout()
        row.addWidget(self.folder_edit, 1)
        row.addWidget(browse)
        folder_label = QLabel("F&older")
        folder_label.setBuddy(self.folder_edit)
        form.addRow(folder_label, row)
        form.addRow("", self.names_box)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.button(QDialogButtonBox.StandardButton.Ok).setText("&Export")
        buttons.accepted.connect(self._accept)
        buttons.rejected.connect(self.reject)
        self.problem = QLabel("")
        self.problem.setStyleSheet("color: #c62828;")
        layout = QVBoxLayout(self)
        layout.addWidget(QLabel(f"{count} session(s) selected. The files are written, read back and only then "
                                "put in the folder; a cancelled export leaves nothing."))
        layout.addLayout(form)
        layout.addWidget(self.problem)
        layout.addWidget(buttons)

    @property
    def fmt(self) -> str:
        return str(self.format_box.currentData())

    @property
    def folder(self) -> Path:
        return Path(self.folder_edit.text().strip()).expanduser()

    def _browse(self) -> None:
        path = QFileDialog.getExistingDirectory(self, "Export into this folder", self.folder_edit.text())
        if path:
            self.folder_edit.setText(path)

    def _accept(self) -> None:
        if not self.folder.is_dir():
            self.problem.setText(f"The folder {self.folder} does not exist.")
            return
        self.accept()


class SessionDetails(QDialog):
    """The manifest's essentials and every event of one session (read by the worker: a
    :class:`~app.worker.session_data.SessionOverview`; a folder is read here, for a caller without a worker)."""

    def __init__(self, folder: Path | SessionOverview, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        session = folder if isinstance(folder, SessionOverview) else overview_of(load_session(folder))
        folder = session.folder
        m = session.manifest
        self.setWindowTitle(f"Session {folder.name} — {m.get('patient_id', '?')}")
        lines = [
            f"Patient: {m.get('patient_id', '?')}    Operator: {m.get('operator', '?')}",
            f"Start: {(m.get('start') or {}).get('t_wall', '?')}    End: {(m.get('end') or {}).get('t_wall', '—')}",
            f"Duration: {_duration_text(session.duration_s)}    App version: {m.get('app_version', '?')}",
            "Streams: " + ", ".join(f"{n} ({count} samples)" for n, count in session.samples.items()),
        ]
        if m.get("note"):
            lines.append(f"Note: {m['note']}")
        if session.problems:
            lines.append("Problems: " + "; ".join(session.problems))
        header = QLabel("\n".join(lines))
        header.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        header.setWordWrap(True)  # a long stream list wraps instead of widening the dialog past the screen
        self.events = QTableWidget(len(session.events), 4)
        self.events.setHorizontalHeaderLabels(["Time", "Event", "Who", "Details"])
        self.events.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        for row, e in enumerate(session.events):
            cells = [str(e.get("t_wall", ""))[11:23], str(e.get("kind", "")), str(e.get("who", "")),
                     json.dumps(e.get("data", {}), ensure_ascii=False, default=str)]
            for col, text in enumerate(cells):
                item = QTableWidgetItem(text)
                if col == 3:
                    item.setToolTip(text)  # long details are elided in the cell
                self.events.setItem(row, col, item)
        events_header = self.events.horizontalHeader()
        for col in range(3):
            events_header.setSectionResizeMode(col, QHeaderView.ResizeMode.ResizeToContents)
        events_header.setSectionResizeMode(3, QHeaderView.ResizeMode.Stretch)
        scripts = [e for e in session.events if e.get("kind") == "script_start"]
        self.script_text = QPlainTextEdit("\n\n".join(f"# --- {e['data'].get('name', 'script')}\n"
                                                      f"{e['data'].get('text', '')}" for e in scripts))
        self.script_text.setReadOnly(True)
        self.script_text.setAccessibleName("Scripts run")
        layout = QVBoxLayout(self)
        layout.addWidget(header)
        layout.addWidget(self.events, 2)
        layout.addWidget(QLabel("Scripts run"))
        layout.addWidget(self.script_text, 1)
        close = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        close.rejected.connect(self.reject)
        layout.addWidget(close)
        self.resize(900, 600)


class SessionsBrowser(QWidget):
    """List, open, export and replay the sessions of one patient. The reading and writing run in the worker
    process (``tasks``: the main window's; without one the browser starts its own and ends it when it closes)."""

    opened = Signal(object)  # the window or dialog an action opened, once its data is read

    def __init__(self, root: Path | None = None, history_s: float = 30.0, parent: QWidget | None = None,
                 active: Callable[[], Path | None] | None = None, tasks: QtTasks | None = None) -> None:
        super().__init__(parent)
        self.root = root or paths.sessions_dir()
        self.active = active or (lambda: None)  # the folder being recorded now (shown "in progress")
        self.history_s = history_s
        self.tasks = tasks or QtTasks(parent=self)
        self._own_tasks = tasks is None
        if not self._own_tasks:
            self.tasks.warm()  # the window's worker: started now, so the first open does not wait for it
        self.setWindowTitle("Sessions")
        self.windows: list[QWidget] = []  # replay windows and dialogs kept alive
        self.jobs: list[ExportJob] = []
        self.summaries: list[ListedSession] = []  # the rows, in the table's order
        # The list is read off the GUI thread whenever an archive is in use (always, in the application): a
        # clinic's server may take a while, and the local folders' manifests and events are files too. The loader
        # thread's result comes back through a queue, taken by a timer on the GUI thread.
        self.loading = False
        self.problem = ""  # why the archive's sessions are not listed ('' when they are, or no archive is in use)
        self._generation = 0
        self._results: queue.SimpleQueue[tuple[int, Callable[[Any, str], None], Any, str, bool]] = queue.SimpleQueue()
        self._pending: list[ListedSession] = []  # listed, not yet in the table (put in a few each turn: _fill)
        self._listed = False  # the loader's last block came
        self._here = ""  # this station's name, for the Station column
        self._row_cost_s = 0.0004  # the GUI thread's CPU to put in one row, as last measured (_fill)
        self._said_at = 0.0  # when the status line last counted the rows listed
        self._loader: threading.Thread | None = None
        self._pump = QTimer(self)
        self._pump.setInterval(15)
        self._pump.timeout.connect(self._take)
        self._cache: Path | None = None  # archived sessions of other stations, copied here to be read (private)

        self.patient_box = QComboBox()
        self.patient_box.setAccessibleName("Patient")
        self.patient_box.currentIndexChanged.connect(lambda _i: self.refresh())
        refresh = QPushButton("&Refresh")
        refresh.clicked.connect(self.reload_patients)
        top = QHBoxLayout()
        top.addWidget(QLabel("Patient"))
        top.addWidget(self.patient_box, 1)
        top.addWidget(refresh)

        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(list(COLUMNS))
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        # Several sessions may be selected (Ctrl/Shift) for a research export; the other actions take the current one.
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.ExtendedSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        # Sized to the first rows' contents only: a patient's hundreds of sessions (every station's) would otherwise
        # be measured cell by cell at each fill (500 rows: 98 ms in one turn, 33 ms so; docs/archive.md).
        header.setResizeContentsPrecision(SIZED_ON_ROWS)
        header.setSectionResizeMode(2, QHeaderView.ResizeMode.Stretch)  # the exercises: elided, whole in the tooltip
        self.table.setAccessibleName("Sessions")
        self.table.itemSelectionChanged.connect(self._update_buttons)
        self.table.itemDoubleClicked.connect(lambda _it: self.replay())

        self.open_button = QPushButton("&Open…")
        self.open_button.clicked.connect(self.open_details)
        self.hdf5_button = QPushButton("Export &HDF5…")
        self.hdf5_button.clicked.connect(lambda: self.ask_export("hdf5"))
        self.csv_button = QPushButton("Export &CSV…")
        self.csv_button.clicked.connect(lambda: self.ask_export("csv"))
        self.research_button = QPushButton("Research e&xport…")  # BIDS, XDF, EDF+ (app/research_export)
        self.research_button.setToolTip("Export the selected sessions as a BIDS dataset, XDF or EDF+ files")
        self.research_button.clicked.connect(self.ask_research_export)
        self.research_tasks: list[Task] = []
        self.replay_button = QPushButton("&Replay")
        self.replay_button.clicked.connect(self.replay)
        self.summary_button = QPushButton("S&ummary…")  # metrics (app/ui/session_summary.py)
        self.summary_button.clicked.connect(self.open_summary)
        self.progress_button = QPushButton("Pro&gress…")  # the patient's trends (app/ui/progress_view.py)
        self.progress_button.clicked.connect(self.open_progress)
        self.status = QLabel("")
        # A sentence of its own under the buttons, wrapped: an export's answer names its folder and files, and on
        # the buttons' row it widened the window past the screen.
        self.status.setWordWrap(True)
        self.status.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        buttons = QHBoxLayout()
        for b in (self.open_button, self.hdf5_button, self.csv_button, self.research_button, self.replay_button,
                  self.summary_button, self.progress_button):
            buttons.addWidget(b)
        buttons.addStretch(1)
        # A window of its own needs its own way out (issue #30: only the title bar's cross closed it).
        self.close_button = QPushButton("&Close")
        self.close_button.clicked.connect(self.close)
        buttons.addWidget(self.close_button)
        QShortcut(QKeySequence(Qt.Key.Key_Escape), self, activated=self.close)

        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.table, 1)
        layout.addLayout(buttons)
        layout.addWidget(self.status)
        self.resize(980, 420)
        self.reload_patients()

    # ------------------------------------------------------------------ listing
    # The list is read in blocks (app.archive.reads.session_blocks: one page of the archive each) on the loader
    # thread, and the rows are put in the table a few at a time on the GUI thread, at most FILL_BUDGET_S of its CPU a
    # turn: a patient's newest sessions are listed at once and the thousands behind them follow without a long turn
    # (10 000 rows in one turn held the window ~0.7 s; 2 000, 145 ms: docs/archive.md).
    FILL_BUDGET_S = 0.004

    def _load(self, work: Callable[[Callable[..., None]], None]) -> None:
        """``work(post)`` reads; each ``post(done, result, problem, last=False)`` has ``done(result, problem)`` called
        on the GUI thread, in order. ``work`` runs on the loader thread when an archive is in use, here otherwise (a
        library use of the browser on a folder: the folders' files, as before the archive; the rows all put in
        before this returns). A newer load drops an older one's results."""
        self._generation += 1
        generation = self._generation
        self._pending.clear()
        self._listed = False
        if not station.in_use():
            work(lambda done, result, problem, last=False: done(result, problem))
            self._fill(None)
            self._listing_shown()
            return
        self.loading = True
        self._say("Loading sessions…")

        def post(done: Callable[[Any, str], None], result: Any, problem: str, last: bool = False) -> None:
            self._results.put((generation, done, result, problem, last))

        def run() -> None:
            try:
                work(post)
            except Exception as exc:  # never a traceback in the window: the list says it could not be read
                log.exception("listing the sessions failed")
                post(self._listing_begun, None, "")
                post(self._listing_done, None, f"The sessions could not be listed: {exc}", True)

        self._loader = threading.Thread(target=run, name="sessions-loader", daemon=True)
        self._loader.start()
        self._pump.start()

    def _take(self) -> None:
        """The loader's news, then rows into the table within the turn's budget; the pump stops when all are in."""
        while True:
            try:
                generation, done, result, problem, last = self._results.get_nowait()
            except queue.Empty:
                break
            if generation != self._generation:
                continue
            done(result, problem)
            if last:
                self._listed = True
        self._fill(self.FILL_BUDGET_S)
        if self._listed and not self._pending:
            self.loading = False
            self._pump.stop()
            self._listing_shown()
        elif self.summaries and time.monotonic() >= self._said_at + 0.5:
            # twice a second: a wrapped label's new text lays the window out again (~3 ms a turn)
            self._said_at = time.monotonic()
            self._say(f"Loading sessions… {self.table.rowCount()} listed so far")

    def _listing_blocks(self, pid: str | None, active: Path | None, post: Callable[..., None],
                        problem: str = "") -> None:
        """The patient's rows, block by block, to ``post`` (on any thread); the last post says why the archive's are
        missing ('' when they are not)."""
        post(self._listing_begun, None, "")
        if pid:
            in_use, archive = station.in_use(), station.current()
            if in_use and archive is None:
                problem = problem or station.unreachable()
            try:
                for block in reads.session_blocks(pid, self.root, archive, in_use, active):
                    post(self._listing_block, block, "")
            except ArchiveError as exc:  # what came from the archive goes: this station's folders alone, from the top
                problem = problem or str(exc)
                post(self._listing_begun, None, "")
                for block in reads.session_blocks(pid, self.root, None, True, active):
                    post(self._listing_block, block, "")
        post(self._listing_done, None, problem, True)

    def _patients(self) -> tuple[list[str], str]:
        archive, in_use = station.current(), station.in_use()
        try:
            return reads.patient_ids(self.root, archive, in_use), ""
        except ArchiveError as exc:
            return reads.patient_ids(self.root, None, in_use), str(exc)

    def reload_patients(self, select: str | None = None) -> None:
        """The patients (the archive's and this station's folders') and the sessions of ``select`` (or of the one
        selected now), read together off the GUI thread."""
        current = select or self.patient_box.currentData()
        active = self.active()

        def work(post: Callable[..., None]) -> None:
            ids, problem = self._patients()
            pid = current if current in ids else (ids[0] if ids else None)
            post(self._patients_loaded, (ids, pid), "")
            self._listing_blocks(pid, active, post, problem)

        self._load(work)

    def _patients_loaded(self, result: Any, _problem: str) -> None:
        ids, pid = result
        self.patient_box.blockSignals(True)
        self.patient_box.clear()
        for p in ids:
            self.patient_box.addItem(p, p)
        self.patient_box.setCurrentIndex(max(0, self.patient_box.findData(pid)) if pid else 0)
        self.patient_box.blockSignals(False)

    def set_patient(self, patient_id: str) -> None:
        self.reload_patients(patient_id)

    def refresh(self) -> None:
        """The selected patient's sessions, read again (off the GUI thread when an archive is in use)."""
        pid = self.patient_box.currentData()
        active = self.active()
        self._load(lambda post: self._listing_blocks(pid, active, post))

    def _listing_begun(self, _result: Any, _problem: str) -> None:
        self.summaries = []
        self._pending.clear()
        self.table.setRowCount(0)
        header = self.table.horizontalHeader()
        for col in range(self.table.columnCount()):  # sized again to the new list's first rows (_size_columns)
            if header.sectionResizeMode(col) == QHeaderView.ResizeMode.Interactive:
                header.setSectionResizeMode(col, QHeaderView.ResizeMode.ResizeToContents)
        self.table.setColumnHidden(STATION_COLUMN, not station.in_use())
        self._here = station.current().station if station.current() is not None else ""
        self._update_buttons()

    def _listing_block(self, rows: list[ListedSession], _problem: str) -> None:
        self.summaries.extend(rows)
        self._pending.extend(rows)

    def _listing_done(self, _result: Any, problem: str) -> None:
        self.problem = problem

    def _fill(self, budget_s: float | None) -> None:
        """Rows of ``_pending`` into the table, as many as ``budget_s`` of this thread's CPU takes by the last turn's
        cost a row (None: all), added in one step: each step of adding rows costs the view and its row header a
        walk of their own."""
        if not self._pending:
            return
        started = time.thread_time()
        table = self.table
        first = table.rowCount() == 0
        count = len(self._pending) if budget_s is None else max(10, int(budget_s / self._row_cost_s))
        batch, self._pending[:count] = self._pending[:count], []
        row = table.rowCount()
        table.setRowCount(row + len(batch))
        for k, s in enumerate(batch):
            self._set_row(row + k, s)
        self._row_cost_s = max(1e-5, (time.thread_time() - started) / len(batch))
        if first and table.rowCount():
            table.selectRow(0)
        if table.rowCount() >= SIZED_ON_ROWS or (not self._pending and (self._listed or budget_s is None)):
            self._size_columns()

    def _size_columns(self) -> None:
        """The columns sized once, to the first rows put in (SIZED_ON_ROWS), then kept: left to size themselves to
        their contents (ResizeToContents), Qt measured the rows again after every turn that added some (25-35 ms of
        the window's CPU a turn with 10 000 sessions coming)."""
        header = self.table.horizontalHeader()
        for col in range(self.table.columnCount()):
            if header.sectionResizeMode(col) == QHeaderView.ResizeMode.ResizeToContents:
                self.table.resizeColumnToContents(col)
                header.setSectionResizeMode(col, QHeaderView.ResizeMode.Interactive)

    def _set_row(self, row: int, s: ListedSession) -> None:
        """One row's cells, through the table's model: a QTableWidgetItem made in Python keeps a Python object per
        cell for the table's life (70 000 for 10 000 sessions), and the collector's full walks over them held the
        window 120-170 ms at a time; the model makes the items in C++ (``table.item`` still answers)."""
        exercises = ", ".join(s.exercises) if s.exercises else "—"
        cells = (_date_text(s.start), _duration_text(s.duration_s), exercises, str(s.alarms), s.operator,
                 s.status.text, s.station_text(self._here))
        model = self.table.model()
        key = str(s.folder) if s.folder is not None else s.uuid
        display, tooltip, foreground = (Qt.ItemDataRole.DisplayRole, Qt.ItemDataRole.ToolTipRole,
                                        Qt.ItemDataRole.ForegroundRole)
        for col, text in enumerate(cells):
            data: dict[Qt.ItemDataRole, Any] = {display: text, FOLDER_ROLE: key}
            if col == 2 and s.exercises:
                data[tooltip] = exercises  # a long list is elided in its cell
            if col == 5:
                data[tooltip] = s.status.tooltip
                if not s.status.ok:
                    data[foreground] = QColor("#c62828")
            if col == STATION_COLUMN:
                data[tooltip] = _where_words(s)
                if s.where in (reads.WAITING, reads.REFUSED):
                    data[foreground] = QColor("#8a5a00" if s.where == reads.WAITING else "#c62828")
            model.setItemData(model.index(row, col), data)

    def _listing_shown(self) -> None:
        """Every row is in: the status line says why the archive's are missing, if they are."""
        self._say("")
        problem = self.problem
        if problem:
            self._say(f"{problem[:1].upper()}{problem[1:].rstrip('.')}. Only this station's sessions are listed; "
                      "they wait for the archive.", error=True)
        self._update_buttons()

    def selected_session(self) -> ListedSession | None:
        row = self.table.currentRow()
        if row < 0 or row >= len(self.summaries):
            return None
        return self.summaries[row]

    def selected_sessions(self) -> list[ListedSession]:
        """The sessions selected (in the table's order)."""
        rows = sorted({i.row() for i in self.table.selectedIndexes()})
        return [self.summaries[r] for r in rows if 0 <= r < len(self.summaries)]

    def selected_folder(self) -> Path | None:
        """The selected session's folder on this station (None: none selected, or it is only in the archive)."""
        s = self.selected_session()
        return s.folder if s is not None else None

    def selected_folders(self) -> list[Path]:
        """The selected sessions' folders on this station (in the table's order)."""
        return [s.folder for s in self.selected_sessions() if s.folder is not None]

    def select_folder(self, folder: Path) -> None:
        for row, s in enumerate(self.summaries):
            if s.folder == folder:
                self.table.selectRow(row)
                return

    def _update_buttons(self) -> None:
        ok = self.selected_session() is not None
        for b in (self.open_button, self.hdf5_button, self.csv_button, self.replay_button, self.summary_button):
            b.setEnabled(ok)
        self.research_button.setEnabled(bool(self.selected_sessions()))
        self.progress_button.setEnabled(ok)

    # ------------------------------------------------------------------ actions
    def _open(self, kind: str, args: tuple[Any, ...], title: str, make: Callable[[Any], QWidget | None]) -> Task:
        """Read in the worker, then ``make(result)`` the window on the GUI thread (shown, kept, ``opened``); a
        failure is one sentence in the status line."""
        def done(task: Task) -> None:
            if task.status is TaskStatus.CANCELLED:
                self.status.setText(f"{title}: cancelled.")
                return
            if not task.ok:
                self._say(task.error, error=True)
                return
            widget = make(task.result)
            if widget is None:
                return
            self.windows.append(widget)
            widget.show()
            self.status.setText("")
            self.opened.emit(widget)

        return self.tasks.run(kind, *args, title=title, parent=self, on_done=done)

    def _say(self, text: str, error: bool = False) -> None:
        self.status.setText(text)
        self.status.setStyleSheet("color: #c62828;" if error else "")

    def _cache_dir(self) -> Path:
        """A private folder (0700) for the archived sessions of other stations copied to be read; removed when the
        browser closes."""
        if self._cache is None:
            self._cache = Path(tempfile.mkdtemp(prefix="linarmpp-archived-"))
        return self._cache

    def _archive_args(self) -> tuple[str, str, str] | None:
        archive = station.current()
        return reads.args_of(archive) if archive is not None else None

    def _read(self, listed: ListedSession, kind: str, title: str, make: Callable[[Any], QWidget | None],
              *args: Any, outputs: tuple[Any, ...] = (), on_done: Callable[[Task], Any] | None = None) -> Task | None:
        """The worker job ``kind`` on the session's folder: this station's, or the archive's copy made first (in
        the worker, with progress: a 30-minute session is tens of MB)."""
        if listed.folder is not None:
            job, job_args = kind, (str(listed.folder), *args)
        else:
            archive = self._archive_args()
            if archive is None:
                self._say(f"{(station.unreachable() or 'The archive is not open').rstrip('.')}: the session "
                          f"{listed.folder_name} recorded on {listed.station or 'another station'} cannot be read "
                          "now.", error=True)
                return None
            job, job_args = ARCHIVED_JOB, (kind, archive, [listed.uuid], str(self._cache_dir()), *args)
        if on_done is not None:
            return self.tasks.run(job, *job_args, title=title, parent=self, outputs=outputs, on_done=on_done)
        return self._open(job, job_args, title, make)

    def open_details(self) -> Task | None:
        s = self.selected_session()
        if s is None:
            return None
        return self._read(s, "session_overview", f"Reading session {_name(s)}",
                          lambda overview: SessionDetails(overview, self))

    def open_summary(self) -> Task | None:
        s = self.selected_session()
        if s is None:
            return None
        from app.ui.session_summary import SessionSummaryDialog

        return self._read(s, "session_summary", f"Summary of session {_name(s)}",
                          lambda data: SessionSummaryDialog(data.folder, data=data, tasks=self.tasks, parent=self,
                                                            staged=True))

    def open_progress(self) -> Task | None:
        pid = self.patient_box.currentData()
        if not pid:
            return None
        from app.ui.progress_view import ProgressDialog

        archive = self._archive_args()
        return self._open(PROGRESS_JOB, (pid, str(self.root), archive), f"Progress of {pid}",
                          lambda rows: ProgressDialog(pid, self.root, parent=self, rows=rows, tasks=self.tasks))

    def replay(self) -> Task | None:
        s = self.selected_session()
        if s is None:
            return None
        from app.ui.replay_window import ReplayWindow

        return self._read(s, "session_data", f"Replay of session {_name(s)}",
                          lambda data: ReplayWindow(data, self.history_s, staged=True))

    def ask_export(self, kind: str) -> None:
        listed = self.selected_session()
        if listed is None:
            return
        default = listed.folder_name.replace("/", "_")
        if kind == "hdf5":
            path, _ = QFileDialog.getSaveFileName(self, "Export session to HDF5", str(Path.home() / f"{default}.h5"),
                                                  "HDF5 files (*.h5 *.hdf5)")
        else:
            path = QFileDialog.getExistingDirectory(self, "Export session to CSV files (choose a folder)",
                                                    str(Path.home()))
            path = str(Path(path) / default) if path else ""
        if path:
            self.export(listed.folder if listed.folder is not None else listed, kind, Path(path))

    def export(self, folder: Path | ListedSession, kind: str, destination: Path,
               on_done: Callable[[bool, str], Any] | None = None) -> ExportJob | None:
        """Export in the worker with a progress dialog (Cancel); a failure is one message (the status line and a
        message box), and nothing is said written that was not verified. Returns the running job. ``folder``: a
        session folder, or a listed session (an archived one of another station: copied first, in the worker)."""
        listed = folder if isinstance(folder, ListedSession) else None
        folder = Path(listed.folder_name) if listed is not None else Path(folder)  # type: ignore[arg-type]
        job = ExportJob(folder, kind, destination, self.tasks.service)

        def done(task: Task) -> None:
            if job in self.jobs:
                self.jobs.remove(job)
            self._say(job.message, error=task.status is TaskStatus.FAILED)
            if task.status is TaskStatus.FAILED:
                self._export_not_written(job.message)
            if on_done is not None:
                on_done(job.ok, job.message)

        title = f"Export of {folder.name} to {kind.upper()}"
        if listed is not None:
            task = self._read(listed, EXPORT_JOBS[kind], title, lambda _r: None, str(destination),
                              outputs=(destination,), on_done=done)
            if task is None:
                return None
            job.task = task
        else:
            job.task = self.tasks.run(EXPORT_JOBS[kind], str(folder), str(destination), title=title, parent=self,
                                      outputs=(destination,), on_done=done)
        self.jobs.append(job)
        return job

    def _export_not_written(self, message: str) -> None:
        """The one sentence of a failed export, in a window-modal box too (the status line is easy to miss)."""
        box = QMessageBox(QMessageBox.Icon.Warning, "Export not written", message, QMessageBox.StandardButton.Ok, self)
        box.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        box.open()
        self.message_box = box

    def ask_research_export(self) -> ResearchExportDialog | None:
        """Export… → the format and the folder (the documents folder by default) → the export, in the worker."""
        folders: list[Path | ListedSession] = [s.folder if s.folder is not None else s
                                               for s in self.selected_sessions()]
        if not folders:
            return None
        dialog = ResearchExportDialog(len(folders), documents_folder(), self)
        dialog.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        dialog.accepted.connect(lambda: self.research_export(folders, dialog.fmt, dialog.folder,
                                                             include_names=dialog.names_box.isChecked()))
        dialog.open()
        self.export_dialog = dialog
        return dialog

    def research_export(self, folders: list[Path | ListedSession], fmt: str, destination: Path,
                        include_names: bool = False, on_done: Callable[[Task], Any] | None = None) -> Task | None:
        """Export ``folders`` as ``fmt`` into ``destination`` in the worker, with a progress dialog (Cancel). The
        files are made in a staging folder there and moved in only once all are written and read back: a cancel or
        a failure leaves nothing, and says so in one sentence."""
        from app.research_export.jobs import JOB_KIND, new_stamp, staging_target

        stamp = new_stamp()
        what = dict(RESEARCH_FORMATS)[fmt].split(" (")[0]
        title = f"Export of {len(folders)} session(s) as {what}"

        def done(task: Task) -> None:
            if task in self.research_tasks:
                self.research_tasks.remove(task)
            if task.status is TaskStatus.CANCELLED:
                self._say("Export cancelled: nothing was written.")
            elif task.ok:
                self._say(str(task.result))
            else:
                self._say(task.error, error=True)
                self._export_not_written(task.error)
            if on_done is not None:
                on_done(task)

        archived = [f.uuid for f in folders if isinstance(f, ListedSession)]
        extra: dict[str, Any] = {}
        if archived:  # sessions of other stations: read by the worker as they stream from the archive (no copy)
            archive = self._archive_args()
            if archive is None:
                self._say(f"{(station.unreachable() or 'The archive is not open').rstrip('.')}: sessions of "
                          "other stations cannot be exported now.", error=True)
                return None
            extra = {"archived": archived, "archive": archive}
        named = [f.uuid if isinstance(f, ListedSession) else str(f) for f in folders]  # in the table's order
        task = self.tasks.run(JOB_KIND, fmt, named, str(destination), stamp, include_names=include_names, **extra,
                              title=title, parent=self, outputs=(staging_target(destination, stamp),), on_done=done)
        self.research_tasks.append(task)
        return task

    def closeEvent(self, event: QCloseEvent) -> None:
        self._generation += 1  # a load still running is dropped
        self._pump.stop()
        if self._own_tasks:
            self.tasks.close()
        if self._cache is not None:  # the copies of other stations' sessions (a replay open keeps its mapped files)
            shutil.rmtree(self._cache, ignore_errors=True)
            self._cache = None
        super().closeEvent(event)


ARCHIVED_JOB = "app.archive.reads:archived_job"  # a job on archived sessions copied from the archive first
PROGRESS_JOB = "app.archive.reads:progress_job"  # the progress rows of every station's sessions


def _name(s: ListedSession) -> str:
    return s.folder.name if s.folder is not None else s.folder_name.rpartition("/")[2]


def _where_words(s: ListedSession) -> str:
    if s.where == reads.WAITING:
        return "Recorded on this station and not yet in the archive: it is uploaded when the archive can be reached."
    if s.where == reads.REFUSED:
        return "The archive refused this session (another session holds its UUID): it stays on this station."
    if s.where == reads.ARCHIVED and s.folder is None:
        return f"Recorded on station {s.station}: read from the archive (copied when opened)."
    if s.where == reads.ARCHIVED:
        return "In the archive; this station has its folder too."
    return ""


__all__ = ["STOP_LEVELS", "SessionStatus", "SessionsBrowser", "session_status"]
