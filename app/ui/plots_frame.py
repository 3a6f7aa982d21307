"""Frame 2 — live graphs of any signal, chosen at run time, with a Save button in the lower part
(seed D2.1).

* A checkable tree lists every signal of every device (device → stream → channel) from the
  :class:`~app.ui.signal_store.SignalStore`.
* Selected signals are drawn in stacked plots, one per unit, sharing one time axis (seconds before
  the newest sample; linked zoom and pan).
* Drawing happens on a timer at ``ui.refresh_hz`` from the store's min/max envelope, never per sample.
* Pause freezes a copy of the buffers (so what is on screen can still be zoomed, read and saved
  while the devices keep streaming); zooming or panning the time axis while live pauses too.
* A crosshair shows the time and every selected signal's value under the mouse.
* **Save** writes the selected signals over the visible range or the whole buffer to CSV;
  **Export PNG** saves the plots as a picture.

Keys (when the frame has focus): Space or P pause/resume, A autoscale and follow, Home follow live,
+/- history length, Ctrl+S save, Ctrl+E export PNG.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QEvent, QObject, QRectF, QSettings, Qt, QTimer, Signal
from PySide6.QtGui import (
    QColor,
    QFont,
    QFontMetrics,
    QImage,
    QKeyEvent,
    QPainter,
    QPainterPath,
    QPen,
    QPicture,
    QPolygonF,
    QTransform,
)
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QFileDialog,
    QFrame,
    QGraphicsItem,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QSplitter,
    QStyle,
    QTreeWidget,
    QTreeWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.core import streams
from app.core.paths import sessions_dir
from app.manager import LinarmppManager
from app.ui.plot_render import CurveImage, CurveRenderer, PaneJob
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.signal_store import SignalInfo, SignalStore, shared_store, signal_key
from app.ui.theme import colours, curve_colour
from app.ui.widgets import on_screen

log = logging.getLogger(__name__)

KEY_ROLE = Qt.ItemDataRole.UserRole
SI_BASE_UNITS = {"m", "N", "N/m", "m/s", "m/s^2", "A", "V", "s", "S", "Ω", "W", "Hz"}
FES_CHANNEL = re.compile(r"(Current|Pulse width) ch (\d+)")  # the stimulator's channel labels
HISTORY_CHOICES_S = (5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0)
DEFAULT_SIGNALS = (signal_key(streams.LINARM_VSA, "handlePos"), signal_key(streams.LINARM_VSA, "equilibriumPos"),
                   signal_key(streams.LINARM_VSA, "interactionForce"), signal_key(streams.PHYSIO_MAIN, "heartRate"))
SCOPE_VISIBLE, SCOPE_ALL = "visible", "all"
LAYOUT_ONE_TABLE, LAYOUT_PER_STREAM = "one_table", "per_stream"
NO_UNIT = "(no unit)"
# The smallest graph pane that still shows its curve, its rotated unit label and three tick labels
# without touching a neighbour's (measured at the default 9 pt font: label ~70 px tall).
MIN_PANE_HEIGHT_PX = 84
BOTTOM_AXIS_PX = 40  # the shared time axis with its values and title
# Vertical autoscale with hysteresis: the range follows the data only when the data leaves it or fills
# less than Y_FILL_MIN of it, and then with Y_HEADROOM of the data's span above and below. A range that
# moved every frame re-generated the axis and its grid every frame (the largest part of a frame).
Y_FILL_MIN = 0.4
Y_HEADROOM = 0.15
Y_PADDING = 0.05  # "Fit" (A key, Fit button): close around the data
# The graphs take at most this share of the GUI thread: when a frame (drawing + painting) costs more
# than GRAPH_DUTY of the interval, the interval grows, so the e-stop and the other views keep their turn.
GRAPH_DUTY = 0.35
# ... and at most this share of a core for the thread that strokes the curves (app.ui.plot_render).
RENDER_DUTY = 0.5
MAX_INTERVAL_MS = 250  # never slower than 4 frames a second


def sticky_y_range(current: tuple[float, float] | None, lo: float, hi: float,
                   snap: bool = False) -> tuple[float, float] | None:
    """The new vertical range for data spanning [lo, hi] shown in ``current``, or None to keep it.

    Kept while it holds the data and the data fills at least Y_FILL_MIN of it; otherwise the data's
    span plus Y_HEADROOM each side (``snap``: always a new range, Y_PADDING each side). The data is
    never outside the range returned (or kept)."""
    span = hi - lo
    if span <= 0:
        # A flat line: a band around it of a tenth of its value, at least one unit -- a band of 1e-9 made
        # a flat zero read "×1e-12" on the axis (issue #30, the Replay window's robot-state signals).
        span = max(abs(hi) * 0.1, 1.0)
        lo, hi = lo - span / 2, hi + span / 2
    if not snap and current is not None:
        c_lo, c_hi = current
        if c_lo <= lo and hi <= c_hi and span >= Y_FILL_MIN * (c_hi - c_lo):
            return None
    pad = span * (Y_PADDING if snap else Y_HEADROOM)
    return lo - pad, hi + pad


class LiveViewBox(pg.ViewBox):
    """A ViewBox whose vertical autorange follows ``y_bounds`` (set by the frame from the data it
    drew) through :func:`sticky_y_range`, instead of re-measuring every item and moving the range on
    every frame. Autorange stays pyqtgraph's own switch: ``enableAutoRange``, mouse zoom turns it off."""

    def __init__(self) -> None:
        super().__init__(enableMenu=False)  # the panes have no context menu (building it cost ~8 ms a pane)
        self.y_bounds: tuple[float, float] | None = None
        self.snap_y = True

    def enableAutoRange(self, axis: Any = None, enable: Any = True, x: Any = None, y: Any = None) -> None:
        was_on = self.state["autoRange"][1] is not False
        super().enableAutoRange(axis, enable, x, y)
        if not was_on and self.state["autoRange"][1] is not False:
            self.snap_y = True  # switched on again: fit the data closely once

    def updateAutoRange(self) -> None:
        if self.state["autoRange"][0] is not False:  # x autorange (pyqtgraph's own "A" button): its way
            super().updateAutoRange()
            return
        self._autoRangeNeedsUpdate = False
        if self.state["autoRange"][1] is False or self.y_bounds is None:
            return
        current = None if self.snap_y else tuple(self.viewRange()[1])
        new = sticky_y_range(current, *self.y_bounds, snap=self.snap_y)  # type: ignore[arg-type]
        self.snap_y = False
        if new is not None:
            self.setRange(yRange=new, padding=0.0, disableAutoRange=False)


class FastCurve(pg.GraphicsObject):
    """A curve that costs almost nothing to update (#37: pyqtgraph's PlotCurveItem spent ~0.2 ms per curve and
    frame re-measuring its bounds and informing its view; 49 curves held the GUI thread ~15 ms a frame).

    ``setData(x, y, y_bounds)`` writes the points into the polygon it keeps (reallocated only when the number of
    points changes; a NaN breaks the line: a path then) and moves its bounding rectangle only when the data leave
    it or fill less than 80 % of it; it does not ask for a repaint (the frame repaints its view once, not once per
    curve). ``paint`` draws the polygon with a cosmetic pen. ``getData`` returns what was set. ``opts`` is what
    pyqtgraph's legend reads for its sample."""

    def __init__(self, pen: QPen, name: str) -> None:
        super().__init__()
        self.pen = pen
        self.opts: dict[str, Any] = {"pen": pen, "name": name, "antialias": False, "fillLevel": None,
                                     "fillBrush": None, "symbol": None}
        self._x = np.zeros(0)
        self._y = np.zeros(0)
        self._poly = QPolygonF()
        self._points: np.ndarray | None = None  # a view of the polygon's own memory (n × 2)
        self._path: QPainterPath | None = None
        self._rect = QRectF()
        self.finite = True  # no NaN in the points (else the line breaks at each)
        self.user_visible = True  # the legend's sample toggles it
        self.drawn_elsewhere = False  # the frame's renderer strokes it (the item itself stays hidden)

    def setVisible(self, visible: bool) -> None:  # type: ignore[override]
        """The user's choice (the legend's sample); the item shows only when it is not drawn elsewhere."""
        self.user_visible = bool(visible)
        super().setVisible(self.user_visible and not self.drawn_elsewhere)

    def isVisible(self) -> bool:  # type: ignore[override]
        return self.user_visible

    def set_drawn_elsewhere(self, elsewhere: bool) -> None:
        self.drawn_elsewhere = elsewhere
        super().setVisible(self.user_visible and not elsewhere)

    def name(self) -> str:
        return str(self.opts["name"])

    def set_pen(self, pen: QPen) -> None:
        self.pen = pen
        self.opts["pen"] = pen
        self.update()

    def getData(self) -> tuple[np.ndarray, np.ndarray]:
        return self._x, self._y

    def setData(self, x: Any, y: Any, y_bounds: tuple[float, float] | None = None,
                finite: bool | None = None, *, drawn_here: bool = True) -> None:
        """The curve's points; ``y_bounds`` (the finite minimum and maximum of ``y``) and ``finite`` (no NaN in
        ``y``) when the caller knows them already. ``drawn_here=False``: the points are kept (getData, the
        crosshair) but drawn elsewhere (the frame's renderer): no polygon is built."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        self._x, self._y = x, y
        if not drawn_here:
            self.finite = bool(np.isfinite(y).all()) if finite is None else finite
            return
        if y_bounds is None and y.size:
            with np.errstate(invalid="ignore"):
                y_bounds = (float(np.fmin.reduce(y)), float(np.fmax.reduce(y)))
        if len(x) < 2 or y_bounds is None or not math.isfinite(y_bounds[0]):
            self._points, self._path = None, None
            self._poly = QPolygonF()
            return
        if finite is None:
            finite = bool(np.isfinite(y).all())
        self.finite = finite
        if finite:
            if self._points is None or len(self._points) != len(x):
                self._poly = pg.functions.create_qpolygonf(len(x))
                self._points = pg.functions.ndarray_from_qpolygonf(self._poly)
            self._points[:, 0] = x
            self._points[:, 1] = y
            self._path = None
        else:  # gaps: a path that lifts the pen at each NaN
            self._path = pg.functions.arrayToQPath(x, y, connect="finite")
        self._set_rect(float(x[0]), float(x[-1]), *y_bounds)

    def _set_rect(self, x0: float, x1: float, y0: float, y1: float) -> None:
        """A rectangle a little larger than the data, kept while the data stay in it and fill most of it: a
        geometry change costs the scene's and the view's bookkeeping, so not one per frame."""
        old = self._rect
        w, h = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
        if (not old.isNull() and old.left() <= x0 and x1 <= old.right() and old.top() <= y0
                and y1 <= old.bottom() and old.width() <= 1.25 * w and old.height() <= 1.25 * h):
            return
        self.prepareGeometryChange()
        self._rect = QRectF(x0 - 0.1 * w, y0 - 0.1 * h, 1.2 * w, 1.2 * h)
        self.informViewBoundsChanged()

    def boundingRect(self) -> QRectF:
        return QRectF(self._rect)

    def dataBounds(self, ax: int, frac: float = 1.0, orthoRange: Any = None) -> tuple[float | None, float | None]:
        data = self._x if ax == 0 else self._y
        if not data.size:
            return None, None
        with np.errstate(invalid="ignore"):
            lo, hi = float(np.fmin.reduce(data)), float(np.fmax.reduce(data))
        return (lo, hi) if math.isfinite(lo) else (None, None)

    def paint(self, painter: QPainter, *_args: Any) -> None:
        painter.setPen(self.pen)
        if self._path is not None:
            painter.drawPath(self._path)
        elif self._points is not None:
            painter.drawPolyline(self._poly)


class _TimedGraphics(pg.GraphicsLayoutWidget):
    """The graphs' view, timing its own paint (the larger part of a frame's cost)."""

    def __init__(self) -> None:
        super().__init__()
        self.last_paint_s = 0.0

    def paintEvent(self, event: Any) -> None:
        t0 = time.perf_counter()
        super().paintEvent(event)
        self.last_paint_s = time.perf_counter() - t0


def _pane_min_height(last: bool) -> int:
    """A pane's minimum height: the last pane carries the time axis, room for it besides a pane's own height."""
    return MIN_PANE_HEIGHT_PX + (BOTTOM_AXIS_PX if last else 0)


def prepare_axis(axis: pg.AxisItem) -> None:
    """What ``axis`` draws (its ticks, labels and grid lines), now, as its first paint would (pyqtgraph's
    AxisItem.paint keeps it as a picture until its range or size changes): the first paint of many panes at once
    spent most of its ~2 ms a pane there, so a staged build prepares it a pane per turn (#37)."""
    if axis.picture is not None or not axis.isVisible():
        return
    picture = QPicture()
    painter = QPainter(picture)
    try:
        if axis.style["tickFont"]:
            painter.setFont(axis.style["tickFont"])
        specs = axis.generateDrawSpecs(painter)
        if specs is not None:
            axis.drawPicture(painter, *specs)
    finally:
        painter.end()
    axis.picture = picture


class PlotsFrame(QWidget):
    # "Larger" pressed (True) or released: the window gives the graphs the whole column (#37: at 1366×768 six
    # graphs left 1.5 readable panes beside the Commands frame). Only offered when a window listens.
    enlarge_toggled = Signal(bool)

    def __init__(self, manager: LinarmppManager | None, store: SignalStore | None = None, *,
                 qt_bus: QtBus | None = None) -> None:
        """The live graphs of ``manager``'s devices, fed by ``qt_bus`` (the window's adapter; without one the
        frame makes its own) through the manager's shared store; or, with ``store``, that store's signals."""
        super().__init__()
        self.manager = manager
        self.qt_bus: QtBus | None = None  # None: a given store's signals (a replay), no live data
        if store is None:
            assert manager is not None
            self.qt_bus = qt_bus_for(manager, qt_bus, self)
            store = shared_store(manager, self.qt_bus)
        self.store = store
        refresh_hz = manager.config.ui.refresh_hz if manager is not None else 30.0
        self.selected: list[str] = []
        self._wanted: list[str] = []  # selection from settings, kept until its device appears
        self.paused = False
        self._frozen: SignalStore | None = None
        self.t_ref: float | None = None  # the newest sample's time (the right edge when following)
        # Time of x = 0: None = the newest sample (live: the axis runs -history..0); a replay sets the
        # session's start, so its axis is session time (issue #19: it ran -25..0).
        self.x_origin: float | None = None
        self.history_s = min(30.0, store.history_s)
        self.plots: dict[str, pg.PlotItem] = {}  # unit → plot
        self.curves: dict[str, FastCurve] = {}
        self._curve_plot: dict[str, pg.PlotItem] = {}  # key -> the plot its curve is in
        self._vlines: dict[str, pg.InfiniteLine] = {}  # unit -> its pane's crosshair line
        self._styled: dict[int, bool] = {}  # id of a pane's plot -> styled as the last pane (_style_pane)
        self.vlines: list[pg.InfiniteLine] = []
        self._dirty = True
        self._building_tree = False
        self._follow_x = True
        self.cursor_x: float | None = None
        self.frame_times: list[float] = []
        self._drawn_t: float | None = None  # newest sample time of the last live frame
        self._base_interval_ms = int(1000 / max(1.0, refresh_hz))
        self._interval_set = self._base_interval_ms  # what _adapt_interval last put on the timer
        self.frame_cost_s = 0.0  # smoothed cost of one frame (drawing + painting) on the GUI thread
        # Live and following, the curves are stroked off the GUI thread (app.ui.plot_render) and each pane shows
        # their image; paused, zoomed or exported, its curve items draw them (``_image_mode``).
        self.render_off_thread = True
        self._image_mode = False
        self.images: dict[str, CurveImage] = {}  # unit -> its pane's rendered curves
        self.renderer = CurveRenderer(self)
        self.renderer.rendered.connect(self._on_rendered)
        self._frame_seq = 0
        self._shown_seq = 0

        self.session_t0: float | None = None  # monotonic time of the session's start: CSV time 0
        self.session_name = ""  # "<patient>/<session folder>" while a session runs
        if manager is not None:
            manager.session_changed.connect(self._on_session)
            if manager.recorder is not None:
                self._on_session(manager.recorder.folder)

        self._build_ui()
        self._restore_settings()
        self._rebuild_tree()
        self.store.signals_changed.connect(self._rebuild_tree)
        self.store.updated.connect(self._mark_dirty)

        self.timer = QTimer(self)
        self.timer.setInterval(self._base_interval_ms)
        self.timer.timeout.connect(self._tick)
        self.timer.start()

    # ------------------------------------------------------------------ names
    def _muscles(self) -> dict[int, str]:
        """Channel -> muscle of the loaded FES profile (empty without one)."""
        fes = self.manager.driver(streams.FES) if self.manager is not None else None
        profile = getattr(fes, "profile", None)
        channels = getattr(profile, "channels", None) or {}
        return {int(ch): str(cp.muscle) for ch, cp in channels.items() if getattr(cp, "muscle", "")}

    def display_label(self, info: SignalInfo) -> str:
        """The name shown in the tree, legends and readout. FES channels lead with their number, then
        the quantity, then the muscle of the loaded profile (issue #19: eight identical "Current c…")."""
        match = FES_CHANNEL.fullmatch(info.label)
        if info.device != streams.FES or match is None:
            return info.label
        kind, number = match.group(1).lower(), int(match.group(2))
        muscle = self._muscles().get(number)
        return f"{number} {kind}" + (f" · {muscle}" if muscle else "")

    # ------------------------------------------------------------------ building
    def _build_ui(self) -> None:
        pg.setConfigOptions(antialias=False)
        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        outer.setSpacing(2)
        self.splitter = QSplitter(Qt.Orientation.Horizontal)
        outer.addWidget(self.splitter, 1)

        self.tree = QTreeWidget()
        self.tree.setHeaderLabels(["Signal", "Unit"])
        self.tree.setIndentation(14)
        self.tree.setMinimumWidth(110)
        tree_header = self.tree.header()
        tree_header.setStretchLastSection(False)
        tree_header.setSectionResizeMode(0, QHeaderView.ResizeMode.Stretch)
        tree_header.setSectionResizeMode(1, QHeaderView.ResizeMode.ResizeToContents)
        self.tree.setAccessibleName("Signals to plot")
        self.tree.itemChanged.connect(self._on_item_changed)
        self.splitter.addWidget(self.tree)

        right = QWidget()
        rlay = QVBoxLayout(right)
        rlay.setContentsMargins(0, 0, 0, 0)
        rlay.setSpacing(2)
        top = QHBoxLayout()
        self.pause_button = QPushButton("Pause")
        self.pause_button.setCheckable(True)
        self.pause_button.setToolTip("Freeze the graphs (Space or P); zoom, read and save what you see")
        self.pause_button.toggled.connect(self.set_paused)
        top.addWidget(self.pause_button)
        self.history_box = QComboBox()
        self.history_box.setAccessibleName("History length")
        self.history_box.setToolTip("History shown (+ / - keys)")
        for h in HISTORY_CHOICES_S:
            if h <= self.store.history_s + 1e-9:
                self.history_box.addItem(f"{h:g} s", h)
        if self.history_box.findData(self.store.history_s) < 0:
            self.history_box.addItem(f"{self.store.history_s:g} s", self.store.history_s)
        self.history_box.currentIndexChanged.connect(
            lambda _i: self.set_history(float(self.history_box.currentData())))
        top.addWidget(self.history_box)
        self.autoscale_box = QCheckBox("Auto &Y")
        self.autoscale_box.setChecked(True)
        self.autoscale_box.setToolTip("Fit the vertical axes to the visible data")
        self.autoscale_box.toggled.connect(self.set_autoscale)
        top.addWidget(self.autoscale_box)
        self.fit_button = QPushButton("&Fit")
        self.fit_button.setToolTip("Autoscale every axis and follow the live data (A)")
        self.fit_button.clicked.connect(self.fit)
        top.addWidget(self.fit_button)
        self.enlarge_button = QPushButton("&Larger")
        self.enlarge_button.setCheckable(True)
        self.enlarge_button.setToolTip("Give the graphs the whole column: the Commands frame is hidden until you "
                                       "press this again (or open a command tab)")
        self.enlarge_button.toggled.connect(self.enlarge_toggled.emit)
        self.enlarge_button.setVisible(False)  # shown by a window that can make room (set_enlarge_offered)
        top.addWidget(self.enlarge_button)
        top.addStretch(1)
        rlay.addLayout(top)

        self.graphics = _TimedGraphics()
        c = colours()
        self.graphics.setBackground(c.plot_background)
        self.graphics.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.graphics.setAccessibleName("Graphs")
        self.graphics.setMinimumSize(160, 120)
        self.graphics.installEventFilter(self)
        self.graphics.scene().sigMouseMoved.connect(self._on_mouse_moved)
        # The panes scroll rather than shrink (issue #30: a 4th and 5th pane got no height at all and
        # their axis labels ran into the others'): each pane keeps MIN_PANE_HEIGHT_PX, the area shows as
        # many as fit and a scroll bar says there are more.
        self.graphs_scroll = QScrollArea()
        self.graphs_scroll.setWidgetResizable(True)
        self.graphs_scroll.setFrameShape(QFrame.Shape.NoFrame)
        self.graphs_scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.graphs_scroll.setWidget(self.graphics)
        self.graphs_scroll.setMinimumSize(160, 120)
        # a pane scrolled into view is reduced and drawn by the next frame, new samples or not
        self.graphs_scroll.verticalScrollBar().valueChanged.connect(self._mark_dirty)
        rlay.addWidget(self.graphs_scroll, 1)

        self.readout = QLabel(" ")
        self.readout.setWordWrap(True)
        self.readout.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.readout.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        rlay.addWidget(self.readout)

        bottom = QHBoxLayout()
        self.save_button = QPushButton("&Save…")
        self.save_button.setToolTip("Save the selected signals to CSV (Ctrl+S)")
        self.save_button.clicked.connect(self._ask_save)
        bottom.addWidget(self.save_button)
        self.scope_box = QComboBox()
        self.scope_box.setAccessibleName("What to save")
        self.scope_box.addItem("visible", SCOPE_VISIBLE)
        self.scope_box.addItem("whole buffer", SCOPE_ALL)
        self.scope_box.setToolTip("Save the visible time range or everything buffered")
        bottom.addWidget(self.scope_box)
        # Streams of different rates in one table leave empty cells (issue #30): the choice is said, and
        # one file per stream (each dense, at its own rate) is offered.
        self.layout_box = QComboBox()
        self.layout_box.setAccessibleName("CSV layout")
        self.layout_box.addItem("one table", LAYOUT_ONE_TABLE)
        self.layout_box.addItem("a file per stream", LAYOUT_PER_STREAM)
        self.layout_box.setToolTip("One table: one row per sampling instant of any stream, a stream's cells "
                                   "empty between its own samples.\nA file per stream: each stream at its "
                                   "own rate, no empty cells.")
        bottom.addWidget(self.layout_box)
        self.png_button = QPushButton("&PNG…")
        self.png_button.setToolTip("Save the graphs as a picture (Ctrl+E)")
        self.png_button.clicked.connect(self._ask_png)
        bottom.addWidget(self.png_button)
        self.status = QLabel("")
        self.status.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        bottom.addWidget(self.status, 1)
        rlay.addLayout(bottom)

        self.splitter.addWidget(right)
        self.splitter.setStretchFactor(0, 0)
        self.splitter.setStretchFactor(1, 1)
        self.splitter.setSizes([230, 560])

    def _rebuild_tree(self) -> None:
        """(Re)list every signal of the store: device → stream → channel, checked when selected."""
        for _ in self.tree_steps():
            pass

    def tree_steps(self) -> Iterator[None]:
        """_rebuild_tree a device per ``next()`` (a replay's staged build: the whole list took ~9 ms, #37); the
        list's layout and width once complete."""
        self._building_tree = True
        try:
            self.tree.clear()
            devices: dict[str, QTreeWidgetItem] = {}
            streams: dict[str, QTreeWidgetItem] = {}
            wanted = set(self.selected) | set(self._wanted)
            flags_parent = (Qt.ItemFlag.ItemIsEnabled | Qt.ItemFlag.ItemIsUserCheckable
                            | Qt.ItemFlag.ItemIsAutoTristate | Qt.ItemFlag.ItemIsSelectable)
            for info in self.store.signals():
                dev = devices.get(info.device)
                if dev is None:
                    if devices:
                        yield
                    dev = QTreeWidgetItem(self.tree, [info.device, ""])
                    dev.setFlags(flags_parent)
                    dev.setCheckState(0, Qt.CheckState.Unchecked)
                    devices[info.device] = dev
                parent = dev
                stream_label = info.stream.split(".", 1)[1] if "." in info.stream else info.stream
                if stream_label not in ("main",):
                    parent = streams.get(info.stream)
                    if parent is None:
                        parent = QTreeWidgetItem(dev, [stream_label, ""])
                        parent.setFlags(flags_parent)
                        parent.setCheckState(0, Qt.CheckState.Unchecked)
                        streams[info.stream] = parent
                label = self.display_label(info) or info.channel
                item = QTreeWidgetItem(parent, [label, info.unit])
                item.setData(0, KEY_ROLE, info.key)
                item.setToolTip(0, f"{label}\n{info.key}" if label != info.label else info.key)
                item.setFlags(Qt.ItemFlag.ItemIsEnabled | Qt.ItemFlag.ItemIsUserCheckable
                              | Qt.ItemFlag.ItemIsSelectable)
                item.setCheckState(0, Qt.CheckState.Checked if info.key in wanted else Qt.CheckState.Unchecked)
            self.tree.expandAll()
        finally:
            self._building_tree = False
        self._muscles_shown = self._muscles()
        self._fit_tree()

    def _fit_tree(self) -> None:
        """Give the signal list the width its names need (FES names, which carry a muscle, may be
        elided: their tooltip has them whole), at most 40 % of the frame."""
        fm = self.tree.fontMetrics()
        check = self.tree.style().pixelMetric(QStyle.PixelMetric.PM_IndicatorWidth, None, self.tree) + 8
        need = 0
        for item in self._leaf_items():
            depth = 0
            p = item.parent()
            while p is not None:
                depth += 1
                p = p.parent()
            key = item.data(0, KEY_ROLE)
            if key is not None and self.store.info(key).device == streams.FES:
                continue
            need = max(need, fm.horizontalAdvance(item.text(0)) + check + self.tree.indentation() * (depth + 1))
        unit = max((fm.horizontalAdvance(i.text(1)) for i in self._leaf_items()), default=20) + 16
        width = need + unit + self.tree.verticalScrollBar().sizeHint().width() + 8
        sizes = self.splitter.sizes()
        total = sum(sizes) or 790
        width = min(width, int(total * 0.4))
        if sizes and sizes[0] < width:
            self.splitter.setSizes([width, max(total - width, 160)])
        self._collect_selection()

    def _leaf_items(self) -> Iterable[QTreeWidgetItem]:
        stack = [self.tree.topLevelItem(i) for i in range(self.tree.topLevelItemCount())]
        while stack:
            item = stack.pop(0)
            key = item.data(0, KEY_ROLE)
            if key:
                yield item
            stack[0:0] = [item.child(i) for i in range(item.childCount())]

    def _on_item_changed(self, _item: QTreeWidgetItem, _col: int) -> None:
        if not self._building_tree:
            self._collect_selection()

    def _collect_selection(self) -> None:
        selected = [it.data(0, KEY_ROLE) for it in self._leaf_items() if it.checkState(0) == Qt.CheckState.Checked]
        available = {i.key for i in self.store.signals()}
        # Keep wanted signals of devices not (yet) present; forget those the user unticked.
        self._wanted = [k for k in self._wanted if k not in available]
        if selected != self.selected or (not self.plots and selected):
            self.selected = selected
            self._rebuild_plots()

    def panes_min_height(self) -> int:
        """The graphs' own minimum: every pane MIN_PANE_HEIGHT_PX, plus the time axis under the last, plus the
        layout's spacing between the panes and its margins."""
        layout = self.graphics.ci.layout
        n = len(self.plots)
        margins = layout.getContentsMargins()
        spacing = max(0.0, layout.verticalSpacing()) * max(0, n - 1) + margins[1] + margins[3]
        return max(120, MIN_PANE_HEIGHT_PX * n + BOTTOM_AXIS_PX + math.ceil(spacing))

    @property
    def _axis_width(self) -> int:
        fm = QFontMetrics(self.graphics.font())
        return fm.horizontalAdvance("-8888.88") + fm.lineSpacing() + 16

    def _rebuild_plots(self) -> None:
        """One pane per unit of the selected signals, in the tree's order. Panes whose unit stays are kept (their
        curves added or removed, their colours renewed): building a pane costs ~25 ms of the GUI thread, and
        re-building all eleven when one box was ticked held it 0.3–0.5 s (#37: the GUI watch judges such stalls
        while the patient is driven)."""
        by_unit: dict[str, list[str]] = {}
        for key in self.selected:
            unit = self.store.info(key).unit or NO_UNIT
            by_unit.setdefault(unit, []).append(key)
        old_order = list(self.plots)
        kept = {unit: plot for unit, plot in self.plots.items() if unit in by_unit}
        for unit, plot in self.plots.items():
            if unit not in by_unit:
                self._drop_pane(unit, plot)
        # A kept pane whose row changes (another pane dropped above it, or a new one taking a row above it) is
        # laid out again: keeping only the kept panes' order put a new first pane over the kept one in row 0.
        new_rows = {unit: row for row, unit in enumerate(by_unit)}
        relayout = any(old_order.index(unit) != new_rows[unit] for unit in kept)
        if relayout:  # the kept panes change places: out of the layout, back in below in the new order
            for plot in kept.values():
                self.graphics.ci.removeItem(plot)
        self.plots = {}
        self._image_mode = False
        for row, (unit, keys) in enumerate(by_unit.items()):
            plot = kept.get(unit)
            if plot is None:
                plot = self._new_pane(unit, row)
            elif relayout:
                self.graphics.ci.addItem(plot, row=row, col=0)
            self.plots[unit] = plot
            self._sync_curves(unit, plot, keys)
        self._finish_panes()

    def _finish_panes(self) -> None:
        """What every pane needs once the set of panes is known: its x-axis linked to the first's, the time axis
        under the last only, the minimum heights, the curves drawn by the items until the renderer's next frame,
        then a frame."""
        units = list(self.plots)
        first = self._first_plot()
        for row, unit in enumerate(units):
            plot = self.plots[unit]
            plot.setXLink(None if plot is first else first)
            self._style_pane(plot, last=row == len(units) - 1)
        self._link_panes()

    def _style_pane(self, plot: pg.PlotItem, last: bool) -> None:
        """The time axis's values and label under the last pane only, and each pane's minimum height (not again
        when unchanged: a staged build styles a pane when it makes it, before the graphs are laid out)."""
        if self._styled.get(id(plot)) == last:
            return
        self._styled[id(plot)] = last
        self._style_time_axis(plot.getAxis("bottom"), last)
        plot.setMinimumHeight(_pane_min_height(last))

    def _style_time_axis(self, axis: pg.AxisItem, last: bool) -> None:
        """A pane's bottom axis: the time's values and label under the last pane only."""
        axis.setStyle(showValues=last)
        if last:
            axis.setLabel("time" if self.x_origin is None else "session time", "s")
        else:
            axis.showLabel(False)

    def _link_panes(self) -> None:
        """The rest of _finish_panes once the panes are linked and styled."""
        units = list(self.plots)
        first = self._first_plot()
        self.vlines = [self._vlines[unit] for unit in units]
        for image in self.images.values():
            image.setVisible(False)
            image.set_image(None)
        for curve in self.curves.values():
            curve.set_drawn_elsewhere(False)
        if first is not None:
            self._apply_x_range()
        # Each pane at least MIN_PANE_HEIGHT_PX (its rotated unit label and three ticks readable); the
        # scroll area around the panes, not the window, takes what does not fit (a 768 px screen).
        self.graphics.setMinimumHeight(self.panes_min_height())
        self._dirty = True
        self.redraw()

    @staticmethod
    def _pane_parts() -> tuple[LiveViewBox, dict[str, pg.AxisItem]]:
        """A pane's view and axes, made apart from it: a pane made on them costs half of one that makes them, so a
        staged build makes them a piece before (#37)."""
        return LiveViewBox(), {side: pg.AxisItem(side) for side in ("left", "bottom")}  # (top, right: hidden)

    @staticmethod
    def _bare_pane(parts: tuple[LiveViewBox, dict[str, pg.AxisItem]]) -> pg.PlotItem:
        """pyqtgraph's PlotItem on ``parts``, not styled yet (_new_pane): ~10 ms, most of it its options menu's
        widgets, which pyqtgraph builds in the constructor and keeps as the plot's state -- so a staged build makes
        it a piece of its own (#37)."""
        view, axes = parts
        return pg.PlotItem(viewBox=view, axisItems=axes)

    def _new_pane(self, unit: str, row: int | None,
                  parts: tuple[LiveViewBox, dict[str, pg.AxisItem]] | None = None,
                  plot: pg.PlotItem | None = None, last: bool | None = None) -> pg.PlotItem:
        """A pane for ``unit`` in ``row`` of the graphs (laid out at once), or apart from them (``row`` None: the
        caller adds it, see selection_steps); on ``parts`` (_pane_parts) or on ``plot`` (_bare_pane) when given.
        ``last``: the pane's place is known (the last or not) and its time axis styled already (_style_time_axis)."""
        c = colours()
        if plot is None:
            plot = self._bare_pane(parts if parts is not None else self._pane_parts())
        if row is not None:
            self._add_to_layout(plot, row, lay_out=True)
        plot.setMenuEnabled(False)
        plot.showGrid(x=True, y=True, alpha=c.grid_alpha)
        for axis in ("left", "bottom"):
            # Grid lines at major ticks only: the minor grid cost ~8 ms a frame (blended lines).
            plot.getAxis(axis).setStyle(maxTickLevel=0)
        if unit == NO_UNIT:
            plot.setLabel("left", unit)
        elif unit in SI_BASE_UNITS:
            plot.setLabel("left", units=unit)  # pyqtgraph adds SI prefixes (mm, kN/m)
        else:  # already prefixed (mA, µs) or not SI (bpm, %): as it is, never "pmA"
            plot.setLabel("left", f"({unit})")
        # Aligned time axes in every plot, wide enough for tick labels such as "-317.05" beside the
        # rotated unit label (issue #19: "(mm)" was overlapped by the ticks, also in PNGs).
        plot.getAxis("left").setWidth(self._axis_width)
        # SI prefixes only where the unit is an SI base unit: α (no unit) read "551 (×0.001)".
        plot.getAxis("left").enableAutoSIPrefix(unit in SI_BASE_UNITS)
        plot.setMinimumHeight(_pane_min_height(bool(last)))
        if last is not None:
            self._styled[id(plot)] = last
        plot.enableAutoRange(axis="y", enable=self.autoscale_box.isChecked())
        plot.enableAutoRange(axis="x", enable=False)
        plot.vb.sigRangeChangedManually.connect(self._on_manual_range)
        plot.vb.sigXRangeChanged.connect(self._mark_dirty)
        # A pane's image is drawn for its range and size: either changing needs a new one (static data too)
        plot.vb.sigYRangeChanged.connect(self._mark_dirty)
        plot.vb.sigResized.connect(self._mark_dirty)
        legend = plot.addLegend(offset=(4, 2), labelTextSize="8pt")
        legend.setBrush(pg.mkBrush(c.plot_background + "c0"))
        # The axes (with their grid, which spans the plot) and the legend lie under the curves, so
        # they were re-drawn, text and all, on every frame: drawn once into a pixmap instead, and
        # again only when they change (a new range, a resize).
        for item in (plot.getAxis("left"), plot.getAxis("bottom"), legend):
            item.setCacheMode(QGraphicsItem.CacheMode.DeviceCoordinateCache)
        vline = pg.InfiniteLine(angle=90, movable=False, pen=pg.mkPen(c.plot_foreground, width=1,
                                                                       style=Qt.PenStyle.DashLine))
        vline.setVisible(False)
        plot.addItem(vline, ignoreBounds=True)
        self._vlines[unit] = vline
        image = CurveImage(plot.vb)
        image.setVisible(False)
        self.images[unit] = image
        return plot

    def _add_to_layout(self, plot: pg.PlotItem, row: int, lay_out: bool) -> None:
        """``GraphicsLayout.addItem(plot, row, 0)``, which then lays out the whole layout at once (every pane resized,
        its axes re-labelled) -- unless ``lay_out`` is False: that waits for Qt's layout request, one for all the
        panes added in a turn."""
        ci = self.graphics.ci
        if lay_out:
            ci.addItem(plot, row=row, col=0)
            return
        layout = ci.layout
        layout.activate = lambda: None  # pyqtgraph's own bookkeeping of the cell, without its immediate layout
        try:
            ci.addItem(plot, row=row, col=0)
        finally:
            del layout.activate  # Qt's own again

    def _drop_pane(self, unit: str, plot: pg.PlotItem) -> None:
        for key in [k for k, p in self._curve_plot.items() if p is plot]:
            del self.curves[key], self._curve_plot[key]
        self._vlines.pop(unit, None)
        self.images.pop(unit, None)
        self._styled.pop(id(plot), None)
        self.graphics.ci.removeItem(plot)

    def _sync_curves(self, unit: str, plot: pg.PlotItem, keys: list[str]) -> None:
        """The pane's curves are exactly ``keys``, each in its colour (its place among the selected signals)."""
        legend = plot.legend
        for key in [k for k, p in self._curve_plot.items() if p is plot and k not in keys]:
            curve = self.curves.pop(key)
            del self._curve_plot[key]
            legend.removeItem(curve)
            plot.removeItem(curve)
        for key in keys:
            info = self.store.info(key)
            pen = pg.mkPen(curve_colour(self.selected.index(key)), width=1)
            pen.setCosmetic(True)
            curve = self.curves.get(key)
            if curve is None:
                self.curves[key] = self._new_curve(plot, key, self.selected.index(key))
                self._curve_plot[key] = plot
            else:
                name = f"{info.device}: {self.display_label(info)}"  # an FES channel's muscle may have changed
                if curve.pen.color() != pen.color() or curve.name() != name:
                    curve.set_pen(pen)
                    curve.opts["name"] = name
                    for sample, label in legend.items:
                        if getattr(sample, "item", None) is curve:
                            sample.update()
                            if label.text != name:
                                label.setText(name)

    def _new_curve(self, plot: pg.PlotItem, key: str, place: int) -> FastCurve:
        """``key``'s curve in ``plot`` and its legend, in the colour of its ``place`` among the selected signals."""
        info = self.store.info(key)
        pen = pg.mkPen(curve_colour(place), width=1)
        pen.setCosmetic(True)
        curve = FastCurve(pen, f"{info.device}: {self.display_label(info)}")
        plot.addItem(curve)
        plot.legend.addItem(curve, curve.name())
        for part in plot.legend.items[-1]:  # its sample line and its label: drawn once, blitted after (#37)
            part.setCacheMode(QGraphicsItem.CacheMode.DeviceCoordinateCache)
        # ... and the label's text, a child item of its own that the label's cache does not hold: laid out and
        # drawn again for every entry of the legends shown, in each frame's paint (#37)
        plot.legend.items[-1][1].item.setCacheMode(QGraphicsItem.CacheMode.DeviceCoordinateCache)
        return curve

    # ------------------------------------------------------------------ behaviour
    def _draw_store(self) -> SignalStore:
        return self._frozen if self.paused and self._frozen is not None else self.store

    def _mark_dirty(self, *_args: Any) -> None:
        self._dirty = True

    def _first_plot(self) -> pg.PlotItem | None:
        return next(iter(self.plots.values()), None)

    def _apply_x_range(self) -> None:
        plot = self._first_plot()
        if plot is not None:
            right = 0.0 if self.x_origin is None or self.t_ref is None else self.t_ref - self.x_origin
            plot.setXRange(right - self.history_s, right, padding=0)

    def visible_range(self) -> tuple[float, float] | None:
        """Absolute (monotonic) time range on screen, or None before any data."""
        plot = self._first_plot()
        if plot is None or self.t_ref is None:
            return None
        x0, x1 = plot.vb.viewRange()[0]
        return self._x0() + x0, self._x0() + x1

    def _x0(self) -> float:
        """The time of x = 0 (see ``x_origin``)."""
        assert self.t_ref is not None
        return self.t_ref if self.x_origin is None else self.x_origin

    def _tick(self) -> None:
        """The timer's slot: a frame only when it can be seen and something new is there to draw;
        then the interval adapts to the frame's cost (GRAPH_DUTY)."""
        if getattr(self, "_muscles_shown", None) is not None and self.manager is not None \
                and self._muscles() != self._muscles_shown:
            self._rebuild_tree()  # another FES profile: its muscles name the channels
            self._rebuild_plots()
        if not self.curves or not on_screen(self):
            return
        if not self.paused and not self._dirty and self.store.last_time() == self._drawn_t:
            return  # no new sample, nothing moved: the picture on screen is current
        self.redraw()
        self._adapt_interval()

    def _adapt_interval(self) -> None:
        if self.timer.interval() != self._interval_set:  # set from outside: the new fastest rate
            self._base_interval_ms = self._interval_set = self.timer.interval()
        # The paint measured is the previous frame's (it follows the drawing, asynchronously).
        cost = self.frame_times[-1] / 1000.0 + self.graphics.last_paint_s if self.frame_times else 0.0
        self.frame_cost_s = cost if self.frame_cost_s == 0.0 else 0.8 * self.frame_cost_s + 0.2 * cost
        wanted = int(1000.0 * max(self.frame_cost_s / GRAPH_DUTY,
                                  (self.renderer.render_cost_s / RENDER_DUTY) if self._image_mode else 0.0))
        # (Before #37 a frame also waited for the time axis to move by a pixel: 75 ms at 60 s over 800 px, so
        # the graphs showed a new value at most 13 times a second; they keep up at the display's rate now.)
        interval = min(MAX_INTERVAL_MS, max(self._base_interval_ms, wanted))
        if abs(interval - self.timer.interval()) > max(2, self.timer.interval() // 10):
            self.timer.setInterval(interval)
            self._interval_set = interval

    def showEvent(self, event: Any) -> None:
        super().showEvent(event)
        self._dirty = True  # catch up at the next tick on what was skipped while hidden

    def hideEvent(self, event: Any) -> None:
        super().hideEvent(event)
        self.renderer.park()  # a hidden frame draws nothing: its drawing thread need not wait for the next frame

    def redraw(self) -> None:
        """Draw the selected signals from the buffers (the timer calls this)."""
        if not self.curves:
            return
        t_start = time.perf_counter()
        store = self._draw_store()
        if not self.paused:
            now = self.store.last_time()
            if now is None:
                return
            self.t_ref = now
        elif not self._dirty:
            return
        if self.t_ref is None:
            return
        if self._follow_x and not self.paused:
            self._apply_x_range()
        rng = self.visible_range()
        if rng is None:
            return
        span = rng[1] - rng[0]
        t0, t1 = rng[0] - 0.02 * span, rng[1] + 0.02 * span  # a little beyond the edges: no gaps when panning
        first = self._first_plot()
        width_px = max(100, int(first.vb.width())) if first is not None else 100  # the panes share one width
        # Every signal reduced to the pixels at once, a stream's channels together (SignalStore.envelope_rows),
        # their bounds and gaps found per stream; each curve only copies its points (FastCurve); one repaint, or
        # (live) the points handed to the renderer's thread, which strokes them into each pane's image.
        images = self.render_off_thread and not self.paused and self._follow_x
        self._set_image_mode(images)
        keys = [k for k in self.curves if k in store]
        for key in self.curves.keys() - set(keys):
            self.curves[key].setData([], [])
        # Following the newest sample, a pane scrolled out of view is neither reduced nor drawn (scrolling marks the
        # graphs dirty: the next frame does it); a replay's panes (x = 0 its session's start) all hold their points.
        in_view = self._panes_in_view() if images else set()
        reduced = in_view if images and self.x_origin is None else {id(plot) for plot in self.plots.values()}
        keys = [k for k in keys if id(self._curve_plot[k]) in reduced]
        bounds = {id(plot): [math.inf, -math.inf] for plot in self.plots.values() if id(plot) in reduced}
        x_origin = self._x0()
        for stream_keys, t, rows, _pairs in store.envelope_rows(keys, t0, t1, max_points=2 * width_px):
            x = t - x_origin
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN row has no bounds
                lows, highs = np.fmin.reduce(rows, axis=1), np.fmax.reduce(rows, axis=1)
            complete = np.isfinite(rows).all(axis=1)
            for i, key in enumerate(stream_keys):
                lo, hi = float(lows[i]), float(highs[i])
                finite = math.isfinite(lo)
                self.curves[key].setData(x, rows[i], (lo, hi) if finite else None, bool(complete[i]),
                                         drawn_here=not images)
                if finite:
                    b = bounds[id(self._curve_plot[key])]
                    b[0], b[1] = min(b[0], lo), max(b[1], hi)
        for plot in self.plots.values():
            if isinstance(plot.vb, LiveViewBox) and id(plot) in bounds:
                lo, hi = bounds[id(plot)]
                y_bounds = (lo, hi) if lo <= hi else None
                if y_bounds != plot.vb.y_bounds:
                    plot.vb.y_bounds = y_bounds
                    plot.vb.updateAutoRange()  # the sticky range moves only when the data leave it
        if images:
            self._submit_frame(in_view)
        else:
            self.graphics.viewport().update()
        self._dirty = False
        self._drawn_t = self.t_ref
        self.frame_times.append(1000.0 * (time.perf_counter() - t_start))
        del self.frame_times[:-100]
        if self.cursor_x is not None:
            self._update_readout(self.cursor_x)

    def set_enlarge_offered(self, offered: bool) -> None:
        self.enlarge_button.setVisible(offered)

    def set_enlarged(self, enlarged: bool) -> None:
        """Show the button's state without asking again (the window changed the layout itself)."""
        self.enlarge_button.blockSignals(True)
        self.enlarge_button.setChecked(enlarged)
        self.enlarge_button.blockSignals(False)

    # ------------------------------------------------------------------ drawing off the GUI thread (#37)
    def _set_image_mode(self, on: bool) -> None:
        """Show the panes' rendered images (on) or their curve items (off)."""
        if on == self._image_mode:
            return
        self._image_mode = on
        for curve in self.curves.values():
            curve.set_drawn_elsewhere(on)
        for image in self.images.values():
            image.setVisible(on)
            if not on:
                image.set_image(None)
        if not on:
            self._dirty = True  # the curve items need their polygons: the next frame builds them

    def _panes_in_view(self) -> set[int]:
        """The panes (ids of their plots) the scroll area shows now (a pane scrolled into view is drawn by the next
        frame; the others cost the window's thread nothing: #37)."""
        seen = self.graphics.viewport().visibleRegion().boundingRect()
        return {id(plot) for plot in self.plots.values()
                if self.graphics.mapFromScene(plot.vb.sceneBoundingRect()).boundingRect().intersects(seen)}

    def _submit_frame(self, in_view: set[int]) -> None:
        """Hand the points of the panes in view to the renderer (each one's view transform computed here, from the
        view's range and size as pyqtgraph maps them)."""
        dpr = self.graphics.devicePixelRatioF()
        panes: list[PaneJob] = []
        by_plot: dict[int, PaneJob] = {}
        for unit, plot in self.plots.items():
            if id(plot) not in in_view:
                continue
            vb = plot.vb
            vb.prepareForPaint()  # a pending autorange now, not at the paint after the image is drawn
            w, h = float(vb.width()), float(vb.height())
            (x0, x1), (y0, y1) = vb.viewRange()
            if w < 2 or h < 2 or x1 <= x0 or y1 <= y0:
                continue
            transform = QTransform()
            transform.translate(w / 2, h / 2)
            transform.scale(w / (x1 - x0), -h / (y1 - y0))
            transform.translate(-(x0 + x1) / 2, -(y0 + y1) / 2)
            job = PaneJob(unit, math.ceil(w), math.ceil(h), dpr, transform)
            panes.append(job)
            by_plot[id(plot)] = job
        for key, curve in self.curves.items():
            job = by_plot.get(id(self._curve_plot[key]))
            x, y = curve.getData()
            if job is not None and curve.user_visible and len(x) > 1:
                job.curves.append((QPen(curve.pen), x, y, curve.finite))
        self._frame_seq += 1
        self.renderer.submit(self._frame_seq, panes)

    def _on_rendered(self, frame: int, images: dict[str, Any]) -> None:
        """A frame drawn by the renderer (GUI thread): each pane shows its image, unless a newer one is shown
        already or the panes are drawn here now."""
        if not self._image_mode or frame <= self._shown_seq:
            return
        self._shown_seq = frame
        for unit, image in images.items():
            item = self.images.get(unit)
            if item is not None:
                item.set_image(image)

    def set_paused(self, paused: bool) -> None:
        if paused == self.paused:
            return
        self.paused = paused
        if paused:
            self._frozen = self.store.frozen_copy(self.selected) if self.selected else None
        else:
            self._frozen = None
            self._follow_x = True
        self.pause_button.blockSignals(True)
        self.pause_button.setChecked(paused)
        self.pause_button.blockSignals(False)
        self.pause_button.setText("Resume" if paused else "Pause")
        self.status.setText("paused" if paused else "")
        self._dirty = True
        self.redraw()

    def toggle_pause(self) -> None:
        self.set_paused(not self.paused)

    def set_history(self, seconds: float) -> None:
        self.history_s = min(float(seconds), self.store.history_s)
        idx = self.history_box.findData(self.history_s)
        if idx >= 0 and idx != self.history_box.currentIndex():
            self.history_box.blockSignals(True)
            self.history_box.setCurrentIndex(idx)
            self.history_box.blockSignals(False)
        self._follow_x = True
        self._apply_x_range()
        self._dirty = True
        self.redraw()

    def step_history(self, direction: int) -> None:
        idx = max(0, min(self.history_box.count() - 1, self.history_box.currentIndex() + direction))
        self.history_box.setCurrentIndex(idx)

    def set_autoscale(self, on: bool) -> None:
        if self.autoscale_box.isChecked() != on:
            self.autoscale_box.setChecked(on)  # comes back here through `toggled`
            return
        for plot in self.plots.values():
            plot.enableAutoRange(axis="y", enable=on)

    def fit(self) -> None:
        """Autoscale the values and follow the live data again."""
        self.set_autoscale(True)
        for plot in self.plots.values():
            plot.enableAutoRange(axis="y", enable=True)
            if isinstance(plot.vb, LiveViewBox):
                plot.vb.snap_y = True  # close around the data now, whatever the range was
        self._follow_x = True
        self._apply_x_range()
        self._dirty = True
        self.redraw()

    def _on_manual_range(self, mask: Any) -> None:
        """Mouse zoom/pan on the time axis while live freezes the view there."""
        x_changed = bool(mask[0]) if isinstance(mask, list | tuple) and mask else True
        if x_changed:
            self._follow_x = False
            if not self.paused:
                self.set_paused(True)
        self._dirty = True

    def set_selected(self, keys: Sequence[str]) -> None:
        """Tick exactly ``keys`` in the tree (unknown ones are kept for when their device appears)."""
        self._tick_keys(keys)
        self._collect_selection()

    def _tick_keys(self, keys: Sequence[str]) -> None:
        available = {i.key for i in self.store.signals()}
        self._wanted = [k for k in keys if k not in available]
        wanted = set(keys)
        self._building_tree = True
        try:
            for item in self._leaf_items():
                state = Qt.CheckState.Checked if item.data(0, KEY_ROLE) in wanted else Qt.CheckState.Unchecked
                item.setCheckState(0, state)
        finally:
            self._building_tree = False

    def selection_steps(self, keys: Sequence[str]) -> Iterator[None]:
        """``set_selected(keys)`` a piece per ``next()``, for a caller that runs one piece per turn of the event
        loop (the replay window, opened during a therapy: #37). From a frame without panes: one pane (with its curves
        and legend) built per step, apart from the graphs; then one step puts them all in the graphs, which are laid
        out once, linked, styled and drawn. (Adding a pane to the graphs re-laid out and re-drew every pane already
        there: a turn per pane grew with the panes.) The graphs are not drawn until then. With panes shown already:
        ``set_selected`` in one step. A selection changed meanwhile (a box ticked) built the panes itself: the steps
        end."""
        if self.plots:
            self.set_selected(keys)
            return
        self.graphics.setUpdatesEnabled(False)  # (a paint between two steps drew every pane built so far)
        try:
            yield from self._build_panes(keys)
            yield  # laid out between this step and the next (Qt's layout request), drawn after the last
            for plot in list(self.plots.values()):  # the axes' pictures a pane per step, for the first paint
                for axis in (plot.getAxis("left"), plot.getAxis("bottom")):
                    # Its label placed again: the first screen's range, given after the layout, may have changed its
                    # text ("(m)" -> "(mm)"), which pyqtgraph centres only when the axis is resized.
                    axis.resizeEvent()
                    prepare_axis(axis)
                yield
        finally:
            self.graphics.setUpdatesEnabled(True)

    def _build_panes(self, keys: Sequence[str]) -> Iterator[None]:
        self._tick_keys(keys)
        selected = [it.data(0, KEY_ROLE) for it in self._leaf_items() if it.checkState(0) == Qt.CheckState.Checked]
        self.selected = list(selected)
        by_unit: dict[str, list[str]] = {}
        for key in selected:
            by_unit.setdefault(self.store.info(key).unit or NO_UNIT, []).append(key)
        built: dict[str, tuple[pg.PlotItem, dict[str, FastCurve]]] = {}
        last_unit = next(reversed(by_unit), None)
        for unit, unit_keys in by_unit.items():
            # A pane in three pieces: its view and axes; pyqtgraph's plot on them; its style, legend and curves (in
            # one piece: the pane lays itself out once after it, not once per piece).
            parts = self._pane_parts()
            self._style_time_axis(parts[1]["bottom"], last=unit == last_unit)  # styled before the pane lays it out
            yield
            if self._overtaken(selected, built):
                return
            bare = self._bare_pane(parts)
            yield
            if self._overtaken(selected, built):
                return
            plot = self._new_pane(unit, None, parts, bare, last=unit == last_unit)
            built[unit] = plot, {key: self._new_curve(plot, key, selected.index(key)) for key in unit_keys}
            yield
            if self._overtaken(selected, built):
                return
        self._image_mode = False
        for row, (unit, (plot, curves)) in enumerate(built.items()):
            self._add_to_layout(plot, row, lay_out=False)  # one layout for them all, at Qt's next turn
            self.plots[unit] = plot
            self.curves.update(curves)
            self._curve_plot.update(dict.fromkeys(curves, plot))
        self.graphics.setMinimumHeight(self.panes_min_height())  # (its final height before that layout)
        # Laid out alone in the turn after this step (every pane resized: the longest piece, it grows with the
        # panes); linked and given the first screen's range and data in the step after it.
        yield
        first = self._first_plot()
        for plot in self.plots.values():
            plot.setXLink(None if plot is first else first)
        self._link_panes()

    def _overtaken(self, selected: list[str], built: dict[str, Any]) -> bool:
        """The panes were built meanwhile (a box ticked while _build_panes ran): those it built are for nobody."""
        if not self.plots and self.selected == selected:
            return False
        for other in built:
            if other not in self.plots:
                self._vlines.pop(other, None)
                self.images.pop(other, None)
        return True

    # ------------------------------------------------------------------ cursor
    def _on_mouse_moved(self, pos: Any) -> None:
        for plot in self.plots.values():
            if plot.vb.sceneBoundingRect().contains(pos):
                self.set_cursor(plot.vb.mapSceneToView(pos).x())
                return

    def set_cursor(self, x: float | None) -> None:
        """Show the crosshair at ``x`` seconds (relative to the newest sample) and the values there."""
        self.cursor_x = x
        for line in self.vlines:
            line.setVisible(x is not None)
            if x is not None:
                line.setPos(x)
        if x is None:
            self.readout.setText(" ")
        else:
            self._update_readout(x)

    def _update_readout(self, x: float) -> None:
        if self.t_ref is None:
            return
        store = self._draw_store()
        parts = [f"<b>t = {x:+.3f} s</b>"]
        for key in self.selected:
            if key not in store:
                continue
            info = store.info(key)
            hit = store.value_at(key, self._x0() + x)
            value = "—" if hit is None else f"{hit[1]:.4g}"
            colour = curve_colour(self.selected.index(key))
            parts.append(f"<span style='color:{colour}'>■</span> {self.display_label(info)}: {value} {info.unit}"
                         .rstrip())
        self.readout.setText("  ".join(parts))

    def readout_text(self) -> str:
        return self.readout.text()

    # ------------------------------------------------------------------ keys
    def eventFilter(self, obj: QObject, event: QEvent) -> bool:
        if obj is self.graphics and event.type() == QEvent.Type.KeyPress:
            return self.handle_key(event)  # type: ignore[arg-type]
        return super().eventFilter(obj, event)

    def keyPressEvent(self, event: QKeyEvent) -> None:
        if not self.handle_key(event):
            super().keyPressEvent(event)

    def handle_key(self, event: QKeyEvent) -> bool:
        key = event.key()
        mods = event.modifiers() & ~Qt.KeyboardModifier.KeypadModifier
        K = Qt.Key
        ctrl = mods == Qt.KeyboardModifier.ControlModifier
        plain = mods in (Qt.KeyboardModifier.NoModifier, Qt.KeyboardModifier.ShiftModifier)
        if plain and key in (K.Key_Space, K.Key_P):
            self.toggle_pause()
        elif plain and key == K.Key_A:
            self.fit()
        elif plain and key == K.Key_Home:
            self.set_paused(False)
            self.fit()
        elif plain and key in (K.Key_Plus, K.Key_Equal):
            self.step_history(+1)
        elif plain and key == K.Key_Minus:
            self.step_history(-1)
        elif ctrl and key == K.Key_S:
            self._ask_save()
        elif ctrl and key == K.Key_E:
            self._ask_png()
        else:
            return False
        event.accept()
        return True

    # ------------------------------------------------------------------ saving
    def save_csv(self, path: str | Path, scope: str | None = None, layout: str | None = None) -> int:
        """Write the selected signals to ``path``: ``scope`` "visible" (the time range on screen) or
        "all" (everything buffered); default: the scope chosen in the frame. ``layout`` "per_stream" writes
        one file per stream beside ``path`` (``<stem>-<stream>.csv``). Returns the row count (summed)."""
        scope = scope or self.scope_box.currentData()
        layout = layout or self.layout_box.currentData()
        if not self.selected:
            raise ValueError("no signal selected")
        store = self._draw_store()
        t_from = t_to = None
        if scope == SCOPE_VISIBLE:
            rng = self.visible_range()
            if rng is not None:
                t_from, t_to = rng
        keys = [k for k in self.selected if k in store]
        zero_text = f"the start of session {self.session_name}" if self.session_name else ""
        groups: dict[str, list[str]] = {}
        for k in keys:
            groups.setdefault(store.info(k).stream, []).append(k)
        path = Path(path)
        if layout == LAYOUT_PER_STREAM and len(groups) > 1:
            rows, names = 0, []
            for stream, stream_keys in groups.items():
                target = path.with_name(f"{path.stem}-{stream}{path.suffix or '.csv'}")
                rows += store.export_csv(target, stream_keys, t_from, t_to, t_zero=self.session_t0,
                                         t_zero_text=zero_text)
                names.append(target.name)
            self.status.setText(f"saved {rows} rows in {len(names)} files ({', '.join(names)})")
        else:
            rows = store.export_csv(path, keys, t_from, t_to, t_zero=self.session_t0, t_zero_text=zero_text)
            mixed = " (streams of different rates: empty cells between a stream's samples)" if len(groups) > 1 else ""
            self.status.setText(f"saved {rows} rows to {path.name}{mixed}")
        log.info("plots: saved %d rows of %d signals to %s (%s)", rows, len(keys), path, layout)
        return rows

    def _on_session(self, folder: Path | None) -> None:
        if folder is None:
            self.session_t0, self.session_name = None, ""
        else:
            self.session_t0 = time.monotonic()
            self.session_name = f"{Path(folder).parent.name}/{Path(folder).name}"

    def default_file(self, suffix: str) -> Path:
        """``<patient>_<session>_<HHMMSS>.<suffix>`` in the session's folder, or ``signals_<date>_<time>``
        in the sessions folder without a session (issue #19: always "signals.csv")."""
        stamp = time.strftime("%H%M%S")
        recorder = getattr(self.manager, "recorder", None)
        if recorder is not None:
            folder = Path(recorder.folder)
            return folder / f"{folder.parent.name}_{folder.name}_{stamp}.{suffix}"
        return sessions_dir() / f"signals_{time.strftime('%Y%m%d')}_{stamp}.{suffix}"

    def export_title(self) -> str:
        """The PNG's title: patient/session, date and time, and what each graph shows in which unit."""
        who = self.session_name or "no session"
        units = " · ".join(f"{unit}: " + ", ".join(self.display_label(self.store.info(k)) for k in keys)
                           for unit, keys in self._keys_by_unit().items())
        return f"{who} · {time.strftime('%Y-%m-%d %H:%M:%S')} · {units}"

    def _keys_by_unit(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {}
        for key in self.selected:
            if key in self.store:
                out.setdefault(self.store.info(key).unit or NO_UNIT, []).append(key)
        return out

    def export_png(self, path: str | Path, width: int = 1200, scale: float = 1.5) -> bool:
        """The graphs laid out ``width`` logical pixels wide (each graph at least 220 high), drawn at
        ``scale`` × (crisp text and lines; 1800 px wide by default) under a title line with the
        patient/session, the date and the units -- not a grab of the small on-screen frame."""
        view = self.graphics
        old_size = view.size()
        was_images = self._image_mode
        if was_images:  # drawn here, at the picture's size, by the curve items
            self._set_image_mode(False)
            self.render_off_thread = False
            self.redraw()
        height = max(old_size.height(), 320, 220 * len(self.plots))
        font = QFont(self.font())
        title_h = int(QFontMetrics(font).lineSpacing() * 2)
        image = QImage(int(width * scale), int((height + title_h) * scale), QImage.Format.Format_RGB32)
        image.setDevicePixelRatio(scale)
        image.fill(QColor(colours().plot_background))
        painter = QPainter(image)
        try:
            view.resize(width, height)  # lays the scene out at the export size (no repaint in between)
            painter.setRenderHint(QPainter.RenderHint.Antialiasing)
            painter.setRenderHint(QPainter.RenderHint.TextAntialiasing)
            painter.setFont(font)
            painter.setPen(QColor(colours().plot_foreground))
            text = QFontMetrics(font).elidedText(self.export_title(), Qt.TextElideMode.ElideRight, width - 20)
            painter.drawText(QRectF(10, 0, width - 20, title_h),
                             int(Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignVCenter), text)
            view.scene().render(painter, QRectF(0, title_h, width, height),
                                view.mapToScene(view.viewport().rect()).boundingRect())
        finally:
            painter.end()
            view.resize(old_size)
            if was_images:
                self.render_off_thread = True
                self._dirty = True
        ok = image.save(str(path))
        self.status.setText(f"exported {Path(path).name}" if ok else "export failed")
        return ok

    def _ask_save(self) -> None:
        if not self.selected:
            self.status.setText("tick at least one signal to save")
            return
        path, _ = QFileDialog.getSaveFileName(self, "Save signals", str(self.default_file("csv")),
                                              "CSV files (*.csv)")
        if path:
            try:
                self.save_csv(path)
            except OSError as exc:
                self.status.setText(f"could not save: {exc.strerror or exc}")

    def _ask_png(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Export graphs", str(self.default_file("png")),
                                              "PNG images (*.png)")
        if path:
            self.export_png(path)

    # ------------------------------------------------------------------ settings
    def save_settings(self, settings: QSettings) -> None:
        settings.setValue("plots/selected", json.dumps(self.selected + self._wanted))
        settings.setValue("plots/history_s", self.history_s)
        settings.setValue("plots/autoscale", "1" if self.autoscale_box.isChecked() else "0")
        settings.setValue("plots/save_scope", self.scope_box.currentData())
        settings.setValue("plots/save_layout", self.layout_box.currentData())
        settings.setValue("plots/splitter", self.splitter.saveState())

    def _restore_settings(self) -> None:
        settings = QSettings()
        raw = settings.value("plots/selected")
        try:
            selected = json.loads(raw) if isinstance(raw, str) else None
        except ValueError:
            selected = None
        self._wanted = [str(k) for k in selected] if isinstance(selected, list) else list(DEFAULT_SIGNALS)
        try:
            history = float(settings.value("plots/history_s", self.history_s))
        except (TypeError, ValueError):
            history = self.history_s
        self.history_s = min(history, self.store.history_s)
        idx = self.history_box.findData(self.history_s)
        self.history_box.blockSignals(True)
        self.history_box.setCurrentIndex(idx if idx >= 0 else self.history_box.count() - 1)
        self.history_box.blockSignals(False)
        self.history_s = float(self.history_box.currentData())
        self.autoscale_box.setChecked(str(settings.value("plots/autoscale", "1")) != "0")
        scope_idx = self.scope_box.findData(settings.value("plots/save_scope", SCOPE_VISIBLE))
        self.scope_box.setCurrentIndex(max(0, scope_idx))
        self.layout_box.setCurrentIndex(max(0, self.layout_box.findData(
            settings.value("plots/save_layout", LAYOUT_ONE_TABLE))))
        state = settings.value("plots/splitter")
        if state is not None:
            self.splitter.restoreState(state)
