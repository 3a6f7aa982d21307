"""The VR stand-in's window (app.devices.sim.vr_standin): the rail seen from above, the target zone and the handle.

    python -m app.ui.vr_standin_window --listen HOST:PORT --peer HOST:PORT [the stand-in's other options]

The stand-in itself is Qt-free (the simulators must not load Qt); this module adds the window around it.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from app.devices.sim.patient_model.process import ParentWatch
from app.devices.sim.vr_standin import StandinGame, StandinLink
from app.devices.sim.vr_standin import main as standin_main
from app.wire.udp_frames import TaskState


def run_window(link: StandinLink, idle_exit_s: float, watch: ParentWatch) -> int:
    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    app = QApplication.instance() or QApplication(sys.argv[:1])
    win = make_window(link.game)
    win.show()

    def poll() -> None:
        for _ in range(20):  # drain what is queued without blocking the event loop
            link.receive(0.0)
        win.update()
        if watch.parent_gone() or (idle_exit_s > 0 and time.monotonic() - link.last_frame_t > idle_exit_s):
            app.quit()

    timer = QTimer()
    timer.timeout.connect(poll)
    timer.start(10)
    return app.exec()


def _window_class() -> type:
    from PySide6.QtCore import QRectF, Qt
    from PySide6.QtGui import QColor, QFont, QPainter, QPen
    from PySide6.QtWidgets import QWidget

    class _StandinWindow(QWidget):
        """The rail seen from above: target zone (green when reached), handle (blue), score."""

        RAIL_M = 0.5

        def __init__(self, game: StandinGame) -> None:
            super().__init__()
            self.game = game
            self.setWindowTitle("LINarm++ VR stand-in")
            self.resize(520, 160)

        def paintEvent(self, event: object) -> None:
            g = self.game
            p = QPainter(self)
            p.setRenderHint(QPainter.RenderHint.Antialiasing)
            p.fillRect(self.rect(), QColor("#1d2733"))
            margin = 30.0
            width = self.width() - 2 * margin
            y = self.height() * 0.6

            def x_of(pos: float) -> float:
                return margin + width * min(1.0, max(0.0, pos / self.RAIL_M))

            p.setPen(QPen(QColor("#8a9bb0"), 4))
            p.drawLine(int(margin), int(y), int(margin + width), int(y))
            f = g.last_frame
            if f is not None and math.isfinite(f.targetPosition):
                reached = f.task.taskState == TaskState.REACHED
                colour = QColor("#3cb371" if reached else "#f0a030")
                half = max(4.0, width * g.tolerance_m / self.RAIL_M)
                xt = x_of(f.targetPosition)
                p.fillRect(QRectF(xt - half, y - 25, 2 * half, 50), colour)
            if f is not None and math.isfinite(f.robotPosition):
                p.setBrush(QColor("#4aa3ff"))
                p.setPen(Qt.PenStyle.NoPen)
                p.drawEllipse(QRectF(x_of(f.robotPosition) - 10, y - 10, 20, 20))
            p.setPen(QColor("white"))
            p.setFont(QFont(p.font().family(), 12))
            sub = "-" if g.subTask is None else str(g.subTask)
            p.drawText(int(margin), 28, f"Score {g.score}    targets {g.reached} reached, {g.missed} missed"
                                        f"    sub-task {sub}")
            p.end()

    return _StandinWindow


def make_window(game: StandinGame) -> Any:
    """The stand-in's window (a QWidget).  Qt is imported only here: the headless process never loads it."""
    return _window_class()(game)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if "--window" not in args:
        args.append("--window")
    return standin_main(args, run_window=run_window)


if __name__ == "__main__":
    sys.exit(main())
