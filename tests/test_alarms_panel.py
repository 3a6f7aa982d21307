"""Alarms panel and banner: level colours (distinct, one per grade), acknowledgement with the
operator's name (recorded as a session event by the supervisor), the audible signal on STOP and
FATAL only (repeated while unacknowledged), and alarms raised from another thread."""

from __future__ import annotations

import threading
from typing import Any

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QScrollArea

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.ui.alarms_panel import LEVEL_STYLES, AlarmBanner, AlarmsPanel, highest_unacknowledged
from app.ui.qt_bus import shared_qt_bus


def settle(manager: LinarmppManager) -> None:
    """The journal's records reach the panels at the adapter's tick: this one now."""
    shared_qt_bus(manager.bus).tick()


def _setup(qtbot, repeat_s: float = 60.0) -> tuple[LinarmppManager, AlarmsPanel, list[tuple[str, dict[str, Any]]]]:
    manager = LinarmppManager(AppConfig(), factories={})
    events: list[tuple[str, dict[str, Any]]] = []
    manager.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    panel = AlarmsPanel(manager, repeat_s=repeat_s)
    panel.beep = lambda: None  # counted in panel.beeps; no sound in tests
    qtbot.addWidget(panel)
    panel.resize(680, 380)
    panel.show()
    return manager, panel, events


def test_levels_are_colour_coded_and_only_stop_and_fatal_beep(qtbot) -> None:
    manager, panel, _events = _setup(qtbot)
    sup = manager.supervisor
    sup.raise_alarm(AlarmLevel.INFO, "linarm", "linarm reconnected")
    sup.raise_alarm(AlarmLevel.WARNING, "physio", "physio stopped sending data")
    settle(manager)
    assert panel.beeps == 0
    sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: TRACKING_ERROR")
    settle(manager)
    assert panel.beeps == 1
    sup.raise_alarm(AlarmLevel.FATAL, "fes", "stimulator lost")
    settle(manager)
    assert panel.beeps == 2
    # newest first: FATAL, STOP, WARNING, INFO
    rows = [panel.tree.topLevelItem(i) for i in range(panel.tree.topLevelItemCount())]
    assert [r.text(0) for r in rows] == ["FATAL", "STOP", "WARNING", "INFORMATION"]
    colours = [panel.level_colour_of_row(i) for i in range(4)]
    expected = [LEVEL_STYLES[lv].background for lv in (AlarmLevel.FATAL, AlarmLevel.STOP, AlarmLevel.WARNING,
                                                       AlarmLevel.INFO)]
    assert colours == expected and len(set(colours)) == 4
    assert LEVEL_STYLES[AlarmLevel.STOP].background == "#d32f2f"  # red
    assert LEVEL_STYLES[AlarmLevel.WARNING].background == "#ffb300"  # amber
    assert "FATAL" in panel.summary.text() and "4 active" in panel.summary.text()
    assert panel.repeat.isActive()


def test_acknowledge_needs_an_operator_and_is_recorded(qtbot) -> None:
    manager, panel, events = _setup(qtbot)
    sup = manager.supervisor
    stop = sup.raise_alarm(AlarmLevel.STOP, "robot monitor", "Robot stopped: handle speed")
    warn = sup.raise_alarm(AlarmLevel.WARNING, "physio", "physio stopped sending data")
    settle(manager)
    panel.tree.topLevelItem(1).setSelected(True)  # the STOP (newest first)
    qtbot.mouseClick(panel.ack_selected, Qt.MouseButton.LeftButton)
    assert "operator" in panel.message.text() and not any(a.acknowledged for a in sup.alarms())
    qtbot.keyClicks(panel.operator, "Dr Rossi")
    panel.tree.topLevelItem(1).setSelected(True)
    qtbot.mouseClick(panel.ack_selected, Qt.MouseButton.LeftButton)
    acked = {a.ident: a.acknowledged for a in sup.alarms()}
    assert acked == {stop.ident: True, warn.ident: False}
    assert ("alarm_acknowledged", {"ident": stop.ident, "operator": "Dr Rossi"}) in events
    assert [kind for kind, _d in events].count("alarm") == 2  # each alarm is an event too
    assert not panel.repeat.isActive()  # no unacknowledged STOP/FATAL left: the sound stops
    row = next(panel.tree.topLevelItem(i) for i in range(2) if panel.tree.topLevelItem(i).text(0) == "STOP")
    assert row.text(3) == "ack. Dr Rossi"
    qtbot.mouseClick(panel.ack_all, Qt.MouseButton.LeftButton)
    assert all(a.acknowledged for a in sup.alarms()) and not panel.ack_all.isEnabled()
    assert "No active alarms" in panel.summary.text()
    panel.show_acknowledged.setChecked(False)
    assert panel.tree.topLevelItemCount() == 0


def test_sound_repeats_while_a_stop_is_unacknowledged(qtbot) -> None:
    manager, panel, _events = _setup(qtbot, repeat_s=0.05)
    manager.supervisor.raise_alarm(AlarmLevel.STOP, "linarm", "connection lost")
    qtbot.waitUntil(lambda: panel.beeps >= 3, timeout=2000)
    panel.operator.setText("nurse")
    assert panel.acknowledge_all() == 1
    assert not panel.repeat.isActive()


def test_banner_shows_the_newest_open_alarm_and_follows_other_threads(qtbot) -> None:
    manager, panel, _events = _setup(qtbot)
    banner = AlarmBanner(manager)
    qtbot.addWidget(banner)
    assert banner.current is None and "No active alarms" in banner.label.text()
    sup = manager.supervisor
    worker = threading.Thread(target=lambda: sup.raise_alarm(AlarmLevel.WARNING, "physio", "silent"))
    worker.start()
    worker.join()
    qtbot.waitUntil(lambda: banner.current is not None and panel.tree.topLevelItemCount() == 1, timeout=2000)
    stop = sup.raise_alarm(AlarmLevel.STOP, "linarm", "LINarm error: OVER_FORCE")
    sup.raise_alarm(AlarmLevel.INFO, "operator", "note")
    settle(manager)
    # The newest open alarm is shown (never a stale one); the count and a red list button say more are open.
    assert banner.current is not stop and banner.current.text == "note"
    assert banner.label.full_text().startswith("INFORMATION ") and banner.button.text() == "Alarms (3)…"
    assert LEVEL_STYLES[AlarmLevel.STOP].background in banner.button.styleSheet()
    assert not banner.recover_button.isHidden(), "an open STOP offers Recover"
    with qtbot.waitSignal(banner.show_alarms_requested, timeout=1000):
        banner.button.click()
    sup.acknowledge(banner.current.ident, "x")
    settle(manager)
    assert banner.current is stop and LEVEL_STYLES[AlarmLevel.STOP].background in banner.styleSheet()
    sup.acknowledge(stop.ident, "x")
    settle(manager)
    assert banner.current is not None and banner.current.level is AlarmLevel.WARNING
    assert banner.recover_button.isHidden()
    assert highest_unacknowledged([]) == (None, 0)


def test_fits_a_scroll_area_without_scrolling_as_a_whole(qtbot) -> None:
    manager, panel, _events = _setup(qtbot)
    manager.supervisor.raise_alarm(AlarmLevel.STOP, "linarm", "a long message " * 20)
    outer = QScrollArea()
    outer.setWidgetResizable(True)
    panel.setParent(None)
    outer.setWidget(panel)
    qtbot.addWidget(outer)
    outer.resize(680, 300)
    outer.show()
    qtbot.waitExposed(outer)
    assert outer.verticalScrollBar().maximum() == 0


def test_the_list_updates_row_by_row_and_stays_correct(qtbot) -> None:
    manager, panel, _events = _setup(qtbot)
    sup = manager.supervisor
    first = [sup.raise_alarm(AlarmLevel.WARNING, "physio", f"w{i}") for i in range(5)]
    settle(manager)
    rows_before = [panel.tree.topLevelItem(i) for i in range(5)]
    stop = sup.raise_alarm(AlarmLevel.STOP, "linarm", "stop")
    settle(manager)
    # A new alarm adds one row on top; the rows already there are the same objects (no rebuild).
    assert panel.tree.topLevelItemCount() == 6
    assert [panel.tree.topLevelItem(i) for i in range(1, 6)] == rows_before
    assert panel.tree.topLevelItem(0).text(4) == "stop"
    idents = [int(panel.tree.topLevelItem(i).data(0, Qt.ItemDataRole.UserRole)) for i in range(6)]
    assert idents == sorted(idents, reverse=True)  # newest first
    # Acknowledging one changes that row in place: status, plain colours past the level cell, not bold.
    row = panel.tree.topLevelItem(5)
    assert int(row.data(0, Qt.ItemDataRole.UserRole)) == first[0].ident
    panel.tree.clearSelection()
    panel.operator.setText("Dr Bianchi")
    assert panel.acknowledge([first[0].ident]) == 1
    assert panel.tree.topLevelItem(5) is row and row.text(3) == "ack. Dr Bianchi"
    assert not row.font(1).bold() and row.background(1).style() == Qt.BrushStyle.NoBrush
    assert row.background(0).color().name() == LEVEL_STYLES[AlarmLevel.WARNING].background
    assert panel.tree.topLevelItem(0).text(3) == "ACTIVE" and panel.tree.topLevelItem(0).font(1).bold()
    # An acknowledgement made elsewhere (the supervisor itself) shows too.
    sup.acknowledge(stop.ident, "script")
    settle(manager)
    assert panel.tree.topLevelItem(0).text(3) == "ack."
    assert "4 active" in panel.summary.text() and not panel.repeat.isActive()
    # The filter still hides acknowledged alarms, and selection survives it.
    panel.tree.topLevelItem(1).setSelected(True)
    selected = int(panel.tree.topLevelItem(1).data(0, Qt.ItemDataRole.UserRole))
    panel.show_acknowledged.setChecked(False)
    shown = {int(panel.tree.topLevelItem(i).data(0, Qt.ItemDataRole.UserRole))
             for i in range(panel.tree.topLevelItemCount())}
    assert shown == {a.ident for a in first[1:]}
    assert [int(i.data(0, Qt.ItemDataRole.UserRole)) for i in panel.tree.selectedItems()] == [selected]
    panel.acknowledge([first[1].ident])  # acknowledged while hidden from the list: its row goes
    assert panel.tree.topLevelItemCount() == 3
    panel.show_acknowledged.setChecked(True)
    assert panel.tree.topLevelItemCount() == 6


def test_a_long_session_keeps_open_alarms_in_a_bounded_list(qtbot, monkeypatch) -> None:
    import app.ui.alarms_panel as alarms_panel

    monkeypatch.setattr(alarms_panel, "ROW_LIMIT", 10)
    manager, panel, _events = _setup(qtbot)
    sup = manager.supervisor
    stop = sup.raise_alarm(AlarmLevel.STOP, "linarm", "the first, still open")
    panel.operator.setText("nurse")
    for i in range(30):
        info = sup.raise_alarm(AlarmLevel.INFO, "operator", f"note {i}")
        panel.acknowledge([info.ident])
    assert panel.tree.topLevelItemCount() == 10
    idents = [int(panel.tree.topLevelItem(i).data(0, Qt.ItemDataRole.UserRole)) for i in range(10)]
    assert stop.ident in idents  # the open STOP stays; the oldest acknowledged notes went
    assert idents[:9] == sorted(idents[:9], reverse=True) and idents[-1] == stop.ident


def test_recover_without_a_session_asks_the_name_once(qtbot) -> None:
    """No session gives the operator: Recover… , type the name, Recover -- three actions, all logged."""
    manager, _panel, events = _setup(qtbot)
    banner = AlarmBanner(manager)
    qtbot.addWidget(banner)
    banner.show()
    sup = manager.supervisor
    sup.emergency_stop("button")
    sup.raise_alarm(AlarmLevel.WARNING, "physio", "sensor off")
    settle(manager)
    assert not banner.recover_button.isHidden()
    banner.recover_button.click()  # 1
    dialog = banner.dialog
    assert dialog is not None and dialog.restart_button is None and dialog.operator.text() == ""
    dialog.recover_button.click()  # refused: no name yet
    assert "operator" in dialog.error.text() and sup.estop_latched
    qtbot.keyClicks(dialog.operator, "Dr Verdi")  # 2
    dialog.recover_button.click()  # 3
    assert not sup.estop_latched and not [a for a in sup.alarms() if not a.acknowledged]
    steps = [d for k, d in events if k == "recovery"]
    assert {d["operator"] for d in steps} == {"Dr Verdi"} and steps[-1]["step"] == "done"
    assert ("emergency_stop_reset", {"operator": "Dr Verdi"}) in events
    assert banner.recover_button.isHidden()
