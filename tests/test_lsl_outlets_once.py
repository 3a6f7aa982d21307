"""The live LSL streams are opened once, whatever starts them (issue #41): a headless run that also starts a
session used to open every outlet twice (the run's start_lsl and the session's), and only one of the two event
outlets carried the markers — LabRecorder users saw each stream twice and could record the silent one."""

from __future__ import annotations

import collections
from dataclasses import replace

import pytest

from app.core.config import AppConfig
from app.session import lsl
from tests.fakes import counter_factory

AVAILABLE, STATUS = lsl.lsl_status()


@pytest.mark.skipif(not AVAILABLE, reason=f"liblsl cannot be loaded on this platform: {STATUS}")
def test_a_headless_run_that_starts_a_session_opens_each_outlet_once(tmp_path, qtbot, monkeypatch) -> None:
    import pylsl

    from app.devices import registry
    from app.scripting import headless

    opened: collections.Counter[str] = collections.Counter()
    markers: collections.Counter[str] = collections.Counter()
    real_outlet = pylsl.StreamOutlet

    class CountingOutlet(real_outlet):  # type: ignore[misc,valid-type]
        def __init__(self, info, *args, **kwargs) -> None:
            super().__init__(info, *args, **kwargs)
            self.counted_name = f"{info.name()}#{opened[info.name()]}"
            opened[info.name()] += 1

        def push_sample(self, x, timestamp=0.0, pushthrough=True) -> None:
            markers[self.counted_name] += 1
            super().push_sample(x, timestamp, pushthrough)

    monkeypatch.setattr(pylsl, "StreamOutlet", CountingOutlet)
    monkeypatch.setattr(registry, "default_factories", lambda config: {"counter": counter_factory(tmp_path)})
    monkeypatch.setattr(headless, "_let_the_record_show_the_safe_state", lambda manager, app: None)
    script = tmp_path / "s.py"
    script.write_text("x = 1\n", encoding="utf-8")
    cfg = AppConfig()
    cfg = replace(cfg, recording=replace(cfg.recording, lsl=True))

    def prepare(manager) -> None:  # the run also starts a session (a patient, an operator, its recording)
        manager.start_session("P-LSL", "tester", root=tmp_path / "sessions")

    code = headless.run_headless(cfg, str(script), home_first=False, prepare=prepare,
                                 record_dir=str(tmp_path / "rec"), output=lambda stream, text: None)
    assert code == 0
    assert opened == {"counter.main": 1, lsl.EVENTS_STREAM: 1}, f"outlets opened: {dict(opened)}"
    assert markers[f"{lsl.EVENTS_STREAM}#0"] > 0, f"markers pushed per outlet: {dict(markers)}"
