"""Session → Patients…: the patients of this workstation, searched and edited, and each one's therapy plan.

The list reads the station's archive (app.archive.station.list_entries; without an archive, the YAML files of
``paths.patients_dir()``: a record that cannot be loaded is listed with its reason, never hidden). Each entry
keeps the record's version: the profile form and the plan form save as of it, and a save refused because the
patient was changed meanwhile says by whom, where and when, and offers Reload. "Edit profile…" opens the
profile form (app/ui/patient_dialog.py); "Therapy plan…"
edits the ordered exercises of the plan with each exercise's own form: every value is checked against the
exercise's declared range (app.therapy.exercises: Parameter.check / validate) as it is typed, and a plan with a value
out of range is not saved — the reason is said in words, at the field.

Never on the GUI thread (#37): reading and validating every record takes ~5-15 ms a patient (2 000 patients: tens
of seconds), so the list is read by a loader thread (:func:`app.archive.station.entry_blocks`: one snapshot of the
archive, validated block by block) and handed over through a queue; the window takes what has come on a timer and
adds rows for at most a few ms a turn ("Loading patients… 125 so far"), the search filtering what is loaded. A
saved form updates its one row (the record it saved), never the whole list.
"""

from __future__ import annotations

import bisect
import html
import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer
from PySide6.QtWidgets import (
    QAbstractItemView,
    QDialog,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.archive import station
from app.archive.api import ArchiveError
from app.core.config import SafetyConfig
from app.therapy.exercises import load_library
from app.therapy.patients import (
    PatientEntry,
    matches,
)
from app.ui.plan_dialog import PlanDialog, step_text

log = logging.getLogger(__name__)

_COLUMNS = ("Patient ID", "Name", "Affected side", "Plan", "Updated")
TURN_BUDGET_S = 0.006  # rows added per turn of the GUI thread: at most this long (a frame is 16 ms)
RESIZE_PRECISION_ROWS = 100  # the rows the columns' widths are measured on
POLL_MS = 15  # while loading: how often the window takes the blocks that came


def _key(patient_id: str) -> tuple[str, str]:
    """The list's order (the archive's: case-insensitive id)."""
    return patient_id.lower(), patient_id


def _local_time(iso: str) -> str:
    import datetime as _dt

    try:
        return _dt.datetime.fromisoformat(iso).astimezone().strftime("%Y-%m-%d %H:%M")
    except ValueError:
        return iso or "?"


class PatientsDialog(QDialog):
    """The patients: search, a profile's details, new / edit profile, therapy plan. A change to the profile of
    the patient whose session runs applies to that session at once (``manager``: the window's, by default the
    parent's), and this window says what changed."""

    def __init__(self, safety: SafetyConfig | None = None, folder: Path | None = None,
                 parent: QWidget | None = None, manager: Any = None) -> None:
        super().__init__(parent)
        self.safety = safety
        self.folder = folder
        self.manager = manager if manager is not None else getattr(parent, "manager", None)
        self.entries: list[PatientEntry] = []  # every patient loaded so far, in the list's order
        self._by_id: dict[str, PatientEntry] = {}
        self.shown: list[PatientEntry] = []  # the loaded patients the search finds; the table holds the first _filled
        self._filled = 0
        self._select: str | None = None  # the patient to select once their row is there
        self._generation = 0  # the load whose blocks are taken (an older loader's are dropped)
        self._blocks: queue.SimpleQueue[tuple[int, list[PatientEntry] | None, str]] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._loader: threading.Thread | None = None
        self.loading = False
        self._library: dict[str, Any] | None = None  # the exercises by id, for the plans shown in the details
        self._pump = QTimer(self)
        self._pump.setInterval(POLL_MS)
        self._pump.timeout.connect(self._take)
        self.child: QDialog | None = None  # the profile or plan dialog open on top of this one
        self.setWindowTitle("Patients")
        self.search = QLineEdit()
        self.search.setAccessibleName("Search patients")
        self.search.setPlaceholderText("Search: ID, name, record number or notes")
        self.search.setClearButtonEnabled(True)
        self.search.textChanged.connect(lambda _t: self.refresh())
        self.table = QTableWidget(0, len(_COLUMNS))
        self.table.setHorizontalHeaderLabels(list(_COLUMNS))
        self.table.setAccessibleName("Patients")
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.verticalHeader().setVisible(False)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(1, QHeaderView.ResizeMode.Stretch)
        # Sized to the contents of the first rows only: every row added would otherwise re-measure every row
        # (thousands of patients: a long turn at each block).
        header.setResizeContentsPrecision(RESIZE_PRECISION_ROWS)
        self.table.itemSelectionChanged.connect(self._selected)
        self.table.cellDoubleClicked.connect(lambda _r, _c: self.edit_profile())
        self.details = QLabel("")
        self.details.setWordWrap(True)
        self.details.setTextFormat(Qt.TextFormat.RichText)
        self.details.setAlignment(Qt.AlignmentFlag.AlignTop | Qt.AlignmentFlag.AlignLeft)
        self.details.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.details.setMinimumWidth(300)
        self.new_button = QPushButton("&New patient…")
        self.new_button.clicked.connect(self.new_patient)
        self.edit_button = QPushButton("&Edit profile…")
        self.edit_button.clicked.connect(self.edit_profile)
        self.plan_button = QPushButton("Therapy &plan…")
        self.plan_button.clicked.connect(self.edit_plan)
        close = QPushButton("&Close")
        close.clicked.connect(self.accept)
        buttons = QHBoxLayout()
        for b in (self.new_button, self.edit_button, self.plan_button):
            buttons.addWidget(b)
        buttons.addStretch(1)
        buttons.addWidget(close)
        left = QVBoxLayout()
        left.addWidget(self.search)
        left.addWidget(self.table, 1)
        body = QHBoxLayout()
        body.addLayout(left, 3)
        body.addWidget(self.details, 2)
        # What a change did to the running session ("Applied to the running session at once: …").
        self.session_note = QLabel("")
        self.session_note.setObjectName("sessionNote")
        self.session_note.setWordWrap(True)
        self.session_note.setVisible(False)
        # The archive cannot be reached: said here, once, plainly (the forms refuse to save and say why too).
        self.archive_note = QLabel("")
        self.archive_note.setObjectName("archiveNote")
        self.archive_note.setWordWrap(True)
        self.archive_note.setStyleSheet("color: #b00020; font-weight: bold;")
        self.archive_note.setVisible(False)
        self.read_only = False  # the archive unreachable: the station's copies shown, nothing saved (_finished)
        self.loading_note = QLabel("")
        self.loading_note.setObjectName("loadingNote")
        self.loading_note.setVisible(False)
        lay = QVBoxLayout(self)
        lay.addWidget(self.archive_note)
        lay.addWidget(self.loading_note)
        lay.addLayout(body, 1)
        lay.addWidget(self.session_note)
        lay.addLayout(buttons)
        self.resize(1000, 560)
        self.reload()

    # ------------------------------------------------------------------ list
    @property
    def loaded(self) -> bool:
        """Every patient read and every row the search finds in the table."""
        return not self.loading and self._filled == len(self.shown)

    def reload(self, select: str | None = None) -> None:
        """Read the list again, on the loader thread; ``select`` (or the patient selected now) is selected when
        their row comes."""
        self._select = select or self.selected_id()
        self._stop.set()  # an older loader stops at its next block; its blocks are dropped
        self._generation += 1
        self._stop = threading.Event()
        self.entries, self._by_id, self.shown, self._filled = [], {}, [], 0
        self.table.setRowCount(0)
        self.loading = True
        self.loading_note.setText("Loading patients…")
        self.loading_note.setVisible(True)
        self._loader = threading.Thread(target=self._load, args=(self._generation, self._stop),
                                        name="patients-loader", daemon=True)
        self._loader.start()
        self._pump.start()
        self._selected()

    def _load(self, generation: int, stop: threading.Event) -> None:
        """The loader thread: blocks of entries into the queue, then (generation, None, problem)."""
        problem = ""
        if self._library is None:  # the plans' exercise names in the details: read here, once
            try:
                self._library = {e.ident: e for e in load_library()[0]}
            except Exception:
                log.exception("reading the exercise library failed")
        try:
            for part in station.entry_blocks(self.safety, folder=self.folder):
                if stop.is_set():
                    return
                self._blocks.put((generation, part, ""))
        except ArchiveError as exc:
            problem = str(exc)
        except Exception as exc:  # never a traceback in the window: the list says it is incomplete
            log.exception("listing the patients failed")
            problem = f"The patients could not all be listed: {exc}"
        self._blocks.put((generation, None, problem))

    def _take(self) -> None:
        """A turn of the GUI thread: the blocks that came, and rows for at most TURN_BUDGET_S."""
        deadline = time.perf_counter() + TURN_BUDGET_S
        while time.perf_counter() < deadline:
            try:
                generation, part, problem = self._blocks.get_nowait()
            except queue.Empty:
                break
            if generation != self._generation:
                continue
            if part is None:
                self._finished(problem)
                break
            text = self.search.text()
            for entry in part:
                self._add(entry, matches(entry, text))
            self.loading_note.setText(f"Loading patients… {len(self.entries)} so far")
        self._fill(deadline)
        if not self.loading and self._filled == len(self.shown):
            self._pump.stop()

    def _finished(self, problem: str) -> None:
        self.loading = False
        self.loading_note.setVisible(False)
        # The archive cannot be reached and the station's copies of the patients it read stand in (app.archive.cache):
        # listed and shown, read-only; the sentence says since when. A session can still be started for them.
        self.read_only = bool(problem) and self.folder is None and bool(station.offline_since())
        if self.read_only:
            self.archive_note.setText(station.offline_sentence() if self.entries else
                                      f"{problem.rstrip('.')}. Patients cannot be opened or saved, nor their sessions "
                                      "started, until the archive is back (this station holds no copy of any).")
        elif problem:
            self.archive_note.setText(f"{problem.rstrip('.')}. Patients cannot be opened or saved, nor their "
                                      "sessions started, until the archive is back." if not self.entries else
                                      f"{problem.rstrip('.')}. The list may be incomplete.")
        self.archive_note.setVisible(bool(problem))
        self.new_button.setEnabled(not (problem and not self.entries) and not self.read_only)
        self._selected()
        if self._select is not None and self._select not in self._by_id:
            self._select = None

    def _add(self, entry: PatientEntry, show: bool) -> None:
        """A patient into the loaded list (replacing an older copy of them), and into the shown rows if ``show``."""
        old = self._by_id.get(entry.patient_id)
        self._by_id[entry.patient_id] = entry
        if old is not None:
            self.entries[self.entries.index(old)] = entry
            if old in self.shown:
                row = self.shown.index(old)
                self.shown[row] = entry
                if row < self._filled:
                    self._set_row(row, entry)
                    if entry.patient_id == self.selected_id():
                        self._selected()
            return
        keys = [_key(e.patient_id) for e in self.entries[-1:]]
        if not keys or keys[0] < _key(entry.patient_id):  # the loader's order: appended
            self.entries.append(entry)
        else:
            bisect.insort(self.entries, entry, key=lambda e: _key(e.patient_id))
        if show:
            at = bisect.bisect(self.shown, _key(entry.patient_id), key=lambda e: _key(e.patient_id))
            self.shown.insert(at, entry)
            if at < self._filled:  # among the rows already there (a patient saved while the list loads)
                self.table.insertRow(at)
                self._set_row(at, entry)
                self._filled += 1

    def _fill(self, deadline: float) -> None:
        """Rows for the shown patients not yet in the table, until ``deadline``; then the selection."""
        if self._filled < len(self.shown):
            self.table.setUpdatesEnabled(False)
            while self._filled < len(self.shown):
                row = self._filled
                self.table.insertRow(row)
                self._set_row(row, self.shown[row])
                self._filled += 1
                if self._filled % 16 == 0 and time.perf_counter() > deadline:
                    break
            self.table.setUpdatesEnabled(True)
        if not self.table.selectionModel().selectedRows():
            self._select_wanted()

    def _select_wanted(self) -> None:
        """Select the patient asked for once their row is there (else, once loaded, the first row)."""
        want = self._select
        row = next((k for k, e in enumerate(self.shown[:self._filled]) if e.patient_id == want), None)
        if row is None and want is not None and self.loading:
            return  # their row may still come
        if row is None and self._filled:
            row = 0
        if row is not None:
            self._select = None
            self.table.selectRow(row)
        self._selected()

    def _set_row(self, row: int, e: PatientEntry) -> None:
        p = e.profile
        if p is None:
            cells = (e.patient_id, "(the file cannot be loaded: see the details)", "", "", "")
        else:
            plan = f"{len(p.therapy_plan)} step(s)" if p.therapy_plan else "none"
            cells = (p.patient_id, p.full_name or "—", p.affected_side, plan, p.updated[:16].replace("T", " "))
        for col, value in enumerate(cells):
            item = QTableWidgetItem(value)
            item.setData(Qt.ItemDataRole.UserRole, e.patient_id)
            self.table.setItem(row, col, item)

    def refresh(self, select: str | None = None) -> None:
        """The search applied to the patients loaded so far (the rest as they come)."""
        self._select = select or self.selected_id()
        text = self.search.text()
        self.shown = [e for e in self.entries if matches(e, text)]
        self._filled = 0
        self.table.clearSelection()
        self.table.setRowCount(0)
        self._fill(time.perf_counter() + TURN_BUDGET_S)
        if self._filled < len(self.shown):
            self._pump.start()
        self._selected()

    def put(self, entry: PatientEntry, select: bool = True) -> None:
        """A record just saved (or read) here: its row updated, or added; selected when ``select`` — shown even if
        the search would hide it."""
        if select and not matches(entry, self.search.text()):
            self.search.blockSignals(True)  # a patient just created must be seen, whatever the search was
            self.search.clear()
            self.search.blockSignals(False)
            self._add(entry, False)
            self.refresh(entry.patient_id)
        else:
            self._add(entry, matches(entry, self.search.text()))
            self._fill(time.perf_counter() + TURN_BUDGET_S)
        if select:
            self._select = entry.patient_id
            self.table.clearSelection()
            self._select_wanted()

    def done(self, result: int) -> None:
        self._stop_loading()
        super().done(result)

    def closeEvent(self, event: Any) -> None:
        self._stop_loading()
        super().closeEvent(event)

    def _stop_loading(self) -> None:
        self._stop.set()
        self._pump.stop()

    def selected_id(self) -> str | None:
        rows = self.table.selectionModel().selectedRows() if self.table.selectionModel() else []
        if not rows:
            return None
        item = self.table.item(rows[0].row(), 0)
        return item.data(Qt.ItemDataRole.UserRole) if item is not None else None

    def selected_entry(self) -> PatientEntry | None:
        pid = self.selected_id()
        return None if pid is None else self._by_id.get(pid)

    def _selected(self) -> None:
        entry = self.selected_entry()
        if entry is None and self.loading and not self.table.rowCount():
            self.edit_button.setEnabled(False)
            self.plan_button.setEnabled(False)
            self.details.setText("<i>Loading patients…</i>")
            return
        ok = entry is not None and entry.profile is not None
        self.edit_button.setEnabled(ok and not self.read_only)
        self.plan_button.setEnabled(ok and not self.read_only)
        text = self.details_html(entry, self._library)
        if self.read_only and entry is not None:
            seen = _local_time(station.copy_seen_at(entry.patient_id))  # as the red line's "since" (local time)
            text = (f"<p style='color:#b00020'>This station's copy, read from the archive at {html.escape(seen)}: "
                    "read-only.</p>" + text)
        self.details.setText(text)

    @staticmethod
    def details_html(entry: PatientEntry | None, library: dict[str, Any] | None = None) -> str:
        """The details of ``entry``; ``library``: the exercises by id (read once, on the loader thread: reading
        the library takes ~50 ms, too long for a click), else read here."""
        if entry is None:
            return "<i>No patient matches.</i>"
        if entry.profile is None:
            return (f"<b>{html.escape(entry.patient_id)}</b><br>"
                    f"<span style='color:#b00020'>{html.escape(entry.error)}</span>")
        p = entry.profile
        esc = html.escape
        lines = [f"<h3>{esc(p.patient_id)}</h3>"]
        for label, value in (("Name", p.full_name), ("Date of birth", p.birth_date),
                             ("Medical record no.", p.record_number), ("Affected side", p.affected_side)):
            lines.append(f"{label}: <b>{esc(value or '—')}</b>")
        s = p.scores
        scores = [f"{n} {v}" for n, v in (("FM-UE", s.fugl_meyer_ue), ("ARAT", s.action_research_arm_test),
                                          ("BBT", s.box_and_block), ("MAS", s.modified_ashworth)) if v is not None]
        lines.append("Scores: " + (esc(", ".join(scores)) + (f" ({esc(s.assessed_on)})" if s.assessed_on else "")
                                   if scores else "—"))
        if p.therapy_plan:
            if library is None:
                library = {e.ident: e for e in load_library()[0]}
            steps = "".join(f"<li>{esc(step_text(step, library.get(step.exercise), k + 1)[len(str(k + 1)) + 2:])}</li>"
                            for k, step in enumerate(p.therapy_plan))
            lines.append(f"Therapy plan:<ol style='margin-top:0'>{steps}</ol>")
        else:
            lines.append("Therapy plan: none")
        if p.notes:
            lines.append(f"Notes: {esc(p.notes)}")
        return "<br>".join(lines)

    # ------------------------------------------------------------------ actions
    def _open(self, dialog: QDialog, select: str | None) -> QDialog:
        """Open ``dialog`` on top of this one (window-modal, not a nested event loop: F12 and the alarms keep
        working), and reload the list when it closes."""
        self.child = dialog

        def closed(result: int) -> None:
            saved = getattr(dialog, "profile", None)
            if saved is not None:  # the record the form saved (or reloaded), with its version: its row only
                old = self._by_id.get(saved.patient_id)
                path = old.path if old is not None else Path(saved.patient_id)
                self.put(PatientEntry(saved.patient_id, path, saved, "", int(getattr(dialog, "version", 0) or 0)),
                         select=select is None or select == saved.patient_id)
            pid = select or getattr(saved, "patient_id", None)
            if result == QDialog.DialogCode.Accepted and pid:
                self.apply_to_session(pid)

        dialog.finished.connect(closed)
        dialog.open()
        return dialog

    def apply_to_session(self, patient_id: str) -> list[str]:
        """The saved profile of ``patient_id`` reaches the running session at once when it is that session's
        patient (the next command meets the new caps and limits); says so here. Returns the changes."""
        manager = self.manager
        current = getattr(manager, "patient_profile", None)
        if manager is None or getattr(manager, "recorder", None) is None or current is None \
                or current.patient_id != patient_id:
            return []
        entry = self._by_id.get(patient_id)
        if entry is None or entry.profile is None:
            return []
        changes = manager.update_session_profile(entry.profile, entry.version or None)
        if changes:
            self.session_note.setText(f"Applied to {patient_id}'s running session at once: " + "; ".join(changes)
                                      + ". The next command meets them.")
            self.session_note.setStyleSheet("color: #1b5e20; font-weight: bold;")
            self.session_note.setVisible(True)
        return changes

    def operator(self) -> str:
        """Who the saves are recorded as: the running session's operator (else the computer's login)."""
        return station.default_operator(str(getattr(self.manager, "operator", "") or ""))

    def new_patient(self) -> QDialog:
        """A new patient's profile; once saved, their therapy plan opens at once (one action fewer, #36)."""
        from app.ui.patient_dialog import PatientDialog

        dialog = PatientDialog(None, self.safety, self.folder, self, operator=self.operator())

        def saved(result: int) -> None:
            profile = getattr(dialog, "profile", None)
            if result == QDialog.DialogCode.Accepted and profile is not None:
                QTimer.singleShot(0, self, lambda: self._plan_for(profile.patient_id))

        dialog.finished.connect(saved)
        return self._open(dialog, None)

    def _plan_for(self, patient_id: str) -> PlanDialog | None:
        if self.selected_id() != patient_id:
            return None
        return self.edit_plan()

    def edit_profile(self) -> QDialog | None:
        from app.ui.patient_dialog import PatientDialog

        entry = self.selected_entry()
        if entry is None or entry.profile is None or self.read_only:
            return None
        return self._open(PatientDialog(entry.profile, self.safety, self.folder, self, version=entry.version or None,
                                        operator=self.operator()), entry.patient_id)

    def edit_plan(self) -> PlanDialog | None:
        entry = self.selected_entry()
        if entry is None or entry.profile is None or self.read_only:
            return None
        dialog = PlanDialog(entry.profile, self.safety, self.folder, parent=self, version=entry.version or None,
                            operator=self.operator())
        self._open(dialog, entry.patient_id)
        return dialog
