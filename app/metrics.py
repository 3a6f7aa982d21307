"""Per-repetition metrics of a therapy session: what a movement was like, in the literature's measures.

Pure: numpy in, numbers out (no Qt, no files) — but for :func:`session_metrics`, the one function that reads
a session folder. Definitions and sources are in docs/metrics.md; each function's docstring names its own.

A repetition is what the exercise marked (``repetition_start`` / ``repetition_end`` session events, written by
``linarmppManager.startRepetition / endRepetition``); where an exercise marked none, the handle's movements are
segmented from its speed (:func:`segment_by_speed`). Times are seconds from the session's start, SI units.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# ------------------------------------------------------------------------------------------- parameters
SPEED_CUTOFF_HZ = 10.0  # low-pass of the position before differentiating (−3 dB), human reaching < 10 Hz
SPARC_AMPLITUDE_THRESHOLD = 0.05  # Balasubramanian et al. 2015: adaptive cut-off where |V(f)| ≥ 5 % of its peak
SPARC_MAX_CUTOFF_HZ = 10.0  # ... but never above 10 Hz
SPARC_PADDING = 4  # zero padding: FFT length = 2^(ceil(log2 n) + 4)
PEAK_PROMINENCE = 0.05  # a speed peak must rise and fall by 5 % of the repetition's peak speed
ONSET_FRACTION = 0.05  # movement onset / offset: speed crosses 5 % of the peak speed ...
ONSET_MIN_SPEED_M_S = 0.005  # ... and at least 5 mm/s (the encoder's noise floor stays below)
SEGMENT_FRACTION = 0.10  # segmentation: a movement is where speed exceeds 10 % of the session's peak speed
SEGMENT_MIN_SPEED_M_S = 0.02  # ... and at least 2 cm/s
SEGMENT_MIN_DURATION_S = 0.2  # shorter bursts are not movements
SEGMENT_MIN_RANGE_M = 0.01  # nor are movements of less than 1 cm
SEGMENT_MERGE_GAP_S = 0.1  # two bursts less than 0.1 s apart are one movement
PHYSIO_WINDOW_S = 1.0  # heart rate / skin conductance: mean over 1 s at the start and at the end
GRIP_WINDOW_S = 0.1  # grip at start: mean over the 100 ms before the repetition starts


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
        sel = (self.t >= t0) & (self.t <= t1)
        return self.v[sel]


@dataclass(frozen=True)
class Mark:
    """A repetition the exercise marked: start and end time (s), its index, whether it was completed."""

    start: float
    end: float
    index: int
    ok: bool = True


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
    speed_peaks: int
    peak_force_n: float | None = None
    mean_force_n: float | None = None
    grip_at_start_n: float | None = None
    reaction_time_s: float | None = None
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
    "speed_peaks": ("", "Speed peaks"),
    "peak_force_n": ("N", "Peak force"),
    "mean_force_n": ("N", "Mean force"),
    "grip_at_start_n": ("N", "Grip at start"),
    "reaction_time_s": ("s", "Reaction time"),
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
    wall; its response exp(−2π²σ²f²) is 1/√2 at σ = √(ln 2 / 4π²) / f_c ≈ 0.1325 / f_c). Ends are mirrored."""
    x = np.asarray(x, dtype=float)
    sigma = math.sqrt(math.log(2.0) / (4.0 * math.pi ** 2)) / cutoff_hz * rate_hz  # in samples
    half = math.ceil(4 * sigma)
    if half < 1 or len(x) < 3:
        return x.copy()
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    k /= k.sum()
    pad = min(half, len(x) - 1)
    padded = np.concatenate([2 * x[0] - x[pad:0:-1], x, 2 * x[-1] - x[-2:-pad - 2:-1]])
    y = np.convolve(padded, k, mode="same")
    return y[pad:pad + len(x)]


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


def segment_by_speed(t: np.ndarray, speed: np.ndarray, x: np.ndarray | None = None, *,
                     fraction: float = SEGMENT_FRACTION, min_speed: float = SEGMENT_MIN_SPEED_M_S,
                     onset_fraction: float = ONSET_FRACTION, min_duration_s: float = SEGMENT_MIN_DURATION_S,
                     min_range_m: float = SEGMENT_MIN_RANGE_M,
                     merge_gap_s: float = SEGMENT_MERGE_GAP_S) -> list[tuple[float, float]]:
    """Movements (start, end) where the speed exceeds max(``fraction`` × the 99th percentile speed,
    ``min_speed``), each widened to where its speed falls below max(``onset_fraction`` × its own peak, 5 mm/s);
    bursts closer than ``merge_gap_s`` are one movement; too short or too small ones are dropped."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(speed, dtype=float)
    if len(v) < 3:
        return []
    level = max(fraction * float(np.percentile(v, 99)), min_speed)
    high = v > level
    edges = np.diff(high.astype(int))
    starts = list(np.nonzero(edges == 1)[0] + 1)
    ends = list(np.nonzero(edges == -1)[0] + 1)
    if high[0]:
        starts.insert(0, 0)
    if high[-1]:
        ends.append(len(v))
    segs: list[list[int]] = []
    for a, b in zip(starts, ends, strict=True):
        floor = max(onset_fraction * float(v[a:b].max()), ONSET_MIN_SPEED_M_S)
        while a > 0 and v[a - 1] > floor:
            a -= 1
        while b < len(v) and v[b] > floor:
            b += 1
        if segs and t[a] - t[segs[-1][1] - 1] <= merge_gap_s:
            segs[-1][1] = max(segs[-1][1], b)
        else:
            segs.append([a, b])
    out = []
    for a, b in segs:
        b = min(b, len(v)) - 1
        if t[b] - t[a] < min_duration_s:
            continue
        if x is not None and float(np.ptp(np.asarray(x)[a:b + 1])) < min_range_m:
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
def repetition_metrics(sig: SessionSignals, start: float, end: float, index: int, *, completed: bool = True,
                       source: str = "marks") -> RepetitionMetrics:
    """Every metric of the repetition [start, end] (s from the session's start)."""
    rate = sig.rate_hz
    pos = sig.position
    # the movement's samples, with 0.5 s either side so the low-pass has context at the edges
    sel = (pos.t >= start - 0.5) & (pos.t <= end + 0.5)
    tu, xu = resample_uniform(pos.t[sel], pos.v[sel], rate)
    v = np.abs(velocity(xu, rate)) if len(xu) else np.zeros(0)
    inside = (tu >= start) & (tu <= end)
    t_in, x_in, v_in = tu[inside], xu[inside], v[inside]
    if len(x_in) >= 2:
        range_m = float(np.ptp(x_in))
        path = float(np.sum(np.abs(np.diff(lowpass(xu, rate)[inside]))))
        peak = float(v_in.max())
        bounds = movement_bounds(t_in, v_in)
        # mean speed over the movement itself, not the wait before it (a trigger) or the rest after it
        a, b = bounds if bounds is not None else (0, len(v_in) - 1)
        mean = float(v_in[a:b + 1].mean())
        sp = sparc(v_in, rate)
        peaks = speed_peaks(v_in)
        onset = float(t_in[a]) if bounds is not None else None
        offset = float(t_in[b]) if bounds is not None else None
    else:
        range_m = path = peak = mean = sp = math.nan
        peaks, onset, offset = 0, None, None
    m = RepetitionMetrics(index, start, end, end - start, range_m, path, peak, mean, sp, peaks,
                          completed=completed, source=source, movement_onset_s=onset, movement_end_s=offset,
                          movement_time_s=(offset - onset) if onset is not None and offset is not None else None)
    if sig.force is not None and len(sig.force):
        f = np.abs(sig.force.window(start, end))
        f = f[np.isfinite(f)]
        if len(f):
            m.peak_force_n, m.mean_force_n = float(f.max()), float(f.mean())
    if sig.grip is not None and len(sig.grip):
        m.grip_at_start_n = _mean(sig.grip.window(start - GRIP_WINDOW_S, start))
        if m.grip_at_start_n is None:  # no sample in the window: the nearest one
            m.grip_at_start_n = float(np.interp(start, sig.grip.t, sig.grip.v))
        if sig.trigger_threshold_n is not None and onset is not None:
            crossing = last_rising_crossing(sig.grip, sig.trigger_threshold_n, onset, start - 1.0)
            if crossing is not None:
                m.reaction_time_s = max(0.0, onset - crossing)
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


def repetitions(sig: SessionSignals) -> list[RepetitionMetrics]:
    """The exercise's marked repetitions, or the movements segmented from the speed where it marked none."""
    if sig.marks:
        return [repetition_metrics(sig, mk.start, mk.end, mk.index, completed=mk.ok, source="marks")
                for mk in sig.marks]
    found: list[tuple[float, float]] = []
    for t, x in _pieces(sig.position, sig.exclude):
        if len(t) < 3:
            continue
        tu, xu = resample_uniform(t, x, sig.rate_hz)
        found += segment_by_speed(tu, np.abs(velocity(xu, sig.rate_hz)), xu)
    return [repetition_metrics(sig, a, b, k + 1, source="speed") for k, (a, b) in enumerate(found)]


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
def marks_from_events(events: Iterable[Mapping[str, Any]], t_zero: float, t_end: float) -> list[Mark]:
    """Pair ``repetition_start`` / ``repetition_end`` events. A start without its end (the script was stopped,
    or the next start came first) ends there, as not completed."""
    marks: list[Mark] = []
    open_: tuple[float, int] | None = None
    for e in events:
        kind = e.get("kind")
        if kind not in ("repetition_start", "repetition_end", "script_stop"):
            continue
        t = float(e.get("t_mono", t_zero)) - t_zero
        data = e.get("data") or {}
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
    """The metrics' inputs from a loaded :class:`app.recording.RecordedSession`."""
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

    vsa = session.streams.get("linarm.vsa")
    rate = float(vsa.nominal_rate_hz) if vsa is not None and vsa.nominal_rate_hz else 200.0
    position = series("linarm.vsa", "handlePos", regular=True) or Series(np.zeros(0), np.zeros(0))
    sig = SessionSignals(position=position, rate_hz=rate,
                         force=series("linarm.vsa", "interactionForce", regular=True),
                         grip=series("physio.main", "force"),
                         heart_rate=series("physio.main", "heartRate"),
                         skin_conductance=series("physio.main", "skinConductance"),
                         alpha=series("patient_model.main", "alpha"),
                         a_r=series("patient_model.main", "a_r"),
                         a_f=series("patient_model.main", "a_f"))
    fes = session.streams.get("fes.channels")
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
    sig.exclude = homing_intervals(session)
    threshold = exercise_params(session.events).get("trigger_threshold_n")
    sig.trigger_threshold_n = float(threshold) if threshold is not None else None
    return sig


HOMING_MARGIN_S = 0.2  # the position settles after the encoders are re-referenced


def homing_intervals(session: Any) -> list[tuple[float, float]]:
    """Where the robot was homing (s from the session's start), with a margin after each."""
    from app.devices.linarm_protocol import ControlState

    state = session.streams.get("linarm.state")
    if state is None or not len(state.t) or "controlState" not in state.data:
        return []
    t = state.t - session.start_mono
    homing = np.concatenate([[False], state.data["controlState"] == int(ControlState.HOME_CTRL_STATE), [False]])
    edges = np.diff(homing.astype(int))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    out = []
    for a, b in zip(starts, ends, strict=True):
        end = float(t[b]) if b < len(t) else float(t[-1])
        out.append((float(t[a]) - 0.05, end + HOMING_MARGIN_S))
    return out


def session_alarms(session: Any) -> list[dict[str, Any]]:
    """Alarms and interruptions of a session, times from its start."""
    t0 = session.start_mono
    kinds = {"alarm", "emergency_stop", "script_stop", "exercise_paused", "exercise_resumed", "gap_start"}
    out = []
    for e in session.events:
        if e.get("kind") not in kinds:
            continue
        data = dict(e.get("data") or {})
        if e["kind"] == "script_stop" and data.get("status") in ("finished", None):
            continue
        out.append({"t_s": round(float(e.get("t_mono", t0)) - t0, 3), "kind": e["kind"], "data": _clean(data)})
    return out


def metrics_of_session(session: Any, since_mono: float | None = None,
                       until_mono: float | None = None) -> dict[str, Any]:
    """``{"repetitions": [...], "summary": {...}, "alarms": [...]}`` of a loaded session; with ``since_mono`` /
    ``until_mono`` (monotonic times) only the repetitions starting and the alarms raised in between (one
    exercise of the session)."""
    sig = signals_from_session(session)
    lo = -math.inf if since_mono is None else since_mono - session.start_mono
    hi = math.inf if until_mono is None else until_mono - session.start_mono
    events = [e for e in session.events if lo <= float(e.get("t_mono", 0.0)) - session.start_mono <= hi]
    if since_mono is not None or until_mono is not None:
        sig.marks = [mk for mk in sig.marks if lo <= mk.start <= hi]
        params = exercise_params(events)
        threshold = params.get("trigger_threshold_n")
        sig.trigger_threshold_n = float(threshold) if threshold is not None else None
    reps = [r for r in repetitions(sig) if lo <= r.start_s <= hi]
    alarms = [a for a in session_alarms(session) if lo <= a["t_s"] <= hi]
    duration = session.duration_s if since_mono is None and until_mono is None else \
        min(hi, session.duration_s) - max(lo, 0.0)
    summary = summarize(reps, duration_s=duration,
                        alarms=sum(1 for a in alarms if a["kind"] in ("alarm", "emergency_stop")))
    params = exercise_params(events)
    if params:
        summary["exercise_params"] = _clean(params)
    return {"repetitions": [r.as_dict() for r in reps], "summary": summary, "alarms": alarms}


def session_metrics(folder: str | Path) -> dict[str, Any]:
    """Read a session folder and compute its metrics (the command line's ``--metrics``)."""
    from app.recording import load_session

    return metrics_of_session(load_session(folder))
