"""Delivered = shown (issue #36): the electrode set-up runs with the assistance's pulse-width override off, at the
pulse width its dialog shows (before: the dialog said 250 µs, the bursts on the wire were the assistance's
≤ 160 µs); the override is recorded and shown on the FES tab; a time-based profile's end is said."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from app.core import streams
from app.core.config import AppConfig
from app.devices import linarm, rehastim
from app.manager import LinarmppManager
from app.therapy.electrodes import SetupPlan
from app.therapy.patients import PatientProfile

pytestmark = pytest.mark.realtime


def test_the_electrode_set_up_stimulates_at_the_pulse_width_its_dialog_shows(qtbot: Any) -> None:
    from app.ui.electrode_setup import ElectrodeSetupDialog
    from app.ui.fes_panel import FesPanel

    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create, "fes": rehastim.create})
    events: list[tuple[str, dict[str, Any]]] = []
    manager.bus.listen("test", lambda r: events.append((r.kind, r.data)))
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


def test_a_cap_raised_in_the_patients_window_applies_to_the_running_session_at_once(
        qtbot: Any, tmp_path: Any, monkeypatch: Any) -> None:
    """Before #36: raised from 20 to 30 mA in the Patients window, the cap stayed 20 mA for the rest of the
    session, silently. Lowered again, it applies at once too."""
    from PySide6.QtWidgets import QTableWidgetItem

    from app.core.fes_profile import load_profile
    from app.therapy.patients import ClinicalChannelCap, PatientFes, save_patient
    from app.ui.patients_window import PatientsDialog

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    cfg = AppConfig()
    save_patient(PatientProfile("PZ-CAP", fes=PatientFes(caps={3: ClinicalChannelCap(max_current_ma=20.0)})),
                 safety=cfg.safety)
    manager = LinarmppManager(cfg, factories={"fes": rehastim.create})
    manager.start()
    try:
        fes = manager.driver("fes")
        qtbot.waitUntil(lambda: fes.device_ready, timeout=5000)
        manager.start_session("PZ-CAP", "Dr Bianchi", root=tmp_path / "sessions")
        wrist = load_profile(rehastim_profiles() / "wrist_extension_time.yaml").with_scales(current_scale=1.25)
        with pytest.raises(Exception, match="above the cap of 20 mA"):  # 25 mA
            fes.load_profile(wrist, "FES panel")
        patients = PatientsDialog(cfg.safety, manager=manager)
        qtbot.addWidget(patients)
        patients.show()
        qtbot.waitUntil(lambda: patients.loaded, timeout=5000)  # read on a thread of its own
        patients.search.setText("PZ-CAP")
        edit = patients.edit_profile()
        edit.caps_table.setItem(2, 0, QTableWidgetItem("30"))
        edit.accept()
        qtbot.waitUntil(lambda: patients.session_note.isVisibleTo(patients), timeout=3000)
        assert "channel 3 current cap 20 mA → 30 mA" in patients.session_note.text()
        assert "running session at once" in patients.session_note.text()
        fes.load_profile(wrist, "FES panel")  # the next command meets the new cap
        assert manager.patient_profile.fes.caps[3].max_current_ma == 30.0
        edit = patients.edit_profile()
        edit.caps_table.setItem(2, 0, QTableWidgetItem("15"))
        edit.accept()
        qtbot.waitUntil(lambda: "30 mA → 15 mA" in patients.session_note.text(), timeout=3000)
        with pytest.raises(Exception, match="above the cap of 15 mA"):
            fes.load_profile(wrist, "FES panel")
        patients.close()
        folder = manager.recorder.folder
        manager.end_session()
        import json

        kinds = [json.loads(line) for line in (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()]
        updates = [e["data"]["changes"] for e in kinds if e["kind"] == "patient_profile_updated"]
        assert updates == [["channel 3 current cap 20 mA → 30 mA"], ["channel 3 current cap 30 mA → 15 mA"]]
    finally:
        manager.shutdown()


def rehastim_profiles() -> Any:
    from app.core.config import RESOURCES

    return RESOURCES / "fes_profiles"
