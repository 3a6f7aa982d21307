"""The electrode set-up dialog (issue #32): its plot and table from a set-up, the discomfort ratings, the
choice saved in the patient's profile, the FES panel's button, and one run on the simulated devices.

The tests that need devices share the module's rig (tests/rigs.py, #38: the simulators in their own process, as the
app runs them), put back in the known state between them; the reset checks what a set-up leaves (stimulation, caps,
district channels, its lease and bus queue, the robot's hold)."""

from __future__ import annotations

import shutil

import pytest

from app.core.config import AppConfig
from app.devices.sim.patient import SimulatedPatient
from app.manager import LinarmppManager
from app.safety.fes_limits import FesLimits
from app.therapy.electrodes import Combination, District, ElectrodeSetup, SetupPlan
from app.therapy.patients import PatientProfile, load_patient
from app.ui.electrode_setup import COLUMNS, ElectrodeSetupDialog
from tests.conftest import screenshot_path
from tests.rigs import RigSpec
from tests.test_electrodes import Rig

DELTOID = District("anterior deltoid", tuple(Combination(ch, e) for ch, e in
                                             ((1, "1-2"), (2, "3-4"), (3, "1-3"), (4, "2-4"))), "positive")


@pytest.fixture(scope="module")
def shared_rig_spec() -> RigSpec:
    return RigSpec(devices=("linarm", "fes"), host="process")  # homed at power-up: the homing has its own tests


def a_result():
    patient = SimulatedPatient(seed=11)
    patient.set_electrode_distances({1: 2.0, 2: 0.866, 3: 1.5, 4: 0.5})
    return ElectrodeSetup(DELTOID, SetupPlan(ceiling_ma=30.0), FesLimits(), Rig(patient).ports()).run()


@pytest.fixture
def dialog(qtbot):
    manager = LinarmppManager(AppConfig(), factories={})
    d = ElectrodeSetupDialog(manager)
    qtbot.addWidget(d)
    yield d
    d.close()


def cell(d: ElectrodeSetupDialog, row: int, col: int) -> str:
    return d.table.item(row, col).text()


def test_screenshot_and_table_at_1366(dialog, qtbot) -> None:
    result = a_result()
    dialog.resize(1366, 768)
    dialog.show()
    qtbot.waitExposed(dialog)
    dialog.show_result(result)
    assert [cell(dialog, r, 0) for r in range(4)] == ["1", "2", "3", "4"]
    assert "proposed" in cell(dialog, 3, 1) and cell(dialog, 3, 4) != "—"
    assert dialog.proposal_label.text().startswith("Proposed: channel 4")
    assert dialog.accept_button.isEnabled() and dialog.pick_button.isEnabled()
    curves = {ch: c.getData() for ch, c in dialog._curves.items()}
    assert len(curves[4][0]) == len(SetupPlan(ceiling_ma=30.0).ladder(30)) and max(curves[4][1]) > 5
    assert dialog.table.columnCount() == len(COLUMNS)
    out = screenshot_path("electrode-setup-1366.png")
    image = dialog.grab().toImage()
    assert (image.width(), image.height()) == (1366, 768)
    tmp = out.with_suffix(".tmp.png")
    assert image.save(str(tmp))
    shutil.move(tmp, out)


def test_discomfort_rating_changes_the_proposal(dialog) -> None:
    dialog.show_result(a_result())
    spin = dialog.table.cellWidget(3, len(COLUMNS) - 1)
    assert spin.specialValueText() == "not rated"
    spin.setValue(9)  # channel 4 hurts
    assert dialog.result.combination(4).discomfort == 9
    assert dialog.proposal_label.text().startswith("Proposed: channel 2")
    spin.setValue(spin.minimum())
    assert dialog.result.combination(4).discomfort is None
    assert dialog.proposal_label.text().startswith("Proposed: channel 4")


def test_the_choice_is_saved_and_recorded(dialog) -> None:
    events: list[tuple[str, dict]] = []
    dialog.manager.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    dialog.manager.patient_profile = PatientProfile("UI7")
    dialog.manager.operator = "therapist U"
    dialog.show_result(a_result())
    dialog.table.selectRow(1)
    assert dialog.use_selected()  # the therapist picks channel 2 instead of the proposed 4
    stored = load_patient("UI7").fes.electrodes["anterior deltoid"]
    assert (stored.channel, stored.proposed_channel, stored.chosen_by) == (2, 4, "therapist U")
    choice = next(d for k, d in events if k == "electrode_choice")
    assert choice["channel"] == 2 and not choice["accepted_proposal"] and choice["saved"]
    assert "saved in UI7's profile" in dialog.status.text()
    assert dialog.accept_proposal()
    assert load_patient("UI7").fes.electrodes["anterior deltoid"].channel == 4


def test_without_devices_the_setup_does_not_start(dialog) -> None:
    assert not dialog.start()
    assert "needs the stimulator" in dialog.status.text()


def test_the_fes_panel_opens_the_setup(shared_manager, qtbot) -> None:
    from app.ui.fes_panel import FesPanel

    panel = FesPanel(shared_manager)
    qtbot.addWidget(panel)
    panel.electrodes_button.click()
    assert isinstance(panel.electrode_dialog, ElectrodeSetupDialog) and panel.electrode_dialog.isVisible()
    assert panel.electrode_dialog.district_box.currentText() == "anterior deltoid"
    panel.electrode_dialog.close()


@pytest.mark.slow
@pytest.mark.realtime
def test_the_dialog_on_the_simulated_devices(shared_manager, qtbot) -> None:
    manager = shared_manager  # the robot homed, IDLE at the home position
    fes = manager.driver("fes")
    manager.patient.set_electrode_distances({1: 2.0, 2: 0.5, 3: 1.5, 4: 0.866})
    manager.patient_profile = PatientProfile("UI8")
    d = ElectrodeSetupDialog(manager)
    qtbot.addWidget(d)
    d.show()
    # one burst per combination (12 mA: above the best sites' motor threshold; the ladder is test_electrodes')
    assert d.start(SetupPlan(ceiling_ma=12.0, start_ma=12.0, step_ma=4.0, ramp_s=0.0, hold_s=0.4,
                             measure_s=0.2, baseline_s=0.15, rest_s=0.1))
    assert not d.start_button.isEnabled() and d.stop_button.isEnabled()
    qtbot.waitUntil(lambda: not d.running and d.start_button.isEnabled(), timeout=60000)
    assert d.progress.value() == 4, (d.status.text(), d.result.aborted)  # 4 combinations x 12 mA
    assert [len(r.bursts) for r in d.result.combinations] == [1, 1, 1, 1]
    assert d.result.proposal.channel == 2, d.result.proposal
    assert d.accept_proposal()
    assert fes.district_channels == {"anterior deltoid": 2}
    assert load_patient("UI8").fes.electrodes["anterior deltoid"].channel == 2
    d.close()


def test_editing_the_patient_keeps_the_chosen_electrodes(qtbot) -> None:
    """The Patients dialog does not show the electrode choices; saving the form must not drop them."""
    from dataclasses import replace

    from app.therapy.patients import ElectrodeChoice
    from app.ui.patient_dialog import PatientDialog

    profile = PatientProfile("PD1")
    profile = replace(profile, fes=replace(profile.fes, electrodes={
        "triceps": ElectrodeChoice(6, "3-4", "2026-11-25T22:00:00+00:00", "therapist D", 5, 0.4, 12.0, 2)}))
    d = PatientDialog(profile, AppConfig().safety)
    qtbot.addWidget(d)
    d.notes.setPlainText("edited")
    edited = d.validate()
    assert edited is not None and edited.notes == "edited"
    assert edited.fes.electrodes == profile.fes.electrodes


def test_a_session_applies_the_patients_electrodes_and_its_end_forgets_them(shared_manager, tmp_path) -> None:
    from dataclasses import replace

    from app.therapy.patients import ElectrodeChoice, save_patient

    profile = PatientProfile("SE1")
    save_patient(replace(profile, fes=replace(profile.fes, electrodes={"triceps": ElectrodeChoice(7, "1-3")})))
    manager = shared_manager
    fes = manager.driver("fes")
    manager.start_session("SE1", "therapist", root=tmp_path)
    assert fes.district_channels == {"triceps": 7}
    manager.end_session()
    assert fes.district_channels == {}
