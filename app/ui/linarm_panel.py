"""The LINarm manager panel (seed D2.2 §3.1, Fig. 4): every command of the LinarmUser API as
buttons and inputs, for the commands frame.

The inputs are generated from the protocol table (``COMMANDS_BY_NAME``): one input per argument,
with the table's kind, unit and range, so the panel cannot drift from the wire. The ranges shown
next to the inputs are the safety supervisor's limits (``config.safety.robot``); the inputs
themselves accept anything the wire can carry, because the supervisor -- not the panel -- is the one
place that enforces limits, and its refusal is shown in plain words.

Every command goes through ``LinarmDriver.submit`` (the device's one command queue, #29): it returns a
CommandStatus at once and the GUI thread never waits on it; a timer collects the finished statuses on the
GUI thread and shows each outcome: done, refused by the supervisor (its reason, in red), refused by the
controller (its code), timeout or link lost.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QColor, QFocusEvent, QHideEvent
from PySide6.QtWidgets import (
    QAbstractSpinBox,
    QButtonGroup,
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFrame,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QProgressBar,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QSpinBox,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from app.core import journal, streams
from app.devices.command_queue import CommandQueueClosed, CommandStatus
from app.devices.linarm import LinarmCommandError, LinarmTimeout
from app.devices.transport import TransportError
from app.manager import LinarmppManager
from app.safety.supervisor import SafetyError
from app.ui.qt_bus import shared_qt_bus
from app.ui.theme import colours
from app.ui.widgets import RefreshWhenVisible
from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import Kind
from app.wire.linarm_constants import K
from app.wire.linarm_protocol import (
    COMMANDS_BY_NAME,
    ENUMS,
    Arg,
    ControlState,
    ErrorState,
    HomeState,
    ReplyError,
)

log = logging.getLogger(__name__)

SOURCE = "gui"

# ------------------------------------------------------------------------------------------- inputs

UNIT_TEXT = {"m/s^2": "m/s²", "m/(N s)": "m/(N·s)", "N/(m s)": "N/(m·s)", "N s/m": "N·s/m"}
# unit -> (decimals, single step, half-span used when the table gives no range)
UNIT_INPUT: dict[str, tuple[int, float, float]] = {
    "m": (4, 0.005, 1.0),
    "m/s": (3, 0.01, 2.0),
    "m/s^2": (3, 0.05, 20.0),
    "s": (2, 0.1, 600.0),
    "N/m": (1, 50.0, 20000.0),
    "N": (1, 1.0, 1000.0),
    "A": (2, 0.1, 50.0),
    "m/(N s)": (5, 0.0005, 1.0),
    "N/(m s)": (2, 1.0, 1e6),
    "N s/m": (2, 1.0, 1e5),
    "m/count": (9, 1e-6, 1.0),
    "": (4, 0.01, 1000.0),
}

# The inputs of the controller's own settings start at its defaults, read from the one constants table
# (app/wire/linarm_constants.py, which the firmware and the simulator use too); "Read" buttons fetch the
# live values. The move inputs start at modest values of the panel's own.
CONTROLLER_DEFAULTS: dict[str, float] = {
    "Ka": K["ADMITTANCE_KA"], "Kt": K["ASSISTANCE_KT"], "Apos": K["ASSISTANCE_TARGET"],
    "minPos": K["POS_MIN"], "maxPos": K["POS_MAX"], "maxTrackingError": K["MAX_TRACKING_ERROR"],
    "maxForce": K["MAX_FORCE"], "maxCurrent": K["MAX_CURRENT"],
    "homeCentre": K["HOME_CENTRE"], "homeDelta": K["HOME_DELTA"], "homingVelocity": K["HOMING_VELOCITY"],
}
DEFAULTS: dict[str, Any] = {
    "targetPos": K["HOME_CENTRE"], "targetDeltaPos": K["HOME_DELTA"], "stiffness": 900.0,
    "maxVel": 0.15, "maxAcc": 0.15, "execTime": 0.0, "trigger": False,
    "centreVelocity": 0.05, "deltaVelocity": 0.01, "disp": 0.0, "param": 0.0,
    **CONTROLLER_DEFAULTS,
}

ARG_LABELS: dict[str, str] = {
    "targetPos": "Centre target", "targetDeltaPos": "Delta target", "stiffness": "Stiffness",
    "maxVel": "Max velocity", "maxAcc": "Max acceleration", "execTime": "Duration", "trigger": "Wait for trigger",
    "centreVelocity": "Centre speed", "deltaVelocity": "Delta speed",
    "Ka": "Admittance Ka", "Kt": "Assistance Kt", "Apos": "Assistance target", "disp": "Spring displacement",
    "minPos": "Min position", "maxPos": "Max position", "maxTrackingError": "Max tracking error",
    "maxForce": "Max force", "maxCurrent": "Max current", "homeCentre": "Home centre", "homeDelta": "Home delta",
    "homingVelocity": "Homing velocity", "index": "Motor", "kp": "Kp", "ki": "Ki", "kd": "Kd",
    "mode": "Trigger mode", "param": "Trigger parameter", "controlMode": "Control mode", "type": "Trajectory",
    "demo": "Demo", "virtual": "Virtual VSA", "disable": "Disable endstrokes", "controlState": "Control state",
}

COMMAND_TITLES: dict[str, str] = {
    "setCtrlState": "Control state", "setCtrlMode": "Set mode", "goToHome": "Go home", "resetError": "Reset error",
    "setTrajectoryType": "Set trajectory", "moveCentreTo": "Move centre", "moveDeltaTo": "Move delta",
    "setStiffness": "Set stiffness", "setCentreVelocity": "Jog centre", "setDeltaVelocity": "Jog delta",
    "setPidTunings": "PID tunings", "getPidTunings": "Read PID tunings", "setHomeParameter": "Home parameters",
    "setPosLimit": "Position limits",
}

CODE_HINTS: dict[ReplyError, str] = {
    ReplyError.UNKNOWN_COMMAND: "the controller does not know this command (firmware version?)",
    ReplyError.BAD_ARGUMENT: "an argument could not be read",
    ReplyError.OUT_OF_RANGE: "a value is outside the controller's limits",
    ReplyError.WRONG_STATE: "not allowed in the current control state",
    ReplyError.WRONG_MODE: "not allowed in the current control mode: select the right mode first",
    ReplyError.NOT_HOMED: "the robot is not homed: press Go home first",
    ReplyError.IN_ERROR: "an error is latched: press Reset error first",
    ReplyError.BUSY: "homing is in progress: wait, or press Idle to cancel",
    ReplyError.NOT_SUPPORTED: "not supported with the current trigger mode",
}

HOME_TEXT: dict[int, str] = {
    HomeState.HOME_NOT_DONE: "Not homed",
    HomeState.HOME_SEEK_MIN: "Homing 1/3: seeking the min endstroke",
    HomeState.HOME_SEEK_MAX: "Homing 2/3: seeking the max endstroke",
    HomeState.HOME_MOVE_TO_HOME: "Homing 3/3: moving to home",
    HomeState.HOME_DONE: "Homed",
}


def unit_text(unit: str) -> str:
    return UNIT_TEXT.get(unit, unit)


PRETTY_NAMES = {"VEL": "Velocity", "TARGET_POS": "Target position", "TRAPEZOIDAL": "Trapezoidal",
                "NO_TRIGGER": "No trigger", "TRIGGER_ON_FORCE": "On force", "TRIGGER_ON_POSITION": "On position"}


def pretty_enum(member: Any) -> str:
    """``POS_REF_BY_TARGET_POS`` -> ``Target position``; ``ON_CTRL_STATE`` -> ``On``."""
    name = member.name
    if name.endswith("_CTRL_STATE"):
        name = name[: -len("_CTRL_STATE")]
    for prefix in ("POS_REF_BY_", "HOME_"):
        if name.startswith(prefix):
            name = name[len(prefix):]
    return PRETTY_NAMES.get(name, name.replace("_", " ").lower().capitalize())


def command_title(name: str) -> str:
    if name in COMMAND_TITLES:
        return COMMAND_TITLES[name]
    words = []
    for ch in name:
        if ch.isupper() and words:
            words.append(" ")
        words.append(ch.lower())
    return "".join(words).capitalize()


class ArgInput:
    """One argument's input, generated from its table entry (kind, unit, enum, range)."""

    def __init__(self, arg: Arg, default: Any = None) -> None:
        self.arg = arg
        self.label = ARG_LABELS.get(arg.name, arg.name)
        self.widget: QWidget
        if arg.enum is not None:
            box = QComboBox()
            for member in ENUMS[arg.enum]:
                box.addItem(f"{pretty_enum(member)} ({int(member)})", int(member))
            if default is not None:
                box.setCurrentIndex(max(0, box.findData(int(default))))
            self.widget = box
        elif arg.kind is Kind.TEXT_BOOL:
            check = QCheckBox(self.label)
            check.setChecked(bool(default))
            self.widget = check
        elif arg.kind is Kind.TEXT_INT:
            spin = QSpinBox()
            spin.setRange(int(arg.min if arg.min is not None else -(2**31)),
                          int(arg.max if arg.max is not None else 2**31 - 1))
            spin.setValue(int(default or spin.minimum()))
            self.widget = spin
        else:
            decimals, step, span = UNIT_INPUT.get(arg.unit, UNIT_INPUT[""])
            spin = QDoubleSpinBox()
            spin.setDecimals(decimals)
            spin.setSingleStep(step)
            lo = arg.min if arg.min is not None else -span
            hi = arg.max if arg.max is not None else span
            spin.setRange(lo, hi)
            if arg.unit:
                spin.setSuffix(f" {unit_text(arg.unit)}")
            spin.setValue(float(default if default is not None else max(lo, min(hi, 0.0))))
            spin.setAccelerated(True)
            spin.setCorrectionMode(QAbstractSpinBox.CorrectionMode.CorrectToNearestValue)
            spin.setKeyboardTracking(False)
            spin.setMinimumWidth(110)
            self.widget = spin
        self.widget.setObjectName(f"arg:{arg.name}")
        self.widget.setAccessibleName(f"{self.label} ({unit_text(arg.unit)})" if arg.unit else self.label)

    def value(self) -> Any:
        w = self.widget
        if isinstance(w, QComboBox):
            return int(w.currentData())
        if isinstance(w, QCheckBox):
            return w.isChecked()
        if isinstance(w, QSpinBox):
            return int(w.value())
        assert isinstance(w, QDoubleSpinBox)
        return float(w.value())

    def set_value(self, value: Any) -> None:
        w = self.widget
        if isinstance(w, QComboBox):
            w.setCurrentIndex(max(0, w.findData(int(value))))
        elif isinstance(w, QCheckBox):
            w.setChecked(bool(value))
        elif isinstance(w, QSpinBox):
            w.setValue(int(value))
        elif isinstance(w, QDoubleSpinBox) and math.isfinite(float(value)):
            w.setValue(float(value))

    def set_hint(self, hint: str) -> None:
        table = ""
        if self.arg.min is not None or self.arg.max is not None:
            table = f"protocol range {self.arg.min if self.arg.min is not None else '−∞'} .. " \
                    f"{self.arg.max if self.arg.max is not None else '+∞'}"
        tip = "; ".join(t for t in (hint and f"allowed {hint}", table) if t)
        self.widget.setToolTip(f"{self.label}{' — ' + tip if tip else ''}")
        self.widget.setAccessibleDescription(tip)


class HoldButton(QPushButton):
    """A press-and-hold button: ``held`` on press, ``let_go`` on release -- also when the pointer
    leaves it, when it loses focus or is hidden, so a jog can never be left running by the GUI."""

    held = Signal()
    let_go = Signal()

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.setAutoRepeat(False)
        self._holding = False
        self.pressed.connect(self._press)
        self.released.connect(self._release)

    @property
    def holding(self) -> bool:
        return self._holding

    def _press(self) -> None:
        if not self._holding:
            self._holding = True
            self.held.emit()

    def _release(self) -> None:
        if self._holding:
            self._holding = False
            self.let_go.emit()

    def focusOutEvent(self, event: QFocusEvent) -> None:
        super().focusOutEvent(event)
        self.setDown(False)
        self._release()

    def hideEvent(self, event: QHideEvent) -> None:
        super().hideEvent(event)
        self._release()

    def changeEvent(self, event: Any) -> None:
        super().changeEvent(event)
        if not self.isEnabled():
            self._release()


@dataclass
class Outcome:
    command: str
    kind: str  # "sending", "ok", "refused", "controller", "timeout", "link", "error", "event"
    text: str
    code: ReplyError | None = None
    t_wall: float = 0.0

    @property
    def ok(self) -> bool:
        return self.kind == "ok"


class CommandForm:
    """The inputs of one command plus its button(s); ``shared`` inputs are used instead of own ones
    (the move commands share one motion profile)."""

    def __init__(self, panel: LinarmPanel, name: str, button_text: str | None = None, *,
                 shared: dict[str, ArgInput] | None = None, read: str | None = None,
                 fixed: dict[str, Any] | None = None) -> None:
        self.panel = panel
        self.name = name
        self.command = COMMANDS_BY_NAME[name]
        shared = shared or {}
        self.fixed = fixed or {}
        self.inputs: dict[str, ArgInput] = {}
        self.own: list[ArgInput] = []
        for arg in self.command.args:
            if arg.name in self.fixed:
                continue
            if arg.name in shared:
                self.inputs[arg.name] = shared[arg.name]
                continue
            inp = ArgInput(arg, DEFAULTS.get(arg.name))
            inp.set_hint(panel.limit_hint(arg.name))
            self.inputs[arg.name] = inp
            self.own.append(inp)
        self.button = QPushButton(button_text or command_title(name))
        self.button.setObjectName(f"send:{name}")
        self.button.setToolTip(f"Send {name}" + (f" — {self.command.doc}" if self.command.doc else ""))
        self.button.clicked.connect(self.send)
        self.read_button: QPushButton | None = None
        self._needs_read = False
        self.read = read
        if read is not None:
            self.read_button = QPushButton("Read")
            self.read_button.setObjectName(f"send:{read}")
            self.read_button.setToolTip(f"Read the controller's value ({read})")
            self.read_button.clicked.connect(self.read_back)

    def require_read(self) -> None:
        """Keep Send disabled until a Read succeeded for the current read arguments (e.g. the motor)."""
        self._needs_read = True
        self.button.setEnabled(False)
        self.button.setToolTip("Read the current values first (nothing is sent with placeholder values)")
        assert self.read is not None
        for arg in COMMANDS_BY_NAME[self.read].args:
            widget = self.inputs[arg.name].widget
            signal = widget.currentIndexChanged if isinstance(widget, QComboBox) else widget.valueChanged
            signal.connect(lambda *_a: self.button.setEnabled(False))

    def values(self) -> tuple[Any, ...]:
        out = []
        for arg in self.command.args:
            out.append(self.fixed[arg.name] if arg.name in self.fixed else self.inputs[arg.name].value())
        return tuple(out)

    def send(self) -> CommandStatus | None:
        return self.panel.send(self.name, *self.values())

    def read_back(self) -> CommandStatus | None:
        assert self.read is not None
        spec = COMMANDS_BY_NAME[self.read]
        args = tuple(self.inputs[a.name].value() for a in spec.args)

        def fill(values: dict[str, Any]) -> None:
            for key, value in values.items():
                if key in self.inputs and key not in ("index",):
                    self.inputs[key].set_value(value)
            if self._needs_read and all(values.get(k, v) == v for k, v in zip(
                    (a.name for a in spec.args), args, strict=True)):
                self.button.setEnabled(True)

        return self.panel.send(self.read, *args, on_ok=fill)

    def add_to(self, grid: QGridLayout, row: int, title: str | None = None) -> int:
        """Lay the form out on ``grid`` (label | input | allowed range | buttons); returns the next row."""
        buttons = QHBoxLayout()
        buttons.setSpacing(4)
        buttons.addWidget(self.button)
        if self.read_button is not None:
            buttons.addWidget(self.read_button)
        if title is not None or len(self.own) != 1:
            head = QLabel(f"<b>{title or command_title(self.name)}</b>")
            grid.addWidget(head, row, 0, 1, 3)
            grid.addLayout(buttons, row, 3)
            row += 1
            first = False
        else:
            first = True
        for inp in self.own:
            if isinstance(inp.widget, QCheckBox):
                grid.addWidget(inp.widget, row, 0, 1, 2)
            else:
                label = QLabel(inp.label)
                label.setBuddy(inp.widget)
                grid.addWidget(label, row, 0)
                grid.addWidget(inp.widget, row, 1)
            hint = QLabel(self.panel.limit_hint(inp.arg.name))
            hint.setObjectName("hint")
            hint.setStyleSheet(f"color: {colours().idle};")
            grid.addWidget(hint, row, 2)
            if first:
                grid.addLayout(buttons, row, 3)
                first = False
            row += 1
        return row


def _restyle(widget: QWidget, sheet: str) -> None:
    """Set a style sheet only when it changes (each call re-polishes the widget: slow at 10 Hz)."""
    if widget.styleSheet() != sheet:
        widget.setStyleSheet(sheet)


def _set_text(label: QLabel, text: str) -> None:
    if label.text() != text:
        label.setText(text)


def _set_format(bar: QProgressBar, text: str) -> None:
    if bar.format() != text:
        bar.setFormat(text)


def _grid() -> QGridLayout:
    grid = QGridLayout()
    grid.setContentsMargins(6, 6, 6, 6)
    grid.setHorizontalSpacing(8)
    grid.setVerticalSpacing(4)
    grid.setColumnStretch(2, 1)
    return grid


def _scroll(content: QWidget) -> QScrollArea:
    area = QScrollArea()
    area.setWidgetResizable(True)
    area.setFrameShape(QFrame.Shape.NoFrame)
    area.setProperty("scrolls", True)  # a long form: its lower rows may scroll (primary controls are on top)
    area.setWidget(content)
    return area


# -------------------------------------------------------------------------------------------- panel


class LinarmPanel(RefreshWhenVisible, QWidget):
    """Buttons and inputs for the LINarm: states, modes, homing, moves, jog, interaction parameters,
    limits. ``last_outcome`` / ``outcomes`` hold what the operator saw (tests read them)."""

    refresh_timer_attr = "_timer"

    outcome_shown = Signal(object)  # Outcome

    def __init__(self, manager: LinarmppManager) -> None:
        super().__init__()
        self.manager = manager
        self.limits = manager.config.safety.robot
        self.outcomes: list[Outcome] = []
        self.last_outcome: Outcome | None = None
        self._pending: list[tuple[str, CommandStatus, Callable[[dict[str, Any]], None] | None]] = []
        # The controller's errors come from the journal, through the window's adapter (never from the driver).
        shared_qt_bus(manager.bus).device_event.connect(self._on_device_event)
        self.forms: dict[str, CommandForm] = {}

        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.setSpacing(3)
        self.status = QLabel()
        self.status.setObjectName("linarmStatus")
        self.status.setTextFormat(Qt.TextFormat.RichText)
        # No word wrap anywhere in this layout: a height-for-width label makes an enclosing scroll area
        # (the commands frame's) size the panel by its preferred height and scroll it as a whole.
        self.status.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        lay.addWidget(self.status)
        from app.ui.held_by import HeldByLabel

        self.held_by = HeldByLabel(manager.supervisor, "robot")  # one owner during a run (#36)
        lay.addWidget(self.held_by)

        self.tabs = QTabWidget()
        self.tabs.setDocumentMode(True)
        self.tabs.setUsesScrollButtons(True)
        lay.addWidget(self.tabs, 1)
        self.pages: list[QWidget] = []
        self._build_control_page()
        self._build_move_page()
        self._build_interaction_page()
        self._build_limits_page()
        self._build_log_page()

        self.outcome = QLabel("Ready.")
        self.outcome.setObjectName("linarmOutcome")
        self.outcome.setWordWrap(True)
        self.outcome.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.outcome.setFrameShape(QFrame.Shape.StyledPanel)
        self.outcome.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Fixed)
        # Room for two lines, always: the layout must not jump when a long refusal arrives.
        self.outcome.setFixedHeight(2 * self.outcome.fontMetrics().lineSpacing() + 8)
        lay.addWidget(self.outcome)

        self._poll = QTimer(self)
        self._poll.setInterval(30)
        self._poll.timeout.connect(self._collect)
        self._timer = QTimer(self)
        self._timer.setInterval(100)
        self._timer.timeout.connect(self._tick)
        self._timer.start()
        self.refresh()

    # ------------------------------------------------------------------ building
    def limit_hint(self, arg_name: str) -> str:
        """The supervisor's limit for an argument, as text (the inputs accept more: the supervisor decides)."""
        lim = self.limits
        pos = f"{lim.position_min_m:.3f} – {lim.position_max_m:.3f} m"
        return {
            "targetPos": pos, "Apos": pos, "minPos": pos, "maxPos": pos,
            "targetDeltaPos": f"0 – {lim.max_delta_m:.3f} m",
            "stiffness": f"0 – {lim.max_stiffness_n_m:.0f} N/m",
            "Kt": f"0 – {lim.max_stiffness_n_m:.0f} N/m",
            "maxVel": f"≤ {lim.max_velocity_m_s:.3f} m/s",
            "centreVelocity": f"≤ {lim.max_velocity_m_s:.3f} m/s",
            "deltaVelocity": f"≤ {lim.max_velocity_m_s:.3f} m/s",
            "maxAcc": f"≤ {lim.max_acceleration_m_s2:.3f} m/s²",
            "execTime": "0 = from max velocity/acceleration",
            "maxForce": f"≤ {lim.max_interaction_force_n:.0f} N",
            "Ka": f"≤ {lim.max_velocity_m_s / max(lim.max_interaction_force_n, 1e-9):.5f} m/(N·s)",
            "disp": f"± {lim.max_delta_m:.3f} m",
        }.get(arg_name, "")

    def _page(self, title: str) -> QVBoxLayout:
        content = QWidget()
        v = QVBoxLayout(content)
        v.setContentsMargins(4, 4, 4, 4)
        v.setSpacing(6)
        self.pages.append(content)
        self.tabs.addTab(_scroll(content), title)
        return v

    def _form(self, name: str, grid: QGridLayout, row: int, button: str | None = None, title: str | None = None,
              **kw: Any) -> int:
        form = CommandForm(self, name, button, **kw)
        self.forms[name] = form
        return form.add_to(grid, row, title)

    def _build_control_page(self) -> None:
        v = self._page("&Control")
        box = QGroupBox("Control state")
        g = _grid()
        box.setLayout(g)
        self.state_buttons: dict[int, QPushButton] = {}
        self.state_group = QButtonGroup(self)
        self.state_group.setExclusive(True)
        row = QHBoxLayout()
        for state, text, tip in (
            (ControlState.IDLE_CTRL_STATE, "&Idle", "Motors off (always accepted; cancels homing)"),
            (ControlState.HOME_CTRL_STATE, "Ho&me", "Homing, or hold the home position when already homed"),
            (ControlState.ON_CTRL_STATE, "O&n", "Motors on in the selected control mode (needs homing)"),
        ):
            b = QPushButton(text)
            b.setCheckable(True)
            b.setObjectName(f"state:{state.name}")
            b.setToolTip(tip)
            b.setMinimumHeight(30)
            b.clicked.connect(lambda _c=False, s=int(state): self.set_control_state(s))
            self.state_group.addButton(b, int(state))
            self.state_buttons[int(state)] = b
            row.addWidget(b)
        g.addLayout(row, 0, 0, 1, 4)

        self.home_button = QPushButton("&Go home")
        self.home_button.setObjectName("send:goToHome")
        self.home_button.setToolTip("Full homing on the endstroke switches if not yet homed, else move to home")
        self.home_button.clicked.connect(self.go_home)
        self.home_progress = QProgressBar()
        self.home_progress.setObjectName("homeProgress")
        self.home_progress.setRange(0, int(HomeState.HOME_DONE))
        self.home_progress.setTextVisible(True)
        self.home_progress.setAccessibleName("Homing progress")
        self.cancel_home = QPushButton("Cancel")
        self.cancel_home.setToolTip("Stop homing: motors off (Idle)")
        self.cancel_home.clicked.connect(lambda: self.set_control_state(int(ControlState.IDLE_CTRL_STATE)))
        self.cancel_home.setVisible(False)
        g.addWidget(self.home_button, 1, 0)
        g.addWidget(self.home_progress, 1, 1, 1, 2)
        g.addWidget(self.cancel_home, 1, 3)

        self.reset_button = QPushButton("&Reset error")
        self.reset_button.setObjectName("send:resetError")
        self.reset_button.setToolTip("Clear the latched error; the controller stays Idle")
        self.reset_button.clicked.connect(lambda: self.send("resetError"))
        self.error_label = QLabel()
        self.error_label.setObjectName("errorState")
        g.addWidget(self.reset_button, 2, 0)
        g.addWidget(self.error_label, 2, 1, 1, 3)
        v.addWidget(box)

        box = QGroupBox("Mode and trajectory")
        g = _grid()
        box.setLayout(g)
        r = self._form("setCtrlMode", g, 0)
        r = self._form("setTrajectoryType", g, r)
        v.addWidget(box)

        box = QGroupBox("Demo and virtual spring")
        g = _grid()
        box.setLayout(g)
        self.demo_check = QCheckBox("&Demo (run without the robot; Idle only)")
        self.demo_check.setObjectName("demo")
        self.demo_check.clicked.connect(lambda on: self.send("setDemo", bool(on)))
        self.virtual_check = QCheckBox("&Virtual VSA spring")
        self.virtual_check.setObjectName("virtualVsa")
        self.virtual_check.clicked.connect(lambda on: self.send("enableVirtualVsa", bool(on)))
        g.addWidget(self.demo_check, 0, 0, 1, 4)
        g.addWidget(self.virtual_check, 1, 0, 1, 4)
        self._form("setVirtualVsaSpringDisplacement", g, 2, "Set")
        v.addWidget(box)
        v.addStretch(1)

    def _build_move_page(self) -> None:
        v = self._page("&Move")
        box = QGroupBox("Motion profile (shared by the moves)")
        g = _grid()
        box.setLayout(g)
        move = COMMANDS_BY_NAME["moveCentreTo"]
        self.profile: dict[str, ArgInput] = {}
        row = 0
        for arg in move.args[1:]:
            inp = ArgInput(arg, DEFAULTS.get(arg.name))
            inp.set_hint(self.limit_hint(arg.name))
            self.profile[arg.name] = inp
            if isinstance(inp.widget, QCheckBox):
                inp.widget.setText("Wait for trigger (armed move; needs a trigger mode)")
                g.addWidget(inp.widget, row, 0, 1, 4)
            else:
                label = QLabel(inp.label)
                label.setBuddy(inp.widget)
                hint = QLabel(self.limit_hint(arg.name))
                hint.setStyleSheet(f"color: {colours().idle};")
                g.addWidget(label, row, 0)
                g.addWidget(inp.widget, row, 1)
                g.addWidget(hint, row, 2, 1, 2)
            row += 1
        v.addWidget(box)

        box = QGroupBox("Targets (mode Target position; the centre also in Impedance)")
        g = _grid()
        box.setLayout(g)
        r = self._form("moveCentreTo", g, 0, "Move", shared=self.profile)
        r = self._form("moveDeltaTo", g, r, "Move", shared=self.profile)
        self._form("setStiffness", g, r, "Set", shared=self.profile)
        v.addWidget(box)

        box = QGroupBox("Jog (mode Velocity): hold the button, release to stop")
        g = _grid()
        box.setLayout(g)
        self.jog_buttons: dict[str, tuple[HoldButton, HoldButton]] = {}
        self.jog_speed: dict[str, ArgInput] = {}
        for r, (name, minus, plus) in enumerate((("setCentreVelocity", "◀ −x", "+x ▶"),
                                                  ("setDeltaVelocity", "− delta", "+ delta"))):
            arg = COMMANDS_BY_NAME[name].args[0]
            inp = ArgInput(arg, DEFAULTS.get(arg.name))
            inp.set_hint(self.limit_hint(arg.name))
            assert isinstance(inp.widget, QDoubleSpinBox)
            inp.widget.setMinimum(0.0)  # a speed; the button gives the direction
            self.jog_speed[name] = inp
            label = QLabel(inp.label)
            label.setBuddy(inp.widget)
            b_minus, b_plus = HoldButton(minus), HoldButton(plus)
            for sign, b in ((-1.0, b_minus), (1.0, b_plus)):
                b.setObjectName(f"jog:{name}:{'+' if sign > 0 else '-'}")
                b.setToolTip(f"Hold to move (Space works too); {name} is sent with 0 on release")
                b.held.connect(lambda n=name, s=sign: self.send(n, s * self.jog_speed[n].value()))
                b.let_go.connect(lambda n=name: self.send(n, 0.0))
            g.addWidget(label, r, 0)
            g.addWidget(inp.widget, r, 1)
            g.addWidget(b_minus, r, 2)
            g.addWidget(b_plus, r, 3)
            self.jog_buttons[name] = (b_minus, b_plus)
        g.setColumnStretch(3, 1)
        v.addWidget(box)
        v.addStretch(1)

    def _build_interaction_page(self) -> None:
        v = self._page("&Interaction")
        box = QGroupBox("Admittance and assistance (modes Admittance / Assistance)")
        g = _grid()
        box.setLayout(g)
        r = self._form("setAdmittanceParameter", g, 0, "Set", read="getAdmittanceParameter")
        r = self._form("setAssistanceParameter", g, r, "Set", read="getAssistanceParameter")
        self._form("setAssistanceTargetPos", g, r, "Set", read="getAssistanceTargetPos")
        v.addWidget(box)
        note = QLabel("Admittance: v = Ka·F.  Assistance: v = Ka·(F + Kt·(target − handle)).")
        note.setWordWrap(True)
        note.setStyleSheet(f"color: {colours().idle};")
        v.addWidget(note)
        box = QGroupBox("Trigger (armed moves)")
        g = _grid()
        box.setLayout(g)
        r = self._form("setTriggerMode", g, 0, "Set")
        self._form("setTriggerParameter", g, r, "Set")
        v.addWidget(box)
        v.addStretch(1)

    def _build_limits_page(self) -> None:
        v = self._page("&Limits")
        box = QGroupBox("Controller limits (the safety supervisor checks them too)")
        g = _grid()
        box.setLayout(g)
        r = self._form("setPosLimit", g, 0, "Set")
        for name in ("setMaxVelocity", "setMaxAcceleration", "setMaxForce", "setMaxCurrent", "setMaxTrackingError"):
            r = self._form(name, g, r, "Set")
        v.addWidget(box)
        box = QGroupBox("Homing and motor loops")
        g = _grid()
        box.setLayout(g)
        r = self._form("setHomeParameter", g, 0, "Set")
        self._form("setPidTunings", g, r, "Set", read="getPidTunings")
        # Never send placeholder gains: Set stays disabled until this motor's tunings were read.
        pid = self.forms["setPidTunings"]
        pid.require_read()
        v.addWidget(box)
        box = QGroupBox("Endstrokes")
        g = _grid()
        box.setLayout(g)
        self.endstrokes_check = QCheckBox("Disable endstroke switches (normally not allowed)")
        self.endstrokes_check.setObjectName("endstrokesDisabled")
        self.endstrokes_check.clicked.connect(lambda on: self.send("disableEndstrokes", bool(on)))
        g.addWidget(self.endstrokes_check, 0, 0, 1, 4)
        v.addWidget(box)
        v.addStretch(1)

    def _build_log_page(self) -> None:
        self.log_list = QListWidget()
        self.log_list.setObjectName("commandLog")
        self.log_list.setAccessibleName("Command outcomes")
        self.tabs.addTab(self.log_list, "L&og")

    # ------------------------------------------------------------------ commands
    def driver(self) -> Any:
        return self.manager.driver(streams.LINARM)

    def set_control_state(self, state: int) -> CommandStatus | None:
        return self.send("setCtrlState", int(state))

    def go_home(self) -> CommandStatus | None:
        return self.send("goToHome")

    def send(self, name: str, *args: Any,
             on_ok: Callable[[dict[str, Any]], None] | None = None) -> CommandStatus | None:
        """Submit a command without waiting; its outcome is shown when its status completes."""
        title = command_title(name)
        driver = self.driver()
        if driver is None:
            self._show(Outcome(name, "link", f"{title}: not sent — the LINarm is switched off in the configuration"))
            return None
        try:
            future = driver.submit(name, *args, source=SOURCE)
        except (ValueError, TypeError) as exc:  # a value the wire cannot carry: refused before the queue
            self._show(Outcome(name, "error", f"{title}: not sent — {exc}"))
            return None
        self._pending.append((name, future, on_ok))
        self._show(Outcome(name, "sending", f"{title}: sending…"), log_it=False)
        if not self._poll.isActive():
            self._poll.start()
        return future

    def _collect(self) -> None:
        still: list[tuple[str, CommandStatus, Callable[[dict[str, Any]], None] | None]] = []
        for name, future, on_ok in self._pending:
            if not future.done():
                still.append((name, future, on_ok))
                continue
            outcome = self._outcome_of(name, future)
            if outcome.ok and on_ok is not None:
                try:
                    on_ok(future.result())
                except Exception:
                    log.exception("linarm panel: handling the reply of %s failed", name)
            self._show(outcome)
        self._pending = still
        if not still:
            self._poll.stop()
        self.refresh()

    @staticmethod
    def _outcome_of(name: str, future: CommandStatus) -> Outcome:
        title = command_title(name)
        if future.cancelled():
            return Outcome(name, "link", f"{title}: cancelled (the LINarm driver stopped)")
        exc = future.exception()
        if exc is None:
            values = future.result() or {}
            shown = ", ".join(f"{k} = {v:.6g}" if isinstance(v, float) else f"{k} = {v}" for k, v in values.items())
            return Outcome(name, "ok", f"{title}: accepted{' — ' + shown if shown else ''}")
        if isinstance(exc, SafetyError):
            return Outcome(name, "refused", f"Not sent — refused by the safety supervisor: {exc.reason}.")
        if isinstance(exc, LinarmCommandError):
            # The plain-words hint says what to do; the controller's own text is kept for the log.
            hint = CODE_HINTS.get(exc.code, "") or exc.message
            extra = f" [controller: {exc.message}]" if exc.message and hint != exc.message else ""
            return Outcome(name, "controller",
                           f"{title}: the LINarm refused it — {exc.code.name} (code {int(exc.code)})"
                           f"{': ' + hint if hint else ''}.{extra}", code=exc.code)
        if isinstance(exc, LinarmTimeout):
            return Outcome(name, "timeout", f"{title}: no answer from the LINarm — {exc}. Check the link.")
        if isinstance(exc, TransportError):
            return Outcome(name, "link", f"{title}: not sent — {exc}.")
        if isinstance(exc, CommandQueueClosed):
            return Outcome(name, "link", f"{title}: not sent — the LINarm link closed before it was sent.")
        return Outcome(name, "error", f"{title}: not sent — {exc}")

    def _show(self, outcome: Outcome, log_it: bool = True) -> None:
        outcome.t_wall = time.time()
        c = colours()
        colour = {"ok": c.ok, "sending": c.idle, "event": c.bad}.get(outcome.kind, c.bad)
        self.outcome.setText(outcome.text)
        self.outcome.setStyleSheet(f"color: {colour};" + ("font-weight: bold;" if outcome.kind != "sending" else ""))
        self.outcome.setAccessibleName(outcome.text)
        self.last_outcome = outcome
        if log_it:
            self.outcomes.append(outcome)
            stamp = time.strftime("%H:%M:%S", time.localtime(outcome.t_wall))
            item = QListWidgetItem(f"{stamp}  {outcome.text}")
            item.setForeground(QColor(colour))
            self.log_list.insertItem(0, item)
            while self.log_list.count() > 500:
                self.log_list.takeItem(self.log_list.count() - 1)
            del self.outcomes[:-500]
        self.outcome_shown.emit(outcome)

    def _on_device_event(self, device: str, kind: str, detail: str) -> None:
        if device == streams.LINARM and kind == journal.CONTROLLER_ERROR:
            self._on_controller_error(detail)

    def _on_controller_error(self, text: str) -> None:
        self._show(Outcome("", "event", f"{text} — the motors are off; press Reset error."))

    # ------------------------------------------------------------------ state

    def refresh(self) -> None:
        driver = self.driver()
        c = colours()
        connected = bool(driver is not None and driver.connected)
        for page in self.pages:
            page.setEnabled(connected)
        if driver is None:
            self.status.setText(f"<span style='color:{c.idle}'>●</span> LINarm is off in the configuration")
            return
        if not connected:
            self.status.setText(f"<span style='color:{c.bad}'>●</span> <b>LINarm disconnected</b> — "
                                "commands are disabled until it is connected")
            return
        state = driver.latest("linarm.state")
        if state is None:
            self.status.setText(f"<span style='color:{c.warn}'>●</span> LINarm connected, waiting for its state…")
            return
        cs, mode = ControlState(state.controlState), proto.ControlMode(state.controlMode)
        home, err = HomeState(state.homeState), ErrorState(state.errorState)
        cs_col = {ControlState.IDLE_CTRL_STATE: c.idle, ControlState.HOME_CTRL_STATE: c.warn}.get(cs, c.ok)
        home_col = c.ok if home is HomeState.HOME_DONE else (c.idle if home is HomeState.HOME_NOT_DONE else c.warn)
        err_col = c.ok if err is ErrorState.NO_ERROR else c.bad
        demo = " · <b>DEMO</b>" if state.demo else ""
        _set_text(
            self.status,
            f"<span style='color:{c.ok}'>●</span> State <b style='color:{cs_col}'>{pretty_enum(cs)}</b>"
            f" · Mode <b>{pretty_enum(mode)}</b> · <span style='color:{home_col}'>{HOME_TEXT[home]}</span>"
            f" · Error <b style='color:{err_col}'>{pretty_enum(err)}</b>{demo}")
        button = self.state_buttons.get(int(cs))
        if button is not None and not button.isChecked():
            button.setChecked(True)
        for value, b in self.state_buttons.items():
            _restyle(b, f"QPushButton {{ background: {cs_col}; color: white; font-weight: bold; }}"
                     if value == int(cs) else "")
        self.home_progress.setValue(int(home))
        failed = err is ErrorState.HOMING_FAILED
        _set_format(self.home_progress, "Homing failed — reset the error" if failed else HOME_TEXT[home])
        chunk = c.bad if failed else (c.ok if home is HomeState.HOME_DONE else c.warn)
        _restyle(
            self.home_progress,
            "QProgressBar { border: 1px solid #9e9e9e; border-radius: 3px; text-align: center; min-height: 20px; }"
            f" QProgressBar::chunk {{ background: {chunk}; }}")
        homing = cs is ControlState.HOME_CTRL_STATE and home not in (HomeState.HOME_DONE, HomeState.HOME_NOT_DONE)
        self.cancel_home.setVisible(homing)
        _set_text(self.error_label, f"Error: <b style='color:{err_col}'>{pretty_enum(err)}</b>")
        self.reset_button.setEnabled(err is not ErrorState.NO_ERROR)
        busy = {name for name, _f, _cb in self._pending}
        # The mode boxes follow the robot (a script or the controller may change the mode), unless the
        # operator is choosing in one right now or its command is on its way (issue #19: the box said
        # "Velocity (0)" while the robot was in "Target position (1)").
        for form_name, arg_name, attr in (("setCtrlMode", "controlMode", "controlMode"),
                                          ("setTrajectoryType", "type", "trajectoryType"),
                                          ("setTriggerMode", "mode", "triggerMode")):
            form = self.forms.get(form_name)
            value = getattr(state, attr, None)
            if form is None or value is None or form_name in busy:
                continue
            box = form.inputs[arg_name].widget
            if isinstance(box, QComboBox) and not box.hasFocus() and not box.view().isVisible() \
                    and box.currentData() != int(value):
                box.setCurrentIndex(max(0, box.findData(int(value))))
        for check, value, name in ((self.demo_check, state.demo, "setDemo"),
                                   (self.virtual_check, state.virtualVsa, "enableVirtualVsa"),
                                   (self.endstrokes_check, state.endstrokesDisabled, "disableEndstrokes")):
            if name not in busy and check.isChecked() != bool(value):
                check.setChecked(bool(value))

    def closeEvent(self, event: Any) -> None:
        for pair in getattr(self, "jog_buttons", {}).values():
            for b in pair:
                b._release()
        super().closeEvent(event)
