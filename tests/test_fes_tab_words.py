"""The FES tab says what is delivered (issue #36): a time profile that ends says so (it went on saying
"Stimulating."), a long refusal never squeezes the buttons (16 px high at 1366×768), a run holding the stimulator
is named and the tab's Start is refused with a sentence (the panel on a simulated RehaStim)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from app.ui.fes_panel import FesPanel
from tests.test_fes_panel import panel  # noqa: F401 -- the FES tab on a simulated RehaStim

SHORT = """\
version: 1
name: One second (test)
axis: time
frequency_hz: 30.0
channels:
  3:
    muscle: extensor carpi radialis
    mode: single
    current_ma: {level: 6.0, ramp_up: [0.0, 0.3], ramp_down: [0.7, 1.0], baseline: 0.0}
    pulse_width_us: {level: 150.0, ramp_up: [0.0, 0.3], ramp_down: [0.7, 1.0], baseline: 0.0}
"""


def test_a_time_profile_that_ends_says_it_ended(panel: FesPanel, qtbot: Any, tmp_path: Path) -> None:  # noqa: F811
    path = tmp_path / "short.yaml"
    path.write_text(SHORT, encoding="utf-8")
    assert panel.load_profile_file(path)
    panel.start()
    qtbot.waitUntil(lambda: panel.message.text() == "Stimulating.", timeout=5000)
    qtbot.waitUntil(lambda: not panel.driver.stimulating, timeout=5000)
    qtbot.waitUntil(lambda: "ended" in panel.message.text(), timeout=2000)
    assert panel.message.text() == "Stimulation ended: the time profile finished (1 s)."
    assert "Stimulating" not in panel.status_label.text()


def test_a_long_refusal_does_not_squeeze_the_buttons(panel: FesPanel, qtbot: Any) -> None:  # noqa: F811
    panel.resize(700, 420)
    tall = {b: b.sizeHint().height() for b in (panel.start_button, panel.stop_button, panel.load_button)}
    panel.show_message("Not started: " + "profile 'Frontal reaching' refused: channel 1: the profile reaches 28 mA, "
                       "above the cap of 20 mA; " * 6, "bad")
    qtbot.wait(50)
    for button, height in tall.items():
        assert button.height() >= height, (button.text(), button.height(), height)


def test_a_run_holding_the_stimulator_is_named_and_the_tab_refused(panel: FesPanel, qtbot: Any) -> None:  # noqa: F811
    from app.core.ownership import RUN_SOURCES, Lease

    sup = panel.manager.supervisor
    assert not panel.held_by.isVisibleTo(panel)
    assert panel.load_profile_file(Path(__file__).resolve().parents[1] / "resources" / "fes_profiles"
                                   / "wrist_extension_time.yaml")
    sup.take_lease(Lease("run-9", "Assisted reaching with FES", frozenset({"robot", "stimulator"}), RUN_SOURCES))
    qtbot.waitUntil(lambda: panel.held_by.isVisibleTo(panel), timeout=2000)
    assert panel.held_by.text().startswith("Stimulator held by: Assisted reaching with FES")
    panel.start()
    qtbot.waitUntil(lambda: panel.message.text().startswith("Not started"), timeout=3000)
    assert "the stimulator is held by Assisted reaching with FES" in panel.message.text()
    assert not panel.driver.stimulating
    sup.release_lease("run-9", "finished")
    qtbot.waitUntil(lambda: not panel.held_by.isVisibleTo(panel), timeout=2000)
