"""Per-repetition metrics on synthetic reaches whose answers are known from the definitions.

The SPARC references are computed here independently of app.session.metrics: the continuous Fourier transform of the
analytic speed profile by quadrature on a fine frequency grid (no FFT, no padding), the adaptive cut-off where
the normalised magnitude last reaches 0.05 below 10 Hz, and the arc length of that curve.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from app.session.metrics import (
    Mark,
    Series,
    SessionSignals,
    analyse,
    fes_charge_uc,
    marks_from_events,
    regular_times,
    repetitions,
    segment_by_speed,
    sparc,
    speed_peaks,
    summarize,
    velocity,
)

FS = 200.0


def min_jerk(tau: np.ndarray) -> np.ndarray:
    """Normalised minimum-jerk position (Flash & Hogan 1985): 0 → 1 for τ in [0, 1]."""
    tau = np.clip(tau, 0.0, 1.0)
    return 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5


def min_jerk_speed(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return 30 * tau ** 2 * (1 - tau) ** 2


def trapezoid(t: np.ndarray, distance: float, v_max: float, acc: float) -> tuple[np.ndarray, np.ndarray]:
    """Position and speed of a trapezoidal velocity profile from 0 to ``distance`` starting at t = 0."""
    t_acc = v_max / acc
    t_total = distance / v_max + t_acc
    v = np.minimum.reduce([acc * t, np.full_like(t, v_max), acc * (t_total - t)])
    v = np.clip(v, 0.0, None)
    v[(t < 0) | (t > t_total)] = 0.0
    x = np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2 * np.diff(t))])
    return x, v


def sparc_reference(speed_fn, duration: float, f_max: float = 10.0, threshold: float = 0.05) -> float:
    """SPARC from its definition, by quadrature of the continuous Fourier transform."""
    t = np.linspace(0.0, duration, 2001)
    v = speed_fn(t)
    f = np.linspace(0.0, f_max, 10001)
    spectrum = np.concatenate([np.abs(np.trapezoid(v[None, :] * np.exp(-2j * np.pi * np.outer(fc, t)), t, axis=1))
                               for fc in np.array_split(f, 20)])
    spectrum /= spectrum.max()
    last = int(np.nonzero(spectrum >= threshold)[0][-1])
    f, spectrum = f[:last + 1], spectrum[:last + 1]
    return -float(np.sum(np.sqrt((np.diff(f) / (f[-1] - f[0])) ** 2 + np.diff(spectrum) ** 2)))


@functools.cache
def min_jerk_sparc_reference() -> float:
    """SPARC of the minimum-jerk speed profile, from its definition: one quadrature (~1.5 s of CPU) for the seven
    tests that compare with it — the same number each time, so computed once per process."""
    return sparc_reference(min_jerk_speed, 1.0)


@functools.cache
def trapezoid_sparc_reference(distance: float, v_max: float, acc: float) -> float:
    """SPARC of a trapezoidal speed profile, from its definition (computed once per profile, as above)."""
    return sparc_reference(lambda tt: trapezoid(tt, distance, v_max, acc)[1], distance / v_max + v_max / acc)


def signals(t: np.ndarray, x: np.ndarray, marks: list[Mark] | None = None, **kw) -> SessionSignals:
    return SessionSignals(position=Series(t, x), rate_hz=FS, marks=marks or [], **kw)


def reach(start: float, duration: float, distance: float, total: float, x0: float = 0.1,
          rng: np.random.Generator | None = None, noise_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, total, 1 / FS)
    x = x0 + distance * min_jerk((t - start) / duration)
    if rng is not None:
        x = x + rng.normal(0.0, noise_m, len(x))
    return t, x


# ------------------------------------------------------------------------------------------- SPARC itself
def test_sparc_of_a_minimum_jerk_speed_matches_the_definition_whatever_the_duration() -> None:
    reference = min_jerk_sparc_reference()
    assert reference == pytest.approx(-1.40, abs=0.01)  # the value the 2015 paper's figures show
    for duration in (0.6, 1.0, 2.5):
        t = np.arange(0.0, duration + 1e-9, 1 / FS)
        assert sparc(0.3 / duration * min_jerk_speed(t / duration), FS) == pytest.approx(reference, abs=0.01)


def test_sparc_of_a_trapezoid_matches_the_definition() -> None:
    t = np.arange(0.0, 3.0, 1 / FS)
    _, v = trapezoid(t, 0.3, 0.15, 0.5)
    duration = 0.3 / 0.15 + 0.15 / 0.5
    reference = trapezoid_sparc_reference(0.3, 0.15, 0.5)
    # the trapezoid's spectrum has side lobes near 0.05: on the FFT's 0.024 Hz grid the cut-off lands a
    # little apart from the continuous one
    assert sparc(v[t <= duration], FS) == pytest.approx(reference, abs=0.06)
    assert reference < min_jerk_sparc_reference()  # corners make it less smooth than minimum jerk


def test_speed_peaks_counts_submovements_not_noise() -> None:
    t = np.arange(0.0, 2.0, 1 / FS)
    one = min_jerk_speed(t / 1.0)
    two = min_jerk_speed(t / 1.0) + min_jerk_speed((t - 0.7) / 1.0)
    assert speed_peaks(one) == 1
    assert speed_peaks(two) == 2
    rng = np.random.default_rng(1)
    assert speed_peaks(one + rng.normal(0, 0.01, len(one))) == 1  # 1 % noise is under the 5 % hysteresis
    assert speed_peaks(np.zeros(50)) == 0


# ------------------------------------------------------------------------------------------- whole reaches
@pytest.mark.parametrize("duration, distance", [(1.0, 0.30), (1.6, 0.20), (0.8, 0.15)])
def test_minimum_jerk_reach(duration: float, distance: float) -> None:
    t, x = reach(0.5, duration, distance, duration + 1.0)
    (m,) = repetitions(signals(t, x, [Mark(0.5, 0.5 + duration, 1)]))
    assert m.duration_s == pytest.approx(duration)
    assert m.start_s == 0.5 and m.end_s == pytest.approx(0.5 + duration)
    assert m.range_m == pytest.approx(distance, rel=1e-3)
    assert m.path_length_m == pytest.approx(distance, rel=5e-3)
    assert m.peak_speed_m_s == pytest.approx(1.875 * distance / duration, rel=0.02)  # 15/8 D/T
    # the movement: where the speed exceeds 5 % of its peak, τ in [τ₀, 1 − τ₀] with τ₀(1 − τ₀) = √0.003125
    tau0 = (1 - math.sqrt(1 - 4 * math.sqrt(0.003125))) / 2
    assert m.movement_time_s == pytest.approx((1 - 2 * tau0) * duration, abs=0.011)
    covered = float(min_jerk(np.array(1 - tau0)) - min_jerk(np.array(tau0)))
    assert m.mean_speed_m_s == pytest.approx(covered * distance / ((1 - 2 * tau0) * duration), rel=0.02)
    assert m.sparc == pytest.approx(min_jerk_sparc_reference(), abs=0.05)
    assert m.speed_peaks == 1


def test_trapezoidal_reach() -> None:
    distance, v_max, acc = 0.30, 0.15, 0.5
    duration = distance / v_max + v_max / acc  # 2.3 s
    t = np.arange(0.0, duration + 1.5, 1 / FS)
    x = 0.1 + trapezoid(t - 0.5, distance, v_max, acc)[0]
    (m,) = repetitions(signals(t, x, [Mark(0.5, 0.5 + duration, 1)]))
    assert m.range_m == pytest.approx(distance, rel=2e-3)
    assert m.peak_speed_m_s == pytest.approx(v_max, rel=0.01)
    assert m.mean_speed_m_s == pytest.approx(distance / duration, rel=0.05)  # the 5 % onset trims little
    reference = trapezoid_sparc_reference(distance, v_max, acc)
    assert m.sparc == pytest.approx(reference, abs=0.1)  # the 10 Hz low-pass rounds the corners a little
    assert m.speed_peaks == 1


def test_noisy_reach_keeps_range_speed_and_smoothness() -> None:
    rng = np.random.default_rng(7)
    t, x = reach(0.5, 1.2, 0.25, 2.5, rng=rng, noise_m=2e-4)  # 0.2 mm of measurement noise
    (m,) = repetitions(signals(t, x, [Mark(0.5, 1.7, 1)]))
    assert m.range_m == pytest.approx(0.25, rel=0.01)
    assert m.peak_speed_m_s == pytest.approx(1.875 * 0.25 / 1.2, rel=0.05)
    assert m.sparc == pytest.approx(min_jerk_sparc_reference(), abs=0.15)
    assert m.speed_peaks == 1


def test_two_peak_movement_is_less_smooth() -> None:
    t = np.arange(0.0, 3.0, 1 / FS)
    x = 0.1 + 0.15 * min_jerk((t - 0.5) / 0.8) + 0.15 * min_jerk((t - 1.1) / 0.8)  # a corrective submovement
    (m,) = repetitions(signals(t, x, [Mark(0.5, 1.9, 1)]))
    smooth_t, smooth_x = reach(0.5, 1.4, 0.30, 3.0)
    (s,) = repetitions(signals(smooth_t, smooth_x, [Mark(0.5, 1.9, 1)]))
    assert m.range_m == pytest.approx(0.30, rel=1e-3)
    assert m.speed_peaks == 2 and s.speed_peaks == 1
    assert m.sparc < s.sparc - 0.3


# ------------------------------------------------------------------------------------------- segmentation
def back_and_forth(n: int, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` 0.25 m reaches of 1 s, alternately out and back, with 1 s rests between."""
    t = np.arange(0.0, 2.0 * n + 1.0, 1 / FS)
    x = np.full_like(t, 0.1)
    for k in range(n):
        step = 0.25 * min_jerk((t - (1.0 + 2.0 * k)) / 1.0)
        x += step if k % 2 == 0 else -step
    if rng is not None:
        x += rng.normal(0.0, 1e-4, len(x))
    return t, x


@pytest.mark.parametrize("n, noisy", [(1, False), (6, False), (8, True)])
def test_segmentation_finds_every_reach(n: int, noisy: bool) -> None:
    t, x = back_and_forth(n, np.random.default_rng(n) if noisy else None)
    reps = repetitions(signals(t, x))
    assert len(reps) == n
    for k, m in enumerate(reps):
        assert m.source == "speed" and m.index == k + 1
        assert m.start_s == pytest.approx(1.0 + 2.0 * k, abs=0.15)
        assert m.end_s == pytest.approx(2.0 + 2.0 * k, abs=0.15)
        assert m.range_m == pytest.approx(0.25, rel=0.02)
        assert m.peak_speed_m_s == pytest.approx(1.875 * 0.25, rel=0.05)


def test_segmentation_ignores_rest_and_small_jitter() -> None:
    t = np.arange(0.0, 10.0, 1 / FS)
    rng = np.random.default_rng(3)
    still = 0.2 + rng.normal(0, 1e-4, len(t))
    assert repetitions(signals(t, still)) == []
    jitter = still + 0.004 * np.sin(2 * np.pi * 1.5 * t)  # 4 mm sway: under the 1 cm minimum range
    tu = t
    v = np.abs(velocity(jitter, FS))
    assert segment_by_speed(tu, v, jitter) == []


# ------------------------------------------------------------------------------------------- other signals
def test_force_grip_trigger_assistance_fes_and_physiology() -> None:
    t, x = reach(1.3, 1.0, 0.2, 4.0)
    grip = np.where(t >= 1.0, 30.0, 5.0)  # the grip rises through 20 N at 1.0 s; the reach begins at 1.3 s
    sig = signals(t, x, [Mark(1.2, 2.3, 1)],
                  force=Series(t, np.where((t > 1.3) & (t < 2.3), -8.0, 0.0)),
                  grip=Series(t, grip), trigger_threshold_n=20.0,
                  heart_rate=Series(t, 70.0 + 5.0 * (t > 1.25)),  # up between the two 1 s windows
                  skin_conductance=Series(t, 2.0 + 0.5 * t),
                  alpha=Series(t, np.full_like(t, 0.4)), a_r=Series(t, np.full_like(t, 0.3)),
                  a_f=Series(t, np.full_like(t, 0.1)),
                  fes_current={2: Series(t, np.where(t < 2.2, 20.0, 0.0))},
                  fes_pulse_width={2: Series(t, np.full_like(t, 200.0))}, fes_frequency_hz=40.0)
    (m,) = repetitions(sig)
    assert m.peak_force_n == 8.0 and 0 < m.mean_force_n < 8.0
    assert m.grip_at_start_n == 30.0
    # onset = where the speed passes 5 % of its peak: 30 τ²(1 − τ)² = 0.05 × 15/8, τ(1 − τ) = √0.003125
    tau = (1 - math.sqrt(1 - 4 * math.sqrt(0.003125))) / 2  # 0.0593 of the 1 s reach
    assert m.movement_onset_s == pytest.approx(1.3 + tau, abs=0.01)
    # no prompt recorded: no patient reaction time; the trigger (1.0 s) to the handle's onset is the robot's
    assert m.reaction_time_s is None
    assert m.robot_latency_s == pytest.approx(0.3 + tau, abs=0.01)
    assert (m.mean_alpha, m.mean_a_r, m.mean_a_f) == pytest.approx((0.4, 0.3, 0.1))
    assert m.fes_charge_uc == {"2": pytest.approx(20 * 200 * 40 * 1.0 / 1000, rel=0.01)}  # 1.0 s at 20 mA
    assert m.heart_rate_change_bpm == pytest.approx(5.0)
    assert m.skin_conductance_change_us == pytest.approx(0.5 * 1.1, abs=0.02)  # the 1 s means are 1.1 s apart


def test_fes_charge_holds_each_value_until_the_next() -> None:
    t = np.array([0.0, 1.0, 2.0, 3.0])
    cur = Series(t, [10.0, 0.0, 10.0, 0.0])
    pw = Series(t, [100.0] * 4)
    assert fes_charge_uc(cur, pw, 50.0, 0.0, 3.0) == pytest.approx(2 * 10 * 100 * 50 / 1000)
    assert fes_charge_uc(cur, pw, 50.0, 0.5, 2.5) == pytest.approx(1.0 * 10 * 100 * 50 / 1000)


def test_marks_from_events_pairs_starts_and_ends() -> None:
    ev = [{"kind": "repetition_start", "t_mono": 101.0, "data": {"index": 1, "total": 3}},
          {"kind": "repetition_end", "t_mono": 103.0, "data": {"index": 1, "ok": True}},
          {"kind": "repetition_start", "t_mono": 104.0, "data": {"index": 2}},
          {"kind": "repetition_start", "t_mono": 106.0, "data": {"index": 3}},  # 2 had no end
          {"kind": "script_stop", "t_mono": 107.0, "data": {"status": "stopped"}}]
    marks = marks_from_events(ev, 100.0, 10.0)
    assert marks == [Mark(1.0, 3.0, 1, True), Mark(4.0, 6.0, 2, False), Mark(6.0, 7.0, 3, False)]


def test_regular_times_spreads_a_shared_decode_time_backwards() -> None:
    t = np.array([0.0, 0.005, 0.02, 0.02, 0.02, 0.025])
    assert regular_times(t, 200.0) == pytest.approx([0.0, 0.005, 0.01, 0.015, 0.02, 0.025])


def test_summary_means_and_json_safety() -> None:
    t, x = back_and_forth(4)
    reps = repetitions(signals(t, x))
    s = summarize(reps, duration_s=9.0, alarms=1)
    assert s["repetitions"] == 4 and s["completed"] == 4 and s["alarms"] == 1
    assert s["range_m"]["mean"] == pytest.approx(0.25, rel=0.02) and s["range_m"]["n"] == 4
    assert "peak_force_n" not in s  # no force recorded: no entry, never NaN
    d = reps[0].as_dict()
    assert d["peak_force_n"] is None and not any(isinstance(v, float) and math.isnan(v) for v in d.values())


# ------------------------------------------------------------------------------------------- issue #28
@pytest.mark.parametrize("profile", ["min_jerk", "trapezoid", "short_min_jerk"])
@pytest.mark.parametrize("noisy", [False, True])
def test_sparc_does_not_move_when_the_window_takes_more_rest(profile: str, noisy: bool) -> None:
    """Property (#28 acceptance 2): widening a repetition's window by up to 0.5 s of rest on either side moves
    SPARC by at most 0.01 (it is taken from rest to rest, whatever the cut)."""
    t = np.arange(0.0, 4.0, 1 / FS)
    if profile == "trapezoid":
        x = 0.1 + trapezoid(t - 1.5, 0.3, 0.15, 0.5)[0]
        start, end = 1.45, 1.5 + 2.3 + 0.05
    else:
        duration, distance = (1.0, 0.3) if profile == "min_jerk" else (0.5, 0.05)
        x = 0.1 + distance * min_jerk((t - 1.5) / duration)
        start, end = 1.45, 1.5 + duration + 0.05
    if noisy:  # the encoder's 10 µm steps and a little noise at rest
        x = np.round((x + np.random.default_rng(5).normal(0.0, 5e-6, len(x))) / 1e-5) * 1e-5
    base = repetitions(signals(t, x, [Mark(start, end, 1)]))[0].sparc
    assert math.isfinite(base)
    for before in (0.0, 0.1, 0.25, 0.5):
        for after in (0.0, 0.1, 0.25, 0.5):
            (m,) = repetitions(signals(t, x, [Mark(start - before, min(end + after, 3.99), 1)]))
            assert abs(m.sparc - base) <= 0.01, (before, after, m.sparc, base)


def test_sparc_of_mirror_image_reaches_is_the_same() -> None:
    """A 5 cm reach out and its mirror image back: the same smoothness (the cut was −1.405 vs −1.598)."""
    t = np.arange(0.0, 5.0, 1 / FS)
    x = 0.1 + 0.05 * min_jerk((t - 1.0) / 0.6) - 0.05 * min_jerk((t - 2.6) / 0.6)
    out, back = repetitions(signals(t, x, [Mark(0.95, 1.65, 1), Mark(2.5, 3.3, 2)]))
    assert out.sparc == pytest.approx(back.sparc, abs=0.01)
    assert out.sparc == pytest.approx(min_jerk_sparc_reference(), abs=0.05)


@pytest.mark.parametrize("n", range(1, 13))
def test_lowpass_keeps_a_constant_and_a_ramp_however_short(n: int) -> None:
    from app.session.metrics import lowpass

    assert lowpass(np.full(n, 3.0), FS) == pytest.approx(np.full(n, 3.0))
    ramp = 0.1 + 0.001 * np.arange(n)
    assert lowpass(ramp, FS) == pytest.approx(ramp, abs=1e-9)


@pytest.mark.parametrize("v_max, acc", [(0.15, 0.5), (0.30, 1.0)])
def test_reaches_without_a_rest_are_split_at_each_turn(v_max: float, acc: float) -> None:
    """Trapezoidal reaches out and back with no pause, as the robot moves (the speed dips below the floor
    only for a moment at the turn): one repetition per reach, never merged across the turn, however fast."""
    duration = 0.3 / v_max + v_max / acc
    t = np.arange(0.0, 1.0 + 6 * duration + 1.0, 1 / FS)
    x = np.full_like(t, 0.1)
    for k in range(6):
        step = trapezoid(t - 1.0 - k * duration, 0.3, v_max, acc)[0]
        step[t > 1.0 + (k + 1) * duration] = 0.3
        x += step if k % 2 == 0 else -step
    reps = repetitions(signals(t, x))
    assert len(reps) == 6
    for m in reps:
        assert m.range_m == pytest.approx(0.3, abs=0.002)
        assert m.speed_peaks == 1
        assert m.peak_speed_m_s == pytest.approx(v_max, rel=0.03)
        assert m.movement_time_s == pytest.approx(duration, abs=0.1)


def test_short_dips_within_one_movement_still_join() -> None:
    """A reach whose speed dips below the onset level for under 0.1 s without turning back is one movement."""
    t = np.arange(0.0, 4.0, 1 / FS)
    x = 0.1 + 0.1 * min_jerk((t - 1.0) / 0.8) + 0.1 * min_jerk((t - 1.8) / 0.8)
    reps = repetitions(signals(t, x))
    assert len(reps) == 1 and reps[0].range_m == pytest.approx(0.2, abs=0.002)
    assert reps[0].speed_peaks == 2  # two submovements, one repetition


def test_a_tremor_at_rest_is_not_a_movement_and_does_not_join_reaches() -> None:
    t = np.arange(0.0, 9.0, 1 / FS)
    x = 0.1 + 0.25 * min_jerk((t - 1.0) / 1.0) - 0.25 * min_jerk((t - 3.0) / 1.0) + 0.25 * min_jerk((t - 5.0) / 1.0)
    x = x + 0.0015 * np.sin(2 * math.pi * 5.0 * t)  # ±1.5 mm at 5 Hz, everywhere
    reps = repetitions(signals(t, x))
    assert len(reps) == 3
    for m in reps:
        assert m.range_m == pytest.approx(0.25, abs=0.006)  # the tremor's own 3 mm peak to peak at the ends


def test_speed_ratio_and_dimensionless_jerk_of_a_minimum_jerk_reach() -> None:
    t, x = reach(1.0, 1.0, 0.3, 3.0)
    (m,) = repetitions(signals(t, x, [Mark(0.9, 2.1, 1)]))
    # mean over the movement (onset to end at 5 % of the peak) / peak: 1/1.875 of the whole, a little more
    assert m.speed_ratio == pytest.approx(0.60, abs=0.02)
    # (T³/v_peak²)∫jerk²: 720/1.875² = 204.8 for the whole reach; the 5 % onset trims T, the 6 Hz low-pass jerk
    assert 120 < m.dimensionless_jerk < 220 and m.ldlj == pytest.approx(-math.log(m.dimensionless_jerk))
    two = repetitions(signals(*reach(1.0, 1.0, 0.3, 3.0), [Mark(0.9, 2.1, 1)]))[0]
    assert two.dimensionless_jerk == pytest.approx(m.dimensionless_jerk)


def test_patient_reaction_time_from_the_prompt_to_the_grips_onset() -> None:
    from app.session.metrics import Prompt

    t, x = reach(2.0, 1.0, 0.2, 4.0)
    # the prompt at 1.0 s; the grip starts rising at 1.5 s (τ 0.1 s towards 38 N), crosses 20 N at ~1.575 s
    grip = np.where(t < 1.5, 1.0, 38.0 - 37.0 * np.exp(-(t - 1.5) / 0.1))
    grip = np.where(t > 2.4, 1.0, grip)
    sig = signals(t, x, [Mark(1.0, 3.2, 1)], grip=Series(t, grip), trigger_threshold_n=20.0,
                  prompts=[Prompt(1.0, 1, "squeeze", 20.0)])
    (m,) = repetitions(sig)
    assert m.reaction_time_s == pytest.approx(0.5, abs=0.01)  # the patient's, not the robot's start-up
    crossing = 1.5 + 0.1 * math.log(37.0 / 18.0)
    assert m.robot_latency_s == pytest.approx(m.movement_onset_s - crossing, abs=0.01)
    assert m.grip_at_trigger_n == pytest.approx(38.0 - 37.0 * math.exp(-0.9 / 0.1), abs=0.1)  # the squeeze's peak
    assert m.grip_at_start_n == m.grip_at_trigger_n  # not the resting 1 N before the mark


def test_a_skipped_marked_repetition_is_not_completed() -> None:
    """No movement of the handle within the mark (the trigger never came): not completed, whatever the
    exercise said; a movement that covers less than 90 % of the commanded distance neither."""
    t = np.arange(0.0, 8.0, 1 / FS)
    x = 0.1 + 0.2 * min_jerk((t - 4.5) / 1.0)  # only the second repetition moves
    sig = signals(t, x, [Mark(0.5, 3.5, 1, ok=True), Mark(4.0, 6.0, 2, ok=True)], movement_distance_m=0.2)
    skipped, done = repetitions(sig)
    assert not skipped.completed and done.completed
    sig.movement_distance_m = 0.3  # commanded 0.3 m, the handle covered 0.2
    assert not repetitions(sig)[1].completed


def test_a_reach_whose_onset_falls_just_before_its_mark_is_that_repetitions() -> None:
    """The clinician's day's assisted reaching (session report: "1 of 2 completed" for a run whose script and
    handle reached the target twice): the handle came back to the start, and the second reach's onset — widened
    back to 5 mm/s — lay 23 ms before the second mark's start. The reach was filed as "outside the repetitions" and
    the repetition kept only its 1.6 cm tail: not completed. An onset within the smear before a mark is that
    mark's movement (a movement inside an earlier mark stays that mark's)."""
    t = np.arange(0.0, 12.0, 1 / FS)
    out = 0.15 * min_jerk((t - 1.0) / 1.5)           # rep 1: 0.15 -> 0.30 m from 1.0 s
    back = -0.15 * min_jerk((t - 3.5) / 1.5)         # back to the start from 3.5 s, settled by 5.0 s
    again = 0.15 * min_jerk((t - 5.03) / 1.5)        # rep 2's reach: its onset 30 ms before its mark at 5.15 s
    x = 0.15 + out + back + again
    marks = [Mark(0.95, 3.0, 1, ok=True), Mark(5.15, 7.0, 2, ok=True)]
    sig = signals(t, x, marks, movement_distance_m=0.15)
    first, second = repetitions(sig)
    assert first.completed and second.completed, (first, second)
    assert second.movement_onset_s == pytest.approx(5.12, abs=0.01)  # before the mark: the case
    assert second.range_m == pytest.approx(0.15, abs=0.01)
    assert [p for p in analyse(sig).positioning if p["start_s"] > 4.95] == []  # not "outside the repetitions"


def test_homing_then_an_immediate_movement_is_not_clipped() -> None:
    """The first movement right after homing keeps its start (a fixed 0.2 s margin cut it)."""
    from types import SimpleNamespace

    from app.session.metrics import homing_intervals
    from app.wire.linarm_protocol import ControlState

    t = np.arange(0.0, 6.0, 1 / FS)
    x = np.where(t < 1.8, 0.0, 0.25) + 0.2 * min_jerk((t - 2.0) / 1.0)  # re-referenced at 1.8 s; moves at 2.0 s
    state_t = np.array([0.0, 1.0, 2.0, 2.01, 6.0])
    states = np.array([0, int(ControlState.HOME_CTRL_STATE), int(ControlState.HOME_CTRL_STATE), 2, 2])
    session = SimpleNamespace(start_mono=0.0, streams={"linarm.state": SimpleNamespace(
        t=np.repeat(state_t, 1), data={"controlState": np.where(state_t < 1.0, 0, states)})})
    session.streams["linarm.state"].data["controlState"] = np.array([0, 3, 3, 2, 2])
    session.streams["linarm.state"].data["controlState"][1:3] = int(ControlState.HOME_CTRL_STATE)
    exclude = homing_intervals(session, Series(t, x))
    assert exclude[0][1] == pytest.approx(2.01, abs=0.01)  # the homing's end: the jump was inside it
    sig = signals(t, x, exclude=exclude)
    (m,) = repetitions(sig)
    assert m.range_m == pytest.approx(0.2, abs=0.002)
    assert m.start_s < 2.1


def test_the_prompt_mark_is_a_session_event_with_its_cue() -> None:
    from app.core.progress import ExerciseProgress

    events: list[tuple[str, dict]] = []
    progress = ExerciseProgress(lambda kind, **data: events.append((kind, data)))
    progress.start_repetition(3, 8)
    progress.prompt(None, "squeeze", 20)
    progress.prompt(4, "move")
    assert events[1:] == [("prompt", {"index": 3, "cue": "squeeze", "threshold_n": 20.0}),
                          ("prompt", {"index": 4, "cue": "move"})]
