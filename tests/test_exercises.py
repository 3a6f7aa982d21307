"""Exercises as forms: the library loads, values are validated with reasons, nothing starts when refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from app.therapy.exercises import ExerciseError, find_exercise, load_exercise, load_library, start_exercise, validate


def test_library_holds_the_seed_exercises_with_valid_defaults() -> None:
    library, problems = load_library()
    assert problems == []
    assert [e.ident for e in library][:4] == ["trigger_reaching", "assisted_reaching_fes", "free_admittance",
                                              "temperature_follow"]
    for e in library:
        assert e.description and e.script.is_file()
        compile(e.script.read_text(encoding="utf-8"), str(e.script), "exec")
        checked = validate(e, e.defaults())
        assert checked.ok, (e.ident, checked.errors)


def test_validation_refuses_with_the_reason() -> None:
    e = find_exercise("trigger_reaching")
    checked = validate(e, {"movements": "0", "speed_m_s": "0.5", "end_m": "far", "rest_s": "2,5",
                           "trigger_threshold_n": "nan"})
    assert not checked.ok
    assert checked.errors["movements"] == "0 is below the minimum 1"
    assert checked.errors["speed_m_s"] == "0.5 m/s is above the maximum 0.3 m/s"
    assert checked.errors["end_m"] == "'far' is not a number"
    assert checked.errors["trigger_threshold_n"] == "must be a finite number"
    assert "rest_s" not in checked.errors and checked.params["rest_s"] == 2.5  # a decimal comma is accepted
    assert "Speed: 0.5 m/s is above the maximum 0.3 m/s" in checked.message(e)
    assert validate(e, {"movements": "2.5"}).errors["movements"] == "must be a whole number"
    assert "no parameter" in validate(e, {"bogus": 1}).errors["bogus"]
    fes = find_exercise("assisted_reaching_fes")
    assert validate(fes, {"use_fes": "maybe"}).errors["use_fes"] == "must be yes or no"
    assert "one of" in validate(fes, {"fes_profile": "other.yaml"}).errors["fes_profile"]


class FakeRunner:
    def __init__(self) -> None:
        self.started: list[tuple[str, str, dict[str, Any]]] = []
        self.running = False

    def start(self, source: str, filename: str, params: dict[str, Any], **run: Any) -> None:
        self.started.append((source, filename, params))


class FakeSupervisor:
    def __init__(self) -> None:
        self.events: list[tuple[str, dict[str, Any]]] = []

    def record(self, kind: str, **data: Any) -> None:  # the supervisor's journal entry point
        self.events.append((kind, data))


def test_start_exercise_starts_only_valid_values_and_records_them() -> None:
    supervisor = FakeSupervisor()  # no session: the events the application records land here (the journal's stand-in)
    manager = type("M", (), {"supervisor": supervisor, "recorder": None,
                             "record_event": lambda self, kind, who="", **data: supervisor.record(kind, **data)})()
    runner = FakeRunner()
    e = find_exercise("trigger_reaching")
    refused = start_exercise(runner, manager, e, {"speed_m_s": 0.9})
    assert not refused.ok and runner.started == [] and manager.supervisor.events == []
    ok = start_exercise(runner, manager, e, {"movements": "6"})
    assert ok.ok
    (source, filename, params), = runner.started
    assert "startRepetition" in source
    assert filename == str(e.script) and params["movements"] == 6 and params["speed_m_s"] == 0.15
    assert manager.supervisor.events == [("exercise_start", {"exercise": "trigger_reaching", "title": e.title,
                                                             "script": "trigger_reaching.py", "params": params})]
    runner.running = True
    with pytest.raises(RuntimeError):
        start_exercise(runner, manager, e, {})


@pytest.mark.parametrize("text, fragment", [
    ("title: x\nparameters:\n  - {name: a, type: float, default: 5, min: 0, max: 1}\n", "the default is refused"),
    ("title: x\nparameters:\n  - {name: a, type: colour, default: 1}\n", "type must be one of"),
    ("title: x\nparameters:\n  - {name: a, default: 1, unknown: 2}\n", "unknown key"),
    ("title: x\nparameters:\n  - {name: a}\n", "a default is required"),
    ("title: x\nbogus: 1\n", "unknown key"),
])
def test_a_malformed_exercise_is_refused(tmp_path: Path, text: str, fragment: str) -> None:
    (tmp_path / "x.py").write_text("pass\n")
    (tmp_path / "x.yaml").write_text(text)
    with pytest.raises(ExerciseError, match=fragment):
        load_exercise(tmp_path / "x.yaml")
    library, problems = load_library(tmp_path)
    assert library == [] and len(problems) == 1


def test_the_patient_dialog_keeps_a_therapy_plan(qtbot) -> None:
    from app.therapy.patients import PatientProfile, PlannedExercise
    from app.ui.patient_dialog import PatientDialog

    plan = [PlannedExercise("trigger_reaching", {"movements": 6}, "start gently")]
    dialog = PatientDialog(PatientProfile(patient_id="P9", therapy_plan=plan))
    qtbot.addWidget(dialog)
    profile = dialog.validate()
    assert profile is not None and profile.therapy_plan == plan
