"""The FES profile editor: tables ⇄ profile, validation highlighting with reasons, live preview, undo/redo,
save/load (malformed files named by line, nothing changed), keyboard use; plus its screenshot."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from PySide6.QtCore import Qt

from app.core.fes_profile import load_profile
from app.ui.fes_editor import CUR_TRAP0, WID_TRAP0, FesProfileEditor
from app.ui.fes_panel import PROFILES_DIR
from tests.conftest import screenshot_path

FRONTAL = PROFILES_DIR / "frontal_reaching.yaml"
LEVEL, UP0, UP1, DOWN0, DOWN1, BASE = range(6)


@pytest.fixture
def editor(qtbot) -> FesProfileEditor:
    e = FesProfileEditor(load_profile(FRONTAL))
    qtbot.addWidget(e)
    e.show()
    qtbot.waitExposed(e)
    return e


def test_tables_show_the_profile_and_give_it_back(editor: FesProfileEditor) -> None:
    original = load_profile(FRONTAL)
    assert editor.current_table.rowCount() == editor.width_table.rowCount() == 4
    assert editor.current_table.item(0, 1).text() == "anterior deltoid"
    assert editor.current_table.item(0, CUR_TRAP0 + LEVEL).text() == "28"
    assert editor.width_table.item(3, 0).text() == "6"
    assert editor.profile() == original
    assert editor.cell_problems == {}
    assert editor.save_button.isEnabled()


def test_bad_cells_are_highlighted_with_the_reason(editor: FesProfileEditor) -> None:
    editor.set_cell("current", 1, CUR_TRAP0 + LEVEL, "200")
    why = editor.cell_problems[("current", 1, CUR_TRAP0 + LEVEL)]
    assert "200 mA is outside the allowed range 0 .. 126 mA" in why
    item = editor.current_table.item(1, CUR_TRAP0 + LEVEL)
    assert item.toolTip() == why and item.background().color().name() == "#f4b6b6"
    assert editor.profile() is None and not editor.save_button.isEnabled() and not editor.apply_button.isEnabled()
    editor.set_cell("width", 0, WID_TRAP0 + UP1, "abc")
    assert editor.cell_problems[("width", 0, WID_TRAP0 + UP1)] == "'abc' is not a number"
    editor.set_cell("width", 2, WID_TRAP0 + DOWN0, "0.97")  # after the ramp-down end: points decrease
    assert "must not decrease" in editor.cell_problems[("width", 2, WID_TRAP0 + DOWN0)]
    editor.set_cell("current", 3, 0, "1")  # channel 1 twice
    assert editor.cell_problems[("current", 3, 0)] == "channel 1 is already in row 1"
    editor.set_cell("current", 2, 2, "quadruplet")
    assert editor.cell_problems[("current", 2, 2)] == "single, doublet or triplet"
    assert "cell(s) to fix" in editor.problems_label.text()
    for _ in range(5):
        editor.undo_stack.undo()
    assert editor.cell_problems == {} and editor.profile() == load_profile(FRONTAL)
    assert editor.current_table.item(1, CUR_TRAP0 + LEVEL).toolTip() == ""


def test_phase_axis_points_stay_in_0_to_1_but_time_allows_seconds(editor: FesProfileEditor) -> None:
    editor.set_cell("current", 0, CUR_TRAP0 + DOWN1, "2.5")
    assert "outside 0 .. 1" in editor.cell_problems[("current", 0, CUR_TRAP0 + DOWN1)]
    editor.axis_box.setCurrentText("time")
    assert editor.cell_problems == {}
    assert editor.profile().axis == "time"
    editor.undo_stack.undo()  # the axis change
    assert editor.axis_box.currentText() == "phase" and editor.cell_problems


def test_preview_follows_the_tables(editor: FesProfileEditor) -> None:
    x, y = editor.curves[("current", 1)].getData()
    assert x[0] == 0.0 and x[-1] == pytest.approx(1.0)
    assert max(y) == pytest.approx(28.0)
    editor.set_cell("current", 0, CUR_TRAP0 + LEVEL, "12")
    _, y = editor.curves[("current", 1)].getData()
    assert max(y) == pytest.approx(12.0)
    _, w = editor.curves[("width", 5)].getData()
    assert max(w) == pytest.approx(200.0)
    assert set(editor.curves) == {(k, ch) for k in ("current", "width") for ch in (1, 2, 5, 6)}


def test_undo_redo_cells_and_rows(editor: FesProfileEditor) -> None:
    editor.set_cell("width", 0, WID_TRAP0 + LEVEL, "150")
    assert editor.profile().channels[1].pulse_width_us.level == 150.0
    editor.add_channel()
    assert editor.current_table.rowCount() == 5 and editor.current_table.item(4, 0).text() == "3"
    editor.current_table.setCurrentCell(0, 0)
    editor.remove_channel()
    assert sorted(editor.profile().channels) == [2, 3, 5, 6]
    editor.undo_stack.undo()
    editor.undo_stack.undo()
    assert sorted(editor.profile().channels) == [1, 2, 5, 6]
    editor.undo_stack.undo()
    assert editor.profile() == load_profile(FRONTAL)
    assert not editor.undo_stack.canUndo()
    editor.redo_button.click()
    assert editor.profile().channels[1].pulse_width_us.level == 150.0


def test_keyboard_edit_and_undo_shortcut(editor: FesProfileEditor, qtbot) -> None:
    # On a real X server keys and shortcuts reach only the active window (offscreen, every window is).
    editor.activateWindow()
    qtbot.waitActive(editor)
    table = editor.current_table
    table.setFocus()
    table.setCurrentCell(0, CUR_TRAP0 + LEVEL)
    qtbot.keyClick(table, Qt.Key.Key_F2)
    editor_widget = table.focusWidget()
    assert editor_widget is not table
    editor_widget.selectAll()
    qtbot.keyClicks(editor_widget, "15")
    qtbot.keyClick(editor_widget, Qt.Key.Key_Return)  # the delegate commits on the next event loop pass
    qtbot.waitUntil(lambda: editor.profile().channels[1].current_ma.level == 15.0, timeout=1000)
    assert editor.isVisible()  # Return did not press a dialog button
    qtbot.keyClick(table, Qt.Key.Key_Z, Qt.KeyboardModifier.ControlModifier)
    assert editor.profile().channels[1].current_ma.level == 28.0


def test_save_and_load(editor: FesProfileEditor, tmp_path: Path) -> None:
    editor.set_cell("current", 0, 1, "front deltoid")
    target = tmp_path / "mine.yaml"
    saved: list[str] = []
    editor.profile_saved.connect(saved.append)
    assert editor.save_file(target)
    assert saved == [str(target)] and editor.undo_stack.isClean()
    assert load_profile(target).channels[1].muscle == "front deltoid"
    fresh = FesProfileEditor(None)
    assert fresh.load_file(target)
    assert fresh.profile() == load_profile(target)
    fresh.deleteLater()


def test_malformed_file_is_rejected_with_the_line_and_nothing_changes(editor: FesProfileEditor,
                                                                      tmp_path: Path) -> None:
    editor.set_cell("current", 0, CUR_TRAP0 + LEVEL, "21")
    before = editor.profile()
    bad = tmp_path / "bad.yaml"
    bad.write_text(FRONTAL.read_text(encoding="utf-8").replace("mode: single", "mode: quadruplet", 1),
                   encoding="utf-8")
    line = next(i for i, ln in enumerate(bad.read_text(encoding="utf-8").splitlines(), 1) if "quadruplet" in ln)
    assert not editor.load_file(bad)
    assert f"bad.yaml:{line}:" in editor.problems_label.text()
    assert editor.profile() == before and editor.undo_stack.canUndo()


def test_invalid_profile_cannot_be_saved(editor: FesProfileEditor, tmp_path: Path) -> None:
    editor.set_cell("current", 0, CUR_TRAP0 + LEVEL, "-3")
    assert not editor.save_file(tmp_path / "x.yaml")
    assert not (tmp_path / "x.yaml").exists()


def test_screenshot_fes_editor(editor: FesProfileEditor) -> None:
    editor.resize(1280, 720)
    editor.set_cell("current", 1, CUR_TRAP0 + UP1, "0.02")  # before the ramp start: shown as bad
    editor.current_table.setCurrentCell(1, CUR_TRAP0 + UP1)
    out = screenshot_path("fes-editor.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    image = editor.grab().toImage()
    assert image.width() >= 1200
    tmp = out.with_suffix(".tmp.png")
    assert image.save(str(tmp))
    shutil.move(tmp, out)


def test_a_bad_cell_keeps_the_last_valid_preview(editor: FesProfileEditor) -> None:
    """Issue #19: one invalid cell blanked both plots."""
    editor.set_cell("current", 0, CUR_TRAP0 + LEVEL, "12")
    editor.set_cell("current", 0, CUR_TRAP0 + LEVEL, "abc")
    assert ("current", 0, CUR_TRAP0 + LEVEL) in editor.cell_problems
    assert set(editor.curves) == {(k, ch) for k in ("current", "width") for ch in (1, 2, 5, 6)}
    curve = editor.curves[("current", 1)]
    _, y = curve.getData()
    assert max(y) == pytest.approx(12.0), "the row's last valid values, not the bad cell"
    assert curve.opts["pen"].style() == Qt.PenStyle.DashLine
    editor.set_cell("current", 0, CUR_TRAP0 + LEVEL, "14")
    assert editor.curves[("current", 1)].opts["pen"].style() == Qt.PenStyle.SolidLine
