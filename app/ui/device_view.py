"""Frame 3 — a simplified picture of LINarm2 moving with the live state: the rail, the two motor
carriages, the springs from each carriage to the handle (zig-zag lines), the handle, and the
current exercise target.

On a real X server (Qt platform ``xcb``) this is a ``pyqtgraph.opengl`` 3D scene with mouse
camera control, drawn in a native child window of its own (a ``QOpenGLWindow`` in a window container),
not a ``QOpenGLWidget``: a QOpenGLWidget makes Qt compose the whole top-level window through OpenGL on
every repaint of any widget in it (the graphs at 30 Hz), which with software GL (Mesa llvmpipe) cost
~25 % of a core with the 3D scene unchanged. The scene is re-rendered only when something in it moves
by a visible amount (``GL_STEP_M``) or the camera moves, at most 20 times a second.
Anywhere else (``offscreen``, Wayland without GLX, ...) it is a 2D QPainter side view of the same scene:
a GL widget must never even be constructed there, because offscreen GL crashes the process uncatchably (qt-stack.md §2).

Positions come from the bus's latest samples (``QtBus.latest``) at the UI refresh rate: motors from
``linarm.motor0`` and ``linarm.motor1``, the handle from ``linarm.vsa``; the target from ``set_target()`` when set,
otherwise from the VR renderer's ``vr.main`` targetPos.
"""

from __future__ import annotations

import atexit
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import shiboken6
from PySide6.QtCore import QPoint, QPointF, QRectF, QSizeF, Qt, QTimer
from PySide6.QtGui import QColor, QFont, QGuiApplication, QPainter, QPainterPath, QPen
from PySide6.QtWidgets import QLabel, QSizePolicy, QVBoxLayout, QWidget

from app.core import streams
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.theme import colours
from app.ui.values_frame import format_value  # no "-0.000 m"
from app.ui.widgets import RefreshWhenVisible

log = logging.getLogger(__name__)

CARRIAGE_LEN_M = 0.04
HANDLE_RADIUS_M = 0.012
SPRING_COILS = 8
RAIL_MARGIN_M = 0.03
CANVAS_MARGIN_PX = 24.0
MAX_REFRESH_HZ = 20.0  # the picture follows the arm's motion smoothly to the eye; each render costs CPU
GL_STEP_M = 0.0005  # the 3D scene spans ~0.7 m over a few hundred pixels: 0.5 mm is about a pixel


@dataclass
class SceneState:
    """What the picture shows; None = unknown (drawn greyed at a default place)."""

    motor0: float | None = None
    motor1: float | None = None
    handle: float | None = None
    target: float | None = None
    connected: bool = False


def _attr(sample: Any, name: str) -> float | None:
    value = getattr(sample, name, None)
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def spring_points(x0: float, x1: float, amplitude: float, coils: int = SPRING_COILS,
                  lead: float = 0.15) -> np.ndarray:
    """A zig-zag from x0 to x1 as (n, 2) points (x, offset): straight leads at both ends, then
    ``coils`` teeth of ±amplitude; compresses and stretches with the distance."""
    length = x1 - x0
    a = x0 + length * lead
    b = x1 - length * lead
    teeth = 2 * coils
    xs = [x0, a]
    ys = [0.0, 0.0]
    for i in range(teeth):
        xs.append(a + (b - a) * (i + 0.5) / teeth)
        ys.append(amplitude if i % 2 == 0 else -amplitude)
    xs += [b, x1]
    ys += [0.0, 0.0]
    return np.column_stack((xs, ys))


class DeviceView(RefreshWhenVisible, QWidget):
    def __init__(self, manager: LinarmppManager, *, allow_gl: bool = True, qt_bus: QtBus | None = None) -> None:
        """``allow_gl=False`` draws the 2D scene even where OpenGL works (no GPU driver, tests). The live state
        comes through ``qt_bus`` (the window's; else the view's own)."""
        super().__init__()
        self.manager = manager
        self.qt_bus = qt_bus_for(manager, qt_bus, self)
        limits = manager.config.safety.robot
        self.rail = (min(0.0, limits.position_min_m - RAIL_MARGIN_M), limits.position_max_m + RAIL_MARGIN_M)
        self.state = SceneState()
        self._api_target: float | None = None
        self._api_target_set = False
        self.gl_view: Any = None
        self.gl_container: QWidget | None = None
        self.canvas: RobotCanvas | None = None

        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(2)
        if allow_gl and QGuiApplication.platformName() == "xcb":
            try:
                self._gl = GlScene(self.rail)
                self.gl_view = self._gl.view
                self.gl_container = QWidget.createWindowContainer(self.gl_view, self)
                self.gl_container.setMinimumSize(240, 160)
                self.gl_container.setAccessibleName("LINarm 3D view")
                _GL_CONTAINERS[:] = [b for b in _GL_CONTAINERS if shiboken6.isValid(b)] + [self.gl_container]
                lay.addWidget(self.gl_container, 1)
            except Exception:  # PyOpenGL missing or GL failing to initialise: the 2D view still works
                log.exception("3D view unavailable; using the 2D drawing")
                self.gl_view = None
        if self.gl_view is None:
            self.canvas = RobotCanvas(self.rail)
            lay.addWidget(self.canvas, 1)
        self.caption = QLabel()
        self.caption.setAlignment(Qt.AlignmentFlag.AlignCenter)
        lay.addWidget(self.caption)

        self.timer = QTimer(self)
        self.timer.setInterval(int(1000 / max(1.0, min(MAX_REFRESH_HZ, manager.config.ui.refresh_hz))))
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        self.refresh()

    # ------------------------------------------------------------------ API
    def set_target(self, pos_m: float | None) -> None:
        """Show an exercise target at ``pos_m`` (m); None returns to the VR renderer's target."""
        self._api_target = pos_m
        self._api_target_set = pos_m is not None
        self.refresh()

    # ------------------------------------------------------------------ live state
    def _latest(self, stream: str) -> Any:
        if not self.qt_bus.connected(streams.device_of(stream)):
            return None
        return self.qt_bus.latest(stream)

    def read_state(self) -> SceneState:
        vsa = self._latest(streams.LINARM_VSA)
        m0 = _attr(self._latest(streams.LINARM_MOTOR0), "position")
        m1 = _attr(self._latest(streams.LINARM_MOTOR1), "position")
        handle = _attr(vsa, "handlePos")
        if vsa is not None and (m0 is None or m1 is None):
            centre, delta = _attr(vsa, "equilibriumPos"), _attr(vsa, "delta")
            if centre is not None and delta is not None:  # motors not streamed: place them from the VSA
                m0 = centre - abs(delta) - 0.05 if m0 is None else m0
                m1 = centre + abs(delta) + 0.05 if m1 is None else m1
        linarm = self.manager.devices.get(streams.LINARM)
        target = self._api_target if self._api_target_set else self._exercise_target(linarm)
        connected = linarm is not None and self.qt_bus.connected(streams.LINARM)
        return SceneState(m0, m1, handle, target, connected)


    def _exercise_target(self, linarm: Any) -> float | None:
        """The target to show: while an exercise runs, where the robot is taking the handle (its last
        moveCentreTo); otherwise the VR game's target. The VR game's 0.1/0.4 m was shown during an exercise
        moving between 0.15 and 0.35 m (issue #30)."""
        runs = getattr(self.manager, "runs", None)
        running = runs is not None and runs.current() is not None
        robot_target = getattr(linarm.driver, "centre_target_m", None) if linarm is not None else None
        if running and robot_target is not None:
            return float(robot_target)
        return _attr(self._latest(streams.VR_MAIN), "targetPos")

    def refresh(self) -> None:
        state = self.read_state()
        self.state = state
        if self.canvas is not None:
            self.canvas.set_state(state)
        elif self.gl_view is not None:
            self._gl.set_state(state)
        parts = []
        if state.handle is not None:
            parts.append(f"handle {format_value(state.handle, 3)} m")
        if state.target is not None:
            parts.append(f"target {format_value(state.target, 3)} m")
        if not state.connected:
            parts.insert(0, "robot not connected")
        text = "  ·  ".join(parts) or "no robot data"
        if text != self.caption.text():
            self.caption.setText(text)

    def paint_native_views(self, painter: QPainter, top: QWidget) -> None:
        """Paint the 3D scene where its native window shows in ``top`` (for ``top.grab()``)."""
        box = self.gl_container
        if box is None or not box.isVisible() or box.visibleRegion().isEmpty():
            return
        painter.drawImage(QRectF(box.mapTo(top, QPoint(0, 0)), QSizeF(box.size())), self.render_image())

    def render_image(self) -> Any:
        """The current picture as a QImage (the GL framebuffer, or the 2D drawing)."""
        if self.gl_view is not None:
            return self._gl.grab()
        assert self.canvas is not None
        return self.canvas.grab().toImage()


def _defaults(state: SceneState, rail: tuple[float, float]) -> tuple[float, float, float, bool]:
    """Positions to draw (unknown ones at rest around the rail's middle) and whether they are live."""
    mid = (rail[0] + rail[1]) / 2
    live = state.motor0 is not None and state.motor1 is not None and state.handle is not None
    m0 = state.motor0 if state.motor0 is not None else mid - 0.12
    m1 = state.motor1 if state.motor1 is not None else mid + 0.12
    h = state.handle if state.handle is not None else (m0 + m1) / 2
    return m0, m1, h, live


class RobotCanvas(QWidget):
    """The 2D side view: rail with a scale, carriages, zig-zag springs, handle and target."""

    def __init__(self, rail: tuple[float, float]) -> None:
        super().__init__()
        self.rail = rail
        self.state = SceneState()
        self._drawn: tuple[Any, ...] | None = None
        self.setMinimumSize(240, 120)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.setAccessibleName("LINarm picture")

    def set_state(self, state: SceneState) -> None:
        self.state = state
        # Repaint only when something moves by half a pixel or more: the handle creeps by fractions of
        # a millimetre between refreshes, and a repaint that changes no pixel is pure GUI-thread time.
        drawn = self._drawn_key(state)
        if drawn != self._drawn:
            self._drawn = drawn
            self.update()

    def _drawn_key(self, state: SceneState) -> tuple[Any, ...]:
        lo, hi = self.rail
        px_per_m = max(1.0, self.width() - 2 * CANVAS_MARGIN_PX) / (hi - lo)

        def px(v: float | None) -> int | None:
            return None if v is None else round(2.0 * v * px_per_m)

        return (px(state.motor0), px(state.motor1), px(state.handle), px(state.target), state.connected,
                self.width(), self.height())

    def paintEvent(self, _event: Any) -> None:
        c = colours()
        dark = c.name == "dark"
        p = QPainter(self)
        p.setRenderHint(QPainter.RenderHint.Antialiasing)
        w, h = self.width(), self.height()
        p.fillRect(self.rect(), QColor("#20242a" if dark else "#f4f6f8"))
        margin = CANVAS_MARGIN_PX
        lo, hi = self.rail
        scale = (w - 2 * margin) / (hi - lo)

        def X(m: float) -> float:
            return margin + (m - lo) * scale

        y_rail = h * 0.62
        unit = max(6.0, min(h * 0.09, 0.02 * scale))  # drawing size of ~2 cm, bounded by the height
        m0, m1, hx, live = _defaults(self.state, self.rail)
        ink = QColor(c.text if dark else "#37474f")
        faded = 255 if live else 90

        # Rail and scale (every 5 cm, labelled every 10 cm).
        p.setPen(Qt.PenStyle.NoPen)
        p.setBrush(QColor("#78909c"))
        p.drawRoundedRect(QRectF(X(lo), y_rail, X(hi) - X(lo), unit * 0.6), 3, 3)
        p.setPen(QPen(ink, 1))
        font = QFont(self.font())
        font.setPointSize(8)
        p.setFont(font)
        tick = math.ceil(lo / 0.05) * 0.05
        while tick <= hi + 1e-9:
            x = X(tick)
            major = abs(round(tick / 0.1) * 0.1 - tick) < 1e-6
            p.drawLine(QPointF(x, y_rail + unit * 0.6), QPointF(x, y_rail + unit * (1.2 if major else 0.9)))
            if major:
                p.drawText(QRectF(x - 20, y_rail + unit * 1.2, 40, 14), Qt.AlignmentFlag.AlignCenter, f"{tick:.1f} m")
            tick += 0.05

        # Target: a dashed vertical line with a flag.
        if self.state.target is not None:
            tx = X(self.state.target)
            green = QColor(c.ok)
            pen = QPen(green, 2, Qt.PenStyle.DashLine)
            p.setPen(pen)
            p.drawLine(QPointF(tx, y_rail - unit * 5.5), QPointF(tx, y_rail + unit * 0.6))
            flag = QPainterPath(QPointF(tx, y_rail - unit * 5.5))
            flag.lineTo(tx + unit * 1.6, y_rail - unit * 4.9)
            flag.lineTo(tx, y_rail - unit * 4.3)
            flag.closeSubpath()
            p.fillPath(flag, green)
            p.drawText(QRectF(tx - 40, y_rail - unit * 7.2, 80, unit * 1.5), Qt.AlignmentFlag.AlignCenter, "target")

        # Springs between carriages and handle.
        y_spring = y_rail - unit * 1.2
        spring_pen = QPen(QColor(120, 120, 120, faded) if not dark else QColor(200, 200, 200, faded), 1.6)
        p.setPen(spring_pen)
        half_c = CARRIAGE_LEN_M / 2 * scale
        r_handle = max(unit * 0.9, HANDLE_RADIUS_M * scale)
        for x0, x1 in ((X(m0) + half_c, X(hx) - r_handle), (X(hx) + r_handle, X(m1) - half_c)):
            if x1 - x0 < 2:
                continue
            pts = spring_points(x0, x1, unit * 0.6)
            path = QPainterPath(QPointF(pts[0, 0], y_spring + pts[0, 1]))
            for px, py in pts[1:]:
                path.lineTo(px, y_spring + py)
            p.drawPath(path)

        # Motor carriages.
        blue = QColor("#1565c0")
        blue.setAlpha(faded)
        for name, mx in (("M0", m0), ("M1", m1)):
            rect = QRectF(X(mx) - half_c, y_rail - unit * 2.4, 2 * half_c, unit * 2.4)
            p.setPen(QPen(QColor("#0d47a1"), 1))
            p.setBrush(blue)
            p.drawRoundedRect(rect, 3, 3)
            p.setPen(QColor("white"))
            p.drawText(rect, Qt.AlignmentFlag.AlignCenter, name)

        # Handle: a carriage with an upright grip.
        orange = QColor("#ef6c00")
        orange.setAlpha(faded)
        p.setPen(QPen(QColor("#8d3b00"), 1))
        p.setBrush(orange)
        p.drawRoundedRect(QRectF(X(hx) - r_handle, y_rail - unit * 1.9, 2 * r_handle, unit * 1.9), 3, 3)
        p.drawRoundedRect(QRectF(X(hx) - r_handle * 0.45, y_rail - unit * 4.4, r_handle * 0.9, unit * 2.6),
                          r_handle * 0.4, r_handle * 0.4)

        if not live:
            p.setPen(ink)
            font.setPointSize(11)
            p.setFont(font)
            p.drawText(QRectF(0, 4, w, 20), Qt.AlignmentFlag.AlignCenter, "no robot data")
        p.end()


_GL_WINDOW_CLASS: Any = None
_GL_CONTAINERS: list[QWidget] = []  # see _delete_gl_containers


def _delete_gl_containers() -> None:
    """At exit, before PySide's own clean-up: delete the windows that still hold a 3D view (Qt then
    deletes each container and its GL window, in order). PySide does not know that a container owns its
    window: its clean-up would delete the Python-created GL window first and leave a container of a
    window still alive with a dangling pointer, a segfault when the application object goes."""
    for box in _GL_CONTAINERS:
        if shiboken6.isValid(box):
            top = box.window()
            shiboken6.delete(top if shiboken6.isValid(top) else box)


atexit.register(_delete_gl_containers)  # registered after PySide's (imported above): runs before it


_GL_SHARE_CONTEXT: Any = None


def _share_context() -> Any:
    """The context every 3D view shares its GL objects with: Qt's global one when the application asked
    for it (app.application.prepare_qt), else one of our own (never made current on a surface)."""
    global _GL_SHARE_CONTEXT
    from PySide6.QtGui import QOpenGLContext

    if QOpenGLContext.globalShareContext() is not None:
        return QOpenGLContext.globalShareContext()
    if _GL_SHARE_CONTEXT is None:
        context = QOpenGLContext()
        if not context.create():
            raise RuntimeError("cannot create an OpenGL context")
        _GL_SHARE_CONTEXT = context
    return _GL_SHARE_CONTEXT


def gl_window_class() -> Any:
    """pyqtgraph's 3D view on a ``QOpenGLWindow`` (built once, on first use: importing pyqtgraph.opengl
    needs PyOpenGL, and only xcb gets here)."""
    global _GL_WINDOW_CLASS
    if _GL_WINDOW_CLASS is None:
        from pyqtgraph.opengl.GLViewWidget import GLViewMixin
        from PySide6.QtOpenGL import QOpenGLWindow

        class GlWindow(GLViewMixin, QOpenGLWindow):  # type: ignore[misc]
            """A native GL window rendering on its own: the widgets around it stay raster."""

            def __init__(self) -> None:
                # All the 3D views share one context group: pyqtgraph compiles its shader programs once
                # per process and keeps their ids, which a second view's own context would not know
                # (seen as 'invalid value' from glUseProgram in a second window of bench_window).
                super().__init__(_share_context())
                self.frames = 0  # scenes rendered (tests, benchmarks)

            def paintGL(self) -> None:
                self.frames += 1
                super().paintGL()

        _GL_WINDOW_CLASS = GlWindow
    return _GL_WINDOW_CLASS


def _moved(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return (a is None) != (b is None)
    return abs(a - b) >= GL_STEP_M


class GlScene:
    """The 3D scene (built only on xcb): meshes moved by translation every refresh."""

    def __init__(self, rail: tuple[float, float]) -> None:
        import pyqtgraph.opengl as gl
        from pyqtgraph import Vector

        self.gl = gl
        self.rail = rail
        self._alpha = 1.0
        lo, hi = rail
        mid = (lo + hi) / 2
        self._drawn: SceneState | None = None
        # Renders this scene asked for (tests, benchmarks); the window's ``frames`` also counts the paints the
        # window system asks for (an expose), which are not the scene's choice.
        self.renders_requested = 0
        view = gl_window_class()()
        view.setBackgroundColor(QColor("#20242a") if colours().name == "dark" else QColor("#e9edf1"))
        view.setCameraPosition(pos=Vector(mid, 0, 0.02), distance=0.6, elevation=28, azimuth=-65)
        self.view = view

        grid = gl.GLGridItem()
        grid.setSize(x=hi - lo + 0.2, y=0.3)
        grid.setSpacing(x=0.05, y=0.05)
        grid.translate(mid, 0, -0.02)
        view.addItem(grid)

        self.rail_item = self._box((hi - lo, 0.03, 0.02), (0.47, 0.56, 0.61, 1.0))
        self.rail_item.translate(mid, 0, -0.01)
        view.addItem(self.rail_item)
        self.motor_items = [self._box((CARRIAGE_LEN_M, 0.06, 0.05), (0.08, 0.4, 0.75, 1.0)) for _ in range(2)]
        self.handle_item = self._box((0.03, 0.05, 0.03), (0.94, 0.42, 0.0, 1.0))
        grip = gl.MeshData.cylinder(rows=1, cols=16, radius=[0.012, 0.012], length=0.09)
        self.grip_item = gl.GLMeshItem(meshdata=grip, smooth=True, color=(0.94, 0.42, 0.0, 1.0), shader="shaded")
        self.target_item = self._box((0.006, 0.12, 0.16), (0.18, 0.49, 0.2, 0.55), translucent=True)
        self.springs = [gl.GLLinePlotItem(width=2.0, color=(0.35, 0.35, 0.35, 1.0), antialias=True)
                        for _ in range(2)]
        for item in (*self.motor_items, self.handle_item, self.grip_item, self.target_item, *self.springs):
            view.addItem(item)

    def _box(self, size: tuple[float, float, float], colour: tuple[float, ...], translucent: bool = False) -> Any:
        """A box with flat per-face shading (top brightest), which reads better than the 'shaded'
        shader, whose fixed light leaves top faces dark."""
        sx, sy, sz = (s / 2 for s in size)
        verts = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
        faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                          [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        mesh = self.gl.MeshData(vertexes=verts, faces=faces)
        item = self.gl.GLMeshItem(meshdata=mesh, smooth=False, shader=None, drawEdges=False,
                                  glOptions="translucent" if translucent else "opaque")
        item.base_colour = tuple(colour)
        self._colour_box(item, colour[3] if len(colour) > 3 else 1.0)
        return item

    @staticmethod
    def _colour_box(item: Any, alpha: float) -> None:
        r, g, b = item.base_colour[:3]
        # Face pairs in _box order: -x, +x, -y, +y, -z, +z.
        shade = np.repeat([0.7, 0.7, 0.85, 0.6, 0.5, 1.0], 2)
        colours_ = np.column_stack((np.clip(shade * r * 1.1, 0, 1), np.clip(shade * g * 1.1, 0, 1),
                                    np.clip(shade * b * 1.1, 0, 1), np.full(12, alpha)))
        item.opts["meshdata"].setFaceColors(colours_)
        item.meshDataChanged()

    @staticmethod
    def _place(item: Any, x: float, y: float, z: float) -> None:
        item.resetTransform()
        item.translate(x, y, z)

    def grab(self) -> Any:
        """The rendered scene as a QImage."""
        return self.view.grabFramebuffer()

    def set_state(self, state: SceneState) -> None:
        """Move the meshes and render, only when something moved by ``GL_STEP_M`` or more since the last
        render (the state is noisy by micrometres; a render that changes no pixel is wasted CPU)."""
        last = self._drawn
        if last is not None and last.connected == state.connected and not any(
                _moved(getattr(state, k), getattr(last, k)) for k in ("motor0", "motor1", "handle", "target")):
            return
        self._drawn = state
        m0, m1, hx, live = _defaults(state, self.rail)
        self._place(self.motor_items[0], m0, 0, 0.025)
        self._place(self.motor_items[1], m1, 0, 0.025)
        self._place(self.handle_item, hx, 0, 0.015)
        self._place(self.grip_item, hx, 0, 0.03)
        alpha = 1.0 if live else 0.35
        if alpha != self._alpha:  # recolouring rebuilds the mesh buffers: only on change
            self._alpha = alpha
            for item in (*self.motor_items, self.handle_item):
                self._colour_box(item, alpha)
            self.grip_item.setColor((0.94, 0.42, 0.0, alpha))
        for spring, (x0, x1) in zip(self.springs, ((m0 + CARRIAGE_LEN_M / 2, hx - 0.015),
                                                   (hx + 0.015, m1 - CARRIAGE_LEN_M / 2)), strict=True):
            pts = spring_points(x0, x1, 0.012) if x1 > x0 else np.array([[x0, 0.0], [x1, 0.0]])
            pos = np.column_stack((pts[:, 0], np.zeros(len(pts)), 0.03 + pts[:, 1]))
            spring.setData(pos=pos)
        if state.target is not None:
            self._place(self.target_item, state.target, 0, 0.08)
            self.target_item.setVisible(True)
        else:
            self.target_item.setVisible(False)
        self.renders_requested += 1
        self.view.update()

