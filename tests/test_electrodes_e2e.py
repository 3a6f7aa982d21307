"""The electrode set-up on the real simulated devices (issue #32): the LINarm and RehaStim simulators on their
links, the real drivers, the safety supervisor. Checked on the stimulator's wire (the bytes the simulated
RehaStim received, decoded with app/wire/sciencemode.py): the proposal, the ceiling and the patient's caps,
the emergency stop during a burst, and a district-addressed profile on the chosen channel afterwards.

One rig for the module (tests/rigs.py, #38): the simulators in their own process, as the app runs them, put back
in the known state between the tests (the reset checks the set-up's leftovers: stimulation, caps, district
channels, its lease and bus queue, the robot's hold). The plans test the procedure, not a count of steps: the
fewest bursts that still show the ladder, the cap and the proposal."""

from __future__ import annotations

import threading
import time

import pytest

from app.archive.station import save_choice
from app.core.config import RESOURCES
from app.core.fes_profile import load_profile, parse_profile
from app.safety.fes_limits import ChannelCaps
from app.therapy.electrodes import (
    Combination,
    District,
    SetupPlan,
    app_ports,
    choice_event,
    run_district_setup,
)
from app.therapy.patients import PatientProfile, load_patient
from app.wire.sciencemode import Sm1CommandDecoder, Sm1Init, Sm1Stop, Sm1Update
from tests.rigs import RigSpec

pytestmark = [pytest.mark.realtime, pytest.mark.slow]

# Channel 4: 12 and 16 mA; channel 2 (capped at 14 mA): 12 mA only -- the ladder, the ceiling and the cap in three
# bursts (8 mA, below both sites' motor threshold, measured nothing).
PLAN = SetupPlan(ceiling_ma=16.0, start_ma=12.0, step_ma=4.0, ramp_s=0.0, hold_s=0.5, measure_s=0.25,
                 baseline_s=0.2, rest_s=0.2)
DELTOID = District("anterior deltoid", (Combination(2, "3-4"), Combination(4, "2-4")), "positive")
DISTRICT_PROFILE = """
version: 1
name: deltoid by district (test)
axis: time
frequency_hz: 40.0
districts:
  anterior deltoid:
    current_ma: {level: 10.0, ramp_up: [0.0, 0.5], ramp_down: [1.0, 1.2]}
    pulse_width_us: {level: 200.0, ramp_up: [0.0, 0.5], ramp_down: [1.0, 1.2]}
"""


def wire(sim) -> list[tuple[float, object, tuple[int, ...]]]:
    """(time the device read it, command, the channel list in force) for everything the driver sent."""
    decoder = Sm1CommandDecoder()
    channels: tuple[int, ...] = ()
    out = []
    for t, data in list(sim.host_bytes_log):
        for msg in decoder.feed(data):
            if isinstance(msg, Sm1Init):
                channels = tuple(msg.config.channels)
            out.append((t, msg, channels))
    return out


def currents_on_the_wire(sim, since: float = 0.0) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for t, msg, channels in wire(sim):
        if t >= since and isinstance(msg, Sm1Update):
            for ch, s in zip(channels, msg.settings, strict=True):
                out.setdefault(ch, []).append(s.current_ma)
    return out


@pytest.fixture(scope="module")
def shared_rig_spec() -> RigSpec:
    return RigSpec(devices=("linarm", "fes"), host="process")  # homed at power-up: the homing has its own tests


@pytest.fixture
def rig(shared_manager):
    """The module's rig, in its known state (the robot homed, IDLE at the home position), the stimulator's wire
    logged from now on."""
    manager = shared_manager
    manager.devices["fes"].simulator.keep_host_log = True
    # the array: channel 4 is the best pair, channel 2 needs 20 % more current for the same force
    manager.patient.set_electrode_distances({2: 0.866, 4: 0.5})
    return manager


def run_setup(manager, plan: SetupPlan = PLAN, stopped=lambda: False):
    events: list[tuple[str, dict]] = []
    robot, fes = manager.driver("linarm"), manager.driver("fes")
    result = run_district_setup(fes, robot, manager.supervisor, robot.latest,  # the stream queued as the app does
                                lambda kind, data: events.append((kind, data)), DELTOID, plan, stopped,
                                bus=manager.bus)
    return result, events


def test_setup_on_the_simulated_devices(rig, qtbot, tmp_path) -> None:
    manager = rig
    fes, robot = manager.driver("fes"), manager.driver("linarm")
    sim = manager.devices["fes"].simulator
    fes.set_clinical_caps({2: ChannelCaps(max_current_ma=14.0)})  # the patient's cap on channel 2
    previous = load_profile(RESOURCES / "fes_profiles" / "wrist_extension_time.yaml")
    fes.load_profile(previous)
    t_start = time.monotonic()
    result, events = run_setup(manager)
    assert not result.aborted, result.aborted
    # (1) the proposal is the best pair; the measured response per mA of the two differs as the array does
    assert result.proposal.channel == 4, result.proposal
    ranking = dict(result.proposal.ranking)
    assert ranking[4] > 1.15 * ranking.get(2, 0.0)
    # never above the ceiling nor the patient's cap, on the wire
    on_wire = currents_on_the_wire(sim, t_start)
    assert max(on_wire[4]) == 16 and max(on_wire[2]) == 12  # 16 mA would be above the 14 mA cap: not tried
    assert all(ma <= 16 for values in on_wire.values() for ma in values)
    assert set(on_wire) == {2, 4}
    # every burst in the record, and the result
    assert [k for k, _ in events].count("electrode_burst") == 3 and events[-1][0] == "electrode_setup_result"
    # the robot held the arm (ON, position hold) and was given back as found
    state = robot.latest("linarm.state")
    assert state.controlState in (0, 2)
    # the stimulator has its profile back
    assert fes.profile == previous

    # (2) the choice saved in the patient's profile; a district profile then stimulates the chosen channel
    profile = save_choice(result, 4, PatientProfile("E2E1"), "therapist T", "", manager.config.safety)
    assert load_patient("E2E1").fes.electrodes["anterior deltoid"].channel == 4
    assert choice_event(result, profile.fes.electrodes["anterior deltoid"])["accepted_proposal"]
    fes.set_district_channels(profile.fes.district_channels())
    t_mark = time.monotonic()
    fes.load_profile(parse_profile(DISTRICT_PROFILE, "district.yaml"))
    fes.start_stimulation("test")
    qtbot.waitUntil(lambda: not fes.stimulating, timeout=4000)
    inits = [ch for t, msg, ch in wire(sim) if t >= t_mark and isinstance(msg, Sm1Init)]
    assert inits == [(4,)]
    assert max(currents_on_the_wire(sim, t_mark)[4]) == 10

    # the old channel-numbered examples still load and run, on their own channels
    fes.set_clinical_caps({})  # (the example's 25 mA on channel 2 is above this test patient's cap)
    for name, channels, phase in (("frontal_reaching.yaml", (1, 2, 5, 6), 0.3), ("wrist_extension_time.yaml", (3,),
                                                                                    None)):
        t_mark = time.monotonic()
        fes.load_profile(load_profile(RESOURCES / "fes_profiles" / name))
        fes.set_phase(phase)
        fes.start_stimulation("test")
        qtbot.waitUntil(lambda t_mark=t_mark: any(
            ma > 0 for values in currents_on_the_wire(sim, t_mark).values() for ma in values), timeout=4000)
        fes.stop_stimulation("test done", "test")
        assert [ch for t, msg, ch in wire(sim) if t >= t_mark and isinstance(msg, Sm1Init)] == [channels]
        assert set(currents_on_the_wire(sim, t_mark)) == set(channels)


def test_emergency_stop_during_a_burst(rig, qtbot) -> None:
    manager = rig
    fes, sim = manager.driver("fes"), manager.devices["fes"].simulator
    box: dict = {}
    worker = threading.Thread(target=lambda: box.update(zip(("result", "events"), run_setup(manager), strict=True)))
    worker.start()
    try:
        qtbot.waitUntil(lambda: any(ma >= 8 for values in currents_on_the_wire(sim).values() for ma in values),
                        timeout=8000)
        t0 = time.monotonic()
        manager.supervisor.emergency_stop("test", "pressed during an electrode test burst")
        worker.join(5.0)
    finally:
        if worker.is_alive():
            manager.supervisor.emergency_stop("test", "cleanup")
            worker.join(5.0)
    assert not worker.is_alive()
    # the tap stamps Stop when the simulator reads it: under load its thread may not have read it yet
    qtbot.waitUntil(lambda: any(t >= t0 and isinstance(msg, Sm1Stop) for t, msg, _ch in wire(sim)), timeout=2000)
    stop_t = next(t for t, msg, _ch in wire(sim) if t >= t0 and isinstance(msg, Sm1Stop))
    delay = stop_t - t0
    print(f"e-stop during a burst: Stop on the wire after {delay * 1000:.1f} ms")
    assert delay <= 0.1, f"Stop after {delay * 1000:.1f} ms"  # the bench's p99 target is 20 ms; CI gets slack
    result, events = box["result"], box["events"]
    assert "emergency stop" in result.aborted
    assert events[-1][0] == "electrode_setup_aborted"  # and the robot left as the e-stop put it (IDLE)
    # the robot's state as it reports it (its next sample: the latest one may predate the e-stop by a period)
    qtbot.waitUntil(lambda: manager.driver("linarm").latest("linarm.state").controlState == 0, timeout=2000)
    # nothing stimulates after the Stop: no update with current, no new channel list
    after = [(msg, ch) for t, msg, ch in wire(sim) if t > stop_t]
    assert not any(isinstance(m, Sm1Init) for m, _ in after)
    assert all(s.current_ma == 0 for m, _ in after if isinstance(m, Sm1Update) for s in m.settings)
    assert not fes.stimulating


def test_script_stop_ends_the_setup(rig, qtbot) -> None:
    manager = rig
    sim = manager.devices["fes"].simulator
    stop = threading.Event()
    box: dict = {}
    worker = threading.Thread(target=lambda: box.update(
        zip(("result", "events"), run_setup(manager, stopped=stop.is_set), strict=True)))
    worker.start()
    qtbot.waitUntil(lambda: any(ma >= 8 for values in currents_on_the_wire(sim).values() for ma in values),
                    timeout=8000)
    stop.set()
    worker.join(5.0)
    assert not worker.is_alive()
    assert box["result"].aborted == "stopped: the script was stopped"
    assert not manager.driver("fes").stimulating



def test_script_api_with_the_simulators_in_their_own_process(rig, qtbot) -> None:
    """As the app runs by default: the simulators (and the patient) in the simulator process, which hears the
    stimulator through its hook; the script API's fes.electrodeSetup runs the set-up and accepts the proposal."""
    from app.scripting.api import FESUser, ScriptContext

    manager = rig
    assert manager.simulators.out_of_process
    manager.patient.set_electrode_distances({1: 2.0, 2: 1.5, 3: 0.5, 4: 0.866})  # channel 3 is the best
    manager.patient_profile = PatientProfile("API1")
    manager.operator = "therapist S"
    context = ScriptContext(manager, source="test script")
    try:
        # one current per combination (12 mA: the ladder is the other tests') at the API's clinical timing
        summary = FESUser(context).electrodeSetup("anterior deltoid", 12, 12, 4, 250, True)
    finally:
        context.close()
    assert not summary["aborted"], summary["aborted"]
    assert summary["proposedChannel"] == 3 and summary["accepted"] == 3, summary
    assert [c["channel"] for c in summary["combinations"]] == [1, 2, 3, 4]
    assert all(len(c["bursts"]) == 1 for c in summary["combinations"])
    assert load_patient("API1").fes.electrodes["anterior deltoid"].chosen_by == "therapist S"
    assert manager.driver("fes").district_channels == {"anterior deltoid": 3}
    on_wire = currents_on_the_wire(manager.devices["fes"].simulator)
    assert set(on_wire) == {1, 2, 3, 4} and max(max(v) for v in on_wire.values()) == 12


def test_the_rigs_reset_undoes_a_setup_left_half_way(shared_manager, _shared_rig, qtbot) -> None:
    """What a set-up that failed half-way leaves on the shared rig -- its lease, the patient's caps, a district's
    channel, its queue of the LINarm's stream, the arm held -- is named by the rig's check and undone by its reset,
    so the next test starts from the known state."""
    from app.ui.electrode_setup import setup_lease

    rig, m = _shared_rig, shared_manager  # (shared_manager: the module's xdist group, and the reset before)
    assert rig.problems() == []
    fes, robot = m.driver("fes"), m.driver("linarm")
    m.take_lease(setup_lease())
    fes.set_clinical_caps({2: ChannelCaps(max_current_ma=14.0)})
    fes.set_district_channels({"anterior deltoid": 4})
    ports = app_ports(fes, robot.command, m.bus.latest, m.supervisor.robot_hold_reason, lambda _k, _d: None,
                      DELTOID.name, "electrode set-up", bus=m.bus)
    ports.hold_arm()
    qtbot.waitUntil(lambda: robot.latest("linarm.state").controlState == 2, timeout=3000)
    problems = " / ".join(rig.problems())
    for left in ("devices are leased", "the patient's FES caps are set", "district channels are set",
                 "'electrode set-up'", "the robot is not IDLE"):
        assert left in problems, problems
    rig.reset()
    assert rig.problems() == []
    assert m.supervisor.lease("robot") is None and fes.district_channels == {}
