"""The Exercises tab: the form validates (a value out of range is refused with the reason, nothing starts),
a therapy plan is offered in order, an exercise starts in one click, shows its repetitions and elapsed time,
and its summary appears at the end."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import Qt

from app.core.bus import StreamBus
from app.core.config import AppConfig, UdpEndpoint
from app.core.progress import ExerciseProgress
from app.therapy.patients import PatientProfile, PlannedExercise
from app.ui.exercises_panel import ExercisesPanel
from app.ui.qt_bus import shared_qt_bus

pytestmark = pytest.mark.sim_homed  # a homed LINarm from the start: the homing is tested on its own


class FakeRunner:
    def __init__(self) -> None:
        self.started: list[tuple[str, str, dict[str, Any]]] = []
        self.running = False
        self.result = None

    def start(self, source: str, filename: str, params: dict[str, Any], **run: Any) -> None:
        self.started.append((source, filename, params))


class StubManager:
    def __init__(self, profile: PatientProfile | None = None) -> None:
        self.progress = ExerciseProgress()
        self.bus = StreamBus()  # the panel follows the progress through the adapter of this bus
        self.patient_profile = profile
        self.recorder = None
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.supervisor = self

    def record(self, kind: str, **data: Any) -> None:  # the supervisor's journal entry point
        self.events.append((kind, data))

    def record_event(self, kind: str, who: str = "", **data: Any) -> None:  # the application's record (journal)
        self.record(kind, **data)


def test_out_of_range_is_refused_with_the_reason_and_nothing_starts(qtbot) -> None:
    runner = FakeRunner()
    manager = StubManager()
    panel = ExercisesPanel(manager, runner=runner)
    qtbot.addWidget(panel)
    panel.select("trigger_reaching")
    assert panel.exercise is not None and panel.exercise.ident == "trigger_reaching"
    assert "grip" in panel.description.text()
    panel.fields["speed_m_s"].widget.setText("0.5")
    panel.fields["movements"].widget.setText("zero")
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    assert runner.started == [] and manager.events == []
    assert panel.fields["speed_m_s"].error.text() == "0.5 m/s is above the maximum 0.3 m/s"
    assert not panel.fields["speed_m_s"].error.isHidden()
    assert panel.fields["movements"].error.text() == "'zero' is not a number"
    assert panel.message.text().startswith("Not started: Movements: 'zero' is not a number; Speed: 0.5 m/s")
    # corrected: one click starts it, with the form's values as exerciseParams
    panel.fields["speed_m_s"].widget.setText("0.2")
    panel.fields["movements"].widget.setText("6")
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    (_, filename, params), = runner.started
    assert filename.endswith("trigger_reaching.py") and params["speed_m_s"] == 0.2 and params["movements"] == 6
    assert manager.events[0][0] == "exercise_start" and panel.fields["speed_m_s"].error.isHidden()


def test_the_patients_therapy_plan_is_offered_in_order(qtbot) -> None:
    plan = [PlannedExercise("free_admittance", {"duration_s": 90}),
            PlannedExercise("trigger_reaching", {"movements": 4, "trigger_threshold_n": 15})]
    panel = ExercisesPanel(StubManager(PatientProfile(patient_id="P1", therapy_plan=plan)), runner=FakeRunner())
    qtbot.addWidget(panel)
    assert not panel.plan_box.isHidden() and panel.plan_list.count() == 2
    assert panel.plan_list.item(0).text() == "1. Free admittance"
    assert panel.exercise.ident == "free_admittance" and panel.values()["duration_s"] == "90"
    panel.plan_list.setCurrentRow(1)
    assert panel.exercise.ident == "trigger_reaching"
    assert panel.values()["movements"] == "4" and panel.values()["trigger_threshold_n"] == "15"
    assert panel.values()["speed_m_s"] == "0.15"  # what the plan leaves out keeps its default
    no_plan = ExercisesPanel(StubManager(), runner=FakeRunner())
    qtbot.addWidget(no_plan)
    assert no_plan.plan_box.isHidden()


@pytest.mark.slow
def test_exercise_runs_with_progress_and_its_summary_appears(qtbot, tmp_path: Path) -> None:
    from app.manager import LinarmppManager
    from app.scripting.runner import ScriptRunner

    cfg = AppConfig()
    cfg = replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"),
                                       vr=UdpEndpoint(mode="off")))
    manager = LinarmppManager(cfg)
    runner = None
    try:
        manager.start()
        qtbot.waitUntil(manager.all_connected, timeout=10000)
        manager.start_session("PZ-UI", "therapist-1", root=tmp_path / "sessions")
        runner = ScriptRunner(manager)
        panel = ExercisesPanel(manager, runner=runner)
        qtbot.addWidget(panel)
        labels: list[str] = []
        shared_qt_bus(manager.bus).progress_changed.connect(lambda _s: labels.append(panel.repetition_label.text()))
        panel.select("trigger_reaching")
        for name, value in {"movements": "2", "start_m": "0.15", "end_m": "0.30", "speed_m_s": "0.2",
                            "acceleration_m_s2": "0.5", "trigger_threshold_n": "0", "rest_s": "0.3"}.items():
            panel.set_value(name, value)
        qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
        assert runner.running and not panel.start_button.isEnabled() and panel.stop_button.isEnabled()
        qtbot.waitUntil(lambda: "Repetition 1 of 2" in labels or not runner.running, timeout=30000)
        assert "Repetition 1 of 2" in labels, runner.result  # else: why the exercise ended
        assert panel.elapsed_label.text().startswith("elapsed ")
        if hasattr(runner, "pause"):  # contract 2: the kernel's runner can hold a script
            qtbot.mouseClick(panel.pause_button, Qt.MouseButton.LeftButton)
            qtbot.waitUntil(lambda: "(paused)" in panel.elapsed_label.text(), timeout=3000)
            qtbot.mouseClick(panel.pause_button, Qt.MouseButton.LeftButton)
        qtbot.waitUntil(lambda: "Repetition 2 of 2" in labels or not runner.running, timeout=30000)
        assert "Repetition 2 of 2" in labels, runner.result
        qtbot.waitUntil(lambda: panel.summary_dialog is not None, timeout=30000)
        assert runner.result.status == "finished"
        assert "finished" in panel.message.text() and panel.start_button.isEnabled()
        summary = panel.summary_dialog.summary
        assert summary.table.rowCount() == 2
        for r in summary.metrics["repetitions"]:
            assert r["range_m"] == pytest.approx(0.15, rel=0.05)
            assert r["peak_speed_m_s"] == pytest.approx(0.2, rel=0.06)
        assert summary.metrics["summary"]["exercise_params"]["movements"] == 2
        assert set(summary.plots) == {"Peak speed", "Smoothness (SPARC)", "Range of motion", "Interaction force"}
        panel.summary_dialog.close()
        exercise_summary = panel.summary_dialog
        manager.end_session()  # the whole session's summary follows
        qtbot.waitUntil(lambda: panel.summary_dialog is not exercise_summary, timeout=10000)
        assert panel.summary_dialog.summary.metrics["summary"]["repetitions"] == 2
        assert panel.summary_dialog.windowTitle().startswith("Summary — PZ-UI")
        panel.summary_dialog.close()
    finally:
        if runner is not None:
            runner.stop("test over", wait_s=2.0)
        manager.end_session()
        manager.shutdown()


class HoldingRunner(FakeRunner):
    """A runner with contract 2's pause/resume (they hold the script and pause the progress)."""

    def __init__(self, progress: ExerciseProgress) -> None:
        super().__init__()
        self.progress = progress
        self.stop_reasons: list[str] = []

    def start(self, source: str, filename: str, params: dict[str, Any], **run: Any) -> None:
        super().start(source, filename, params)
        self.running = True
        self.progress.begin("trigger_reaching.py", int(params["movements"]))

    def pause(self) -> None:
        self.progress.pause()

    def resume(self) -> None:
        self.progress.resume()

    def request_stop(self, reason: str) -> None:
        self.stop_reasons.append(reason)


def test_progress_pause_resume_stop_and_the_end(qtbot) -> None:
    manager = StubManager()
    runner = HoldingRunner(manager.progress)
    panel = ExercisesPanel(manager, runner=runner)
    qtbot.addWidget(panel)
    panel.select("trigger_reaching")
    panel.set_value("movements", "8")
    assert not panel.pause_button.isEnabled() and not panel.stop_button.isEnabled()
    qtbot.mouseClick(panel.start_button, Qt.MouseButton.LeftButton)
    assert "No session is being recorded" in panel.message.text()
    assert panel.pause_button.isEnabled() and not panel.form_box.isEnabled()
    for k in (1, 2):
        manager.progress.start_repetition(k, 8)
        manager.progress.end_repetition(k)
    manager.progress.start_repetition(3)
    manager.progress.report("squeeze the handle (20 N) to move")
    shared_qt_bus(manager.bus).tick()  # the progress reaches the panel at the adapter's tick: now
    assert panel.repetition_label.text() == "Repetition 3 of 8"
    assert panel.progress_bar.maximum() == 8 and panel.progress_bar.value() == 2
    assert panel.progress_text.text() == "squeeze the handle (20 N) to move"
    assert panel.elapsed_label.text().startswith("elapsed 0:0")
    qtbot.mouseClick(panel.pause_button, Qt.MouseButton.LeftButton)
    assert manager.progress.state.paused_since is not None
    shared_qt_bus(manager.bus).tick()
    assert panel.pause_button.text() == "&Resume" and "(paused)" in panel.elapsed_label.text()
    qtbot.mouseClick(panel.pause_button, Qt.MouseButton.LeftButton)
    shared_qt_bus(manager.bus).tick()
    assert manager.progress.state.paused_since is None and panel.pause_button.text() == "&Pause"
    qtbot.mouseClick(panel.stop_button, Qt.MouseButton.LeftButton)
    assert runner.stop_reasons == ["stopped by the operator (Exercises tab)"]
    runner.result = type("R", (), {"status": "stopped", "message": "stopped by the operator"})()
    runner.running = False
    manager.progress.finish("stopped")
    qtbot.waitUntil(lambda: panel.start_button.isEnabled(), timeout=2000)
    assert panel.message.text().startswith("Trigger reaching") and "stopped" in panel.message.text()
    assert panel.summary_dialog is None  # nothing was recorded: no summary to show
