"""FES limit logic (pure): what the safety supervisor lets through to the stimulator.

The limiter *refuses* (raises ``FesLimitError``) a commanded per-channel (current, pulse width) that is
out of limits; it never clamps a command, because a silently altered stimulation is worse than a
refused one. Only the live scale knobs are clamped (``clamp_scale``), and they report that they were.

Limits applied to every channel of every update:
- caps: the smallest of the device cap (MAX_CURRENT_MA / MAX_PULSE_WIDTH_US), the configured cap (all channels and per
  channel) and the per-patient clinical cap;
- start ramp: after ``start(now)`` the caps rise linearly from 0 to their value over ``start_ramp_s``;
- rate of increase: an increase must satisfy Δ ≤ rate · min(now − t_change, max_step_interval_s), where
  t_change is when that channel's value last changed. Decreases are never limited. Measuring from the
  last *change* lets a smooth profile sent at any update rate climb 1 mA at a time; the interval cap
  bounds the largest single step (rate · max_step_interval_s) after a long plateau;
- r.m.s. current per channel, from current, pulse width, frequency and pulse group (see ``rms_current_ma``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from app.wire.sciencemode import (
    CHANNELS,
    CHANNELS_TEXT,
    MAX_CURRENT_MA,
    MAX_PULSE_WIDTH_US,
    ChannelListConfig,
    PulseMode,
    PulseSetting,
)

_EPS = 1e-9

# Peaks or scales below this are treated as zero: dividing by a subnormal overflows (found by hypothesis).
_NEGLIGIBLE = 1e-9


class FesLimitError(Exception):
    """A commanded stimulation is outside the limits; ``reason`` is a sentence for the user."""

    def __init__(self, reason: str, channel: int | None = None) -> None:
        self.reason = reason
        self.channel = channel
        super().__init__(reason)


def rms_current_ma(
    current_ma: float, pulse_width_us: float, frequency_hz: float, mode: PulseMode = PulseMode.SINGLE
) -> float:
    """R.m.s. current of a symmetric biphasic pulse train.

    Each pulse is two phases of ``pulse_width_us`` at ``current_ma`` (the 100 µs inter-phase pause
    carries no current), ``mode.pulses`` pulses per period, ``frequency_hz`` periods per second:
    I_rms = I · √(2 · pw · f · n)  (reference §5: I_peak·√(phase·f), doubled inside the root for biphasic).
    """
    duty = 2.0 * pulse_width_us * 1e-6 * frequency_hz * PulseMode(mode).pulses
    return current_ma * math.sqrt(max(duty, 0.0))


@dataclass(frozen=True)
class ChannelCaps:
    """Caps for one channel (configured or clinical). ``max_rms_current_ma`` None = the global limit."""

    max_current_ma: float = float(MAX_CURRENT_MA)
    max_pulse_width_us: float = float(MAX_PULSE_WIDTH_US)
    max_rms_current_ma: float | None = None


def _check_range(name: str, value: float, lo: float, hi: float, unit: str) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} = {value!r} is outside the allowed range {lo:g}..{hi:g} {unit}")


@dataclass(frozen=True)
class FesLimits:
    """All FES limits. Validated on construction (ValueError naming the field and the range)."""

    max_current_ma: float = 40.0  # configured, every channel
    max_pulse_width_us: float = 300.0
    channel_caps: Mapping[int, ChannelCaps] = field(default_factory=dict)  # configured, per channel
    clinical_caps: Mapping[int, ChannelCaps] = field(default_factory=dict)  # per patient, per channel
    max_current_rise_ma_s: float = 40.0
    max_pulse_width_rise_us_s: float = 500.0
    start_ramp_s: float = 1.0
    max_rms_current_ma: float = 10.0
    max_step_interval_s: float = 0.1

    def __post_init__(self) -> None:
        _check_range("max_current_ma", self.max_current_ma, 0, MAX_CURRENT_MA, "mA")
        _check_range("max_pulse_width_us", self.max_pulse_width_us, 0, MAX_PULSE_WIDTH_US, "µs")
        _check_range("max_current_rise_ma_s", self.max_current_rise_ma_s, _EPS, 1e6, "mA/s")
        _check_range("max_pulse_width_rise_us_s", self.max_pulse_width_rise_us_s, _EPS, 1e7, "µs/s")
        _check_range("start_ramp_s", self.start_ramp_s, 0, 3600, "s")
        _check_range("max_rms_current_ma", self.max_rms_current_ma, 0, MAX_CURRENT_MA, "mA")
        _check_range("max_step_interval_s", self.max_step_interval_s, _EPS, 10, "s")
        for label, caps in (("channel_caps", self.channel_caps), ("clinical_caps", self.clinical_caps)):
            for ch, cap in caps.items():
                if ch not in CHANNELS:
                    raise ValueError(f"{label}: channel {ch!r} is not one of {CHANNELS_TEXT}")
                _check_range(f"{label}[{ch}].max_current_ma", cap.max_current_ma, 0, MAX_CURRENT_MA, "mA")
                _check_range(
                    f"{label}[{ch}].max_pulse_width_us", cap.max_pulse_width_us, 0, MAX_PULSE_WIDTH_US, "µs"
                )
                if cap.max_rms_current_ma is not None:
                    _check_range(
                        f"{label}[{ch}].max_rms_current_ma", cap.max_rms_current_ma, 0, MAX_CURRENT_MA, "mA"
                    )

    @classmethod
    def from_config(
        cls, fes_safety: Any, clinical_caps: Mapping[int, ChannelCaps] | None = None
    ) -> FesLimits:
        """From ``app.core.config.FesSafety`` (duck-typed: max_current_ma, max_pulse_width_us,
        max_current_rise_ma_s,
        max_pulse_width_rise_us_s, max_rms_current_ma, start_ramp_s, channels {ch: caps})."""
        channels = {
            int(ch): ChannelCaps(
                float(c.max_current_ma), float(c.max_pulse_width_us), getattr(c, "max_rms_current_ma", None)
            )
            for ch, c in dict(getattr(fes_safety, "channels", {}) or {}).items()
        }
        return cls(
            max_current_ma=float(fes_safety.max_current_ma),
            max_pulse_width_us=float(fes_safety.max_pulse_width_us),
            channel_caps=channels,
            clinical_caps=dict(clinical_caps or {}),
            max_current_rise_ma_s=float(fes_safety.max_current_rise_ma_s),
            max_pulse_width_rise_us_s=float(fes_safety.max_pulse_width_rise_us_s),
            start_ramp_s=float(fes_safety.start_ramp_s),
            max_rms_current_ma=float(fes_safety.max_rms_current_ma),
        )

    def caps_for(self, channel: int) -> tuple[float, float, float]:
        """(max current mA, max pulse width µs, max r.m.s. mA) for a channel: the tightest of all layers."""
        current = min(float(MAX_CURRENT_MA), self.max_current_ma)
        width = min(float(MAX_PULSE_WIDTH_US), self.max_pulse_width_us)
        rms = self.max_rms_current_ma
        for caps in (self.channel_caps, self.clinical_caps):
            cap = caps.get(channel)
            if cap is not None:
                current = min(current, cap.max_current_ma)
                width = min(width, cap.max_pulse_width_us)
                if cap.max_rms_current_ma is not None:
                    rms = min(rms, cap.max_rms_current_ma)
        return current, width, rms


def profile_limit_problems(limits: FesLimits, peaks: Mapping[int, tuple[float, float]],
                           patient: str = "") -> list[str]:
    """Why a profile with these per-channel peaks (mA, µs; scaled) would be refused, each reason naming the
    limit that refuses it: the stimulator's own range, the site's configuration (every channel, then the
    channel's own cap) or the patient's clinical cap. Empty when every peak is within every layer. The FES
    editor shows these before Apply (issue #30: a 60 mA profile read "valid", then Apply was refused)."""
    who = f"patient {patient}" if patient else "the patient"
    out: list[str] = []
    for ch, (current, width) in sorted(peaks.items()):
        layers: list[tuple[str, float, float]] = [
            ("the stimulator's range", float(MAX_CURRENT_MA), float(MAX_PULSE_WIDTH_US)),
            ("the site's limit (configuration, every channel)", limits.max_current_ma, limits.max_pulse_width_us),
        ]
        site = limits.channel_caps.get(ch)
        if site is not None:
            layers.append((f"the site's cap for channel {ch}", site.max_current_ma, site.max_pulse_width_us))
        clinical = limits.clinical_caps.get(ch)
        if clinical is not None:
            layers.append((f"{who}'s clinical cap for channel {ch}", clinical.max_current_ma,
                           clinical.max_pulse_width_us))
        for what, value, index, unit in (("current", current, 1, "mA"), ("pulse width", width, 2, "µs")):
            # Ties go to the most specific layer (the patient's cap over the site's equal limit): that is
            # the one a therapist can act on.
            tightest = min(reversed(layers), key=lambda layer: layer[index])
            cap = float(tightest[index])  # index 1 or 2: a float of the layer
            if value > cap + 1e-9:
                out.append(f"Channel {ch}: peak {what} {value:g} {unit} is above {tightest[0]} of {cap:g} {unit}.")
    return out


@dataclass(frozen=True)
class FesUpdate:
    """A commanded stimulation: the channel list in force and the setting of each of its channels."""

    config: ChannelListConfig
    settings: Mapping[int, PulseSetting]


@dataclass(frozen=True)
class ScaleClamp:
    scale: float
    clamped: bool
    reason: str = ""


@dataclass
class _ChannelState:
    current_ma: float = 0.0
    pulse_width_us: float = 0.0
    current_changed_at: float = 0.0
    width_changed_at: float = 0.0


class FesLimiter:
    """Stateful check of a stream of updates against ``FesLimits``. Not thread-safe: one owner."""

    def __init__(self, limits: FesLimits) -> None:
        self.limits = limits
        self._started_at: float | None = None
        self._last_now: float | None = None
        self._state: dict[int, _ChannelState] = {}

    @property
    def started(self) -> bool:
        return self._started_at is not None

    def accepted(self) -> dict[int, tuple[float, float]]:
        """The last accepted (current mA, pulse width µs) per channel."""
        return {ch: (s.current_ma, s.pulse_width_us) for ch, s in self._state.items()}

    def set_limits(self, limits: FesLimits) -> None:
        """New limits take effect for the next check (the present state is kept)."""
        self.limits = limits

    def start(self, now: float) -> None:
        """Stimulation starts from zero: the start ramp and the rate limits count from ``now``."""
        self._started_at = now
        self._last_now = now
        self._state = {ch: _ChannelState(0.0, 0.0, now, now) for ch in CHANNELS}

    def stop(self) -> None:
        """Stimulation stopped (everything at zero); a new ``start`` is needed before non-zero commands."""
        self._started_at = None
        self._state = {}

    def ceiling(self, channel: int, now: float) -> tuple[float, float]:
        """The present (current, pulse width) ceiling of a channel: caps times the start-ramp fraction."""
        current, width, _ = self.limits.caps_for(channel)
        if self._started_at is None:
            return 0.0, 0.0
        ramp = self.limits.start_ramp_s
        frac = 1.0 if ramp <= 0 else min(1.0, max(0.0, (now - self._started_at) / ramp))
        return current * frac, width * frac

    def check(self, update: FesUpdate, now: float) -> None:
        """Accept (and remember) ``update`` at time ``now`` or raise FesLimitError. A refused update changes
        nothing. Channels of the list missing from ``settings`` count as 0."""
        if self._last_now is not None and now < self._last_now:
            raise FesLimitError(f"time went backwards ({now:.6f} s < {self._last_now:.6f} s)")
        lim = self.limits
        new: dict[int, PulseSetting] = {}
        for ch in update.config.channels:
            new[ch] = update.settings.get(ch, PulseSetting(0, 0))
        for ch in update.settings:
            if ch not in update.config.channels:
                raise FesLimitError(f"channel {ch} is not in the channel list {update.config.channels}", ch)
        for ch, s in new.items():
            if ch not in CHANNELS:
                raise FesLimitError(f"channel {ch} does not exist ({CHANNELS_TEXT})", ch)
            if s.current_ma < 0 or s.pulse_width_us < 0:
                raise FesLimitError(f"channel {ch}: negative current or pulse width", ch)
            if self._started_at is None:
                if s.current_ma > 0:
                    raise FesLimitError(
                        f"channel {ch}: {s.current_ma} mA commanded but stimulation is not started", ch
                    )
                continue
            cap_current, cap_width, cap_rms = lim.caps_for(ch)
            if s.current_ma > cap_current + _EPS:
                raise FesLimitError(
                    f"channel {ch}: {s.current_ma} mA exceeds the cap of {cap_current:g} mA", ch
                )
            if s.pulse_width_us > cap_width + _EPS:
                raise FesLimitError(
                    f"channel {ch}: {s.pulse_width_us} µs exceeds the cap of {cap_width:g} µs", ch
                )
            ramp_current, ramp_width = self.ceiling(ch, now)
            if s.current_ma > ramp_current + _EPS:
                raise FesLimitError(
                    f"channel {ch}: {s.current_ma} mA exceeds the start-ramp ceiling of "
                    f"{ramp_current:.1f} mA at {now - self._started_at:.2f} s",
                    ch,
                )
            if s.pulse_width_us > ramp_width + _EPS:
                raise FesLimitError(
                    f"channel {ch}: {s.pulse_width_us} µs exceeds the start-ramp ceiling of "
                    f"{ramp_width:.0f} µs at {now - self._started_at:.2f} s",
                    ch,
                )
            st = self._state[ch]
            rise = s.current_ma - st.current_ma
            allowed = lim.max_current_rise_ma_s * min(now - st.current_changed_at, lim.max_step_interval_s)
            if rise > allowed + _EPS:
                raise FesLimitError(
                    f"channel {ch}: current rises by {rise:g} mA; at most {allowed:.2f} mA allowed "
                    f"now ({lim.max_current_rise_ma_s:g} mA/s)",
                    ch,
                )
            rise = s.pulse_width_us - st.pulse_width_us
            allowed = lim.max_pulse_width_rise_us_s * min(now - st.width_changed_at, lim.max_step_interval_s)
            if rise > allowed + _EPS:
                raise FesLimitError(
                    f"channel {ch}: pulse width rises by {rise:g} µs; at most {allowed:.1f} µs "
                    f"allowed now ({lim.max_pulse_width_rise_us_s:g} µs/s)",
                    ch,
                )
            rms = rms_current_ma(
                s.current_ma, s.pulse_width_us, update.config.channel_frequency_hz(ch), s.mode
            )
            if rms > cap_rms + _EPS:
                raise FesLimitError(
                    f"channel {ch}: r.m.s. current {rms:.1f} mA exceeds {cap_rms:g} mA "
                    f"({s.current_ma} mA, {s.pulse_width_us} µs, "
                    f"{update.config.channel_frequency_hz(ch):.1f} Hz, {PulseMode(s.mode).name})",
                    ch,
                )
        # accepted: remember (channels not in the list are off)
        self._last_now = now
        if self._started_at is None:
            return
        for ch in CHANNELS:
            s = new.get(ch, PulseSetting(0, 0))
            st = self._state[ch]
            if s.current_ma != st.current_ma:
                st.current_ma, st.current_changed_at = float(s.current_ma), now
            if s.pulse_width_us != st.pulse_width_us:
                st.pulse_width_us, st.width_changed_at = float(s.pulse_width_us), now

    def clamp_scale(
        self,
        knob: Literal["current", "pulse_width"],
        requested: float,
        *,
        other_scale: float,
        peaks: Mapping[int, tuple[float, float]],
        config: ChannelListConfig,
        modes: Mapping[int, PulseMode] | None = None,
    ) -> ScaleClamp:
        """Largest allowed value of a live scale knob, at most ``requested``.

        ``peaks``: per channel the unscaled profile maxima (current mA, pulse width µs); ``other_scale``
        is the
        present value of the other knob. The knob stops where a scaled peak reaches a cap or the r.m.s. limit
        (both peaks assumed at once, which is conservative). Reports which limit stopped it.
        """
        if not math.isfinite(requested) or requested <= 0:
            return ScaleClamp(0.0, requested != 0, "" if requested == 0 else "a scale cannot be negative")
        best, reason = requested, ""
        for ch, (peak_current, peak_width) in sorted(peaks.items()):
            cap_current, cap_width, cap_rms = self.limits.caps_for(ch)
            mode = (modes or {}).get(ch, PulseMode.SINGLE)
            per_pulse = (
                2e-6 * config.channel_frequency_hz(ch) * PulseMode(mode).pulses
            )  # duty per µs of width
            if knob == "current":
                if peak_current <= _NEGLIGIBLE:
                    continue
                candidates = [(cap_current / peak_current, f"channel {ch} current cap {cap_current:g} mA")]
                width = other_scale * peak_width
                if width > _NEGLIGIBLE:
                    candidates.append(
                        (
                            cap_rms / (peak_current * math.sqrt(per_pulse * width)),
                            f"channel {ch} r.m.s. limit {cap_rms:g} mA",
                        )
                    )
            else:
                if peak_width <= _NEGLIGIBLE:
                    continue
                candidates = [(cap_width / peak_width, f"channel {ch} pulse-width cap {cap_width:g} µs")]
                current = other_scale * peak_current
                if current > _NEGLIGIBLE:
                    candidates.append(
                        (
                            (cap_rms / current) ** 2 / (per_pulse * peak_width),
                            f"channel {ch} r.m.s. limit {cap_rms:g} mA",
                        )
                    )
            for limit, why in candidates:
                if limit < best:
                    best, reason = limit, why
        return ScaleClamp(best, best < requested, reason)
