"""Per-repetition metrics of a therapy session: what a movement was like, in the literature's measures.

Pure: numpy in, numbers out (no Qt, no files) — but for :func:`session_metrics`, the one function that reads
a session folder. Definitions and sources are in docs/metrics.md; each function's docstring names its own.

A repetition is what the exercise marked (``repetition_start`` / ``repetition_end`` session events, written by
``linarmppManager.startRepetition / endRepetition``), its onset and end taken from the handle; where an exercise
marked none, the handle's movements are segmented from its speed and its turns (:func:`segment_by_speed`).
Robot positioning (homing, moves outside the marks or before the exercise's first ``prompt``) is reported
apart (:func:`analyse`); per exercise run of the run record: :func:`metrics_by_run`. The patient's reaction
time runs from the exercise's ``prompt`` to the grip's onset. Times are seconds from the session's start, SI
units.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.core import streams
from app.session.alarm_count import counted_alarms

# ------------------------------------------------------------------------------------------- parameters
SPEED_CUTOFF_HZ = 6.0  # low-pass of the position before differentiating (−3 dB): docs/metrics.md, "Speed"
SPARC_AMPLITUDE_THRESHOLD = 0.05  # Balasubramanian et al. 2015: adaptive cut-off where |V(f)| ≥ 5 % of its peak
SPARC_MAX_CUTOFF_HZ = 10.0  # ... but never above 10 Hz
SPARC_PADDING = 4  # zero padding: FFT length = 2^(ceil(log2 n) + 4)
SPARC_SPEED_CUTOFF_HZ: float | None = None  # SPARC's speed: not low-passed (the reference's input; docs/metrics.md)
PEAK_PROMINENCE = 0.05  # a speed peak must rise and fall by 5 % of the repetition's peak speed
ONSET_FRACTION = 0.05  # movement onset / offset: speed crosses 5 % of the peak speed ...
ONSET_MIN_SPEED_M_S = 0.005  # ... and at least 5 mm/s (the encoder's noise floor stays below)
SEGMENT_FRACTION = 0.10  # segmentation: a movement is where speed exceeds 10 % of the session's peak speed
SEGMENT_MIN_SPEED_M_S = 0.02  # ... and at least 2 cm/s
SEGMENT_MIN_DURATION_S = 0.2  # shorter bursts are not movements
SEGMENT_MIN_RANGE_M = 0.01  # nor are movements of less than 1 cm
SEGMENT_MERGE_GAP_S = 0.1  # two bursts less than 0.1 s apart are one movement
PHYSIO_WINDOW_S = 1.0  # heart rate / skin conductance: mean over 1 s at the start and at the end
GRIP_WINDOW_S = 0.1  # grip at start (no trigger): mean over the 100 ms before the repetition starts
REVERSAL_M = 0.005  # a turn of the movement's direction: the handle goes back ≥ 5 mm from its furthest point
SPARC_REST_SPEED_M_S = ONSET_MIN_SPEED_M_S  # SPARC's window: the movement from rest (< 5 mm/s) to rest
GRIP_ONSET_MARGIN_N = 2.0  # a squeeze's onset: the grip rises ≥ 2 N above its resting baseline ...
GRIP_ONSET_FRACTION = 0.10  # ... or 10 % of the way from the baseline to the trigger threshold, if more
BASELINE_WINDOW_S = 0.5  # the resting grip: median of the 0.5 s before the prompt
PROMPT_SLACK_S = 0.15  # a movement that began this much before the exercise's first prompt was positioning
# A movement whose onset lies this much before a mark's start (and inside no earlier mark) is that mark's: the
# low-pass and the widening to 5 mm/s smear an onset back, and a patient may set off on the cue's heels. Without it
# the clinician's day's second assisted reach (onset 23 ms before its mark) was "outside the repetitions" and the
# repetition "not completed" while the script and the handle said it was reached.
MARK_SLACK_S = PROMPT_SLACK_S
COVERED_FRACTION = 0.9  # completed: the handle covered ≥ 90 % of the commanded distance (docs/metrics.md)


# ------------------------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class Series:
    """One recorded signal: times (s, any origin, non-decreasing) and values."""

    t: np.ndarray
    v: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", np.asarray(self.t, dtype=float))
        object.__setattr__(self, "v", np.asarray(self.v, dtype=float))

    def __len__(self) -> int:
        return len(self.t)

    def window(self, t0: float, t1: float) -> np.ndarray:
        return self.between(t0, t1)[1]

    def between(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """(t, v) of the samples with t0 <= t <= t1. Times in order (as recorded): two binary searches and a slice,
        not a comparison of every sample of the session (a 30-minute session's metrics made ~1 500 such windows:
        a quarter of their time); the same samples as the comparison, which stays for times out of order."""
        ordered = self.__dict__.get("_ordered")
        if ordered is None:
            ordered = bool(len(self.t) < 2 or np.all(self.t[1:] >= self.t[:-1]))  # False with a NaN time
            object.__setattr__(self, "_ordered", ordered)
        if not ordered:
            sel = (self.t >= t0) & (self.t <= t1)
            return self.t[sel], self.v[sel]
        if not t0 <= t1:  # also a NaN bound: nothing, as the comparison gives
            return self.t[:0], self.v[:0]
        a, b = int(np.searchsorted(self.t, t0, "left")), int(np.searchsorted(self.t, t1, "right"))
        return self.t[a:b], self.v[a:b]


@dataclass(frozen=True)
class Mark:
    """A repetition the exercise marked: start and end time (s), its index, whether it was completed."""

    start: float
    end: float
    index: int
    ok: bool = True


@dataclass(frozen=True)
class Prompt:
    """The exercise's cue to the patient (``prompt`` event): "squeeze" (a grip trigger) or "move"."""

    t: float
    index: int | None = None
    cue: str = "squeeze"
    threshold_n: float | None = None


@dataclass
class SessionSignals:
    """What the metrics read, all on one time axis (s from the session's start)."""

    position: Series  # handle position, m
    rate_hz: float = 200.0  # the position's nominal sample rate
    force: Series | None = None  # interaction force, N
    grip: Series | None = None  # grip force, N
    heart_rate: Series | None = None  # bpm
    skin_conductance: Series | None = None  # µS
    alpha: Series | None = None
    a_r: Series | None = None
    a_f: Series | None = None
    fes_current: dict[int, Series] = field(default_factory=dict)  # mA per channel
    fes_pulse_width: dict[int, Series] = field(default_factory=dict)  # µs per channel
    fes_frequency_hz: float | None = None
    marks: list[Mark] = field(default_factory=list)
    trigger_threshold_n: float | None = None
    exclude: list[tuple[float, float]] = field(default_factory=list)  # not movements (homing), for segmentation
    prompts: list[Prompt] = field(default_factory=list)
    movement_distance_m: float | None = None  # what the exercise commands per movement (its parameters), if known


@dataclass
class RepetitionMetrics:
    index: int
    start_s: float
    end_s: float
    duration_s: float
    range_m: float
    path_length_m: float
    peak_speed_m_s: float
    mean_speed_m_s: float
    sparc: float
    speed_peaks: int  # the number of submovements (Rohrer et al. 2002)
    speed_ratio: float | None = None  # mean / peak speed
    dimensionless_jerk: float | None = None  # (T³ / v_peak²) ∫ jerk² dt
    ldlj: float | None = None  # −ln(dimensionless jerk)
    peak_force_n: float | None = None
    mean_force_n: float | None = None
    grip_at_start_n: float | None = None
    grip_at_trigger_n: float | None = None
    reaction_time_s: float | None = None  # the patient's: the prompt to the grip's onset (or the movement's)
    robot_latency_s: float | None = None  # the robot's: the trigger (grip through the threshold) to the handle's onset
    prompt_s: float | None = None
    movement_onset_s: float | None = None
    movement_end_s: float | None = None
    movement_time_s: float | None = None
    mean_alpha: float | None = None
    mean_a_r: float | None = None
    mean_a_f: float | None = None
    fes_charge_uc: dict[str, float] = field(default_factory=dict)
    heart_rate_change_bpm: float | None = None
    skin_conductance_change_us: float | None = None
    completed: bool = True
    source: str = "marks"  # "marks" (the exercise's) or "speed" (segmented)

    def as_dict(self) -> dict[str, Any]:
        return {k: _clean(v) for k, v in asdict(self).items()}


# Metrics averaged in the summary (name → unit, label), in the order reports show them.
SUMMARY_METRICS: dict[str, tuple[str, str]] = {
    "duration_s": ("s", "Duration"),
    "movement_time_s": ("s", "Movement time"),
    "range_m": ("m", "Range of motion"),
    "path_length_m": ("m", "Path length"),
    "peak_speed_m_s": ("m/s", "Peak speed"),
    "mean_speed_m_s": ("m/s", "Mean speed"),
    "sparc": ("", "SPARC"),
    "speed_peaks": ("", "Submovements (speed peaks)"),
    "speed_ratio": ("", "Mean / peak speed"),
    "ldlj": ("", "Log dimensionless jerk"),
    "peak_force_n": ("N", "Peak force"),
    "mean_force_n": ("N", "Mean force"),
    "grip_at_start_n": ("N", "Grip at trigger"),
    "reaction_time_s": ("s", "Reaction time"),
    "robot_latency_s": ("s", "Robot latency"),
    "mean_alpha": ("", "Mean α"),
    "mean_a_r": ("", "Mean a_r"),
    "mean_a_f": ("", "Mean a_f"),
    "heart_rate_change_bpm": ("bpm", "Heart-rate change"),
    "skin_conductance_change_us": ("µS", "Skin-conductance change"),
}


# ------------------------------------------------------------------------------------------- signal tools
def regular_times(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Sample times from decode times. Samples decoded from one read share a time stamp although the device
    sampled them 1/rate apart, earlier: walking back from the last one, each sample is at most its decode time
    and at least one period before the next."""
    t = np.asarray(t, dtype=float)
    if len(t) < 2 or rate_hz <= 0:
        return t.copy()
    # out[i] = min(t[i], out[i+1] − p); with w = out − i·p that is a reverse running minimum of t − i·p
    steps = np.arange(len(t)) / rate_hz
    return np.minimum.accumulate((t - steps)[::-1])[::-1] + steps


def resample_uniform(t: np.ndarray, v: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation onto a uniform grid from t[0] at ``rate_hz``."""
    t = np.asarray(t, dtype=float)
    if len(t) < 2:
        return t.copy(), np.asarray(v, dtype=float).copy()
    n = math.floor((t[-1] - t[0]) * rate_hz + 1e-9) + 1
    grid = t[0] + np.arange(n) / rate_hz
    return grid, np.interp(grid, t, v)


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float = SPEED_CUTOFF_HZ) -> np.ndarray:
    """Zero-phase Gaussian low-pass, −3 dB at ``cutoff_hz`` (a Gaussian kernel does not ring, unlike a brick
    wall; its response exp(−2π²σ²f²) is 1/√2 at σ = √(ln 2 / 4π²) / f_c ≈ 0.1325 / f_c). Ends are mirrored
    (odd reflection, so a ramp stays a ramp); where the input is shorter than the kernel, each output is the
    weighted mean of the samples the kernel covers (a constant stays that constant, however short)."""
    x = np.asarray(x, dtype=float)
    sigma = math.sqrt(math.log(2.0) / (4.0 * math.pi ** 2)) / cutoff_hz * rate_hz  # in samples
    half = math.ceil(4 * sigma)
    if half < 1 or len(x) < 3:
        return x.copy()
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    k /= k.sum()
    # odd reflection about each end, repeated until the kernel is covered (an input shorter than the kernel:
    # np.convolve's mode="same" returned the kernel's length and zeros beyond the ends pulled values down)
    padded, offset = x, 0
    while offset < half:
        padded = np.concatenate([2 * padded[0] - padded[:0:-1], padded, 2 * padded[-1] - padded[-2::-1]])
        offset = (len(padded) - len(x)) // 2
    y = np.convolve(padded, k, mode="valid")  # len(padded) − 2·half samples, centred
    start = offset - half
    return y[start:start + len(x)]


def velocity(x: np.ndarray, rate_hz: float, cutoff_hz: float = SPEED_CUTOFF_HZ) -> np.ndarray:
    """Velocity of a uniformly sampled position: low-passed (see :func:`lowpass`), then central differences."""
    x = lowpass(x, rate_hz, cutoff_hz)
    if len(x) < 2:
        return np.zeros_like(x)
    return np.gradient(x, 1.0 / rate_hz)


def sparc(speed: np.ndarray, rate_hz: float, padding: int = SPARC_PADDING,
          max_cutoff_hz: float = SPARC_MAX_CUTOFF_HZ, threshold: float = SPARC_AMPLITUDE_THRESHOLD) -> float:
    """Spectral arc length (Balasubramanian, Melendez-Calderon, Roby-Brami, Burdet 2015, J NeuroEng Rehabil
    12:112; first form 2012, IEEE TBME 59(8)). The speed profile's Fourier magnitude V̂(ω), normalised to its
    peak, is taken up to an adaptive cut-off ω_c: the highest frequency up to 10 Hz where V̂ is still ≥ 0.05;
    SPARC = −∫₀^ω_c √((1/ω_c)² + (dV̂/dω)²) dω. About −1.40 for a minimum-jerk reach, whatever its length
    and duration; more negative is less smooth. NaN for fewer than 4 samples or no movement."""
    v = np.asarray(speed, dtype=float)
    if len(v) < 4 or not np.any(v != 0) or not np.all(np.isfinite(v)):
        return math.nan
    nfft = int(2 ** (math.ceil(math.log2(len(v))) + padding))
    f = np.arange(nfft) * rate_hz / nfft
    mag = np.abs(np.fft.fft(v, nfft))
    mag = mag / mag.max()
    keep = f <= max_cutoff_hz
    f, mag = f[keep], mag[keep]
    above = np.nonzero(mag >= threshold)[0]
    lo, hi = int(above[0]), int(above[-1])
    f, mag = f[lo:hi + 1], mag[lo:hi + 1]
    if len(f) < 2:
        return 0.0
    df = np.diff(f) / (f[-1] - f[0])
    return float(-np.sum(np.sqrt(df ** 2 + np.diff(mag) ** 2)))


def speed_peaks(speed: np.ndarray, prominence: float = PEAK_PROMINENCE) -> int:
    """Number of peaks of a speed profile (Rohrer et al. 2002, J Neurosci 22(18)): local maxima that rise by
    at least ``prominence`` × the peak speed above the preceding trough and fall by as much before the next
    peak (or the end). Hysteresis makes it insensitive to noise smaller than that."""
    v = np.asarray(speed, dtype=float)
    if len(v) == 0 or not np.isfinite(v).all():
        return 0
    h = prominence * float(np.max(v))
    if h <= 0:
        return 0
    count = 0
    trough = float(v[0])
    peak: float | None = None
    for s in v:
        if peak is None:
            trough = min(trough, s)
            if s >= trough + h:
                peak = s
        else:
            if s > peak:
                peak = s
            elif s <= peak - h:
                count += 1
                peak, trough = None, s
    if peak is not None:
        count += 1  # the profile ended while still high: the last peak counts (a cut repetition)
    return count


def turning_points(x: np.ndarray, hysteresis: float = REVERSAL_M) -> list[int]:
    """Indices where the movement's direction turns: alternate extremes of ``x``, each confirmed only once the
    signal has gone back by at least ``hysteresis`` from it (so noise and tremor smaller than that do not
    turn it; a zig-zag with hysteresis)."""
    x = np.asarray(x, dtype=float).tolist()  # Python floats: the same values, a scalar read ~4x faster in the loop
    out: list[int] = []
    if len(x) < 2:
        return out
    hi = lo = 0
    direction = 0
    for i in range(1, len(x)):
        xi = x[i]
        if direction >= 0 and xi > x[hi]:
            hi = i
        if direction <= 0 and xi < x[lo]:
            lo = i
        if direction >= 0 and x[hi] - xi >= hysteresis:
            out.append(hi)
            direction, lo = -1, i
        elif direction <= 0 and xi - x[lo] >= hysteresis:
            out.append(lo)
            direction, hi = 1, i
    return out


def segment_by_speed(t: np.ndarray, speed: np.ndarray, x: np.ndarray | None = None, *,
                     fraction: float = SEGMENT_FRACTION, min_speed: float = SEGMENT_MIN_SPEED_M_S,
                     onset_fraction: float = ONSET_FRACTION, min_duration_s: float = SEGMENT_MIN_DURATION_S,
                     min_range_m: float = SEGMENT_MIN_RANGE_M, merge_gap_s: float = SEGMENT_MERGE_GAP_S,
                     reversal_m: float = REVERSAL_M) -> list[tuple[float, float]]:
    """Movements (start, end) of a uniformly sampled handle: where the speed exceeds max(``fraction`` × the
    99th percentile speed, ``min_speed``), each widened to where its speed falls below max(``onset_fraction``
    × its own peak, 5 mm/s). Bursts closer than ``merge_gap_s`` are one movement only when the handle kept its
    direction between them: the position (``x``, low-passed) is cut at every turn of direction first
    (:func:`turning_points`, ``reversal_m`` of hysteresis), and nothing is widened or merged across a turn.
    Too short or too small movements are dropped."""
    t = np.asarray(t, dtype=float)
    v = np.abs(np.asarray(speed, dtype=float))
    if len(v) < 3:
        return []
    level = max(fraction * float(np.percentile(v, 99)), min_speed)
    bounds = [0, len(v)]
    xs: np.ndarray | None = None
    if x is not None:
        xs = np.asarray(x, dtype=float)
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        smooth = lowpass(xs, 1.0 / dt) if dt > 0 else xs
        bounds = [0, *[i for i in turning_points(smooth, reversal_m) if 0 < i < len(v)], len(v)]
    out: list[tuple[float, float]] = []
    speeds = v.tolist()  # the widening below reads sample by sample: Python floats (the same values) read faster
    for p, q in itertools.pairwise(bounds):
        if q - p < 2:
            continue
        high = v[p:q] > level
        edges = np.diff(high.astype(int))
        starts = list(np.nonzero(edges == 1)[0] + 1 + p)
        ends = list(np.nonzero(edges == -1)[0] + 1 + p)
        if high[0]:
            starts.insert(0, p)
        if high[-1]:
            ends.append(q)
        segs: list[list[int]] = []
        for a, b in zip(starts, ends, strict=True):
            floor = max(onset_fraction * float(v[a:b].max()), ONSET_MIN_SPEED_M_S)
            while a > p and speeds[a - 1] > floor:
                a -= 1
            while b < q and speeds[b] > floor:
                b += 1
            if segs and t[a] - t[segs[-1][1] - 1] <= merge_gap_s:
                segs[-1][1] = max(segs[-1][1], b)
            else:
                segs.append([a, b])
        for a, b in segs:
            b = min(b, len(v)) - 1
            if t[b] - t[a] < min_duration_s:
                continue
            if xs is not None and float(np.ptp(xs[a:b + 1])) < min_range_m:
                continue
            out.append((float(t[a]), float(t[b])))
    return out


def movement_bounds(t: np.ndarray, speed: np.ndarray) -> tuple[int, int] | None:
    """Indices of the first and last sample where the speed exceeds max(5 % of its peak, 5 mm/s): the
    movement's onset and end."""
    v = np.asarray(speed, dtype=float)
    if len(v) == 0:
        return None
    above = np.nonzero(v > max(ONSET_FRACTION * float(v.max()), ONSET_MIN_SPEED_M_S))[0]
    return (int(above[0]), int(above[-1])) if len(above) else None


def rest_to_rest(speed: np.ndarray, a: int, b: int, rest: float = SPARC_REST_SPEED_M_S) -> tuple[int, int]:
    """Widen the movement [a, b] to the last sample at rest (speed ≤ ``rest``) on either side."""
    v = np.asarray(speed, dtype=float)
    while a > 0 and v[a - 1] > rest:
        a -= 1
    while b < len(v) - 1 and v[b + 1] > rest:
        b += 1
    return a, b


def last_rising_crossing(series: Series, threshold: float, before: float, after: float) -> float | None:
    """The last time in (after, before] the signal rose through ``threshold`` (linear between samples)."""
    sel = (series.t > after - 1.0) & (series.t <= before)
    t, v = series.t[sel], series.v[sel]
    rises = np.nonzero((v[:-1] < threshold) & (v[1:] >= threshold))[0]
    rises = rises[t[rises + 1] > after]
    if not len(rises):
        return None
    i = int(rises[-1])
    frac = (threshold - v[i]) / (v[i + 1] - v[i]) if v[i + 1] != v[i] else 1.0
    return float(t[i] + frac * (t[i + 1] - t[i]))


def first_rising_crossing(series: Series, threshold: float, after: float, before: float) -> float | None:
    """The first time in (after, before] the signal rose through ``threshold`` from below (linear)."""
    sel = (series.t >= after) & (series.t <= before)
    idx = np.nonzero(sel)[0]
    if len(idx) < 1:
        return None
    i0 = max(int(idx[0]) - 1, 0)
    t, v = series.t[i0:int(idx[-1]) + 1], series.v[i0:int(idx[-1]) + 1]
    rises = np.nonzero((v[:-1] < threshold) & (v[1:] >= threshold))[0]
    for i in rises:
        frac = (threshold - v[i]) / (v[i + 1] - v[i]) if v[i + 1] != v[i] else 1.0
        tc = float(t[i] + frac * (t[i + 1] - t[i]))
        if tc > after:
            return tc
    return None


@dataclass(frozen=True)
class Squeeze:
    """One squeeze of the grip after a prompt: its onset, where it crossed the threshold, its peak."""

    onset: float
    crossing: float
    peak_n: float
    baseline_n: float


def squeeze_after(grip: Series, threshold: float, prompt: float, before: float) -> Squeeze | None:
    """The first squeeze after ``prompt``: the grip rising through ``threshold`` (from below: a grip still
    held at the prompt must be released first), traced back to its onset — where it was last within
    max(2 N, 10 % of the way to the threshold) of its resting baseline (median of the 0.5 s before the
    prompt, below the threshold) — and its peak until it falls back below the threshold."""
    crossing = first_rising_crossing(grip, threshold, prompt, before)
    if crossing is None:
        return None
    rest = grip.window(prompt - BASELINE_WINDOW_S, prompt)
    rest = rest[np.isfinite(rest) & (rest < threshold)]
    if not len(rest):
        rest = grip.window(prompt, crossing)
        rest = rest[np.isfinite(rest) & (rest < threshold)]
    baseline = float(np.median(rest)) if len(rest) else 0.0
    level = baseline + max(GRIP_ONSET_MARGIN_N, GRIP_ONSET_FRACTION * (threshold - baseline))
    level = min(level, threshold)
    sel = (grip.t >= prompt) & (grip.t <= crossing)
    t, v = grip.t[sel], grip.v[sel]
    onset = prompt
    below = np.nonzero(v <= level)[0]
    if len(below):
        i = int(below[-1])
        if i + 1 < len(v) and v[i + 1] != v[i]:
            onset = float(t[i] + (level - v[i]) / (v[i + 1] - v[i]) * (t[i + 1] - t[i]))
        else:
            onset = float(t[i])
    onset = min(max(onset, prompt), crossing)
    va = grip.v[grip.t >= crossing]
    fall = np.nonzero(va < threshold)[0]
    peak_sel = va[:int(fall[0])] if len(fall) else va  # the squeeze: until it falls back below the threshold
    peak = float(np.nanmax(peak_sel)) if len(peak_sel) else float(threshold)
    return Squeeze(onset, crossing, peak, baseline)


def dimensionless_jerk(x: np.ndarray, rate_hz: float) -> float:
    """Dimensionless jerk of a movement's low-passed position (Hogan & Sternad 2009, J Mot Behav 41(6); the
    peak-speed normalisation of Balasubramanian et al. 2012/2015): (T³ / v_peak²) ∫ (d³x/dt³)² dt, T the
    movement's duration. 204.8 for a minimum-jerk reach (720 / 1.875²); larger is less smooth."""
    x = np.asarray(x, dtype=float)
    if len(x) < 8:
        return math.nan
    dt = 1.0 / rate_hz
    v = np.gradient(x, dt)
    jerk = np.gradient(np.gradient(v, dt), dt)
    peak = float(np.max(np.abs(v)))
    if peak <= 0:
        return math.nan
    duration = (len(x) - 1) * dt
    return float(duration ** 3 / peak ** 2 * np.sum(jerk ** 2) * dt)


def _mean(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    return float(values.mean()) if len(values) else None


def _change(series: Series | None, t0: float, t1: float, window: float = PHYSIO_WINDOW_S) -> float | None:
    if series is None or not len(series):
        return None
    a = _mean(series.window(t0 - window, t0))
    b = _mean(series.window(max(t0, t1 - window), t1))
    return None if a is None or b is None else b - a


def fes_charge_uc(current_ma: Series, pulse_width_us: Series, frequency_hz: float, t0: float, t1: float) -> float:
    """Charge delivered by one channel in [t0, t1], µC per phase: Σ I·PW·f·Δt (mA × µs = nC; each sample
    holds until the next — what was last sent stays on the channel)."""
    t, i_ma = current_ma.t, current_ma.v
    if len(t) == 0:
        return 0.0
    pw = np.interp(t, pulse_width_us.t, pulse_width_us.v) if len(pulse_width_us) else np.zeros_like(t)
    edges = np.clip(np.append(t, t[-1]), t0, t1)
    dt = np.diff(edges)  # sample k holds from t[k] to t[k+1], clipped to the window
    q_nc = np.nansum(i_ma * pw * frequency_hz * dt)
    return float(q_nc / 1000.0)


# ------------------------------------------------------------------------------------------- per repetition
def _kinematics(sig: SessionSignals, lo: float, hi: float,
                span: tuple[float, float] | None = None) -> dict[str, Any]:
    """The handle's movement within [lo, hi]: range, path, speeds, onset and end, smoothness. ``span``: the
    segmented movement's own bounds (onset and end), where the window also holds a wait at rest (a trigger)
    in which a tremor would otherwise pass the onset threshold."""
    rate = sig.rate_hz
    pos = sig.position
    out: dict[str, Any] = {"range_m": math.nan, "path_length_m": math.nan, "peak_speed_m_s": math.nan,
                           "mean_speed_m_s": math.nan, "sparc": math.nan, "speed_peaks": 0, "onset": None,
                           "end": None, "speed_ratio": None, "dimensionless_jerk": None, "ldlj": None}
    # the movement's samples, with 0.5 s either side so the low-pass has context at the edges
    tu, xu = resample_uniform(*pos.between(lo - 0.5, hi + 0.5), rate)
    if len(xu) < 2:
        return out
    xf = lowpass(xu, rate)
    v = np.abs(np.gradient(xf, 1.0 / rate))
    inside = np.nonzero((tu >= lo) & (tu <= hi))[0]
    if len(inside) < 2:
        return out
    i0, i1 = int(inside[0]), int(inside[-1])
    t_in, x_in, v_in = tu[i0:i1 + 1], xu[i0:i1 + 1], v[i0:i1 + 1]
    out["range_m"] = float(np.ptp(x_in))
    out["path_length_m"] = float(np.sum(np.abs(np.diff(xf[i0:i1 + 1]))))
    out["peak_speed_m_s"] = peak = float(v_in.max())
    bounds = movement_bounds(t_in, v_in)
    if span is not None:
        a_s = int(np.searchsorted(t_in, span[0] - 1e-9))
        b_s = int(np.searchsorted(t_in, span[1] + 1e-9)) - 1
        if 0 <= a_s < b_s < len(t_in):
            bounds = (a_s, b_s)
    # mean speed over the movement itself, not the wait before it (a trigger) or the rest after it
    a, b = bounds if bounds is not None else (0, len(v_in) - 1)
    out["mean_speed_m_s"] = mean = float(v_in[a:b + 1].mean())
    out["speed_peaks"] = speed_peaks(v_in)
    if bounds is not None:
        out["onset"], out["end"] = float(t_in[a]), float(t_in[b])
        if peak > 0:
            out["speed_ratio"] = mean / peak
        dj = dimensionless_jerk(xf[i0 + a:i0 + b + 1], rate)
        if math.isfinite(dj) and dj > 0:
            out["dimensionless_jerk"], out["ldlj"] = dj, -math.log(dj)
        # SPARC on the speed itself (no low-pass: the reference's input), from rest to rest: the movement
        # widened to where the speed is at rest, and zeros beyond (its rests), so where the repetition's window
        # was cut does not move it
        raw = np.abs(np.gradient(xu, 1.0 / rate)) if SPARC_SPEED_CUTOFF_HZ is None else \
            np.abs(velocity(xu, rate, SPARC_SPEED_CUTOFF_HZ))
        ra, rb = rest_to_rest(v, i0 + a, i0 + b)
        ra, rb = max(ra, i0), min(rb, i1)
        out["sparc"] = sparc(raw[ra:rb + 1], rate)
    return out


def repetition_metrics(sig: SessionSignals, start: float, end: float, index: int, *, completed: bool = True,
                       source: str = "marks", movement: tuple[float, float] | None = None,
                       prompt: Prompt | None = None, span: tuple[float, float] | None = None) -> RepetitionMetrics:
    """Every metric of the repetition [start, end] (s from the session's start). ``movement`` limits the
    kinematics to the handle's own movement (its onset to its end, which may run past a marked end);
    ``prompt`` is the exercise's cue the patient's reaction time is measured from."""
    lo, hi = movement if movement is not None else (start, end)
    k = _kinematics(sig, lo, hi, span)
    onset, offset = k["onset"], k["end"]
    m = RepetitionMetrics(index, start, end, end - start, k["range_m"], k["path_length_m"], k["peak_speed_m_s"],
                          k["mean_speed_m_s"], k["sparc"], k["speed_peaks"], speed_ratio=k["speed_ratio"],
                          dimensionless_jerk=k["dimensionless_jerk"], ldlj=k["ldlj"],
                          completed=completed, source=source, movement_onset_s=onset, movement_end_s=offset,
                          movement_time_s=(offset - onset) if onset is not None and offset is not None else None)
    if sig.force is not None and len(sig.force):
        f = np.abs(sig.force.window(start, max(end, hi)))
        f = f[np.isfinite(f)]
        if len(f):
            m.peak_force_n, m.mean_force_n = float(f.max()), float(f.mean())
    threshold = prompt.threshold_n if prompt is not None and prompt.threshold_n is not None \
        else sig.trigger_threshold_n
    if prompt is not None:
        m.prompt_s = prompt.t
    if sig.grip is not None and len(sig.grip):
        m.grip_at_start_n = _mean(sig.grip.window(start - GRIP_WINDOW_S, start))
        if m.grip_at_start_n is None:  # no sample in the window: the nearest one
            m.grip_at_start_n = float(np.interp(start, sig.grip.t, sig.grip.v))
        if threshold is not None:
            squeeze = None
            if prompt is not None and prompt.cue == "squeeze":
                limit = onset if onset is not None else max(end, hi)
                squeeze = squeeze_after(sig.grip, threshold, prompt.t, limit + 0.05)
                if squeeze is not None:
                    m.reaction_time_s = squeeze.onset - prompt.t
            crossing = squeeze.crossing if squeeze is not None else None
            if crossing is None and onset is not None:  # no prompt: the last crossing before the movement
                crossing = last_rising_crossing(sig.grip, threshold, onset, start - 1.0)
            if crossing is not None:
                if onset is not None and onset >= crossing - 0.05:
                    m.robot_latency_s = max(0.0, onset - crossing)
                if squeeze is None:
                    squeeze = squeeze_after(sig.grip, threshold, crossing - 0.05, crossing + 0.05)
                if squeeze is not None:
                    m.grip_at_trigger_n = squeeze.peak_n
                    m.grip_at_start_n = squeeze.peak_n  # the squeeze that triggered, not the resting grip
    if prompt is not None and prompt.cue == "move" and onset is not None and onset >= prompt.t:
        m.reaction_time_s = onset - prompt.t  # an active movement: the cue to the handle's own onset
    for name in ("alpha", "a_r", "a_f"):
        series = getattr(sig, name)
        if series is not None and len(series):
            setattr(m, f"mean_{name}", _mean(series.window(start, end)))
    if sig.fes_current and sig.fes_frequency_hz:
        for ch, cur in sorted(sig.fes_current.items()):
            pw = sig.fes_pulse_width.get(ch, Series(np.zeros(0), np.zeros(0)))
            q = fes_charge_uc(cur, pw, sig.fes_frequency_hz, start, end)
            if q > 0:
                m.fes_charge_uc[str(ch)] = q
    m.heart_rate_change_bpm = _change(sig.heart_rate, start, end)
    m.skin_conductance_change_us = _change(sig.skin_conductance, start, end)
    return m


def find_movements(sig: SessionSignals) -> list[tuple[float, float]]:
    """Every movement of the handle (s), segmented from its speed and its turns (:func:`segment_by_speed`),
    homing left out."""
    found: list[tuple[float, float]] = []
    for t, x in _pieces(sig.position, sig.exclude):
        if len(t) < 3:
            continue
        tu, xu = resample_uniform(t, x, sig.rate_hz)
        found += segment_by_speed(tu, np.abs(velocity(xu, sig.rate_hz)), xu)
    return found


@dataclass
class Analysis:
    """The repetitions of a stretch of a session and the robot's positioning moves, apart."""

    repetitions: list[RepetitionMetrics]
    positioning: list[dict[str, Any]]


def _positioning_entry(sig: SessionSignals, kind: str, a: float, b: float) -> dict[str, Any]:
    k = _kinematics(sig, a, b) if kind != "homing" else {}
    return _clean({"kind": kind, "start_s": a, "end_s": b, "duration_s": b - a,
                   "range_m": k.get("range_m"), "peak_speed_m_s": k.get("peak_speed_m_s")})


def _prompt_for(prompts: Sequence[Prompt], lo: float, hi: float, index: int | None = None) -> Prompt | None:
    inside = [p for p in prompts if lo - 1e-6 <= p.t <= hi]
    same = [p for p in inside if index is not None and p.index == index]
    pick = same or inside
    return pick[-1] if pick else None


def analyse(sig: SessionSignals, lo: float = -math.inf, hi: float = math.inf) -> Analysis:
    """The repetitions in [lo, hi] and the positioning moves. With marks, each marked repetition takes the
    handle's movement whose onset falls within it (its end may run past the mark: the handle still moved);
    movements outside every mark are positioning. Without marks, every movement is a repetition, but for
    those before the exercise's first prompt (moving to the start point) — positioning too. Homing is always
    positioning."""
    movements = [(a, b) for a, b in find_movements(sig) if lo <= a <= hi]
    marks = [mk for mk in sig.marks if lo <= mk.start <= hi]
    prompts = [p for p in sig.prompts if lo <= p.t <= hi]
    positioning = [_positioning_entry(sig, "homing", a, b) for a, b in sig.exclude
                   if lo <= a <= hi or lo <= b <= hi]
    reps: list[RepetitionMetrics] = []
    if marks:
        owner: list[int | None] = []
        onsets: list[float] = []
        for a, b in movements:
            onset = _onset_of(sig, a, b)
            k = next((i for i, mk in enumerate(marks) if mk.start - 1e-6 <= onset <= mk.end), None)
            if k is None:  # just before a mark (inside none): that mark's (MARK_SLACK_S)
                k = next((i for i, mk in enumerate(marks) if mk.start - MARK_SLACK_S <= onset < mk.start), None)
            owner.append(k)
            onsets.append(onset)
        for i, mk in enumerate(marks):
            mine = [movements[j] for j, o in enumerate(owner) if o == i]
            others = [movements[j] for j, o in enumerate(owner) if o != i]
            # the window: the mark, less the tail of an earlier movement, plus this movement's own tail
            w0 = max([mk.start, *[b for a, b in others if a < mk.start < b]])
            early = [onsets[j] for j, o in enumerate(owner) if o == i and onsets[j] < w0]
            w0 = min([w0, *early])  # a movement set off just before the mark: from its onset
            w1 = max([mk.end, *[b for _, b in mine]])
            w1 = min([w1, *[a for a, _ in others if w0 < a < w1 and not (mine and a < mine[-1][1])]])
            nxt = marks[i + 1].start if i + 1 < len(marks) else math.inf
            prompt = _prompt_for(prompts, mk.start, min(mk.end, nxt), mk.index)
            span = (mine[0][0], mine[-1][1]) if mine else None
            m = repetition_metrics(sig, mk.start, max(mk.end, w1), mk.index, completed=mk.ok, source="marks",
                                   movement=(w0, w1), prompt=prompt, span=span)
            m.completed = mk.ok and covered(m, sig.movement_distance_m) and bool(mine)
            reps.append(m)
        positioning += [_positioning_entry(sig, "outside_repetitions", a, b)
                        for (a, b), o in zip(movements, owner, strict=True) if o is None]
    else:
        first_prompt = prompts[0].t if prompts else None
        k = 0
        prev_start = -math.inf
        for a, b in movements:
            # began before the exercise's cue (by more than the low-pass and the widening to 5 mm/s smear it)
            if first_prompt is not None and a < first_prompt - PROMPT_SLACK_S:
                positioning.append(_positioning_entry(sig, "to_start", a, b))
                continue
            k += 1
            # The last cue since the previous movement began: a script cues when the *commanded* centre has
            # arrived (the seed's Fig. 18: within 5 mm), while the handle may still be settling, so the
            # previous movement's end can fall after the cue (the clinician's day: every RT was "—").
            # ... and the cue before this movement's onset, never the next one (given while this one settles).
            prompt = _prompt_for(prompts, max(prev_start, lo), a + 0.05)
            m = repetition_metrics(sig, a, b, k, source="speed", prompt=prompt)
            m.completed = covered(m, None)
            reps.append(m)
            prev_start = a
    positioning.sort(key=lambda p: p["start_s"])
    return Analysis(reps, positioning)


def _onset_of(sig: SessionSignals, a: float, b: float) -> float:
    k = _kinematics(sig, a, b)
    return float(k["onset"]) if k["onset"] is not None else a


def covered(m: RepetitionMetrics, distance_m: float | None) -> bool:
    """Whether the handle really covered the movement (docs/metrics.md, "Completed"): its recorded range
    within the repetition is at least 1 cm, and at least 90 % of the distance the exercise commands when its
    parameters say it."""
    r = m.range_m
    if r is None or not math.isfinite(r) or r < SEGMENT_MIN_RANGE_M:
        return False
    return distance_m is None or r >= COVERED_FRACTION * distance_m


def repetitions(sig: SessionSignals) -> list[RepetitionMetrics]:
    """The exercise's marked repetitions, or the movements segmented from the speed where it marked none
    (positioning moves left out: see :func:`analyse`)."""
    return analyse(sig).repetitions


def _pieces(series: Series, exclude: Sequence[tuple[float, float]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The series cut where it is excluded (homing: the encoders are re-referenced, the position jumps)."""
    keep = np.ones(len(series), dtype=bool)
    for a, b in exclude:
        keep &= ~((series.t >= a) & (series.t <= b))
    if not keep.any():
        return []
    idx = np.nonzero(keep)[0]
    splits = np.nonzero(np.diff(idx) > 1)[0] + 1
    return [(series.t[part], series.v[part]) for part in np.split(idx, splits)]


def summarize(reps: Sequence[RepetitionMetrics], *, duration_s: float | None = None,
              alarms: int = 0) -> dict[str, Any]:
    """Session summary: counts, and per metric the mean, standard deviation, first and last value."""
    out: dict[str, Any] = {
        "repetitions": len(reps),
        "completed": sum(1 for r in reps if r.completed),
        "source": reps[0].source if reps else "none",
        "session_duration_s": duration_s,
        "alarms": alarms,
    }
    for name in SUMMARY_METRICS:
        values = np.array([float(v) for r in reps if (v := getattr(r, name)) is not None], dtype=float)
        values = values[np.isfinite(values)]
        if len(values):
            out[name] = {"mean": float(values.mean()), "sd": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
                         "first": float(values[0]), "last": float(values[-1]), "n": len(values)}
    charge: dict[str, float] = {}
    for r in reps:
        for ch, q in r.fes_charge_uc.items():
            charge[ch] = charge.get(ch, 0.0) + q
    if charge:
        out["fes_charge_uc"] = charge
    return {k: _clean(v) for k, v in out.items()}


def _clean(value: Any) -> Any:
    """JSON-friendly: NaN / inf become None (JSON has no NaN), numpy scalars plain numbers."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# ------------------------------------------------------------------------------------------- from a recording
def _event_t(e: Mapping[str, Any], default: float) -> float | None:
    """An event's time: ``default`` when it has none, None when it has one that is not a number (a malformed
    record: app.session.recording lists it among the session's problems; the metrics leave the event out)."""
    t = e.get("t_mono", default)
    if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
        return None
    return float(t)


def _event_data(e: Mapping[str, Any]) -> Mapping[str, Any]:
    data = e.get("data")
    return data if isinstance(data, Mapping) else {}


def marks_from_events(events: Iterable[Mapping[str, Any]], t_zero: float, t_end: float) -> list[Mark]:
    """Pair ``repetition_start`` / ``repetition_end`` events. A start without its end (the script was stopped,
    or the next start came first) ends there, as not completed."""
    marks: list[Mark] = []
    open_: tuple[float, int] | None = None
    for e in events:
        kind = e.get("kind")
        if kind not in ("repetition_start", "repetition_end", "script_stop"):
            continue
        t_mono = _event_t(e, t_zero)
        if t_mono is None:
            continue
        t = t_mono - t_zero
        data = _event_data(e)
        if kind == "repetition_start":
            if open_ is not None:
                marks.append(Mark(open_[0], t, open_[1], ok=False))
            open_ = (t, int(data.get("index", len(marks) + 1)))
        elif open_ is not None:
            ok = bool(data.get("ok", True)) if kind == "repetition_end" else False
            marks.append(Mark(open_[0], t, open_[1], ok=ok))
            open_ = None
    if open_ is not None:
        marks.append(Mark(open_[0], t_end, open_[1], ok=False))
    return marks


def exercise_params(events: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """The parameters of the last exercise started from a form (``exercise_start`` event), if any."""
    params: dict[str, Any] = {}
    for e in events:
        if e.get("kind") == "exercise_start":
            params = dict((e.get("data") or {}).get("params") or {})
    return params


def signals_from_session(session: Any) -> SessionSignals:
    """The metrics' inputs from a loaded :class:`app.session.recording.RecordedSession`."""
    t0 = session.start_mono
    t_end = session.end_mono - t0

    def series(stream: str, channel: str, regular: bool = False) -> Series | None:
        s = session.streams.get(stream)
        if s is None or channel not in s.data or not len(s.t):
            return None
        t = regular_times(s.t, s.nominal_rate_hz) if regular else s.t
        v = s.data[channel]
        finite = np.isfinite(v)  # "unknown" samples (NaN: e.g. the force before homing) carry no value
        return Series(t[finite] - t0, v[finite]) if finite.any() else None

    vsa = session.streams.get(streams.LINARM_VSA)
    rate = float(vsa.nominal_rate_hz) if vsa is not None and vsa.nominal_rate_hz else 200.0
    position = series(streams.LINARM_VSA, "handlePos", regular=True) or Series(np.zeros(0), np.zeros(0))
    sig = SessionSignals(position=position, rate_hz=rate,
                         force=series(streams.LINARM_VSA, "interactionForce", regular=True),
                         grip=series(streams.PHYSIO_MAIN, "force", regular=True),
                         heart_rate=series(streams.PHYSIO_MAIN, "heartRate"),
                         skin_conductance=series(streams.PHYSIO_MAIN, "skinConductance"),
                         alpha=series(streams.PATIENT_MODEL_MAIN, "alpha"),
                         a_r=series(streams.PATIENT_MODEL_MAIN, "a_r"),
                         a_f=series(streams.PATIENT_MODEL_MAIN, "a_f"))
    fes = session.streams.get(streams.FES_CHANNELS)
    if fes is not None and len(fes.t):
        for name in fes.data:
            if name.startswith("current") and np.nanmax(np.abs(fes.data[name])) > 0:
                ch = int(name.removeprefix("current"))
                sig.fes_current[ch] = Series(fes.t - t0, fes.data[name])
                if f"pulseWidth{ch}" in fes.data:
                    sig.fes_pulse_width[ch] = Series(fes.t - t0, fes.data[f"pulseWidth{ch}"])
        freqs = [e["data"].get("frequency_hz") for e in session.events
                 if e.get("kind") == "fes_profile_loaded" and (e.get("data") or {}).get("frequency_hz")]
        if freqs:
            sig.fes_frequency_hz = float(freqs[-1])
        else:
            sig.fes_frequency_hz = float(((session.manifest.get("config") or {}).get("fes") or {})
                                         .get("frequency_hz") or 0.0) or None
    sig.marks = marks_from_events(session.events, t0, t_end)
    sig.prompts = prompts_from_events(session.events, t0)
    sig.exclude = homing_intervals(session, position)
    params = exercise_params(session.events)
    threshold = params.get("trigger_threshold_n")
    sig.trigger_threshold_n = float(threshold) if threshold is not None else None
    sig.movement_distance_m = movement_distance(params)
    return sig


def prompts_from_events(events: Iterable[Mapping[str, Any]], t_zero: float,
                        run_id: str | None = None) -> list[Prompt]:
    """The exercise's cues (``prompt`` events: ``linarmppManager.prompt``), times from ``t_zero``."""
    out = []
    for e in events:
        if e.get("kind") != "prompt":
            continue
        data = _event_data(e)
        t_mono = _event_t(e, t_zero)
        if t_mono is None or (run_id is not None and data.get("run_id") not in (None, run_id)):
            continue
        threshold = data.get("threshold_n")
        index = data.get("index")
        out.append(Prompt(t_mono - t_zero, int(index) if index is not None else None,
                          str(data.get("cue") or "squeeze"), float(threshold) if threshold is not None else None))
    return out


def movement_distance(params: Mapping[str, Any]) -> float | None:
    """The distance one movement of the exercise covers, from its parameters (start and end or target), if
    they say it."""
    start = params.get("start_m")
    end = params.get("end_m", params.get("target_m"))
    try:
        return abs(float(end) - float(start)) if start is not None and end is not None else None
    except (TypeError, ValueError):
        return None


HOMING_MARGIN_S = 0.2  # the position may still jump (encoders re-referenced) this long after homing ends
HOMING_JUMP_M = 0.005  # a jump: more than 5 mm from one sample to the next (1 m/s at 200 Hz, no arm moves so)


def homing_intervals(session: Any, position: Series | None = None) -> list[tuple[float, float]]:
    """Where the robot was homing (s from the session's start). After each, up to the position's last jump
    within ``HOMING_MARGIN_S`` (re-referenced encoders) — not a fixed margin, which clipped the start of a
    movement that followed homing at once."""
    from app.wire.linarm_protocol import ControlState

    state = session.streams.get(streams.LINARM_STATE)
    if state is None or not len(state.t) or "controlState" not in state.data:
        return []
    t = state.t - session.start_mono
    homing = np.concatenate([[False], state.data["controlState"] == int(ControlState.HOME_CTRL_STATE), [False]])
    edges = np.diff(homing.astype(int))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    out = []
    for a, b in zip(starts, ends, strict=True):
        end = float(t[b]) if b < len(t) else float(t[-1])
        if position is not None and len(position):
            sel = np.nonzero((position.t >= end - 0.05) & (position.t <= end + HOMING_MARGIN_S))[0]
            if len(sel) > 1:
                jumps = np.nonzero(np.abs(np.diff(position.v[sel])) > HOMING_JUMP_M)[0]
                if len(jumps):
                    end = max(end, float(position.t[sel[int(jumps[-1]) + 1]]))
        else:
            end += HOMING_MARGIN_S
        out.append((float(t[a]) - 0.05, end))
    return out


def session_alarms(session: Any) -> list[dict[str, Any]]:
    """Alarms and interruptions of a session, times from its start."""
    t0 = session.start_mono
    kinds = {"alarm", "emergency_stop", "script_stop", "exercise_paused", "exercise_resumed", "gap_start"}
    out = []
    for e in session.events:
        if e.get("kind") not in kinds:
            continue
        data = dict(_event_data(e))
        t_mono = _event_t(e, t0)
        if t_mono is None or (e["kind"] == "script_stop" and data.get("status") in ("finished", None)):
            continue
        out.append({"t_s": round(t_mono - t0, 3), "kind": e["kind"], "data": _clean(data)})
    return out


def _alarms_between(session: Any, lo: float, hi: float) -> int:
    """The alarms raised between ``lo`` and ``hi`` s from the session's start, counted as every view counts them
    (app.session.alarm_count: over the whole record, then by time, so that a STOP latched earlier is known)."""
    t0 = session.start_mono
    return sum(1 for e in counted_alarms(session.events) if lo <= round(float(e.get("t_mono", t0)) - t0, 3) <= hi)


def metrics_of_session(session: Any, since_mono: float | None = None,
                       until_mono: float | None = None) -> dict[str, Any]:
    """``{"repetitions": [...], "summary": {...}, "alarms": [...], "positioning": [...], "runs": [...]}`` of a
    loaded session; with ``since_mono`` / ``until_mono`` (monotonic times) only the repetitions starting and
    the alarms raised in between (one exercise of the session). ``runs``: :func:`metrics_by_run`, as dicts."""
    sig = signals_from_session(session)
    lo = -math.inf if since_mono is None else since_mono - session.start_mono
    hi = math.inf if until_mono is None else until_mono - session.start_mono
    events = [e for e in session.events
              if (te := _event_t(e, 0.0)) is not None and lo <= te - session.start_mono <= hi]
    params = exercise_params(events)
    if since_mono is not None or until_mono is not None:
        threshold = params.get("trigger_threshold_n")
        sig.trigger_threshold_n = float(threshold) if threshold is not None else None
        sig.movement_distance_m = movement_distance(params)
    by_run = metrics_by_run(session, sig)
    t0 = session.start_mono
    by_run = [r for r in by_run  # the runs overlapping the window (their repetitions are filtered below)
              if r.run.started_mono - t0 <= hi and (r.run.ended_mono or session.end_mono) - t0 >= lo]
    reps: list[dict[str, Any]] = []
    positioning: list[dict[str, Any]] = []
    objects: list[RepetitionMetrics] = []
    for r in by_run:
        for m, d in zip(r.objects, r.repetitions, strict=True):
            if lo <= m.start_s <= hi:
                reps.append(d)
                objects.append(m)
        positioning += [p for p in r.positioning if lo <= p["start_s"] <= hi]
    alarms = [a for a in session_alarms(session) if lo <= a["t_s"] <= hi]
    duration = session.duration_s if since_mono is None and until_mono is None else \
        min(hi, session.duration_s) - max(lo, 0.0)
    summary = summarize(objects, duration_s=duration, alarms=_alarms_between(session, lo, hi))
    summary["positioning_moves"] = sum(1 for p in positioning if p["kind"] != "homing")
    if params:
        summary["exercise_params"] = _clean(params)
    return {"repetitions": reps, "summary": summary, "alarms": alarms, "positioning": positioning,
            "runs": [r.as_dict() for r in by_run]}


# ------------------------------------------------------------------------------------------- per run
@dataclass
class RunMetrics:
    """One exercise run's metrics (app.core.runs.RunMetricsRef's shape): its repetitions numbered within the run
    from 1 (dicts of :class:`RepetitionMetrics`), its own summary, and the robot's positioning moves apart."""

    run: Any  # app.core.runs.ExerciseRun
    repetitions: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    positioning: list[dict[str, Any]] = field(default_factory=list)
    objects: list[RepetitionMetrics] = field(default_factory=list, repr=False)

    def as_dict(self) -> dict[str, Any]:
        run = self.run
        return _clean({"run_id": run.run_id, "title": run.title, "program": run.program.ident,
                       "source": run.source, "end_reason": run.end_reason, "end": run.end_text(),
                       "parameters": {p.name: p.value for p in run.parameters},
                       "repetitions": self.repetitions, "summary": self.summary, "positioning": self.positioning})


def _runs_of(session: Any) -> list[Any]:
    """The session's runs (app.core.runs); a recording made before runs were recorded gets one per script run
    (``script_start`` / ``script_stop``), or one for the whole session."""
    from dataclasses import replace as _replace

    from app.core.runs import ExerciseRun, Program, runs_from_events, text_hash

    runs = runs_from_events(session.events, t_end=session.end_mono)
    if runs:
        return runs
    out: list[ExerciseRun] = []
    for e in session.events:
        data = _event_data(e)
        t_event = _event_t(e, session.start_mono)
        if t_event is None:
            continue
        t = t_event
        if e.get("kind") == "script_start":
            name = str(data.get("name") or "script")
            text = str(data.get("text") or "")
            out.append(ExerciseRun(run_id=f"script-{len(out) + 1}",
                                   program=Program("script_file", name, Path(name).stem, text_hash(text), path=name),
                                   parameters=(), source="script_tab", operator=str(e.get("who") or ""),
                                   started_mono=t, started_wall=0.0))
        elif e.get("kind") == "script_stop" and out and out[-1].running:
            status = str(data.get("status") or "finished")
            reason = {"finished": "finished", "error": "script_error", "refused": "refused",
                      "stopped": "stopped_by_operator"}.get(status, "stopped_by_operator")
            out[-1] = _replace(out[-1], ended_mono=t, end_reason=reason, end_detail=str(data.get("reason") or ""),
                               state="finished" if reason == "finished" else "stopped")
    out = [r if not r.running else _replace(r, ended_mono=session.end_mono, end_reason="crashed", state="stopped")
           for r in out]
    if not out:
        out = [ExerciseRun(run_id="session", program=Program("script_file", "", "session", ""), parameters=(),
                           source="headless", operator="", started_mono=session.start_mono, started_wall=0.0,
                           ended_mono=session.end_mono, end_reason="finished", state="finished")]
    return out


def metrics_by_run(session: Any, sig: SessionSignals | None = None) -> list[RunMetrics]:
    """Per exercise run of a loaded session (app.core.runs.runs_from_events): its repetitions numbered within the
    run, its own summary and its positioning moves. A run refused before its first movement is "not started":
    no repetition, whatever the robot did while positioning."""
    import copy

    sig = signals_from_session(session) if sig is None else sig
    t0 = session.start_mono
    out: list[RunMetrics] = []
    for run in _runs_of(session):
        lo = run.started_mono - t0
        hi = (run.ended_mono if run.ended_mono is not None else session.end_mono) - t0
        run_events = [e for e in session.events
                      if (te := _event_t(e, t0)) is not None and lo - 1e-6 <= te - t0 <= hi + 1e-6]
        mine = [e for e in run_events if (e.get("data") or {}).get("run_id") in (None, run.run_id)]
        rs = copy.copy(sig)
        rs.marks = [mk for mk in marks_from_events(mine, t0, hi) if lo - 1e-6 <= mk.start <= hi]
        rs.prompts = prompts_from_events(mine, t0, run.run_id)
        params = {**exercise_params(run_events), **run.params_dict()}
        threshold = params.get("trigger_threshold_n")
        if threshold is not None:
            rs.trigger_threshold_n = float(threshold)
        rs.movement_distance_m = movement_distance(params) if params else sig.movement_distance_m
        result = analyse(rs, lo, hi)
        reps = result.repetitions
        positioning = result.positioning
        not_started = run.end_reason == "refused" and not rs.marks
        if not_started:  # refused before its first movement: what moved was the robot positioning
            positioning = sorted(positioning + [_positioning_entry(rs, "before_refusal", m.start_s, m.end_s)
                                                for m in reps], key=lambda p: p["start_s"])
            reps = []
        for k, m in enumerate(reps):
            if m.source == "speed":
                m.index = k + 1
        summary = summarize(reps, duration_s=hi - lo, alarms=_alarms_between(session, lo, hi))
        summary.update(_clean({"run_id": run.run_id, "title": run.title, "end_reason": run.end_reason,
                               "exercise_params": params, "not_started": not_started,
                               "positioning_moves": sum(1 for p in positioning if p["kind"] != "homing")}))
        dicts = []
        for m in reps:
            d = m.as_dict()
            d["run_id"] = run.run_id
            dicts.append(d)
        out.append(RunMetrics(run, dicts, summary, positioning, reps))
    return out


def session_metrics(folder: str | Path) -> dict[str, Any]:
    """Read a session folder and compute its metrics (the command line's ``--metrics``)."""
    from app.session.recording import load_session

    return metrics_of_session(load_session(folder))
