"""Drawing the live graphs' curves off the GUI thread (issue #37).

Stroking a curve is what costs: a noisy signal reduced to two points per pixel column is a zig-zag of a few
thousand segments, 0.3–10 ms each on the raster engine, and 49 of them in the window's paint held the GUI thread
(and the e-stop button and F12 it reads) for tens of ms. Here the GUI thread only reduces the samples to the
pixels (numpy, ~1 ms for every signal) and hands each pane's points to a :class:`CurveRenderer`: a thread of its
own draws them into one transparent image per pane with QPainter (which releases the interpreter lock while it
draws), and the pane shows that image (:class:`CurveImage`: its paint is one blit).

The renderer works on one frame at a time: a frame submitted while it draws replaces the one waiting (the newest
data wins, nothing queues up). Its thread starts with the first frame and ends after ``IDLE_EXIT_S`` without one.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QObject, QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QImage, QPainter, QPen, QTransform
from PySide6.QtWidgets import QGraphicsObject

log = logging.getLogger(__name__)

IDLE_EXIT_S = 1.0


@dataclass
class PaneJob:
    """One pane's curves: the image's size in logical pixels, its device pixel ratio, the transform from the
    pane's view coordinates (seconds, the unit) to the image's logical pixels, and each curve's pen and points."""

    key: Any
    width: int
    height: int
    dpr: float
    transform: QTransform
    curves: list[tuple[QPen, np.ndarray, np.ndarray, bool]] = field(default_factory=list)  # pen, x, y, no NaN


def render_pane(job: PaneJob) -> QImage:
    """The pane's curves drawn into a transparent image (any thread)."""
    image = QImage(max(1, round(job.width * job.dpr)), max(1, round(job.height * job.dpr)),
                   QImage.Format.Format_ARGB32_Premultiplied)
    image.setDevicePixelRatio(job.dpr)
    image.fill(Qt.GlobalColor.transparent)
    painter = QPainter(image)
    try:
        painter.setTransform(job.transform)
        for pen, x, y, finite in job.curves:
            if len(x) < 2:
                continue
            painter.setPen(pen)
            if finite:
                # The zig-zag through the (minimum, maximum) pairs, as a polygon filled from numpy in microseconds:
                # stroking it (C++, the interpreter lock released) costs more than a path of one line per pixel
                # column, but building that path held the lock 1.3 ms a curve, and the lock is what the e-stop's
                # paths and the window's thread wait for (measured: docs/decisions.md, #37).
                painter.drawPolyline(pg.functions.arrayToQPolygonF(x, y))
            else:  # a NaN lifts the pen
                painter.drawPath(pg.functions.arrayToQPath(x, y, connect="finite"))
    finally:
        painter.end()
    return image


class CurveImage(QGraphicsObject):
    """A pane's rendered curves, shown over its view box (a child of the ViewBox, in its pixel coordinates)."""

    def __init__(self, parent: Any) -> None:
        super().__init__(parent)
        self.setZValue(1000)  # over the view's own items (grid, cursor line); the axes are outside the view box
        self.setAcceptedMouseButtons(Qt.MouseButton.NoButton)
        self.image: QImage | None = None
        self._rect = QRectF()

    def set_image(self, image: QImage | None) -> None:
        rect = QRectF() if image is None else QRectF(0, 0, image.width() / image.devicePixelRatio(),
                                                     image.height() / image.devicePixelRatio())
        if rect != self._rect:
            self.prepareGeometryChange()
            self._rect = rect
        self.image = image
        self.update()

    def boundingRect(self) -> QRectF:
        return QRectF(self._rect)

    def paint(self, painter: QPainter, *_args: Any) -> None:
        if self.image is not None:
            painter.drawImage(QPointF(0, 0), self.image)


class CurveRenderer(QObject):
    """Draws submitted frames on a thread of its own; ``rendered(frame, {pane key: image})`` comes back queued to
    the thread the renderer lives on (the GUI thread)."""

    rendered = Signal(object, object)

    def __init__(self, parent: QObject | None = None, idle_exit_s: float = IDLE_EXIT_S) -> None:
        super().__init__(parent)
        self.idle_exit_s = idle_exit_s
        self._cond = threading.Condition()
        self._job: tuple[int, list[PaneJob]] | None = None
        self._thread: threading.Thread | None = None
        self._closed = False
        self._park = False  # end the thread now if nothing waits (the frame was hidden), not after idle_exit_s
        self.frames = 0  # frames drawn
        self.render_cost_s = 0.0  # smoothed CPU time to draw a frame (the frame rate adapts to it)

    @property
    def running(self) -> bool:
        thread = self._thread
        return thread is not None and thread.is_alive()

    def submit(self, frame: int, panes: list[PaneJob]) -> None:
        """Draw ``panes`` (replacing a frame still waiting); never blocks."""
        with self._cond:
            if self._closed:
                return
            self._job = (frame, panes)
            self._park = False
            self._cond.notify()
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="plot-render", daemon=True)
                self._thread.start()

    def _run(self) -> None:
        while True:
            with self._cond:
                if self._job is None and not self._closed and not self._park:
                    self._cond.wait(self.idle_exit_s)
                job, self._job = self._job, None
                if job is None or self._closed:
                    self._thread = None
                    self._park = False
                    return
            frame, panes = job
            t0 = time.thread_time()  # its share of a core (RENDER_DUTY), not the time others took it away
            try:
                images = {pane.key: render_pane(pane) for pane in panes}
            except Exception:  # a bad frame must not end the renderer
                log.exception("plots: a frame could not be drawn")
                continue
            cost = time.thread_time() - t0
            self.render_cost_s = cost if not self.frames else 0.8 * self.render_cost_s + 0.2 * cost
            self.frames += 1
            try:
                self.rendered.emit(frame, images)
            except RuntimeError:  # the frame (and this object) is being destroyed
                return

    def park(self) -> None:
        """The drawing thread ends as soon as it has nothing to draw (the frame is hidden: a window closed, a
        tab changed), rather than idling ``idle_exit_s`` first; the next frame submitted starts it again."""
        with self._cond:
            self._park = True
            self._cond.notify()

    def close(self, timeout_s: float = 1.0) -> None:
        with self._cond:
            self._closed = True
            self._job = None
            self._cond.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
