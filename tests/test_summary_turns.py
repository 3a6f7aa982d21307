"""Issue #37, acceptance 1 (a run's summary): a run's tab, built a piece per turn of the event loop when it is first
shown, lays out and draws each of its plots once it is complete -- not again for every plot added after it.

Before this test, each plot took the place of a placeholder whose size hint was not the plot's: every plot added
re-laid out the grid, so the plots before it were resized and drawn again in the same turn (two or three plots drawn in
one turn, 8-12 ms each), and a plot was drawn with its frame only, then again with each curve. Layouts and paints are
counted here (not times: the turns' lengths are the bench's, bench/bench_heavy_work.py), so the test holds on a busy
machine."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import pyqtgraph as pg
from PySide6.QtCore import QEvent, QObject

from app.session.recording import load_session
from app.session.reports import run_reports
from app.ui.session_summary import SUMMARY_PLOTS, SessionSummary
from tests.long_session import write_long_session

SESSION_S = 120.0  # two runs with repetitions (tests/long_session.py); the tab's pieces do not depend on the length


class _Watch(QObject):
    """Counts each summary plot's resizes, and the paints of a plot whose curves are not all there yet."""

    def __init__(self) -> None:
        super().__init__()
        self.resized: Counter[str] = Counter()
        self.painted: Counter[str] = Counter()
        self.painted_incomplete: list[str] = []
        self.expected: dict[str, int] = {}  # plot title -> its curves once complete

    def eventFilter(self, obj: Any, event: QEvent) -> bool:
        if event.type() == QEvent.Type.Resize and isinstance(obj, pg.PlotWidget):
            self.resized[_title(obj)] += 1
        elif event.type() == QEvent.Type.Paint and isinstance(obj.parent(), pg.PlotWidget):
            plot = obj.parent()
            self.painted[_title(plot)] += 1
            if len(plot.getPlotItem().listDataItems()) < self.expected.get(_title(plot), 0):
                self.painted_incomplete.append(_title(plot))
        return False


def _title(plot: pg.PlotWidget) -> str:
    return plot.getPlotItem().titleLabel.text


def test_a_run_tab_lays_out_and_draws_each_plot_once_complete(qtbot: Any, tmp_path: Path) -> None:
    from PySide6.QtWidgets import QApplication

    reports = run_reports(load_session(write_long_session(tmp_path, seconds=SESSION_S)))
    assert len(reports) >= 2 and reports[0].repetitions
    summary = SessionSummary(reports, "a session", None, staged=True)
    qtbot.addWidget(summary)
    summary.resize(900, 700)
    summary.show()
    qtbot.waitUntil(lambda: summary.is_ready, timeout=10000)
    watch = _Watch()
    reps = reports[0].repetitions
    for title, keys, unit in SUMMARY_PLOTS:
        shown = title + (f" [{unit}]" if unit else "")
        watch.expected[shown] = sum(1 for key, _ in keys if any(r.get(key) is not None for r in reps))
    app = QApplication.instance()
    app.installEventFilter(watch)
    try:
        summary.tabs.setCurrentIndex(1)  # the first run's tab: built now, a piece per turn
        qtbot.waitUntil(lambda: summary.is_ready, timeout=20000)
        qtbot.wait(200)  # the last plot's paint
    finally:
        app.removeEventFilter(watch)
    view = summary.run_views[reports[0].run.run_id]
    assert len(view.plots) == len(SUMMARY_PLOTS)
    print(f"\nresized {dict(watch.resized)}; painted {dict(watch.painted)}")
    assert watch.resized and max(watch.resized.values()) == 1, \
        f"while the run's tab was built, its plots were laid out {dict(watch.resized)} times"
    assert not watch.painted_incomplete, \
        f"plots drawn before their curves were all there: {Counter(watch.painted_incomplete)}"
    assert set(watch.painted) == set(watch.expected)  # every plot drawn (the tab is tall enough to show them)
