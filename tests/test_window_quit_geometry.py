"""Issue #36, small things a clinician meets every day, in the main window: Ctrl+Q (File → Quit, the window's own
close button) in the middle of an exercise asks first, with End session's words, and never loses unsaved edits
of the Script tab's editor (Save / Discard / Cancel); a geometry made on another screen is not restored there
(each screen size keeps its own), the maximised state is remembered — the test opens the window on one screen
size and reopens it on the other, both ways."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import QEventLoop, QRect, QSettings, Qt, QTimer
from PySide6.QtGui import QAction, QKeySequence, QScreen
from PySide6.QtWidgets import QApplication, QMessageBox

from app.core.config import AppConfig
from app.core.runs import Program
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow

TRIGGER = "Trigger reaching (grip-triggered passive movements)"


@pytest.fixture
def manager() -> Any:
    m = LinarmppManager(AppConfig(), factories={})  # no device: the window alone
    yield m
    m.shutdown()


class Questions(list):
    """The questions asked, (title, text), and the answers to give, in order (No when none is left)."""

    answers: list[QMessageBox.StandardButton]


@pytest.fixture
def asked(monkeypatch: pytest.MonkeyPatch) -> Questions:
    """Every question the window asks; answered from ``asked.answers``."""
    questions = Questions()
    answers: list[QMessageBox.StandardButton] = []

    def question(_parent: Any, title: str, text: str, *args: Any, **kwargs: Any) -> QMessageBox.StandardButton:
        questions.append((title, text))
        return answers.pop(0) if answers else QMessageBox.StandardButton.No

    monkeypatch.setattr(QMessageBox, "question", staticmethod(question))
    monkeypatch.setattr(QApplication, "quit", staticmethod(lambda: None))  # the test's application stays
    questions.answers = answers
    return questions


def questions_on_quit(window: MainWindow) -> list[tuple[str, str]]:
    """Press Quit (Ctrl+Q's action) in ``window`` from its event loop, answer "No" / "Cancel" to whatever it asks,
    and return the questions, (title, text): [] when it quit without asking. Reusable (the clinician's day)."""
    questions: list[tuple[str, str]] = []

    def question(_parent: Any, title: str, text: str, *args: Any, **kwargs: Any) -> QMessageBox.StandardButton:
        questions.append((title, text))
        buttons = args[0] if args else kwargs.get("buttons", QMessageBox.StandardButton.No)
        cancel = QMessageBox.StandardButton.Cancel
        return cancel if buttons & cancel else QMessageBox.StandardButton.No

    original = QMessageBox.question
    QMessageBox.question = staticmethod(question)  # type: ignore[method-assign]
    try:
        _trigger_in_loop(_quit_action(window))
    finally:
        QMessageBox.question = original  # type: ignore[method-assign]
    return questions


def _quit_action(window: MainWindow) -> QAction:
    return next(a for a in window.findChildren(QAction) if a.text().replace("&", "") == "Quit")


def _trigger_in_loop(action: QAction) -> None:
    """As in the running app: Quit is triggered from inside the event loop."""
    loop = QEventLoop()
    QTimer.singleShot(0, action.trigger)
    QTimer.singleShot(0, loop.quit)
    loop.exec()


def test_ctrl_q_in_the_middle_of_an_exercise_asks_first(qtbot, manager, asked) -> None:
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    run = manager.runs.start(Program("exercise", "trigger_reaching", TRIGGER, "x"), (), "exercises_tab", "Dr Rossi")
    quit_action = _quit_action(window)
    assert quit_action.shortcut() == QKeySequence(QKeySequence.StandardKey.Quit)  # Ctrl+Q
    _trigger_in_loop(quit_action)
    assert asked and asked[0][0] == "Quit", asked
    assert f"“{TRIGGER}” is running." in asked[0][1]
    assert "Stimulation stops and the robot goes idle." in asked[0][1]  # End session's words
    assert window.isVisible() and manager.runs.get(run.run_id).running  # "No": nothing stopped, nothing closed
    window.close()  # the window's own close button asks the same
    assert len(asked) == 2 and asked[1][0] == "Quit" and window.isVisible()
    assert questions_on_quit(window)[0][0] == "Quit" and window.isVisible()  # the reusable form says the same
    manager.runs.end(run.run_id, "finished")
    _trigger_in_loop(quit_action)  # nothing runs any more: Quit quits, without a question
    assert len(asked) == 2 and not window.isVisible()


def test_quit_never_loses_unsaved_script_edits(qtbot, manager, asked, tmp_path: Path) -> None:
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    console = window.frames["CommandsFrame"].panels["ScriptConsole"]
    script = tmp_path / "reach.py"
    script.write_text("print('saved')\n")
    console.load_file(script)
    console.editor.setFocus()
    qtbot.keyClicks(console.editor, "# edited")  # typed, as a therapist does
    assert console.editor.document().isModified()
    answers = asked.answers
    answers.append(QMessageBox.StandardButton.Cancel)
    _trigger_in_loop(_quit_action(window))
    assert asked and asked[-1][0] == "Unsaved script", asked
    assert "reach.py has changes that are not saved" in asked[-1][1]
    assert window.isVisible() and "# edited" in console.editor.toPlainText()  # Cancel: nothing lost
    answers.append(QMessageBox.StandardButton.Discard)  # Discard: the window may close, the file is untouched
    assert window.may_quit() and script.read_text() == "print('saved')\n"
    answers.append(QMessageBox.StandardButton.Save)
    _trigger_in_loop(_quit_action(window))
    assert "# edited" in script.read_text() and not window.isVisible()  # Save: written, then quit


# ------------------------------------------------------------------------------------------- geometry
SCREENS = {"laptop": QRect(0, 0, 1366, 740), "desk": QRect(0, 0, 1920, 1040)}  # available areas (below a panel)


def _open_on(qtbot, manager: LinarmppManager, monkeypatch: pytest.MonkeyPatch, screen: str) -> MainWindow:
    monkeypatch.setattr(QScreen, "availableGeometry", lambda _self, area=SCREENS[screen]: QRect(area))
    window = MainWindow(manager)
    qtbot.addWidget(window)
    return window


def _size(window: MainWindow) -> tuple[int, int]:
    g = window.normalGeometry() if window.isMaximized() else window.geometry()
    return g.width(), g.height()


def _close(window: MainWindow) -> None:
    window.close()
    assert not window.isVisible()


def test_a_geometry_made_on_another_screen_is_not_restored_there(qtbot, manager, asked, monkeypatch) -> None:
    settings = QSettings()
    for key in ("main/geometry", "main/state"):
        settings.remove(key)
    # On the 1366×768 laptop, the therapist makes the window 1272×720, not maximised, and quits.
    window = _open_on(qtbot, manager, monkeypatch, "laptop")
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.setGeometry(40, 10, 1272, 720)
    _close(window)
    # Reopened on the 1920×1080 desk: the whole screen, not the laptop's 1272×720 (it was, #36).
    window = _open_on(qtbot, manager, monkeypatch, "desk")
    assert window.isMaximized() or _size(window) == (1920, 1040), _size(window)
    assert window.geometry().width() >= 1900 or window.isMaximized()
    # There the window is made 1500×900 and closed; back on the laptop it is not squeezed into it (1011×718 with
    # clipped labels, #36): the laptop's own.
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.setGeometry(100, 60, 1500, 900)
    _close(window)
    window = _open_on(qtbot, manager, monkeypatch, "laptop")
    assert not window.isMaximized() and _size(window) == (1272, 720), _size(window)
    _close(window)
    # And the desk's own again, both ways.
    window = _open_on(qtbot, manager, monkeypatch, "desk")
    assert not window.isMaximized() and _size(window) == (1500, 900), _size(window)
    # Maximised is remembered.
    window.setWindowState(Qt.WindowState.WindowMaximized)
    _close(window)
    window = _open_on(qtbot, manager, monkeypatch, "desk")
    assert window.isMaximized()
    _close(window)
