"""The LINarm viewer (seed D2.2 §3.1, Fig. 4): every state quantity of the robot at a glance --
control state, mode, homing, error (colour-coded names), trigger and trajectory settings, the
flags, the VSA (centre, delta, stiffness, handle, force) and both motors.

Labels and units come from the driver's stream specs (``LinarmDriver.streams``), enum names from
the protocol table; values are the bus's latest samples (``QtBus.latest``), read on a timer, never per sample.
"""

from __future__ import annotations

import math
from typing import Any

from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QFont, QFontDatabase
from PySide6.QtWidgets import QFrame, QGridLayout, QGroupBox, QHBoxLayout, QLabel, QScrollArea, QVBoxLayout, QWidget

from app.core import streams
from app.devices.linarm import STATE_STREAM, VSA_STREAM, LinarmDriver
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.theme import colours
from app.ui.widgets import LabelBoard, RefreshWhenVisible
from app.wire import linarm_protocol as proto
from app.wire.linarm_protocol import ControlState, ErrorState, HomeState

DASH = "—"

# (sample field, label, enum in linarm_protocol.ENUMS or None for a flag)
STATE_ROWS: list[tuple[str, str, str | None]] = [
    ("controlState", "Control state", "CONTROL_STATES"),
    ("controlMode", "Control mode", "CONTROL_MODES"),
    ("homeState", "Home state", "HOME_STATES"),
    ("errorState", "Error state", "ERROR_STATES"),
    ("triggerMode", "Trigger mode", "TRIGGER_MODES"),
    ("trajectoryType", "Trajectory", "TRAJECTORY_TYPES"),
    ("initialized", "Initialised", None),
    ("demo", "Demo", None),
    ("virtualVsa", "Virtual VSA", None),
    ("endstrokesDisabled", "Endstrokes disabled", None),
]
# decimals per unit (positions to 0.1 mm)
DECIMALS = {"m": 4, "m/s": 3, "N/m": 0, "N": 2, "A": 2}
MOTOR_STREAMS = tuple(s for s in LinarmDriver.streams if s.name in streams.LINARM_MOTORS)
# Labels shown once per stream (the stream specs' own labels for the state; see STATE_STREAM).
_STATE_LABELS = {ch.name: ch.label for ch in STATE_STREAM.channels}


def _unit(unit: str) -> str:
    return {"m/s^2": "m/s²"}.get(unit, unit)


def format_number(value: Any, decimals: int) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return DASH
    if not math.isfinite(v):
        return DASH
    text = f"{v:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text


def enum_text(enum_attr: str, value: Any) -> str:
    try:
        member = proto.ENUMS[enum_attr](int(value))
    except (TypeError, ValueError, KeyError):
        return DASH if value is None else str(value)
    return f"{member.name} ({int(member)})"


def state_colour(field: str, value: Any) -> str:
    """Green = fine / active, amber = in progress, red = error, grey = idle or unknown."""
    c = colours()
    if value is None:
        return c.idle
    v = int(value)
    if field == "errorState":
        return c.ok if v == ErrorState.NO_ERROR else c.bad
    if field == "controlState":
        return {ControlState.IDLE_CTRL_STATE: c.idle, ControlState.HOME_CTRL_STATE: c.warn}.get(v, c.ok)
    if field == "homeState":
        if v == HomeState.HOME_DONE:
            return c.ok
        return c.idle if v == HomeState.HOME_NOT_DONE else c.warn
    if field == "endstrokesDisabled":
        return c.bad if v else c.text
    if field == "demo":
        return c.warn if v else c.text
    return c.text


class LinarmViewer(RefreshWhenVisible, LabelBoard, QWidget):
    def __init__(self, manager: LinarmppManager, *, qt_bus: QtBus | None = None) -> None:
        """The robot of ``manager``; its samples and link state through ``qt_bus`` (the window's; else its own)."""
        super().__init__()
        self.manager = manager
        self.qt_bus = qt_bus_for(manager, qt_bus, self)
        self.values: dict[str, QLabel] = {}
        self._shown: dict[str, tuple[str, str]] = {}
        mono = QFontDatabase.systemFont(QFontDatabase.SystemFont.FixedFont)

        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        outer.setSpacing(3)
        self.header = QLabel()
        self.header.setObjectName("viewerHeader")
        self.header.setTextFormat(Qt.TextFormat.RichText)
        outer.addWidget(self.header)
        content = QWidget()
        row = QHBoxLayout(content)
        row.setContentsMargins(2, 2, 2, 2)
        row.setSpacing(6)
        area = QScrollArea()
        area.setWidgetResizable(True)
        area.setFrameShape(QFrame.Shape.NoFrame)
        area.setWidget(content)
        outer.addWidget(area, 1)

        box = QGroupBox("State")
        g = self._grid(box)
        for r, (key, label, _enum) in enumerate(STATE_ROWS):
            g.addWidget(QLabel(_STATE_LABELS.get(key, label)), r, 0)
            self._value(g, f"state.{key}", r, 1, mono, bold=True)
        g.addWidget(QLabel("Controller time"), len(STATE_ROWS), 0)
        self._value(g, "state.controllerTime", len(STATE_ROWS), 1, mono)
        g.setRowStretch(len(STATE_ROWS) + 1, 1)
        row.addWidget(box)

        right = QVBoxLayout()
        box = QGroupBox("VSA")
        g = self._grid(box)
        for r, ch in enumerate(VSA_STREAM.channels):
            g.addWidget(QLabel(ch.label), r, 0)
            self._value(g, f"vsa.{ch.name}", r, 1, mono)
            g.addWidget(QLabel(_unit(ch.unit)), r, 2)
        right.addWidget(box)

        box = QGroupBox("Motors")
        g = self._grid(box)
        for col, spec in enumerate(MOTOR_STREAMS, start=1):
            head = QLabel(f"<b>Motor {spec.name[-1]}</b>")
            head.setAlignment(Qt.AlignmentFlag.AlignRight)
            g.addWidget(head, 0, col)
        for r, ch in enumerate(MOTOR_STREAMS[0].channels, start=1):
            g.addWidget(QLabel(ch.name.capitalize()), r, 0)
            for col, spec in enumerate(MOTOR_STREAMS, start=1):
                self._value(g, f"{spec.name.split('.')[1]}.{ch.name}", r, col, mono)
            g.addWidget(QLabel(_unit(ch.unit)), r, len(MOTOR_STREAMS) + 1)
        right.addWidget(box)
        right.addStretch(1)
        row.addLayout(right, 1)

        self.timer = QTimer(self)
        hz = min(20.0, max(1.0, float(manager.config.ui.refresh_hz)))
        self.timer.setInterval(int(1000 / hz))
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        self.refresh()

    @staticmethod
    def _grid(box: QGroupBox) -> QGridLayout:
        g = QGridLayout(box)
        g.setContentsMargins(6, 4, 6, 4)
        g.setHorizontalSpacing(10)
        g.setVerticalSpacing(2)
        return g

    def _value(self, grid: QGridLayout, key: str, row: int, col: int, font: QFont, bold: bool = False) -> None:
        label = QLabel(DASH)
        label.setObjectName(f"value:{key}")
        f = QFont(font)
        f.setBold(bold)
        label.setFont(f)
        label.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
        label.setMinimumWidth(label.fontMetrics().horizontalAdvance("POS_REF_BY_ADMITTANCE (3)" if bold else
                                                                    "-0.00000"))
        grid.addWidget(label, row, col)
        self.values[key] = label



    def refresh(self) -> None:
        c = colours()
        driver = self.manager.driver(streams.LINARM)
        if driver is None:
            self.header.setText(f"<span style='color:{c.idle}'>●</span> LINarm is off in the configuration")
            fresh = False
        elif not self.qt_bus.connected(streams.LINARM):
            self.header.setText(f"<span style='color:{c.bad}'>●</span> <b>LINarm disconnected</b>"
                                " — last known values, greyed")
            fresh = False
        elif self.qt_bus.silent(streams.LINARM):
            self.header.setText(f"<span style='color:{c.warn}'>●</span> LINarm connected but silent"
                                " — values are stale")
            fresh = False
        else:
            rate = max(driver.rates().values(), default=0.0)
            fw = getattr(driver, "firmware_version", "")
            self.header.setText(f"<span style='color:{c.ok}'>●</span> LINarm connected · {rate:.0f} Hz"
                                + (f" · firmware {fw}" if fw else ""))
            fresh = True
        latest = (lambda _s: None) if driver is None else self.qt_bus.latest
        state = latest(streams.LINARM_STATE)
        for key, _label, enum_attr in STATE_ROWS:
            value = getattr(state, key, None)
            if enum_attr is not None:
                text = enum_text(enum_attr, value)
            else:
                text = DASH if value is None else ("yes" if value else "no")
            self._set(f"state.{key}", text, state_colour(key, value) if fresh else c.idle)
        self._set("state.controllerTime", format_number(getattr(state, "controllerTime", None), 3) + " s"
                  if state is not None else DASH, c.text if fresh else c.idle)
        vsa = latest(streams.LINARM_VSA)
        for ch in VSA_STREAM.channels:
            self._set(f"vsa.{ch.name}", format_number(getattr(vsa, ch.name, None), DECIMALS.get(ch.unit, 3)),
                      c.text if fresh else c.idle)
        for spec in MOTOR_STREAMS:
            sample = latest(spec.name)
            short = spec.name.split(".")[1]
            for ch in spec.channels:
                self._set(f"{short}.{ch.name}", format_number(getattr(sample, ch.name, None),
                                                              DECIMALS.get(ch.unit, 3)),
                          c.text if fresh else c.idle)
