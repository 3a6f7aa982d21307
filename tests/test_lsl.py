"""LSL outlets: resolved with pylsl, samples read back with LSL-clock time stamps."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace

import numpy as np
import pytest

from app.core.config import AppConfig, RecordingConfig
from app.manager import LinarmppManager
from app.session import lsl
from tests.fakes import counter_factory

AVAILABLE, STATUS = lsl.lsl_status()


def lsl_config(on: bool = True) -> AppConfig:
    return replace(AppConfig(), recording=RecordingConfig(lsl=on))


def test_off_by_default_and_missing_library_is_reported(tmp_path, caplog, monkeypatch) -> None:
    manager = LinarmppManager(lsl_config(False), factories={})
    assert lsl.start_lsl(manager) is None
    monkeypatch.setattr(lsl, "lsl_status", lambda: (False, "LSL unavailable: liblsl not found"))
    with caplog.at_level(logging.WARNING, logger="app.session.lsl"):
        assert lsl.start_lsl(LinarmppManager(lsl_config(True), factories={})) is None
    assert "running without LSL" in caplog.text and "liblsl not found" in caplog.text


def _resolve(pylsl, outlet) -> object:
    """Our own outlet (by uid: another process on this host may publish the same source id)."""
    uid = outlet.get_info().uid()
    source_id = outlet.get_info().source_id()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        for info in pylsl.resolve_byprop("source_id", source_id, minimum=1, timeout=2.0):
            if info.uid() == uid:
                return info
    raise AssertionError(f"outlet {source_id} not resolved")


@pytest.mark.skipif(not AVAILABLE, reason=f"liblsl cannot be loaded on this platform: {STATUS}")
def test_outlets_resolve_and_stream_in_lsl_time(tmp_path, qtbot) -> None:
    import pylsl

    manager = LinarmppManager(lsl_config(True), factories={"counter": counter_factory(tmp_path)})
    manager.start()
    bridge = None
    try:
        qtbot.waitUntil(manager.all_connected, timeout=5000)
        bridge = lsl.start_lsl(manager)
        assert bridge is not None and set(bridge.outlets) == {"counter.main"}
        info = _resolve(pylsl, bridge.outlets["counter.main"])
        assert (info.name(), info.type(), info.channel_count(), info.nominal_srate()) == ("counter.main", "counter",
                                                                                          1, 1000.0)
        inlet = pylsl.StreamInlet(info)
        inlet.open_stream(timeout=5)
        full = inlet.info(timeout=5)
        channel = full.desc().child("channels").child("channel")
        assert (channel.child_value("label"), channel.child_value("unit")) == ("count", "")
        values: list[float] = []
        stamps: list[float] = []
        deadline = time.monotonic() + 10
        while len(values) < 500 and time.monotonic() < deadline:
            chunk, ts = inlet.pull_chunk(timeout=0.5)
            values += [row[0] for row in chunk]
            stamps += ts
        assert len(values) >= 500
        assert np.all(np.diff(values) == 1), "samples lost or repeated on the way through LSL"
        assert np.all(np.diff(stamps) >= 0)
        now = pylsl.local_clock()
        assert now - 5.0 < stamps[-1] <= now + 0.01, "time stamps must be in LSL's clock"

        events = _resolve(pylsl, bridge.events_outlet)
        markers = pylsl.StreamInlet(events)
        markers.open_stream(timeout=5)
        manager.record_event("script_start", "tester", name="reach.py")  # the journal: the one way a marker goes
        sample, stamp = markers.pull_sample(timeout=5)
        assert sample is not None and json.loads(sample[0])["data"]["name"] == "reach.py"
        assert abs(stamp - pylsl.local_clock()) < 5.0
    finally:
        if bridge is not None:
            bridge.stop()
        manager.shutdown()


@pytest.mark.skipif(not AVAILABLE, reason=f"liblsl cannot be loaded on this platform: {STATUS}")
def test_the_marker_outlet_hears_the_journal_with_or_without_a_session(tmp_path, qtbot) -> None:
    """#40: the marker outlet subscribes to the journal on the bus, so a record reaches it whenever the outlets run
    (it took the recorder's events, so markers flowed only while a session recorded) and reads as the session
    record writes it; its subscription ends with the outlets."""
    import pylsl

    manager = LinarmppManager(lsl_config(True), factories={})
    manager.start()
    before = {id(s) for s in manager.bus.subscriptions()}
    bridge = manager.start_lsl()  # the manager's outlets: the session below uses them too
    try:
        assert bridge is not None and manager.recorder is None
        markers = pylsl.StreamInlet(_resolve(pylsl, bridge.events_outlet))
        markers.open_stream(timeout=5)
        manager.record_event("exercise_chosen", "tester", exercise="reach")
        sample, _ = markers.pull_sample(timeout=5)
        assert sample is not None, "no marker for a record published while no session records"
        marker = json.loads(sample[0])
        assert (marker["kind"], marker["who"], marker["origin"], marker["data"]) == (
            "exercise_chosen", "tester", "app", {"exercise": "reach"})

        folder = manager.start_session("P-LSL", "tester", root=tmp_path / "sessions")
        manager.record_event("exercise_chosen", "tester", exercise="grip")
        manager.end_session()
        pushed = []
        while (sample := markers.pull_sample(timeout=1)[0]) is not None:
            pushed.append(json.loads(sample[0]))
        written = [json.loads(line) for line in (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()]
        chosen = [e for e in written if e["kind"] == "exercise_chosen"]
        assert chosen and chosen[0] in pushed, (chosen, pushed)  # the marker is the session record's line
        assert [e for e in pushed if e["kind"] == "exercise_chosen"] == chosen, "one marker per record"
    finally:
        manager.shutdown()  # stops the outlets
    assert [s.name for s in manager.bus.subscriptions() if id(s) not in before] == []
    assert bridge._thread is None
