"""Exercise progress: repetition marks become state and session events, on a virtual clock."""

from __future__ import annotations

import pytest

from app.core.progress import ExerciseProgress


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_marks_become_state_and_events(qapp) -> None:
    events: list[tuple[str, dict]] = []
    clock = Clock()
    progress = ExerciseProgress(lambda kind, **data: events.append((kind, data)), clock=clock)
    seen = []
    progress.subscribe(seen.append)
    progress.begin("trigger_exercise.py")
    clock.t += 2.0
    progress.start_repetition(1, 8)
    assert progress.state.label() == "repetition 1 of 8"
    progress.end_repetition()
    progress.pause()
    clock.t += 5.0
    progress.resume()
    clock.t += 1.0
    assert progress.state.elapsed_s(clock.t) == pytest.approx(3.0)
    progress.start_repetition(2)
    progress.report("reach the target")
    progress.finish("stopped")
    kinds = [k for k, _ in events]
    assert kinds == ["repetition_start", "repetition_end", "exercise_paused", "exercise_resumed",
                     "repetition_start", "progress", "repetition_end"]
    assert events[0][1] == {"index": 1, "total": 8}
    assert events[-1][1]["ok"] is False  # repetition 2 was cut by the stop
    assert seen[-1].running is False and seen[-1].repetition == 2 and seen[-1].total == 8


def test_bad_marks_are_refused(qapp) -> None:
    progress = ExerciseProgress()
    with pytest.raises(ValueError):
        progress.start_repetition(0)
    with pytest.raises(ValueError):
        progress.begin("x", total=0)
