"""Issue #36, small things a clinician meets every day, outside the main window: the run summary fits a 1366×768
screen (its Close button on it); the patient picker at the session's start shows names with the ids and record
numbers and is searched; a new patient's therapy plan is made from the session-start dialog (the first run's
path); the mouse wheel over a number box or a drop-down list scrolls the form unless the box has the focus."""

from __future__ import annotations

import shutil
import subprocess
import threading
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import QPoint, QPointF, QRect, Qt
from PySide6.QtGui import QScreen, QWheelEvent
from PySide6.QtWidgets import (
    QApplication,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QPushButton,
    QScrollArea,
    QSpinBox,
    QWidget,
)

from app.core.config import AppConfig
from app.therapy.patients import PatientProfile, load_patient, save_patient
from tests.conftest import screenshot_path
from tests.run_sessions import RunSpec, write_run_session

SAFETY = AppConfig().safety
TRIGGER = "Trigger reaching (grip-triggered passive movements)"


# ------------------------------------------------------------------------------------------- the run summary
def test_the_run_summary_fits_a_1366x768_screen(qtbot, tmp_path: Path, monkeypatch) -> None:
    from app.ui.session_summary import SessionSummaryDialog

    area = QRect(0, 0, 1366, 740)  # 1366×768 below a 28 px panel
    monkeypatch.setattr(QScreen, "availableGeometry", lambda _self: QRect(area))
    folder = write_run_session(tmp_path / "P1" / "20260301-100000",
                               [RunSpec(TRIGGER, "trigger_reaching", reps=12, failed=(3, 7), reason="refused",
                                        detail="FES current above the cap")])
    dialog = SessionSummaryDialog(folder)
    qtbot.addWidget(dialog)
    dialog.show()
    qtbot.waitExposed(dialog)
    title_bar = 30  # the window manager's, above the dialog
    assert dialog.minimumSizeHint().height() + title_bar <= area.height(), dialog.minimumSizeHint()
    assert dialog.frameGeometry().height() <= area.height() and dialog.height() + title_bar <= area.height()
    close = next(b for b in dialog.findChildren(QPushButton) if b.text() == "&Close")
    bottom = close.mapTo(dialog, QPoint(0, close.height())).y()
    assert close.isVisible() and bottom <= dialog.height(), (bottom, dialog.height())
    dialog.grab().save(str(screenshot_path("run-summary-1366.png")))


# ------------------------------------------------------------------------------------------- the patient picker
@pytest.fixture
def patients(tmp_path: Path) -> Path:
    folder = tmp_path / "patients"
    folder.mkdir()
    save_patient(PatientProfile("P-017", full_name="Bianchi Maria", record_number="MRN-20417"), folder, SAFETY)
    save_patient(PatientProfile("P-018", full_name="Rossi Anna", record_number="MRN-31002"), folder, SAFETY)
    save_patient(PatientProfile("PSEUDO-9"), folder, SAFETY)
    return folder


def _items(box: QComboBox) -> list[str]:
    return [box.itemText(i) for i in range(box.count())]


def test_the_patient_picker_shows_names_and_is_searched(qtbot, patients: Path) -> None:
    from app.ui.patient_dialog import StartSessionDialog

    dialog = StartSessionDialog(SAFETY, patients)
    qtbot.addWidget(dialog)
    assert "Loading patients" in dialog.problem.text()  # read off the window's thread
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
    assert _items(dialog.patient_box) == ["Bianchi Maria — P-017 (record MRN-20417)",
                                          "Rossi Anna — P-018 (record MRN-31002)", "PSEUDO-9"]
    for search, found in (("rossi", ["P-018"]), ("MRN-204", ["P-017"]), ("pseudo", ["PSEUDO-9"]),
                          ("maria bianchi", ["P-017"]), ("", ["P-017", "P-018", "PSEUDO-9"])):
        dialog.search_edit.setText(search)
        assert [dialog.patient_box.itemData(i) for i in range(dialog.patient_box.count())] == found, search
    dialog.search_edit.setText("nobody")
    assert dialog.patient_box.count() == 0 and "No patient matches" in dialog.problem.text()
    dialog.search_edit.setText("anna")
    dialog.operator_edit.setText("Dr Verdi")
    assert dialog.values() == ("P-018", "Dr Verdi", "")


def test_a_reload_while_the_first_read_runs_lists_what_the_last_read_found(qtbot, patients: Path,
                                                                            monkeypatch) -> None:
    """The patients are read on a thread; a reload (a form closed) while the first read still runs makes two
    readers, and the first may end last: its stale list must not take the place of the second's (the dialog then
    said "Loading patients…" for ever: a loaded run of the suite failed on it)."""
    import app.ui.patient_dialog as patient_dialog

    real = patient_dialog.list_patients
    calls: list[int] = []
    first_may_end, second_ended = threading.Event(), threading.Event()

    def first_slow(folder: Any, safety: Any) -> Any:
        calls.append(1)
        if len(calls) == 1:
            first_may_end.wait(5.0)
            return real(folder, safety)
        found = real(folder, safety)
        second_ended.set()
        return found

    monkeypatch.setattr(patient_dialog, "list_patients", first_slow)
    dialog = patient_dialog.StartSessionDialog(SAFETY, patients)
    qtbot.addWidget(dialog)
    dialog.reload("P-018")
    qtbot.waitUntil(second_ended.is_set, timeout=5000)
    first_may_end.set()
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
    assert dialog.patient_box.currentData() == "P-018" and dialog.patient_box.count() == 3


def test_a_new_patients_plan_is_made_from_the_session_start(qtbot, patients: Path) -> None:
    """The first run: from the session-start dialog (window-modal over the window) to a new patient with a
    two-step plan, without leaving it. Actions: New patient… (1), the id (2), Save (3), Therapy plan… (4), Add to
    plan (5), the second exercise (6), Add to plan (7), Save (8); then the operator (9) and Start session (10)."""
    from app.ui.patient_dialog import PatientDialog, StartSessionDialog
    from app.ui.plan_dialog import PlanDialog

    dialog = StartSessionDialog(SAFETY, patients)
    qtbot.addWidget(dialog)
    dialog.show()
    form = dialog.new_patient()  # 1
    assert isinstance(form, PatientDialog) and form.isVisible()
    form.id_edit.setText("P-100")  # 2
    form.name_edit.setText("Verdi Carla")
    form.accept()  # 3
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)  # the list read again, the new patient chosen
    assert dialog.patient_box.currentData() == "P-100" and dialog.plan_button.isEnabled()
    plan = dialog.edit_plan()  # 4
    assert isinstance(plan, PlanDialog) and plan.isVisible() and plan.profile.patient_id == "P-100"
    plan.add_button.click()  # 5: the library's first exercise
    row = next(i for i in range(plan.library_list.count())
               if plan.library_list.item(i).data(Qt.ItemDataRole.UserRole) == "free_admittance")
    plan.library_list.setCurrentRow(row)  # 6
    plan.add_button.click()  # 7
    plan.accept()  # 8 (saved on a thread of its own, #37: its answer is waited for)
    qtbot.waitUntil(lambda: not plan.saving, timeout=5000)
    assert plan.saved is not None, plan.error_label.text()
    qtbot.waitUntil(lambda: dialog.loaded, timeout=5000)
    assert [s.exercise for s in load_patient("P-100", SAFETY, patients).therapy_plan][1] == "free_admittance"
    assert len(load_patient("P-100", SAFETY, patients).therapy_plan) == 2
    dialog.operator_edit.setText("Dr Verdi")  # 9
    assert dialog.values()[:2] == ("P-100", "Dr Verdi") and not dialog.problem.text()  # 10: Start session


# ------------------------------------------------------------------------------------------- the mouse wheel
def _wheel(widget: QWidget, notches: int = 1) -> QWheelEvent:
    centre = QPointF(widget.width() / 2, widget.height() / 2)
    event = QWheelEvent(centre, QPointF(widget.mapToGlobal(centre.toPoint())), QPoint(0, 0),
                        QPoint(0, -120 * notches), Qt.MouseButton.NoButton, Qt.KeyboardModifier.NoModifier,
                        Qt.ScrollPhase.NoScrollPhase, False)
    QApplication.sendEvent(widget, event)
    return event


def _long_form(qtbot) -> tuple[QScrollArea, QDoubleSpinBox, QSpinBox, QComboBox]:
    scroll = QScrollArea()
    qtbot.addWidget(scroll)
    form = QWidget()
    layout = QFormLayout(form)
    current = QDoubleSpinBox()
    current.setRange(0, 100)
    current.setValue(20.0)
    count = QSpinBox()
    count.setRange(0, 50)
    count.setValue(8)
    side = QComboBox()
    side.addItems(["left", "right", "both"])
    layout.addRow("Current", current)
    layout.addRow("Movements", count)
    layout.addRow("Side", side)
    for k in range(40):  # a long form: the scroll area has somewhere to scroll
        layout.addRow(f"Row {k}", QSpinBox())
    scroll.setWidget(form)
    scroll.setGeometry(100, 100, 300, 200)
    scroll.show()
    qtbot.waitExposed(scroll)
    return scroll, current, count, side


def test_the_mouse_wheel_changes_a_box_only_when_it_has_the_focus(qtbot) -> None:
    from app.ui.widgets import install_wheel_guard

    install_wheel_guard()
    assert install_wheel_guard() is install_wheel_guard()  # one guard for the application
    scroll, current, count, side = _long_form(qtbot)
    assert current.focusPolicy() == Qt.FocusPolicy.StrongFocus  # the wheel alone gives no focus
    assert side.focusPolicy() != Qt.FocusPolicy.WheelFocus
    for box, target in ((current, current.lineEdit()), (count, count.lineEdit()), (side, side)):
        event = _wheel(target)
        assert (current.value(), count.value(), side.currentIndex()) == (20.0, 8, 0), box
        assert not event.isAccepted()  # left to the form: a real wheel goes on to the scroll area
    scroll.activateWindow()
    qtbot.waitUntil(scroll.isActiveWindow, timeout=3000)
    count.setFocus()
    qtbot.waitUntil(count.hasFocus, timeout=3000)
    _wheel(count)  # the box the clinician clicked into: the wheel sets it
    assert count.value() == 7


@pytest.mark.skipif(shutil.which("xdotool") is None, reason="xdotool is not installed")
def test_a_real_wheel_over_a_box_scrolls_the_form(qtbot) -> None:
    """The X server's own wheel event (xdotool), which Qt passes on to the scroll area when the box leaves it."""
    from app.ui.widgets import install_wheel_guard

    if QApplication.platformName() != "xcb":
        pytest.skip("needs an X server (Xvfb)")
    install_wheel_guard()
    scroll, current, _count, _side = _long_form(qtbot)
    bar = scroll.verticalScrollBar()
    centre = current.mapToGlobal(QPoint(current.width() // 2, current.height() // 2))
    subprocess.run(["xdotool", "mousemove", str(centre.x()), str(centre.y()), "click", "5", "click", "5"],
                   check=True, timeout=10)
    qtbot.waitUntil(lambda: bar.value() > 0, timeout=3000)
    assert current.value() == 20.0
