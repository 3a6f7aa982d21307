"""The main window with the manager: every device connects, the status bar says so, and closing
leaves no thread behind."""

from __future__ import annotations

from PySide6.QtCore import QSize, QThread
from PySide6.QtWidgets import QApplication, QMessageBox

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow
from tests.fakes import counter_factory


def running_driver_threads() -> list[QThread]:
    return [t for t in QApplication.instance().findChildren(QThread) if t.isRunning()]


def make_window(qtbot, tmp_path, names=("alpha", "beta")):
    manager = LinarmppManager(AppConfig(), factories={n: counter_factory(tmp_path, n) for n in names})
    manager.start()
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    return manager, window


def test_window_shows_devices_connected_and_closes_cleanly(qtbot, tmp_path) -> None:
    manager, window = make_window(qtbot, tmp_path)
    qtbot.waitUntil(manager.all_connected, timeout=5000)
    qtbot.waitUntil(lambda: all("connected" in w.text() and "disconnected" not in w.text()
                                for w in window.device_status.values()), timeout=3000)
    assert set(window.device_status) == {"alpha", "beta"}
    for name in ("1 · Values", "2 · Graphs", "3 · Device view", "4 · Commands"):
        assert any(d.windowTitle() == name for d in window.docks.values())
    drivers = [h.driver for h in manager.devices.values()]
    window.close()
    manager.shutdown(timeout_s=1.0)
    assert not any(d.isRunning() for d in drivers)
    assert all(not h.simulator.running for h in manager.devices.values())


def test_the_window_has_one_bus_adapter_and_closing_it_unsubscribes(qtbot, tmp_path) -> None:
    """Issue #29: one adapter turns bus traffic into Qt signals for the whole window; a closed window's adapter
    no longer subscribes to the bus (napari style: the Qt layer lets go on close)."""
    from app.ui.physio_viewer import PULSE_SUBSCRIBER
    from app.ui.qt_bus import BATCHES_NAME, EVENTS_NAME

    manager, window = make_window(qtbot, tmp_path, names=("alpha",))
    ui_names = {BATCHES_NAME, EVENTS_NAME, PULSE_SUBSCRIBER}

    def ui_subscriptions() -> list[str]:
        return sorted(sub.name for sub in manager.bus.subscriptions() if sub.name in ui_names)

    try:
        qtbot.waitUntil(manager.all_connected, timeout=5000)
        commands = window.frames["CommandsFrame"]
        readers = [*window.frames.values(), *commands.panels.values()]
        adapters = {id(w.qt_bus) for w in readers if getattr(w, "qt_bus", None) is not None}
        assert adapters == {id(window.qt_bus)}  # every frame and panel that reads the bus, through the one
        assert ui_subscriptions() == [BATCHES_NAME, EVENTS_NAME]  # the graphs' columns and the link events
        qtbot.waitUntil(lambda: window.frames["PlotsFrame"].store.count("counter.main.count") > 50, timeout=3000)
        window.close()
        assert ui_subscriptions() == [] and window.qt_bus.closed and not window.qt_bus.timer.isActive()
    finally:
        manager.shutdown(timeout_s=1.0)


def test_emergency_stop_button_and_key_latch_and_reset(qtbot, tmp_path, monkeypatch) -> None:
    manager, window = make_window(qtbot, tmp_path, names=("alpha",))
    calls: list[str] = []
    manager.supervisor.register_estop_action("record", calls.append)
    window.estop_button.click()
    assert manager.supervisor.estop_latched and len(calls) == 1
    assert window.estop_reset.isEnabled() and "STOPPED" in window.estop_label.text()
    # The key works whatever has focus, including inside a modal dialog.
    box = QMessageBox(window)
    box.setModal(True)
    box.show()
    qtbot.waitExposed(box)
    from PySide6.QtCore import Qt
    from PySide6.QtTest import QTest

    QTest.keyClick(box, Qt.Key.Key_F12)
    assert len(calls) == 2
    box.close()
    # The button acts on the press itself, not when it is let go.
    QTest.mousePress(window.estop_button, Qt.MouseButton.LeftButton)
    assert len(calls) == 3
    QTest.mouseRelease(window.estop_button, Qt.MouseButton.LeftButton)
    assert len(calls) == 3  # and only once per press
    monkeypatch.setattr(QMessageBox, "question", lambda *a, **k: QMessageBox.StandardButton.Yes)
    window.estop_reset.click()
    assert not manager.supervisor.estop_latched
    kinds = [a.text for a in manager.supervisor.alarms()]
    assert "Emergency stop reset" in kinds[-1]
    window.close()
    manager.shutdown()


def test_layout_persists_between_runs(qtbot, tmp_path) -> None:
    manager, window = make_window(qtbot, tmp_path, names=("alpha",))
    wanted = window.minimumSizeHint().expandedTo(window.minimumSize()) + QSize(7, 5)
    window.resize(wanted)
    wanted = window.size()  # what the screen allowed
    window.docks["DeviceView"].setFloating(True)
    window.close()
    manager.shutdown()
    (tmp_path / "2").mkdir()
    manager2, window2 = make_window(qtbot, tmp_path / "2", names=("alpha",))
    # The offscreen screen is 800 px wide: Qt may fit a restored window to it by a few pixels.
    assert window2.size().height() == wanted.height() and abs(window2.size().width() - wanted.width()) <= 10
    assert window2.docks["DeviceView"].isFloating()
    window2.docks["DeviceView"].setFloating(False)
    window2.close()
    manager2.shutdown()


def test_dark_palette_is_switchable_and_remembered(qtbot, tmp_path) -> None:
    from PySide6.QtGui import QPalette

    manager, window = make_window(qtbot, tmp_path, names=("alpha",))
    light = QApplication.instance().palette().color(QPalette.ColorRole.Window).lightness()
    window.dark_action.setChecked(True)
    dark = QApplication.instance().palette().color(QPalette.ColorRole.Window).lightness()
    assert dark < light
    window.close()
    manager.shutdown()
    (tmp_path / "again").mkdir()
    manager2, window2 = make_window(qtbot, tmp_path / "again", names=("alpha",))
    assert window2.dark_action.isChecked()
    window2.dark_action.setChecked(False)
    assert QApplication.instance().palette().color(QPalette.ColorRole.Window).lightness() == light
    window2.close()
    manager2.shutdown()


def test_first_run_maximised_view_toggles_enabled_end_session_states(qtbot, tmp_path, monkeypatch) -> None:
    """Issue #19: opened at 1280×720 in a corner; the View menu's frame toggles looked disabled;
    "End session" was enabled with no session; its confirmation ignored unacknowledged alarms."""
    from PySide6.QtCore import QSettings

    from app.safety.supervisor import AlarmLevel

    settings = QSettings()
    settings.remove("main/geometry")
    settings.remove("main/state")
    manager, window = make_window(qtbot, tmp_path, names=("alpha",))
    assert window.isMaximized()
    assert all(d.toggleViewAction().isEnabled() for d in window.docks.values())
    assert not window.end_action.isEnabled()
    manager.start_session("P001", "Dr Rossi", root=tmp_path / "sessions")
    assert window.end_action.isEnabled()
    manager.supervisor.raise_alarm(AlarmLevel.STOP, "alpha", "test stop")
    asked: list[str] = []
    monkeypatch.setattr(QMessageBox, "question",
                        lambda _p, _t, text, *a, **k: (asked.append(text), QMessageBox.StandardButton.No)[1])
    window.end_session()
    open_ = sum(1 for a in manager.supervisor.alarms() if not a.acknowledged)
    assert f"{open_} alarm(s) are not acknowledged" in asked[0] and manager.recorder is not None
    manager.end_session()
    assert not window.end_action.isEnabled()
    window.close()
    manager.shutdown()
