"""The whole application on its default configuration: every simulated device (the LINarm, the
physiological board, the RehaStim on ptys; the patient model and the VR stand-in as processes on
loopback UDP) connects, the status bar says so, and closing leaves no thread and no process behind."""

from __future__ import annotations

import time

from PySide6.QtCore import QThread
from PySide6.QtWidgets import QApplication

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow


def test_every_simulated_device_connects_and_closing_leaves_nothing_running(qtbot) -> None:
    manager = LinarmppManager(AppConfig())
    manager.start()
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    assert set(manager.devices) == {"linarm", "physio", "fes", "patient_model", "vr"}
    qtbot.waitUntil(manager.all_connected, timeout=15000)
    qtbot.waitUntil(lambda: all(" connected" in label.text() for label in window.device_status.values()),
                    timeout=3000)
    processes = [p for h in manager.devices.values() for p in h.extras.get("processes", [])]
    # the patient model's and the VR stand-in's helpers, and the FES dead man's switch (app/devices/fes_guardian.py)
    assert len(processes) == 3 and all(p.poll() is None for p in processes)
    drivers = [h.driver for h in manager.devices.values()]
    window.close()
    t0 = time.monotonic()
    manager.shutdown(timeout_s=1.0)
    assert time.monotonic() - t0 < 1.0, "closing with every device running takes under a second"
    assert not any(d.isRunning() for d in drivers)
    assert not [t for t in QApplication.instance().findChildren(QThread) if t.isRunning()]
    qtbot.waitUntil(lambda: all(p.poll() is not None for p in processes), timeout=2000)
    assert all(not h.simulator.running for h in manager.devices.values() if h.simulator is not None)
