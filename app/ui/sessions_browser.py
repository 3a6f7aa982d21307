"""Sessions browser: a patient's sessions (date, duration, exercises, alarms); open, export, replay.

Exports run on a worker thread behind a cancellable progress dialog; the GUI stays live.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QColor, QKeySequence, QShortcut
from PySide6.QtWidgets import (
    QAbstractItemView,
    QComboBox,
    QDialog,
    QDialogButtonBox,
    QFileDialog,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPlainTextEdit,
    QProgressDialog,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app import paths
from app.export import ExportCancelled, export_csv, export_hdf5
from app.patients import list_patients
from app.recording import (
    EVENTS_FILE,
    SessionSummary,
    list_patients_with_sessions,
    list_sessions,
    load_session,
    read_events,
)
from app.reports import run_titles

log = logging.getLogger(__name__)

COLUMNS = ("Date", "Duration", "Exercises", "Alarms", "Operator", "Status")
FOLDER_ROLE = Qt.ItemDataRole.UserRole


def _date_text(iso: str) -> str:
    try:
        return _dt.datetime.fromisoformat(iso).strftime("%Y-%m-%d %H:%M")
    except ValueError:
        return iso or "?"


def _duration_text(seconds: float) -> str:
    m, s = divmod(round(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


@dataclass(frozen=True)
class SessionStatus:
    """What the Status column says, and why (its tooltip)."""

    text: str
    tooltip: str
    ok: bool


STOP_LEVELS = ("STOP", "FATAL")


def session_status(summary: SessionSummary, active: Path | None = None) -> SessionStatus:
    """``in progress`` (the session being recorded now), ``interrupted`` (the app never ended it),
    else ``complete`` only when every exercise finished and no STOP alarm was raised -- otherwise
    what went wrong (issue #19: 5 aborted exercises and 12 alarms showed as "complete")."""
    if active is not None and summary.folder.resolve() == active.resolve():
        return SessionStatus("in progress", "This session is being recorded now.", True)
    if not summary.complete:
        return SessionStatus("interrupted", "The session was not stopped normally (crash or power loss); "
                             "its data end at the last flush.", False)
    events, _dropped = read_events(summary.folder / EVENTS_FILE)
    ends = [e.get("data", {}) for e in events if e.get("kind") == "script_stop"]
    aborted = [d for d in ends if str(d.get("status", "finished")) != "finished"]
    stops = [e for e in events if e.get("kind") == "alarm" and e.get("data", {}).get("level") in STOP_LEVELS]
    problems = []
    if aborted:
        problems.append(f"{len(aborted)} of {len(ends)} exercise(s) aborted")
    if stops:
        problems.append(f"{len(stops)} stop alarm(s)")
    if not problems:
        return SessionStatus("complete", "Ended normally; every exercise finished, no stop alarm.", True)
    reasons = "; ".join(sorted({str(d.get("reason", d.get("status", ""))) for d in aborted})[:5])
    return SessionStatus("ended: " + ", ".join(problems),
                         "Ended normally, but " + " and ".join(problems) + (f". Causes: {reasons}" if reasons else ""),
                         False)


class ExportJob:
    """One export on a worker thread; ``done``, ``ok`` and ``message`` tell the result (the browser
    polls them from a GUI timer, so nothing crosses threads but plain attributes)."""

    def __init__(self, folder: Path, kind: str, destination: Path) -> None:
        if kind not in ("hdf5", "csv"):
            raise ValueError(f"unknown export kind {kind!r}")
        self.folder, self.kind, self.destination = folder, kind, destination
        self.fraction = 0.0
        self.cancelled = threading.Event()
        self.done = False
        self.ok = False
        self.message = ""
        self._thread = threading.Thread(target=self._run, name="session-export", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def cancel(self) -> None:
        self.cancelled.set()

    def _progress(self, fraction: float) -> bool:
        self.fraction = fraction
        return not self.cancelled.is_set()

    def _run(self) -> None:
        try:
            session = load_session(self.folder)
            if self.kind == "hdf5":
                export_hdf5(session, self.destination, self._progress)
            else:
                export_csv(session, self.destination, self._progress)
            self.ok, self.message = True, f"exported to {self.destination}"
        except ExportCancelled:
            self.message = "export cancelled"
        except Exception as exc:
            log.exception("export of %s failed", self.folder)
            self.message = f"export failed: {exc}"
        self.done = True


class SessionDetails(QDialog):
    """The manifest's essentials and every event of one session."""

    def __init__(self, folder: Path, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        session = load_session(folder)
        m = session.manifest
        self.setWindowTitle(f"Session {folder.name} — {m.get('patient_id', '?')}")
        lines = [
            f"Patient: {m.get('patient_id', '?')}    Operator: {m.get('operator', '?')}",
            f"Start: {(m.get('start') or {}).get('t_wall', '?')}    End: {(m.get('end') or {}).get('t_wall', '—')}",
            f"Duration: {_duration_text(session.duration_s)}    App version: {m.get('app_version', '?')}",
            "Streams: " + ", ".join(f"{n} ({len(s)} samples)" for n, s in session.streams.items()),
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
    """List, open, export and replay the sessions of one patient."""

    def __init__(self, root: Path | None = None, history_s: float = 30.0, parent: QWidget | None = None,
                 active: Callable[[], Path | None] | None = None) -> None:
        super().__init__(parent)
        self.root = root or paths.sessions_dir()
        self.active = active or (lambda: None)  # the folder being recorded now (shown "in progress")
        self.history_s = history_s
        self.setWindowTitle("Sessions")
        self.windows: list[QWidget] = []  # replay windows and dialogs kept alive
        self.jobs: list[ExportJob] = []
        self.summaries: list[SessionSummary] = []

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
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
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
        self.replay_button = QPushButton("&Replay")
        self.replay_button.clicked.connect(self.replay)
        self.summary_button = QPushButton("S&ummary…")  # metrics (app/ui/session_summary.py)
        self.summary_button.clicked.connect(self.open_summary)
        self.progress_button = QPushButton("Pro&gress…")  # the patient's trends (app/ui/progress_view.py)
        self.progress_button.clicked.connect(self.open_progress)
        self.status = QLabel("")
        buttons = QHBoxLayout()
        for b in (self.open_button, self.hdf5_button, self.csv_button, self.replay_button, self.summary_button,
                  self.progress_button):
            buttons.addWidget(b)
        buttons.addWidget(self.status, 1)
        # A window of its own needs its own way out (issue #30: only the title bar's cross closed it).
        self.close_button = QPushButton("&Close")
        self.close_button.clicked.connect(self.close)
        buttons.addWidget(self.close_button)
        QShortcut(QKeySequence(Qt.Key.Key_Escape), self, activated=self.close)

        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.table, 1)
        layout.addLayout(buttons)
        self.resize(980, 420)
        self.reload_patients()

    # ------------------------------------------------------------------ listing
    def reload_patients(self, select: str | None = None) -> None:
        current = select or self.patient_box.currentData()
        ids = set(list_patients_with_sessions(self.root))
        ids |= {e.patient_id for e in list_patients()}
        self.patient_box.blockSignals(True)
        self.patient_box.clear()
        for pid in sorted(ids, key=str.lower):
            self.patient_box.addItem(pid, pid)
        idx = self.patient_box.findData(current) if current else 0
        self.patient_box.setCurrentIndex(max(0, idx))
        self.patient_box.blockSignals(False)
        self.refresh()

    def set_patient(self, patient_id: str) -> None:
        self.reload_patients(patient_id)

    def refresh(self) -> None:
        pid = self.patient_box.currentData()
        self.summaries = list_sessions(pid, self.root) if pid else []
        self.table.setRowCount(len(self.summaries))
        for row, s in enumerate(self.summaries):
            titles = run_titles(s.folder) or s.exercises  # the runs' titles, not file names (older: scripts)
            exercises = ", ".join(titles) if titles else "—"
            status = session_status(s, self.active())
            cells = (_date_text(s.start), _duration_text(s.duration_s), exercises, str(s.alarms), s.operator,
                     status.text)
            for col, text in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setData(FOLDER_ROLE, str(s.folder))
                if col == 2 and titles:
                    item.setToolTip(exercises)  # a long list is elided in its cell
                if col == 5:
                    item.setToolTip(status.tooltip)
                    if not status.ok:
                        item.setForeground(QColor("#c62828"))
                self.table.setItem(row, col, item)
        if self.summaries:
            self.table.selectRow(0)
        self._update_buttons()

    def selected_folder(self) -> Path | None:
        row = self.table.currentRow()
        if row < 0 or row >= len(self.summaries):
            return None
        return self.summaries[row].folder

    def select_folder(self, folder: Path) -> None:
        for row, s in enumerate(self.summaries):
            if s.folder == folder:
                self.table.selectRow(row)
                return

    def _update_buttons(self) -> None:
        ok = self.selected_folder() is not None
        for b in (self.open_button, self.hdf5_button, self.csv_button, self.replay_button, self.summary_button):
            b.setEnabled(ok)
        self.progress_button.setEnabled(ok)

    # ------------------------------------------------------------------ actions
    def open_details(self) -> SessionDetails | None:
        folder = self.selected_folder()
        if folder is None:
            return None
        dialog = SessionDetails(folder, self)
        self.windows.append(dialog)
        dialog.show()
        return dialog

    def open_summary(self) -> QWidget | None:
        folder = self.selected_folder()
        if folder is None:
            return None
        from app.ui.session_summary import SessionSummaryDialog

        dialog = SessionSummaryDialog(folder, parent=self)
        self.windows.append(dialog)
        dialog.show()
        return dialog

    def open_progress(self) -> QWidget | None:
        pid = self.patient_box.currentData()
        if not pid:
            return None
        from app.ui.progress_view import ProgressDialog

        dialog = ProgressDialog(pid, self.root, parent=self)
        self.windows.append(dialog)
        dialog.show()
        return dialog

    def replay(self) -> QWidget | None:
        folder = self.selected_folder()
        if folder is None:
            return None
        from app.ui.replay_window import ReplayWindow

        window = ReplayWindow(folder, self.history_s)
        self.windows.append(window)
        window.show()
        return window

    def ask_export(self, kind: str) -> None:
        folder = self.selected_folder()
        if folder is None:
            return
        default = folder.parent.name + "_" + folder.name
        if kind == "hdf5":
            path, _ = QFileDialog.getSaveFileName(self, "Export session to HDF5", str(Path.home() / f"{default}.h5"),
                                                  "HDF5 files (*.h5 *.hdf5)")
        else:
            path = QFileDialog.getExistingDirectory(self, "Export session to CSV files (choose a folder)",
                                                    str(Path.home()))
            path = str(Path(path) / default) if path else ""
        if path:
            self.export(folder, kind, Path(path))

    def export(self, folder: Path, kind: str, destination: Path,
               on_done: Callable[[bool, str], Any] | None = None) -> ExportJob:
        """Export with a cancellable progress dialog; returns the running job."""
        job = ExportJob(folder, kind, destination)
        dialog = QProgressDialog(f"Exporting {folder.name} to {kind.upper()}…", "Cancel", 0, 1000, self)
        dialog.setWindowModality(Qt.WindowModality.WindowModal)
        dialog.setMinimumDuration(300)
        dialog.canceled.connect(job.cancel)
        timer = QTimer(dialog)
        timer.setInterval(50)

        def poll() -> None:
            if not job.done:
                dialog.setValue(int(job.fraction * 1000))
                return
            timer.stop()
            dialog.reset()
            dialog.close()
            self.status.setText(job.message)
            if job in self.jobs:
                self.jobs.remove(job)
            if on_done is not None:
                on_done(job.ok, job.message)

        timer.timeout.connect(poll)
        self.jobs.append(job)
        job.progress_dialog = dialog  # type: ignore[attr-defined]
        job.start()
        timer.start()
        return job
