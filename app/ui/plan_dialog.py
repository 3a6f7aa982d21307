"""The therapy plan form: a patient's ordered exercises, each value checked against the exercise's own ranges and,
when saved, against the patient's current caps, limits and electrode choices (#36). Opened from the Patients
window, the session-start dialog and the Exercises tab; its own module so that none of them imports another."""

from __future__ import annotations

import logging
import queue
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDialog,
    QDialogButtonBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QListWidget,
    QListWidgetItem,
    QPushButton,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from app.archive import station
from app.archive.api import ArchiveError, StaleRecord
from app.core.config import SafetyConfig
from app.therapy.exercises import Exercise, Parameter, load_library
from app.therapy.patients import (
    PatientError,
    PatientProfile,
    PlannedExercise,
    PlanProblem,
    plan_problems,
    prescription_problems,
)

log = logging.getLogger(__name__)

_ERROR_STYLE = "background: #ffd6d6;"
_PROBLEM_STYLE = "color: #b00020;"  # the form's message: what refuses the plan
_SAVING_STYLE = "color: #444; font-style: italic;"


def _value_text(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def step_text(step: PlannedExercise, exercise: Exercise | None, number: int) -> str:
    """"2. Trigger reaching — Movements 6, Speed 0.15 m/s" (the values that differ from the exercise's)."""
    if exercise is None:
        return f"{number}. {step.exercise} (not in the library)"
    changed = []
    for p in exercise.parameters:
        if p.name in step.params and step.params[p.name] != p.default:
            changed.append(f"{p.label} {_value_text(step.params[p.name])}{' ' + p.unit if p.unit else ''}")
    return f"{number}. {exercise.title}" + (f" — {', '.join(changed)}" if changed else " — its default values")


@dataclass(frozen=True)
class SaveOutcome:
    """What saving a plan came to: the record saved, or the problems that refuse it, or the concurrent save that
    refused it, or why it could not be saved (a sentence)."""

    saved: Any = None  # the archive's saved record (its profile and version)
    problems: list[PlanProblem] = field(default_factory=list)
    stale: StaleRecord | None = None
    error: str = ""


def save_plan(plan: list[PlannedExercise], profile: PatientProfile, version: int, safety: SafetyConfig | None,
              library: list[Exercise], *, operator: str = "", archive: Any = None,
              folder: Path | None = None) -> SaveOutcome:
    """``plan`` checked and saved as ``profile``'s plan, as of the record's ``version`` (no Qt: the plan form runs it
    on a thread of its own). The patient is read again first: a cap changed since the form opened counts, and the
    save keeps it; the plan is checked against this patient before anything moves (#36)."""
    problems = plan_problems(plan, library)
    try:  # the patient as saved now (a cap changed since this dialog opened counts; the save keeps it)
        record = station.read_record(profile.patient_id, safety, archive=archive, folder=folder)
    except (ArchiveError, OSError, PatientError, ValueError) as exc:
        return SaveOutcome(error=f"The plan is not saved: the patient's profile cannot be read ({exc})")
    current = record.profile if record is not None else profile
    # Checked against this patient before anything moves (#36): caps, limits and electrode choices.
    problems += prescription_problems(plan, current, safety, library)
    problems.sort(key=lambda p: p.step)
    if problems:
        return SaveOutcome(problems=problems)
    try:  # the plan alone, as of the version this form showed: nothing else of the record is written
        saved = station.save_profile(replace(current, therapy_plan=plan),
                                     expected_version=version if record is not None else None,
                                     operator=station.default_operator(operator),
                                     fields=["therapy_plan"] if record is not None else None,
                                     safety=safety, archive=archive, folder=folder, reason="therapy plan")
    except StaleRecord as exc:
        return SaveOutcome(stale=exc)
    except (ArchiveError, OSError, PatientError, ValueError) as exc:
        return SaveOutcome(error=f"The plan is not saved: {exc}")
    return SaveOutcome(saved=saved)


class PlanDialog(QDialog):
    """Edit ``profile``'s therapy plan: ordered steps, each an exercise of the library with its values."""

    def __init__(self, profile: PatientProfile, safety: SafetyConfig | None = None, folder: Path | None = None,
                 library: list[Exercise] | None = None, parent: QWidget | None = None, *, version: int | None = None,
                 operator: str = "", archive: Any = None) -> None:
        """``version``: the archive record's version ``profile`` was read at (None: read the record now, the plan
        shown is its plan). The plan is saved as of that version and alone (``fields=["therapy_plan"]``): a cap or
        an electrode choice saved meanwhile stays; a plan saved meanwhile by someone else refuses this one."""
        super().__init__(parent)
        self.safety = safety
        self.folder = folder
        self.archive = archive  # None: the station's (app.archive.station), or the YAML folder without one
        self.operator = operator
        if version is None:
            record = station.record_or_none(profile.patient_id, archive=archive, folder=folder)
            if record is not None:
                profile, version = record.profile, record.version
        self.profile = profile
        self.version = version or 0
        self.library = library if library is not None else load_library()[0]
        self.exercises = {e.ident: e for e in self.library}
        self.saved: PatientProfile | None = None
        # the plan being edited: the exercise, the values as typed (text for numbers), the note
        self.steps: list[dict[str, Any]] = [
            {"exercise": s.exercise, "values": dict(s.params), "note": s.note} for s in profile.therapy_plan]
        self.setWindowTitle(f"Therapy plan — {profile.patient_id}")
        self.editors: dict[str, QWidget] = {}
        self._current: int | None = None

        self.step_list = QListWidget()
        self.step_list.setAccessibleName("Plan steps")
        self.step_list.setWordWrap(True)
        self.step_list.currentRowChanged.connect(self._show_step)
        # The library, one double-click (or Enter) per step added (#36: a two-step plan in two actions).
        self.library_list = QListWidget()
        self.library_list.setAccessibleName("Exercises to add")
        self.library_list.setToolTip("Double-click an exercise (or press Enter) to add it to the plan")
        for e in self.library:
            item = QListWidgetItem(e.title)
            item.setData(Qt.ItemDataRole.UserRole, e.ident)
            item.setToolTip(f"{e.title}\n\n{e.description}")
            self.library_list.addItem(item)
        self.library_list.setCurrentRow(0)
        self.library_list.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.library_list.setTextElideMode(Qt.TextElideMode.ElideRight)  # the whole title in the tooltip
        rows = max(1, min(len(self.library), 5))
        self.library_list.setMaximumHeight(rows * (self.library_list.fontMetrics().lineSpacing() + 6) + 8)
        self.library_list.itemActivated.connect(lambda item: self.add_step(item.data(Qt.ItemDataRole.UserRole)))
        self.add_button = QPushButton("&Add to plan")
        self.add_button.clicked.connect(self._add_selected)
        self.remove_button = QPushButton("&Remove")
        self.remove_button.clicked.connect(self.remove_step)
        self.up_button = QPushButton("Move &up")
        self.up_button.clicked.connect(lambda: self.move_step(-1))
        self.down_button = QPushButton("Move &down")
        self.down_button.clicked.connect(lambda: self.move_step(1))
        add_row = QHBoxLayout()
        add_row.addWidget(self.library_list, 1)
        add_row.addWidget(self.add_button, 0, Qt.AlignmentFlag.AlignTop)
        order_row = QHBoxLayout()
        for b in (self.up_button, self.down_button, self.remove_button):
            order_row.addWidget(b)
        left = QVBoxLayout()
        left.addWidget(QLabel("<b>Steps, in the order the Exercises tab offers them</b>"))
        left.addWidget(self.step_list, 1)
        left.addLayout(order_row)
        left.addWidget(QLabel("Add an exercise of the library:"))
        left.addLayout(add_row)

        self.step_title = QLabel("")
        self.step_title.setWordWrap(True)
        self.step_title.setTextFormat(Qt.TextFormat.PlainText)
        self.step_title.setStyleSheet("font-weight: bold;")
        self.step_box = QGroupBox("Values")
        self.step_form = QFormLayout(self.step_box)
        self.description = QLabel("")
        self.description.setWordWrap(True)
        self.description.setStyleSheet("color: #444;")
        right = QVBoxLayout()
        right.addWidget(self.step_title)
        right.addWidget(self.step_box)
        right.addWidget(self.description)
        right.addStretch(1)

        self.error_label = QLabel("")
        self.error_label.setWordWrap(True)
        self.error_label.setStyleSheet(_PROBLEM_STYLE)
        self.error_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.error_label.setAccessibleName("Plan problems")
        self.buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Save | QDialogButtonBox.StandardButton.Cancel)
        self.buttons.accepted.connect(self.accept)
        self.buttons.rejected.connect(self.reject)
        # Offered when the plan was saved by someone else since this form opened (StaleRecord).
        self.reload_button = self.buttons.addButton("&Reload", QDialogButtonBox.ButtonRole.ResetRole)
        self.reload_button.setToolTip("Show the plan as it is saved now (the steps here are replaced)")
        self.reload_button.clicked.connect(self.reload)
        self.reload_button.setVisible(False)

        left_w, right_w = QWidget(), QWidget()
        left_w.setLayout(left)
        right_w.setLayout(right)
        split = QSplitter()
        self.editing = split  # held while a save runs: what is saved is what is shown
        split.addWidget(left_w)
        split.addWidget(right_w)
        split.setStretchFactor(0, 1)
        split.setStretchFactor(1, 1)
        lay = QVBoxLayout(self)
        lay.addWidget(split, 1)
        lay.addWidget(self.error_label)
        lay.addWidget(self.buttons)
        self.resize(960, 560)
        # Saving runs on a thread of its own (accept); its outcome is queued with its generation and taken here
        # on the window's thread, the pattern of the session-start dialog's patient list.
        self._saving = False
        self._focus_before: QWidget | None = None
        self._generation = 0
        self._outcomes: queue.SimpleQueue[tuple[int, SaveOutcome]] = queue.SimpleQueue()
        self._pump = QTimer(self)
        self._pump.setInterval(10)
        self._pump.timeout.connect(self._take)
        self._refresh_list(0 if self.steps else None)

    # ------------------------------------------------------------------ the list
    def _refresh_list(self, select: int | None) -> None:
        self.step_list.blockSignals(True)
        self.step_list.clear()
        for k, step in enumerate(self.steps):
            text = step_text(self._planned(step), self.exercises.get(step["exercise"]), k + 1)
            self.step_list.addItem(text)
            self.step_list.item(k).setToolTip(text)  # whole, however narrow the list
        self.step_list.blockSignals(False)
        self._current = None
        if select is not None and self.steps:
            self.step_list.setCurrentRow(max(0, min(select, len(self.steps) - 1)))
        else:
            self._show_step(-1)
        self._sync_buttons()

    def _sync_buttons(self) -> None:
        row = self.step_list.currentRow()
        self.remove_button.setEnabled(row >= 0)
        self.up_button.setEnabled(row > 0)
        self.down_button.setEnabled(0 <= row < len(self.steps) - 1)

    def _add_selected(self) -> None:
        item = self.library_list.currentItem()
        if item is not None:
            self.add_step(item.data(Qt.ItemDataRole.UserRole))

    def add_step(self, ident: str) -> None:
        exercise = self.exercises[ident]
        self.steps.append({"exercise": ident, "values": exercise.defaults(), "note": ""})
        self._refresh_list(len(self.steps) - 1)

    def remove_step(self) -> None:
        row = self.step_list.currentRow()
        if row >= 0:
            del self.steps[row]
            self._refresh_list(min(row, len(self.steps) - 1) if self.steps else None)

    def move_step(self, delta: int) -> None:
        row = self.step_list.currentRow()
        other = row + delta
        if row < 0 or not 0 <= other < len(self.steps):
            return
        self.steps[row], self.steps[other] = self.steps[other], self.steps[row]
        self._refresh_list(other)

    # ------------------------------------------------------------------ one step's form
    def _show_step(self, row: int) -> None:
        while self.step_form.rowCount():
            self.step_form.removeRow(0)
        self.editors = {}
        self._current = row if 0 <= row < len(self.steps) else None
        self._sync_buttons()
        if self._current is None:
            self.step_title.setText("No step selected")
            self.description.setText("Add an exercise of the library to the plan.")
            return
        step = self.steps[row]
        exercise = self.exercises.get(step["exercise"])
        if exercise is None:
            self.step_title.setText(f"Step {row + 1}: {step['exercise']}")
            self.description.setText("This exercise is not in the library any more: remove the step.")
            return
        self.step_title.setText(f"Step {row + 1}: {exercise.title}")
        self.description.setText(exercise.description)
        hint_width = max((self.fontMetrics().horizontalAdvance(p.describe_range()) for p in exercise.parameters),
                         default=0) + 8
        for p in exercise.parameters:
            editor = self._editor(p, step["values"].get(p.name, p.default))
            self.editors[p.name] = editor
            hint = QLabel(p.describe_range())
            hint.setStyleSheet("color: #555;")
            hint.setMinimumWidth(hint_width)  # the fields line up whatever their ranges say
            row_w = QHBoxLayout()
            row_w.addWidget(editor, 1)
            row_w.addWidget(hint)
            self.step_form.addRow(p.label + (f" [{p.unit}]" if p.unit else ""), row_w)
        note = QLineEdit(step.get("note", ""))
        note.setAccessibleName("Step note")
        note.textChanged.connect(lambda text: self._set_note(text))
        self.editors["__note__"] = note
        self.step_form.addRow("Note", note)

    def _editor(self, p: Parameter, value: Any) -> QWidget:
        if p.type == "bool":
            box = QCheckBox()
            box.setChecked(bool(p.check(value)[0]) if not p.check(value)[1] else bool(p.default))
            box.setAccessibleName(p.label)
            box.toggled.connect(lambda on, name=p.name: self._set_value(name, on))
            return box
        if p.type == "choice":
            combo = QComboBox()
            combo.addItems(list(p.options))
            combo.setCurrentText(str(value))
            combo.setAccessibleName(p.label)
            combo.currentTextChanged.connect(lambda text, name=p.name: self._set_value(name, text))
            return combo
        edit = QLineEdit(_value_text(value))
        edit.setAccessibleName(p.label)
        edit.setToolTip(p.help)
        edit.textChanged.connect(lambda text, name=p.name: self._set_value(name, text))
        return edit

    def _set_note(self, text: str) -> None:
        if self._current is not None:
            self.steps[self._current]["note"] = text

    def _set_value(self, name: str, value: Any) -> None:
        """Keep what was typed and check it at once against the exercise's range (said next to the form)."""
        if self._current is None:
            return
        step = self.steps[self._current]
        step["values"][name] = value
        exercise = self.exercises[step["exercise"]]
        p = exercise.parameter(name)
        _, why = p.check(value)
        editor = self.editors.get(name)
        if editor is not None:
            editor.setStyleSheet(_ERROR_STYLE if why else "")
        self.error_label.setText(f"Step {self._current + 1}, {exercise.title} — {p.label}: {why}" if why else "")
        item = self.step_list.item(self._current)
        if item is not None and not why:
            item.setText(step_text(self._planned(step), exercise, self._current + 1))
            item.setToolTip(item.text())

    # ------------------------------------------------------------------ saving
    def _planned(self, step: dict[str, Any]) -> PlannedExercise:
        """The step with its values converted where they are valid (typed text otherwise, for the checks)."""
        exercise = self.exercises.get(step["exercise"])
        params = dict(step["values"])
        if exercise is not None:
            for p in exercise.parameters:
                if p.name in params:
                    value, why = p.check(params[p.name])
                    if not why:
                        params[p.name] = value
        return PlannedExercise(step["exercise"], params, step.get("note", ""))

    def plan(self) -> list[PlannedExercise]:
        return [self._planned(s) for s in self.steps]

    @property
    def saving(self) -> bool:
        """A save runs (on its thread): the form is held, Save and Cancel wait for its answer."""
        return self._saving

    def accept(self) -> None:
        """Save the plan: checked and written on a thread of its own (the patient is read again, every step checked
        against the exercise's ranges and against the patient's caps, limits and electrodes, the FES profiles read,
        then the record written: tens of ms the window's thread must not spend), the answer taken back here by
        :meth:`_take`. Meanwhile the form says so and is held: what is saved is what is shown, nothing twice."""
        if self._saving:
            return
        plan = self.plan()  # the values as shown now (converted here: what the thread checks is what is seen)
        self._focus_before = self.focusWidget()  # given back after a refusal that names no field
        self._generation += 1
        self._set_saving(True)
        # Drawn now, and the thread started once the click's own events are handled: the saving thread shares the
        # interpreter, and every event of the window's then waits for it to yield (bench/bench_plan_save.py: the
        # window's longest stall per save, quiet, median 11 ms started at once, 5.5 ms so).
        self.repaint()
        generation, profile, version = self._generation, self.profile, self.version
        QTimer.singleShot(0, self, lambda: self._start_save(generation, plan, profile, version))

    def _start_save(self, generation: int, plan: list[PlannedExercise], profile: PatientProfile,
                    version: int) -> None:
        threading.Thread(target=self._save, args=(generation, plan, profile, version), name="plan-save",
                         daemon=True).start()
        self._pump.start()

    def reject(self) -> None:
        """Cancel and Escape wait for a save that runs: it may already be written, and a form closed as cancelled
        over a saved plan would keep it from the running session (which hears only an accepted form)."""
        if self._saving:
            return
        super().reject()

    def _set_saving(self, on: bool) -> None:
        self._saving = on
        self.editing.setEnabled(not on)
        for button in self.buttons.buttons():
            button.setEnabled(not on)
        if on:
            self.error_label.setStyleSheet(_SAVING_STYLE)
            self.error_label.setText("Saving the plan… (Cancel waits until the archive has answered)")
        else:
            self.error_label.setStyleSheet(_PROBLEM_STYLE)
            self.error_label.setText("")

    def _save(self, generation: int, plan: list[PlannedExercise], profile: PatientProfile, version: int) -> None:
        """The saving thread: the outcome queued with its generation, whatever happens (never a form left saving)."""
        try:
            outcome = save_plan(plan, profile, version, self.safety, self.library, operator=self.operator,
                                archive=self.archive, folder=self.folder)
        except Exception as exc:  # said in the form: never a traceback, never a form left saving
            log.exception("saving the therapy plan failed")
            outcome = SaveOutcome(error=f"The plan is not saved: {exc}")
        self._outcomes.put((generation, outcome))

    def _take(self) -> None:
        while True:
            try:
                generation, outcome = self._outcomes.get_nowait()
            except queue.Empty:
                return
            if generation == self._generation:
                break
        self._pump.stop()
        self._set_saving(False)
        self._finish(outcome)

    def _finish(self, outcome: SaveOutcome) -> None:
        """The save's answer, on the window's thread: as the save said it before it ran on its own thread."""
        if outcome.problems:
            problems = outcome.problems
            self.error_label.setText("The plan is not saved:\n" + "\n".join(str(p) for p in problems))
            first = problems[0]
            self.step_list.setCurrentRow(first.step - 1)
            editor = self.editors.get(first.parameter)
            if editor is not None:
                editor.setStyleSheet(_ERROR_STYLE)
                editor.setFocus()
            # _show_step cleared the message's neighbour: say it again
            self.error_label.setText("The plan is not saved:\n" + "\n".join(str(p) for p in problems))
            return
        if outcome.stale is not None:
            exc = outcome.stale
            self.error_label.setText(f"The plan is not saved: the plan was changed by {exc.changed_by or 'someone'} "
                                     f"on station {exc.changed_station or '(unknown)'} at {exc.changed_at}. Reload "
                                     "shows their plan (the steps here are then replaced); Cancel keeps theirs.")
            self.reload_button.setVisible(True)
            self.reload_button.setFocus()
            self.saved = None
            return
        if outcome.error or outcome.saved is None:
            self.error_label.setText(outcome.error or "The plan is not saved.")
            self.saved = None
            if self._focus_before is not None:
                self._focus_before.setFocus()
            return
        saved = outcome.saved
        self.profile, self.version = saved.profile, saved.version
        self.saved = saved.profile
        super().accept()

    def reload(self) -> bool:
        """The plan as the record holds it now (after a refused save): its steps replace the form's."""
        try:
            record = station.read_record(self.profile.patient_id, archive=self.archive, folder=self.folder)
        except (ArchiveError, OSError, PatientError, ValueError) as exc:
            self.error_label.setText(f"The patient cannot be read again: {exc}")
            return False
        if record is None:
            return False
        self.profile, self.version = record.profile, record.version
        self.steps = [{"exercise": s.exercise, "values": dict(s.params), "note": s.note}
                      for s in record.profile.therapy_plan]
        self._refresh_list(0 if self.steps else None)
        self.reload_button.setVisible(False)
        who = f" by {record.changed_by} on {record.changed_station} at {record.changed_at}" if record.changed_by else ""
        self.error_label.setText(f"The plan as saved{who} is shown. Change it again if needed, then Save.")
        return True
