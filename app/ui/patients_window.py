"""Session → Patients…: the patients of this workstation, searched and edited, and each one's therapy plan.

The list reads the station's archive (app.archive.station.list_entries; without an archive, the YAML files of
``paths.patients_dir()``: a record that cannot be loaded is listed with its reason, never hidden). Each entry
keeps the record's version: the profile form and the plan form save as of it, and a save refused because the
patient was changed meanwhile says by whom, where and when, and offers Reload. "Edit profile…" opens the
profile form (app/ui/patient_dialog.py); "Therapy plan…"
edits the ordered exercises of the plan with each exercise's own form: every value is checked against the
exercise's declared range (app.exercises: Parameter.check / validate) as it is typed, and a plan with a value
out of range is not saved — the reason is said in words, at the field.
"""

from __future__ import annotations

import html
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
from app.config import SafetyConfig
from app.exercises import load_library
from app.patients import (
    PatientEntry,
    matches,
)
from app.ui.plan_dialog import PlanDialog, step_text

_COLUMNS = ("Patient ID", "Name", "Affected side", "Plan", "Updated")


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
        self.entries: list[PatientEntry] = []
        self.shown: list[PatientEntry] = []
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
        lay = QVBoxLayout(self)
        lay.addWidget(self.archive_note)
        lay.addLayout(body, 1)
        lay.addWidget(self.session_note)
        lay.addLayout(buttons)
        self.resize(1000, 560)
        self.reload()

    # ------------------------------------------------------------------ list
    def reload(self, select: str | None = None) -> None:
        select = select or self.selected_id()
        try:
            self.entries = station.list_entries(self.safety, folder=self.folder)
            problem = ""
        except ArchiveError as exc:
            self.entries, problem = [], str(exc)
        if problem:
            self.archive_note.setText(f"{problem}. Patients cannot be opened or saved, nor their sessions "
                                      "started, until the archive is back.")
        self.archive_note.setVisible(bool(problem))
        self.new_button.setEnabled(not problem)
        if select and not any(e.patient_id == select and matches(e, self.search.text()) for e in self.entries):
            self.search.blockSignals(True)  # a patient just created must be seen, whatever the search was
            self.search.clear()
            self.search.blockSignals(False)
        self.refresh(select)

    def refresh(self, select: str | None = None) -> None:
        select = select or self.selected_id()
        text = self.search.text()
        self.shown = [e for e in self.entries if matches(e, text)]
        self.table.setRowCount(len(self.shown))
        for row, e in enumerate(self.shown):
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
        ids = [e.patient_id for e in self.shown]
        self.table.clearSelection()
        if select in ids:
            self.table.selectRow(ids.index(select))
        elif ids:
            self.table.selectRow(0)
        self._selected()

    def selected_id(self) -> str | None:
        rows = self.table.selectionModel().selectedRows() if self.table.selectionModel() else []
        if not rows:
            return None
        item = self.table.item(rows[0].row(), 0)
        return item.data(Qt.ItemDataRole.UserRole) if item is not None else None

    def selected_entry(self) -> PatientEntry | None:
        pid = self.selected_id()
        return next((e for e in self.entries if e.patient_id == pid), None)

    def _selected(self) -> None:
        entry = self.selected_entry()
        ok = entry is not None and entry.profile is not None
        self.edit_button.setEnabled(ok)
        self.plan_button.setEnabled(ok)
        self.details.setText(self.details_html(entry))

    @staticmethod
    def details_html(entry: PatientEntry | None) -> str:
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
            pid = select or getattr(getattr(dialog, "profile", None), "patient_id", None)
            self.reload(pid)
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
        entry = next((e for e in self.entries if e.patient_id == patient_id), None)
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
        self.refresh(patient_id)
        if self.selected_id() != patient_id:
            return None
        return self.edit_plan()

    def edit_profile(self) -> QDialog | None:
        from app.ui.patient_dialog import PatientDialog

        entry = self.selected_entry()
        if entry is None or entry.profile is None:
            return None
        return self._open(PatientDialog(entry.profile, self.safety, self.folder, self, version=entry.version or None,
                                        operator=self.operator()), entry.patient_id)

    def edit_plan(self) -> PlanDialog | None:
        entry = self.selected_entry()
        if entry is None or entry.profile is None:
            return None
        dialog = PlanDialog(entry.profile, self.safety, self.folder, parent=self, version=entry.version or None,
                            operator=self.operator())
        self._open(dialog, entry.patient_id)
        return dialog
