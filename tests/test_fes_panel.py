"""The FES manager panel on a simulated RehaStim: start/stop, load (good and malformed files), the knobs
and the per-channel numbers they give, channel status; plus its screenshot."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from PySide6.QtCore import QPoint, Qt

from app.core.config import AppConfig
from app.core.fes_profile import load_profile
from app.devices import rehastim
from app.manager import LinarmppManager
from app.ui.fes_panel import MAX_RISE_PER_ACTION, PROFILES_DIR, FesPanel
from tests.conftest import screenshot_path

FRONTAL = PROFILES_DIR / "frontal_reaching.yaml"
WRIST = PROFILES_DIR / "wrist_extension_time.yaml"


@pytest.fixture
def panel(qtbot) -> Iterator[FesPanel]:
    manager = LinarmppManager(AppConfig(), factories={"fes": rehastim.create})
    manager.start()
    try:
        p = FesPanel(manager)
        qtbot.addWidget(p)
        p.resize(900, 560)
        p.show()
        qtbot.waitUntil(lambda: p.driver is not None and p.driver.device_ready, timeout=3000)
        yield p
    finally:
        manager.shutdown()


def column(p: FesPanel, col: int) -> list[str]:
    return [p.table.item(r, col).text() for r in range(p.table.rowCount())]


def test_load_start_knobs_stop(panel: FesPanel, qtbot) -> None:
    assert not panel.start_button.isEnabled()  # nothing loaded
    assert panel.load_profile_file(WRIST)
    assert panel.start_button.isEnabled()
    assert column(panel, 0) == ["3"] and column(panel, 1) == ["extensor carpi radialis"]
    assert column(panel, 2) == ["20.0"] and column(panel, 3) == ["200"]  # peak mA / µs at scale 1
    panel.current_knob.dial.setValue(50)  # 0.50 ×
    assert panel.driver.current_scale == pytest.approx(0.5)
    assert column(panel, 2) == ["10.0"] and panel.current_knob.value_label.text() == "0.50 ×"
    panel.start_button.click()  # the start's acks come back on the FES queue's thread; the GUI does not wait
    qtbot.waitUntil(lambda: panel.driver.stimulating and "Stimulating" in panel.status_label.text(), timeout=3000)
    assert not panel.load_button.isEnabled()
    qtbot.waitUntil(lambda: int(column(panel, 4)[0]) > 0, timeout=3000)  # "Now mA" is what was sent
    panel.stop_button.click()
    assert not panel.driver.stimulating
    qtbot.waitUntil(lambda: column(panel, 7) == ["off"], timeout=1000)


def test_knob_stops_at_the_cap_and_says_so(panel: FesPanel, qtbot) -> None:
    assert panel.load_profile_file(FRONTAL)  # ch 1 peaks at 28 mA; the configured cap is 40 mA
    for _ in range(20):  # raised one step per action, up to the cap
        panel.current_knob.dial.setValue(panel.current_knob.dial.value() + 5)
    panel.current_knob.dial.setValue(200)
    applied = panel.driver.current_scale
    assert applied == pytest.approx(40 / 28)
    assert panel.current_knob.dial.value() == round(applied * 100)  # the dial jumped back to the cap
    qtbot.waitUntil(lambda: "current cap 40 mA" in panel.message.text(), timeout=1000)
    assert "stops at 1.43" in panel.message.text()
    assert column(panel, 2)[0] == "40.0"


def test_keyboard_turns_the_knob(panel: FesPanel, qtbot) -> None:
    assert panel.load_profile_file(FRONTAL)
    panel.width_knob.dial.setFocus()
    qtbot.keyClick(panel.width_knob.dial, Qt.Key.Key_PageDown)
    assert panel.driver.pulse_width_scale == pytest.approx(0.95)
    qtbot.keyClick(panel.width_knob.dial, Qt.Key.Key_End)  # never a jump to the top
    assert panel.driver.pulse_width_scale == pytest.approx(1.0)


@pytest.mark.parametrize("knob", ["current_knob", "width_knob"])
def test_a_click_anywhere_on_a_knob_changes_the_scale_by_at_most_one_step(panel: FesPanel, qtbot, knob) -> None:
    """Issue #19: one click set 1.00 -> 0.00×, another 0.05 -> 1.73× (QDial puts the value under the pointer)."""
    assert panel.load_profile_file(WRIST)
    dial = getattr(panel, knob).dial
    read = (lambda: panel.driver.current_scale) if knob == "current_knob" else (lambda: panel.driver.pulse_width_scale)
    panel.driver.set_current_scale(0.05, "test") if knob == "current_knob" else panel.driver.set_pulse_width_scale(
        0.05, "test")
    panel.refresh()
    qtbot.waitExposed(panel)
    rect = dial.rect()
    for start in (0.05, 1.0):
        for x in range(2, rect.width() - 2, max(1, rect.width() // 9)):
            for y in range(2, rect.height() - 2, max(1, rect.height() // 9)):
                before = read()
                qtbot.mouseClick(dial, Qt.MouseButton.LeftButton, pos=QPoint(x, y))
                assert abs(read() - before) <= 0.01 + 1e-9, f"click at {x},{y}: {before} -> {read()}"
        if knob == "current_knob":
            panel.driver.set_current_scale(start, "test")
        else:
            panel.driver.set_pulse_width_scale(start, "test")
        panel.refresh()
    # A drag changes it gradually, a wheel notch by one unit.
    before = read()
    qtbot.mousePress(dial, Qt.MouseButton.LeftButton, pos=rect.center())
    qtbot.mouseMove(dial, rect.center() + QPoint(0, -rect.height()))  # a fast flick far up
    qtbot.mouseRelease(dial, Qt.MouseButton.LeftButton, pos=rect.center() + QPoint(0, -rect.height()))
    assert 0 < read() - before <= MAX_RISE_PER_ACTION + 1e-9


def test_malformed_profile_is_rejected_with_its_line_and_nothing_changes(panel: FesPanel, tmp_path: Path) -> None:
    assert panel.load_profile_file(FRONTAL)
    before = panel.driver.profile
    bad = tmp_path / "bad.yaml"
    text = FRONTAL.read_text(encoding="utf-8").replace("level: 28.0", "level: lots")
    bad.write_text(text, encoding="utf-8")
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if "level: lots" in ln)
    assert not panel.load_profile_file(bad)
    assert f"bad.yaml:{line}:" in panel.message.text()
    assert "channels.1.current_ma.level" in panel.message.text()
    assert panel.driver.profile is before
    broken = tmp_path / "broken.yaml"
    broken.write_text("version: 1\nname: x\naxis: [phase\n", encoding="utf-8")
    assert not panel.load_profile_file(broken)
    assert "broken.yaml:" in panel.message.text() and "not valid YAML" in panel.message.text()
    assert panel.driver.profile is before


def test_refusals_are_shown(panel: FesPanel, tmp_path: Path) -> None:
    hot = tmp_path / "hot.yaml"
    hot.write_text(WRIST.read_text(encoding="utf-8").replace("level: 20.0", "level: 90.0"), encoding="utf-8")
    assert load_profile(hot).channels[3].current_ma.level == 90.0  # a valid file...
    assert not panel.load_profile_file(hot)  # ...above the configured cap
    assert "above the cap of 40 mA" in panel.message.text()
    panel.load_profile_file(WRIST)
    panel.manager.supervisor.emergency_stop("test", "pressed")
    panel.start()
    assert "Not started" in panel.message.text() and "emergency stop is latched" in panel.message.text()
    panel.refresh()
    assert "emergency stop latched" in panel.status_label.text()


def test_edit_profile_opens_the_editor_and_applies(panel: FesPanel, qtbot) -> None:
    from app.ui.fes_editor import FesProfileEditor

    panel.load_profile_file(FRONTAL)
    panel.edit_button.click()
    editor = panel.editor
    assert isinstance(editor, FesProfileEditor)
    qtbot.waitExposed(editor)
    editor.set_cell("current", 0, 3, "20")  # ch 1 level 28 → 20 mA
    editor.apply_button.click()
    assert panel.driver.profile.channels[1].current_ma.level == 20.0
    editor.close()


def test_panel_without_fes(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={})
    p = FesPanel(manager)
    qtbot.addWidget(p)
    assert not p.start_button.isEnabled() and "off" in p.status_label.text()


def test_screenshot_fes_manager(panel: FesPanel, qtbot) -> None:
    panel.load_profile_file(FRONTAL)
    panel.current_knob.dial.setValue(120)
    panel.driver.set_phase(0.3)
    panel.start_button.click()
    qtbot.waitUntil(lambda: int(column(panel, 4)[0]) >= 20, timeout=4000)
    panel.refresh()
    out = screenshot_path("fes-manager.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    image = panel.grab().toImage()
    assert image.width() >= 800
    tmp = out.with_suffix(".tmp.png")
    assert image.save(str(tmp))
    shutil.move(tmp, out)
    panel.stop()


def test_the_requested_rate_is_shown_and_the_delivered_one_explained(panel: FesPanel, qtbot) -> None:
    """Issue #19: a 30 Hz profile was shown as "29.9 Hz" without a word."""
    assert panel.load_profile_file(WRIST)
    panel.start_button.click()
    qtbot.waitUntil(lambda: panel.driver.channel_list is not None, timeout=3000)
    panel.refresh()
    text = panel.profile_label.text()
    delivered = panel.driver.channel_list.frequency_hz
    assert "30 Hz" in text
    if abs(delivered - 30.0) >= 0.05:
        assert f"delivered {delivered:.1f} Hz" in text and "time steps" in text
    panel.stop_button.click()


@pytest.mark.realtime
@pytest.mark.sim_in_thread  # the simulator's core is reached to withhold an ack
def test_start_does_not_block_the_gui_thread_while_the_stimulator_has_not_answered(panel: FesPanel, qtbot) -> None:
    """Issue #29: Start waited for the channel list init's ack on the GUI thread (up to ack_timeout_s). Now the
    click returns at once, the button says "Starting…", and a missing ack is said in plain words."""
    assert panel.load_profile_file(WRIST)
    sim = panel.manager.devices["fes"].simulator
    sim.with_core(lambda core: core.inject_no_ack(1))  # the init's ack never comes
    t0 = time.monotonic()
    panel.start_button.click()
    blocked = time.monotonic() - t0
    assert blocked < 0.1, f"the GUI thread waited {blocked * 1000:.0f} ms in Start"
    assert panel.start_button.text() == "Starting…" and not panel.start_button.isEnabled()
    qtbot.waitUntil(lambda: "Not started" in panel.message.text(), timeout=3000)
    assert "did not acknowledge the channel list init" in panel.message.text()
    assert not panel.driver.stimulating and panel.start_button.text() == "&Start stimulation"
    sim.with_core(lambda core: core.clear_faults())
    panel.start_button.click()
    qtbot.waitUntil(lambda: panel.driver.stimulating and "Stimulating." in panel.message.text(), timeout=3000)
    panel.stop_button.click()
    assert not panel.driver.stimulating
