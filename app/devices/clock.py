"""Device time → host time: when was a sample taken, on the host's monotonic clock?

A driver knows two times for every sample: when the bytes carrying it came back from a read (the *arrival*,
``time.monotonic``), and — for devices that have one — the device's own clock at sampling (the LINarm's
``t_us``, the physiological board's millisecond tick). The arrival is late by a delay that varies: the link
(USB-serial adapters deliver several frames per read), the operating system (a busy machine runs the reading
thread late) and the reading loop's own batching. Stamping samples with it puts several samples on one instant
and moves them all late. The device clock is regular but counts on another time base, with its own origin and
rate (a crystal is off by up to ~±100 ppm), and it may wrap or restart.

:class:`DeviceClock` maps the device clock onto the host's: ``host = x + offset + drift · x`` (``x`` the
device time since the clock was seeded). Because every delay is positive, every observed ``arrival − x`` lies
on or above the true line, so the line is estimated from the *lower envelope* of those points — the way
Lab Streaming Layer's clock synchronisation keeps the best (least delayed) measurements, and the classic
convex-hull method of network clock-skew estimation:

* points are decimated to the minimum of each ``bin_s`` of device time and kept for ``window_s``;
* every ``refit_s`` the lower convex hull of the kept minima is computed; its edge spanning the middle of the window
  gives the drift (a long baseline between two least-delayed points); the offset is the supporting line with
  that slope, i.e. the lowest point — so a later sample can only move the line down, never up;
* a sample below the line moves the line down at once (it proves the offset lower);
* the mapped time is never after the arrival (a sample cannot arrive before it was taken) and always after
  the previous sample's (strictly increasing for strictly increasing device time).

Robustness: the raw counter is unwrapped (``wrap_s``); a backwards step, or a step that disagrees with the
host's elapsed time by more than ``jump_s`` (a device reset, a counter restarted by a reconnect), re-seeds
the clock from that sample on (``resets`` counts them), and so do ``late_run_s`` of samples all more than
``late_s`` above the line (the device clock fell behind: a reset the counter cannot show); once warmed up,
a single sample more than ``outlier_s`` below the line is treated as a corrupt device time (stamped on the
line, not used) unless ``outlier_run`` of them in a row say the device clock really moved (then it re-seeds).

Streams without a device clock use :class:`DeviceClock` on a *counted* clock: the sample's sequence number
(or its index) times the nominal period, with a short window — a dejittered arrival time.

Pure Python, no Qt: the drivers call :meth:`DeviceClock.map` on their threads, tests on a virtual clock.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass


@dataclass
class ClockEstimate:
    """The current line: ``host = x + offset_s + drift · x``, x device seconds since the seed."""

    offset_s: float
    drift: float
    points: int  # bins in the window
    span_s: float  # device time the window covers


def _lower_hull(xs: list[float], ys: list[float]) -> list[int]:
    """Indices of the lower convex hull of points sorted by x (Andrew's monotone chain, lower half)."""
    hull: list[int] = []
    for i in range(len(xs)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            # keep b only if a → b → i turns left (counter-clockwise): b lies below the chord a → i
            cross = (xs[b] - xs[a]) * (ys[i] - ys[a]) - (ys[b] - ys[a]) * (xs[i] - xs[a])
            if cross <= 0.0:
                hull.pop()
            else:
                break
        hull.append(i)
    return hull


class DeviceClock:
    """Online map of one device clock onto the host's monotonic clock (seconds on both sides)."""

    def __init__(self, *, wrap_s: float | None = None, window_s: float = 30.0, bin_s: float = 0.05,
                 jump_s: float = 1.0, outlier_s: float = 0.1, outlier_run: int = 3,
                 warmup_s: float = 2.0, max_drift: float = 1e-3, recent_s: float = 5.0,
                 late_s: float = 0.25, late_run_s: float = 5.0, refit_s: float = 0.5,
                 reorder_s: float = 0.02) -> None:
        self.wrap_s = wrap_s
        self.window_s = window_s
        self.bin_s = bin_s
        self.jump_s = jump_s
        self.outlier_s = outlier_s
        self.outlier_run = outlier_run
        self.warmup_s = warmup_s
        self.max_drift = max_drift
        self.recent_s = recent_s
        self.late_s = late_s
        self.late_run_s = late_run_s
        self.refit_s = refit_s
        self.reorder_s = reorder_s
        self.resets = -1  # the first seed is not a reset
        self.outliers = 0
        self._seeded = False
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything: the next sample seeds the clock (a reconnect, a new device)."""
        self._seeded = False
        self._raw_last = 0.0  # the last raw device reading (wrapped)
        self._x = 0.0  # unwrapped device time since the seed
        self._arrival_last = 0.0
        self._origin = 0.0  # host time of the seed: y values are kept small
        self._bins_x: list[float] = []
        self._bins_y: list[float] = []
        self._bin_start = 0.0
        self._refit_at = 0.0
        self._offset = 0.0
        self._drift = 0.0
        self._suspect = 0
        self._late_since: float | None = None
        self._last_x = -1.0
        self._last_mapped = float("-inf")
        self._last_result = float("-inf")

    def _seed(self, raw: float, arrival: float) -> None:
        self.resets += 1
        last_result = self._last_result
        self.reset()
        self._seeded = True
        self._raw_last, self._x, self._arrival_last, self._origin = raw, 0.0, arrival, arrival
        self._bin_start = 0.0
        self._offset = 0.0
        self._last_result = last_result  # monotonic across a re-seed as well

    @property
    def estimate(self) -> ClockEstimate:
        span = self._bins_x[-1] - self._bins_x[0] if self._bins_x else 0.0
        return ClockEstimate(self._origin + self._offset, self._drift, len(self._bins_x), span)

    # ------------------------------------------------------------------ the map
    def map(self, device_s: float, arrival_s: float) -> float:
        """Host time (monotonic s) at which the sample with device time ``device_s`` (raw, wrapping at
        ``wrap_s``) was taken, given that it arrived at ``arrival_s``."""
        if not self._seeded:
            self._seed(device_s, arrival_s)
            return self._stamp(0.0, arrival_s)
        if device_s == self._raw_last and self._last_x == self._x:
            return self._last_mapped  # another sample of the same device instant (the LINarm's VSA and motors)
        step = device_s - self._raw_last
        if self.wrap_s is not None:
            step %= self.wrap_s
            if step > self.wrap_s / 2:
                step -= self.wrap_s  # a step back, not most of a wrap ahead
        elapsed = arrival_s - self._arrival_last
        if -self.reorder_s <= step < 0.0:
            # a sample a little older than the last (another stream of the same clock, a reordered datagram):
            # on the line, leaving the estimate and the other samples' order alone
            x = self._x + step
            return min(self._origin + x + self._offset + self._drift * x, arrival_s)
        # The device clock and the host's must advance alike; bursts and late reads make them differ by the
        # link's delay, never by more than jump_s: beyond that the device clock jumped (reset, restart).
        if step < 0.0 or abs(step - elapsed) > self.jump_s:
            self._seed(device_s, arrival_s)
            return self._stamp(0.0, arrival_s)
        x = self._x + step
        y = arrival_s - self._origin - x
        line = self._offset + self._drift * x
        warmed = bool(self._bins_x) and x - self._bins_x[0] >= self.warmup_s
        if warmed and y < line - self.outlier_s:
            self._suspect += 1
            if self._suspect >= self.outlier_run:
                self._seed(device_s, arrival_s)
                return self._stamp(0.0, arrival_s)
            self.outliers += 1
            # a corrupt device time: stamp the sample where the last good one leads, advance nothing
            return self._monotonic(min(arrival_s, self._last_mapped + max(0.0, elapsed)))
        self._suspect = 0
        # Every sample far above the line for late_run_s: the device clock fell behind (a board that restarted
        # quicker than its counter's wrap can show, a clock set back) — or the link really is that slow; either
        # way the line no longer describes it: start again.
        if y - line > self.late_s:
            if self._late_since is None:
                self._late_since = x
            elif x - self._late_since > self.late_run_s:
                self._seed(device_s, arrival_s)
                return self._stamp(0.0, arrival_s)
        else:
            self._late_since = None
        self._raw_last, self._x, self._arrival_last = device_s, x, arrival_s
        self._add(x, y)
        return self._stamp(x, arrival_s)

    def _stamp(self, x: float, arrival_s: float) -> float:
        if x == self._last_x:
            return self._last_mapped
        mapped = self._origin + x + self._offset + self._drift * x
        mapped = min(mapped, arrival_s)  # never after its arrival
        self._last_x = x
        self._last_mapped = self._monotonic(mapped)
        return self._last_mapped

    def _monotonic(self, t: float) -> float:
        if t <= self._last_result:
            t = self._last_result + 1e-6
        self._last_result = t
        return t

    def _add(self, x: float, y: float) -> None:
        xs, ys = self._bins_x, self._bins_y
        if not xs:
            xs.append(x)
            ys.append(y)
            self._bin_start = x
            self._offset, self._drift = y, 0.0
            return
        if y < self._offset + self._drift * x:
            self._offset = y - self._drift * x  # a less delayed sample: the line moves down at once
        if x - self._bin_start < self.bin_s:
            if y < ys[-1]:
                xs[-1], ys[-1] = x, y
            return
        # a new bin: drop what left the window; refit on the completed bins now and then (the hull is O(bins))
        if x >= self._refit_at or len(xs) < 8:
            self._refit()
            self._refit_at = x + self.refit_s
        xs.append(x)
        ys.append(y)
        self._bin_start = x
        cut = 0
        while cut < len(xs) - 1 and x - xs[cut] > self.window_s:
            cut += 1
        if cut:
            del xs[:cut], ys[:cut]

    def _refit(self) -> None:
        xs, ys = self._bins_x, self._bins_y
        if len(xs) < 3 or xs[-1] - xs[0] < min(self.warmup_s, self.window_s) / 2:
            self._offset = min(y - self._drift * x for x, y in zip(xs, ys, strict=True))
            return
        hull = _lower_hull(xs, ys)
        mid = (xs[0] + xs[-1]) / 2.0
        drift = self._drift
        for a, b in itertools.pairwise(hull):
            if xs[a] <= mid <= xs[b] and xs[b] > xs[a]:
                drift = (ys[b] - ys[a]) / (xs[b] - xs[a])
                break
        self._drift = d = max(-self.max_drift, min(self.max_drift, drift))
        # the offset from the recent points only: a slope slightly off then costs little at the newest samples
        since = xs[-1] - self.recent_s
        self._offset = min(y - d * x for x, y in zip(xs, ys, strict=True) if x >= since)


class CountedClock:
    """A clock for a stream without one: the sample's sequence number (wrapping at ``wrap``) or, without one,
    its index, times the nominal period, mapped by a :class:`DeviceClock` with a short window. The result is
    the arrival time with the read jitter taken out (a dejittered arrival)."""

    def __init__(self, rate_hz: float, wrap: int | None = None, window_s: float = 2.0) -> None:
        self.period_s = 1.0 / rate_hz
        self.wrap = wrap
        self.count = 0
        self.clock = DeviceClock(wrap_s=wrap * self.period_s if wrap else None, window_s=window_s,
                                 bin_s=5 * self.period_s, warmup_s=window_s, jump_s=0.5, max_drift=0.05)

    def reset(self) -> None:
        self.count = 0
        self.clock.reset()

    def map(self, arrival_s: float, seq: int | None = None) -> float:
        n = self.count if seq is None else seq
        self.count += 1
        return self.clock.map(n * self.period_s, arrival_s)
