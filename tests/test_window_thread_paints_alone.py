"""The window's thread paints by itself: Qt's raster engine must not hand its fills to helper threads and wait.

On a busy 2-core machine the window, raised above everything else, waited on a latch for Qt's GUI thread pool
(helpers not raised, competing with every other process): a graph's repaint held it 0.4-0.9 s and the GUI watch
stopped the robot (CI on a clean clone, the firmware building beside the clinician's day). The application and
the suite call ``app.application.prepare_qt`` before their QApplication exists; this checks, in a process of its
own (the suite's QApplication already exists), that after it a large antialiased fill and a smooth image scale
start no pool thread."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PAINT = r"""
import json, os, sys
from app.application import prepare_qt
if sys.argv[1] == "prepared":
    prepare_qt()
from PySide6.QtCore import QRectF, Qt
from PySide6.QtGui import QColor, QImage, QLinearGradient, QPainter
from PySide6.QtWidgets import QApplication
app = QApplication(["paint"])
image = QImage(1600, 1000, QImage.Format.Format_ARGB32_Premultiplied)
painter = QPainter(image)
painter.setRenderHint(QPainter.RenderHint.Antialiasing)
gradient = QLinearGradient(0, 0, 1600, 1000)
gradient.setColorAt(0, QColor("red"))
gradient.setColorAt(1, QColor("blue"))
painter.fillRect(QRectF(0, 0, 1600, 1000), gradient)
small = image.scaled(800, 500, Qt.AspectRatioMode.IgnoreAspectRatio, Qt.TransformationMode.SmoothTransformation)
painter.drawImage(QRectF(0, 0, 1600, 1000), small)
painter.end()
print(json.dumps([open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]))
"""


def _threads_after_painting(mode: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "QT_NO_GUI_THREADPOOL"}
    env["QT_QPA_PLATFORM"] = "offscreen"
    out = subprocess.run([sys.executable, "-c", PAINT, mode], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=60, check=True).stdout
    return list(json.loads(out.strip().splitlines()[-1]))


def test_after_prepare_qt_no_paint_waits_for_a_helper_thread() -> None:
    # The control: without it, Qt starts its pool for this very paint (else the check below proves nothing).
    assert "Thread (pooled)" in _threads_after_painting("plain")
    threads = _threads_after_painting("prepared")
    assert "Thread (pooled)" not in threads, threads
