"""No clipped text anywhere (issue #19): the real window with every device simulated and a session
running is walked at 1366×768 and 1920×1080 -- every Commands tab (and the Robot panel's own tabs),
the dialogs and the side windows -- and every label, button, check box, group title, tab, header and
item-view cell must have the room its text needs (an elided label only with its whole text in the
tooltip). Runs offscreen and under Xvfb alike."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QApplication, QGraphicsView, QGraphicsWidget, QMessageBox, QTabWidget, QWidget

from app.core.config import AppConfig
from app.core.fes_profile import load_profile
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow
from tests.clipping import clipped_texts, squashed_data_widgets

ROOT = Path(__file__).resolve().parent.parent
SIZES = ((1366, 768), (1920, 1080))


STEADY_MS = 40  # the layout has settled when no visible widget moved, resized, showed or hid over this long


def _layout() -> list[tuple[int, bool, tuple[float, ...]]]:
    """Where every widget of every shown top-level window is (and whether it is visible), and every layout item
    of the graphics scenes they show (the graphs' panes)."""
    out: list[tuple[int, bool, tuple[float, ...]]] = []
    for top in QApplication.topLevelWidgets():
        if not top.isVisible():
            continue
        for w in [top, *top.findChildren(QWidget)]:
            out.append((id(w), w.isVisible(), w.geometry().getRect()))
            if isinstance(w, QGraphicsView) and w.isVisible() and w.scene() is not None:
                out += [(id(i), i.isVisible(), i.geometry().getRect()) for i in w.scene().items()
                        if isinstance(i, QGraphicsWidget)]
    return out


def settle(qtbot, ms: int = 150) -> None:
    """Until the layouts have settled — nothing moved, resized, showed or hid over STEADY_MS — and at most ``ms``
    (what was a fixed wait: 98 waits, ~17 s of the module's ~29, mostly on a layout that had long settled)."""
    import time

    deadline = time.monotonic() + ms / 1000
    QApplication.processEvents()
    before = _layout()
    while time.monotonic() < deadline:
        qtbot.wait(min(STEADY_MS, max(1, int((deadline - time.monotonic()) * 1000))))
        now = _layout()
        if now == before:
            break
        before = now
    QApplication.processEvents()


@pytest.fixture(scope="module")
def running_window(qapp) -> Iterator[tuple[LinarmppManager, MainWindow]]:
    import time

    manager = LinarmppManager(AppConfig())
    manager.start()
    window = MainWindow(manager)
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.show()
    deadline = time.monotonic() + 20
    while not manager.all_connected() and time.monotonic() < deadline:
        QApplication.processEvents()
        time.sleep(0.02)
    import tempfile

    manager.start_session("P001", "Dr Francesca Bianchi", root=Path(tempfile.mkdtemp()))
    manager.driver("fes").load_profile(load_profile(ROOT / "resources" / "fes_profiles" / "frontal_reaching.yaml"))
    manager.supervisor.raise_alarm(
        __import__("app.safety.supervisor", fromlist=["AlarmLevel"]).AlarmLevel.STOP, "linarm",
        "LINarm error: WATCHDOG (no host bytes for 0.25 s) — the motors are off")
    yield manager, window
    QMessageBox.question = lambda *a, **k: QMessageBox.StandardButton.Yes  # type: ignore[method-assign]
    window.close()
    manager.shutdown()


def tab_walk(window: MainWindow) -> Iterator[str]:
    """Shows each Commands tab (and each inner tab of a tabbed panel) in turn; yields its name."""
    tabs: QTabWidget = window.frames["CommandsFrame"].tabs
    for i in range(tabs.count()):
        tabs.setCurrentIndex(i)
        name = tabs.tabText(i)
        inner = tabs.widget(i).findChildren(QTabWidget)
        if inner:
            for sub in inner:
                for j in range(sub.count()):
                    sub.setCurrentIndex(j)
                    yield f"{name} › {sub.tabText(j)}"
        else:
            yield name


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_no_text_is_clipped_in_the_main_window(running_window, qtbot, size) -> None:
    _manager, window = running_window
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.resize(*size)
    window._reset_layout(short=size[1] < 900)  # the first-run layout of a screen of this size
    settle(qtbot, 400)
    assert (window.width(), window.height()) == size
    problems: dict[str, list[str]] = {}
    for where in tab_walk(window):
        settle(qtbot)
        checked = [0]
        found = clipped_texts(window, checked)
        assert checked[0] > 40, f"{where}: only {checked[0]} widgets seen"
        if found:
            problems[where] = found
    report = "\n".join(f"[{where}] {p}" for where, ps in problems.items() for p in ps)
    assert not problems, f"clipped at {size}:\n{report}"


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_no_data_widget_is_squashed(running_window, qtbot, size) -> None:
    """Issue #30: every table, tree and graph on every tab shows at least its minimum useful size (three rows
    or all it has; a graph pane MIN_PANE_HEIGHT_PX), and the FES table shows every channel of the profile."""
    manager, window = running_window
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.resize(*size)
    window._reset_layout(short=size[1] < 900)
    plots = window.frames["PlotsFrame"]
    plots.set_selected(SIX_SIGNALS)
    settle(qtbot, 400)
    assert (window.width(), window.height()) == size
    problems: dict[str, list[str]] = {}
    checked = [0]
    for where in tab_walk(window):
        settle(qtbot)
        found = squashed_data_widgets(window, checked)
        if found:
            problems[where] = found
        if where == "FES":
            fes = window.frames["CommandsFrame"].panels["FesPanel"]
            channels = len(manager.driver("fes").profile.channels)
            assert fes.table.rowCount() == channels == 4
            shown = fes.table.viewport().visibleRegion().boundingRect().height()
            need = sum(fes.table.rowHeight(r) for r in range(channels))
            assert shown >= need, f"FES table shows {shown} px of the {need} px its {channels} channels need"
    assert checked[0] > 12, f"only {checked[0]} data widgets seen"
    report = "\n".join(f"[{where}] {p}" for where, ps in problems.items() for p in ps)
    assert not problems, f"squashed at {size}:\n{report}"


# Six signals of six units (m, N, bpm, mA, µs, none): each unit gets a pane of its own, readable (issue #30).
SIX_SIGNALS = ["linarm.vsa.handlePos", "linarm.vsa.interactionForce", "physio.main.heartRate",
               "fes.channels.current1", "fes.channels.pulseWidth1", "patient_model.main.alpha"]


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_each_ticked_signal_gets_a_readable_pane(running_window, qtbot, size) -> None:
    """Ticking signal after signal in the tree: every pane keeps its minimum height (the area scrolls instead),
    the unit labels of neighbouring panes never overlap, and α reads in its own unit (no "×0.001")."""
    from app.ui.plots_frame import MIN_PANE_HEIGHT_PX

    _manager, window = running_window
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.resize(*size)
    window._reset_layout(short=size[1] < 900)
    plots = window.frames["PlotsFrame"]
    plots.set_selected([])
    settle(qtbot, 200)
    leaves = {it.data(0, Qt.ItemDataRole.UserRole): it for it in plots._leaf_items()}
    for n, key in enumerate(SIX_SIGNALS, 1):
        assert key in leaves, f"{key} not in the signal tree"
        leaves[key].setCheckState(0, Qt.CheckState.Checked)
        settle(qtbot, 150)
        assert key in plots.selected
        heights = {unit: plot.size().height() for unit, plot in plots.plots.items()}
        assert all(h >= MIN_PANE_HEIGHT_PX - 1 for h in heights.values()), f"after {n} signals: {heights}"
        labels = [plot.getAxis("left").label.mapRectToScene(plot.getAxis("left").label.boundingRect())
                  for plot in plots.plots.values()]
        for a, b in itertools.pairwise(labels):
            assert not a.intersects(b), f"after {n} signals the unit labels overlap: {a} {b}"
    assert len(plots.plots) == 6
    alpha_axis = next(p for u, p in plots.plots.items() if u == "(no unit)").getAxis("left")
    assert "0.001" not in alpha_axis.labelString() and alpha_axis.autoSIPrefixScale == 1.0
    # Scrolled to its end, the last pane is whole on screen.
    bar = plots.graphs_scroll.verticalScrollBar()
    bar.setValue(bar.maximum())
    settle(qtbot)
    last = list(plots.plots.values())[-1]
    rect = last.mapRectToScene(last.boundingRect())
    viewport = plots.graphs_scroll.viewport()
    top = plots.graphics.mapTo(viewport, plots.graphics.mapFromScene(rect.topLeft()))
    bottom = plots.graphics.mapTo(viewport, plots.graphics.mapFromScene(rect.bottomLeft()))
    assert 0 <= top.y() and bottom.y() <= viewport.height() + 2, (top, bottom, viewport.height())
    plots.set_selected([])


def fully_shown(w: QWidget) -> bool:
    return w.isVisible() and w.visibleRegion().boundingRect().size() == w.size()


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_primary_controls_are_on_screen_without_scrolling(running_window, qtbot, size) -> None:
    """Each Commands tab's primary controls are whole on screen in the first-run layout."""
    _manager, window = running_window
    window.setWindowState(Qt.WindowState.WindowNoState)
    window.resize(*size)
    window._reset_layout(short=size[1] < 900)
    settle(qtbot, 300)
    commands = window.frames["CommandsFrame"]
    robot, fes = commands.panels["LinarmPanel"], commands.panels["FesPanel"]
    console = commands.panels["ScriptConsole"]
    primary = {
        "Robot": [robot.home_button, robot.reset_button, *robot.state_buttons.values()],
        "FES": [fes.start_button, fes.stop_button, fes.current_knob.dial, fes.width_knob.dial, fes.table],
        "Script": [console.editor],
    }
    tabs = commands.tabs
    missing = []
    for title, widgets in primary.items():
        tabs.setCurrentIndex(next(i for i in range(tabs.count()) if tabs.tabText(i) == title))
        robot.tabs.setCurrentIndex(0)
        settle(qtbot)
        missing += [f"{title}: {type(w).__name__} {getattr(w, 'text', lambda: '')()!r}"
                    for w in widgets if not fully_shown(w)]
    assert not missing, f"not whole on screen at {size}: {missing}"


def _dialogs(manager: LinarmppManager, window: MainWindow) -> Iterator[tuple[str, QWidget]]:
    from app.session.recording import sessions_root
    from app.ui.fes_editor import FesProfileEditor
    from app.ui.patient_dialog import PatientDialog, StartSessionDialog
    from app.ui.recovery import RecoverDialog, Restartable
    from app.ui.sessions_browser import SessionsBrowser

    yield "Start session", StartSessionDialog(manager.config.safety, parent=window)
    yield "Patient", PatientDialog(None, manager.config.safety, parent=window)
    yield "Sessions browser", SessionsBrowser(sessions_root(manager.config), manager.config.ui.history_s)
    yield "FES profile editor", FesProfileEditor(manager.driver("fes").profile, window)
    yield "Recover", RecoverDialog(manager, manager.operator, Restartable("trigger_exercise.py", lambda: True), window)


def test_no_text_is_clipped_in_the_dialogs(running_window, qtbot) -> None:
    manager, window = running_window
    problems: list[str] = []
    for name, dialog in _dialogs(manager, window):
        dialog.show()
        qtbot.waitExposed(dialog)
        qtbot.waitUntil(lambda d=dialog: getattr(d, "loaded", True), timeout=5000)  # what it lists, read
        settle(qtbot, 200)
        problems += [f"[{name} {dialog.width()}×{dialog.height()}] {p}" for p in clipped_texts(dialog)]
        screen = dialog.screen().availableGeometry() if dialog.screen() else None
        if screen is not None and screen.width() >= 1366:
            assert dialog.width() <= 1366 and dialog.height() <= 768, f"{name} is larger than a 1366×768 screen"
        dialog.close()
        dialog.deleteLater()
    # The side windows of a recorded session: its details and its replay.
    from app.ui.replay_window import ReplayWindow
    from app.ui.sessions_browser import SessionDetails, SessionsBrowser

    folder = manager.recorder.folder
    manager.supervisor.raise_alarm(__import__("app.safety.supervisor", fromlist=["AlarmLevel"]).AlarmLevel.WARNING,
                                   "physio", "Skin-conductance electrodes off: check the electrodes")
    qtbot.wait(600)
    manager.end_session()
    browser = SessionsBrowser(folder.parent.parent)
    browser.set_patient(folder.parent.name)
    for name, widget in (("Sessions browser with a session", browser), ("Session details", SessionDetails(folder)),
                         ("Replay", ReplayWindow(folder))):
        widget.show()
        qtbot.waitExposed(widget)
        settle(qtbot, 300)
        problems += [f"[{name} {widget.width()}×{widget.height()}] {p}" for p in clipped_texts(widget)]
        widget.close()
        widget.deleteLater()
    assert not problems, "\n".join(problems)
