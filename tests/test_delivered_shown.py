"""Delivered = shown (issue #36): the electrode set-up runs with the assistance's pulse-width override off, at the
pulse width its dialog shows (before: the dialog said 250 µs, the bursts on the wire were the assistance's
≤ 160 µs); the override is recorded and shown on the FES tab; a time-based profile's end is said."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from app import streams
from app.config import AppConfig
from app.devices import linarm, rehastim
from app.electrodes import SetupPlan
from app.manager import LinarmppManager
from app.patients import PatientProfile

pytestmark = pytest.mark.realtime


def test_the_electrode_set_up_stimulates_at_the_pulse_width_its_dialog_shows(qtbot: Any) -> None:
    from app.ui.electrode_setup import ElectrodeSetupDialog
    from app.ui.fes_panel import FesPanel

    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create, "fes": rehastim.create})
    events: list[tuple[str, dict[str, Any]]] = []
    manager.supervisor.add_event_subscriber(lambda kind, data: events.append((kind, data)))
    manager.start()
    widths: list[float] = []
    sub = None
    try:
        robot, fes = manager.driver("linarm"), manager.driver("fes")
        qtbot.waitUntil(lambda: manager.all_connected() and fes.device_ready, timeout=5000)
        robot.command("goToHome", source="test", timeout_s=2.0)
        qtbot.waitUntil(lambda: (s := robot.latest("linarm.state")) is not None and s.homeState == 4, timeout=30000)
        # The patient model's α sets the FES pulse width (the assistance split): 100 + 0.5·0.3·200 = 130 µs.
        manager.assistance.update_alpha(0.3)
        assert fes.pulse_width_override == pytest.approx(130.0)
        panel = FesPanel(manager)  # the override is shown where the pulse width is set
        qtbot.addWidget(panel)
        panel.refresh()
        assert panel.width_lock_note.isVisibleTo(panel) and "130 µs" in panel.width_lock_note.text()
        manager.patient_profile = PatientProfile("PW1")
        dialog = ElectrodeSetupDialog(manager)
        qtbot.addWidget(dialog)
        dialog.show()
        sub = manager.bus.subscribe("test-widths", (streams.FES_CHANNELS,), maxlen=100000)
        stop = threading.Event()

        def keep_alpha() -> None:  # the model keeps sending α during the set-up (100 Hz in the app)
            while not stop.wait(0.05):
                manager.assistance.update_alpha(0.3)

        feeder = threading.Thread(target=keep_alpha, daemon=True)
        feeder.start()
        shown = float(dialog.pulse_width.value())
        assert dialog.start(SetupPlan(ceiling_ma=8.0, start_ma=8.0, step_ma=4.0, pulse_width_us=shown, ramp_s=0.0,
                                      hold_s=0.4, measure_s=0.2, baseline_s=0.15, rest_s=0.1))
        qtbot.waitUntil(lambda: not dialog.running, timeout=60000)
        stop.set()
        feeder.join(2.0)
        for item in sub.drain():
            s = item.sample
            for ch in range(1, 9):
                if getattr(s, f"current{ch}") > 0:
                    widths.append(getattr(s, f"pulseWidth{ch}"))
        assert widths, (dialog.status.text(), dialog.result.aborted)
        # (a burst's width rises with its ramp, at the limiter's rate): each burst reaches what the dialog shows
        assert max(widths) == shown, f"bursts on the wire up to {max(widths)} µs, the dialog shows {shown}"
        kinds = [k for k, _d in events]
        assert "fes_pulse_width_override" in kinds  # taken off, recorded
        refused = [d for k, d in events if k == "lease_refused"]
        assert any(d["source"] == "assistance" and d["what"] == "pulse width override" for d in refused)
        # Given back when the set-up ends: the next α applies it again, and the FES tab says so.
        manager.assistance.update_alpha(0.3, now=1e9)
        assert fes.pulse_width_override == pytest.approx(130.0)
    finally:
        if sub is not None:
            sub.close()
        manager.shutdown()
