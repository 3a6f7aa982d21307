"""An exercise that stimulates, started while stimulation is already on (issue #30 item 4).

The exercise loads its own FES profile, which the stimulator refuses while it stimulates; the clinician read
``CommandError: fes.loadFile('frontal_reaching.yaml') failed: stop stimulation…`` after the start. Now the
conflict is found before the start and said in plain words, with the choice to stop the stimulation first.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from PySide6.QtWidgets import QMessageBox, QWidget

from app.core import streams


def exercise_stimulates(exercise: Any, values: Mapping[str, Any]) -> bool:
    """True when this exercise, with these values, will load and run an FES profile: it has an ``fes_profile``
    parameter and its ``use_fes`` (when it has one) is on."""
    names = {p.name for p in getattr(exercise, "parameters", ())}
    if "fes_profile" not in names:
        return False
    return bool(values.get("use_fes", True)) if "use_fes" in names else True


def fes_conflict_text(manager: Any, exercise: Any, values: Mapping[str, Any]) -> str:
    """The conflict in plain words, or "" when there is none."""
    if not exercise_stimulates(exercise, values):
        return ""
    fes = manager.driver(streams.FES) if streams.FES in getattr(manager, "devices", {}) else None
    if fes is None or not getattr(fes, "stimulating", False):
        return ""
    profile = getattr(getattr(fes, "profile", None), "name", "") or "a profile"
    return (f"Stimulation is on ({profile}). “{exercise.title}” stimulates with its own profile "
            f"({values.get('fes_profile', '')}), which can only be loaded when the stimulation has stopped.")


def resolve_fes_conflict(parent: QWidget | None, manager: Any, exercise: Any, values: Mapping[str, Any],
                         ask: Any = None) -> bool:
    """True when the exercise may start: no conflict, or the clinician chose to stop the stimulation (stopped
    here, through the driver and so the supervisor's record). ``ask`` replaces the question box in tests."""
    text = fes_conflict_text(manager, exercise, values)
    if not text:
        return True
    question = ask or (lambda t: QMessageBox.question(
        parent, "Stimulation is on", t + "\n\nStop the stimulation and start the exercise?",
        QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.Cancel,
        QMessageBox.StandardButton.Cancel) == QMessageBox.StandardButton.Yes)
    if not question(text):
        return False
    manager.driver(streams.FES).stop_stimulation("to start an exercise", "Exercises tab")
    return True
