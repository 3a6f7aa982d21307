"""The FES profile editor (seed Fig. 15): two tables define each channel's current and pulse-width
trapezoids, a live preview plots both profiles, bad cells are highlighted with the reason as tooltip,
and every edit can be undone.

Rows are channels and match between the two tables (the channel, muscle and pulse group are edited in
the current table; the pulse-width table shows the channel). Cells are plain text, parsed and
validated on every change with the same checks as a profile file (``app.core.fes_profile``); a profile can
only be saved or applied when nothing is wrong.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from html import escape
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QModelIndex, QPersistentModelIndex, Qt, Signal
from PySide6.QtGui import QAction, QBrush, QColor, QKeySequence, QUndoCommand, QUndoStack
from PySide6.QtWidgets import (
    QAbstractItemView,
    QComboBox,
    QDialog,
    QDoubleSpinBox,
    QFormLayout,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QPushButton,
    QSplitter,
    QStyledItemDelegate,
    QStyleOptionViewItem,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.core.fes_profile import (
    ChannelProfile,
    FesProfile,
    FesProfileError,
    Trapezoid,
    load_profile,
    save_profile,
)
from app.core.paths import fes_profiles_dir
from app.core.resources import RESOURCES
from app.safety.fes_limits import FesLimits, profile_limit_problems
from app.ui import file_dialogs
from app.ui.file_dialogs import is_bundled
from app.ui.theme import colours, curve_colour
from app.wire.sciencemode import CHANNELS, CHANNELS_TEXT, MAX_CURRENT_MA, MAX_PULSE_WIDTH_US, PulseMode

BUNDLED_PROFILES = RESOURCES / "fes_profiles"

# () -> (the limits Apply will meet, the patient's id for the messages); (None, "") when not known.
LimitsProvider = Callable[[], tuple[FesLimits | None, str]]

log = logging.getLogger(__name__)

TRAP_KEYS = ("level", "ramp_up_start", "ramp_up_end", "ramp_down_start", "ramp_down_end", "baseline")
TRAP_TITLES = ("Level", "Up start", "Up end", "Down start", "Down end", "Baseline")
TRAP_TIPS = ("The plateau value", "Where the ramp up from the baseline starts (s or phase 0..1)",
             "Where the ramp up reaches the level", "Where the ramp down from the level starts",
             "Where the ramp down reaches the baseline", "The value before the ramp up and after the ramp down")
CURRENT_COLUMNS = ("Ch", "Muscle", "Group", *(f"{t} (mA)" if t in ("Level", "Baseline") else t
                                             for t in TRAP_TITLES))
WIDTH_COLUMNS = ("Ch", *(f"{t} (µs)" if t in ("Level", "Baseline") else t for t in TRAP_TITLES))
CUR_TRAP0 = 3  # first trapezoid column in the current table
WID_TRAP0 = 1
MODES = tuple(m.name.lower() for m in PulseMode)
PREVIEW_POINTS = 400
BAD_BACKGROUND = "#f4b6b6"

Cell = tuple[str, int, int]  # (table "current" | "width", row, column)


def _fmt(v: float) -> str:
    return f"{v:g}"


def safe_file_stem(name: str) -> str:
    """A file name from a profile's name ("Wrist extension, 8 s" -> "Wrist_extension_8_s")."""
    stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in name.strip()).strip("_")
    while "__" in stem:
        stem = stem.replace("__", "_")
    return stem or "profile"


def default_profile() -> FesProfile:
    return FesProfile("New profile", "phase", {
        1: ChannelProfile(Trapezoid(20.0, (0.0, 0.2), (0.4, 0.5)), Trapezoid(200.0, (0.0, 0.1), (0.45, 0.5)), ""),
    })


class _CellEdit(QUndoCommand):
    def __init__(self, editor: FesProfileEditor, cell: Cell, old: str, new: str) -> None:
        super().__init__(f"edit {cell[0]} row {cell[1] + 1} column {cell[2] + 1}")
        self.editor, self.cell, self.old, self.new = editor, cell, old, new

    def redo(self) -> None:
        self.editor._write_cell(self.cell, self.new)

    def undo(self) -> None:
        self.editor._write_cell(self.cell, self.old)


class _RowsEdit(QUndoCommand):
    """Replace all rows (add / remove channel, load a file): the two tables' texts before and after."""

    def __init__(self, editor: FesProfileEditor, title: str, old: list[list[list[str]]],
                 new: list[list[list[str]]]) -> None:
        super().__init__(title)
        self.editor, self.old, self.new = editor, old, new

    def redo(self) -> None:
        self.editor._write_rows(self.new)

    def undo(self) -> None:
        self.editor._write_rows(self.old)


class _FieldEdit(QUndoCommand):
    def __init__(self, title: str, apply: Callable[[str], None], old: str, new: str) -> None:
        super().__init__(title)
        self.apply, self.old, self.new = apply, old, new

    def redo(self) -> None:
        self.apply(self.new)

    def undo(self) -> None:
        self.apply(self.old)


class _ModeDelegate(QStyledItemDelegate):
    """The pulse-group cell edits with a combo box (still plain text in the table, so undo sees it)."""

    def createEditor(self, parent: QWidget, option: QStyleOptionViewItem,
                     index: QModelIndex | QPersistentModelIndex) -> QWidget:
        box = QComboBox(parent)
        box.addItems(list(MODES))
        return box

    def setEditorData(self, editor: QWidget, index: QModelIndex | QPersistentModelIndex) -> None:
        assert isinstance(editor, QComboBox)
        editor.setCurrentText(str(index.data() or "single"))

    def setModelData(self, editor: QWidget, model: object, index: QModelIndex | QPersistentModelIndex) -> None:
        assert isinstance(editor, QComboBox)
        model.setData(index, editor.currentText())  # type: ignore[attr-defined]


class FesProfileEditor(QDialog):
    profile_applied = Signal(object)  # FesProfile: "Apply to stimulator"
    profile_saved = Signal(str)

    def __init__(self, profile: FesProfile | None = None, parent: QWidget | None = None,
                 limits: LimitsProvider | None = None) -> None:
        super().__init__(parent)
        # The limits that Apply will meet (site, patient, device), read on every validation: the editor
        # says "valid" only for a profile the stimulator will accept (issue #30).
        self.limits_provider = limits
        self.limit_problems: list[str] = []
        self.setWindowTitle("FES profile editor")
        self.resize(1100, 720)
        self.path: Path | None = None
        self.undo_stack = QUndoStack(self)
        self._writing = False
        self._cache: dict[Cell, str] = {}
        self.cell_problems: dict[Cell, str] = {}
        self.general_problems: list[str] = []
        self._profile: FesProfile | None = None

        # header fields
        self.name_edit = QLineEdit()
        self.axis_box = QComboBox()
        self.axis_box.addItems(["phase", "time"])
        self.axis_box.setToolTip("phase: points are fractions 0..1 of the current LINarm movement; "
                                 "time: seconds from the start of stimulation")
        self.frequency_box = QDoubleSpinBox()
        self.frequency_box.setRange(1.0, 100.0)
        self.frequency_box.setDecimals(1)
        self.frequency_box.setSuffix(" Hz")
        self.description_edit = QLineEdit()
        form = QFormLayout()
        for label, w in (("&Name", self.name_edit), ("&Axis", self.axis_box), ("&Frequency", self.frequency_box),
                         ("&Description", self.description_edit)):
            form.addRow(label, w)
        self._field_values = {"name": "", "axis": "", "frequency": "", "description": ""}
        self.name_edit.editingFinished.connect(lambda: self._field_changed("name"))
        self.description_edit.editingFinished.connect(lambda: self._field_changed("description"))
        self.axis_box.currentTextChanged.connect(lambda _t: self._field_changed("axis"))
        self.frequency_box.valueChanged.connect(lambda _v: self._field_changed("frequency"))

        # tables
        self.current_table = self._make_table(CURRENT_COLUMNS, "Current trapezoids (mA)")
        self.width_table = self._make_table(WIDTH_COLUMNS, "Pulse-width trapezoids (µs)")
        self.current_table.setItemDelegateForColumn(2, _ModeDelegate(self.current_table))
        self.current_table.itemChanged.connect(lambda item: self._item_changed("current", item))
        self.width_table.itemChanged.connect(lambda item: self._item_changed("width", item))

        # preview
        c = colours()
        self.preview = pg.GraphicsLayoutWidget()
        self.preview.setBackground(c.plot_background)
        self.current_plot = self.preview.addPlot(row=0, col=0)
        self.width_plot = self.preview.addPlot(row=1, col=0)
        self.current_plot.setLabel("left", "current", units="mA")
        self.width_plot.setLabel("left", "pulse width", units="µs")
        self.width_plot.setXLink(self.current_plot)
        for p in (self.current_plot, self.width_plot):
            p.showGrid(x=True, y=True, alpha=c.grid_alpha)
            p.setMouseEnabled(x=False, y=False)
            p.addLegend(offset=(-10, 10))
        self.curves: dict[tuple[str, int], pg.PlotDataItem] = {}

        self.problems_label = QLabel()
        self.problems_label.setWordWrap(True)
        self.problems_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)

        # actions and buttons (all reachable from the keyboard)
        self.undo_action = self.undo_stack.createUndoAction(self, "&Undo")
        self.undo_action.setShortcut(QKeySequence.StandardKey.Undo)
        self.redo_action = self.undo_stack.createRedoAction(self, "&Redo")
        self.redo_action.setShortcut(QKeySequence.StandardKey.Redo)
        self.addActions([self.undo_action, self.redo_action])
        for seq, fn in ((QKeySequence.StandardKey.Save, self.save), (QKeySequence.StandardKey.Open, self.choose_file)):
            act = QAction(self)
            act.setShortcut(seq)
            act.triggered.connect(fn)
            self.addAction(act)
        self.add_button = QPushButton("Add &channel")
        self.remove_button = QPushButton("Re&move channel")
        self.undo_button = QPushButton("&Undo")
        self.redo_button = QPushButton("&Redo")
        self.load_button = QPushButton("&Open…")
        self.save_button = QPushButton("&Save")
        self.save_as_button = QPushButton("Save &as…")
        self.apply_button = QPushButton("A&pply to stimulator")
        self.close_button = QPushButton("Close")
        for b in (self.add_button, self.remove_button, self.undo_button, self.redo_button, self.load_button,
                  self.save_button, self.save_as_button, self.apply_button, self.close_button):
            b.setAutoDefault(False)  # Return in a table cell commits the cell; it must not press a button
            b.setDefault(False)
        self.undo_button.clicked.connect(self.undo_stack.undo)
        self.redo_button.clicked.connect(self.undo_stack.redo)
        self.undo_stack.canUndoChanged.connect(self.undo_button.setEnabled)
        self.undo_stack.canRedoChanged.connect(self.redo_button.setEnabled)
        self.undo_button.setEnabled(False)
        self.redo_button.setEnabled(False)
        self.add_button.clicked.connect(self.add_channel)
        self.remove_button.clicked.connect(self.remove_channel)
        self.load_button.clicked.connect(self.choose_file)
        self.save_button.clicked.connect(self.save)
        self.save_as_button.clicked.connect(self.save_as)
        self.apply_button.clicked.connect(self.apply)
        self.close_button.clicked.connect(self.close)

        buttons = QHBoxLayout()
        for b in (self.add_button, self.remove_button, self.undo_button, self.redo_button):
            buttons.addWidget(b)
        buttons.addStretch(1)
        for b in (self.load_button, self.save_button, self.save_as_button, self.apply_button, self.close_button):
            buttons.addWidget(b)
        tables = QWidget()
        tl = QVBoxLayout(tables)
        tl.setContentsMargins(0, 0, 0, 0)
        tl.addLayout(form)
        tl.addWidget(QLabel("<b>Current</b> (mA; points in the axis' unit)"))
        tl.addWidget(self.current_table)
        tl.addWidget(QLabel("<b>Pulse width</b> (µs)"))
        tl.addWidget(self.width_table)
        splitter = QSplitter(Qt.Orientation.Horizontal)
        splitter.addWidget(tables)
        splitter.addWidget(self.preview)
        splitter.setStretchFactor(0, 3)
        splitter.setStretchFactor(1, 2)
        splitter.setSizes([700, 500])
        lay = QVBoxLayout(self)
        lay.addWidget(splitter, 1)
        lay.addWidget(self.problems_label)
        lay.addLayout(buttons)

        self.set_profile(profile or default_profile())

    # ------------------------------------------------------------------ building blocks
    def _make_table(self, columns: tuple[str, ...], name: str) -> QTableWidget:
        t = QTableWidget(0, len(columns))
        t.setHorizontalHeaderLabels(list(columns))
        tips = {"Ch": f"Channel {CHANNELS_TEXT}", "Muscle": "The muscle this channel stimulates (free text)",
                "Group": "Pulse group: single, doublet or triplet"}
        for c, title in enumerate(columns):
            first = len(columns) - len(TRAP_KEYS)
            tip = TRAP_TIPS[c - first] if c >= first else tips.get(title, "")
            t.horizontalHeaderItem(c).setToolTip(tip)
        t.setAccessibleName(name)
        t.verticalHeader().setVisible(False)
        t.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        t.setEditTriggers(QAbstractItemView.EditTrigger.AllEditTriggers)
        t.setTabKeyNavigation(True)
        t.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        t.horizontalHeader().setStretchLastSection(True)
        return t

    def table(self, name: str) -> QTableWidget:
        return self.current_table if name == "current" else self.width_table

    def _rows_of(self, profile: FesProfile) -> list[list[list[str]]]:
        rows = []
        for ch, cp in sorted(profile.channels.items()):
            def trap(t: Trapezoid) -> list[str]:
                return [_fmt(t.level), _fmt(t.ramp_up[0]), _fmt(t.ramp_up[1]), _fmt(t.ramp_down[0]),
                        _fmt(t.ramp_down[1]), _fmt(t.baseline)]
            rows.append([[str(ch), cp.muscle, PulseMode(cp.mode).name.lower(), *trap(cp.current_ma)],
                         [str(ch), *trap(cp.pulse_width_us)]])
        return rows

    def _current_rows(self) -> list[list[list[str]]]:
        out = []
        for r in range(self.current_table.rowCount()):
            out.append([[self._text(("current", r, c)) for c in range(len(CURRENT_COLUMNS))],
                        [self._text(("width", r, c)) for c in range(len(WIDTH_COLUMNS))]])
        return out

    def _text(self, cell: Cell) -> str:
        item = self.table(cell[0]).item(cell[1], cell[2])
        return item.text() if item is not None else ""

    def _write_cell(self, cell: Cell, text: str) -> None:
        name, row, col = cell
        self._writing = True
        try:
            item = self.table(name).item(row, col)
            if item is None:
                item = QTableWidgetItem()
                self.table(name).setItem(row, col, item)
            item.setText(text)
            self._cache[cell] = text
            if name == "current" and col == 0:  # the channel shows in both tables
                self._write_cell(("width", row, 0), text)
        finally:
            self._writing = False
        self.validate()

    def _write_rows(self, rows: list[list[list[str]]]) -> None:
        self._writing = True
        try:
            for name in ("current", "width"):
                self.table(name).setRowCount(len(rows))
            self._cache = {}
            for r, (cur, wid) in enumerate(rows):
                for name, texts in (("current", cur), ("width", wid)):
                    for c, text in enumerate(texts):
                        item = QTableWidgetItem(text)
                        if name == "width" and c == 0:
                            item.setFlags(item.flags() & ~Qt.ItemFlag.ItemIsEditable)
                            item.setToolTip("Edit the channel in the current table")
                        self.table(name).setItem(r, c, item)
                        self._cache[(name, r, c)] = text
        finally:
            self._writing = False
        self.validate()

    def _item_changed(self, name: str, item: QTableWidgetItem) -> None:
        if self._writing:
            return
        cell = (name, item.row(), item.column())
        old, new = self._cache.get(cell, ""), item.text()
        if old == new:
            return
        self.undo_stack.push(_CellEdit(self, cell, old, new))

    def _field_changed(self, key: str) -> None:
        if self._writing:
            return
        new = self._field_text(key)
        old = self._field_values[key]
        if old == new:
            return
        self.undo_stack.push(_FieldEdit(f"edit {key}", lambda text, key=key: self._set_field(key, text), old, new))

    def _field_text(self, key: str) -> str:
        return {"name": self.name_edit.text, "axis": self.axis_box.currentText,
                "frequency": lambda: _fmt(self.frequency_box.value()),
                "description": self.description_edit.text}[key]()

    def _set_field(self, key: str, text: str) -> None:
        self._writing = True
        try:
            if key == "name":
                self.name_edit.setText(text)
            elif key == "axis":
                self.axis_box.setCurrentText(text)
            elif key == "frequency":
                self.frequency_box.setValue(float(text))
            else:
                self.description_edit.setText(text)
            self._field_values[key] = text
        finally:
            self._writing = False
        self.validate()

    # ------------------------------------------------------------------ public
    def set_profile(self, profile: FesProfile) -> None:
        """Show ``profile`` (a fresh start: the undo history is cleared)."""
        self._last_good = {}
        self._writing = True
        try:
            self.name_edit.setText(profile.name)
            self.axis_box.setCurrentText(profile.axis)
            self.frequency_box.setValue(profile.frequency_hz)
            self.description_edit.setText(profile.description)
            self._field_values = {k: self._field_text(k) for k in self._field_values}
        finally:
            self._writing = False
        self._scales = (profile.current_scale, profile.pulse_width_scale)
        self._write_rows(self._rows_of(profile))
        self.undo_stack.clear()
        self.undo_stack.setClean()

    def set_cell(self, name: str, row: int, col: int, text: str) -> None:
        """Edit a cell as the user would (undoable)."""
        item = self.table(name).item(row, col)
        assert item is not None
        item.setText(text)

    def profile(self) -> FesProfile | None:
        """The edited profile, or None while something is wrong."""
        return self._profile

    def add_channel(self) -> None:
        rows = self._current_rows()
        used = {r[0][0] for r in rows}
        free = next((str(ch) for ch in CHANNELS if str(ch) not in used), None)
        if free is None:
            self.problems_label.setText(f"All {len(CHANNELS)} channels are in use.")
            return
        new = [*rows, [[free, "", "single", "0", "0", "0", "0", "0", "0"], [free, "0", "0", "0", "0", "0", "0"]]]
        self.undo_stack.push(_RowsEdit(self, f"add channel {free}", rows, new))
        self.current_table.setCurrentCell(len(new) - 1, 1)
        self.current_table.setFocus()

    def remove_channel(self) -> None:
        rows = self._current_rows()
        row = self.current_table.currentRow()
        if row < 0:
            row = self.width_table.currentRow()
        if not rows or row < 0 or row >= len(rows):
            self.problems_label.setText("Select a row of the channel to remove.")
            return
        new = rows[:row] + rows[row + 1:]
        self.undo_stack.push(_RowsEdit(self, f"remove channel {rows[row][0][0]}", rows, new))

    def choose_file(self) -> None:
        start = self.path.parent if self.path is not None and not is_bundled(self.path) else fes_profiles_dir()
        path = file_dialogs.ask_open_file(self, "Open FES profile", start,
                                          "FES profiles (*.yaml *.yml);;All files (*)", places=(BUNDLED_PROFILES,))
        if path:
            self.load_file(path)

    def load_file(self, path: str | Path) -> bool:
        """Load a profile file; on an error show it (file, line, key) and change nothing."""
        try:
            profile = load_profile(path)
        except FesProfileError as exc:
            self.problems_label.setText(f"<span style='color:{colours().bad}'>Not loaded: {escape(str(exc))}</span>")
            return False
        self.set_profile(profile)
        self.path = Path(path)
        self.setWindowTitle(f"FES profile editor — {self.path.name}")
        return True

    def save(self) -> bool:
        if self.path is None or is_bundled(self.path):  # a bundled example is read-only: saved as a copy
            return self.save_as()
        return self.save_file(self.path)

    def save_as(self) -> bool:
        return self.save_file(path) if (path := self.ask_save_path()) else False

    def ask_save_path(self) -> str:
        """Where to save: proposed in the user's profiles folder (a bundled example's name, or the profile's
        name); a path inside the bundled folder is refused in words."""
        name = self.path.name if self.path is not None else f"{safe_file_stem(self.name_edit.text())}.yaml"
        start = self.path if self.path is not None and not is_bundled(self.path) else fes_profiles_dir() / name
        path = file_dialogs.ask_save_file(self, "Save FES profile", start, "FES profiles (*.yaml *.yml)", "yaml")
        if path and is_bundled(path):
            self.problems_label.setText(f"<span style='color:{colours().bad}'>Not saved: the bundled example "
                                        "profiles are read-only; save your copy in your own folder.</span>")
            return ""
        return path

    def save_file(self, path: str | Path) -> bool:
        profile = self._profile
        if profile is None:
            self.problems_label.setText(f"<span style='color:{colours().bad}'>Not saved: fix the highlighted "
                                        "cells first.</span>")
            return False
        try:
            save_profile(profile, path)
        except (OSError, FesProfileError) as exc:
            self.problems_label.setText(f"<span style='color:{colours().bad}'>Not saved: {escape(str(exc))}</span>")
            return False
        self.path = Path(path)
        self.undo_stack.setClean()
        self.setWindowTitle(f"FES profile editor — {self.path.name}")
        self.problems_label.setText(f"Saved to {escape(str(self.path))}")
        self.profile_saved.emit(str(self.path))
        return True

    def apply(self) -> None:
        if self._profile is None:
            self.problems_label.setText(f"<span style='color:{colours().bad}'>Fix the highlighted cells "
                                        "first.</span>")
            return
        self.profile_applied.emit(self._profile)

    def show_refusal(self, text: str) -> None:
        """A refusal of Apply, in the editor where the therapist is looking (not behind it)."""
        self.problems_label.setText(f"<span style='color:{colours().bad}'>{escape(text)}</span>")

    # ------------------------------------------------------------------ validation and preview
    def validate(self) -> None:
        problems: dict[Cell, str] = {}
        general: list[str] = []
        axis = self.axis_box.currentText()
        channels: dict[int, ChannelProfile] = {}
        stale: dict[int, tuple[int, ChannelProfile]] = {}  # row -> its last valid channel (being edited)
        seen: dict[int, int] = {}
        if not hasattr(self, "_last_good"):
            self._last_good: dict[int, tuple[int, ChannelProfile]] = {}
        self._last_good = {r: v for r, v in self._last_good.items() if r < self.current_table.rowCount()}
        for r in range(self.current_table.rowCount()):
            ch_text = self._text(("current", r, 0)).strip()
            ch: int | None = int(ch_text) if ch_text.isdigit() else None
            if ch is None or ch not in CHANNELS:
                problems[("current", r, 0)] = f"a channel number {CHANNELS_TEXT}"
                ch = None
            elif ch in seen:
                problems[("current", r, 0)] = f"channel {ch} is already in row {seen[ch] + 1}"
                ch = None
            else:
                seen[ch] = r
            mode = self._text(("current", r, 2)).strip().lower()
            if mode not in MODES:
                problems[("current", r, 2)] = "single, doublet or triplet"
            traps = []
            for name, first, maximum, unit in (("current", CUR_TRAP0, MAX_CURRENT_MA, "mA"),
                                               ("width", WID_TRAP0, MAX_PULSE_WIDTH_US, "µs")):
                values: list[float] = []
                for i in range(len(TRAP_KEYS)):
                    cell = (name, r, first + i)
                    try:
                        v = float(self._text(cell).strip())
                        if not math.isfinite(v):
                            raise ValueError
                        values.append(v)
                    except ValueError:
                        problems[cell] = f"'{self._text(cell)}' is not a number"
                if len(values) != len(TRAP_KEYS):
                    traps.append(None)
                    continue
                trap = Trapezoid(values[0], (values[1], values[2]), (values[3], values[4]), values[5])
                bad = trap.problems(axis, maximum, unit)  # type: ignore[arg-type]
                for key, why in bad:
                    cols = {"level": [0], "baseline": [5], "ramp_up": [1, 2], "ramp_down": [3, 4]}[key]
                    if key == "ramp_down" and "must not decrease" in why:
                        cols = [1, 2, 3, 4]
                    for col in cols:
                        problems.setdefault((name, r, first + col), why)
                traps.append(None if bad else trap)
            if ch is not None and mode in MODES and traps[0] is not None and traps[1] is not None:
                channels[ch] = ChannelProfile(traps[0], traps[1], self._text(("current", r, 1)).strip(),
                                              PulseMode[mode.upper()])
                self._last_good[r] = (ch, channels[ch])
            elif r in self._last_good:
                stale[r] = self._last_good[r]  # a bad cell: the row's last valid preview stays, dashed
        profile: FesProfile | None = None
        if not problems:
            try:
                profile = FesProfile(self.name_edit.text().strip() or "unnamed", axis, channels,  # type: ignore[arg-type]
                                     self.frequency_box.value(), self.description_edit.text(), *self._scales)
            except FesProfileError as exc:
                general.append(f"{exc.key}: {exc.problem}")
        self.limit_problems = []
        if profile is not None and self.limits_provider is not None:
            limits, patient = self.limits_provider()
            if limits is not None:
                self.limit_problems = profile_limit_problems(limits, profile.peaks(scaled=True), patient)
        self._profile = profile
        self.cell_problems = problems
        self.general_problems = general
        self._highlight()
        self._plot(channels, axis, {ch: cp for ch, cp in stale.values() if ch not in channels})
        bad = colours().bad
        if problems:
            first = sorted(problems)[0]
            self.problems_label.setText(
                f"<span style='color:{bad}'>{len(problems)} cell(s) to fix — {first[0]} table row {first[1] + 1}: "
                f"{escape(problems[first])}</span>")
        elif general:
            self.problems_label.setText(f"<span style='color:{bad}'>{escape('; '.join(general))}</span>")
        elif self.limit_problems:
            self.problems_label.setText(
                f"<span style='color:{bad}'>Valid as a file, but the stimulator would refuse it now: "
                f"{escape(' '.join(self.limit_problems))}</span>")
        else:
            self.problems_label.setText("Profile is valid." + ("" if self.undo_stack.isClean() else " (not saved)"))
        self.save_button.setEnabled(profile is not None)
        self.save_as_button.setEnabled(profile is not None)
        self.apply_button.setEnabled(profile is not None and not self.limit_problems)

    def _highlight(self) -> None:
        self._writing = True
        try:
            for name in ("current", "width"):
                t = self.table(name)
                for r in range(t.rowCount()):
                    for c in range(t.columnCount()):
                        item = t.item(r, c)
                        if item is None:
                            continue
                        why = self.cell_problems.get((name, r, c))
                        item.setBackground(QBrush(QColor(BAD_BACKGROUND)) if why else QBrush())
                        if why:
                            item.setForeground(QBrush(QColor("#000000")))
                        else:
                            item.setData(Qt.ItemDataRole.ForegroundRole, None)
                        item.setToolTip(why or ("Edit the channel in the current table"
                                                if name == "width" and c == 0 else ""))
        finally:
            self._writing = False

    def _plot(self, channels: dict[int, ChannelProfile], axis: str,
              stale: dict[int, ChannelProfile] | None = None) -> None:
        """Both previews; ``stale`` channels (a cell of theirs is invalid) are drawn dashed as they
        last were valid, so one bad cell never blanks the plots (issue #19)."""
        stale = stale or {}
        for p in (self.current_plot, self.width_plot):
            p.clear()
            if p.legend is not None:
                p.legend.clear()
        self.curves = {}
        if axis == "phase":
            end = 1.0
        else:
            end = max((max(cp.current_ma.ramp_down[1], cp.pulse_width_us.ramp_down[1])
                       for cp in (*channels.values(), *stale.values())), default=1.0) * 1.1 or 1.0
        x = np.linspace(0.0, end, PREVIEW_POINTS)
        shown = {**{ch: (cp, False) for ch, cp in channels.items()}, **{ch: (cp, True) for ch, cp in stale.items()}}
        for i, (ch, (cp, old)) in enumerate(sorted(shown.items())):
            pen = pg.mkPen(curve_colour(i), width=2,
                           style=Qt.PenStyle.DashLine if old else Qt.PenStyle.SolidLine)
            label = f"ch {ch}" + (f" {cp.muscle}" if cp.muscle else "") + (" (last valid)" if old else "")
            cur = np.array([cp.current_ma.value_at(v) for v in x])
            wid = np.array([cp.pulse_width_us.value_at(v) for v in x])
            self.curves[("current", ch)] = self.current_plot.plot(x, cur, pen=pen, name=label)
            self.curves[("width", ch)] = self.width_plot.plot(x, wid, pen=pen, name=label)
        self.width_plot.setLabel("bottom", "movement phase" if axis == "phase" else "time", units=None if
                                 axis == "phase" else "s")
