"""The FES manager panel (seed Fig. 14): start/stop, the loaded profile, the two live scale knobs with
the currents and pulse widths they amount to per channel, and each channel's status.

Everything goes through the FES driver's thread-safe methods; refusals (limits, e-stop, device) and
faults are shown in words in the message line, never swallowed.
"""

from __future__ import annotations

import logging
from html import escape
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import (
    QAbstractItemView,
    QDial,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.core import journal, streams
from app.core.config import RESOURCES
from app.core.fes_profile import MAX_SCALE, FesProfile, FesProfileError, load_profile
from app.core.journal import Record
from app.core.paths import fes_profiles_dir
from app.devices.command_queue import CommandQueueClosed, CommandStatus
from app.devices.rehastim import FesDriver, FesError, scale_clamp_text
from app.manager import LinarmppManager
from app.safety.fes_limits import FesLimits
from app.safety.supervisor import SafetyError
from app.ui import file_dialogs
from app.ui.qt_bus import shared_qt_bus
from app.ui.theme import colours
from app.ui.widgets import RefreshWhenVisible

log = logging.getLogger(__name__)

PROFILES_DIR = RESOURCES / "fes_profiles"
DIAL_STEPS = 100  # dial units per 1.0 of scale (0.01 resolution)
# The most one action (a key, a wheel notch, a drag event, a programmatic set) may RAISE a scale by:
# an accidental click or twitch must never raise stimulation by more than this. Lowering is never capped.
MAX_RISE_PER_ACTION = 0.05
DRAG_PX_PER_STEP = 4  # a drag changes the dial by one unit per 4 px, relative to where it was pressed
COLUMNS = ("Ch", "Muscle", "Peak mA", "Peak µs", "Now mA", "Now µs", "Cap mA / µs", "Status")


class StepDial(QDial):
    """A dial that never jumps: a click (anywhere on it) changes nothing, a drag moves it relative to
    where it was pressed (up/right = more) one unit per ``DRAG_PX_PER_STEP`` px and at most
    ``max_rise`` units up per mouse event, the wheel one unit per notch, PgUp/PgDn one page
    (= ``max_rise``), End at most ``max_rise`` up. QDial's own mouse handling sets the value under the
    pointer: one click went 0.05 -> 1.73× (issue #19)."""

    def __init__(self, max_rise: int, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.max_rise = max_rise
        self._press: tuple[int, int] | None = None  # x + (-y) at the press, value at the press
        self._moved = 0

    def _step_to(self, target: int) -> None:
        v = self.value()
        if target > v:
            target = min(target, v + self.max_rise)
        self.setValue(max(self.minimum(), min(self.maximum(), target)))

    def mousePressEvent(self, event: Any) -> None:
        if event.button() != Qt.MouseButton.LeftButton:
            event.ignore()
            return
        p = event.position()
        self._press = (int(p.x() - p.y()), self.value())
        self.setSliderDown(True)
        self.setFocus(Qt.FocusReason.MouseFocusReason)
        event.accept()

    def mouseMoveEvent(self, event: Any) -> None:
        if self._press is None:
            event.ignore()
            return
        p = event.position()
        origin, start = self._press
        travelled = int(p.x() - p.y()) - origin
        self._step_to(start + int(travelled / DRAG_PX_PER_STEP))
        event.accept()

    def mouseReleaseEvent(self, event: Any) -> None:
        if self._press is not None:
            self._press = None
            self.setSliderDown(False)
        event.accept()

    def wheelEvent(self, event: Any) -> None:
        notches = event.angleDelta().y() // 120 or (1 if event.angleDelta().y() > 0 else -1
                                                     if event.angleDelta().y() < 0 else 0)
        self._step_to(self.value() + notches * self.singleStep())
        event.accept()

    def keyPressEvent(self, event: Any) -> None:
        key = event.key()
        if key == Qt.Key.Key_End:
            self._step_to(self.maximum())
            event.accept()
            return
        if key in (Qt.Key.Key_PageUp, Qt.Key.Key_Up, Qt.Key.Key_Right):
            step = self.pageStep() if key == Qt.Key.Key_PageUp else self.singleStep()
            self._step_to(self.value() + step)
            event.accept()
            return
        super().keyPressEvent(event)  # down, PgDn, Home: lowering is never capped


class ScaleKnob(QWidget):
    """A QDial for one scale factor (0 .. MAX_SCALE) with its value in words."""

    def __init__(self, title: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.title = QLabel(title)
        self.title.setAlignment(Qt.AlignmentFlag.AlignHCenter)
        rise = round(MAX_RISE_PER_ACTION * DIAL_STEPS)
        self.dial = StepDial(rise)
        self.dial.setRange(0, int(MAX_SCALE * DIAL_STEPS))
        self.dial.setSingleStep(1)
        self.dial.setPageStep(rise)
        self.dial.setNotchesVisible(True)
        self.dial.setNotchTarget(10.0)
        self.dial.setWrapping(False)
        self.dial.setTracking(True)
        self.dial.setFocusPolicy(Qt.FocusPolicy.StrongFocus)  # arrows / PgUp / PgDn / Home / End
        self.dial.setAccessibleName(title)
        self.dial.setMinimumSize(84, 84)
        self.value_label = QLabel()
        self.value_label.setAlignment(Qt.AlignmentFlag.AlignHCenter)
        self.title.setBuddy(self.dial)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.setSpacing(2)
        lay.addWidget(self.title)
        lay.addWidget(self.dial, 1)
        lay.addWidget(self.value_label)

    def set_scale(self, scale: float) -> None:
        self.dial.blockSignals(True)
        self.dial.setValue(round(scale * DIAL_STEPS))
        self.dial.blockSignals(False)

    def scale(self) -> float:
        return self.dial.value() / DIAL_STEPS


START_TEXT = "&Start stimulation"
STARTING_TEXT = "Starting…"


def start_failure_text(exc: BaseException) -> str:
    """Why a start did not happen, in the words shown to the user."""
    reason = getattr(exc, "reason", None)
    if reason:
        return str(reason)
    if isinstance(exc, CommandQueueClosed):
        return "the stimulator's link closed before it could start"
    return str(exc) or type(exc).__name__


class FesPanel(RefreshWhenVisible, QWidget):
    # A start's status when it completes, delivered on the GUI thread (emitted from the FES command queue's
    # thread: a queued connection). The GUI never waits for the stimulator's acks (#29).
    start_finished = Signal(object)

    def __init__(self, manager: LinarmppManager, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.manager = manager
        driver = manager.driver(streams.FES)
        self.driver: FesDriver | None = driver if isinstance(driver, FesDriver) else None
        self.editor: QWidget | None = None
        self.last_dir = fes_profiles_dir()  # the user's profiles; the bundled examples are a side-bar place

        self.status_label = QLabel()
        self.status_label.setTextFormat(Qt.TextFormat.RichText)
        self.start_button = QPushButton(START_TEXT)
        self._starting: CommandStatus | None = None  # a start on its way (the button says "Starting…")
        self.stop_button = QPushButton("S&top stimulation")
        self.stop_button.setStyleSheet("QPushButton { font-weight: bold; }")
        self.load_button = QPushButton("&Load profile…")
        self.edit_button = QPushButton("&Edit profile…")
        for b, tip in ((self.start_button, "Initialise the channel list and run the loaded profile"),
                       (self.stop_button, "Send Stop to the stimulator now"),
                       (self.load_button, "Load a profile file (YAML)"),
                       (self.edit_button, "Open the profile editor")):
            b.setToolTip(tip)
        self.profile_label = QLabel("No profile loaded")
        self.profile_label.setWordWrap(True)
        # Issue #32: choose each district's best electrode combination of its array (app/ui/electrode_setup.py).
        self.electrodes_button = QPushButton("Electrode set-&up…")
        self.electrodes_button.setToolTip("Test each electrode combination of a district's array and choose the best")
        self.electrodes_button.clicked.connect(self.open_electrode_setup)
        self.electrode_dialog: QWidget | None = None

        self.current_knob = ScaleKnob("Current scale")
        self.width_knob = ScaleKnob("Pulse-width scale")
        self.current_knob.dial.valueChanged.connect(lambda _v: self._knob_moved("current"))
        self.width_knob.dial.valueChanged.connect(lambda _v: self._knob_moved("pulse_width"))

        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(list(COLUMNS))
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.NoSelection)
        self.table.setFocusPolicy(Qt.FocusPolicy.NoFocus)
        # Compact rows: all eight channels must fit beside the controls on a 768 px screen (issue #30).
        self.table.verticalHeader().setDefaultSectionSize(self.table.fontMetrics().lineSpacing() + 6)
        self.table.setVerticalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAsNeeded)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(1, QHeaderView.ResizeMode.Stretch)
        header.setStretchLastSection(False)

        self.message = QLabel()
        self.message.setTextFormat(Qt.TextFormat.PlainText)  # reasons contain "<=" and file paths
        self.message.setWordWrap(True)
        self.message.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)

        # 1366×768 first: Start/Stop, the knobs and the channel table on screen together (issue #19).
        buttons = QGridLayout()
        buttons.setSpacing(4)
        for i, b in enumerate((self.start_button, self.stop_button, self.load_button, self.edit_button)):
            buttons.addWidget(b, i // 2, i % 2)
        for b in (self.start_button, self.stop_button, self.load_button, self.edit_button, self.electrodes_button):
            # A long refusal below must never squeeze them (#36: 16 px high buttons at 1366×768).
            b.setMinimumHeight(b.sizeHint().height())
        buttons.addWidget(self.electrodes_button, 2, 0, 1, 2)
        left = QVBoxLayout()
        left.setSpacing(4)
        left.addWidget(self.status_label)
        from app.ui.held_by import HeldByLabel

        self.held_by = HeldByLabel(manager.supervisor, "stimulator")  # one owner during a run (#36)
        left.addWidget(self.held_by)
        left.addLayout(buttons)
        left.addWidget(self.profile_label)
        # Why the pulse-width knob does not turn, on screen and not only in a tooltip (issue #30).
        self.width_lock_note = QLabel("Pulse width set by the assistance: its knob is locked until the "
                                      "assistance stops.")
        self.width_lock_note.setWordWrap(True)
        self.width_lock_note.setVisible(False)
        left.addWidget(self.width_lock_note)
        left.addStretch(1)
        knobs = QGroupBox("Live scale factors")
        kl = QGridLayout(knobs)
        kl.setContentsMargins(4, 4, 4, 4)
        kl.addWidget(self.current_knob, 0, 0)
        kl.addWidget(self.width_knob, 0, 1)
        # Why the pulse-width knob does not turn, on screen and not only in a tooltip (issue #30).
        top = QHBoxLayout()
        top.addLayout(left, 1)
        top.addWidget(knobs)
        channels = QGroupBox("Channels")
        cl = QVBoxLayout(channels)
        cl.setContentsMargins(4, 4, 4, 4)
        self._fit_table_rows()
        cl.addWidget(self.table)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)
        lay.setSpacing(4)
        lay.addLayout(top)
        lay.addWidget(channels, 1)
        lay.addWidget(self.message)

        self.start_button.clicked.connect(self.start)
        self.start_finished.connect(self._start_done)
        self.stop_button.clicked.connect(self.stop)
        self.load_button.clicked.connect(self.choose_profile_file)
        self.edit_button.clicked.connect(self.open_editor)
        if self.driver is not None:  # the stimulator's faults, clamps and stops: the journal, through the adapter
            shared_qt_bus(manager.bus).record.connect(self._on_record)
        self.timer = QTimer(self)
        self.timer.setInterval(100)
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        self._shown_profile: FesProfile | None = None
        self.refresh()

    # ------------------------------------------------------------------ actions
    def start(self) -> CommandStatus | None:
        """Submit the start and return at once; its outcome is shown when its status completes (_start_done)."""
        if self.driver is None or self._starting is not None:
            return None
        status = self.driver.submit_start("FES panel")
        if not status.done():
            self._starting = status
            self.start_button.setText(STARTING_TEXT)
            self.start_button.setEnabled(False)
            self.show_message("Starting: initialising the stimulator's channel list…", "warn")
        status.add_done_callback(self._emit_start_finished)  # at once (this thread) when already decided
        return status

    def _emit_start_finished(self, status: CommandStatus) -> None:
        try:
            self.start_finished.emit(status)
        except RuntimeError:  # the panel was deleted while the start was on its way
            pass

    def _start_done(self, status: CommandStatus) -> None:
        if self._starting is status:
            self._starting = None
        self.start_button.setText(START_TEXT)
        exc = status.exception(0) if not status.cancelled() else FesError("the start was cancelled")
        if exc is None:
            self.show_message("Stimulating.", "ok")
        elif isinstance(exc, SafetyError | FesError | CommandQueueClosed):
            self.show_message(f"Not started: {start_failure_text(exc)}", "bad")
        else:
            log.error("FES start failed: %r", exc)
            self.show_message(f"Not started: {start_failure_text(exc)}", "bad")
        self.refresh()

    def _on_record(self, record: Record) -> None:
        if record.origin != journal.SAFETY:
            return
        data = record.data
        if record.kind == journal.FES_FAULT:
            self.show_message(str(data.get("text", "")), "bad")
        elif record.kind == journal.FES_SCALE and data.get("reason"):
            self.show_message(scale_clamp_text(str(data.get("knob")), float(data.get("applied", 0.0)),
                                               str(data["reason"])), "warn")
        elif record.kind in (journal.FES_STARTED, journal.FES_STOPPED):
            self._stimulation_changed(record.kind == journal.FES_STARTED)

    def _stimulation_changed(self, on: bool) -> None:
        """Stimulation ended by itself (a time profile's end, a fault, the run holding it): the message must not
        go on saying "Stimulating." (#36)."""
        d = self.driver
        if not on and d is not None and self.message.text().startswith("Stimulating"):
            profile = d.profile
            if profile is not None and profile.axis == "time" and d.clock() - d.started_at >= profile.end:
                self.show_message(f"Stimulation ended: the time profile finished ({profile.end:g} s).", "ok")
            else:
                self.show_message("Stimulation stopped.", "warn")
        self.refresh()

    def stop(self) -> None:
        if self.driver is not None:
            self.driver.stop_stimulation("stop button", "FES panel")
            self.show_message("Stopped.", "ok")
        self.refresh()

    def open_electrode_setup(self) -> None:
        from app.ui.electrode_setup import ElectrodeSetupDialog

        if self.electrode_dialog is None:
            self.electrode_dialog = ElectrodeSetupDialog(self.manager, self)
        self.electrode_dialog.show()
        self.electrode_dialog.raise_()

    def choose_profile_file(self) -> None:
        path = file_dialogs.ask_open_file(self, "Load FES profile", self.last_dir,
                                          "FES profiles (*.yaml *.yml);;All files (*)", places=(PROFILES_DIR,))
        if path:
            self.load_profile_file(path)

    def load_profile_file(self, path: str | Path) -> bool:
        """Read, validate and load a profile; on any problem say where and change nothing."""
        try:
            profile = load_profile(path)
        except FesProfileError as exc:
            self.show_message(f"Profile not loaded: {exc}", "bad")
            return False
        self.last_dir = Path(path).parent
        return self.apply_profile(profile)

    def apply_profile(self, profile: FesProfile) -> bool:
        if self.driver is None:
            self.show_message("FES is off in the configuration.", "bad")
            return False
        try:
            self.driver.load_profile(profile, "FES panel")
        except (SafetyError, FesError) as exc:
            self.show_message(f"Profile not loaded: {exc.reason}", "bad")
            return False
        self.show_message(f"Profile {profile.name!r} loaded.", "ok")
        self.refresh()
        return True

    def _limits_now(self) -> tuple[FesLimits | None, str]:
        """The limits a profile will meet on Apply: the stimulator's limiter (site + the patient's caps)."""
        lim = self.manager.supervisor.fes_limiter
        profile = self.manager.patient_profile
        return (lim.limits if lim is not None else None), (profile.patient_id if profile is not None else "")

    def _apply_from_editor(self, editor: Any, profile: FesProfile) -> None:
        if self.apply_profile(profile):
            editor.problems_label.setText(f"Applied to the stimulator: {escape(profile.name)}.")
        else:
            editor.show_refusal(self.message.text())

    def open_editor(self) -> None:
        from app.ui.fes_editor import FesProfileEditor

        editor = FesProfileEditor(self.driver.profile if self.driver else None, self, limits=self._limits_now)
        editor.profile_applied.connect(lambda profile: self._apply_from_editor(editor, profile))
        editor.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        editor.show()
        self.editor = editor

    def _knob_moved(self, knob: str) -> None:
        if self.driver is None or self.driver.profile is None:
            return
        w = self.current_knob if knob == "current" else self.width_knob
        requested = w.scale()
        profile = self.driver.profile
        now = profile.current_scale if knob == "current" else profile.pulse_width_scale
        if requested > now + MAX_RISE_PER_ACTION + 1e-9:  # whatever moved the dial: one step up at most
            requested = now + MAX_RISE_PER_ACTION
            self.show_message(f"Raised by {MAX_RISE_PER_ACTION:.2f}× at most per action; turn again to go further.",
                              "warn")
        try:
            if knob == "current":
                applied = self.driver.set_current_scale(requested, "FES panel")
            else:
                applied = self.driver.set_pulse_width_scale(requested, "FES panel")
        except (SafetyError, FesError) as exc:
            self.show_message(exc.reason, "bad")
            return
        if round(applied * DIAL_STEPS) != w.dial.value():
            w.set_scale(applied)  # the knob stops at the cap (the driver said why)
        self.refresh()

    def show_message(self, text: str, kind: str = "ok") -> None:
        c = colours()
        colour = {"ok": c.text, "warn": c.warn, "bad": c.bad}.get(kind, c.text)
        self.message.setStyleSheet(f"color: {colour};")
        self.message.setText(text)

    # ------------------------------------------------------------------ view

    def _fit_table_rows(self) -> None:
        """Every channel of the profile on screen at once (issue #30: 1 of 4 rows showed at 1366×768):
        the table is as tall as its rows, at least three; the tab scrolls if the screen is shorter."""
        self.table.setMinimumHeight(table_height_for_rows(self.table, max(3, self.table.rowCount())))

    def refresh(self) -> None:
        c = colours()
        d = self.driver
        if d is None:
            self.status_label.setText(f"<b style='color:{c.idle}'>FES is off in the configuration</b>")
            for w in (self.start_button, self.stop_button, self.load_button, self.edit_button,
                      self.current_knob, self.width_knob):
                w.setEnabled(False)
            return
        protocol = {"sm1": "ScienceMode 1", "sm2": "ScienceMode 2"}[d.protocol]
        if d.stimulating:
            state, colour = "Stimulating", c.warn
        elif d.device_ready:
            state, colour = "Ready", c.ok
        elif d.connected:
            state, colour = "Waiting for the stimulator", c.warn
        else:
            state, colour = "Not connected", c.bad
        latched = " — <b>emergency stop latched</b>" if self.manager.supervisor.estop_latched else ""
        self.status_label.setText(f"<b style='color:{colour}'>● {state}</b> &nbsp; RehaStim, {protocol}{latched}")
        profile = d.profile
        self.start_button.setEnabled(profile is not None and d.device_ready and not d.stimulating
                                     and self._starting is None)
        self.stop_button.setEnabled(True)  # Stop is always allowed
        self.load_button.setEnabled(not d.stimulating)
        for knob in (self.current_knob, self.width_knob):
            knob.setEnabled(profile is not None)
        override = d.pulse_width_override
        # Delivered = shown (#36): the assistance's pulse width replaces the profile's on every channel, said here
        # whether or not a profile is loaded yet (the next one loaded gets it too).
        note = (f"Pulse width set by the assistance: {override:.0f} µs on every channel, instead of the "
                "profile's. Its knob is locked until the assistance stops." if override is not None else "")
        if self.width_lock_note.text() != note:
            self.width_lock_note.setText(note)
        self.width_lock_note.setVisible(override is not None)
        self.width_knob.dial.setEnabled(profile is not None and override is None)
        if profile is None:
            self.profile_label.setText("No profile loaded")
            self.table.setRowCount(0)
            return
        if not self.current_knob.dial.isSliderDown():
            self.current_knob.set_scale(profile.current_scale)
        if not self.width_knob.dial.isSliderDown():
            self.width_knob.set_scale(profile.pulse_width_scale)
        self.current_knob.value_label.setText(f"{profile.current_scale:.2f} ×")
        if override is None:
            self.width_knob.value_label.setText(f"{profile.pulse_width_scale:.2f} ×")
            self.width_knob.value_label.setToolTip("")
        else:
            self.width_knob.value_label.setText(f"{override:.0f} µs (assistance)")
            self.width_knob.value_label.setToolTip(
                "The assistance controller sets the pulse width from the patient model's effort estimate "
                f"(now {override:.0f} µs); this knob is locked until the assistance stops.")
        axis = "movement phase" if profile.axis == "phase" else f"time, {profile.end:g} s"
        ccl = d.channel_list
        # The requested rate; the delivered one only when it differs (the stimulator's period has a
        # fixed grain, so 30 Hz comes out as 29.9 Hz) -- said, not silently shown instead.
        freq = f"{profile.frequency_hz:g} Hz"
        if ccl and abs(ccl.frequency_hz - profile.frequency_hz) >= 0.05:
            freq += (f" (delivered {ccl.frequency_hz:.1f} Hz: the stimulator's pulse period "
                     "is a whole number of its time steps)")
        # Name and what it does on two lines; the free-text description in the tooltip (it took four lines
        # of a 768 px screen, above the channels the therapist needs to see).
        self.profile_label.setText(f"<b>{escape(profile.name)}</b><br>{axis} · {freq} · "
                                   f"{len(profile.channels)} channel(s)")
        self.profile_label.setToolTip(profile.description)
        rows = d.channel_status()
        if self.table.rowCount() != len(rows):
            self.table.setRowCount(len(rows))
            self._fit_table_rows()
        for r, s in enumerate(rows):
            values = (str(s.channel), s.muscle, f"{s.peak_current_ma:.1f}", f"{s.peak_pulse_width_us:.0f}",
                      str(s.sent_current_ma), str(s.sent_pulse_width_us),
                      f"{s.cap_current_ma:g} / {s.cap_pulse_width_us:g}", s.note)
            for col, text in enumerate(values):
                item = self.table.item(r, col)
                if item is None:
                    item = QTableWidgetItem()
                    if col != 1:
                        item.setTextAlignment(Qt.AlignmentFlag.AlignCenter)
                    self.table.setItem(r, col, item)
                if item.text() != text:
                    item.setText(text)
            status = self.table.item(r, len(COLUMNS) - 1)
            note_colour = {"following": c.ok, "off": c.idle}.get(s.note, c.warn)
            status.setForeground(_brush(note_colour))


def table_height_for_rows(table: QTableWidget, rows: int) -> int:
    """The height at which ``table`` shows ``rows`` rows and its header without scrolling."""
    row_h = table.verticalHeader().defaultSectionSize()
    return table.horizontalHeader().sizeHint().height() + rows * row_h + 2 * table.frameWidth() + 2


def _brush(colour: str) -> QBrush:
    return QBrush(QColor(colour))
