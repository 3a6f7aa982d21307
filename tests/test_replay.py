"""Replay: the recorded values come back as live batches and show up in the graphs."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from app.core.bus import Channel, StreamSpec
from app.core.config import AppConfig
from app.session.recording import RecordedSession, SessionRecorder, load_session
from app.session.replay import ReplaySource
from tests.fakes import ListenerDriver
from tests.recorder_host import recorder_host

RATE_HZ = 10.0
SECONDS = 20.0


def _Driver() -> ListenerDriver:
    return ListenerDriver(StreamSpec("fake.main", (Channel("x", "m", "Position"), Channel("f", "N", "Force")), RATE_HZ))



@pytest.fixture
def session(tmp_path) -> RecordedSession:
    driver = _Driver()
    config = AppConfig()
    manager = recorder_host(config, {"fake": driver})
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P020", "op", root=tmp_path)
    rng = np.random.default_rng(2)
    t0 = time.monotonic()
    for i in range(int(SECONDS * RATE_HZ)):
        sample = SimpleNamespace(x=float(rng.random() * 0.3), f=float(rng.standard_normal() * 10))
        for fn in driver.listeners:
            fn("fake.main", t0 + i / RATE_HZ, sample)
    recorder.event("script_start", "op", name="reach.py", text="")
    recorder.stop()
    return load_session(folder)


def test_advancing_delivers_every_sample_once(session) -> None:
    source = ReplaySource(session)
    recorded = session.streams["fake.main"]
    assert source.duration >= SECONDS - 1 / RATE_HZ
    parts = []
    while not source.at_end:
        batch = source.advance(0.37).get("fake.main")
        if batch is not None:
            assert batch.stream.name == "fake.main" and set(batch.data) == {"x", "f"}
            parts.append(batch)
    t = np.concatenate([b.t for b in parts])
    assert np.array_equal(t, recorded.t)
    assert np.array_equal(np.concatenate([b.data["f"] for b in parts]), recorded.data["f"])
    source.seek(-5)
    assert source.elapsed == 0.0
    source.seek(1e9)
    assert source.at_end


def test_replay_window_shows_the_recorded_values(session, qtbot) -> None:
    from app.ui.replay_window import ReplayWindow

    window = ReplayWindow(session, history_s=30.0)
    qtbot.addWidget(window)
    window.show()
    recorded = session.streams["fake.main"]
    window.plots.set_history(10.0)

    def shown(key: str) -> tuple[np.ndarray, np.ndarray]:
        x, y = window.plots.curves[key].getData()
        return np.asarray(x) + window.plots.x_origin, np.asarray(y)  # the x-axis is session time

    window.seek(12.0)
    pos = window.source.position
    assert window.slider.value() == 1200 and "00:12.000" in window.time_label.text()
    x0, x1 = window.plots.plots[next(iter(window.plots.plots))].vb.viewRange()[0]
    assert x1 == pytest.approx(12.0, abs=0.15) and x0 == pytest.approx(2.0, abs=0.15), \
        "issue #19: the x-axis is session time (it ran -10..0)"
    t, x = shown("fake.main.x")
    assert window.plots.t_ref <= pos and t[-1] >= window.plots.t_ref - 1e-9
    assert t[0] <= window.plots.t_ref - 10.0 + 1 / RATE_HZ, "the graph shows the whole history before 'now'"
    # Exactly the recorded samples of the shown stretch: none missing, none altered.
    expected = (recorded.t >= t[0] - 1e-9) & (recorded.t <= t[-1] + 1e-9)
    assert len(t) == int(expected.sum()) >= 100
    np.testing.assert_allclose(t, recorded.t[expected], rtol=0, atol=1e-9)
    assert np.array_equal(x, recorded.data["x"][expected]), "the graph must show the recorded values"
    assert np.array_equal(shown("fake.main.f")[1], recorded.data["f"][expected])
    assert window.plots.t_ref == recorded.t[expected][-1], "the newest replayed sample is 'now'"

    window.step(2.0)
    t_after, _ = shown("fake.main.x")
    assert t_after[-1] == pytest.approx(recorded.t[recorded.t <= pos + 2.0][-1])

    window.slider.setValue(300)  # the time slider seeks back
    assert window.source.elapsed == pytest.approx(3.0)
    t_back, x_back = shown("fake.main.x")
    early = recorded.t <= window.source.position
    assert np.array_equal(x_back, recorded.data["x"][early]) and len(t_back) == int(early.sum())

    window.set_playing(True)
    start = window.source.elapsed
    qtbot.waitUntil(lambda: window.source.elapsed > start + 0.2, timeout=3000)
    window.set_playing(False)
    assert not window.playing


def test_a_click_on_the_replay_slider_seeks_there(session, qtbot) -> None:
    """Issue #19: no page jumps on click; the replay's slider goes where it is clicked."""
    from PySide6.QtCore import QPoint, Qt

    from app.ui.replay_window import ReplayWindow

    window = ReplayWindow(session, history_s=30.0)
    qtbot.addWidget(window)
    window.show()
    qtbot.waitExposed(window)
    slider = window.slider
    qtbot.mouseClick(slider, Qt.MouseButton.LeftButton, pos=QPoint(slider.width() * 3 // 4, slider.height() // 2))
    fraction = slider.value() / slider.maximum()
    assert 0.6 < fraction < 0.9
    assert window.source.elapsed == pytest.approx(slider.value() / 100, abs=0.02)


def test_replay_opens_on_measured_signals_and_closes_from_its_own_button(tmp_path, qtbot) -> None:
    """Issue #30: Replay opened on the robot's flat-zero state codes with an axis scaled ×1e-12 and had no
    Close button. Now: the live graphs' default signals it recorded, a flat line on a readable axis, Close."""
    from app.devices.linarm import STATE_STREAM, VSA_STREAM
    from app.ui.plots_frame import sticky_y_range
    from app.ui.replay_window import ReplayWindow, default_replay_signals

    state, vsa = ListenerDriver(STATE_STREAM), ListenerDriver(VSA_STREAM)
    config = AppConfig()
    manager = recorder_host(config, {"linarm": state, "linarm2": vsa})
    recorder = SessionRecorder()
    folder = recorder.start(manager, "P021", "op", root=tmp_path)
    t0 = time.monotonic()
    for i in range(40):
        t = t0 + i * 0.05
        for fn in state.listeners:
            fn(STATE_STREAM.name, t, SimpleNamespace(**{c.name: 0.0 for c in STATE_STREAM.channels}))
        for fn in vsa.listeners:
            fn(VSA_STREAM.name, t, SimpleNamespace(**{c.name: 0.1 + 0.001 * i for c in VSA_STREAM.channels}))
    recorder.stop()
    rec = load_session(folder)
    chosen = default_replay_signals(rec)
    assert chosen and not any(k.startswith("linarm.state.") for k in chosen)
    assert "linarm.vsa.handlePos" in chosen
    lo, hi = sticky_y_range(None, 0.0, 0.0, snap=True)
    assert hi - lo >= 1.0  # a flat zero: a band of a unit, not of 1e-9
    window = ReplayWindow(rec)
    qtbot.addWidget(window)
    window.show()
    assert sorted(window.plots.selected) == sorted(chosen)
    window.close_button.click()
    assert not window.isVisible()


def test_the_sessions_windows_close_from_their_own_buttons(session, qtbot) -> None:
    """Issue #30: the Sessions browser and a session's details had no Close button."""
    from app.ui.sessions_browser import SessionDetails, SessionsBrowser

    browser = SessionsBrowser(session.folder.parent.parent)
    qtbot.addWidget(browser)
    browser.show()
    browser.close_button.click()
    assert not browser.isVisible()
    details = SessionDetails(session.folder)
    qtbot.addWidget(details)
    details.show()
    from PySide6.QtWidgets import QDialogButtonBox

    details.findChild(QDialogButtonBox).button(QDialogButtonBox.StandardButton.Close).click()
    assert not details.isVisible()
