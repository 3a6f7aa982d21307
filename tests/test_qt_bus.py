"""The Qt adapter of the stream bus (issue #29): a real StreamBus published into by hand, its traffic as Qt
signals on the GUI thread; the adapter listens only while someone listens to it, and a closed one (a closed
window's) leaves nothing subscribed."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
from PySide6.QtCore import QObject

from app.core.bus import Channel, StreamBus, StreamSpec
from app.ui.qt_bus import BATCHES_NAME, EVENTS_NAME, QtBus, takes_qt_bus

MAIN = StreamSpec("dev.main", (Channel("x", "m", "X"), Channel("f", "N", "F")), 100.0)
OTHER = StreamSpec("other.main", (Channel("y", "", "Y"),), 50.0)


def _bus() -> StreamBus:
    bus = StreamBus()
    bus.declare([MAIN, OTHER])
    return bus


def _names(bus: StreamBus) -> list[str]:
    return sorted(sub.name for sub in bus.subscriptions())


def test_samples_arrive_as_columns_on_the_gui_thread_at_display_rate(qtbot) -> None:
    bus = _bus()
    qt_bus = QtBus(bus)
    got: list[tuple[dict, bool]] = []
    qt_bus.samples.connect(lambda batches: got.append((batches, threading.current_thread() is threading.main_thread())))

    def publish() -> None:  # a driver thread: one read of 50 samples, one wake
        for k in range(50):
            bus.publish(MAIN.name, 1.0 + k * 0.01, SimpleNamespace(x=float(k), f=-float(k)), 1.5, wake=False)
        bus.publish(OTHER.name, 2.0, SimpleNamespace(y=7.0), wake=False)
        bus.wake()

    worker = threading.Thread(target=publish)
    with qtbot.waitSignal(qt_bus.samples, timeout=1000):
        worker.start()
        worker.join()
    qtbot.waitUntil(lambda: sum(len(b.get(MAIN.name, ())) for b, _ in got) == 50, timeout=1000)
    assert all(on_gui for _b, on_gui in got)
    main = [b[MAIN.name] for b, _ in got if MAIN.name in b]
    x = np.concatenate([b.data["x"] for b in main])
    t = np.concatenate([b.t for b in main])
    assert x.tolist() == [float(k) for k in range(50)] and np.allclose(t, 1.0 + np.arange(50) * 0.01)
    assert main[0].stream == MAIN and main[0].arrival is not None and main[0].arrival[0] == 1.5
    assert any(OTHER.name in b and b[OTHER.name].data["y"].tolist() == [7.0] for b, _ in got)
    assert len(got) <= 2  # columns per tick, never a signal per sample
    assert qt_bus.latest(MAIN.name).x == 49.0 and qt_bus.specs("dev") == {MAIN.name: MAIN}
    qt_bus.close()


def test_device_events_become_connection_and_silence_signals(qtbot) -> None:
    bus = _bus()
    qt_bus = QtBus(bus)
    events: list[tuple[str, str, str]] = []
    silences: list[tuple[str, bool]] = []
    qt_bus.device_event.connect(lambda *a: events.append(a))
    qt_bus.silence_changed.connect(lambda *a: silences.append(a))
    assert not qt_bus.connected("dev")
    with qtbot.waitSignal(qt_bus.connection_changed, timeout=1000) as blocker:
        bus.event("dev", "connected", "connected (serial /dev/pts/9)")
    assert blocker.args == ["dev", True, "connected (serial /dev/pts/9)"]
    assert qt_bus.connected("dev") and not qt_bus.silent("dev")
    with qtbot.waitSignal(qt_bus.silence_changed, timeout=1000):
        bus.event("dev", "silent")
    assert qt_bus.silent("dev") and qt_bus.connected("dev")
    bus.event("dev", "alive", "0.300")
    bus.event("dev", "controller_error", "TRACKING_ERROR")
    with qtbot.waitSignal(qt_bus.connection_changed, timeout=1000) as blocker:
        bus.event("dev", "disconnected", "read failed: [Errno 5] Input/output error")
    assert blocker.args == ["dev", False, "read failed: [Errno 5] Input/output error"]
    assert silences == [("dev", True), ("dev", False)]
    assert [e[1] for e in events] == ["connected", "silent", "alive", "controller_error", "disconnected"]
    assert events[2] == ("dev", "alive", "0.300") and events[3] == ("dev", "controller_error", "TRACKING_ERROR")
    assert not qt_bus.connected("dev") and qt_bus.reason("dev").startswith("read failed")
    qt_bus.close()


def test_a_query_sees_an_event_before_the_next_tick_emits_it(qtbot) -> None:
    """A frame refreshing just after a device dropped shows the drop (a test stops a driver and refreshes)."""
    bus = _bus()
    qt_bus = QtBus(bus)
    changes: list[tuple[str, bool, str]] = []
    qt_bus.connection_changed.connect(lambda *a: changes.append(a))
    qt_bus.timer.stop()  # no tick between the event and the query
    bus.event("dev", "connected", "up")
    assert qt_bus.connected("dev") and changes == []
    bus.event("dev", "disconnected", "unplugged")
    assert not qt_bus.connected("dev") and qt_bus.reason("dev") == "unplugged"
    qt_bus.tick()  # and the signals still go out, in order
    assert changes == [("dev", True, "up"), ("dev", False, "unplugged")]
    qt_bus.close()


def test_an_adapter_built_after_the_devices_connected_knows_their_state(qtbot) -> None:
    bus = _bus()
    bus.event("dev", "connected", "up")
    bus.event("other", "connected", "up")
    bus.event("other", "silent")
    bus.event("gone", "disconnected", "no port")
    qt_bus = QtBus(bus)
    assert qt_bus.connected("dev") and not qt_bus.silent("dev") and qt_bus.reason("dev") == "up"
    assert qt_bus.connected("other") and qt_bus.silent("other")
    assert not qt_bus.connected("gone") and qt_bus.reason("gone") == "no port"
    assert not qt_bus.connected("never") and not qt_bus.silent("never")
    qt_bus.close()


def test_it_listens_only_while_someone_listens_to_it(qtbot) -> None:
    bus = _bus()
    qt_bus = QtBus(bus)
    assert not qt_bus.timer.isActive() and _names(bus) == [EVENTS_NAME]  # nobody connected yet

    def slot(_batches: object) -> None:
        pass

    qt_bus.samples.connect(slot)
    assert qt_bus.timer.isActive() and _names(bus) == [BATCHES_NAME, EVENTS_NAME]
    qt_bus.samples.disconnect(slot)
    qt_bus.tick()
    # Nobody draws: no columns are kept on the driver threads, and the timer stops.
    assert _names(bus) == [EVENTS_NAME] and not qt_bus.timer.isActive()
    bus.publish(MAIN.name, 1.0, SimpleNamespace(x=1.0, f=0.0))
    bus.event("dev", "connected", "up")
    assert qt_bus.connected("dev")  # the state is kept with nobody listening ...
    changes: list[tuple[str, bool, str]] = []
    qt_bus.connection_changed.connect(lambda *a: changes.append(a))  # link states only: no batches
    assert qt_bus.timer.isActive() and _names(bus) == [EVENTS_NAME]
    qt_bus.tick()
    assert changes == []  # ... but no signal is held back for listeners that came later
    qt_bus.close()


def test_a_closed_adapter_unsubscribes_and_emits_nothing_more(qtbot) -> None:
    bus = _bus()
    qt_bus = QtBus(bus)
    got: list[object] = []
    qt_bus.samples.connect(got.append)
    qt_bus.device_event.connect(lambda *a: got.append(a))
    qt_bus.close()
    assert bus.subscriptions() == [] and qt_bus.closed and not qt_bus.timer.isActive()
    bus.publish(MAIN.name, 1.0, SimpleNamespace(x=1.0, f=0.0))
    bus.event("dev", "connected", "up")
    qt_bus.tick()
    qtbot.wait(100)
    assert got == []
    qt_bus.samples.connect(lambda _b: None)  # connecting again does not bring it back
    assert bus.subscriptions() == [] and not qt_bus.timer.isActive()


def test_an_adapter_destroyed_with_its_parent_unsubscribes(qtbot) -> None:
    bus = _bus()
    owner = QObject()
    qt_bus = QtBus(bus, parent=owner)
    qt_bus.samples.connect(lambda _b: None)
    assert _names(bus) == [BATCHES_NAME, EVENTS_NAME]
    del qt_bus
    with qtbot.waitSignal(owner.destroyed, timeout=1000):
        owner.deleteLater()
    assert bus.subscriptions() == []


def test_frames_say_whether_they_take_the_adapter() -> None:
    class Plain:
        def __init__(self, manager: object) -> None:
            self.manager = manager

    class Reader:
        def __init__(self, manager: object, *, qt_bus: QtBus | None = None) -> None:
            self.qt_bus = qt_bus

    assert takes_qt_bus(Reader) and not takes_qt_bus(Plain)
