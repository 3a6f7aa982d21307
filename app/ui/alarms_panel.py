"""Alarms: the safety supervisor's graded alarms (information, warning, stop, fatal) as a list with
level colours, time, source, text and acknowledgement, plus a compact banner for the main window.

The supervisor owns the alarms and records each one -- and each acknowledgement, with the
operator's name -- as a session event; this module only shows them and asks it to acknowledge.
STOP and FATAL alarms also sound: once when raised, then again every ``repeat_s`` seconds while
any of them is unacknowledged (QtMultimedia is not in PySide6-Essentials, so the sound is
``QApplication.beep()``; ``beep`` is an attribute so tests can count the calls).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from PySide6.QtCore import QEvent, QSize, Qt, QTimer, Signal
from PySide6.QtGui import QBrush, QColor, QFont, QFontMetrics
from PySide6.QtWidgets import (
    QAbstractItemView,
    QApplication,
    QCheckBox,
    QFrame,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QPushButton,
    QSizePolicy,
    QTreeWidget,
    QTreeWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.manager import LinarmppManager
from app.safety.supervisor import Alarm, AlarmLevel
from app.ui.qt_bus import shared_qt_bus
from app.ui.recovery import RecoverDialog, Recovery, Restartable, recovery_needed
from app.ui.widgets import ElidedLabel


@dataclass(frozen=True)
class LevelStyle:
    name: str
    background: str
    foreground: str


# One place for the alarm colours (IEC 60601-1-8 spirit: the higher the priority, the louder the colour).
LEVEL_STYLES: dict[AlarmLevel, LevelStyle] = {
    AlarmLevel.INFO: LevelStyle("Information", "#cfe3f5", "#0d3c61"),   # pale blue
    AlarmLevel.WARNING: LevelStyle("Warning", "#ffb300", "#1a1a1a"),    # amber
    AlarmLevel.STOP: LevelStyle("Stop", "#d32f2f", "#ffffff"),          # red
    AlarmLevel.FATAL: LevelStyle("Fatal", "#6a0046", "#ffffff"),        # dark magenta
}
SOUNDING = AlarmLevel.STOP  # this level and above sound
COLUMNS = ("Level", "Time", "Source", "Status", "Message")
MESSAGE_COLUMN = COLUMNS.index("Message")
STATUS_COLUMN = COLUMNS.index("Status")
ROW_LIMIT = 1000  # rows kept in the list; beyond it the oldest acknowledged rows go first


def wrap_elided(text: str, metrics: QFontMetrics, width: int, lines: int) -> str:
    """``text`` broken into at most ``lines`` lines of ``width`` px (at word boundaries where it can), the last
    line elided when the rest does not fit. Lines are joined with newlines."""
    if width <= 0 or not text:
        return text
    out: list[str] = []
    rest = text
    while rest and len(out) < lines:
        if len(out) == lines - 1 or metrics.horizontalAdvance(rest) <= width:
            out.append(metrics.elidedText(rest, Qt.TextElideMode.ElideRight, width))
            break
        # the longest prefix that fits, back to its last space
        fit = len(rest)
        while fit > 1 and metrics.horizontalAdvance(rest[:fit]) > width:
            fit = fit * 3 // 4 if metrics.horizontalAdvance(rest[:fit * 3 // 4]) > width else fit - 1
        cut = rest.rfind(" ", 0, fit + 1)
        cut = cut if cut > 0 else fit
        out.append(rest[:cut].rstrip())
        rest = rest[cut:].lstrip()
    return "\n".join(out)


class LinesLabel(ElidedLabel):
    """Plain text on at most ``lines`` lines, wrapped at words, the last line elided; the whole text in the
    tooltip when anything is cut (#36: the STOP banner and the alarm texts were cut at 1366×768)."""

    def __init__(self, lines: int = 2, parent: QWidget | None = None) -> None:
        self.lines = lines
        super().__init__("", parent)
        self.setWordWrap(False)  # the breaks are ours: the label never lays a line out of sight
        self.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Fixed)
        self._fit_height()

    def _fit_height(self) -> None:
        self.setFixedHeight(self.lines * self.fontMetrics().lineSpacing() + 2 * self.margin() + 6)

    def sizeHint(self) -> QSize:
        return QSize(super().sizeHint().width(), self.height())

    def changeEvent(self, event: Any) -> None:
        if event.type() in (QEvent.Type.FontChange, QEvent.Type.StyleChange):
            self._fit_height()
        super().changeEvent(event)

    def _elide(self) -> None:
        full = self.full_text()
        width = self.contentsRect().width() - 2 * self.margin()
        shown = wrap_elided(full, self.fontMetrics(), max(width, 0), self.lines)
        if shown != self.text():
            QLabel.setText(self, shown)
        cut = shown.replace("\n", " ") != full
        tip = self._tip or (full if cut else "")
        if tip != self.toolTip():
            self.setToolTip(tip)

    def is_elided(self) -> bool:
        return self.text().replace("\n", " ") != self.full_text()

    def setText(self, text: str) -> None:  # the panel's own calls: the same as set_full_text
        self.set_full_text(text)


def alarm_time(alarm: Alarm) -> str:
    return time.strftime("%H:%M:%S", time.localtime(alarm.t_wall))


def highest_unacknowledged(alarms: list[Alarm]) -> tuple[Alarm | None, int]:
    """The most urgent unacknowledged alarm (newest among the highest level) and how many are open."""
    open_ = [a for a in alarms if not a.acknowledged]
    if not open_:
        return None, 0
    return max(open_, key=lambda a: (int(a.level), a.ident)), len(open_)


class AlarmsPanel(QWidget):
    """The alarm list with Acknowledge selected / all (operator's name required)."""

    def __init__(self, manager: LinarmppManager, repeat_s: float = 15.0) -> None:
        super().__init__()
        self.manager = manager
        self.supervisor = manager.supervisor
        self.beep: Callable[[], None] = QApplication.beep
        self.beeps = 0
        self.acknowledged_by: dict[int, str] = {}  # ident -> operator (the supervisor keeps only the flag)
        # The list is kept up to date row by row, never rebuilt on an alarm: an e-stop raises one, and a
        # rebuild (growing with the session's alarms) held up the GUI thread -- and the next e-stop.
        self._rows: dict[int, QTreeWidgetItem] = {}  # ident -> its row (only the rows in the list)
        self._known: dict[int, bool] = {}  # every alarm seen -> acknowledged, as shown
        self._summary_shown: tuple[str, str] | None = None

        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.setSpacing(4)
        self.summary = LinesLabel(2)
        self.summary.setObjectName("alarmSummary")
        lay.addWidget(self.summary)

        self.tree = QTreeWidget()
        self.tree.setObjectName("alarmList")
        self.tree.setAccessibleName("Alarms")
        self.tree.setColumnCount(len(COLUMNS))
        self.tree.setHeaderLabels(list(COLUMNS))
        self.tree.setRootIsDecorated(False)
        self.tree.setUniformRowHeights(True)
        self.tree.setAlternatingRowColors(False)
        self.tree.setSelectionMode(QAbstractItemView.SelectionMode.ExtendedSelection)
        header = self.tree.header()
        header.setStretchLastSection(False)
        for col in range(len(COLUMNS)):
            header.setSectionResizeMode(col, QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(MESSAGE_COLUMN, QHeaderView.ResizeMode.Stretch)
        # A long message is elided in the row; the selected alarm's full text is shown below the list.
        self.tree.itemSelectionChanged.connect(self._show_details)
        lay.addWidget(self.tree, 1)

        row = QHBoxLayout()
        op_label = QLabel("&Operator:")
        self.operator = QLineEdit()
        self.operator.setObjectName("operator")
        self.operator.setPlaceholderText("operator's name")
        self.operator.setToolTip("Who acknowledges; filled in with the session's operator")
        # The session's operator, so nobody retypes it (issue #19); a typed name is kept.
        manager.session_changed.connect(self._on_session)
        self.operator.setMaximumWidth(200)
        op_label.setBuddy(self.operator)
        self.ack_selected = QPushButton("&Acknowledge selected")
        self.ack_selected.clicked.connect(self.acknowledge_selected)
        self.ack_all = QPushButton("Acknowledge a&ll")
        self.ack_all.clicked.connect(self.acknowledge_all)
        self.show_acknowledged = QCheckBox("Show ac&knowledged")
        self.show_acknowledged.setChecked(True)
        self.show_acknowledged.toggled.connect(lambda _on: self.rebuild())
        row.addWidget(op_label)
        row.addWidget(self.operator)
        row.addWidget(self.ack_selected)
        row.addWidget(self.ack_all)
        row.addStretch(1)
        row.addWidget(self.show_acknowledged)
        lay.addLayout(row)
        self.message = LinesLabel(3)  # the selected alarm in full (the row elides it)
        self.message.setObjectName("alarmMessage")
        self.message.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        lay.addWidget(self.message)

        self.repeat = QTimer(self)
        self.repeat.setInterval(int(repeat_s * 1000))
        self.repeat.timeout.connect(self._repeat_sound)
        bold = QFont(self.tree.font())
        bold.setBold(True)
        self._fonts = {False: bold, True: QFont(self.tree.font())}  # acknowledged -> font
        self._brushes = {level: (QBrush(QColor(style.background)), QBrush(QColor(style.foreground)))
                         for level, style in LEVEL_STYLES.items()}
        self._plain = (QBrush(), QBrush())  # the view's own colours (acknowledged rows, except the level)
        adapter = shared_qt_bus(manager.bus, manager.supervisor.alarm)
        adapter.alarm_raised.connect(self._on_alarm)
        # The adapter emits alarms_changed after every alarm_raised: the list follows that one only.
        adapter.alarms_changed.connect(self.refresh)
        self.refresh()

    def _on_session(self, _folder: object) -> None:
        if self.manager.recorder is not None and not self.operator.text().strip():
            self.operator.setText(self.manager.operator)

    # ------------------------------------------------------------------ sound
    def _sound(self) -> None:
        self.beeps += 1
        try:
            self.beep()
        except Exception:  # a missing sound device must never take the alarm list down
            pass

    def _on_alarm(self, alarm: Alarm) -> None:
        if alarm.level >= SOUNDING:
            self._sound()

    def _repeat_sound(self) -> None:
        if any(a.level >= SOUNDING and not a.acknowledged for a in self.supervisor.alarms()):
            self._sound()

    # ------------------------------------------------------------------ acknowledgement
    def _operator(self) -> str | None:
        name = self.operator.text().strip() or self.manager.operator.strip()
        if name and not self.operator.text().strip():
            self.operator.setText(name)  # the session's operator: no retyping
        if not name:
            self.message.setText("Type the operator's name before acknowledging: it goes into the session record.")
            self.message.setStyleSheet("color: #c62828; font-weight: bold;")
            self.operator.setFocus()
            return None
        return name

    def acknowledge(self, idents: list[int]) -> int:
        """Acknowledge these alarms in the operator's name; returns how many were acknowledged."""
        operator = self._operator()
        if operator is None:
            return 0
        open_ids = {a.ident for a in self.supervisor.alarms() if not a.acknowledged}
        done = 0
        for ident in idents:
            if ident in open_ids:
                self.acknowledged_by[ident] = operator
                self.supervisor.acknowledge(ident, operator)
                done += 1
        self.message.setText(f"{done} alarm(s) acknowledged by {operator}." if done else "Nothing to acknowledge.")
        self.message.setStyleSheet("")
        self.refresh()
        return done

    def acknowledge_selected(self) -> int:
        idents = [int(item.data(0, Qt.ItemDataRole.UserRole)) for item in self.tree.selectedItems()]
        if not idents:
            self.message.setText("Select the alarms to acknowledge first (or use Acknowledge all).")
            self.message.setStyleSheet("")
            return 0
        return self.acknowledge(idents)

    def acknowledge_all(self) -> int:
        return self.acknowledge([a.ident for a in self.supervisor.alarms() if not a.acknowledged])

    # ------------------------------------------------------------------ list
    def refresh(self) -> None:
        """Bring the list up to date: add rows for new alarms, restyle those whose acknowledgement
        changed, drop rows of alarms the supervisor no longer has. Rows are never rebuilt here."""
        alarms = self.supervisor.alarms()
        show_acked = self.show_acknowledged.isChecked()
        new: list[Alarm] = []
        for alarm in alarms:
            known = self._known.get(alarm.ident)
            if known is None:
                self._known[alarm.ident] = alarm.acknowledged
                if show_acked or not alarm.acknowledged:
                    new.append(alarm)
            elif known != alarm.acknowledged:
                self._known[alarm.ident] = alarm.acknowledged
                row = self._rows.get(alarm.ident)
                if row is None:
                    continue
                if alarm.acknowledged and not show_acked:
                    self._remove_row(alarm.ident)
                else:
                    self._style_row(row, alarm)
        if len(self._known) != len(alarms):  # the supervisor forgot some alarms: forget their rows
            present = {a.ident for a in alarms}
            for ident in [i for i in self._known if i not in present]:
                del self._known[ident]
                if ident in self._rows:
                    self._remove_row(ident)
        for alarm in new:
            self._insert_row(alarm)
        if len(self._rows) > ROW_LIMIT:
            self._trim_rows()
        self._show_summary(alarms)

    def rebuild(self) -> None:
        """Drop every row and list the alarms again (the "show acknowledged" filter changed)."""
        selected = {int(i.data(0, Qt.ItemDataRole.UserRole)) for i in self.tree.selectedItems()}
        self.tree.clear()
        self._rows.clear()
        self._known.clear()
        self.refresh()
        for ident in selected & self._rows.keys():
            self._rows[ident].setSelected(True)

    def _insert_row(self, alarm: Alarm) -> None:
        style = LEVEL_STYLES[alarm.level]
        item = QTreeWidgetItem([style.name.upper(), alarm_time(alarm), alarm.source, "", alarm.text])
        item.setData(0, Qt.ItemDataRole.UserRole, alarm.ident)
        item.setToolTip(MESSAGE_COLUMN, alarm.text)
        self._style_row(item, alarm)
        # Newest first. Alarms arrive in order, so this is row 0 but for a rare race between threads.
        index = 0
        count = self.tree.topLevelItemCount()
        while index < count and int(self.tree.topLevelItem(index).data(0, Qt.ItemDataRole.UserRole)) > alarm.ident:
            index += 1
        self.tree.insertTopLevelItem(index, item)
        self._rows[alarm.ident] = item

    def _remove_row(self, ident: int) -> None:
        item = self._rows.pop(ident)
        self.tree.takeTopLevelItem(self.tree.indexOfTopLevelItem(item))

    def _trim_rows(self) -> None:
        """Keep ROW_LIMIT rows: the oldest acknowledged rows go first, open alarms only when no
        acknowledged row is left."""
        excess = len(self._rows) - ROW_LIMIT
        for index in range(self.tree.topLevelItemCount() - 1, -1, -1):
            if excess <= 0:
                return
            ident = int(self.tree.topLevelItem(index).data(0, Qt.ItemDataRole.UserRole))
            if self._known.get(ident, True):
                self._remove_row(ident)
                excess -= 1
        while excess > 0:
            ident = int(self.tree.topLevelItem(self.tree.topLevelItemCount() - 1).data(0, Qt.ItemDataRole.UserRole))
            self._remove_row(ident)
            excess -= 1

    def _style_row(self, item: QTreeWidgetItem, alarm: Alarm) -> None:
        if alarm.acknowledged:
            who = self.acknowledged_by.get(alarm.ident)
            status = f"ack. {who}" if who else "ack."
        else:
            status = "ACTIVE"
        item.setText(STATUS_COLUMN, status)
        bg, fg = self._brushes[alarm.level]
        font = self._fonts[alarm.acknowledged]
        for col in range(len(COLUMNS)):
            item.setFont(col, font)
            coloured = col == 0 or not alarm.acknowledged
            item.setBackground(col, bg if coloured else self._plain[0])
            item.setForeground(col, fg if coloured else self._plain[1])

    def _show_summary(self, alarms: list[Alarm]) -> None:
        top, count = highest_unacknowledged(alarms)
        if top is None:
            text, sheet = f"No active alarms ({len(alarms)} in this session).", ""
            self.repeat.stop()
        else:
            style = LEVEL_STYLES[top.level]
            text = f"{count} active alarm(s); most urgent: {style.name.upper()} — {top.text}"
            sheet = f"background: {style.background}; color: {style.foreground}; font-weight: bold; padding: 3px;"
            if top.level >= SOUNDING and not self.repeat.isActive():
                self.repeat.start()
            elif top.level < SOUNDING:
                self.repeat.stop()
        if (text, sheet) != self._summary_shown:  # a style sheet re-polishes: only on a change
            self._summary_shown = (text, sheet)
            self.summary.setText(text)
            self.summary.setStyleSheet(sheet)
        self.ack_all.setEnabled(count > 0)

    def _show_details(self) -> None:
        items = self.tree.selectedItems()
        if len(items) != 1:
            return
        ident = int(items[0].data(0, Qt.ItemDataRole.UserRole))
        alarm = next((a for a in self.supervisor.alarms() if a.ident == ident), None)
        if alarm is not None:
            style = LEVEL_STYLES[alarm.level]
            self.message.setText(f"{style.name.upper()} #{alarm.ident} at {alarm_time(alarm)} from {alarm.source}: "
                                 f"{alarm.text}")
            self.message.setStyleSheet("")

    def level_colour_of_row(self, row: int) -> str:
        """Background colour name of the level cell of ``row`` (tests)."""
        item = self.tree.topLevelItem(row)
        return item.background(0).color().name()


def newest_unacknowledged(alarms: list[Alarm]) -> tuple[Alarm | None, int]:
    """The newest unacknowledged alarm and how many are open: the banner shows what just happened,
    never a stale alarm from before an e-stop reset."""
    open_ = [a for a in alarms if not a.acknowledged]
    if not open_:
        return None, 0
    return max(open_, key=lambda a: a.ident), len(open_)


class AlarmBanner(QFrame):
    """One line for the main window (beside the e-stop): the newest unacknowledged alarm in its
    level's colour, how many are open, and the one place to recover after a STOP (``Recover…``).
    ``show_alarms_requested`` asks the window to show the alarms panel. ``restart_provider`` (set by
    the window) says which interrupted exercise Recover may start again."""

    show_alarms_requested = Signal()
    recovered = Signal(bool, str)

    def __init__(self, manager: LinarmppManager) -> None:
        super().__init__()
        self.manager = manager
        self.restart_provider: Callable[[], Restartable | None] = lambda: None
        self.operator_provider: Callable[[], str] = lambda: manager.operator
        self.script_running: Callable[[], bool] = lambda: False
        self.stop_script: Callable[[], bool] = lambda: False
        self.dialog: RecoverDialog | None = None
        self.recovery: Recovery | None = None
        self.setObjectName("AlarmBanner")
        self.setFrameShape(QFrame.Shape.StyledPanel)
        row = QHBoxLayout(self)
        row.setContentsMargins(6, 2, 6, 2)
        self.label = LinesLabel(2)  # the alarm on two lines, readable at 1366×768; the whole in its tooltip
        self.label.setObjectName("alarmBannerText")
        row.addWidget(self.label, 1)
        self.recover_button = QPushButton("&Recover…")
        self.recover_button.setObjectName("recover")
        self.recover_button.setToolTip("Acknowledge the alarms, reset the e-stop and the robot's error, "
                                       "re-home and restart the interrupted exercise")
        self.recover_button.setStyleSheet("QPushButton { font-weight: bold; }")
        self.recover_button.clicked.connect(self.start_recovery)
        self.recover_button.setVisible(False)
        row.addWidget(self.recover_button)
        self.button = QPushButton("Alarms…")
        self.button.setToolTip("Show the alarm list")
        self.button.clicked.connect(self.show_alarms_requested.emit)
        row.addWidget(self.button)
        self.current: Alarm | None = None
        self._shown: tuple[str, str, str] | None = None
        adapter = shared_qt_bus(manager.bus, manager.supervisor.alarm)
        adapter.alarms_changed.connect(self.refresh)
        # A method, not a lambda: the connection ends with this banner (the window's adapter outlives it).
        adapter.estop_changed.connect(self._estop_changed)
        # A robot error can outlast its acknowledged alarm: look again now and then.
        self._timer = QTimer(self)
        self._timer.setInterval(500)
        self._timer.timeout.connect(self._refresh_recover)
        self._timer.start()
        self.refresh()

    def _estop_changed(self, _latched: bool, _reason: str) -> None:
        self.refresh()

    def refresh(self) -> None:
        top, count = newest_unacknowledged(self.manager.supervisor.alarms())
        self.current = top
        self.button.setText(f"Alarms ({count})…" if count else "Alarms…")
        # The newest alarm is the one shown; the list button stays red while any STOP is open.
        worst, _n = highest_unacknowledged(self.manager.supervisor.alarms())
        urgent = worst is not None and worst.level >= SOUNDING
        sheet = (f"QPushButton {{ background: {LEVEL_STYLES[worst.level].background}; "
                 f"color: {LEVEL_STYLES[worst.level].foreground}; font-weight: bold; }}") if urgent and worst else ""
        if self.button.styleSheet() != sheet:
            self.button.setStyleSheet(sheet)
        self._refresh_recover()
        if top is None:
            self._show("No active alarms", "", "color: #757575;")
            return
        style = LEVEL_STYLES[top.level]
        text = f"{style.name.upper()} {alarm_time(top)} · {top.source}: {top.text}"
        self._show(text, f"#AlarmBanner {{ background: {style.background}; }}",
                   f"color: {style.foreground}; font-weight: bold;")

    def _refresh_recover(self) -> None:
        needed = recovery_needed(self.manager) and self.recovery is None
        if needed == self.recover_button.isHidden():  # only on a change (no re-layout twice a second)
            self.recover_button.setVisible(needed)

    def start_recovery(self) -> RecoverDialog:
        """Open the Recover dialog (non-blocking); its choice runs the recovery."""
        restart = self.restart_provider()
        dialog = RecoverDialog(self.manager, self.operator_provider(), restart, self.window(),
                               script_running=self.script_running())
        self.dialog = dialog

        def accepted() -> None:
            chosen = restart
            if restart is None or dialog.choice == "recover":
                chosen = None
            elif dialog.choice == "continue":
                chosen = restart.continuation()
            self.run_recovery(dialog.operator_name(), chosen)

        dialog.accepted.connect(accepted)
        dialog.open()
        return dialog

    def run_recovery(self, operator: str, restart: Restartable | None) -> Recovery:
        recovery = Recovery(self.manager, operator, restart, self, stop_script=self.stop_script)
        self.recovery = recovery
        self.recover_button.setVisible(False)

        def done(ok: bool, text: str) -> None:
            self.recovery = None
            self.recovered.emit(ok, text)
            self.refresh()

        recovery.finished.connect(done)
        recovery.run()
        return recovery

    def _show(self, text: str, frame_sheet: str, label_sheet: str) -> None:
        # Style sheets re-polish the banner and its children: set them only when the level changes.
        shown = self._shown or ("", None, None)
        if text != shown[0]:
            self.label.set_full_text(text)
            self.setAccessibleName(text)
        if frame_sheet != shown[1]:
            self.setStyleSheet(frame_sheet)
        if label_sheet != shown[2]:
            self.label.setStyleSheet(label_sheet)
        self._shown = (text, frame_sheet, label_sheet)
