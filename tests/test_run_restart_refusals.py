"""Recover restarts a run only when it can run exactly again (issue #26): a library exercise changed on disk
since, or parameters its ranges no longer accept, are refused with the reason in plain words; the dialog then
offers the recovery without the restart. Which run Recover offers: the interrupted one, not a console look
taken after it, never a finished or refused one."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from app.core.config import AppConfig
from app.core.progress import ExerciseProgress
from app.core.runs import Program, RunLog, restart_candidate, text_hash
from app.manager import LinarmppManager
from app.therapy.exercises import exercise_program, load_exercise, run_parameters
from app.ui.exercises_panel import ExercisesPanel
from app.ui.recovery import RecoverDialog, Restartable

ROOT = Path(__file__).resolve().parent.parent


class Runner:
    def __init__(self) -> None:
        self.started: list[dict[str, Any]] = []
        self.running = False
        self.result = None

    def start(self, source: str, filename: str, params: dict[str, Any], **run: Any) -> None:
        self.started.append({"filename": filename, "params": params, **run})


class Manager:
    def __init__(self) -> None:
        self.progress = ExerciseProgress()
        self.patient_profile = None
        self.recorder = None
        self.supervisor = self

    def record(self, kind: str, **data: Any) -> None:  # the supervisor's journal entry point
        pass

    def record_event(self, kind: str, who: str = "", **data: Any) -> None:  # the application's record (journal)
        self.record(kind, **data)


def _library_copy(tmp_path: Path) -> Any:
    for name in ("trigger_reaching.yaml", "trigger_reaching.py"):
        shutil.copy(ROOT / "resources" / "exercises" / name, tmp_path / name)
    return load_exercise(tmp_path / "trigger_reaching.yaml")


def test_an_exercise_changed_on_disk_is_not_restarted(qtbot: Any, tmp_path: Path) -> None:
    exercise = _library_copy(tmp_path)
    runner = Runner()
    panel = ExercisesPanel(Manager(), runner=runner)
    qtbot.addWidget(panel)
    panel.library = [exercise]
    log = RunLog()
    params = {**exercise.defaults(), "movements": 4}
    run = log.start(exercise_program(exercise), run_parameters(exercise, params), "exercises_tab", "Dr A")
    log.end(run.run_id, "emergency_stop", "F12")
    assert panel.restart_problem(run) == ""
    assert panel.restart_run(run) and runner.started[-1]["params"]["movements"] == 4
    assert runner.started[-1]["run_source"] == "recover" and runner.started[-1]["restart_of"] == run.run_id
    script = tmp_path / "trigger_reaching.py"
    script.write_text(script.read_text(encoding="utf-8") + "\n# edited\n", encoding="utf-8")
    assert "changed on disk" in panel.restart_problem(run)
    n = len(runner.started)
    assert not panel.restart_run(run) and len(runner.started) == n  # nothing started


def test_parameters_no_longer_accepted_are_not_restarted(qtbot: Any, tmp_path: Path) -> None:
    exercise = _library_copy(tmp_path)
    panel = ExercisesPanel(Manager(), runner=Runner())
    qtbot.addWidget(panel)
    panel.library = [exercise]
    log = RunLog()
    bad = [*run_parameters(exercise, exercise.defaults())]
    bad[0] = type(bad[0])(bad[0].name, bad[0].label, 1000, bad[0].unit)  # movements beyond the range now
    run = log.start(exercise_program(exercise), bad, "exercises_tab", "Dr A")
    assert "no longer accepted" in panel.restart_problem(run) and "Movements" in panel.restart_problem(run)


def test_the_dialog_says_why_a_run_is_not_restarted(qtbot: Any) -> None:
    manager = LinarmppManager(AppConfig())
    try:
        why = Program("console", "<console>", "Console code", text_hash("x"), text="x").changed_on_disk()
        dialog = RecoverDialog(manager, "Dr A", Restartable("Console code", lambda: True, why_not=why))
        qtbot.addWidget(dialog)
        assert dialog.restart_button is None and dialog.recover_button.text() == "&Recover"
        assert "Console code cannot be restarted: code typed in the console" in dialog.restart_note.text()
        ok = RecoverDialog(manager, "Dr A", Restartable("Trigger reaching", lambda: True,
                                                        details="Movements: 6, Speed: 0.2 m/s"))
        qtbot.addWidget(ok)
        assert ok.restart_button is not None and "Movements: 6, Speed: 0.2 m/s" in ok.restart_note.text()
    finally:
        manager.shutdown()


def test_recover_offers_the_interrupted_run() -> None:
    log = RunLog()
    prog = Program("script_file", "/a.py", "a.py", text_hash("a"), path="/a.py", text="a")
    console = Program("console", "<console>", "Console code", text_hash("b"), text="b")
    first = log.start(prog, (), "script_tab", "A")
    log.end(first.run_id, "emergency_stop")
    look = log.start(console, (), "console", "A")
    log.end(look.run_id, "finished")  # the operator looked at a value after the STOP
    assert restart_candidate(log.runs()) == log.get(first.run_id)
    done = log.start(prog, (), "script_tab", "A")
    assert restart_candidate(log.runs()) == log.get(done.run_id)  # still running: Recover stops it first
    log.end(done.run_id, "finished")
    assert restart_candidate(log.runs()) is None
    refused = log.start(prog, (), "script_tab", "A")
    log.end(refused.run_id, "refused", "FES current above the patient's cap")
    assert restart_candidate(log.runs()) is None
