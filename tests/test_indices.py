"""TPI, MPI and PTI: computed incrementally from the streams, normalised to 0..1."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.devices.sim.patient_model.indices import (
    MotorPerformance,
    PhysiologicalTrend,
    TaskPerformance,
    spectral_arc_length,
)

SETTINGS = settings(max_examples=200, deadline=None)
FS = 100.0


def minimum_jerk_speed(duration: float, distance: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, duration, 1.0 / FS)
    tau = t / duration
    return t, distance / duration * 30.0 * tau**2 * (1.0 - tau) ** 2


# -- TPI ------------------------------------------------------------------------------------------

def test_tpi_from_success_and_time_to_target() -> None:
    tpi = TaskPerformance()
    assert tpi.value == 0.5  # no evidence yet
    for _ in range(10):
        tpi.add_subtask(True, 2.0)
    assert tpi.value == pytest.approx(1.0)
    slow = TaskPerformance()
    for _ in range(10):
        slow.add_subtask(True, 7.5)  # halfway between 3 s and 12 s
    assert slow.value == pytest.approx(0.6 + 0.4 * 0.5)
    failing = TaskPerformance()
    for _ in range(10):
        failing.add_subtask(False, 12.0)
    assert failing.value == 0.0


def test_tpi_forgets_old_subtasks() -> None:
    tpi = TaskPerformance()
    for _ in range(10):
        tpi.add_subtask(False, math.nan)
    for _ in range(10):
        tpi.add_subtask(True, 1.0)
    assert tpi.value == pytest.approx(1.0) and tpi.count == 10


@SETTINGS
@given(st.lists(st.tuples(st.booleans(), st.floats(0, 100) | st.just(math.nan)), max_size=30))
def test_tpi_stays_in_unit_range(results: list[tuple[bool, float]]) -> None:
    tpi = TaskPerformance()
    for ok, duration in results:
        tpi.add_subtask(ok, duration)
        assert 0.0 <= tpi.value <= 1.0


# -- SPARC and MPI --------------------------------------------------------------------------------

def test_sparc_of_a_minimum_jerk_reach() -> None:
    _, v = minimum_jerk_speed(1.0, 0.3)
    assert -1.5 < spectral_arc_length(v, FS) < -1.35
    assert spectral_arc_length(v * 5, FS) == pytest.approx(spectral_arc_length(v, FS))  # amplitude-free


def test_sparc_penalises_submovements() -> None:
    t, smooth = minimum_jerk_speed(2.0, 0.3)
    jerky = np.concatenate([minimum_jerk_speed(0.5, 0.075)[1] for _ in range(4)])
    assert spectral_arc_length(jerky, FS) < spectral_arc_length(smooth, FS) - 0.8
    assert spectral_arc_length(np.zeros(50), FS) == 0.0 and t.size == smooth.size


def feed_movement(mpi: MotorPerformance, speed: np.ndarray, force: float, direction: float = 1.0) -> None:
    mpi.start_movement(0.1, 0.1 + 0.3 * direction)
    for i, v in enumerate(speed):
        mpi.add_sample(i / FS, direction * v, direction * force)


def test_mpi_rewards_smooth_fast_active_movement() -> None:
    good = MotorPerformance()
    assert good.value == 0.5
    _, v = minimum_jerk_speed(1.0, 0.3)  # peak 0.56 m/s
    feed_movement(good, v, force=12.0, direction=-1.0)
    m = good.end_movement()
    assert m is not None and m.directedForce == pytest.approx(12.0)
    assert m.speedScore == 1.0 and m.forceScore == 1.0 and m.smoothnessScore > 0.9
    assert good.value > 0.9

    poor = MotorPerformance()
    jerky = np.concatenate([minimum_jerk_speed(1.0, 0.02)[1] for _ in range(6)])  # slow, stop-and-go
    feed_movement(poor, jerky, force=-8.0)  # the robot drags the patient
    m = poor.end_movement()
    assert m is not None and m.forceScore == pytest.approx(0.1)
    assert poor.value < 0.35


def test_mpi_ignores_too_short_movements_and_samples_outside_movements() -> None:
    mpi = MotorPerformance()
    mpi.add_sample(0.0, 0.2, 5.0)  # no movement started: ignored
    mpi.start_movement(0.0, 0.3)
    for i in range(5):
        mpi.add_sample(i / FS, 0.1, 1.0)
    assert mpi.end_movement() is None and mpi.count == 0 and mpi.value == 0.5


@SETTINGS
@given(st.lists(st.tuples(st.floats(-2, 2), st.floats(-50, 50)), min_size=10, max_size=200))
def test_mpi_stays_in_unit_range(samples: list[tuple[float, float]]) -> None:
    mpi = MotorPerformance()
    mpi.start_movement(0.3, 0.1)
    for i, (v, f) in enumerate(samples):
        mpi.add_sample(i / FS, v, f)
    mpi.end_movement()
    assert 0.0 <= mpi.value <= 1.0


# -- PTI ------------------------------------------------------------------------------------------

def feed_trends(pti: PhysiologicalTrend, seconds: float, hr_slope: float, sc_slope: float,
                temp_slope: float, t0: float = 0.0, noise: float = 0.0, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for t in np.arange(t0, t0 + seconds, 0.01):
        minutes = (t - t0) / 60.0
        pti.add_sample(float(t), 70 + hr_slope * minutes + noise * rng.standard_normal(),
                       5 + sc_slope * minutes + 0.05 * noise * rng.standard_normal(),
                       33 + temp_slope * minutes)


def test_pti_flat_signals_mean_no_trend() -> None:
    pti = PhysiologicalTrend()
    feed_trends(pti, 60, 0, 0, 0, noise=2.0)
    assert pti.value < 0.1


def test_pti_rising_arousal_gives_a_high_index() -> None:
    pti = PhysiologicalTrend()
    feed_trends(pti, 60, hr_slope=6, sc_slope=1, temp_slope=-0.5)
    slopes = pti.slopes()
    assert slopes["heartRate"] == pytest.approx(6, rel=0.02)
    assert slopes["skinConductance"] == pytest.approx(1, rel=0.02)
    assert pti.value == pytest.approx(1.0, abs=0.02)
    half = PhysiologicalTrend()
    feed_trends(half, 60, hr_slope=3, sc_slope=0, temp_slope=0)
    assert half.value == pytest.approx(0.4 * 0.5, abs=0.02)


def test_pti_negative_trend_counts_as_none() -> None:
    pti = PhysiologicalTrend()
    feed_trends(pti, 60, hr_slope=-6, sc_slope=-1, temp_slope=0.5)
    assert pti.value == 0.0


def test_pti_needs_enough_data_and_skips_missing_heart_rate() -> None:
    pti = PhysiologicalTrend()
    feed_trends(pti, 10, 6, 1, -0.5)
    assert pti.value == 0.0 and math.isnan(pti.slopes()["heartRate"])  # only 10 s
    nan_hr = PhysiologicalTrend()
    for t in np.arange(0.0, 60.0, 0.01):
        nan_hr.add_sample(float(t), math.nan, 5 + t / 60.0, 33.0)
    assert math.isnan(nan_hr.slopes()["heartRate"])
    assert nan_hr.value == pytest.approx(0.4 / 0.6, abs=0.02)  # conductance only, renormalised weights


def test_pti_window_forgets_old_trends() -> None:
    pti = PhysiologicalTrend()
    feed_trends(pti, 60, 6, 1, -0.5)
    assert pti.value > 0.9
    for t in np.arange(60.0, 150.0, 0.01):
        pti.add_sample(float(t), 76.0, 6.0, 32.5)
    assert pti.value < 0.05
