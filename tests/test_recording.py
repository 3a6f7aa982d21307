"""Session recording: a 10 s simulated session, events and manifest, gaps, drops, truncated files."""

from __future__ import annotations

import json
import re
import threading
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from app.core.bus import Channel, StreamBus, StreamSpec
from app.core.config import AppConfig, config_as_dict
from app.devices import physio
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel, SafetySupervisor
from app.session.recording import SessionRecorder, list_sessions, load_session, summarize_session
from tests.fakes import counter_factory

ISO_WITH_ZONE = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d+)?[+-]\d\d:\d\d$")


def wait_seconds(qtbot, seconds: float) -> None:
    t0 = time.monotonic()
    qtbot.waitUntil(lambda: time.monotonic() - t0 >= seconds, timeout=int(seconds * 1000) + 5000)


@pytest.mark.slow
def test_ten_second_session_is_complete(tmp_path, qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={"physio": physio.create,
                                                     "counter": counter_factory(tmp_path)})
    previous: list[str] = []
    manager.bus.listen("test", lambda r: previous.append(r.kind))
    manager.start()
    recorder = SessionRecorder()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=5000)
        qtbot.waitUntil(lambda: manager.driver("physio").total_samples("physio.main") > 0, timeout=5000)
        folder = recorder.start(manager, "P001", "dr_rossi", note="first session", root=tmp_path / "sessions")
        assert folder.parent.name == "P001"
        recorder.event("script_start", "dr_rossi", name="reach.py", text="linarm.moveCentreTo(0.2)\n")
        recorder.event("parameter_change", "dr_rossi", name="k_r", old=0.5, new=0.6)
        wait_seconds(qtbot, 5.0)
        manager.supervisor.raise_alarm(AlarmLevel.WARNING, "physio", "test alarm")
        manager.supervisor.emergency_stop("operator", "test e-stop")
        wait_seconds(qtbot, 5.0)
        recorder.event("script_stop", "dr_rossi", name="reach.py", reason="finished")
        recorder.stop("test finished")
    finally:
        recorder.stop()
        manager.shutdown()

    session = load_session(folder)
    assert session.complete and session.problems == []
    m = session.manifest
    assert (m["patient_id"], m["operator"], m["note"]) == ("P001", "dr_rossi", "first session")
    assert m["app_version"] and m["app_version"] != "unknown"
    assert m["config"] == json.loads(json.dumps(config_as_dict(AppConfig())))
    assert ISO_WITH_ZONE.match(m["start"]["t_wall"]) and ISO_WITH_ZONE.match(m["end"]["t_wall"])
    assert 9.5 <= m["duration_s"] <= 15.0
    assert set(m["devices"]) == {"physio", "counter"} and m["devices"]["physio"]["simulated"]
    assert set(session.streams) == {"physio.main", "counter.main"}
    for name, stream in session.streams.items():
        assert m["counts"][name] == len(stream), name
        assert np.all(np.diff(stream.t) >= 0), f"{name}: time stamps go backwards"
        span = stream.t[-1] - stream.t[0]
        assert span >= 9.5, (name, span)
        expected = stream.nominal_rate_hz * span
        assert abs(len(stream) - expected) <= max(3, 0.02 * expected), (name, len(stream), expected)
        assert [c.unit for c in stream.channels] == [c.unit for c in manager.devices[stream.device].driver
                                                     .streams[0].channels]
    counts = session.streams["counter.main"].data["count"]
    assert np.all(np.diff(counts) == 1), "the 1 kHz counter stream lost or repeated samples"
    assert m["dropped_samples"] == {"physio": 0, "counter": 0}

    kinds = [e["kind"] for e in session.events]
    for kind in ("session_start", "script_start", "parameter_change", "alarm", "emergency_stop", "script_stop",
                 "session_stop"):
        assert kind in kinds, kind
    assert kinds[0] == "session_start" and kinds[-1] == "session_stop"
    script = next(e for e in session.events if e["kind"] == "script_start")
    assert script["who"] == "dr_rossi" and script["data"]["text"] == "linarm.moveCentreTo(0.2)\n"
    estop = next(e for e in session.events if e["kind"] == "emergency_stop")
    assert estop["who"] == "operator" and estop["origin"] == "safety" and estop["data"]["reason"] == "test e-stop"
    for e in session.events:
        assert ISO_WITH_ZONE.match(e["t_wall"]) and isinstance(e["t_mono"], float)
    assert "emergency_stop" in previous and "alarm" in previous, "the previous event sink must keep working"

    summary = summarize_session(folder)
    assert summary.exercises == ("reach.py",) and summary.alarms >= 2 and summary.complete
    assert [s.folder for s in list_sessions("P001", tmp_path / "sessions")] == [folder]


# ---------------------------------------------------------------------------------------------- fakes
class FakeDriver:
    """A device publishing on the bus (app/core/bus.py), driven by the test."""

    streams = (StreamSpec("fake.main", (Channel("x", "m", "X"), Channel("y", "N", "Y")), 100.0),)

    def __init__(self, bus: StreamBus) -> None:
        self.bus = bus
        self.connected = True
        bus.declare(self.streams)

    def push(self, t: float, x: float, y: float) -> None:
        self.bus.publish("fake.main", t, SimpleNamespace(x=x, y=y))

    def fire(self, event: str, detail: str = "") -> None:
        self.bus.event("fake", event, detail)


def fake_manager() -> tuple[Any, FakeDriver]:
    """Just what the recorder uses of the application (app.therapy.services.SessionHost)."""
    bus = StreamBus()
    driver = FakeDriver(bus)
    config = AppConfig()
    manager = SimpleNamespace(config=config, bus=bus, supervisor=SafetySupervisor(config.safety),
                              devices={"fake": SimpleNamespace(driver=driver, simulated=True)},
                              fault_policy=SimpleNamespace(recording_failed=lambda folder, error: None),
                              add_shutdown_hook=lambda fn: None)
    return manager, driver


def test_values_are_recorded_exactly_and_listeners_detach(tmp_path) -> None:
    manager, driver = fake_manager()
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P002", "op", root=tmp_path)
    rng = np.random.default_rng(4)
    xs, ys = rng.standard_normal(500) * 1e-3, rng.standard_normal(500) * 1e5
    ts = 1000.0 + np.cumsum(rng.random(500) * 0.01)
    for t, x, y in zip(ts, xs, ys, strict=True):
        driver.push(float(t), float(x), float(y))
    driver.push(float(ts[-1] + 1), float("nan"), 0.0)
    recorder.stop()
    assert manager.bus.subscriptions() == []  # its sample and event queues are closed
    assert manager.supervisor.bus.subscriptions() == []  # nor on the supervisor's journal
    stream = load_session(folder).streams["fake.main"]
    assert np.array_equal(stream.t[:-1], ts) and np.array_equal(stream.data["x"][:-1], xs)
    assert np.array_equal(stream.data["y"][:-1], ys) and np.isnan(stream.data["x"][-1])
    assert [(c.name, c.unit) for c in stream.channels] == [("x", "m"), ("y", "N")]


def test_sessions_are_never_overwritten(tmp_path) -> None:
    manager, _ = fake_manager()
    recorder = SessionRecorder()
    folders = []
    for _ in range(3):
        folders.append(recorder.start(manager, "P003", "op", root=tmp_path))
        recorder.stop()
    assert len(set(folders)) == 3
    assert all(load_session(f).complete for f in folders)
    with pytest.raises(ValueError, match="operator"):
        recorder.start(manager, "P003", "", root=tmp_path)


def test_gap_markers_follow_device_events(tmp_path) -> None:
    manager, driver = fake_manager()
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P004", "op", root=tmp_path)
    driver.fire("silent")
    driver.fire("disconnected", "port vanished")
    driver.fire("connected", "connected (pty)")
    driver.fire("silent")
    driver.fire("alive")
    recorder.stop()
    events = [(e["kind"], e["data"].get("cause")) for e in load_session(folder).events if e["origin"] == "device"]
    assert events == [("gap_start", "silent"), ("device_disconnected", "disconnected"), ("gap_end", "connected"),
                      ("gap_start", "silent"), ("gap_end", "alive")]


def test_queue_overflow_is_counted_and_recorded(tmp_path) -> None:
    manager, driver = fake_manager()
    recorder = SessionRecorder(queue_limit=10)
    gate = threading.Event()
    drain = recorder._drain

    def held_drain() -> None:  # a stalled disk: the writer does not drain until the gate opens
        gate.wait(10)
        drain()

    recorder._drain = held_drain
    folder = recorder.start(manager, "P005", "op", root=tmp_path)
    for i in range(100):
        driver.push(float(i), 0.0, 0.0)
    gate.set()
    recorder.stop()
    session = load_session(folder)
    assert len(session.streams["fake.main"]) == 10
    assert session.manifest["dropped_samples"] == {"fake": 90}
    drops = [e for e in session.events if e["kind"] == "samples_dropped"]
    assert drops and drops[-1]["data"]["dropped_total"] == 90


def test_truncated_last_lines_are_dropped(tmp_path) -> None:
    manager, driver = fake_manager()
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P006", "op", root=tmp_path)
    for i in range(20):
        driver.push(float(i), float(i), float(-i))
    recorder.stop()
    with open(folder / "streams" / "fake.main.csv", "a", encoding="utf-8") as fh:
        fh.write("20.0,20")  # a line cut short by a crash
    with open(folder / "events.jsonl", "a", encoding="utf-8") as fh:
        fh.write('{"t_wall": "2025')
    session = load_session(folder)
    stream = session.streams["fake.main"]
    assert len(stream) == 20 and stream.dropped_lines == 1
    assert np.array_equal(stream.data["y"], -np.arange(20.0))
    assert session.events[-1]["kind"] == "session_stop"
    assert any("incomplete" in p for p in session.problems)


def test_the_recorder_subscribes_to_the_journal_beside_another_listener(tmp_path) -> None:
    """#29: the recorder chained the supervisor's one-slot sink (whoever set it next cut the recorder off, and
    a stop restored a stale one). Now it subscribes to the journal on the bus; another listener stays its owner's."""
    manager, _ = fake_manager()
    theirs: list[str] = []
    listener = manager.supervisor.bus.listen("theirs", lambda r: theirs.append(r.kind))
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P007", "op", root=tmp_path)
    assert not listener.closed
    listener.close()  # the other listener's owner goes: the record still gets the events
    manager.supervisor.record("alarm", source="test", text="after the sink changed")
    recorder.stop()
    assert [e["kind"] for e in load_session(folder).events if e["origin"] == "safety"] == ["alarm"]
