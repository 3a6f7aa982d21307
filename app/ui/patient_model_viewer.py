"""The patient-model viewer: α, a_r, a_f and TPI, MPI, PTI over time, and the decision tree with the
path the model took (D2.2 §3.3).

``PatientModelViewer(manager)`` follows the patient model's stream on the bus: column batches from the Qt bus
adapter's ``samples`` signal fill the plots' history; the latest sample (path, range, level) redraws the tree
on a timer; the link's counters come from ``manager.driver("patient_model")``.  ``feed(t, sample)`` adds one
sample directly (replay, tests).

``DecisionTreeView`` draws every node of layers 1-4 (1 root, 3 groups, 6 TPI, 12 MPI nodes and the
24 PTI leaves, each leaf coloured by the middle of its α range), the taken path highlighted, and
layer 5 as an α axis from −1 to +1 with the final range and the chosen α.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QPointF, QRectF, Qt, QTimer
from PySide6.QtGui import QColor, QFont, QPainter, QPaintEvent, QPen
from PySide6.QtWidgets import QGridLayout, QHBoxLayout, QLabel, QSplitter, QVBoxLayout, QWidget

from app.core import streams
from app.devices.sim.patient_model.decision_tree import (
    GROUPS,
    INDEX_LAYERS,
    DecisionTree,
    TreeConfig,
    load_tree_config,
)
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.theme import colours, curve_colour
from app.ui.widgets import RefreshWhenVisible

ALPHA_CHANNELS = ("alpha", "a_r", "a_f")
INDEX_CHANNELS = ("tpi", "mpi", "pti")
LABELS = {"alpha": "α", "a_r": "a_r", "a_f": "a_f", "tpi": "TPI", "mpi": "MPI", "pti": "PTI"}
GROUP_LABELS = {"assist": "assist", "in_between": "in-between", "resist": "resist"}


def alpha_colour(alpha: float) -> QColor:
    """Diverging: resistance blue, neutral grey, assistance orange."""
    a = min(1.0, max(-1.0, alpha))
    neutral = np.array([0xBD, 0xBD, 0xBD], dtype=float)
    end = np.array([0xE6, 0x6C, 0x00] if a >= 0 else [0x15, 0x65, 0xC0], dtype=float)
    rgb = neutral + abs(a) * (end - neutral)
    return QColor(int(rgb[0]), int(rgb[1]), int(rgb[2]))


class DecisionTreeView(QWidget):
    """The five layers as a tree; the taken path in bold."""

    def __init__(self, config: TreeConfig | None = None, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setMinimumSize(760, 380)
        self.path = ""
        self.alpha = math.nan
        self.alpha_range = (math.nan, math.nan)
        self.level = math.nan
        self.values: dict[str, float] = {}
        self.set_config(config or load_tree_config())

    def set_config(self, config: TreeConfig) -> None:
        self.config = config
        self.ranges = DecisionTree(config).branch_ranges()
        self.update()

    def set_decision(self, path: str, alpha: float, alpha_range: tuple[float, float], level: float,
                     values: dict[str, float]) -> None:
        """``path`` like 'assist/tpi_low/mpi_high/pti_low'; ``values``: clinical_score, tpi, mpi, pti."""
        self.path, self.alpha, self.alpha_range, self.level = path, alpha, alpha_range, level
        self.values = dict(values)
        self.update()

    # ------------------------------------------------------------------ geometry
    def _layout(self) -> tuple[dict[str, QPointF], list[float], float, float]:
        """Node centres by path ('' = root), row y's, leaf spacing, left margin."""
        left, right, top = 150.0, 16.0, 34.0
        bottom_band = 96.0
        rows = [top + i * (self.height() - top - bottom_band) / 4.0 for i in range(5)]
        leaves = [p for p in self.ranges if p.count("/") == 3]
        n = len(leaves)
        step = (self.width() - left - right) / n
        pos: dict[str, QPointF] = {}
        for i, leaf in enumerate(leaves):
            pos[leaf] = QPointF(left + step * (i + 0.5), rows[4])
        for depth in (2, 1, 0):
            for p in [q for q in self.ranges if q.count("/") == depth]:
                kids = [pos[c] for c in pos if c.startswith(p + "/") and c.count("/") == depth + 1]
                pos[p] = QPointF(sum(k.x() for k in kids) / len(kids), rows[depth + 1])
        pos[""] = QPointF(sum(pos[g].x() for g in GROUPS) / 3.0, rows[0])
        return pos, rows, step, left

    def _on_path(self, node: str) -> bool:
        return node == "" or (bool(self.path) and (self.path == node or self.path.startswith(node + "/")))

    # ------------------------------------------------------------------ drawing
    def paintEvent(self, event: QPaintEvent) -> None:
        c = colours()
        p = QPainter(self)
        p.setRenderHint(QPainter.RenderHint.Antialiasing)
        p.fillRect(self.rect(), QColor(c.base))
        pos, rows, step, left = self._layout()
        fg, muted, accent = QColor(c.text), QColor(c.idle), QColor("#C62828")
        small = QFont(self.font())
        small.setPointSizeF(max(6.5, self.font().pointSizeF() * 0.8))

        # edges first, path edges last so they sit on top
        for taken in (False, True):
            for node, pt in pos.items():
                if not node:
                    continue
                parent = node.rsplit("/", 1)[0] if "/" in node else ""
                on = self._on_path(node)
                if on != taken:
                    continue
                p.setPen(QPen(accent if on else muted, 3.0 if on else 1.0))
                p.drawLine(pos[parent], pt)

        # row labels: the quantity, its value, the threshold
        v = self.values
        cs = self.config
        row_text = [
            f"Clinical score {_fmt(v.get('clinical_score'), 0)}\ngroups at {cs.scoreThresholds[0]:g} / "
            f"{cs.scoreThresholds[1]:g}",
            f"TPI {_fmt(v.get('tpi'))}\nhigh ≥ {cs.layers['tpi'].threshold:g}",
            f"MPI {_fmt(v.get('mpi'))}\nhigh ≥ {cs.layers['mpi'].threshold:g}",
            f"PTI {_fmt(v.get('pti'))}\nhigh ≥ {cs.layers['pti'].threshold:g}",
            "α range\n(leaves)",
        ]
        p.setFont(small)
        for i, text in enumerate(row_text):
            p.setPen(fg)
            p.drawText(QRectF(6, rows[i] - 20, left - 24, 40), Qt.AlignmentFlag.AlignVCenter, text)

        # nodes
        for node, pt in pos.items():
            depth = -1 if not node else node.count("/")
            on = self._on_path(node)
            radius = 9.0 if depth < 3 else max(5.0, min(9.0, step * 0.32))
            lo, hi = self.ranges.get(node, (-1.0, 1.0))
            fill = alpha_colour((lo + hi) / 2.0) if depth == 3 else QColor(c.base)
            if on and depth < 3:
                fill = QColor("#FFCDD2")
            p.setBrush(fill)
            p.setPen(QPen(accent if on else muted, 3.0 if on else 1.2))
            p.drawEllipse(pt, radius, radius)
            p.setPen(fg if on else muted)
            if depth == 0:
                label = GROUP_LABELS[node]
                p.drawText(QRectF(pt.x() - 60, pt.y() - 30, 120, 16), Qt.AlignmentFlag.AlignCenter,
                           f"{label} [{lo:+.1f}, {hi:+.1f}]")
            elif depth in (1, 2, 3):
                high = node.rsplit("_", 1)[1] == "high"
                if depth == 3:  # leaves: under the node
                    box = QRectF(pt.x() - 12, pt.y() + radius, 24, 14)
                else:  # inner nodes: beside the edge coming in, outside the circle
                    box = QRectF(pt.x() + radius - 2 if high else pt.x() - radius - 12, pt.y() - radius - 14,
                                 14, 14)
                p.drawText(box, Qt.AlignmentFlag.AlignCenter, "H" if high else "L")

        # the taken leaf: its range under it
        if self.path in pos:
            pt = pos[self.path]
            lo, hi = self.ranges[self.path]
            p.setPen(accent)
            p.drawText(QRectF(pt.x() - 60, pt.y() + 22, 120, 14), Qt.AlignmentFlag.AlignCenter,
                       f"[{lo:+.2f}, {hi:+.2f}]")

        self._draw_alpha_axis(p, left, fg, muted, accent, small)
        p.end()

    def _draw_alpha_axis(self, p: QPainter, left: float, fg: QColor, muted: QColor, accent: QColor,
                         font: QFont) -> None:
        y = self.height() - 40.0
        x0, x1 = left, self.width() - 16.0

        def x_of(a: float) -> float:
            return x0 + (a + 1.0) / 2.0 * (x1 - x0)

        p.setPen(fg)
        p.drawText(QRectF(6, y - 22, left - 24, 44), Qt.AlignmentFlag.AlignVCenter,
                   f"Layer 5: sub-task\nlevel {_fmt(self.level)}")
        for a in np.linspace(-1.0, 1.0, 41):  # the gradient from resistance to assistance
            p.fillRect(QRectF(x_of(a) - (x1 - x0) / 80.0, y - 5, (x1 - x0) / 40.0 + 1, 10), alpha_colour(a))
        p.setPen(QPen(muted, 1.0))
        af = Qt.AlignmentFlag
        for a, text, align in ((-1.0, "−1 resist", af.AlignLeft), (0.0, "0", af.AlignHCenter),
                               (1.0, "+1 assist", af.AlignRight)):
            p.drawLine(QPointF(x_of(a), y + 5), QPointF(x_of(a), y + 10))
            box = QRectF(x_of(a) - (0 if a < 0 else 80 if a > 0 else 40), y + 10, 80, 14)
            p.drawText(box, align | af.AlignTop, text)
        lo, hi = self.alpha_range
        if math.isfinite(lo) and math.isfinite(hi):
            p.setBrush(Qt.BrushStyle.NoBrush)
            p.setPen(QPen(accent, 2.0))
            p.drawRect(QRectF(x_of(lo), y - 9, max(2.0, x_of(hi) - x_of(lo)), 18))
        if math.isfinite(self.alpha):
            xa = x_of(self.alpha)
            p.setPen(QPen(accent, 3.0))
            p.drawLine(QPointF(xa, y - 14), QPointF(xa, y + 14))
            p.setFont(font)
            p.drawText(QRectF(xa - 50, y - 30, 100, 14), Qt.AlignmentFlag.AlignCenter, f"α = {self.alpha:+.3f}")


def _fmt(x: float | None, digits: int = 2) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


class PatientModelViewer(RefreshWhenVisible, QWidget):
    def __init__(self, manager: Any = None, driver: Any = None, tree_config: TreeConfig | None = None,
                 history_s: float = 60.0, refresh_hz: float = 20.0, parent: QWidget | None = None, *,
                 qt_bus: QtBus | None = None) -> None:
        """Live from ``qt_bus`` (the window's; with a manager and none, the viewer's own), or fed by hand
        (:meth:`feed`) without either."""
        super().__init__(parent)
        self.setWindowTitle("Patient model")
        self.manager = manager
        self.driver = driver if driver is not None else (manager.driver(streams.PATIENT_MODEL) if manager else None)
        self.qt_bus = qt_bus_for(manager, qt_bus, self) if manager is not None or qt_bus is not None else None
        self.history_s = history_s
        self._t: deque[float] = deque()
        self._cols: dict[str, deque[float]] = {k: deque() for k in (*ALPHA_CHANNELS, *INDEX_CHANNELS)}
        self._latest: Any = None
        self._shown: Any = None
        self._dirty = False
        self.clinical_score: float | None = None  # shown when there is no driver to ask

        c = colours()
        self.status = QLabel("waiting for the patient model")
        self.values: dict[str, QLabel] = {}
        grid = QGridLayout()
        for i, key in enumerate((*ALPHA_CHANNELS, *INDEX_CHANNELS, "range", "group", "flags")):
            name = LABELS.get(key, key)
            grid.addWidget(QLabel(f"{name}:"), i // 6, 2 * (i % 6))
            self.values[key] = QLabel("–")
            self.values[key].setMinimumWidth(70)
            grid.addWidget(self.values[key], i // 6, 2 * (i % 6) + 1)

        self.alpha_plot = pg.PlotWidget(background=c.plot_background)
        self.index_plot = pg.PlotWidget(background=c.plot_background)
        self.curves: dict[str, pg.PlotDataItem] = {}
        for plot, keys, (lo, hi), title in ((self.alpha_plot, ALPHA_CHANNELS, (-1.05, 1.05), "Assistance"),
                                            (self.index_plot, INDEX_CHANNELS, (-0.02, 1.02), "Indices")):
            plot.setYRange(lo, hi, padding=0)
            plot.showGrid(x=True, y=True, alpha=c.grid_alpha)
            plot.addLegend(offset=(5, 5))
            plot.setLabel("left", title)
            plot.setLabel("bottom", "time", units="s")
            plot.setMouseEnabled(x=False, y=False)
            for key in keys:
                idx = (*ALPHA_CHANNELS, *INDEX_CHANNELS).index(key)
                self.curves[key] = plot.plot([], [], pen=pg.mkPen(curve_colour(idx), width=2 if key == "alpha"
                                                                  else 1.5), name=LABELS[key])
        self.index_plot.setXLink(self.alpha_plot)
        self.tree = DecisionTreeView(tree_config)

        plots = QWidget()
        pl = QVBoxLayout(plots)
        pl.setContentsMargins(0, 0, 0, 0)
        pl.addWidget(self.alpha_plot)
        pl.addWidget(self.index_plot)
        split = QSplitter(Qt.Orientation.Horizontal)
        split.addWidget(plots)
        split.addWidget(self.tree)
        split.setStretchFactor(0, 2)
        split.setStretchFactor(1, 3)
        top = QHBoxLayout()
        top.addWidget(self.status, 1)
        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addLayout(grid)
        layout.addWidget(split, 1)

        if self.qt_bus is not None:
            self.qt_bus.samples.connect(self._on_batches)
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._tick)
        self.timer.start(int(1000 / refresh_hz))

    # ------------------------------------------------------------------ data in
    def _on_batches(self, batches: dict[str, Any]) -> None:
        b = batches.get(streams.PATIENT_MODEL_MAIN)
        if b is None:
            return
        self._t.extend(b.t.tolist())
        for key, col in self._cols.items():
            col.extend(b.data[key].tolist())
        self._trim()
        self._dirty = True

    def feed(self, t: float, sample: Any) -> None:
        """One sample, outside a driver (replay, tests)."""
        self._t.append(t)
        for key, col in self._cols.items():
            col.append(float(getattr(sample, key, math.nan)))
        self._latest = sample
        self._trim()
        self._dirty = True

    def _trim(self) -> None:
        if not self._t:
            return
        cut = self._t[-1] - self.history_s
        while self._t and self._t[0] < cut:
            self._t.popleft()
            for col in self._cols.values():
                col.popleft()

    # ------------------------------------------------------------------ display

    def refresh(self) -> None:
        qt_bus = self.qt_bus if self.driver is not None else None
        latest = qt_bus.latest(streams.PATIENT_MODEL_MAIN) if qt_bus is not None else self._latest
        if qt_bus is not None:
            drops = self.driver.dropped_total if hasattr(self.driver, "dropped_total") else 0
            state = "connected" if qt_bus.connected(streams.PATIENT_MODEL) else "not connected"
            rate = self.driver.rates().get(streams.PATIENT_MODEL_MAIN, 0.0)
            self.status.setText(f"Patient model {state} · {rate:.0f} replies/s · {drops} datagrams dropped")
        if latest is not None and latest is not self._shown:
            self._show_sample(latest)
        if self._dirty and self._t:
            t = np.fromiter(self._t, dtype=float)
            t_rel = t - t[-1]
            for key, col in self._cols.items():
                self.curves[key].setData(t_rel, np.fromiter(col, dtype=float))
            self.alpha_plot.setXRange(-self.history_s, 0, padding=0)
            self._dirty = False

    def _show_sample(self, s: Any) -> None:
        self._shown = s
        for key in (*ALPHA_CHANNELS, *INDEX_CHANNELS):
            self.values[key].setText(_fmt(getattr(s, key, math.nan), 3))
        lo, hi = getattr(s, "alphaMin", math.nan), getattr(s, "alphaMax", math.nan)
        self.values["range"].setText(f"[{_fmt(lo)}, {_fmt(hi)}]")
        path = getattr(s, "path", "")
        self.values["group"].setText(GROUP_LABELS.get(path.split("/", 1)[0], "–") if path else "–")
        self.values["flags"].setText("valid" if getattr(s, "valid", False) else
                                     "fallback" if getattr(s, "fallback", False) else "–")
        values = {name: float(getattr(s, name, math.nan)) for name in INDEX_LAYERS}
        score = getattr(self.driver, "clinical_score", None) if self.driver is not None else self.clinical_score
        values["clinical_score"] = math.nan if score is None else float(score)
        self.tree.set_decision(path, float(getattr(s, "alpha", math.nan)), (lo, hi),
                               float(getattr(s, "level", math.nan)), values)

    def closeEvent(self, event: Any) -> None:
        self.timer.stop()
        super().closeEvent(event)
