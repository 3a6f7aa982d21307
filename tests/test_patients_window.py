"""Session → Patients… (issue #26, item 6): the list of patients, searched; a profile edited; the therapy plan
edited with each exercise's own ranges (a value out of range refused in words, at its field, nothing saved);
the operator chosen at each session start (the last one offered, never pre-filled)."""

from __future__ import annotations

from pathlib import Path

import pytest
from PySide6.QtCore import QSettings, Qt
from PySide6.QtWidgets import QDialogButtonBox, QLineEdit

from app.core.config import AppConfig
from app.therapy.patients import PatientProfile, PlannedExercise, load_patient, plan_problems, save_patient
from tests.clipping import clipped_texts

SAFETY = AppConfig().safety


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    save_patient(PatientProfile(patient_id="PZ-017", full_name="Anna Rossi", record_number="MRN-4471",
                                affected_side="left", notes="shoulder pain above 0.4 m"), tmp_path, SAFETY)
    save_patient(PatientProfile(patient_id="PZ-018", full_name="Bruno Verdi", affected_side="right"), tmp_path, SAFETY)
    save_patient(PatientProfile(patient_id="P-ANON"), tmp_path, SAFETY)
    (tmp_path / "broken.yaml").write_text("patient_id: broken\nscores: {fugl_meyer_ue: 80}\n", encoding="utf-8")
    return tmp_path


def _ids(dialog) -> list[str]:
    return [dialog.table.item(r, 0).text() for r in range(dialog.table.rowCount())]


def test_the_patients_dialog_lists_and_searches(qtbot, folder: Path) -> None:
    from app.ui.patients_window import PatientsDialog

    dialog = PatientsDialog(SAFETY, folder)
    qtbot.addWidget(dialog)
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)  # read on a thread of its own
    dialog.show()
    qtbot.waitExposed(dialog)
    assert sorted(_ids(dialog)) == ["P-ANON", "PZ-017", "PZ-018", "broken"]  # a broken file is listed, not hidden
    assert clipped_texts(dialog) == []
    qtbot.keyClicks(dialog.search, "rossi")
    assert _ids(dialog) == ["PZ-017"] and "Anna Rossi" in dialog.details.text()
    assert "shoulder pain" in dialog.details.text() and dialog.plan_button.isEnabled()
    dialog.search.setText("mrn-4471")
    assert _ids(dialog) == ["PZ-017"]
    dialog.search.setText("nobody")
    assert _ids(dialog) == [] and "No patient matches" in dialog.details.text()
    assert not dialog.edit_button.isEnabled() and not dialog.plan_button.isEnabled()
    dialog.search.setText("broken")
    assert "scores.fugl_meyer_ue" in dialog.details.text() and not dialog.edit_button.isEnabled()


def test_a_profile_is_edited_from_the_list(qtbot, folder: Path) -> None:
    from app.ui.patients_window import PatientsDialog

    dialog = PatientsDialog(SAFETY, folder)
    qtbot.addWidget(dialog)
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)  # read on a thread of its own
    dialog.search.setText("PZ-018")
    edit = dialog.edit_profile()
    assert edit is not None and edit.isVisible() and edit.id_edit.text() == "PZ-018" and edit.id_edit.isReadOnly()
    edit.birth_edit.setText("13/01/1950")
    edit.accept()
    assert edit.result() == 0 and "YYYY-MM-DD" in edit.error_label.text() and edit.birth_edit.styleSheet()
    edit.birth_edit.setText("1950-01-13")
    edit.record_edit.setText("0042")  # stays text: the leading zero is kept
    edit.name_edit.setText("Bruno Verdi-Neri")
    edit.accept()
    assert edit.result() == 1, edit.error_label.text()
    saved = load_patient("PZ-018", SAFETY, folder)
    assert (saved.full_name, saved.birth_date, saved.record_number) == ("Bruno Verdi-Neri", "1950-01-13", "0042")
    qtbot.waitUntil(lambda: dialog.table.item(0, 1).text() == "Bruno Verdi-Neri", timeout=2000)

    new = dialog.new_patient()
    new.id_edit.setText("PZ-019")
    new.accept()
    assert new.result() == 1
    qtbot.waitUntil(lambda: dialog.selected_id() == "PZ-019", timeout=2000)
    assert len(_ids(dialog)) == 5 and dialog.search.text() == ""


def test_the_therapy_plan_is_edited_with_the_exercises_ranges(qtbot, folder: Path) -> None:
    from app.ui.patients_window import PatientsDialog

    dialog = PatientsDialog(SAFETY, folder)
    qtbot.addWidget(dialog)
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)  # read on a thread of its own
    dialog.search.setText("PZ-017")
    plan = dialog.edit_plan()
    assert plan is not None and plan.step_list.count() == 0
    plan.add_step("trigger_reaching")
    qtbot.waitExposed(plan)
    qtbot.waitUntil(lambda: clipped_texts(plan) == [], timeout=3000)  # once the layout has settled
    assert plan.width() <= 1366 and plan.height() <= 768
    speed = plan.editors["speed_m_s"]
    assert isinstance(speed, QLineEdit)
    speed.setText("0.5")  # the exercise allows 0.02 … 0.3 m/s
    assert "Step 1, Trigger reaching" in plan.error_label.text()
    assert "Speed: 0.5 m/s is above the maximum 0.3 m/s" in plan.error_label.text() and speed.styleSheet()
    plan.accept()  # checked on a thread of its own (#37): its answer is waited for
    qtbot.waitUntil(lambda: not plan.saving, timeout=5000)
    assert plan.result() == 0 and "The plan is not saved" in plan.error_label.text()
    assert load_patient("PZ-017", SAFETY, folder).therapy_plan == []  # nothing saved
    plan.editors["movements"].setText("six")
    assert "'six' is not a number" in plan.error_label.text()
    plan.editors["movements"].setText("6")
    speed.setText("0.2")
    assert plan.error_label.text() == ""
    plan.add_step("free_admittance")
    plan.move_step(-1)  # free admittance first
    assert plan.step_list.currentRow() == 0 and plan.step_list.item(0).text().startswith("1. Free admittance")
    plan.step_list.setCurrentRow(1)
    plan.editors["__note__"].setText("start gently")
    plan.accept()
    qtbot.waitUntil(lambda: not plan.saving, timeout=5000)
    assert plan.result() == 1, plan.error_label.text()
    steps = load_patient("PZ-017", SAFETY, folder).therapy_plan
    assert [s.exercise for s in steps] == ["free_admittance", "trigger_reaching"]
    assert steps[1].params["speed_m_s"] == 0.2 and steps[1].params["movements"] == 6 and steps[1].note == "start gently"
    qtbot.waitUntil(lambda: "Therapy plan:" in dialog.details.text() and "Trigger reaching" in dialog.details.text(),
                    timeout=2000)
    assert dialog.table.item(0, 3).text() == "2 step(s)"


def test_plan_problems_are_said_in_words() -> None:
    problems = plan_problems([PlannedExercise("trigger_reaching", {"speed_m_s": 0.5, "cycles": 3}),
                              PlannedExercise("no_such_exercise", {})])
    texts = [str(p) for p in problems]
    assert any("Step 1" in t and "Speed: 0.5 m/s is above the maximum 0.3 m/s" in t for t in texts)
    assert any("has no parameter 'cycles'" in t for t in texts)
    assert "Step 2: there is no exercise 'no_such_exercise' in the library" in texts


def test_the_operator_is_chosen_at_each_session_start(qtbot, folder: Path) -> None:
    from app.ui.patient_dialog import StartSessionDialog

    settings = QSettings()
    before = settings.value("session/operator", None)
    settings.setValue("session/operator", "dr_rossi")
    try:
        dialog = StartSessionDialog(SAFETY, folder)
        qtbot.addWidget(dialog)
        dialog.reload("PZ-017")
        qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
        ok = dialog.buttons.button(QDialogButtonBox.StandardButton.Ok)
        assert dialog.operator_edit.text() == "" and not ok.isEnabled()  # never kept from the last session
        assert "operator" in dialog.problem.text()
        assert dialog.last_operator_button is not None and "dr_rossi" in dialog.last_operator_button.text()
        qtbot.mouseClick(dialog.last_operator_button, Qt.MouseButton.LeftButton)  # offered: one click
        assert dialog.operator_edit.text() == "dr_rossi" and ok.isEnabled()
        assert dialog.values() == ("PZ-017", "dr_rossi", "")
    finally:
        if before is None:
            settings.remove("session/operator")
        else:
            settings.setValue("session/operator", before)


def test_session_patients_opens_the_list_from_the_window(qtbot, tmp_path: Path, monkeypatch) -> None:
    """Session → Patients… opens the list of patients (not an empty "New patient" form)."""
    from PySide6.QtGui import QAction

    from app.manager import LinarmppManager
    from app.ui.main_window import MainWindow
    from app.ui.patients_window import PatientsDialog
    from tests.fakes import counter_factory

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    save_patient(PatientProfile(patient_id="PZ-100", full_name="Carla Neri"))
    manager = LinarmppManager(AppConfig(), factories={"alpha": counter_factory(tmp_path, "alpha")})
    manager.start()
    try:
        window = MainWindow(manager)
        qtbot.addWidget(window)
        window.show()
        action = next(a for a in window.findChildren(QAction) if a.text() == "&Patients…")
        action.trigger()
        dialog = window._patients_window
        assert isinstance(dialog, PatientsDialog) and dialog.isVisible()
        qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
        assert _ids(dialog) == ["PZ-100"] and "Carla Neri" in dialog.details.text()
        dialog.close()
        window.close()
    finally:
        manager.shutdown(timeout_s=1.0)
