"""The physiological sensors viewer (seed D2.2 §3.2, Fig. 7): the four current values with their
units, a small live trace of each (last 10 s) plus the raw pulse waveform, the link's frame rate
and counters (decoded, lost, bad CRC, discarded bytes), the board's sensor-fault flags in words and
the calibration in use.

Labels and units come from the driver's stream spec (``PHYSIO_STREAM``); values are the bus's latest
sample (``QtBus.latest``), read on a timer, never per sample.  The four traces come from the shared signal
store (fed by the Qt bus adapter's ``samples`` batches); the pulse (PPG) is not a stream channel, so the viewer
has a bus subscription of its own to the physio stream, drained on its timer into the last seconds of the
pulse, timed on the board clock so the waveform is not distorted by the bursty USB arrival times.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QFont, QFontDatabase
from PySide6.QtWidgets import QFrame, QGridLayout, QGroupBox, QHBoxLayout, QLabel, QVBoxLayout, QWidget

from app.core import streams
from app.core.bus import SampleItem, StreamBus, Subscription
from app.devices.physio import PHYSIO_STREAM
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.signal_store import SignalStore, shared_store, signal_key
from app.ui.theme import colours, curve_colour
from app.ui.widgets import LabelBoard, on_screen
from app.wire.physio_codec import FAULT_FLAGS

DASH = "—"
STREAM = streams.PHYSIO_MAIN
PULSE_SUBSCRIBER = "physio-viewer-pulse"  # the viewer's own bus subscription (the PPG)
TRACE_S = 10.0  # seconds of history in each small trace
CHANNELS = {ch.name: ch for ch in PHYSIO_STREAM.channels}
# Tile order as the seed lists the sensors: grip force first (it drives the trigger exercises).
TILE_ORDER = ("force", "heartRate", "skinConductance", "temperature")
DECIMALS = {"N": 1, "bpm": 0, "µS": 2, "°C": 2}
# A trace's vertical range is never narrower than this, so sensor noise does not fill the tile.
MIN_SPAN = {"force": 5.0, "heartRate": 10.0, "skinConductance": 1.0, "temperature": 0.5, "ppg": 200.0}
CALIBRATED = ("force", "skinConductance", "temperature")  # fields of app.wire.physio_codec.Calibration

# (flag bit, words, tile it invalidates or None)
FAULT_WORDS = FAULT_FLAGS  # the codec's table: one place for the bits and their meaning
_KNOWN_FLAGS = sum(flag for flag, _w, _c in FAULT_WORDS)


def fault_words(flags: int) -> list[str]:
    """The board's fault bits in words; unknown (reserved) bits are named by their value."""
    words = [w for flag, w, _c in FAULT_WORDS if flags & flag]
    if flags & ~_KNOWN_FLAGS & 0xFF:
        words.append(f"reserved bits 0x{flags & ~_KNOWN_FLAGS & 0xFF:02X}")
    return words


def faulty_channels(flags: int) -> set[str]:
    return {c for flag, _w, c in FAULT_WORDS if c is not None and flags & flag}


def format_value(value: Any, decimals: int) -> str:
    """A number to ``decimals`` places; the dash for missing or NaN (heart rate before lock)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return DASH
    if not math.isfinite(v):
        return DASH
    text = f"{v:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text


class PulseTap:
    """The last seconds of the raw pulse as (board time s, counts), from the viewer's bus subscription to the
    physio stream: drained on the GUI thread (:meth:`take`), so a slow GUI loses only its own oldest beats."""

    def __init__(self, bus: StreamBus, maxlen: int) -> None:
        # The queue holds what arrives between two drains; the deques the last seconds.
        self.subscription: Subscription = bus.subscribe(PULSE_SUBSCRIBER, [STREAM], maxlen=maxlen)
        self._t: deque[float] = deque(maxlen=maxlen)
        self._v: deque[float] = deque(maxlen=maxlen)
        self.generation = 0

    def take(self) -> None:
        for item in self.subscription.drain():
            if isinstance(item, SampleItem):
                self.add(item.sample)

    def add(self, sample: Any) -> None:
        bt = float(sample.boardTime)
        if self._t and bt < self._t[-1]:  # a new connection restarts the board clock
            self._t.clear()
            self._v.clear()
        self._t.append(bt)
        self._v.append(float(sample.ppg))
        self.generation += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.fromiter(self._t, float, len(self._t)), np.fromiter(self._v, float, len(self._v))

    def close(self) -> None:
        self.subscription.close()


def _y_range(y: np.ndarray, min_span: float) -> tuple[float, float] | None:
    finite = y[np.isfinite(y)]
    if finite.size == 0:
        return None
    lo, hi = float(finite.min()), float(finite.max())
    if hi - lo < min_span:
        mid = (hi + lo) / 2
        lo, hi = mid - min_span / 2, mid + min_span / 2
    pad = 0.08 * (hi - lo)
    return lo - pad, hi + pad


def _trace(colour: str, height: int) -> tuple[pg.PlotWidget, pg.PlotDataItem]:
    c = colours()
    plot = pg.PlotWidget(background=c.plot_background)
    plot.setMinimumHeight(height)  # grows with the window; the values stay the same size
    plot.setMouseEnabled(x=False, y=False)
    plot.setMenuEnabled(False)
    plot.hideButtons()
    plot.hideAxis("bottom")
    plot.showGrid(x=True, y=True, alpha=c.grid_alpha)
    axis = plot.getAxis("left")
    small = QFont()
    small.setPointSizeF(7)
    axis.setStyle(tickFont=small, tickTextOffset=2)
    axis.setWidth(34)
    axis.setPen(c.plot_foreground)
    axis.setTextPen(c.plot_foreground)
    plot.setXRange(-TRACE_S, 0, padding=0)
    plot.getPlotItem().setContentsMargins(0, 2, 2, 2)
    curve = plot.plot([], [], pen=pg.mkPen(colour, width=1.5), connect="finite")
    return plot, curve


class PhysioViewer(LabelBoard, QWidget):
    def __init__(self, manager: LinarmppManager, *, qt_bus: QtBus | None = None) -> None:
        """The physiological board of ``manager``: samples, link state and traces through ``qt_bus`` (the
        window's; else the viewer's own), the link's counters from its driver."""
        super().__init__()
        self.manager = manager
        self.qt_bus = qt_bus_for(manager, qt_bus, self)
        self.values: dict[str, QLabel] = {}
        self.units: dict[str, QLabel] = {}
        self.plots: dict[str, pg.PlotWidget] = {}
        self.curves: dict[str, pg.PlotDataItem] = {}
        self._shown: dict[str, tuple[str, str]] = {}
        self._drawn: dict[str, float] = {}  # newest time drawn per trace: redraw only on new data
        self._driver: Any = None
        self._store: SignalStore | None = None
        self._nominal_hz = float(manager.config.devices.physio.rate_hz)
        self._tap_len = int(TRACE_S * max(self._nominal_hz, PHYSIO_STREAM.nominal_rate_hz) * 1.5)
        self._tap: PulseTap | None = None
        # Shared with the `destroyed` handler, which must not reference self.
        self._attachment: dict[str, Any] = {}
        self.destroyed.connect(lambda *_a, a=self._attachment: _detach(a))
        mono = QFontDatabase.systemFont(QFontDatabase.SystemFont.FixedFont)

        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        outer.setSpacing(3)
        self.header = QLabel()
        self.header.setObjectName("viewerHeader")
        self.header.setTextFormat(Qt.TextFormat.RichText)
        outer.addWidget(self.header)
        row = QHBoxLayout()
        row.setSpacing(6)
        outer.addLayout(row, 1)

        left = QVBoxLayout()
        left.setSpacing(4)
        tiles = QGridLayout()
        tiles.setSpacing(4)
        big = QFont(mono)
        big.setPointSizeF(max(16.0, mono.pointSizeF() * 1.8))
        big.setBold(True)
        for i, name in enumerate(TILE_ORDER):
            tiles.addWidget(self._tile(name, big, curve_colour(i)), i // 2, i % 2)
        left.addLayout(tiles, 2)
        pulse = QFrame()
        pulse.setFrameShape(QFrame.Shape.StyledPanel)
        pl = QVBoxLayout(pulse)
        pl.setContentsMargins(4, 2, 4, 2)
        pl.setSpacing(0)
        pl.addWidget(QLabel("Pulse waveform (PPG, raw counts, board clock)"))
        self.plots["ppg"], self.curves["ppg"] = _trace(curve_colour(4), 52)
        pl.addWidget(self.plots["ppg"])
        left.addWidget(pulse, 1)
        row.addLayout(left, 3)

        right = QVBoxLayout()
        right.setSpacing(4)
        box = QGroupBox("Link")
        g = self._grid(box)
        for r, (key, label) in enumerate((("rate", "Frame rate"), ("decoded", "Frames decoded"),
                                          ("lost", "Frames lost"), ("bad", "Bad CRC"),
                                          ("discarded", "Discarded bytes"),
                                          ("discontinuities", "Sequence restarts"))):
            g.addWidget(QLabel(label), r, 0)
            self._value(g, key, r, 1, mono)
        right.addWidget(box)

        box = QGroupBox("Sensor faults")
        g = self._grid(box)
        self._value(g, "faults", 0, 0, QFont(), align=Qt.AlignmentFlag.AlignLeft)
        self.values["faults"].setWordWrap(True)
        right.addWidget(box)

        box = QGroupBox("Calibration (gain · counts + offset)")
        g = self._grid(box)
        for r, name in enumerate(CALIBRATED):
            g.addWidget(QLabel(CHANNELS[name].label), r, 0)
            self._value(g, f"cal.{name}.gain", r, 1, mono)
            self._value(g, f"cal.{name}.offset", r, 2, mono)
        g.addWidget(QLabel(CHANNELS["heartRate"].label), len(CALIBRATED), 0)
        beats = QLabel("from pulse beats")
        beats.setAlignment(Qt.AlignmentFlag.AlignRight)
        g.addWidget(beats, len(CALIBRATED), 1, 1, 2)
        right.addWidget(box)
        right.addStretch(1)
        row.addLayout(right, 2)

        self.timer = QTimer(self)
        hz = min(20.0, max(1.0, float(manager.config.ui.refresh_hz)))
        self.timer.setInterval(int(1000 / hz))
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        self.refresh()

    # ------------------------------------------------------------------ building
    def _tile(self, name: str, font: QFont, colour: str) -> QFrame:
        ch = CHANNELS[name]
        tile = QFrame()
        tile.setFrameShape(QFrame.Shape.StyledPanel)
        g = QGridLayout(tile)
        g.setContentsMargins(4, 2, 4, 2)
        g.setHorizontalSpacing(4)
        g.setVerticalSpacing(0)
        g.addWidget(QLabel(ch.label), 0, 0, 1, 2)
        value = QLabel(DASH)
        value.setObjectName(f"value:{name}")
        value.setFont(font)
        value.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
        value.setMinimumWidth(value.fontMetrics().horizontalAdvance("100.00"))
        self.values[name] = value
        unit = QLabel(ch.unit)
        unit.setObjectName(f"unit:{name}")
        uf = QFont()
        uf.setPointSizeF(font.pointSizeF() * 0.6)
        unit.setFont(uf)
        unit.setAlignment(Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignBottom)
        self.units[name] = unit
        g.addWidget(value, 1, 0)
        g.addWidget(unit, 1, 1)
        g.setColumnStretch(0, 1)
        g.setColumnStretch(1, 1)
        self.plots[name], self.curves[name] = _trace(colour, 46)
        g.addWidget(self.plots[name], 2, 0, 1, 2)
        return tile

    @staticmethod
    def _grid(box: QGroupBox) -> QGridLayout:
        g = QGridLayout(box)
        g.setContentsMargins(6, 4, 6, 4)
        g.setHorizontalSpacing(10)
        g.setVerticalSpacing(2)
        return g

    def _value(self, grid: QGridLayout, key: str, row: int, col: int, font: QFont,
               align: Qt.AlignmentFlag = Qt.AlignmentFlag.AlignRight) -> None:
        label = QLabel(DASH)
        label.setObjectName(f"value:{key}")
        label.setFont(font)
        label.setAlignment(align | Qt.AlignmentFlag.AlignVCenter)
        grid.addWidget(label, row, col)
        self.values[key] = label

    # ------------------------------------------------------------------ reading

    def unit_of(self, channel: str) -> str:
        return self.units[channel].text()

    def colour_of(self, key: str) -> str:
        return self._shown.get(key, ("", ""))[1]

    def _attach(self, driver: Any) -> None:
        """Follow the manager's physio device: subscribe to its pulse, feed the store; let go when it goes."""
        _detach(self._attachment)
        self._driver = driver
        self._tap = None
        self._drawn.clear()
        if driver is None:
            return
        self._store = shared_store(self.manager, self.qt_bus)
        self._tap = PulseTap(self.qt_bus.bus, self._tap_len)
        self._attachment.update(tap=self._tap)

    def _tick(self) -> None:
        """The timer's slot: keep following the device (the pulse must not miss beats), but draw
        nothing while nobody can see the view (see ``on_screen``)."""
        driver = self.manager.driver(streams.PHYSIO)
        if driver is not self._driver:
            self._attach(driver)
        if self._tap is not None:
            self._tap.take()
        if on_screen(self):
            self.refresh()

    def showEvent(self, event: Any) -> None:
        super().showEvent(event)
        self.refresh()  # catch up at once on what was skipped while hidden

    def refresh(self) -> None:
        c = colours()
        driver = self.manager.driver(streams.PHYSIO)
        if driver is not self._driver:
            self._attach(driver)
        if self._tap is not None:
            self._tap.take()
        if driver is None:
            self.header.setText(f"<span style='color:{c.idle}'>●</span> Physiological sensors not connected"
                                " (off in the configuration)")
            fresh = False
        elif not self.qt_bus.connected(streams.PHYSIO):
            self.header.setText(f"<span style='color:{c.bad}'>●</span> <b>Physiological sensors not"
                                " connected</b> — last known values, greyed")
            fresh = False
        elif self.qt_bus.silent(streams.PHYSIO):
            self.header.setText(f"<span style='color:{c.warn}'>●</span> Physiological sensors connected"
                                " but silent — values are stale")
            fresh = False
        else:
            self.header.setText(f"<span style='color:{c.ok}'>●</span> Physiological sensors connected"
                                f" · traces: last {TRACE_S:.0f} s")
            fresh = True
        text = c.text if fresh else c.idle

        sample = self.qt_bus.latest(STREAM) if driver is not None else None
        flags = int(getattr(sample, "flags", 0) or 0)
        bad_channels = faulty_channels(flags)
        for name in TILE_ORDER:
            ch = CHANNELS[name]
            colour = (c.bad if name in bad_channels else c.text) if fresh else c.idle
            self._set(name, format_value(getattr(sample, name, None), DECIMALS.get(ch.unit, 2)), colour)

        decoder = getattr(driver, "decoder", None)
        rate = driver.rates().get(STREAM) if driver is not None else None
        slow = rate is not None and rate < 0.9 * self._nominal_hz  # frames missing or board misconfigured
        self._set("rate", DASH if rate is None else f"{rate:.1f} Hz", (c.warn if slow else c.text) if fresh else c.idle)
        for key, attr in (("decoded", "framesDecoded"), ("lost", "framesLost"), ("bad", "badFrames"),
                          ("discarded", "discardedBytes"), ("discontinuities", "seqDiscontinuities")):
            count = getattr(decoder, attr, None)
            warn = key != "decoded" and bool(count)
            self._set(key, DASH if count is None else str(count), (c.warn if warn else c.text) if fresh else c.idle)

        if sample is None:
            self._set("faults", DASH, c.idle)
        else:
            words = fault_words(flags)
            self._set("faults", ", ".join(words) if words else "none",
                      (c.bad if words else c.ok) if fresh else c.idle)

        calibration = getattr(driver, "calibration", None)
        for name in CALIBRATED:
            unit = CHANNELS[name].unit
            cal = getattr(calibration, name, None)
            self._set(f"cal.{name}.gain", DASH if cal is None else f"{cal.gain:g} {unit}/count", text)
            self._set(f"cal.{name}.offset", DASH if cal is None else f"{cal.offset:+g} {unit}", text)

        if self.isVisible():
            self._draw_traces()

    def _draw_traces(self) -> None:
        store = self._store
        if store is not None and self._driver is not None:
            for name in TILE_ORDER:
                key = signal_key(STREAM, name)
                span = store.time_span([key]) if key in store else None
                if span is None:
                    continue
                t, y = store.snapshot(key, span[1] - TRACE_S, None)
                if t.size == 0 or self._drawn.get(name) == float(t[-1]):
                    continue
                self._drawn[name] = float(t[-1])
                self._draw(name, t - t[-1], y)
        if self._tap is not None:
            gen = float(self._tap.generation)
            if gen and self._drawn.get("ppg") != gen:
                self._drawn["ppg"] = gen
                t, y = self._tap.arrays()
                keep = t >= t[-1] - TRACE_S
                self._draw("ppg", t[keep] - t[-1], y[keep])

    def _draw(self, name: str, t: np.ndarray, y: np.ndarray) -> None:
        self.curves[name].setData(t, y)
        span = _y_range(y, MIN_SPAN[name])
        if span is not None:
            self.plots[name].setYRange(*span, padding=0)


def _detach(attachment: dict[str, Any]) -> None:
    tap = attachment.pop("tap", None)
    if tap is not None:
        tap.close()
