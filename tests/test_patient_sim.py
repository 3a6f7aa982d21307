"""The simulated patient (grip and arm) and the simulated physiological board."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from app.devices.sim.patient import GripMode, HandleMode, SimulatedPatient
from app.devices.sim.physio_signals import PhysioSimSource
from app.wire.physio_codec import PhysioStreamDecoder, decode_frames

DT = 0.01


def grip_trace(p: SimulatedPatient, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(t0, t1, DT)
    return t, np.array([p.grip_force(x) for x in t])


def first_time_above(t: np.ndarray, f: np.ndarray, level: float) -> float:
    idx = np.flatnonzero(f > level)
    return float(t[idx[0]]) if idx.size else math.inf


# -- grip ---------------------------------------------------------------------------------------

def test_idle_grip_is_light() -> None:
    p = SimulatedPatient(seed=1)
    _, f = grip_trace(p, 0.0, 5.0)
    assert f.max() < 5.0 and f.min() >= 0.0


def test_squeeze_crosses_20_newtons_within_half_a_second_and_releases() -> None:
    p = SimulatedPatient(seed=1)
    grip_trace(p, 0.0, 1.0)
    p.squeeze(duration=1.0)  # starts at the patient's latest time, t = 0.99
    t, f = grip_trace(p, 1.0, 4.0)
    assert first_time_above(t, f, 20.0) - 0.99 < 0.5
    plateau = f[(t > 1.5) & (t < 1.95)]
    assert 33.0 < plateau.mean() < 42.0
    assert f[t > 2.8].max() < 5.0  # released after the squeeze


def test_periodic_squeezes() -> None:
    p = SimulatedPatient(seed=2)
    p.grip_force(0.0)
    p.squeeze_periodically(period=2.0, duty=0.5)
    _, f = grip_trace(p, 0.0, 10.0)
    above = f > 20.0
    rising = np.flatnonzero(above[1:] & ~above[:-1])
    assert len(rising) + int(above[0]) == 5
    assert 0.4 < above.mean() < 0.55
    with pytest.raises(ValueError):
        p.squeeze_periodically(period=0.0)


def test_squeeze_when_the_handle_reaches_a_target() -> None:
    p = SimulatedPatient(seed=3)
    p.squeeze_at_targets([0.10, 0.40], tolerance=0.005, duration=1.0, reaction_delay=0.2)
    forces, times = [], []
    for i in range(600):  # handle sweeps 0.2 -> 0.4 m in 2 s, then waits
        t = i * DT
        pos = min(0.40, 0.20 + 0.1 * t)
        p.update_handle(t, pos, 0.1 if pos < 0.40 else 0.0)
        forces.append(p.grip_force(t))
        times.append(t)
    t_arr, f_arr = np.array(times), np.array(forces)
    assert f_arr[t_arr < 1.9].max() < 5.0  # not squeezing on the way
    arrival = 1.95  # within 5 mm of 0.40
    assert first_time_above(t_arr, f_arr, 20.0) - arrival < 0.5
    assert f_arr[t_arr > 4.0].max() < 5.0  # one squeeze per arrival
    # leaving and coming back re-arms the behaviour
    for i in range(600, 1200):
        t = i * DT
        pos = 0.30 if t < 7.0 else 0.40
        p.update_handle(t, pos, 0.0)
        forces.append(p.grip_force(t))
        times.append(t)
    t_arr, f_arr = np.array(times), np.array(forces)
    assert first_time_above(t_arr[t_arr >= 7.0], f_arr[t_arr >= 7.0], 20.0) < 7.5


def test_settings_change_safely_from_another_thread() -> None:
    p = SimulatedPatient(seed=4)
    done = threading.Event()

    def fiddle() -> None:
        for i in range(2000):
            if i % 3 == 0:
                p.squeeze(0.1)
            elif i % 3 == 1:
                p.squeeze_periodically(0.5, 0.3)
            else:
                p.fail_stop_early(0.3, fraction=0.4)
        done.set()

    worker = threading.Thread(target=fiddle)
    worker.start()
    values = []
    i = 0
    while not done.is_set() or i < 200:
        values.append(p.grip_force(i * DT) + p.handle_force(i * DT, 0.1, 0.0))
        i += 1
    worker.join()
    assert all(math.isfinite(v) for v in values)
    assert p.settings().handleMode is HandleMode.STOP_EARLY


def test_deterministic_with_a_seed() -> None:
    def run(seed: int) -> list[float]:
        p = SimulatedPatient(seed=seed)
        p.squeeze_periodically(1.0, 0.5)
        return [p.grip_force(i * DT) + p.handle_force(i * DT, 0.0, 0.0) for i in range(300)]

    assert run(7) == run(7)
    assert run(7) != run(8)


# -- arm ------------------------------------------------------------------------------------------

def simulate_handle(p: SimulatedPatient, seconds: float = 6.0) -> np.ndarray:
    """A 2 kg handle held at 0 by a 100 N/m robot spring; the patient's force moves it."""
    pos, vel, trace = 0.0, 0.0, []
    for i in range(int(seconds / 0.001)):
        t = i * 0.001
        force = p.handle_force(t, pos, vel) - 100.0 * pos - 10.0 * vel
        vel += force / 2.0 * 0.001
        pos += vel * 0.001
        trace.append(pos)
    return np.array(trace)


def test_passive_arm_only_damps() -> None:
    p = SimulatedPatient(seed=5)
    forces = [p.handle_force(i * DT, 0.2, 0.5) for i in range(200)]
    assert np.mean(forces) == pytest.approx(-1.0, abs=0.05)
    assert p.settings().handleMode is HandleMode.PASSIVE


def test_push_reaches_the_target() -> None:
    p = SimulatedPatient(seed=6)
    p.push_to(0.10, force=15.0)
    trace = simulate_handle(p)
    assert abs(trace[-1] - 0.10) < 0.01


def test_weak_patient_falls_short() -> None:
    p = SimulatedPatient(seed=6)
    p.fail_weak(0.10, force=15.0, fraction=0.2)
    trace = simulate_handle(p)
    assert trace.max() < 0.05


def test_patient_who_stops_early_falls_short() -> None:
    p = SimulatedPatient(seed=6)
    p.fail_stop_early(0.10, force=15.0, fraction=0.5)
    trace = simulate_handle(p)
    assert 0.04 < trace.max() < 0.09  # got going, then gave up
    assert trace[-1] < 0.01           # and the robot took the handle back
    assert p.settings().gripMode is GripMode.IDLE


# -- the simulated physiological board -------------------------------------------------------------

def test_board_streams_frames_at_its_rate_in_physical_ranges() -> None:
    p = SimulatedPatient(seed=9)
    src = PhysioSimSource(p, seed=9)
    p.grip_force(0.0)
    p.squeeze_periodically(4.0, 0.5)
    batch = decode_frames(src.frames_until(30.0))
    assert len(batch) == 3001 and batch.discardedBytes == 0
    assert np.all(np.diff(batch.seq.astype(int)) == 1)
    assert 31.9 < batch.temperature.min() and batch.temperature.max() < 34.1
    assert 0.5 < batch.skinConductance.min() and batch.skinConductance.max() < 20.0
    assert batch.force.max() > 30.0 and batch.force.min() < 3.0
    assert src.frames_until(30.0) == b""  # nothing new is due


def test_board_at_one_kilohertz() -> None:
    src = PhysioSimSource(SimulatedPatient(seed=1), seed=1, rate_hz=1000.0)
    dec = PhysioStreamDecoder()
    samples = dec.feed(src.frames_until(70.0))  # the 16-bit counter wraps after 65.5 s
    assert len(samples) == 70001 and dec.framesLost == 0 and dec.seqDiscontinuities == 0
    assert samples[-1].boardTime == pytest.approx(70.0)


def test_phasic_event_raises_skin_conductance() -> None:
    def run(event: bool) -> np.ndarray:
        src = PhysioSimSource(SimulatedPatient(seed=11), seed=11)
        src.frames_until(10.0)
        if event:
            src.phasic_event(10.0, amplitude=0.8)
        return decode_frames(src.frames_until(20.0)).skinConductance

    with_event, without = run(True), run(False)
    diff = with_event - without  # only the response differs: the other noise is unchanged
    assert np.all(diff > -0.015)
    assert 0.75 < diff.max() < 0.85
    assert 11.0 < 10.0 + np.argmax(diff) * DT < 16.0


def test_a_push_builds_up_over_its_rise_time_on_the_patients_clock() -> None:
    """The force of ``push_to(..., rise_s=)`` rises on the patient's own clock, whoever calls when: a test's thread
    stepping the force from outside was starved on a busy machine and its steps arrived together (#38)."""
    p = SimulatedPatient(seed=7)
    p.handle_force(0.0, 0.0, 0.0)  # the patient's clock starts
    p.push_to(0.30, force=15.0, rise_s=0.2)

    def force_at(t: float) -> float:  # the handle held still, far from the target: the push alone (and noise)
        return float(np.mean([p.handle_force(t + i * 1e-4, 0.0, 0.0) for i in range(20)]))

    first, half, full = force_at(0.001), force_at(0.101), force_at(0.301)
    assert first == pytest.approx(0.0, abs=1.0)
    assert half == pytest.approx(7.5, abs=1.0)
    assert full == pytest.approx(15.0, abs=1.0)
    p.push_to(0.30, force=15.0)  # without a rise time: at once, as before
    assert force_at(0.5) == pytest.approx(15.0, abs=1.0)
