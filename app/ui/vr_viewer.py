"""The VR renderer viewer (D2.2 §3.4): link state, packet rates, target and handle on the rail, score.

``VrViewer(manager)`` reads, on a timer, the latest "vr.main" sample on the bus (through the Qt bus adapter)
and the counters of ``manager.driver("vr")``; ``show_sample(sample)`` displays one sample without a driver (tests).
"""

from __future__ import annotations

import math
from typing import Any

from PySide6.QtCore import QPointF, QRectF, QTimer
from PySide6.QtGui import QColor, QPainter, QPaintEvent, QPen
from PySide6.QtWidgets import QFormLayout, QLabel, QVBoxLayout, QWidget

from app.core import streams
from app.ui.qt_bus import QtBus, qt_bus_for
from app.ui.theme import colours
from app.ui.widgets import RefreshWhenVisible
from app.wire.udp_frames import TaskState

RAIL_M = 0.5


class RailView(QWidget):
    """The rail from above: target zone and handle."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setMinimumSize(300, 60)
        self.target = math.nan
        self.handle = math.nan
        self.tolerance = 0.01
        self.reached = False

    def set_state(self, target: float, handle: float, reached: bool) -> None:
        self.target, self.handle, self.reached = target, handle, reached
        self.update()

    def paintEvent(self, event: QPaintEvent) -> None:
        c = colours()
        p = QPainter(self)
        p.setRenderHint(QPainter.RenderHint.Antialiasing)
        margin, y = 14.0, self.height() / 2.0
        width = self.width() - 2 * margin

        def x_of(pos: float) -> float:
            return margin + width * min(1.0, max(0.0, pos / RAIL_M))

        p.setPen(QPen(QColor(c.idle), 3))
        p.drawLine(QPointF(margin, y), QPointF(margin + width, y))
        if math.isfinite(self.target):
            half = max(3.0, width * self.tolerance / RAIL_M)
            p.fillRect(QRectF(x_of(self.target) - half, y - 16, 2 * half, 32),
                       QColor(c.ok if self.reached else c.warn))
        if math.isfinite(self.handle):
            p.setBrush(QColor(c.curves[0]))
            p.setPen(QPen(QColor(c.text), 1))
            p.drawEllipse(QPointF(x_of(self.handle), y), 7, 7)
        p.end()


class VrViewer(RefreshWhenVisible, QWidget):
    def __init__(self, manager: Any = None, driver: Any = None, refresh_hz: float = 10.0,
                 parent: QWidget | None = None, *, qt_bus: QtBus | None = None) -> None:
        """Live from ``qt_bus`` (the window's; with a manager and none, the viewer's own) with the link's
        counters from ``driver`` (the manager's VR driver); :meth:`show_sample` by hand without them."""
        super().__init__(parent)
        self.setWindowTitle("VR renderer")
        self.driver = driver if driver is not None else (manager.driver(streams.VR) if manager else None)
        self.qt_bus = qt_bus_for(manager, qt_bus, self) if manager is not None or qt_bus is not None else None
        self.fields: dict[str, QLabel] = {}
        form = QFormLayout()
        for key, label in (("link", "Link"), ("rates", "Packets"), ("dropped", "Dropped"),
                           ("target", "Target"), ("handle", "Handle"), ("subtask", "Sub-task"),
                           ("score", "Score"), ("targets", "Targets"), ("event", "Last event")):
            self.fields[key] = QLabel("–")
            form.addRow(f"{label}:", self.fields[key])
        self.rail = RailView()
        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addWidget(self.rail, 1)
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._tick)
        self.timer.start(int(1000 / refresh_hz))


    def refresh(self) -> None:
        d, qt_bus = self.driver, self.qt_bus
        if d is None or qt_bus is None:
            return
        connected = qt_bus.connected(streams.VR)
        self.fields["link"].setText("connected" if connected else "not connected (no events from the renderer)")
        self.fields["rates"].setText(f"{getattr(d, 'packet_rate_out', 0.0):.0f} frames/s out, "
                                     f"{getattr(d, 'packet_rate_in', 0.0):.1f} events/s in")
        self.fields["dropped"].setText(f"{getattr(d, 'dropped_total', 0)}")
        sample = qt_bus.latest(streams.VR_MAIN)
        if sample is not None:
            self.show_sample(sample)

    def show_sample(self, s: Any) -> None:
        state = getattr(s, "taskState", 0)
        try:
            state_name = TaskState(state).name.lower()
        except ValueError:
            state_name = str(state)
        self.fields["target"].setText(f"{s.targetPos * 1000:.0f} mm" if math.isfinite(s.targetPos) else "–")
        handle = getattr(s, "handlePos", math.nan)
        self.fields["handle"].setText(f"{handle * 1000:.0f} mm" if math.isfinite(handle) else "–")
        self.fields["subtask"].setText(f"{getattr(s, 'subTask', 0)} ({state_name})")
        self.fields["score"].setText(f"{s.score:.0f}")
        self.fields["targets"].setText(f"{s.targetsReached:.0f} reached, {getattr(s, 'targetsMissed', 0)} missed")
        ttt = getattr(s, "timeToTarget", math.nan)
        event = getattr(s, "lastEvent", "") or "–"
        self.fields["event"].setText(event + (f" (last reach {ttt:.2f} s)" if math.isfinite(ttt) else ""))
        self.rail.set_state(s.targetPos, handle, state == TaskState.REACHED)
