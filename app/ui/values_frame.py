"""Frame 1 — every live quantity as a large number with its unit, readable from 2 m; in the lower
part the robot's control state, mode and error state (colour-coded) and each device's connection
and sample rate.

The frame polls each stream's latest sample on the bus (``QtBus.latest``) on a 5 Hz timer: a number changing
faster cannot be read (a meter's display updates 2-5 times a second; the motion itself is in the graphs and
the device view), and polling costs nothing when devices are absent. A value's text is set only when the shown
(rounded) text changes, and its label paints its own background, so a new digit repaints that label alone.
Absent devices or values show "—".
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from typing import Any

from PySide6.QtCore import QEvent, QObject, Qt, QTimer
from PySide6.QtGui import QFont, QFontMetrics
from PySide6.QtWidgets import (
    QFrame,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QLayout,
    QScrollArea,
    QSizePolicy,
    QVBoxLayout,
    QWidget,
)

from app.core import streams
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.theme import colours
from app.ui.widgets import RefreshWhenVisible
from app.wire.sciencemode import CHANNELS

DASH = "—"
REFRESH_HZ = 5.0  # see the module's docstring
VALUE_PT_STEPS = (22, 20, 18, 16, 14, 13)  # 13 pt bold still reads from 2 m


@dataclass(frozen=True)
class Quantity:
    """One tile: where the value comes from and how it is printed (unit from the StreamSpec)."""

    title: str
    stream: str
    channel: str
    decimals: int
    unit: str  # shown before the device has published its StreamSpec


# The display order of the seed's quantities; units are the streams' own (SI except FES).
GROUPS: list[tuple[str, list[Quantity]]] = [
    ("Robot", [
        Quantity("Handle position", streams.LINARM_VSA, "handlePos", 3, "m"),
        Quantity("Handle velocity", streams.LINARM_VSA, "handleVel", 3, "m/s"),
        Quantity("Interaction force", streams.LINARM_VSA, "interactionForce", 1, "N"),
        Quantity("Stiffness", streams.LINARM_VSA, "stiffness", 0, "N/m"),
        Quantity("Centre", streams.LINARM_VSA, "equilibriumPos", 3, "m"),
        Quantity("Delta", streams.LINARM_VSA, "delta", 4, "m"),
    ]),
    ("Physiology", [
        Quantity("Grip force", streams.PHYSIO_MAIN, "force", 1, "N"),
        Quantity("Heart rate", streams.PHYSIO_MAIN, "heartRate", 0, "bpm"),
        Quantity("Skin conductance", streams.PHYSIO_MAIN, "skinConductance", 2, "µS"),
        Quantity("Temperature", streams.PHYSIO_MAIN, "temperature", 1, "°C"),
    ]),
    ("Patient model", [
        Quantity("α", streams.PATIENT_MODEL_MAIN, "alpha", 2, ""),
        Quantity("a_r", streams.PATIENT_MODEL_MAIN, "a_r", 2, ""),
        Quantity("a_f", streams.PATIENT_MODEL_MAIN, "a_f", 2, ""),
    ]),
]

STATE_STREAM = streams.LINARM_STATE
FES_STREAM = streams.FES_CHANNELS
# (title, channel, enum name in app.wire.linarm_protocol)
STATE_FIELDS: list[tuple[str, str, str]] = [
    ("Control state", "controlState", "CONTROL_STATES"),
    ("Control mode", "controlMode", "CONTROL_MODES"),
    ("Error", "errorState", "ERROR_STATES"),
]


def format_value(value: Any, decimals: int) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return DASH
    if not math.isfinite(v):
        return DASH
    text = f"{v:.{decimals}f}"
    return "0" + text[2:] if text.startswith("-0") and float(text) == 0 else text


def enum_name(enum_attr: str, value: Any) -> str:
    """The name of ``value`` in linarm_protocol's enum, or the number when it is unknown."""
    try:
        number = int(value)
    except (TypeError, ValueError):
        return DASH
    try:
        protocol = importlib.import_module("app.wire.linarm_protocol")
        enum_cls = getattr(protocol, enum_attr)
        name = enum_cls(number).name
    except (ImportError, AttributeError, ValueError, TypeError):
        return str(number)
    for suffix in ("_CTRL_STATE", "_STATE", "_MODE"):
        if name.endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
    return name.replace("POS_REF_BY_", "").replace("_", " ").lower().capitalize() + f" ({number})"


def state_colour(channel: str, value: Any) -> str:
    c = colours()
    try:
        number = int(value)
    except (TypeError, ValueError):
        return c.idle
    if channel == "errorState":
        return c.ok if number == 0 else c.bad
    if channel == "controlState":
        return {0: c.idle, 1: c.warn}.get(number, c.ok)  # idle, homing, on
    return c.ok


class ValueTile(QFrame):
    """A small title over a large value and its unit."""

    def __init__(self, title: str, unit: str, value_pt: int = 22) -> None:
        super().__init__()
        self.setFrameShape(QFrame.Shape.StyledPanel)
        self.unit = unit
        lay = QVBoxLayout(self)
        lay.setContentsMargins(6, 3, 6, 3)
        lay.setSpacing(0)
        self.title = QLabel(title)
        self.value = QLabel(DASH)
        self.value_pt = 0
        self.set_value_pt(value_pt)
        self.value.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
        # Opaque: a new value repaints the label only, not the tile, group and frame beneath it.
        self.value.setAutoFillBackground(True)
        self.value.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        lay.addWidget(self.title)
        lay.addWidget(self.value)
        self.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Fixed)
        self.set_text(DASH)

    def set_value_pt(self, value_pt: int) -> None:
        if value_pt == self.value_pt:
            return
        self.value_pt = value_pt
        small = QFont(self.title.font())
        small.setPointSize(max(8, value_pt // 2 - 1))
        self.title.setFont(small)
        big = QFont(self.value.font())
        big.setPointSize(value_pt)
        big.setBold(True)
        self.value.setFont(big)
        # Pin the heights to the fonts: the tile's row must grow with its font, never clip the digits.
        self.title.setMinimumHeight(QFontMetrics(small).height())
        self.value.setMinimumHeight(QFontMetrics(big).height() + 6)
        self.updateGeometry()

    def set_text(self, text: str, colour: str | None = None) -> None:
        shown = text if text == DASH or not self.unit else f"{text} {self.unit}"
        if shown != self.value.text():
            self.value.setText(shown)
        style = f"color: {colour};" if colour else ""
        if style != self.value.styleSheet():
            self.value.setStyleSheet(style)
        name = f"{self.title.text()}: {shown}"
        if name != self.accessibleName():
            self.setAccessibleName(name)


class ValuesFrame(RefreshWhenVisible, QWidget):
    def __init__(self, manager: LinarmppManager, *, qt_bus: QtBus | None = None) -> None:
        """``manager``'s devices and streams, read through ``qt_bus`` (the window's; else the frame's own)."""
        super().__init__()
        self.manager = manager
        self.qt_bus = qt_bus_for(manager, qt_bus, self)
        self.tiles: dict[tuple[str, str], ValueTile] = {}
        self.state_tiles: dict[str, ValueTile] = {}
        self.fes_labels: list[QLabel] = []
        self.device_labels: dict[str, QLabel] = {}
        self._grids: list[tuple[QGridLayout, list[ValueTile]]] = []

        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        scroll = QScrollArea()  # never clip: on a small screen the tiles scroll instead
        scroll.setProperty("scrolls", True)  # a list meant to scroll (the clipping test knows)
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QFrame.Shape.NoFrame)
        outer.addWidget(scroll)
        body = QWidget()
        scroll.setWidget(body)
        lay = QVBoxLayout(body)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.setSpacing(4)

        for title, quantities in GROUPS:
            box = QGroupBox(title)
            grid = QGridLayout(box)
            grid.setContentsMargins(4, 4, 4, 4)
            grid.setSpacing(4)
            group_tiles = []
            for q in quantities:
                tile = ValueTile(q.title, q.unit)
                self.tiles[(q.stream, q.channel)] = tile
                group_tiles.append(tile)
            self._grids.append((grid, group_tiles))
            lay.addWidget(box)
        self._columns = 0
        self._set_columns(3)

        fes_box = QGroupBox("FES (active channels)")
        self.fes_grid = QGridLayout(fes_box)
        self.fes_grid.setContentsMargins(4, 4, 4, 4)
        self.fes_none = QLabel("no channel active")
        self.fes_grid.addWidget(self.fes_none, 0, 0, 1, 2)
        for ch in CHANNELS:
            label = QLabel("")
            f = QFont(label.font())
            f.setPointSize(16)
            f.setBold(True)
            label.setFont(f)
            label.hide()
            self.fes_grid.addWidget(label, 1 + (ch - 1) // 2, (ch - 1) % 2)
            self.fes_labels.append(label)
        lay.addWidget(fes_box)
        lay.addStretch(1)
        self.scroll = scroll
        self.body = body
        self._fitting = False
        scroll.viewport().installEventFilter(self)

        # Lower part (seed): states and errors, then devices.
        state_box = QGroupBox("Robot state")
        srow = QHBoxLayout(state_box)
        srow.setContentsMargins(4, 4, 4, 4)
        for title, channel, _enum in STATE_FIELDS:
            tile = ValueTile(title, "", value_pt=16)
            self.state_tiles[channel] = tile
            srow.addWidget(tile)
        outer.addWidget(state_box)  # pinned below the values: always visible, never scrolled away

        dev_box = QGroupBox("Devices")
        self.dev_row = QGridLayout(dev_box)
        self.dev_row.setContentsMargins(4, 4, 4, 4)
        outer.addWidget(dev_box)
        # The status bar is the one place for device status (issue #19: it was shown three times);
        # the labels stay for the frame's tests and a Values frame undocked on its own screen.
        dev_box.setVisible(False)
        self.dev_box = dev_box
        self._sync_devices()

        self.timer = QTimer(self)
        self.timer.setInterval(int(1000 / REFRESH_HZ))
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        self.refresh()

    # ------------------------------------------------------------------ sizing
    def eventFilter(self, obj: QObject, event: QEvent) -> bool:
        # The viewport's own resize: the frame's resizeEvent comes before its layout has moved it.
        if obj is self.scroll.viewport() and event.type() == QEvent.Type.Resize and not self._fitting:
            self._fitting = True
            try:
                self.fit_fonts()
            finally:
                self._fitting = False
        return super().eventFilter(obj, event)

    def _set_columns(self, columns: int) -> None:
        if columns == self._columns:
            return
        self._columns = columns
        for grid, tiles in self._grids:
            for tile in tiles:
                grid.removeWidget(tile)
            for i, tile in enumerate(tiles):
                grid.addWidget(tile, i // columns, i % columns)
            for col in range(6):
                grid.setColumnStretch(col, 1 if col < columns else 0)

    def _relayout(self) -> None:
        """Recompute the size hints now: new fonts and columns only post a layout request, and a hint
        read before it is handled is the old one (the fit then never changed anything)."""
        for layout in self.body.findChildren(QLayout):
            layout.invalidate()
        for widget in (*self.body.findChildren(QWidget), self.body):
            layout = widget.layout()
            if layout is not None:
                layout.invalidate()
                layout.activate()

    def fit_fonts(self) -> None:
        """The largest value font (22 pt down to 14 pt), with 2, 3, 4 or 6 tiles a row, at which every
        tile fits without scrolling; wide frames use more columns so the numbers can stay large."""
        available = self.scroll.viewport().height()
        width = self.scroll.viewport().width()
        tiles = list(self.tiles.values())
        best: tuple[int, int, int] | None = None  # (height, pt, columns) of the shortest arrangement
        for pt in VALUE_PT_STEPS:
            for tile in tiles:
                tile.set_value_pt(pt)
            fes_font = QFont(self.fes_none.font())
            fes_font.setPointSize(max(11, pt - 6))
            fes_font.setBold(True)
            for label in self.fes_labels:
                label.setFont(fes_font)
            for columns in (2, 3, 4, 6):
                self._set_columns(columns)
                self._relayout()
                if self.body.minimumSizeHint().width() > width:
                    break
                height = self.body.sizeHint().height()
                if height <= available:
                    return
                if best is None or height < best[0]:
                    best = (height, pt, columns)
        # Nothing fits: the arrangement that scrolls least (issue #19: at 1366×768 the patient model's
        # α/a_r/a_f and the active FES channels were below the fold); never clip a number sideways.
        pt, columns = (best[1], best[2]) if best is not None else (VALUE_PT_STEPS[-1], 2)
        for tile in tiles:
            tile.set_value_pt(pt)
        self._set_columns(columns)

    # ------------------------------------------------------------------ reading
    def _latest(self, stream: str) -> Any:
        """The stream's newest sample while its device is connected (a stale value is never shown)."""
        if not self.qt_bus.connected(streams.device_of(stream)):
            return None
        return self.qt_bus.latest(stream)

    def _unit(self, stream: str, channel: str) -> str | None:
        spec = self.qt_bus.specs().get(stream)
        if spec is None:
            return None
        for ch in spec.channels:
            if ch.name == channel:
                return ch.unit
        return None

    def _sync_devices(self) -> None:
        for name in self.manager.devices:
            if name in self.device_labels:
                continue
            label = QLabel()
            label.setTextFormat(Qt.TextFormat.RichText)
            n = len(self.device_labels)
            self.dev_row.addWidget(label, n // 2, n % 2)
            self.device_labels[name] = label


    def refresh(self) -> None:
        self._sync_devices()
        groups = [q for _t, qs in GROUPS for q in qs]
        samples: dict[str, Any] = {}
        for q in groups:
            if q.stream not in samples:
                samples[q.stream] = self._latest(q.stream)
            tile = self.tiles[(q.stream, q.channel)]
            unit = self._unit(q.stream, q.channel)
            if unit is not None:
                tile.unit = unit
            sample = samples[q.stream]
            tile.set_text(format_value(getattr(sample, q.channel, None), q.decimals))

        state = self._latest(STATE_STREAM)
        for _title, channel, enum_attr in STATE_FIELDS:
            value = getattr(state, channel, None)
            self.state_tiles[channel].set_text(enum_name(enum_attr, value) if value is not None else DASH,
                                               state_colour(channel, value) if value is not None else None)

        fes = self._latest(FES_STREAM)
        fes_driver = self.manager.driver(streams.FES) if hasattr(self.manager, "driver") else None
        profile = getattr(fes_driver, "profile", None)
        muscles = getattr(profile, "channels", None) or {}
        active = 0
        for ch, label in enumerate(self.fes_labels, start=1):
            current = getattr(fes, f"current{ch}", None)
            width = getattr(fes, f"pulseWidth{ch}", None)
            on = current is not None and width is not None and float(current) > 0 and float(width) > 0
            if on:
                active += 1
                label.setText(f"Ch {ch}:  {float(current):.1f} mA · {float(width):.0f} µs")
                muscle = getattr(muscles.get(ch), "muscle", "")
                tip = f"Channel {ch}" + (f" — {muscle}" if muscle else "")
                if label.toolTip() != tip:
                    label.setToolTip(tip)
            label.setVisible(on)
        self.fes_none.setText(DASH if fes is None else "no channel active")
        self.fes_none.setVisible(active == 0)

        c = colours()
        for name, label in self.device_labels.items():
            handle = self.manager.devices.get(name)
            if handle is None:
                label.setText(f"<span style='color:{c.idle}'>●</span> {name} {DASH}")
                continue
            rate = max(handle.driver.rates().values(), default=0.0)  # the link's own diagnostic
            connected = self.qt_bus.connected(name)
            if connected and not self.qt_bus.silent(name):
                colour, state = c.ok, f"{rate:.0f} Hz"
            elif connected:
                colour, state = c.warn, "silent"
            else:
                colour, state = c.bad, "disconnected"
            sim = " (sim)" if handle.simulated else ""
            text = f"<span style='color:{colour}'>●</span> <b>{name}</b>{sim} {state}"
            if text != label.text():  # a rich-text label parses its text again on every setText
                label.setText(text)
                label.setAccessibleName(f"{name} {state}")

    # ------------------------------------------------------------------ test/inspection helpers
    def text_of(self, stream: str, channel: str) -> str:
        return self.tiles[(stream, channel)].value.text()

    def state_text(self, channel: str) -> str:
        return self.state_tiles[channel].value.text()

    def active_fes_texts(self) -> list[str]:
        return [lb.text() for lb in self.fes_labels if not lb.isHidden()]
