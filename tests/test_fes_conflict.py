"""Issue #30 item 4: an exercise that stimulates, started while stimulation is on, is stopped before it starts
with the conflict in plain words and the choice to stop the stimulation (it ended with
"CommandError: fes.loadFile('frontal_reaching.yaml') failed: stop stimulation…" after the start)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QMessageBox

from app.ui.exercises_panel import ExercisesPanel
from tests.test_exercises_panel import FakeRunner, StubManager


class StimulatingFes:
    def __init__(self) -> None:
        self.stimulating = True
        self.profile = SimpleNamespace(name="Wrist extension")
        self.stops: list[tuple[str, str]] = []

    def stop_stimulation(self, reason: str = "", source: str = "") -> None:
        self.stops.append((reason, source))
        self.stimulating = False


def _panel(qtbot) -> tuple[ExercisesPanel, FakeRunner, StimulatingFes]:
    runner, fes = FakeRunner(), StimulatingFes()
    manager = StubManager()
    manager.devices = {"fes": object()}  # type: ignore[attr-defined]
    manager.driver = lambda name: fes if name == "fes" else None  # type: ignore[attr-defined]
    panel = ExercisesPanel(manager, runner=runner)
    qtbot.addWidget(panel)
    panel.select("assisted_reaching_fes")
    return panel, runner, fes


def test_the_conflict_is_said_in_plain_words_and_nothing_starts(qtbot, monkeypatch) -> None:
    panel, runner, fes = _panel(qtbot)
    asked: list[str] = []

    def cancel(*args: Any, **_k: Any) -> QMessageBox.StandardButton:
        asked.append(str(args[2]))
        return QMessageBox.StandardButton.Cancel
    monkeypatch.setattr(QMessageBox, "question", cancel)
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    assert runner.started == [] and fes.stimulating and fes.stops == []
    assert "Stimulation is on (Wrist extension)" in asked[0] and "Assisted reaching with FES" in asked[0]
    text = panel.message.text()
    assert text.startswith("Not started: Stimulation is on") and "Error" not in text and "fes.loadFile" not in text


def test_stopping_the_stimulation_first_starts_the_exercise(qtbot, monkeypatch) -> None:
    panel, runner, fes = _panel(qtbot)
    monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    assert fes.stops == [("to start an exercise", "Exercises tab")] and not fes.stimulating
    assert len(runner.started) == 1 and runner.started[0][1].endswith("assisted_reaching_fes.py")


def test_an_exercise_without_fes_or_with_fes_off_is_not_asked(qtbot, monkeypatch) -> None:
    panel, runner, fes = _panel(qtbot)
    monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: (_ for _ in ()).throw(AssertionError("asked")))
    panel.fields["use_fes"].widget.setChecked(False)
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    assert len(runner.started) == 1 and fes.stimulating
