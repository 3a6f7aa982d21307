"""The Exercises tab: therapy without code. The library (resources/exercises) with descriptions, a form per
exercise drawn from its declared parameters, validation (a value out of range is refused with the reason and
nothing starts), Start in one click on the window's script runner, "repetition 3 of 8" with the elapsed time,
pause / resume / stop, and the exercise's summary when it ends. A patient's therapy plan, when the session's
profile holds one, is offered first, in order.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QKeySequence, QShortcut
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QListWidget,
    QListWidgetItem,
    QProgressBar,
    QPushButton,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from app.core.progress import ProgressState
from app.therapy.exercises import Exercise, Parameter, Validation, load_library, start_exercise, validate
from app.ui.fes_conflict import fes_conflict_text, resolve_fes_conflict
from app.ui.qt_bus import shared_qt_bus

log = logging.getLogger(__name__)

ERROR_STYLE = "color: #c62828;"
SUMMARY_DELAY_MS = 1200  # the recorder writes the streams at least every second: wait for the last samples


class ParameterField:
    """One row of the form: the editor, its unit and range, and the reason when its value is refused."""

    def __init__(self, param: Parameter) -> None:
        self.param = param
        self.error = QLabel("")
        self.error.setStyleSheet(ERROR_STYLE)
        self.error.setWordWrap(True)
        self.error.hide()
        self.widget: QWidget
        if param.type == "bool":
            self.widget = QCheckBox()
        elif param.type == "choice":
            box = QComboBox()
            box.addItems(list(param.options))
            self.widget = box
        else:
            edit = QLineEdit()
            edit.setMaximumWidth(110)
            edit.setAlignment(Qt.AlignmentFlag.AlignRight)
            self.widget = edit
        self.widget.setToolTip(param.help)
        self.widget.setAccessibleName(param.label)
        self.widget.setAccessibleDescription(f"{param.help} ({param.describe_range()})")
        self.hint = QLabel(f"{param.unit}   <span style='color:#777'>{param.describe_range()}</span>"
                           if param.type not in ("bool", "choice") else "")
        self.row = QWidget()
        lay = QHBoxLayout(self.row)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.widget)
        lay.addWidget(self.hint, 1)
        self.set(param.default)

    def set(self, value: Any) -> None:
        w = self.widget
        if isinstance(w, QCheckBox):
            w.setChecked(bool(value))
        elif isinstance(w, QComboBox):
            w.setCurrentText(str(value))
        elif isinstance(w, QLineEdit):
            w.setText(f"{value:g}" if isinstance(value, float) else str(value))

    def value(self) -> Any:
        w = self.widget
        if isinstance(w, QCheckBox):
            return w.isChecked()
        if isinstance(w, QComboBox):
            return w.currentText()
        return w.text()  # type: ignore[union-attr]

    def show_error(self, why: str) -> None:
        self.error.setText(why)
        self.error.setVisible(bool(why))
        self.widget.setStyleSheet("QLineEdit { border: 2px solid #c62828; }" if why else "")


class ExercisesPanel(QWidget):
    def __init__(self, manager: Any, runner: Any = None) -> None:
        super().__init__()
        self.manager = manager
        self._runner = runner
        self.library, problems = load_library()
        self.exercise: Exercise | None = None
        self.fields: dict[str, ParameterField] = {}
        self._plan_step: int | None = None  # the plan step the running exercise came from
        self._started_mono: float | None = None
        self._was_running = False
        self.summary_dialog: QWidget | None = None
        self.last_validation: Validation | None = None

        # ---- left: the therapy plan and the library
        self.plan_box = QGroupBox("Therapy plan")
        self.plan_list = QListWidget()
        self.plan_list.setAccessibleName("Therapy plan")
        self.plan_list.setWordWrap(True)
        self.plan_list.currentRowChanged.connect(self._plan_selected)
        QVBoxLayout(self.plan_box).addWidget(self.plan_list)
        self.exercise_list = QListWidget()
        self.exercise_list.setAccessibleName("Exercises")
        self.exercise_list.setWordWrap(True)
        for e in self.library:
            item = QListWidgetItem(e.title)
            item.setToolTip(f"{e.title}\n\n{e.description}")  # the whole title too: the list may elide it
            self.exercise_list.addItem(item)
        self.exercise_list.currentRowChanged.connect(self._exercise_selected)
        library_box = QGroupBox("Exercises")
        lib_lay = QVBoxLayout(library_box)
        lib_lay.addWidget(self.exercise_list)
        if problems:
            bad = QLabel("Not loaded:\n" + "\n".join(problems))
            bad.setStyleSheet(ERROR_STYLE)
            bad.setWordWrap(True)
            lib_lay.addWidget(bad)
        self._build_session_box()
        left = QWidget()
        left_lay = QVBoxLayout(left)
        left_lay.setContentsMargins(0, 0, 0, 0)
        left_lay.addWidget(self.session_box)
        left_lay.addWidget(self.plan_box)
        left_lay.addWidget(library_box, 1)

        # ---- right: description, form, controls, progress
        self.title = QLabel()
        self.title.setTextFormat(Qt.TextFormat.RichText)
        self.description = QLabel()
        self.description.setWordWrap(True)
        self.form_box = QGroupBox("Parameters")
        self.form = QFormLayout(self.form_box)
        self.form.setFieldGrowthPolicy(QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)

        self.start_button = QPushButton("▶ &Start exercise")
        self.start_button.setDefault(True)
        # Not connected straight to start(): clicked(bool) would arrive as its `source` (recorded as False).
        self.start_button.clicked.connect(lambda _checked=False: self.start())
        self.defaults_button = QPushButton("&Defaults")
        self.defaults_button.clicked.connect(self.reset_defaults)
        self.pause_button = QPushButton("&Pause")
        self.pause_button.clicked.connect(self.toggle_pause)
        self.stop_button = QPushButton("■ S&top")
        self.stop_button.clicked.connect(self.stop)
        controls = QHBoxLayout()
        for b in (self.start_button, self.pause_button, self.stop_button, self.defaults_button):
            controls.addWidget(b)
        controls.addStretch(1)
        QShortcut(QKeySequence("Ctrl+Return"), self, activated=self.start)

        self.message = QLabel("")
        self.message.setWordWrap(True)
        # Why Start is disabled (a STOP latched: Recover first), on screen and not only in a tooltip.
        self.hold_label = QLabel("")
        self.hold_label.setObjectName("startHold")
        self.hold_label.setWordWrap(True)
        self.hold_label.setStyleSheet(ERROR_STYLE)
        self.hold_label.setVisible(False)
        self.repetition_label = QLabel("")
        self.repetition_label.setAccessibleName("Repetition")
        font = self.repetition_label.font()
        font.setPointSizeF(font.pointSizeF() * 1.4)
        font.setBold(True)
        self.repetition_label.setFont(font)
        # The run's state in words ("Trigger reaching — waiting for the grip", "… — stopped: emergency stop"),
        # from the run itself (app/core/runs.py), whichever tab started it.
        self.state_label = QLabel("")
        self.state_label.setObjectName("runState")
        self.state_label.setAccessibleName("Run state")
        self.state_label.setWordWrap(True)
        self.elapsed_label = QLabel("")
        self.progress_bar = QProgressBar()
        self.progress_bar.setTextVisible(False)
        self.progress_bar.setMaximumHeight(12)
        self.progress_text = QLabel("")
        self.progress_text.setWordWrap(True)
        status_box = QGroupBox("Progress")
        status = QVBoxLayout(status_box)
        row = QHBoxLayout()
        row.addWidget(self.repetition_label, 1)
        row.addWidget(self.elapsed_label)
        status.addLayout(row)
        status.addWidget(self.state_label)
        status.addWidget(self.progress_bar)
        status.addWidget(self.progress_text)

        right = QWidget()
        right_lay = QVBoxLayout(right)
        right_lay.setContentsMargins(4, 0, 0, 0)
        right_lay.addWidget(self.title)
        # Start / Pause / Stop and the progress first: at 1366×768 they stay on screen while the
        # description and the form below them scroll (issue #19: primary controls without scrolling).
        right_lay.addLayout(controls)
        right_lay.addWidget(self.hold_label)
        right_lay.addWidget(self.message)
        right_lay.addWidget(status_box)
        right_lay.addWidget(self.description)
        right_lay.addWidget(self.form_box)
        right_lay.addStretch(1)

        split = QSplitter()
        split.addWidget(left)
        split.addWidget(right)
        split.setStretchFactor(1, 2)
        split.setSizes([250, 520])
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.addWidget(split)

        self.timer = QTimer(self)
        self.timer.setInterval(250)
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        progress = getattr(manager, "progress", None)
        if progress is not None and getattr(manager, "bus", None) is not None:
            # its changes come on the script's thread: the window's adapter brings them here
            adapter = shared_qt_bus(manager.bus)
            adapter.watch_progress(progress)
            adapter.progress_changed.connect(self._progress_changed)
        recorder = getattr(manager, "recorder", None)
        self._session_folder: Path | None = Path(recorder.folder) if getattr(recorder, "folder", None) else None
        self._exercised_in_session = False  # an exercise was started from here during this session
        if hasattr(manager, "session_changed"):
            manager.session_changed.connect(self._session_changed)
        if hasattr(manager, "profile_changed"):  # the plan or the caps changed in the Patients window
            manager.profile_changed.connect(lambda _p: self._profile_changed())
        # The summary of a run a STOP ended waits until the recovery is done: it never covers the banner's Recover
        # (issue #36: it opened ~2 s after each STOP and took the first click meant for Recover).
        self._pending_summary: tuple[Path, float | None, float, str, str] | None = None
        # ... but it is read meanwhile: the worker runs at a low priority, and on a busy PC reading the session
        # after the recovery made the summary come 5-10 s after it (the test's two `yes`).
        self._prefetch: _Prefetch | None = None
        self._summary_since: float | None = None  # a continuation's summary starts at the interrupted run's
        from app.ui.recovery import recovery_events

        recovery_events().finished.connect(self._recovery_finished)
        self.load_plan()
        if self.library and self.exercise is None:
            self.exercise_list.setCurrentRow(0)
        self._sync_buttons()

    # ------------------------------------------------------------------ a session from here (no session running)
    def _build_session_box(self) -> None:
        """No session runs: the patients (most recently changed first, with their names and plans), the operator
        (typed, or the last one taken with a click: never pre-filled) and one button that starts the session and
        the plan's first exercise. A returning patient: patient, operator, Start — three actions (#36)."""
        self.session_box = QGroupBox("Start a session")
        self.patient_list = QListWidget()
        self.patient_list.setAccessibleName("Patients")
        self.patient_list.setWordWrap(True)  # the id and the name, whole (the column is narrow at 1366×768)
        self.patient_list.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.patient_list.currentRowChanged.connect(lambda _r: self._sync_session_box())
        self.patient_list.setMaximumHeight(4 * (self.patient_list.fontMetrics().lineSpacing() + 6) + 8)
        self.session_plan = QLabel("")  # what the button starts: the chosen patient's plan, in words
        self.session_plan.setWordWrap(True)
        self.session_plan.setObjectName("sessionPlan")
        self.new_patient_button = QPushButton("&New patient…")
        self.new_patient_button.clicked.connect(self.new_patient)
        self.operator_edit = QLineEdit()
        self.operator_edit.setAccessibleName("Operator")
        self.operator_edit.setPlaceholderText("Operator: your name or staff ID")
        self.operator_edit.textChanged.connect(lambda _t: self._sync_session_box())
        self.last_operator_button = QPushButton("")
        self.last_operator_button.setToolTip("The operator of the last session on this computer: click only if that "
                                             "is you")
        self.last_operator_button.clicked.connect(
            lambda: self.operator_edit.setText(self.last_operator_button.property("operator") or ""))
        self.session_button = QPushButton("▶ Start session")
        self.session_button.clicked.connect(lambda _checked=False: self.start_session_here())
        self.session_problem = QLabel("")
        self.session_problem.setWordWrap(True)
        self.session_problem.setStyleSheet(ERROR_STYLE)
        lay = QVBoxLayout(self.session_box)
        lay.setContentsMargins(4, 4, 4, 4)
        lay.setSpacing(3)
        lay.addWidget(self.patient_list)
        lay.addWidget(self.session_plan)
        op_row = QHBoxLayout()
        op_row.addWidget(self.operator_edit, 1)
        op_row.addWidget(self.last_operator_button)
        lay.addLayout(op_row)
        row = QHBoxLayout()
        row.addWidget(self.new_patient_button)
        row.addWidget(self.session_button, 1)
        lay.addLayout(row)
        lay.addWidget(self.session_problem)
        self.reload_patients()

    def _session_possible(self) -> bool:
        return getattr(self.manager, "recorder", None) is None and hasattr(self.manager, "start_session")

    def reload_patients(self, select: str | None = None) -> None:
        from PySide6.QtCore import QSettings

        from app.therapy.patients import list_patients

        possible = self._session_possible()
        self.session_box.setVisible(possible)
        if not possible:
            return
        current = select or self.selected_patient()
        try:
            safety = getattr(getattr(self.manager, "config", None), "safety", None)
            entries = [e for e in list_patients(safety=safety) if e.profile is not None]
        except OSError:
            entries = []
        entries.sort(key=lambda e: e.profile.updated or e.profile.created or "", reverse=True)
        self._patient_plans = {e.patient_id: list(e.profile.therapy_plan) for e in entries}
        self.patient_list.blockSignals(True)
        self.patient_list.clear()
        for e in entries:
            p = e.profile
            plan = f", plan of {len(p.therapy_plan)}" if p.therapy_plan else ""
            item = QListWidgetItem(f"{p.patient_id} — {p.full_name}{plan}" if p.full_name else f"{p.patient_id}{plan}")
            item.setData(Qt.ItemDataRole.UserRole, p.patient_id)
            self.patient_list.addItem(item)
        ids = [e.patient_id for e in entries]
        self.patient_list.setCurrentRow(ids.index(current) if current in ids else -1)
        self.patient_list.blockSignals(False)
        last = str(QSettings().value("session/operator", "") or "")
        self.last_operator_button.setProperty("operator", last)
        self.last_operator_button.setText(f"I am {last}")
        self.last_operator_button.setVisible(bool(last))
        self._sync_session_box()

    def selected_patient(self) -> str | None:
        item = self.patient_list.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item is not None else None

    def _sync_session_box(self) -> None:
        pid = self.selected_patient()
        operator = self.operator_edit.text().strip()
        plan = getattr(self, "_patient_plans", {}).get(pid, []) if pid else []
        titles = [next((e.title for e in self.library if e.ident == step.exercise), step.exercise) for step in plan]
        self.session_button.setText("▶ Start session and step 1" if titles else "▶ Start session")
        self.session_plan.setText("Plan: " + "; ".join(f"{k + 1}. {t}" for k, t in enumerate(titles)) if titles
                                  else ("No therapy plan: the session starts, then choose an exercise." if pid else ""))
        self.session_plan.setVisible(bool(pid))
        problem = "" if pid else "Choose the patient (or New patient…)."
        if pid and not operator:
            problem = "Enter the operator's name (it signs the session's record)."
        self.session_button.setEnabled(not problem)
        self.session_button.setToolTip(problem or "Starts the session's recording; with a plan, its first exercise")
        self.session_problem.setText("" if not (pid or operator) else problem)

    def start_session_here(self) -> bool:
        """Start the session of the chosen patient with the operator given, then the plan's first exercise (the
        button says which). False with the reason shown when nothing started."""
        from PySide6.QtCore import QSettings

        pid, operator = self.selected_patient(), self.operator_edit.text().strip()
        if not pid or not operator or not self._session_possible():
            self._sync_session_box()
            return False
        try:
            self.manager.start_session(pid, operator)
        except (ValueError, RuntimeError, OSError) as exc:
            text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            self.session_problem.setText(f"Session not started: {text}")
            return False
        QSettings().setValue("session/operator", operator)
        self.operator_edit.clear()
        if self.plan():  # the session's start loaded the plan: its first step is selected
            self.plan_list.setCurrentRow(0)
            return self.start()
        return True

    def new_patient(self) -> QWidget:
        """A new patient's profile, then at once their therapy plan; back here with them chosen."""
        from app.ui.patient_dialog import PatientDialog
        from app.ui.plan_dialog import PlanDialog

        safety = getattr(getattr(self.manager, "config", None), "safety", None)
        dialog = PatientDialog(None, safety, None, self)
        self.patient_dialog = dialog

        def saved(result: int) -> None:
            profile = getattr(dialog, "profile", None)
            if result != 1 or profile is None:
                return
            self.reload_patients(profile.patient_id)
            plan = PlanDialog(profile, safety, parent=self)
            self.plan_dialog = plan
            plan.finished.connect(lambda _r: self.reload_patients(profile.patient_id))
            plan.open()

        dialog.finished.connect(saved)
        dialog.open()
        return dialog

    def _session_changed(self, folder: Path | None) -> None:
        """At the end of a session in which exercises were run from this tab, its whole summary is shown."""
        ended, exercised = self._session_folder, self._exercised_in_session
        self._session_folder = Path(folder) if folder is not None else None
        self._exercised_in_session = False
        self.reload_patients()
        self.load_plan()
        if folder is None and ended is not None and exercised:
            QTimer.singleShot(0, self, lambda: show_when_unblocked(
                self, lambda: self.show_summary(ended, None, None, f"Session {ended.name}")))

    # ------------------------------------------------------------------ the runner (one per window)
    @property
    def runner(self) -> Any:
        """The window's script runner (ScriptConsole.runner); a private one when there is no console."""
        if self._runner is None:
            from app.ui.script_console import ScriptConsole

            console = self.window().findChild(ScriptConsole) if self.window() is not self else None
            if console is not None:
                self._runner = console.runner
            else:
                from app.scripting.runner import ScriptRunner

                self._runner = ScriptRunner(self.manager)
        return self._runner

    # ------------------------------------------------------------------ plan and library
    def plan(self) -> list[Any]:
        profile = getattr(self.manager, "patient_profile", None)
        return list(getattr(profile, "therapy_plan", None) or [])

    def _profile_changed(self) -> None:
        if self._runner is None or not self._runner.running:
            row = self.plan_list.currentRow()
            self.load_plan()
            if 0 <= row < self.plan_list.count():
                self.plan_list.setCurrentRow(row)

    def step_problem(self, step: Any) -> str:
        """Why a plan step would not start now (the patient's limits, caps and electrodes in force): "" if it would."""
        from app.therapy.exercises import run_problems

        exercise = next((e for e in self.library if e.ident == step.exercise), None)
        if exercise is None:
            return f"there is no exercise '{step.exercise}' in the library"
        checked = validate(exercise, step.params)
        if not checked.ok:
            return checked.message(exercise)
        problems = run_problems(self.manager, exercise, checked.params)
        return "; ".join(f"{exercise.parameter(n).label}: {why}" for n, why in problems.items())

    def load_plan(self) -> None:
        plan = self.plan()
        self.plan_list.blockSignals(True)
        self.plan_list.clear()
        for k, step in enumerate(plan):
            title = next((e.title for e in self.library if e.ident == step.exercise), f"{step.exercise} (unknown)")
            values = ", ".join(f"{n}={v}" for n, v in step.params.items())
            problem = self.step_problem(step)  # checked against the patient before anything moves (#36)
            item = QListWidgetItem(f"{k + 1}. {title}" + (" — cannot start" if problem else ""))
            item.setToolTip(values + (f"\n{step.note}" if step.note else "") + (f"\nCannot start: {problem}"
                                                                                  if problem else ""))
            if problem:
                from PySide6.QtGui import QBrush, QColor

                item.setForeground(QBrush(QColor("#c62828")))
            self.plan_list.addItem(item)
        self.plan_list.blockSignals(False)
        self.plan_box.setVisible(bool(plan))
        if plan:
            self.plan_list.setCurrentRow(0)

    def _plan_selected(self, row: int) -> None:
        plan = self.plan()
        if not 0 <= row < len(plan):
            return
        step = plan[row]
        for k, e in enumerate(self.library):
            if e.ident == step.exercise:
                self.exercise_list.blockSignals(True)
                self.exercise_list.setCurrentRow(k)
                self.exercise_list.blockSignals(False)
                self.show_exercise(e, step.params)
                self._plan_step = row
                problem = self.step_problem(step)
                if problem:  # said where it is chosen, not only in the list's tooltip
                    self._say(f"Step {row + 1} cannot start: {problem}", error=True)
                return
        self.message.setText(f"Plan step {row + 1}: no exercise '{step.exercise}' in the library.")
        self.message.setStyleSheet(ERROR_STYLE)

    def _exercise_selected(self, row: int) -> None:
        if 0 <= row < len(self.library):
            self._plan_step = None
            self.plan_list.clearSelection()
            self.show_exercise(self.library[row])

    def select(self, ident: str) -> None:
        for k, e in enumerate(self.library):
            if e.ident == ident:
                self.exercise_list.setCurrentRow(k)
                return
        raise KeyError(ident)

    def show_exercise(self, exercise: Exercise, values: dict[str, Any] | None = None) -> None:
        self.exercise = exercise
        self.title.setText(f"<h3>{exercise.title}</h3>")
        self.description.setText(exercise.description)
        while self.form.rowCount():
            self.form.removeRow(0)
        self.fields = {}
        for p in exercise.parameters:
            f = ParameterField(p)
            if values and p.name in values:
                f.set(values[p.name])
            label = QLabel(f"&{p.label}")
            label.setBuddy(f.widget)
            label.setToolTip(p.help)
            self.form.addRow(label, f.row)
            self.form.addRow("", f.error)
            self.fields[p.name] = f
        self.message.setText("")
        self._sync_buttons()

    def reset_defaults(self) -> None:
        for f in self.fields.values():
            f.set(f.param.default)
            f.show_error("")
        self.message.setText("")

    def values(self) -> dict[str, Any]:
        return {name: f.value() for name, f in self.fields.items()}

    def set_value(self, name: str, value: Any) -> None:
        self.fields[name].set(value)

    # ------------------------------------------------------------------ start / pause / stop
    def hold_reason(self) -> str:
        """Why nothing may start now ("" when it may): a latched e-stop or an open STOP alarm (Recover first)."""
        from app.core.ownership import start_problem

        return start_problem(self.manager, ())

    def start(self, source: str = "exercises_tab", restart_of: str | None = None,
              continues: str | None = None) -> bool:
        """Validate the form and start the exercise; False (with the reasons shown) when nothing started.
        ``source`` and ``restart_of`` go into the run's record (Recover: "recover" and the interrupted run;
        ``continues``: the interrupted run whose remaining repetitions this one does)."""
        if self.exercise is None:
            return False
        hold = self.hold_reason()
        if hold:  # nothing recorded: no refused run (#36)
            self._say(f"Not started: {hold}.", error=True)
            return False
        checked = validate(self.exercise, self.values())
        self.last_validation = checked
        for name, f in self.fields.items():
            f.show_error(checked.errors.get(name, ""))
        if not checked.ok:
            self._say("Not started: " + checked.message(self.exercise), error=True)
            return False
        runner = self.runner
        if runner.running:
            self._say("Not started: a script is running. Stop it first.", error=True)
            return False
        if not resolve_fes_conflict(self, self.manager, self.exercise, checked.params):
            self._say("Not started: " + fes_conflict_text(self.manager, self.exercise, checked.params), error=True)
            return False
        started = time.monotonic()  # before exercise_start is recorded: the summary's window includes it
        try:
            checked = start_exercise(runner, self.manager, self.exercise, checked.params, source=source,
                                     restart_of=restart_of, continues=continues)
        except (RuntimeError, SyntaxError, OSError) as exc:
            self._say(f"Not started: {exc}", error=True)
            return False
        if not checked.ok:  # the patient's limits, caps or electrodes refuse it: nothing moved
            for name, f in self.fields.items():
                f.show_error(checked.errors.get(name, ""))
            self._say("Not started: " + checked.message(self.exercise), error=True)
            return False
        pending = self._pending_summary
        self._pending_summary = None
        self._drop_prefetch()  # this run's own summary comes at its end
        # A continuation's summary covers the interrupted run too (one exercise, two runs).
        self._summary_since = pending[1] if pending is not None and continues and pending[4] == continues else None
        self._started_mono = started
        self._was_running = True
        self._exercised_in_session = getattr(self.manager, "recorder", None) is not None
        self._started_exercise = self.exercise
        recording = getattr(self.manager, "recorder", None) is not None
        self._say(f"{self.exercise.title} started." + ("" if recording else
                  " No session is being recorded: start a session to keep its data and metrics."))
        self._sync_buttons()
        return True

    # ------------------------------------------------------------------ Recover
    def restart_problem(self, run: Any) -> str:
        """Why ``run`` (an exercise's run) cannot be started again exactly ("" when it can)."""
        exercise = next((e for e in self.library if e.ident == run.program.ident), None)
        if exercise is None:
            return f"the exercise '{run.program.ident}' is no longer in the library"
        changed = run.program.changed_on_disk()
        if changed:
            return changed
        from app.therapy.exercises import exercise_program

        try:
            now = exercise_program(exercise)
        except OSError as exc:
            return f"{exercise.script.name} cannot be read ({exc.__class__.__name__})"
        if run.program.version and now.version != run.program.version:
            return f"the exercise {exercise.title} has changed on disk since the run started"
        checked = validate(exercise, run.params_dict())
        if not checked.ok:
            return "its parameters are no longer accepted: " + checked.message(exercise)
        return ""

    def remaining_repetitions(self, run: Any) -> tuple[int, int] | None:
        """(repetitions still to do, planned) of ``run``, for Recover's "continue"; None when its exercise does
        not count repetitions."""
        from app.core.runs import remaining_repetitions

        exercise = next((e for e in self.library if e.ident == run.program.ident), None)
        if exercise is None or not exercise.repetitions:
            return None
        runs = getattr(self.manager, "runs", None)
        live = runs.get(run.run_id) if runs is not None else None
        live = live or run
        try:
            total = int(live.params_dict().get(exercise.repetitions))
        except (TypeError, ValueError):
            return None
        return remaining_repetitions(live, exercise.repetitions), total

    def restart_run(self, run: Any, continue_: bool = False) -> bool:
        """Start ``run``'s exercise again with its parameters (source "recover", linked to ``run``), or, with
        ``continue_``, only its remaining repetitions (a run that continues ``run``): the form shows what runs,
        and this tab follows it."""
        if self.restart_problem(run):
            return False
        exercise = next(e for e in self.library if e.ident == run.program.ident)
        params = run.params_dict()
        continues = None
        if continue_:
            left = self.remaining_repetitions(run)
            if left is None or left[0] <= 0:
                return False
            params = {**params, exercise.repetitions: left[0]}
            continues = run.run_id
        self.exercise_list.blockSignals(True)
        self.exercise_list.setCurrentRow(self.library.index(exercise))
        self.exercise_list.blockSignals(False)
        self._plan_step = None
        self.show_exercise(exercise, params)
        return self.start(source="recover", restart_of=run.run_id, continues=continues)

    def toggle_pause(self) -> None:
        runner = self.runner
        state = self.manager.progress.state
        pause, resume = getattr(runner, "pause", None), getattr(runner, "resume", None)
        if pause is None or resume is None:
            self._say("Pause needs a script runner that can hold a script (not in this build).", error=True)
            return
        if state.paused_since is None:
            pause()
        else:
            resume()
        self._sync_buttons()

    def stop(self) -> None:
        if self.runner.running:
            self.runner.request_stop("stopped by the operator (Exercises tab)")

    def _say(self, text: str, error: bool = False) -> None:
        self.message.setText(text)
        self.message.setStyleSheet(ERROR_STYLE if error else "")

    # ------------------------------------------------------------------ progress
    def _progress_changed(self, state: ProgressState) -> None:
        label = state.label()
        self.repetition_label.setText(label[:1].upper() + label[1:] if label else "")
        if state.total:
            self.progress_bar.setRange(0, state.total)
            done = state.repetition - (1 if state.in_repetition else 0)
            self.progress_bar.setValue(max(0, done))
        else:
            self.progress_bar.setRange(0, 0 if state.running else 1)
        self.progress_text.setText(state.text)
        self.state_label.setText(self.state_text(state))
        self._tick()
        self._sync_buttons()

    @staticmethod
    def state_text(state: ProgressState) -> str:
        """"<title> — <the run's state>": what the progress area says about the run (its own words)."""
        if not state.exercise:
            return ""
        text = state.state_text or ("running" if state.running else "")
        return f"{state.exercise} — {text}" if text else state.exercise

    def _tick(self) -> None:
        self._show_pending_summary()
        progress = getattr(self.manager, "progress", None)
        if progress is None:
            return
        state = progress.state
        if state.started_monotonic is not None:
            m, s = divmod(int(state.elapsed_s()), 60)
            paused = "  (paused)" if state.paused_since is not None else ""
            self.elapsed_label.setText(f"elapsed {m}:{s:02d}{paused}")
        if self._was_running and self._runner is not None and not self._runner.running:
            self._was_running = False
            self._finished()
        self._sync_buttons()

    def _finished(self) -> None:
        result = self._runner.result
        status = result.status if result is not None else "finished"
        exercise = getattr(self, "_started_exercise", None)
        name = exercise.title if exercise is not None else "The exercise"
        text = f"{name}: {status}" + (f" — {result.message}" if result is not None and result.message else "")
        opened = getattr(self._runner, "run", None)
        runs = getattr(self.manager, "runs", None)
        run = runs.get(opened.run_id) if opened is not None and runs is not None else None
        if run is not None and not run.running:  # the run's own end: "emergency stop: …", "refused …"
            text = f"{name}: {run.end_text()}"
        self._say(text, error=status not in ("finished", "stopped"))
        self.progress_bar.setRange(0, 1)
        self.progress_bar.setValue(1 if status == "finished" else 0)
        plan = self.plan()
        if self._plan_step is not None and status == "finished" and self._plan_step + 1 < len(plan):
            self.plan_list.setCurrentRow(self._plan_step + 1)  # the plan's next exercise is offered
        recorder = getattr(self.manager, "recorder", None)
        if recorder is not None and getattr(recorder, "folder", None) is not None:
            since = self._summary_since if self._summary_since is not None else self._started_mono
            self._summary_since = None
            folder, until = Path(recorder.folder), time.monotonic()
            stopped = run is not None and run.end_reason in ("emergency_stop", "safety_stop")
            if stopped or self._recovery_needed():
                # After a STOP the banner's Recover comes first: the summary waits until the recovery is done and
                # nothing runs (a continuation's own summary then covers this run too).
                pending = (folder, since, until, name, run.run_id if run is not None else "")
                self._pending_summary = pending
                self._pending_written = self._pending_after = time.monotonic() + SUMMARY_DELAY_MS / 1000.0
                self._drop_prefetch()
                # Read in the worker while the operator recovers (once the recorder has written the run's last
                # samples): shown as soon as the recovery is done.
                QTimer.singleShot(SUMMARY_DELAY_MS, self, lambda: self._prefetch_summary(pending))
                return
            # Never behind a modal dialog (F12 pressed in one): shown once no modal dialog blocks it.
            QTimer.singleShot(SUMMARY_DELAY_MS, self, lambda: show_when_unblocked(
                self, lambda: self.show_summary(folder, since, until, name)))

    def _recovery_needed(self) -> bool:
        from app.ui.recovery import recovery_needed

        try:
            return recovery_needed(self.manager)
        except Exception:  # a stand-in manager without a supervisor or a bus: nothing to wait for
            return False

    def _show_pending_summary(self) -> None:
        """The summary kept back after a STOP, once the recovery is done and nothing runs (Recover's continuation
        or restart takes its place: that run's summary comes at its end)."""
        pending = self._pending_summary
        if pending is None:
            return
        from app.ui.recovery import recovery_events

        now = time.monotonic()
        if self._recovery_needed() or (self._runner is not None and self._runner.running) \
                or recovery_events().under_way:
            # Recover's own steps run in between (a robot error's reset is polled), then its restart or
            # continuation. A recovery that is not Recover's (the e-stop reset by a script) says nothing when it is
            # done: then the summary waits a while after the last sign of it.
            self._pending_after = max(getattr(self, "_pending_after", 0.0), now + SUMMARY_DELAY_MS / 1000.0)
            return
        if now < getattr(self, "_pending_after", 0.0):
            return
        self._pending_summary = None
        folder, since, until, name, _run_id = pending
        prefetch, self._prefetch = self._prefetch, None
        if prefetch is not None and prefetch.pending != pending:
            prefetch.drop()
            prefetch = None
        show_when_unblocked(self, lambda: self.show_summary(folder, since, until, name, prefetch))

    def _recovery_finished(self, _ok: bool, _text: str) -> None:
        """Recover is done: it started the run again (the pending summary is dropped: that run's own comes at its
        end) or it did not (the summary now, not after a quiet while)."""
        if self._pending_summary is not None:
            self._pending_after = getattr(self, "_pending_written", 0.0)  # the run's last samples written first
            self._show_pending_summary()

    def _summary_tasks(self) -> Any:
        """The window's worker (app.ui.tasks.QtTasks), or None (a panel on its own: the summary is read here)."""
        provider = getattr(self.window(), "tasks", None)
        return provider() if callable(provider) else None

    def _prefetch_summary(self, pending: tuple[Path, float | None, float, str, str]) -> None:
        """The pending summary's session read in the worker now, while the recovery is under way."""
        tasks = self._summary_tasks()
        if self._pending_summary is not pending or self._prefetch is not None or tasks is None:
            return
        self._prefetch = _Prefetch(pending, tasks, f"Summary of {pending[3]}")

    def _drop_prefetch(self) -> None:
        if self._prefetch is not None:
            self._prefetch.drop()
            self._prefetch = None

    def show_summary(self, folder: Path, since: float | None, until: float | None, title: str,
                     prefetch: _Prefetch | None = None) -> QWidget | None:
        """The run's summary: the session is read and its metrics computed in the window's worker process (issue
        #37: a long session read here held the GUI thread, and the interpreter the drivers need, for seconds), then
        the dialog is built here, a run's tab when it is first shown (``summary_dialog`` once it is shown). Without
        a window's worker (a panel on its own) it is read here. ``prefetch``: its reading, begun already. Returns the
        dialog when it was built at once."""
        from app.ui.session_summary import SessionSummaryDialog

        tasks = prefetch.tasks if prefetch is not None else self._summary_tasks()
        if tasks is None:
            try:
                dialog = SessionSummaryDialog(folder, since, until, title=f"{title} — summary", parent=self)
            except Exception:  # the summary must never take the exercise's end down with it
                log.exception("session summary failed")
                self._say(self.message.text() + " (the summary could not be computed: see the log)", error=True)
                return None
            self.summary_dialog = dialog
            dialog.show()
            return dialog

        def done(task: Any) -> None:
            if not task.ok:  # cancelled, or a sentence from the worker: said beside the run's own words
                why = task.error or "cancelled"
                self._say(self.message.text() + f" (the summary could not be computed: {why})", error=True)
                return
            dialog = SessionSummaryDialog(folder, since, until, title=f"{title} — summary", parent=self,
                                          data=task.result, tasks=tasks, staged=True)
            self.summary_dialog = dialog
            dialog.show()

        if prefetch is not None:
            prefetch.then(done)
        else:
            tasks.run("session_summary", str(folder), title=f"Summary of {title}", on_done=done)
        return None

    def _sync_buttons(self) -> None:
        running = self._runner is not None and self._runner.running
        progress = getattr(self.manager, "progress", None)
        paused = progress is not None and progress.state.paused_since is not None
        hold = "" if running else self.hold_reason()
        text = f"Start is disabled: {hold}." if hold else ""
        if self.hold_label.text() != text:
            self.hold_label.setText(text)
            self.hold_label.setVisible(bool(text))
        self.start_button.setEnabled(not running and self.exercise is not None and not hold)
        self.start_button.setToolTip(text)
        self.defaults_button.setEnabled(not running)
        self.form_box.setEnabled(not running)
        self.exercise_list.setEnabled(not running)
        self.plan_list.setEnabled(not running)
        self.pause_button.setEnabled(running)
        self.pause_button.setText("&Resume" if paused else "&Pause")
        self.stop_button.setEnabled(running)


class _Prefetch:
    """A summary's reading in the worker, begun before it is wanted; ``then(done)`` hands the task to ``done`` once
    it has ended (at once if it has). Dropped (the run started again), its result is for nobody: cancelled."""

    def __init__(self, pending: tuple[Path, float | None, float, str, str], tasks: Any, title: str) -> None:
        self.pending = pending
        self.tasks = tasks
        self._ended: Any = None
        self._done: Any = None
        self.task = tasks.run("session_summary", str(pending[0]), title=title, on_done=self._finished)

    def _finished(self, task: Any) -> None:
        self._ended = task
        if self._done is not None:
            self._done(task)

    def then(self, done: Any) -> None:
        self._done = done
        if self._ended is not None:
            done(self._ended)

    def drop(self) -> None:
        self._done = None
        if self._ended is None:
            self.task.cancel()


def show_when_unblocked(owner: QWidget, show: Any) -> None:
    """Run ``show`` (it opens a window) now, or, while a modal dialog is open, once the last one has closed:
    a window opened behind a modal dialog cannot be used, its Close does nothing (issue #26, item 7)."""
    from PySide6.QtWidgets import QApplication

    modal = QApplication.activeModalWidget()
    if modal is None or not modal.isVisible():
        show()
        return

    done = {"once": False}

    def again(*_args: Any) -> None:
        if done["once"]:  # a dialog opened again later must not show it a second time
            return
        done["once"] = True
        QTimer.singleShot(0, owner, lambda: show_when_unblocked(owner, show))

    finished = getattr(modal, "finished", None)
    if finished is not None:
        finished.connect(again)
    else:  # not a QDialog: look again shortly
        QTimer.singleShot(200, owner, again)
