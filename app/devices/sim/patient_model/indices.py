"""The patient model's indices, each normalised to 0..1 and fed incrementally.

TPI -- Task Performance Index (0 poor .. 1 excellent), over the last ``window`` sub-tasks:
    TPI = w * success_rate + (1 - w) * mean(time_score)
    time_score = 1 when the target was reached within ``normTime``, falling linearly to 0 at
    ``maxTime``; a failed sub-task scores 0.  With no sub-task yet: 0.5 (no evidence either way).

MPI -- Motor Performance Index (0 poor .. 1 excellent), mean over the last ``window`` movements of
    the mean of three scores per movement (a movement = one sub-task, start_movement..end_movement):
    * smoothness: spectral arc length (SPARC, Balasubramanian et al. 2015) of the speed profile,
      mapped linearly from ``sparcPoor`` (0) to ``sparcGood`` (1); a minimum-jerk reach gives -1.41;
    * peak speed relative to ``normPeakSpeed``;
    * directed interaction force: mean force the patient puts on the handle toward the target,
      0.5 + 0.5 * F / ``normForce`` (pushing toward the target -> 1, being dragged -> 0).
    With no movement yet: 0.5.

PTI -- Physiological Trend Index (0 no or negative trend .. 1 strong positive change), from
    least-squares slopes over the last ``window`` s of heart rate, skin conductance and skin
    temperature (samples averaged in 0.5 s bins; a channel needs ``minSpan`` s of data):
    channel score = clip(sign * slope / reference slope, 0, 1), weighted mean of the channels.
    A rising heart rate and skin conductance mean sympathetic activation (effort, stress); skin
    temperature counts with sign -1 because peripheral skin temperature falls with it.
    With no usable channel: 0.

Pure: no I/O, no Qt.  Times in s, positions in m, forces in N.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


def _clip01(x: float) -> float:
    return min(1.0, max(0.0, x))


# ---------------------------------------------------------------------------------------------
# TPI


@dataclass(frozen=True)
class TpiNorms:
    window: int = 10             # sub-tasks
    normTime: float = 3.0        # s, reaching within this is "excellent"
    maxTime: float = 12.0        # s, reaching after this scores no time credit
    successWeight: float = 0.6


class TaskPerformance:
    NEUTRAL = 0.5

    def __init__(self, norms: TpiNorms | None = None) -> None:
        self.norms = norms or TpiNorms()
        self._results: deque[tuple[bool, float]] = deque(maxlen=self.norms.window)

    def reset(self) -> None:
        self._results.clear()

    def add_subtask(self, success: bool, duration: float) -> None:
        """A sub-task ended: reached the target (``success``) after ``duration`` s."""
        self._results.append((bool(success), float(duration)))

    def time_score(self, duration: float) -> float:
        n = self.norms
        if math.isnan(duration):
            return 0.0
        return _clip01((n.maxTime - duration) / (n.maxTime - n.normTime))

    @property
    def count(self) -> int:
        return len(self._results)

    @property
    def value(self) -> float:
        if not self._results:
            return self.NEUTRAL
        n = self.norms
        success = sum(ok for ok, _ in self._results) / len(self._results)
        timing = sum(self.time_score(d) if ok else 0.0 for ok, d in self._results) / len(self._results)
        return _clip01(n.successWeight * success + (1.0 - n.successWeight) * timing)


# ---------------------------------------------------------------------------------------------
# MPI


def spectral_arc_length(speed: npt.ArrayLike, fs: float, fc: float = 10.0, amp_threshold: float = 0.05,
                        pad_level: int = 4) -> float:
    """SPARC smoothness of a speed profile sampled at ``fs`` Hz (closer to 0 = smoother).

    Arc length of the normalised magnitude spectrum up to the adaptive cut-off: the highest
    frequency <= ``fc`` whose magnitude is still >= ``amp_threshold`` of the peak."""
    v = np.asarray(speed, dtype=np.float64)
    if v.size < 2 or not np.any(v):
        return 0.0
    nfft = 1 << (math.ceil(math.log2(v.size)) + pad_level)
    freqs = np.arange(nfft) * fs / nfft
    mag = np.abs(np.fft.fft(v, nfft))
    mag = mag / mag.max()
    sel = freqs <= fc
    f_sel, m_sel = freqs[sel], mag[sel]
    above = np.flatnonzero(m_sel >= amp_threshold)
    last = int(above[-1]) if above.size else 1
    f_sel, m_sel = f_sel[: last + 1], m_sel[: last + 1]
    if f_sel.size < 2:
        return 0.0
    df = np.diff(f_sel) / f_sel[-1]
    return -float(np.sum(np.sqrt(df * df + np.diff(m_sel) ** 2)))


@dataclass(frozen=True)
class MpiNorms:
    window: int = 5                # movements
    normPeakSpeed: float = 0.25    # m/s
    sparcGood: float = -1.5        # a minimum-jerk reach gives -1.41
    sparcPoor: float = -4.0
    normForce: float = 10.0        # N toward the target for a full force score
    sampleRate: float = 100.0      # Hz, the speed profile is resampled to it for SPARC


@dataclass(frozen=True)
class MovementMetrics:
    duration: float
    sparc: float
    peakSpeed: float
    directedForce: float
    smoothnessScore: float
    speedScore: float
    forceScore: float

    @property
    def score(self) -> float:
        return (self.smoothnessScore + self.speedScore + self.forceScore) / 3.0


class MotorPerformance:
    NEUTRAL = 0.5
    MIN_SAMPLES = 10

    def __init__(self, norms: MpiNorms | None = None) -> None:
        self.norms = norms or MpiNorms()
        self._movements: deque[MovementMetrics] = deque(maxlen=self.norms.window)
        self._samples: list[tuple[float, float, float]] = []  # t, velocity, force
        self._direction = 0.0
        self._active = False

    def reset(self) -> None:
        self._movements.clear()
        self._samples = []
        self._active = False

    def start_movement(self, start_pos: float, target: float) -> None:
        """A sub-task starts: the handle should go from ``start_pos`` to ``target``."""
        self._samples = []
        self._direction = math.copysign(1.0, target - start_pos) if target != start_pos else 0.0
        self._active = True

    def add_sample(self, t: float, velocity: float, force: float) -> None:
        """Handle velocity (m/s) and the force the patient puts on it (N, + toward +x)."""
        if self._active and all(math.isfinite(x) for x in (t, velocity, force)):
            if not self._samples or t > self._samples[-1][0]:
                self._samples.append((t, velocity, force))

    def end_movement(self) -> MovementMetrics | None:
        """The sub-task ended; returns its metrics (None if too short to judge)."""
        self._active = False
        samples, self._samples = self._samples, []
        if len(samples) < self.MIN_SAMPLES:
            return None
        arr = np.asarray(samples)
        t, vel, force = arr[:, 0], arr[:, 1], arr[:, 2]
        n = self.norms
        grid = np.arange(t[0], t[-1], 1.0 / n.sampleRate)
        speed = np.abs(np.interp(grid, t, vel))
        sparc = spectral_arc_length(speed, n.sampleRate)
        peak = float(np.max(np.abs(vel)))
        directed = float(np.mean(force)) * self._direction
        m = MovementMetrics(
            duration=float(t[-1] - t[0]), sparc=sparc, peakSpeed=peak, directedForce=directed,
            smoothnessScore=_clip01((sparc - n.sparcPoor) / (n.sparcGood - n.sparcPoor)),
            speedScore=_clip01(peak / n.normPeakSpeed),
            forceScore=_clip01(0.5 + 0.5 * directed / n.normForce))
        self._movements.append(m)
        return m

    @property
    def count(self) -> int:
        return len(self._movements)

    @property
    def value(self) -> float:
        if not self._movements:
            return self.NEUTRAL
        return _clip01(sum(m.score for m in self._movements) / len(self._movements))


# ---------------------------------------------------------------------------------------------
# PTI


@dataclass(frozen=True)
class PtiNorms:
    window: float = 60.0            # s
    minSpan: float = 20.0           # s of data a channel needs
    binWidth: float = 0.5           # s
    heartRateSlope: float = 6.0     # bpm/min for a full channel score
    conductanceSlope: float = 1.0   # µS/min
    temperatureSlope: float = 0.5   # °C/min (of falling temperature)
    weights: tuple[float, float, float] = (0.4, 0.4, 0.2)        # heart rate, conductance, temperature
    signs: tuple[float, float, float] = (1.0, 1.0, -1.0)


CHANNELS = ("heartRate", "skinConductance", "temperature")


class PhysiologicalTrend:
    def __init__(self, norms: PtiNorms | None = None) -> None:
        self.norms = norms or PtiNorms()
        self.reset()

    def reset(self) -> None:
        self._bins: deque[tuple[float, tuple[float, float, float]]] = deque()
        self._bin_start: float | None = None
        self._sums = [0.0, 0.0, 0.0]
        self._counts = [0, 0, 0]
        # The slopes change only when the bins do (a bin closed or left the window, every binWidth at most); the
        # model asks for them three times per frame at 100 Hz (#38: the helper's main cost).
        self._slopes: dict[str, float] | None = None

    def add_sample(self, t: float, heartRate: float, skinConductance: float, temperature: float) -> None:
        """One physiological sample; NaN values (e.g. heart rate not locked) are skipped."""
        n = self.norms
        if self._bin_start is None:
            self._bin_start = t
        elif t >= self._bin_start + n.binWidth:
            self._close_bin()
            self._bin_start = t
        for i, v in enumerate((heartRate, skinConductance, temperature)):
            if math.isfinite(v):
                self._sums[i] += v
                self._counts[i] += 1
        while self._bins and self._bins[0][0] < t - n.window:
            self._bins.popleft()
            self._slopes = None

    def _close_bin(self) -> None:
        assert self._bin_start is not None
        m = [s / c if c else math.nan for s, c in zip(self._sums, self._counts, strict=True)]
        self._bins.append((self._bin_start + self.norms.binWidth / 2, (m[0], m[1], m[2])))
        self._sums = [0.0, 0.0, 0.0]
        self._counts = [0, 0, 0]
        self._slopes = None

    def slopes(self) -> dict[str, float]:
        """Least-squares slope per minute of each channel over the window (NaN if too little data)."""
        if self._slopes is None:
            self._slopes = self._fit()
        return dict(self._slopes)

    def _fit(self) -> dict[str, float]:
        out = {c: math.nan for c in CHANNELS}
        if not self._bins:
            return out
        t = np.fromiter((b[0] for b in self._bins), dtype=np.float64)
        values = np.asarray([b[1] for b in self._bins], dtype=np.float64)
        for i, name in enumerate(CHANNELS):
            ok = np.isfinite(values[:, i])
            if np.count_nonzero(ok) < 3:
                continue
            tt = t[ok]
            if tt[-1] - tt[0] < self.norms.minSpan:
                continue
            tc = tt - tt.mean()
            out[name] = float(np.dot(tc, values[ok, i] - values[ok, i].mean()) / np.dot(tc, tc)) * 60.0
        return out

    @property
    def value(self) -> float:
        n = self.norms
        refs = (n.heartRateSlope, n.conductanceSlope, n.temperatureSlope)
        total = weight = 0.0
        for slope, ref, w, sign in zip(self.slopes().values(), refs, n.weights, n.signs, strict=True):
            if math.isnan(slope):
                continue
            total += w * _clip01(sign * slope / ref)
            weight += w
        return total / weight if weight else 0.0
