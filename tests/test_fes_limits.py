"""FES limits: caps, start ramp, rate of increase, r.m.s. current; refused, never clamped (but knobs)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.safety.fes_limits import ChannelCaps, FesLimiter, FesLimitError, FesLimits, FesUpdate, rms_current_ma
from app.wire.sciencemode import ChannelListConfig, PulseMode, PulseSetting

FAST = settings(max_examples=200, deadline=None)
P = PulseSetting
CFG = ChannelListConfig((1, 2), t1_ms=25.0, t2_ms=3.0)  # 40 Hz


def _limits(**kw: object) -> FesLimits:
    args: dict[str, object] = {
        "max_current_ma": 60.0,
        "max_pulse_width_us": 400.0,
        "max_current_rise_ma_s": 20.0,
        "max_pulse_width_rise_us_s": 1000.0,
        "start_ramp_s": 0.0,
        "max_rms_current_ma": 30.0,
        "max_step_interval_s": 0.1,
    }
    args.update(kw)
    return FesLimits(**args)  # type: ignore[arg-type]


def _started(limits: FesLimits, t0: float = 0.0) -> FesLimiter:
    lim = FesLimiter(limits)
    lim.start(t0)
    return lim


def test_rms_formula_matches_reference_numbers() -> None:
    assert rms_current_ma(126, 500, 50.0) == pytest.approx(28.2, abs=0.1)  # reference §5
    assert rms_current_ma(126, 500, 1000 / 10.5, PulseMode.TRIPLET) == pytest.approx(67.3, abs=0.2)
    assert rms_current_ma(0, 500, 50.0) == 0.0


def test_limits_validate_their_fields() -> None:
    with pytest.raises(ValueError, match=r"max_current_ma = 130.*0\.\.126 mA"):
        FesLimits(max_current_ma=130.0)
    with pytest.raises(ValueError, match=r"clinical_caps\[3\]\.max_pulse_width_us"):
        FesLimits(clinical_caps={3: ChannelCaps(max_pulse_width_us=600.0)})
    with pytest.raises(ValueError, match="channel 9"):
        FesLimits(channel_caps={9: ChannelCaps()})


def test_caps_are_the_tightest_layer() -> None:
    limits = _limits(
        channel_caps={1: ChannelCaps(50.0, 300.0)}, clinical_caps={1: ChannelCaps(35.0, 350.0, 5.0)}
    )
    assert limits.caps_for(1) == (35.0, 300.0, 5.0)
    assert limits.caps_for(2) == (60.0, 400.0, 30.0)


def test_from_config_reads_the_safety_section() -> None:
    cfg = SimpleNamespace(
        max_current_ma=40.0,
        max_pulse_width_us=300.0,
        max_current_rise_ma_s=40.0,
        max_pulse_width_rise_us_s=500.0,
        max_rms_current_ma=10.0,
        start_ramp_s=1.0,
        channels={2: SimpleNamespace(max_current_ma=20.0, max_pulse_width_us=250.0)},
    )
    limits = FesLimits.from_config(cfg, {2: ChannelCaps(15.0)})
    assert limits.caps_for(2) == (15.0, 250.0, 10.0) and limits.start_ramp_s == 1.0


def test_not_started_refuses_current() -> None:
    lim = FesLimiter(_limits())
    lim.check(FesUpdate(CFG, {1: P(0, 200), 2: P(0, 0)}), 0.0)  # zero current is always fine
    with pytest.raises(FesLimitError, match="not started"):
        lim.check(FesUpdate(CFG, {1: P(1, 200)}), 0.1)


def test_cap_refused_not_clamped() -> None:
    lim = _started(_limits(clinical_caps={1: ChannelCaps(10.0)}, max_current_rise_ma_s=1000.0))
    with pytest.raises(FesLimitError, match=r"channel 1: 11 mA exceeds the cap of 10 mA") as exc:
        lim.check(FesUpdate(CFG, {1: P(11, 100)}), 1.0)
    assert exc.value.channel == 1
    assert lim.accepted()[1] == (0.0, 0.0)  # nothing changed
    lim.check(FesUpdate(CFG, {1: P(10, 100)}), 1.0)
    assert lim.accepted()[1] == (10.0, 100.0)


def test_rate_of_increase_and_unlimited_decrease() -> None:
    lim = _started(_limits(max_current_rise_ma_s=20.0))
    lim.check(FesUpdate(CFG, {1: P(2, 100)}), 0.1)  # 20 mA/s * 0.1 s = 2 mA
    with pytest.raises(FesLimitError, match="rises by 2 mA"):
        lim.check(FesUpdate(CFG, {1: P(4, 100)}), 0.15)  # only 1 mA allowed after 50 ms
    lim.check(FesUpdate(CFG, {1: P(3, 100)}), 0.15)
    lim.check(FesUpdate(CFG, {1: P(0, 0)}), 0.151)  # decreases are never limited
    # after a long plateau the single step is still bounded by rate * max_step_interval_s (2 mA)
    with pytest.raises(FesLimitError, match="rises"):
        lim.check(FesUpdate(CFG, {1: P(5, 0)}), 100.0)
    lim.check(FesUpdate(CFG, {1: P(2, 0)}), 100.0)


def test_slow_ramp_sent_often_is_accepted() -> None:
    # 1 mA steps every 50 ms at 20 mA/s, with repeated identical updates every 10 ms in between
    lim = _started(_limits(max_current_rise_ma_s=20.0))
    for i in range(1, 400):
        t = i * 0.01
        lim.check(FesUpdate(CFG, {1: P(min(i // 5, 60), min(i, 100))}), t)
    assert lim.accepted()[1] == (60.0, 100.0)


def test_start_ramp_ceiling() -> None:
    lim = _started(
        _limits(start_ramp_s=2.0, max_current_rise_ma_s=1000.0, max_pulse_width_rise_us_s=1e5), 10.0
    )
    assert lim.ceiling(1, 11.0) == (30.0, 200.0)
    with pytest.raises(FesLimitError, match="start-ramp"):
        lim.check(FesUpdate(CFG, {1: P(31, 100)}), 11.0)
    lim.check(FesUpdate(CFG, {1: P(30, 100)}), 11.0)
    lim.check(FesUpdate(CFG, {1: P(60, 400)}), 12.0)
    lim.stop()
    with pytest.raises(FesLimitError, match="not started"):
        lim.check(FesUpdate(CFG, {1: P(1, 100)}), 13.0)


def test_rms_limit_counts_frequency_and_pulse_group() -> None:
    lim = _started(_limits(max_current_rise_ma_s=1e4, max_pulse_width_rise_us_s=1e5, max_rms_current_ma=10.0))
    fast = ChannelListConfig((1, 2), t1_ms=10.0, t2_ms=3.0)  # 100 Hz
    # 40 mA, 300 µs single at 100 Hz: 40*sqrt(0.06) = 9.8 mA r.m.s. -> fine; as a doublet 13.9 -> refused
    lim.check(FesUpdate(fast, {1: P(40, 300)}), 1.0)
    with pytest.raises(FesLimitError, match=r"r\.m\.s\."):
        lim.check(FesUpdate(fast, {1: P(40, 300, PulseMode.DOUBLET)}), 2.0)
    # the same doublet on a low-frequency channel (every 3rd period) is within the limit
    slow = ChannelListConfig((1, 2), 10.0, 3.0, low_frequency_channels=(1,), low_frequency_factor=2)
    lim.check(FesUpdate(slow, {1: P(40, 300, PulseMode.DOUBLET)}), 3.0)


def test_unknown_channel_and_time_going_backwards() -> None:
    lim = _started(_limits())
    with pytest.raises(FesLimitError, match="not in the channel list"):
        lim.check(FesUpdate(CFG, {3: P(0, 0)}), 1.0)
    lim.check(FesUpdate(CFG, {}), 2.0)
    with pytest.raises(FesLimitError, match="backwards"):
        lim.check(FesUpdate(CFG, {}), 1.5)


def test_clamp_scale_stops_at_caps_and_rms() -> None:
    lim = FesLimiter(_limits(clinical_caps={2: ChannelCaps(24.0)}))
    peaks = {1: (30.0, 200.0), 2: (20.0, 200.0)}
    free = lim.clamp_scale("current", 1.1, other_scale=1.0, peaks=peaks, config=CFG)
    assert free.scale == 1.1 and not free.clamped
    capped = lim.clamp_scale("current", 1.5, other_scale=1.0, peaks=peaks, config=CFG)
    assert capped.clamped and capped.scale == pytest.approx(1.2) and "channel 2 current cap" in capped.reason
    width = lim.clamp_scale("pulse_width", 3.0, other_scale=1.0, peaks=peaks, config=CFG)
    assert width.clamped and width.scale == pytest.approx(2.0) and "pulse-width cap" in width.reason
    rms_limited = FesLimiter(_limits(max_rms_current_ma=5.0))
    r = rms_limited.clamp_scale("current", 2.0, other_scale=1.0, peaks=peaks, config=CFG)
    assert r.clamped and "r.m.s." in r.reason
    assert rms_current_ma(30.0 * r.scale, 200.0, 40.0) == pytest.approx(5.0)
    neg = lim.clamp_scale("current", -1.0, other_scale=1.0, peaks=peaks, config=CFG)
    assert neg.scale == 0.0 and neg.clamped


@FAST
@given(
    st.floats(0.01, 3.0),
    st.floats(0.1, 2.0),
    st.sampled_from(list(PulseMode)),
    st.floats(5, 126),
    st.floats(20, 500),
    st.sampled_from(["current", "pulse_width"]),
)
def test_clamped_scale_never_exceeds_limits(
    requested: float, other: float, mode: PulseMode, pc: float, pw: float, knob: str
) -> None:
    limits = _limits(max_rms_current_ma=12.0)
    lim = FesLimiter(limits)
    r = lim.clamp_scale(
        knob,
        requested,
        other_scale=other,
        peaks={1: (pc, pw)},
        config=CFG,  # type: ignore[arg-type]
        modes={1: mode},
    )
    assert 0 <= r.scale <= requested and r.clamped == (r.scale < requested)
    cs, ws = (r.scale, other) if knob == "current" else (other, r.scale)
    cap_c, cap_w, cap_rms = limits.caps_for(1)
    if knob == "current":
        assert pc * cs <= cap_c + 1e-6
    else:
        assert pw * ws <= cap_w + 1e-6
    assert (
        rms_current_ma(pc * cs, pw * ws, 40.0, mode) <= cap_rms + 1e-6
        or (knob == "current" and pw * ws > cap_w)
        or (knob == "pulse_width" and pc * cs > cap_c)
    )


update_step = st.tuples(
    st.floats(0.0, 0.3),  # dt
    st.integers(1, 2),
    st.integers(0, 126),
    st.integers(0, 500),
    st.sampled_from(list(PulseMode)),
)


@FAST
@given(st.lists(update_step, min_size=1, max_size=40), st.floats(0.0, 2.0))
def test_no_accepted_sequence_exceeds_caps_rate_or_rms(steps: list, start_ramp: float) -> None:
    limits = _limits(
        start_ramp_s=start_ramp,
        max_current_rise_ma_s=200.0,
        max_pulse_width_rise_us_s=5000.0,
        clinical_caps={2: ChannelCaps(30.0, 250.0, 3.0)},
    )
    cfg = ChannelListConfig((1, 2), t1_ms=12.5, t2_ms=3.0)  # 80 Hz
    lim = _started(limits, 0.0)
    t = 0.0
    # per channel and quantity: (time of the last change, value) of the delivered staircase
    last = {(ch, q): (0.0, 0) for ch in (1, 2) for q in (0, 1)}
    rates = (limits.max_current_rise_ma_s, limits.max_pulse_width_rise_us_s)
    for dt, ch, current, width, mode in steps:
        t += dt
        # bias towards plausible commands: small steps from the last accepted value half the time
        if current % 2 == 0:
            current = min(126, int(lim.accepted()[ch][0]) + current % 5)
            width = min(500, int(lim.accepted()[ch][1]) + width % 40)
        before = lim.accepted()
        try:
            lim.check(FesUpdate(cfg, {ch: P(current, width, mode)}), t)
        except FesLimitError:
            assert lim.accepted() == before  # a refusal changes nothing
            continue
        cap_c, cap_w, cap_rms = limits.caps_for(ch)
        frac = 1.0 if start_ramp == 0 else min(1.0, t / start_ramp)
        assert current <= cap_c * frac + 1e-6 and width <= cap_w * frac + 1e-6
        assert rms_current_ma(current, width, cfg.channel_frequency_hz(ch), mode) <= cap_rms + 1e-6
        for other in (1, 2):  # the channel not named in the update went to 0
            for q, value in enumerate((current, width) if other == ch else (0, 0)):
                last_t, last_v = last[other, q]
                if value != last_v:
                    # each rise of the staircase is at most rate * min(time since its last change, 0.1 s)
                    window = min(t - last_t, limits.max_step_interval_s)
                    assert value - last_v <= rates[q] * window + 1e-6
                    last[other, q] = (t, value)
        assert lim.accepted()[ch] == (current, width)
