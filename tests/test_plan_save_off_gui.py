"""Saving a therapy plan never holds the window's thread (issue #37): the plan is read, checked and written on a
thread of its own while the form says it is saving; a refusal reaches the form as the same sentence, with nothing
of what was typed lost; success closes it as before (and then, on the window's thread, the running session)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer

from app.core.config import AppConfig
from app.therapy.patients import PatientProfile, load_patient, save_patient

SAFETY = AppConfig().safety


def _dialog(qtbot: Any, folder: Path) -> Any:
    from app.ui.plan_dialog import PlanDialog

    save_patient(PatientProfile(patient_id="PZ-SAVE"), folder, SAFETY)
    dialog = PlanDialog(load_patient("PZ-SAVE", SAFETY, folder), SAFETY, folder)
    qtbot.addWidget(dialog)
    dialog.show()
    dialog.add_step("trigger_reaching")
    return dialog


def test_the_window_turns_while_the_plan_is_checked_and_the_form_says_it_is_saving(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    """The check is made slow here on purpose: it waits (≤ 1 s) for a zero-timer armed on the window's thread just
    before Save. Run on the window's thread, the timer cannot fire until the check is over (it waits in vain);
    on a thread of its own, it fires at once — and meanwhile the form is held and says so."""
    from app.ui import plan_dialog

    dialog = _dialog(qtbot, tmp_path)
    turned = threading.Event()
    release = threading.Event()
    seen: list[bool] = []
    checked_on: list[str] = []
    real_check = plan_dialog.prescription_problems

    def slow_check(*args: Any, **kwargs: Any) -> Any:
        checked_on.append(threading.current_thread().name)
        seen.append(turned.wait(1.0))  # did the window's thread turn while this runs?
        release.wait(1.0)
        return real_check(*args, **kwargs)

    monkeypatch.setattr(plan_dialog, "prescription_problems", slow_check)
    QTimer.singleShot(0, turned.set)
    dialog.accept()
    qtbot.waitUntil(lambda: bool(seen), timeout=3000)
    assert seen == [True], f"the window's thread did not turn while the plan was checked (on {checked_on})"
    assert checked_on != [threading.main_thread().name]
    # saving: said, held, nothing submitted twice, Escape and Cancel wait for the archive's answer
    assert dialog.saving and "Saving the plan" in dialog.error_label.text()
    assert not any(b.isEnabled() for b in dialog.buttons.buttons()) and not dialog.editing.isEnabled()
    qtbot.keyClick(dialog, Qt.Key.Key_Escape)
    dialog.reject()
    dialog.accept()  # a second Save while the first runs: nothing
    assert dialog.isVisible() and dialog.result() == 0
    release.set()
    with qtbot.waitSignal(dialog.finished, timeout=3000) as finished:
        pass
    assert finished.args == [dialog.DialogCode.Accepted] and len(checked_on) == 1
    assert dialog.saved is not None and not dialog.saving
    assert [s.exercise for s in load_patient("PZ-SAVE", SAFETY, tmp_path).therapy_plan] == ["trigger_reaching"]


def test_a_write_error_is_one_sentence_and_the_form_keeps_what_was_typed(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.archive import station

    dialog = _dialog(qtbot, tmp_path)
    dialog.editors["movements"].setText("7")
    steps_before = [dict(s["values"]) for s in dialog.steps]

    def full_disk(*_a: Any, **_k: Any) -> Any:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(station, "save_profile", full_disk)
    dialog.accept()
    qtbot.waitUntil(lambda: not dialog.saving, timeout=3000)
    assert dialog.error_label.text() == "The plan is not saved: [Errno 28] No space left on device"
    assert dialog.isVisible() and dialog.result() == 0 and dialog.saved is None
    assert [dict(s["values"]) for s in dialog.steps] == steps_before and dialog.editors["movements"].text() == "7"
    assert all(b.isEnabled() for b in dialog.buttons.buttons()) and dialog.editing.isEnabled()
    assert load_patient("PZ-SAVE", SAFETY, tmp_path).therapy_plan == []  # nothing half-applied
    monkeypatch.undo()
    dialog.accept()  # the same form, saved once the disk has room
    qtbot.waitUntil(lambda: dialog.result() == dialog.DialogCode.Accepted, timeout=3000)
    assert load_patient("PZ-SAVE", SAFETY, tmp_path).therapy_plan[0].params["movements"] == 7


def test_an_unexpected_failure_of_the_save_is_a_sentence_not_a_form_left_saving(
        qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    from app.ui import plan_dialog

    dialog = _dialog(qtbot, tmp_path)

    def broken(*_a: Any, **_k: Any) -> Any:
        raise RuntimeError("the library could not be read")

    monkeypatch.setattr(plan_dialog, "prescription_problems", broken)
    dialog.accept()
    qtbot.waitUntil(lambda: not dialog.saving, timeout=3000)
    assert dialog.error_label.text() == "The plan is not saved: the library could not be read"
    assert dialog.isVisible() and dialog.result() == 0 and len(dialog.steps) == 1


def test_the_running_session_hears_the_saved_plan_on_the_windows_thread_after_the_form_closed(
        qtbot: Any, tmp_path: Path) -> None:
    """Delivered = shown: the session's patient gets the record the form saved (its plan, its version) once, on
    the window's thread, after the form has closed as accepted (the Patients window's apply_to_session, as before:
    the save's thread never reaches the manager, its supervisor or its devices); the window says what changed."""
    from types import SimpleNamespace

    from app.ui.patients_window import PatientsDialog

    save_patient(PatientProfile(patient_id="PZ-SESSION"), tmp_path, SAFETY)
    calls: list[tuple[Any, Any, str, bool]] = []
    manager = SimpleNamespace(patient_profile=load_patient("PZ-SESSION", SAFETY, tmp_path), recorder=object(),
                              operator="dr_verdi")

    def update_session_profile(profile: Any, version: Any = None) -> list[str]:
        calls.append((profile, version, threading.current_thread().name, plan.isVisible()))
        return ["the plan's length 0 → 1"]

    manager.update_session_profile = update_session_profile
    patients = PatientsDialog(SAFETY, tmp_path, manager=manager)
    qtbot.addWidget(patients)
    qtbot.waitUntil(lambda: patients.loaded, timeout=5000)
    patients.search.setText("PZ-SESSION")
    qtbot.waitUntil(lambda: patients.selected_id() == "PZ-SESSION", timeout=3000)
    plan = patients.edit_plan()
    assert plan is not None
    plan.add_step("trigger_reaching")
    plan.accept()
    assert calls == []  # not while it is saved
    qtbot.waitUntil(lambda: bool(calls), timeout=5000)
    ((profile, version, thread, form_open),) = calls
    saved = load_patient("PZ-SESSION", SAFETY, tmp_path)
    assert profile == saved == plan.saved and [s.exercise for s in profile.therapy_plan] == ["trigger_reaching"]
    assert version == (plan.version or None)  # a YAML folder has no versions; an archive record has one
    assert thread == threading.main_thread().name and not form_open
    assert "Applied to PZ-SESSION's running session at once" in patients.session_note.text()


def _session_manager(monkeypatch: Any) -> Any:
    """A manager without devices whose session's patient is PZ-RUN (a stand-in recorder: the check reads only the
    profile, the configured limits and the exercise library); its records are kept with the thread they came on."""
    from types import SimpleNamespace

    from app.manager import LinarmppManager

    manager = LinarmppManager(AppConfig(), factories={})
    manager.recorder = SimpleNamespace(folder=Path("PZ-RUN"))
    manager.patient_profile = PatientProfile(patient_id="PZ-RUN")
    manager.operator = "dr_verdi"
    records: list[tuple[str, dict[str, Any], str]] = []
    real_record = manager.record_event

    def record_event(kind: str, who: str = "", **data: Any) -> None:
        records.append((kind, data, threading.current_thread().name))
        real_record(kind, who, **data)

    monkeypatch.setattr(manager, "record_event", record_event)
    manager.records = records
    return manager


def _with_a_slow_plan_check(monkeypatch: Any) -> tuple[threading.Event, list[bool], list[str], threading.Event]:
    """The session's plan check made slow: it waits (≤ 1 s) for a zero-timer armed on the window's thread; run on
    the window's thread it waits in vain (the timer fires only once the check is over)."""
    from app.therapy import patients

    turned, release = threading.Event(), threading.Event()
    seen: list[bool] = []
    checked_on: list[str] = []
    real_check = patients.prescription_problems

    def slow_check(*args: Any, **kwargs: Any) -> Any:
        checked_on.append(threading.current_thread().name)
        seen.append(turned.wait(1.0))
        release.wait(1.0)
        return real_check(*args, **kwargs)

    monkeypatch.setattr(patients, "prescription_problems", slow_check)
    return turned, seen, checked_on, release


def _plan_with_problems(**robot: float) -> PatientProfile:
    from app.therapy.patients import PatientRobotLimits, PlannedExercise

    return PatientProfile(patient_id="PZ-RUN", robot=PatientRobotLimits(**robot),
                          therapy_plan=[PlannedExercise("trigger_reaching", {"speed_m_s": 0.2})])


def test_the_running_sessions_plan_check_runs_off_the_windows_thread_and_the_lowered_cap_applies_at_once(
        qtbot: Any, monkeypatch: Any) -> None:
    """After the plan form closed, the running session applies the saved profile and checks its plan (~25 ms on the
    window's thread before): the limits the therapist lowered reach the supervisor before the call returns; the
    check runs on a thread of its own while the window turns; its answer (the plan's problems) is recorded on the
    window's thread."""
    manager = _session_manager(monkeypatch)
    turned, seen, checked_on, release = _with_a_slow_plan_check(monkeypatch)
    QTimer.singleShot(0, turned.set)
    changes = manager.update_session_profile(_plan_with_problems(max_velocity_m_s=0.05))
    assert manager.supervisor.robot.max_velocity_m_s == 0.05  # the lowered cap: at once, by the supervisor
    assert changes and manager.records[0][0] == "patient_profile_updated"
    qtbot.waitUntil(lambda: bool(seen), timeout=3000)
    release.set()
    assert seen == [True], f"the window's thread did not turn while the session's plan was checked (on {checked_on})"
    assert checked_on != [threading.main_thread().name]
    qtbot.waitUntil(lambda: any(kind == "plan_problems" for kind, _d, _t in manager.records), timeout=3000)
    ((problems, thread),) = [(d["problems"], t) for kind, d, t in manager.records if kind == "plan_problems"]
    assert thread == threading.main_thread().name
    assert len(problems) == 1 and "0.05" in problems[0], problems  # 0.2 m/s: above the lowered cap only


def test_a_plan_check_overtaken_by_a_newer_profile_or_the_sessions_end_records_nothing(
        qtbot: Any, monkeypatch: Any) -> None:
    """Each check carries the generation of the profile it read: an answer for a profile the session no longer
    holds (saved again meanwhile, or the session ended) is dropped — only the newest profile's problems are
    recorded, never a mix of two."""
    manager = _session_manager(monkeypatch)
    turned, seen, _checked_on, release = _with_a_slow_plan_check(monkeypatch)
    turned.set()
    manager.update_session_profile(_plan_with_problems(max_velocity_m_s=0.05))
    qtbot.waitUntil(lambda: len(seen) == 1, timeout=3000)
    manager.update_session_profile(PatientProfile(patient_id="PZ-RUN"))  # the plan emptied: nothing to refuse
    release.set()
    qtbot.waitUntil(lambda: len(seen) == 2 and not manager.plan_checks_pending, timeout=3000)
    assert [kind for kind, _d, _t in manager.records if kind == "plan_problems"] == []
    manager.update_session_profile(_plan_with_problems(max_velocity_m_s=0.05))
    manager.recorder = None  # the session ended before the answer came
    qtbot.waitUntil(lambda: len(seen) == 3 and not manager.plan_checks_pending, timeout=3000)
    assert [kind for kind, _d, _t in manager.records if kind == "plan_problems"] == []
