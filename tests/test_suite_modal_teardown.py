"""The suite answers a modal question left waiting in a test's teardown (tests/conftest.py): a window closed after
a failure asked "Stop it and quit?", nobody answered, and the worker waited until the run hung (#38)."""

from __future__ import annotations

import time
from typing import Any

from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QMessageBox

from tests.conftest import MODAL_TEARDOWN_S, _answer_modal_questions


def test_a_waiting_question_is_answered_with_the_button_that_lets_the_teardown_go_on(qtbot: Any) -> None:
    answered: list[str] = []
    started = time.monotonic() - MODAL_TEARDOWN_S  # waited long enough
    timer = QTimer()
    timer.setInterval(50)
    timer.timeout.connect(lambda: _answer_modal_questions(started, answered))
    timer.start()
    box = QMessageBox(QMessageBox.Icon.Question, "Quit", "The exercise is running. Stop it and quit?",
                      QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No)
    box.setDefaultButton(QMessageBox.StandardButton.No)
    try:  # an instance's exec, as QMessageBox.question runs it (a test elsewhere may have replaced that function)
        answer = box.exec()
    finally:
        timer.stop()
    assert answer == QMessageBox.StandardButton.Yes
    assert answered == ["QMessageBox 'Quit': The exercise is running. Stop it and quit?"]


def test_a_question_is_left_alone_before_its_time(qtbot: Any) -> None:
    answered: list[str] = []
    box = QMessageBox(QMessageBox.Icon.Question, "Quit", "Stop it and quit?",
                      QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No)
    qtbot.addWidget(box)
    box.open()  # window-modal, not blocking
    qtbot.waitUntil(box.isVisible)
    _answer_modal_questions(time.monotonic(), answered)
    assert answered == [] and box.isVisible()
    box.done(0)
