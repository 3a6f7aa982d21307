"""Sessions from the main window: a patient + an operator start the recording; ending it stops it."""

from __future__ import annotations

import json

from PySide6.QtWidgets import QMessageBox

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.therapy.patients import PatientProfile, save_patient
from app.ui.main_window import MainWindow
from tests.fakes import counter_factory


def test_session_from_the_window_records_and_applies_patient_limits(qtbot, tmp_path, monkeypatch) -> None:
    import dataclasses

    profile = PatientProfile(patient_id="P042")
    profile = dataclasses.replace(profile, robot=dataclasses.replace(profile.robot, max_velocity_m_s=0.1))
    save_patient(profile)
    manager = LinarmppManager(AppConfig(), factories={"alpha": counter_factory(tmp_path, "alpha")})
    manager.start()
    window = MainWindow(manager)
    qtbot.addWidget(window)
    assert "No session" in window.session_label.text()
    folder = manager.start_session("P042", "therapist-1", "first session", root=tmp_path / "sessions")
    assert "P042" in window.session_label.text() and window.session_button.text() == "End session"
    assert manager.supervisor.robot.max_velocity_m_s == 0.1  # narrowed by the patient's profile
    qtbot.waitUntil(lambda: (folder / "streams").exists() and any((folder / "streams").iterdir()), timeout=3000)
    manager.record_event("parameter_change", name="k_r", old=0.5, new=0.4)
    monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
    window.session_button.click()
    assert manager.recorder is None and "No session" in window.session_label.text()
    assert manager.supervisor.robot == manager.config.safety.robot  # the configured limits again
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["operator"] == "therapist-1"
    kinds = [json.loads(line)["kind"] for line in (folder / "events.jsonl").read_text().splitlines()]
    assert "parameter_change" in kinds and "patient_limits_applied" in kinds
    window.close()
    manager.shutdown()
