"""Recover after a STOP from one place (the alarm banner): acknowledge the open alarms in the session
operator's name, reset the emergency stop, reset the robot's latched error, re-home when needed and,
if an exercise was interrupted, start it again: continue with its remaining repetitions (a new run linked to the
interrupted one) or restart it from the beginning. STOP -> running again is two actions: "Recover…" in the
banner, then "Recover and continue" (or "… restart") in the dialog (three when no session gives the operator's
name).

Every step goes into the session record as a ``recovery`` event with the operator's name. The robot
steps go through the driver (and so the safety supervisor), never around it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from PySide6.QtCore import QObject, QTimer, Signal
from PySide6.QtWidgets import (
    QDialog,
    QFormLayout,
    QLabel,
    QLineEdit,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from app.core import journal, streams
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.wire.linarm_protocol import ErrorState, HomeState

log = logging.getLogger(__name__)

SOURCE = "recover"
NO_ERROR = int(ErrorState.NO_ERROR)
HOME_DONE = int(HomeState.HOME_DONE)
ROBOT_REPLY_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class Restartable:
    """The run a STOP interrupted (app/core/runs.py) and how to start it again. ``why_not``: why it cannot be
    started again exactly (console code, a file changed on disk since): the dialog says so and offers the
    recovery without the restart. ``details``: what the restart runs (its parameters, in words)."""

    name: str
    start: Callable[[], bool]
    why_not: str = ""
    details: str = ""
    run_id: str = ""
    continue_start: Callable[[], bool] | None = None  # the remaining repetitions, as a run continuing this one
    remaining: int = 0
    total: int = 0

    @property
    def possible(self) -> bool:
        return not self.why_not

    @property
    def can_continue(self) -> bool:
        return self.possible and self.continue_start is not None and 0 < self.remaining < self.total

    def continuation(self) -> Restartable:
        """The same, started as the continuation (its remaining repetitions)."""
        assert self.continue_start is not None
        return replace(self, start=self.continue_start,
                       details=f"the remaining {self.remaining} of {self.total} repetitions")


def interrupted_run(manager: LinarmppManager, panels: dict[str, Any]) -> Restartable | None:
    """The run a STOP interrupted (the session's runs, app/core/runs.py: the one still running — Recover stops it first
    — or the last one, stopped), for the banner's Recover: started again exactly (the same exercise with the same
    parameters from the Exercises tab, the same script text from the Script tab), or, for an exercise that counts
    its repetitions, continued with those not yet done. Console code, or an exercise changed on disk since, is not
    restarted: the reason is given instead. ``panels``: the Commands frame's tabs by class name."""
    from app.core.runs import restart_candidate

    runs = getattr(manager, "runs", None)
    run = restart_candidate(runs.runs()) if runs is not None else None
    if run is None:
        return None
    owner = panels.get("ExercisesPanel") if run.program.kind == "exercise" else panels.get("ScriptConsole")
    if run.program.kind == "console" or owner is None:
        why = run.program.changed_on_disk() if run.program.kind == "console" else "its tab is not available"
        return Restartable(run.title, lambda: False, why_not=why, run_id=run.run_id)
    why_not = owner.restart_problem(run)
    if run.program.kind == "exercise":
        details = run.parameters_text()
    else:
        editor = getattr(owner, "editor_text", None)
        details = script_restart_words(run.program, editor() if callable(editor) else None)
    restart = Restartable(run.title, lambda: owner.restart_run(run), why_not=why_not, details=details,
                          run_id=run.run_id)
    remaining = getattr(owner, "remaining_repetitions", None)
    left = remaining(run) if callable(remaining) else None
    if left is not None:
        restart = replace(restart, continue_start=lambda: owner.restart_run(run, continue_=True),
                          remaining=left[0], total=left[1])
    return restart


def script_restart_words(program: Any, editor_text: str | None = None) -> str:
    """What a Script-tab restart runs, in words: always the text that ran (kept in the record). Says "changed on
    disk" only when the file itself changed since the run started; when the text that ran, or the editor's text
    now, differs from the file, it says the editor's text differs (unsaved edits) — and still restarts what ran."""
    from app.core.runs import text_hash

    name = Path(program.path).name if program.path else ""
    if not program.path:
        return "the text that ran (the editor's)"
    changed = program.file_changed()
    if changed:
        return f"the text that ran; {name} has changed on disk since, and its new text is not what restarts"
    if program.file_sha256 and program.text_sha256 != program.file_sha256:
        return f"the text that ran: the editor's text, which differs from {name} on disk (not saved)"
    if editor_text is not None and text_hash(editor_text) != program.text_sha256:
        return f"the text that ran ({name}); the editor's text differs from it now, and is not what restarts"
    return f"the text that ran ({name})"


def robot_state(manager: LinarmppManager) -> Any:
    driver = manager.driver(streams.LINARM)
    if driver is None or not driver.connected:
        return None
    return manager.bus.latest(streams.LINARM_STATE)


def recovery_needed(manager: LinarmppManager) -> bool:
    """A latched e-stop, an open STOP/FATAL alarm or a robot error: the banner offers Recover."""
    sup = manager.supervisor
    if sup.estop_latched:
        return True
    if any(a.level >= AlarmLevel.STOP and not a.acknowledged for a in sup.alarms()):
        return True
    state = robot_state(manager)
    return state is not None and int(state.errorState) != NO_ERROR


def plan(manager: LinarmppManager, restart: Restartable | None, script_running: bool = False) -> list[str]:
    """What Recover will do, in words, in order (shown in the dialog before anything is done)."""
    sup = manager.supervisor
    if restart is not None and not restart.possible:
        restart = None
    steps: list[str] = ["stop the script still running"] if script_running else []
    open_ = sum(1 for a in sup.alarms() if not a.acknowledged)
    if open_:
        steps.append(f"acknowledge {open_} open alarm(s)")
    if sup.estop_latched:
        steps.append("reset the emergency stop")
    state = robot_state(manager)
    if state is not None and int(state.errorState) != NO_ERROR:
        steps.append("reset the robot's error (the motors stay off)")
    if state is not None and int(state.homeState) != HOME_DONE:
        steps.append("home the robot (it moves to its endstrokes)" if restart is None
                     else "home the robot before the exercise (it moves to its endstrokes)")
    return steps or ["nothing to recover"]


class RecoveryEvents(QObject):
    """Every Recover of the process, whoever started it: ``finished(ok, text)`` once one is done, ``under_way`` while
    one is. What waits for a recovery (the summary of the run a STOP ended) knows from it when the recovery is over
    and whether it started the run again, instead of guessing from a quiet moment after it."""

    finished = Signal(bool, str)
    STALE_S = 30.0  # a recovery that never said it finished (an exception in a step) holds nothing longer

    def __init__(self) -> None:
        super().__init__()
        self._running: dict[int, float] = {}  # id() of each recovery under way -> when it began

    @property
    def under_way(self) -> bool:
        now = time.monotonic()
        return any(now - began < self.STALE_S for began in self._running.values())

    def began(self, recovery: object) -> None:
        self._running[id(recovery)] = time.monotonic()

    def ended(self, recovery: object, ok: bool, text: str) -> None:
        self._running.pop(id(recovery), None)
        self.finished.emit(ok, text)


_events: RecoveryEvents | None = None


def recovery_events() -> RecoveryEvents:
    """The process's :class:`RecoveryEvents` (made at first use, on the GUI thread)."""
    global _events
    if _events is None:
        _events = RecoveryEvents()
    return _events


class Recovery(QObject):
    """Runs the steps one after the other on the GUI thread (the robot's replies are polled, never
    waited for). ``finished(ok, text)`` once done (also on :func:`recovery_events`)."""

    step_done = Signal(str)
    finished = Signal(bool, str)

    def __init__(self, manager: LinarmppManager, operator: str, restart: Restartable | None = None,
                 parent: QObject | None = None, stop_script: Callable[[], bool] | None = None) -> None:
        super().__init__(parent)
        self.manager = manager
        if restart is not None and not restart.possible:
            restart = None  # never started: the dialog said why
        # Stops a script still running across the stop (True when one was stopped): it must never
        # carry on commanding the robot once the e-stop is reset.
        self.stop_script = stop_script or (lambda: False)
        self.operator = operator
        self.restart = restart
        self.steps: list[str] = []
        self._future: Future | None = None
        self._waited = 0.0
        self._poll = QTimer(self)
        self._poll.setInterval(30)
        self._poll.timeout.connect(self._check_robot)

    def _log(self, step: str, **data: Any) -> None:
        self.steps.append(step)
        self.manager.supervisor.record(journal.RECOVERY, step=step, operator=self.operator, **data)
        self.step_done.emit(step)

    def run(self) -> None:
        sup = self.manager.supervisor
        recovery_events().began(self)
        self._log("start", restart=self.restart.name if self.restart else "")
        if self.stop_script():
            self._log("script_stopped")
        open_ = [a.ident for a in sup.alarms() if not a.acknowledged]
        for ident in open_:
            sup.acknowledge(ident, self.operator)
        if open_:
            self._log("acknowledged", count=len(open_))
        if sup.estop_latched:
            sup.reset_emergency_stop(self.operator)
            self._log("estop_reset")
            # The reset's own information alarm is part of this recovery: acknowledged with it.
            for alarm in sup.alarms():
                if not alarm.acknowledged and alarm.level < AlarmLevel.WARNING:
                    sup.acknowledge(alarm.ident, self.operator)
        state = robot_state(self.manager)
        if state is not None and int(state.errorState) != NO_ERROR:
            driver = self.manager.driver(streams.LINARM)
            try:
                self._future = driver.command_async("resetError", source=SOURCE)
            except Exception as exc:  # a refusal or a closed driver: say so, do nothing more
                self._finish(False, f"robot error not reset: {exc}")
                return
            self._waited = 0.0
            self._poll.start()
            return
        self._after_robot_reset()

    def _check_robot(self) -> None:
        self._waited += self._poll.interval() / 1000.0
        future = self._future
        if future is None:
            self._poll.stop()
            return
        if not future.done():
            if self._waited > ROBOT_REPLY_TIMEOUT_S:
                self._poll.stop()
                self._finish(False, "the robot did not answer Reset error")
            return
        self._poll.stop()
        self._future = None
        exc = future.exception()
        if exc is not None:
            self._finish(False, f"robot error not reset: {getattr(exc, 'reason', exc)}")
            return
        self._log("robot_error_reset")
        self._after_robot_reset()

    def _after_robot_reset(self) -> None:
        if self.restart is not None:
            # The script runner homes the robot first when needed (it waits for the homing to finish).
            ok = self.restart.start()
            self._log("exercise_restarted" if ok else "exercise_not_restarted", exercise=self.restart.name)
            self._finish(ok, f"{self.restart.name} started again" if ok else f"{self.restart.name} did not start")
            return
        state = robot_state(self.manager)
        if state is not None and int(state.homeState) != HOME_DONE:
            driver = self.manager.driver(streams.LINARM)
            try:
                driver.command_async("goToHome", source=SOURCE)
            except Exception as exc:
                self._finish(False, f"homing not started: {exc}")
                return
            self._log("homing_started")
        self._finish(True, "recovered")

    def _finish(self, ok: bool, text: str) -> None:
        self._log("done" if ok else "failed", text=text)
        self.finished.emit(ok, text)
        recovery_events().ended(self, ok, text)


class RecoverDialog(QDialog):
    """Says what Recover will do and in whose name; one click does it."""

    def __init__(self, manager: LinarmppManager, operator: str, restart: Restartable | None,
                 parent: QWidget | None = None, script_running: bool = False) -> None:
        super().__init__(parent)
        self.setWindowTitle("Recover after the stop")
        self.setMinimumWidth(520)  # its title and the exercise's name, whole (a window manager elides them)
        self.manager = manager
        self.restart = restart
        self.choice: str | None = None  # "continue" | "restart" | "recover"
        lay = QVBoxLayout(self)
        steps = plan(manager, restart, script_running)
        self.steps_label = QLabel("Recover will:<ul>" + "".join(f"<li>{s}</li>" for s in steps) + "</ul>")
        lay.addWidget(self.steps_label)
        # What the restart runs, or why the interrupted run cannot be started again (in plain words).
        self.restart_note = QLabel("")
        self.restart_note.setObjectName("restartNote")
        self.restart_note.setWordWrap(True)
        if restart is not None and restart.can_continue:
            self.restart_note.setText(f"{restart.name}: {restart.total - restart.remaining} of {restart.total} "
                                      f"repetitions were done. Continue runs the remaining {restart.remaining} with "
                                      f"the same parameters ({restart.details}); restart runs all {restart.total}.")
        elif restart is not None and restart.possible:
            self.restart_note.setText(f"Restart: {restart.name}" + (f" — {restart.details}" if restart.details else ""))
        elif restart is not None:
            self.restart_note.setText(f"{restart.name} cannot be restarted: {restart.why_not}. "
                                      "Recover brings the devices back without starting it; start it again "
                                      "yourself if it should continue.")
            self.restart_note.setStyleSheet("color: #8a5a00;")
        self.restart_note.setVisible(bool(self.restart_note.text()))
        lay.addWidget(self.restart_note)
        form = QFormLayout()
        self.operator = QLineEdit(operator)
        self.operator.setObjectName("recoverOperator")
        self.operator.setPlaceholderText("who recovers (goes into the session record)")
        form.addRow("&Operator:", self.operator)
        lay.addLayout(form)
        self.error = QLabel("")
        self.error.setStyleSheet("color: #c62828;")
        lay.addWidget(self.error)
        # One button per choice, one above the other: their texts name the exercise and are long.
        buttons = QVBoxLayout()
        self.continue_button: QPushButton | None = None
        self.restart_button: QPushButton | None = None
        if restart is not None and restart.can_continue:
            self.continue_button = QPushButton(f"Recover and &continue {restart.name} with the remaining "
                                               f"{restart.remaining} repetitions")
            self.continue_button.clicked.connect(lambda: self._choose("continue"))
            buttons.addWidget(self.continue_button)
        if restart is not None and restart.possible:
            self.restart_button = QPushButton(f"Recover and &restart {restart.name}"
                                              + (" from the beginning" if self.continue_button else ""))
            self.restart_button.clicked.connect(lambda: self._choose("restart"))
            buttons.addWidget(self.restart_button)
        self.recover_button = QPushButton("Recover &only" if self.restart_button else "&Recover")
        self.recover_button.clicked.connect(lambda: self._choose("recover"))
        buttons.addWidget(self.recover_button)
        cancel = QPushButton("Cancel")
        cancel.clicked.connect(self.reject)
        buttons.addWidget(cancel)
        first = self.continue_button or self.restart_button or self.recover_button
        first.setDefault(True)
        first.setAutoDefault(True)
        lay.addLayout(buttons)
        if not operator:
            self.operator.setFocus()

    def _choose(self, choice: str) -> None:
        if not self.operator.text().strip():
            self.error.setText("Type the operator's name: every step is recorded in it.")
            self.operator.setFocus()
            return
        self.choice = choice
        self.accept()

    def operator_name(self) -> str:
        return self.operator.text().strip()
