"""Issue #30: the FES editor says "valid" only for a profile the stimulator will accept now (the stimulator's
range, the site's configuration, the patient's clinical cap), naming the limit that refuses; a refusal of
Apply appears in the editor, not behind it; profile files are asked for in the user's folder, and the bundled
examples are read-only."""

from __future__ import annotations

from collections.abc import Iterator
from html import unescape
from pathlib import Path
from typing import Any

import pytest

from app.core.config import AppConfig
from app.core.fes_profile import load_profile
from app.core.paths import fes_profiles_dir
from app.devices import rehastim
from app.manager import LinarmppManager
from app.safety.fes_limits import ChannelCaps, FesLimits, profile_limit_problems
from app.ui import file_dialogs
from app.ui.fes_editor import CUR_TRAP0, FesProfileEditor
from app.ui.fes_panel import PROFILES_DIR, FesPanel

FRONTAL = PROFILES_DIR / "frontal_reaching.yaml"  # channel 1 (anterior deltoid) peaks at 28 mA


def editor_with(qtbot, limits: FesLimits | None, patient: str = "P9") -> FesProfileEditor:
    e = FesProfileEditor(load_profile(FRONTAL), limits=lambda: (limits, patient))
    qtbot.addWidget(e)
    e.show()
    return e


def test_a_profile_above_the_patients_cap_is_not_called_valid(qtbot) -> None:
    caps = FesLimits(clinical_caps={1: ChannelCaps(40.0, 300.0)})
    e = editor_with(qtbot, caps)
    assert "Profile is valid" in e.problems_label.text() and e.apply_button.isEnabled()
    e.set_cell("current", 0, CUR_TRAP0, "60")  # channel 1's level: 60 mA
    text = unescape(e.problems_label.text())
    assert "Profile is valid" not in text
    assert "Channel 1" in text and "60 mA" in text and "patient P9's clinical cap for channel 1 of 40 mA" in text
    assert not e.apply_button.isEnabled()
    assert e.save_button.isEnabled()  # a file may still be kept (for another patient): only Apply is barred


def test_the_tightest_layer_is_named() -> None:
    site = FesLimits(max_current_ma=30.0)
    assert profile_limit_problems(site, {2: (35.0, 100.0)}) == [
        "Channel 2: peak current 35 mA is above the site's limit (configuration, every channel) of 30 mA."]
    per_channel = FesLimits(channel_caps={2: ChannelCaps(20.0, 150.0)}, clinical_caps={2: ChannelCaps(25, 300)})
    problems = profile_limit_problems(per_channel, {2: (22.0, 200.0)}, "P1")
    assert problems == ["Channel 2: peak current 22 mA is above the site's cap for channel 2 of 20 mA.",
                        "Channel 2: peak pulse width 200 µs is above the site's cap for channel 2 of 150 µs."]
    assert profile_limit_problems(FesLimits(), {1: (40.0, 300.0)}) == []


@pytest.fixture
def panel(qtbot) -> Iterator[FesPanel]:
    manager = LinarmppManager(AppConfig(), factories={"fes": rehastim.create})
    manager.start()
    try:
        p = FesPanel(manager)
        qtbot.addWidget(p)
        p.show()
        qtbot.waitUntil(lambda: p.driver is not None and p.driver.device_ready, timeout=3000)
        yield p
    finally:
        manager.shutdown()


def test_the_panels_editor_judges_against_the_stimulators_limits_and_shows_refusals(panel: FesPanel, qtbot) -> None:
    driver = panel.driver
    assert driver is not None
    driver.set_clinical_caps({1: ChannelCaps(40.0, 300.0)})  # as a patient's profile does at session start
    assert panel.load_profile_file(FRONTAL)
    panel.open_editor()
    editor = panel.editor
    editor.set_cell("current", 0, CUR_TRAP0, "60")
    assert "clinical cap for channel 1 of 40 mA" in unescape(editor.problems_label.text())
    assert not editor.apply_button.isEnabled()
    editor.set_cell("current", 0, CUR_TRAP0, "30")
    assert editor.apply_button.isEnabled()
    panel.start()
    qtbot.waitUntil(lambda: driver.stimulating, timeout=3000)
    editor.apply()  # refused by the driver (stimulating): said in the editor itself
    assert "stop stimulation" in editor.problems_label.text().lower()
    panel.stop()
    qtbot.waitUntil(lambda: not driver.stimulating, timeout=3000)
    editor.apply()
    assert "Applied to the stimulator" in editor.problems_label.text()
    assert driver.profile is not None and driver.profile.peaks()[1][0] == 30.0
    editor.close()


def test_profile_files_are_asked_for_in_the_users_folder(panel: FesPanel, qtbot, monkeypatch,
                                                          tmp_path: Path) -> None:
    asked: list[tuple[str, Path, tuple[Path, ...]]] = []

    def ask_open(_parent: Any, title: str, start: Path, _filters: str, places: Any = ()) -> str:
        asked.append((title, Path(start), tuple(places)))
        return ""
    monkeypatch.setattr(file_dialogs, "ask_open_file", ask_open)
    panel.choose_profile_file()
    assert asked[-1][1] == fes_profiles_dir() and PROFILES_DIR in asked[-1][2]
    editor = FesProfileEditor(load_profile(FRONTAL))
    qtbot.addWidget(editor)
    editor.path = FRONTAL  # a bundled example, opened as the panel opens it
    editor.choose_file()
    assert asked[-1][1] == fes_profiles_dir()

    saved_to: list[Path] = []
    bundled_before = FRONTAL.read_bytes()

    def ask_save(_parent: Any, _title: str, start: Path, _filters: str, _suffix: str = "") -> str:
        saved_to.append(Path(start))
        return str(answer)
    monkeypatch.setattr(file_dialogs, "ask_save_file", ask_save)
    answer = FRONTAL  # the user picks the bundled file itself: refused in words, nothing written
    assert not editor.save()
    assert saved_to[-1] == fes_profiles_dir() / FRONTAL.name
    assert "read-only" in editor.problems_label.text() and FRONTAL.read_bytes() == bundled_before
    answer = fes_profiles_dir() / "my_frontal.yaml"
    assert editor.save()
    assert answer.exists() and editor.path == answer
    assert load_profile(answer).peaks() == load_profile(FRONTAL).peaks()
