"""Create or edit a patient profile, and choose patient + operator to start a session (the session-start
dialog: the operator is chosen explicitly each time; the last one is offered as a button, never pre-filled).

The form is validated by the same code that loads profile files (app.therapy.patients.parse_profile →
app.core.yamlschema): the form is turned into the YAML document it would save, and any problem is shown
next to the field it names, in the same words as a bad file would get.
"""

from __future__ import annotations

import logging
import queue
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

from PySide6.QtCore import QSettings, Qt, QTimer
from PySide6.QtWidgets import (
    QComboBox,
    QDialog,
    QDialogButtonBox,
    QFileDialog,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QPlainTextEdit,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.archive import patient_form, station
from app.archive.api import ArchiveError, PatientExists, StaleRecord
from app.core.config import SafetyConfig
from app.therapy.patients import PatientEntry, PatientError, PatientProfile, list_patients, matches
from app.wire.sciencemode import CHANNELS

log = logging.getLogger(__name__)

_SCORES = (("fugl_meyer_ue", "Fugl-Meyer UE (0–66)"), ("modified_ashworth", "Modified Ashworth (0–4)"),
           ("action_research_arm_test", "ARAT (0–57)"), ("box_and_block", "Box and Block (blocks/min)"),
           ("assessed_on", "Assessed on (YYYY-MM-DD)"))
_ROBOT = (("position_min_m", "Position min [m]"), ("position_max_m", "Position max [m]"),
          ("max_velocity_m_s", "Max velocity [m/s]"), ("max_acceleration_m_s2", "Max acceleration [m/s²]"),
          ("max_interaction_force_n", "Max interaction force [N]"), ("max_stiffness_n_m", "Max stiffness [N/m]"),
          ("max_delta_m", "Max delta [m]"))
_CAP_COLUMNS = (("max_current_ma", "Max current [mA]"), ("max_pulse_width_us", "Max pulse width [µs]"),
                ("max_rms_current_ma", "Max r.m.s. [mA]"))
_ERROR_STYLE = "background: #ffd6d6;"


def _text(value: Any) -> str:
    return "" if value is None else str(value)


class PatientDialog(QDialog):
    """Edit ``profile`` (None: a new patient). On OK the profile is validated and saved — through the station's
    archive (app.archive.station) as of the record's ``version``: when anything of the patient was saved since
    (another window, another station, an electrode choice in a session) the save is refused, saying who changed
    it, on which station and when, and the form offers Reload (the saved values, with this form's own changes
    put back where they do not collide; nothing typed is dropped without saying so)."""

    def __init__(self, profile: PatientProfile | None = None, safety: SafetyConfig | None = None,
                 folder: Path | None = None, parent: QWidget | None = None, *, version: int | None = None,
                 operator: str = "", archive: Any = None) -> None:
        super().__init__(parent)
        self.safety = safety
        self.folder = folder
        self.archive = archive  # None: the station's archive, or the YAML folder without one
        self.operator = operator
        if profile is not None and version is None:  # the record as it is now, with its version
            record = station.record_or_none(profile.patient_id, archive=archive, folder=folder)
            if record is not None:
                profile, version = record.profile, record.version
        self.original = profile
        self.version = version or 0  # the record's version the form shows (0: a YAML file)
        self.stale: StaleRecord | None = None  # the last refused save's reason
        self.profile: PatientProfile | None = None  # the saved profile after accept
        self.saved_path: Path | None = None
        self.setWindowTitle("New patient" if profile is None else f"Patient {profile.patient_id}")
        p = profile or PatientProfile()
        self.fields: dict[str, QWidget] = {}

        form = QFormLayout()
        self.id_edit = self._line("patient_id", p.patient_id, "Pseudonym or identifier: letters, digits, - and _")
        self.id_edit.setReadOnly(profile is not None)  # the id names the file and the sessions folder
        form.addRow("Patient ID", self.id_edit)
        self.name_edit = self._line("full_name", p.full_name, "Optional: for the printed record. Leave empty for a "
                                    "pseudonymous profile")
        form.addRow("Name", self.name_edit)
        self.birth_edit = self._line("birth_date", p.birth_date, "Optional: YYYY-MM-DD")
        self.birth_edit.setPlaceholderText("YYYY-MM-DD")
        form.addRow("Date of birth", self.birth_edit)
        self.record_edit = self._line("record_number", p.record_number, "Optional: the clinic's medical record number")
        form.addRow("Medical record no.", self.record_edit)
        self.side_box = QComboBox()
        for side in ("unknown", "left", "right", "both"):
            self.side_box.addItem(side, side)
        self.side_box.setCurrentIndex(self.side_box.findData(p.affected_side))
        self.fields["affected_side"] = self.side_box
        form.addRow("Affected side", self.side_box)
        self.k_r = self._line("assistance.k_r", p.assistance.k_r, "Robot share of the assistance, 0–1")
        self.k_f = self._line("assistance.k_f", p.assistance.k_f, "FES share of the assistance, 0–1")
        form.addRow("Assistance gain k_r", self.k_r)
        form.addRow("Assistance gain k_f", self.k_f)
        self.fes_profile = self._line("fes.profile", p.fes.profile, "FES profile file (resources/fes_profiles)")
        self.fes_browse = QPushButton("&Browse…")
        self.fes_browse.setToolTip("Choose the FES profile file")
        self.fes_browse.clicked.connect(self.browse_fes_profile)
        fes_row = QHBoxLayout()
        fes_row.setContentsMargins(0, 0, 0, 0)
        fes_row.addWidget(self.fes_profile, 1)
        fes_row.addWidget(self.fes_browse)
        form.addRow("FES profile", fes_row)

        scores = QGroupBox("Clinical scores")
        sform = QFormLayout(scores)
        for key, label in _SCORES:
            sform.addRow(label, self._line(f"scores.{key}", getattr(p.scores, key)))
        robot = QGroupBox("Robot limits (empty: the configured limit; only tighter values are accepted)")
        rform = QFormLayout(robot)
        for key, label in _ROBOT:
            rform.addRow(label, self._line(f"robot.{key}", getattr(p.robot, key)))

        caps = QGroupBox("FES clinical caps per channel (empty row: no patient cap)")
        clay = QVBoxLayout(caps)
        self.caps_table = QTableWidget(len(CHANNELS), len(_CAP_COLUMNS))
        self.caps_table.setHorizontalHeaderLabels([label for _k, label in _CAP_COLUMNS])
        self.caps_table.setVerticalHeaderLabels([f"Ch {ch}" for ch in CHANNELS])
        self.caps_table.setAccessibleName("FES clinical caps")
        # Headers whole (issue #19: "Max current [mA", "ax pulse width [µ"): columns fit their titles.
        self.caps_table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        for ch, cap in p.fes.caps.items():
            for col, (key, _label) in enumerate(_CAP_COLUMNS):
                self.caps_table.setItem(ch - 1, col, QTableWidgetItem(_text(getattr(cap, key))))
        clay.addWidget(self.caps_table)

        self.notes = QPlainTextEdit(p.notes)
        self.notes.setAccessibleName("Notes")
        self.fields["notes"] = self.notes
        self.error_label = QLabel("")
        self.error_label.setWordWrap(True)
        self.error_label.setStyleSheet("color: #b00020;")
        self.error_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)

        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Save | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        # Offered when the patient was saved elsewhere since this form opened (StaleRecord).
        self.reload_button = buttons.addButton("&Reload", QDialogButtonBox.ButtonRole.ResetRole)
        self.reload_button.setToolTip("Show the patient as saved now, with this form's changes put back where "
                                      "they do not collide")
        self.reload_button.clicked.connect(self.reload)
        self.reload_button.setVisible(False)

        left = QVBoxLayout()
        left.addLayout(form)
        left.addWidget(scores)
        left.addWidget(QLabel("Notes"))
        left.addWidget(self.notes, 1)
        right = QVBoxLayout()
        right.addWidget(robot)
        right.addWidget(caps, 1)
        cols = QHBoxLayout()
        cols.addLayout(left, 1)
        cols.addLayout(right, 1)
        layout = QVBoxLayout(self)
        layout.addLayout(cols, 1)
        layout.addWidget(self.error_label)
        layout.addWidget(buttons)

    def browse_fes_profile(self) -> None:
        """A file dialog in the FES profiles folder; a file there is kept as its bare name (the
        profile loader finds it there), any other as its full path."""
        from app.ui.fes_panel import PROFILES_DIR

        current = self.fes_profile.text().strip()
        start = Path(current) if current and Path(current).is_absolute() else PROFILES_DIR / current
        path, _ = QFileDialog.getOpenFileName(self, "FES profile", str(start if current else PROFILES_DIR),
                                              "FES profiles (*.yaml *.yml);;All files (*)")
        if path:
            chosen = Path(path)
            self.fes_profile.setText(chosen.name if chosen.parent.resolve() == PROFILES_DIR.resolve() else str(chosen))

    def _line(self, key: str, value: Any, tip: str = "") -> QLineEdit:
        edit = QLineEdit(_text(value))
        edit.setAccessibleName(key)
        if tip:
            edit.setToolTip(tip)
        edit.textChanged.connect(lambda _t, e=edit: e.setStyleSheet(""))
        self.fields[key] = edit
        return edit

    # ------------------------------------------------------------------ form → profile
    def form_data(self) -> dict[str, Any]:
        """The profile's data the fields make (app.archive.patient_form: the rules `linarmpp archive patient add`
        uses too)."""
        caps: dict[Any, dict[str, str]] = {}
        for row, ch in enumerate(CHANNELS):
            cells = {}
            for col, (key, _label) in enumerate(_CAP_COLUMNS):
                item = self.caps_table.item(row, col)
                cells[key] = item.text() if item is not None else ""
            caps[ch] = cells
        texts = patient_form.FormTexts(
            patient_id=self.id_edit.text(), full_name=self.name_edit.text(), birth_date=self.birth_edit.text(),
            record_number=self.record_edit.text(), affected_side=self.side_box.currentData(),
            k_r=self.k_r.text(), k_f=self.k_f.text(), fes_profile=self.fes_profile.text(),
            scores={key: self.fields[f"scores.{key}"].text() for key, _l in _SCORES},  # type: ignore[attr-defined]
            robot={key: self.fields[f"robot.{key}"].text() for key, _l in _ROBOT},  # type: ignore[attr-defined]
            caps=caps, notes=self.notes.toPlainText())
        return patient_form.form_data(texts, self.original)

    def validate(self) -> PatientProfile | None:
        """The form as a valid profile, or None with the problem shown at its field."""
        for widget in self.fields.values():
            widget.setStyleSheet("")
        self.error_label.setText("")
        try:
            return patient_form.profile_of(self.form_data(), self.safety)
        except PatientError as exc:
            self.show_error(patient_form.error_key(exc.key, exc.problem, self.fields), exc.problem)
            return None

    def show_error(self, key: str, problem: str) -> None:
        self.error_label.setText(f"{key or 'profile'}: {problem}")
        widget = self.fields.get(key)
        if widget is None and key.startswith("fes.caps."):
            parts = key.split(".")
            try:
                row = int(parts[2]) - 1
                col = [k for k, _l in _CAP_COLUMNS].index(parts[3]) if len(parts) > 3 else 0
                self.caps_table.setCurrentCell(row, col)
            except (ValueError, IndexError):
                pass
            widget = self.caps_table
        if widget is not None:
            widget.setStyleSheet(_ERROR_STYLE)
            widget.setFocus()

    def accept(self) -> None:
        profile = self.validate()
        if profile is None:
            return
        try:
            record = station.save_profile(profile, expected_version=None if self.original is None else self.version,
                                          operator=station.default_operator(self.operator), safety=self.safety,
                                          archive=self.archive, folder=self.folder)
        except PatientExists:
            self.show_error("patient_id", f"a patient {profile.patient_id!r} already exists")
            return
        except StaleRecord as exc:
            self.stale = exc
            what = f" ({', '.join(station.field_words(f) for f in exc.fields)})" if exc.fields else ""
            self.error_label.setText(
                f"Not saved: {profile.patient_id} was changed{what} by {exc.changed_by or 'someone'} on station "
                f"{exc.changed_station or '(unknown)'} at {exc.changed_at}, after this form was opened. Reload shows "
                "their values with your changes put back where they do not collide; then Save again.")
            self.reload_button.setVisible(True)
            self.reload_button.setFocus()
            return
        except (ArchiveError, OSError, PatientError, ValueError) as exc:
            self.error_label.setText(f"could not save: {exc}")
            return
        if self.archive is None and (self.folder is not None or not station.in_use()):  # the YAML file
            from app.therapy.patients import patient_file

            self.saved_path = patient_file(profile.patient_id, self.folder)
        self.version = record.version
        self.profile = replace(record.profile)
        super().accept()

    def reload(self) -> list[str]:
        """After a refused save: the patient as saved now, with this form's own changes put back on every field the
        other save did not change. Returns the fields where both changed (theirs shown; yours said in the message
        so that nothing typed is lost unsaid)."""
        from app.archive.store import profile_from_values, profile_values

        mine = self.validate()
        try:
            record = station.read_record(self.original.patient_id if self.original else "", archive=self.archive,
                                         folder=self.folder)
        except (ArchiveError, PatientError, OSError, ValueError) as exc:
            self.error_label.setText(f"The patient cannot be read again: {exc}")
            return []
        if record is None or self.original is None:
            return []
        base, theirs = profile_values(self.original), profile_values(record.profile)
        merged, kept, both = dict(theirs), [], []
        if mine is not None:
            yours = profile_values(mine)
            for key in sorted(set(yours) | set(base)):
                if yours.get(key) == base.get(key):
                    continue  # not changed in this form
                if theirs.get(key) == base.get(key):
                    merged[key] = yours.get(key)
                    kept.append(key)
                elif theirs.get(key) != yours.get(key):
                    both.append((key, yours.get(key)))
        merged = {k: v for k, v in merged.items() if v is not None}
        shown = profile_from_values(record.profile.patient_id, merged, record.profile.created, record.profile.updated)
        self.original, self.version, self.stale = record.profile, record.version, None
        self.fill(shown)
        self.reload_button.setVisible(False)
        words = [f"Reloaded: the patient as saved by {record.changed_by} on {record.changed_station} at "
                 f"{record.changed_at} (version {record.version})."]
        if kept:
            words.append(f"Your changes ({', '.join(station.field_words(k) for k in kept)}) are in the form "
                         "again: Save to keep them.")
        if both:
            words.append("Changed there too, their value is shown — yours was: "
                         + "; ".join(f"{station.field_words(k)}: {_short(v)}" for k, v in both) + ".")
        self.error_label.setText(" ".join(words))
        return [k for k, _v in both]

    def fill(self, p: PatientProfile) -> None:
        """Show ``p`` in the form (every field the form edits)."""
        self.id_edit.setText(p.patient_id)
        self.name_edit.setText(p.full_name)
        self.birth_edit.setText(p.birth_date)
        self.record_edit.setText(p.record_number)
        self.side_box.setCurrentIndex(self.side_box.findData(p.affected_side))
        self.k_r.setText(_text(p.assistance.k_r))
        self.k_f.setText(_text(p.assistance.k_f))
        self.fes_profile.setText(p.fes.profile)
        for key, _label in _SCORES:
            self.fields[f"scores.{key}"].setText(_text(getattr(p.scores, key)))  # type: ignore[attr-defined]
        for key, _label in _ROBOT:
            self.fields[f"robot.{key}"].setText(_text(getattr(p.robot, key)))  # type: ignore[attr-defined]
        for row, ch in enumerate(CHANNELS):
            cap = p.fes.caps.get(ch)
            for col, (key, _label) in enumerate(_CAP_COLUMNS):
                self.caps_table.setItem(row, col, QTableWidgetItem(_text(getattr(cap, key)) if cap else ""))
        self.notes.setPlainText(p.notes)


def _short(value: Any) -> str:
    text = "empty" if value in (None, "", {}, []) else str(value)
    return text if len(text) <= 80 else text[:77] + "…"


def patient_text(entry: PatientEntry) -> str:
    """A patient as the session-start list shows them: "Bianchi Maria — P-017 (record MRN-20417)"; a pseudonymous
    profile by its id alone; a file that cannot be loaded says so."""
    p = entry.profile
    if p is None:
        return f"{entry.patient_id} (invalid file)"
    text = f"{p.full_name} — {entry.patient_id}" if p.full_name else entry.patient_id
    return text + (f" (record {p.record_number})" if p.record_number else "")


class StartSessionDialog(QDialog):
    """Choose the patient and the operator of a new session (a session always has both). The patients are listed
    by name, id and record number, and searched; a new patient and their therapy plan are made from here (the
    first run's path to the first exercise: New patient…, Therapy plan…, Start session)."""

    def __init__(self, safety: SafetyConfig | None = None, folder: Path | None = None,
                 parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.safety = safety
        self.folder = folder
        self.child: QDialog | None = None  # the form open on top of this one (window-modal)
        self.setWindowTitle("Start session")
        self.search_edit = QLineEdit()
        self.search_edit.setAccessibleName("Search patients")
        self.search_edit.setPlaceholderText("Search by name, ID or record number")
        self.search_edit.setClearButtonEnabled(True)
        self.search_edit.textChanged.connect(lambda _t: self._fill())  # the list read once, searched here
        self.patient_box = QComboBox()
        self.patient_box.setAccessibleName("Patient")
        self.patient_box.setMinimumContentsLength(28)
        self.patient_box.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.patient_box.currentIndexChanged.connect(self._update)
        new_button = QPushButton("&New patient…")
        new_button.clicked.connect(self.new_patient)
        self.edit_button = QPushButton("&Edit…")
        self.edit_button.clicked.connect(self.edit_patient)
        self.plan_button = QPushButton("Therapy &plan…")
        self.plan_button.setToolTip("The patient's exercises, in the order the Exercises tab offers them")
        self.plan_button.clicked.connect(self.edit_plan)
        row = QHBoxLayout()
        row.addWidget(self.patient_box, 1)
        row.addWidget(self.edit_button)
        row.addWidget(self.plan_button)
        row.addWidget(new_button)
        # The operator signs the session's record: typed (or the last one taken with a click) by whoever starts
        # it, never kept from the last session as the value (issue #26: a colleague signed as someone else).
        self.operator_edit = QLineEdit("")
        self.operator_edit.setAccessibleName("Operator")
        self.operator_edit.setPlaceholderText("Your name or staff ID")
        self.operator_edit.textChanged.connect(self._update)
        self.last_operator = str(QSettings().value("session/operator", "") or "")
        self.last_operator_button: QPushButton | None = None
        operator_row = QHBoxLayout()
        operator_row.addWidget(self.operator_edit, 1)
        if self.last_operator:
            self.last_operator_button = QPushButton(f"I am {self.last_operator}")
            self.last_operator_button.setToolTip("The operator of the last session on this computer: click only if "
                                                 "that is you")
            self.last_operator_button.clicked.connect(lambda: self.operator_edit.setText(self.last_operator))
            operator_row.addWidget(self.last_operator_button)
        self.note_edit = QLineEdit()
        self.note_edit.setAccessibleName("Session note")
        self.problem = QLabel("")
        self.problem.setWordWrap(True)
        self.problem.setStyleSheet("color: #b00020;")
        form = QFormLayout()
        form.addRow("Search", self.search_edit)
        form.addRow("Patient", row)
        form.addRow("Operator", operator_row)
        form.addRow("Note", self.note_edit)
        self.buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        self.buttons.button(QDialogButtonBox.StandardButton.Ok).setText("Start session")
        self.buttons.accepted.connect(self.accept)
        self.buttons.rejected.connect(self.reject)
        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addWidget(self.problem)
        layout.addWidget(self.buttons)
        self.entries: dict[str, PatientEntry] = {}
        self.loading = False
        self._load_problem = ""  # why the last read listed nobody (the archive away, …)
        self._select: str | None = None
        self._generation = 0
        # the loaders' results, taken by the pump: a reload while an earlier read runs makes two loaders, and the
        # earlier one may finish last — each result is queued with its generation, a stale one dropped
        self._reads: queue.SimpleQueue[tuple[int, list[PatientEntry], str]] = queue.SimpleQueue()
        self._pump = QTimer(self)
        self._pump.setInterval(30)
        self._pump.timeout.connect(self._take)
        self.reload()

    @property
    def loaded(self) -> bool:
        """The patients are listed (read on a thread of their own)."""
        return not self.loading

    def reload(self, select: str | None = None) -> None:
        """Read the patients again, off the window's thread (every profile is read and validated: many patients,
        or the clinic's archive, would hold the window meanwhile), then list those the search finds with
        ``select`` (or the one chosen) chosen again."""
        self._select = select or self.patient_box.currentData()
        self._generation += 1
        self.loading = True
        self._update()
        threading.Thread(target=self._load, args=(self._generation,), name="session-patients", daemon=True).start()
        self._pump.start()

    def _load(self, generation: int) -> None:
        """The loader thread: every patient, as the Patients window lists them."""
        try:
            entries, problem = list_patients(self.folder, self.safety), ""
        except Exception as exc:  # never a traceback in the dialog: the list says it is incomplete
            log.exception("listing the patients failed")
            entries, problem = [], f"The patients could not be listed: {exc}"
        self._reads.put((generation, entries, problem))

    def _take(self) -> None:
        while True:
            try:
                generation, entries, problem = self._reads.get_nowait()
            except queue.Empty:
                return
            if generation == self._generation:
                break
        self._pump.stop()
        self._load_problem = problem
        self.entries = {e.patient_id: e for e in entries}
        self.loading = False
        self._fill(self._select)

    def _fill(self, select: str | None = None) -> None:
        """List the patients the search finds (all of them without a search), ``select`` (or the one chosen)
        chosen again. A patient chosen by ``select`` is shown even when the search would hide them."""
        current = select or self.patient_box.currentData()
        search = self.search_edit.text().strip()
        shown = [e for e in self.entries.values() if not search or matches(e, search) or e.patient_id == select]
        self.patient_box.blockSignals(True)
        self.patient_box.clear()
        for entry in shown:
            self.patient_box.addItem(patient_text(entry), entry.patient_id)
            self.patient_box.setItemData(self.patient_box.count() - 1, patient_text(entry), Qt.ItemDataRole.ToolTipRole)
        idx = self.patient_box.findData(current) if current else 0
        self.patient_box.setCurrentIndex(max(0, idx))
        self.patient_box.blockSignals(False)
        self._update()

    def _update(self, *_args: Any) -> None:
        entry = self.entries.get(self.patient_box.currentData())
        problem = ""
        if self.loading:
            problem = "Loading patients…"
        elif entry is None and self._load_problem:
            problem = self._load_problem
        elif entry is None and self.entries and self.search_edit.text().strip():
            problem = "No patient matches the search."
        elif entry is None and station.unreachable():  # not "create one": they exist, the archive is away
            problem = (f"{station.unreachable()[:1].upper()}{station.unreachable()[1:]}: patients cannot be opened "
                       "until it is back.")
        elif entry is None:
            problem = "Create a patient first (New patient…)."
        elif entry.profile is None:
            problem = entry.error
        elif not self.operator_edit.text().strip():
            problem = "Enter the operator's name."
        self.problem.setText(problem)
        valid = entry is not None and entry.profile is not None
        self.edit_button.setEnabled(valid)
        self.plan_button.setEnabled(valid)
        self.buttons.button(QDialogButtonBox.StandardButton.Ok).setEnabled(not problem)

    def _open(self, dialog: QDialog, select: str | None) -> QDialog:
        """Open ``dialog`` on top of this one (window-modal, not a nested event loop: F12 and the alarms keep
        working), and list the patients again when it closes, ``select`` (or the patient it saved) chosen."""
        self.child = dialog
        dialog.finished.connect(lambda _r: self.reload(
            getattr(getattr(dialog, "profile", None), "patient_id", None) if select is None else select))
        dialog.open()
        return dialog

    def new_patient(self) -> QDialog:
        self.search_edit.clear()  # the new patient is shown, whatever was searched
        return self._open(PatientDialog(None, self.safety, self.folder, self,
                                        operator=self.operator_edit.text().strip()), None)

    def edit_patient(self) -> QDialog | None:
        entry = self.entries.get(self.patient_box.currentData())
        if entry is None or entry.profile is None:
            return None
        return self._open(PatientDialog(entry.profile, self.safety, self.folder, self, version=entry.version or None,
                                        operator=self.operator_edit.text().strip()), entry.patient_id)

    def edit_plan(self) -> QDialog | None:
        """The chosen patient's therapy plan (the Patients window's plan form), from the session's start: a new
        patient's plan is made here, before the first session."""
        from app.ui.plan_dialog import PlanDialog

        entry = self.entries.get(self.patient_box.currentData())
        if entry is None or entry.profile is None:
            return None
        return self._open(PlanDialog(entry.profile, self.safety, self.folder, parent=self,
                                     version=entry.version or None, operator=self.operator_edit.text().strip()),
                          entry.patient_id)

    def values(self) -> tuple[str, str, str]:
        """(patient_id, operator, note) as chosen."""
        return str(self.patient_box.currentData() or ""), self.operator_edit.text().strip(), self.note_edit.text()

    def accept(self) -> None:
        self._update()
        if self.problem.text():
            return
        QSettings().setValue("session/operator", self.operator_edit.text().strip())
        super().accept()
