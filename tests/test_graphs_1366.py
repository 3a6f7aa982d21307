"""Six chosen graphs readable at 1366×768 (issue #37; #36 found 1.5 readable panes beside the Commands frame): the
Graphs frame's "Larger" gives them the whole right column, every pane keeps a readable height, none scrolls out of
view; the window is rendered and saved (docs/screenshots/graphs-six-1366.png with LINARMPP_SCREENSHOTS=1)."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QSettings, Qt
from PySide6.QtWidgets import QMessageBox

from app.core.bus import Channel, SampleBatch, StreamSpec
from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow
from app.ui.signal_store import shared_store
from tests.conftest import screenshot_path

SIX = StreamSpec("demo.main", (Channel("position", "m", "Handle position"), Channel("force", "N", "Interaction force"),
                               Channel("speed", "m/s", "Handle velocity"), Channel("hr", "bpm", "Heart rate"),
                               Channel("current", "mA", "1 current"), Channel("alpha", "", "α")), 100.0)
READABLE_PX = 70  # a pane's plot area: its rotated unit and three tick labels (MIN_PANE_HEIGHT_PX less margins)


def test_six_graphs_are_readable_at_1366x768(qtbot, monkeypatch) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    QSettings().remove("plots")
    window = MainWindow(manager)
    qtbot.addWidget(window)
    try:
        window.setWindowState(Qt.WindowState.WindowNoState)
        window.resize(1366, 768)
        window.show()
        window._reset_layout(short=True)  # the first-run layout of a 768-pixel screen
        plots = window.frames["PlotsFrame"]
        store = shared_store(manager, window.qt_bus)
        store.add_stream(SIX, "demo")
        t = np.arange(0.0, 20.0, 0.01)
        store.feed({SIX.name: SampleBatch(SIX, t, {c.name: np.sin(t * (i + 1)) * (i + 1)
                                                   for i, c in enumerate(SIX.channels)})})
        plots.set_selected([f"{SIX.name}.{c.name}" for c in SIX.channels])
        assert len(plots.plots) == 6
        qtbot.wait(300)
        assert plots.enlarge_button.isVisible()
        plots.enlarge_button.click()
        qtbot.waitUntil(lambda: not window.docks["CommandsFrame"].isVisible(), timeout=2000)
        qtbot.wait(500)
        heights = {unit: plot.vb.height() for unit, plot in plots.plots.items()}
        assert min(heights.values()) >= READABLE_PX, heights
        assert plots.graphs_scroll.verticalScrollBar().maximum() == 0, "a pane is out of view"
        image = window.grab()
        assert (image.width(), image.height()) == (1366, 768)
        image.save(str(screenshot_path("graphs-six-1366.png")))
        window.show_tab("Exercises")  # a command tab brings the Commands frame back, and the button says so
        qtbot.waitUntil(lambda: window.docks["CommandsFrame"].isVisible(), timeout=2000)
        assert not plots.enlarge_button.isChecked()
    finally:
        monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
        window.close()
        manager.shutdown()
