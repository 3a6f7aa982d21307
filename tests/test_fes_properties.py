"""Acceptance 4: whatever the profile, the scale factors and the calls (as a script or the GUI make them),
nothing outside the caps, the start ramp, the rate of increase or the r.m.s. limit reaches the wire.

The driver runs against the simulator core on an in-process loopback with a simulated clock (no threads,
no pty), so hypothesis can try hundreds of sessions. An independent checker decodes every byte the driver
wrote, as the device would, and re-applies the limits to what it finds.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from app.core.config import AppConfig
from app.core.fes_profile import ChannelProfile, FesProfile, Trapezoid
from app.devices.rehastim import FesDriver, FesError
from app.devices.sim.rehastim_core import RehaStimSimCore
from app.safety.fes_limits import ChannelCaps, FesLimiter, FesLimits, rms_current_ma
from app.safety.supervisor import SafetyError, SafetySupervisor
from app.wire.sciencemode import (
    BadPacket,
    ChannelListConfig,
    PulseMode,
    PulseSetting,
    Sm1CommandDecoder,
    Sm1Init,
    Sm1Stop,
    Sm1Update,
    Sm2Decoder,
    Sm2InitChannelListMode,
    Sm2StartChannelListMode,
    Sm2StopChannelListMode,
)

FAST = settings(max_examples=200, deadline=None)
TICK_S = 0.005


class Loopback:
    """The wire: what the driver writes goes to the simulated device at once, its reply straight back."""

    description = "loopback"
    is_open = True

    def __init__(self, core: RehaStimSimCore, clock: list[float]) -> None:
        self.core, self.clock = core, clock
        self.wire: list[tuple[float, bytes]] = []
        self.driver: FesDriver | None = None

    def open(self) -> None: ...
    def close(self) -> None: ...

    def read(self, timeout: float) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        t = self.clock[0]
        self.wire.append((t, data))
        reply = self.core.handle_bytes(data, t)
        if reply and self.driver is not None:
            self.driver.on_bytes(reply, 0)


@dataclass
class Session:
    protocol: str
    clock: list[float]
    link: Loopback
    driver: FesDriver
    supervisor: SafetySupervisor
    # (wire index from which, limits): ordered by the wire, not the virtual clock — an update sent at the same
    # instant just before a change of caps was judged by the new caps (hypothesis found it: 0 mA 1 µs, cap 0 µs)
    limits_log: list[tuple[int, FesLimits]] = field(default_factory=list)
    estop_log: list[tuple[int, bool]] = field(default_factory=list)  # (wire index from which, latched)

    def advance(self, seconds: float) -> None:
        end = self.clock[0] + seconds
        while self.clock[0] < end - 1e-12:
            self.clock[0] = min(end, self.clock[0] + TICK_S)
            out = self.link.core.tick(self.clock[0])
            if out:
                self.driver.on_bytes(out, 0)
            self.driver.on_tick(self.clock[0])


_OPEN: list[Session] = []  # closed by the next session and when the test ends: their command queues' threads
                           # would idle on for 1 s each, and the leftover check would wait for them


def _close_open_sessions() -> None:
    while _OPEN:
        _OPEN.pop().driver.commands.close("the session ended")


@pytest.fixture(autouse=True)
def _close_sessions() -> Iterator[None]:
    yield
    _close_open_sessions()


def session(protocol: str, limits: FesLimits) -> Session:
    _close_open_sessions()  # the previous example's (hypothesis draws one session per example)
    clock = [100.0]
    supervisor = SafetySupervisor(AppConfig().safety)
    supervisor.fes_limiter = FesLimiter(limits)
    link = Loopback(RehaStimSimCore(protocol), clock)  # type: ignore[arg-type]
    driver = FesDriver(link, supervisor, protocol=protocol, clock=lambda: clock[0])  # type: ignore[arg-type]
    link.driver = driver
    supervisor.register_estop_action("FES stop", lambda reason: driver.stop_stimulation(reason, "e-stop"))
    driver._set_connected(True, "loopback")
    driver.on_connect()
    driver._driver_thread = threading.get_ident() + 1  # the test thread plays the caller, not the loop
    s = Session(protocol, clock, link, driver, supervisor, [(0, limits)])
    _OPEN.append(s)
    s.advance(0.6 if protocol == "sm2" else 0.01)  # SM2: the device's Init and our InitAck
    assert driver.device_ready
    return s


# ── the independent checker ───────────────────────────────────────────────────────────────────────────


def violations(s: Session) -> list[str]:
    decoder = Sm1CommandDecoder() if s.protocol == "sm1" else Sm2Decoder()
    config: ChannelListConfig | None = None
    started_at = 0.0
    last: dict[int, tuple[int, int]] = {}
    changed: dict[int, tuple[float, float]] = {}
    found: list[str] = []

    def limits_at(index: int) -> FesLimits:
        return [lim for i, lim in s.limits_log if i <= index][-1]

    def latched_at(index: int) -> bool:
        states = [on for i, on in s.estop_log if i <= index]
        return bool(states and states[-1])

    for index, (t, data) in enumerate(s.link.wire):
        for msg in decoder.feed(data):
            if isinstance(msg, BadPacket):
                found.append(f"{t:.3f}: the driver sent a bad packet: {msg.reason}")
            elif isinstance(msg, Sm1Init | Sm2InitChannelListMode):
                config, started_at = msg.config, t
                last = {ch: (0, 0) for ch in config.channels}
                changed = {ch: (t, t) for ch in config.channels}
            elif isinstance(msg, Sm1Stop | Sm2StopChannelListMode):
                config = None
            elif isinstance(msg, Sm1Update | Sm2StartChannelListMode):
                if config is None:
                    found.append(f"{t:.3f}: an update without a channel list")
                    continue
                lim = limits_at(index)
                for ch, p in zip(config.channels, msg.settings, strict=True):
                    found += check_channel(s.protocol, lim, config, ch, p, t, started_at, last[ch], changed[ch],
                                           latched_at(index))
                    old = last[ch]
                    changed[ch] = (t if p.current_ma != old[0] else changed[ch][0],
                                   t if p.pulse_width_us != old[1] else changed[ch][1])
                    last[ch] = (p.current_ma, p.pulse_width_us)
    return found


def check_channel(protocol: str, lim: FesLimits, config: ChannelListConfig, ch: int, p: PulseSetting, t: float,
                  started_at: float, old: tuple[int, int], changed: tuple[float, float], latched: bool) -> list[str]:
    eps = 1e-6
    cap_c, cap_w, cap_rms = lim.caps_for(ch)
    frac = 1.0 if lim.start_ramp_s <= 0 else min(1.0, (t - started_at) / lim.start_ramp_s)
    out = []
    where = f"{t:.3f} ch {ch} {p.current_ma} mA {p.pulse_width_us} µs"
    if p.current_ma > cap_c * frac + eps or p.pulse_width_us > cap_w * frac + eps:
        out.append(f"{where}: above the cap {cap_c:g} mA / {cap_w:g} µs × start ramp {frac:.2f}")
    rise_c = lim.max_current_rise_ma_s * min(t - changed[0], lim.max_step_interval_s)
    rise_w = lim.max_pulse_width_rise_us_s * min(t - changed[1], lim.max_step_interval_s)
    if p.current_ma - old[0] > rise_c + eps or p.pulse_width_us - old[1] > rise_w + eps:
        out.append(f"{where}: rises faster than allowed from {old}")
    rms = rms_current_ma(p.current_ma, p.pulse_width_us, config.channel_frequency_hz(ch), p.mode)
    if rms > cap_rms + eps:
        out.append(f"{where}: {rms:.2f} mA r.m.s. > {cap_rms:g}")
    if latched and p.current_ma > 0:
        out.append(f"{where}: current while the emergency stop is latched")
    if protocol == "sm2" and p.current_ma > 0 and p.pulse_width_us < 20:
        out.append(f"{where}: RehaStim 2 would deliver 20 µs")
    return out


# ── strategies ───────────────────────────────────────────────────────────────────────────────────────


@st.composite
def trapezoids(draw: st.DrawFn, maximum: float, span: float) -> Trapezoid:
    points = sorted(draw(st.lists(st.floats(0, span), min_size=4, max_size=4)))
    level = st.one_of(st.floats(0, maximum), st.sampled_from([maximum / 4, maximum / 2, maximum]))
    return Trapezoid(draw(level), (points[0], points[1]), (points[2], points[3]),
                     draw(st.one_of(st.just(0.0), st.floats(0, maximum))))


@st.composite
def profiles(draw: st.DrawFn) -> FesProfile:
    axis = draw(st.sampled_from(["time", "phase"]))
    span = 1.0 if axis == "phase" else 3.0
    chans = draw(st.lists(st.integers(1, 8), min_size=1, max_size=4, unique=True))
    channels = {ch: ChannelProfile(draw(trapezoids(126, span)), draw(trapezoids(500, span)), "",
                                   draw(st.sampled_from(list(PulseMode)))) for ch in chans}
    return FesProfile("drawn", axis, channels, draw(st.sampled_from([20.0, 25.0, 30.0, 40.0, 50.0])))  # type: ignore[arg-type]


caps = st.builds(ChannelCaps, st.floats(0, 126), st.floats(0, 500), st.one_of(st.none(), st.floats(0, 50)))
limit_sets = st.builds(
    FesLimits,
    max_current_ma=st.one_of(st.floats(0, 126), st.sampled_from([40.0, 126.0])),
    max_pulse_width_us=st.one_of(st.floats(0, 500), st.sampled_from([300.0, 500.0])),
    channel_caps=st.dictionaries(st.integers(1, 8), caps, max_size=2),
    max_current_rise_ma_s=st.floats(1, 400), max_pulse_width_rise_us_s=st.floats(10, 5000),
    start_ramp_s=st.floats(0, 1.5), max_rms_current_ma=st.one_of(st.floats(0.5, 50), st.sampled_from([10.0, 50.0])),
)
scale = st.floats(-0.5, 3.0)
actions = st.lists(st.one_of(
    st.tuples(st.just("wait"), st.floats(0.0, 0.4)),
    st.tuples(st.just("start")),
    st.tuples(st.just("stop")),
    st.tuples(st.just("current_scale"), scale),
    st.tuples(st.just("width_scale"), scale),
    st.tuples(st.just("override"), st.one_of(st.none(), st.floats(0, 600))),
    st.tuples(st.just("phase"), st.one_of(st.none(), st.floats(0, 1))),
    st.tuples(st.just("estop")),
    st.tuples(st.just("reset")),
    st.tuples(st.just("clinical_caps"), st.dictionaries(st.integers(1, 8), caps, max_size=2)),
    st.tuples(st.just("load"), profiles()),
), max_size=20)


def run(s: Session, profile: FesProfile, script: list[tuple]) -> None:
    d = s.driver
    calls = {
        "start": lambda: d.start_stimulation("script"),
        "stop": lambda: d.stop_stimulation("script", "script"),
        "estop": lambda: s.supervisor.emergency_stop("script", "test"),
        "reset": lambda: s.supervisor.reset_emergency_stop("operator"),
    }
    try:
        d.load_profile(profile)
    except (SafetyError, FesError):
        pass
    for action, *args in script:
        try:
            if action == "wait":
                s.advance(args[0])
            elif action in calls:
                before = len(s.link.wire)  # an e-stop counts from its call on, a reset once it is done
                calls[action]()
                if action in ("estop", "reset"):
                    s.estop_log.append((before if action == "estop" else len(s.link.wire),
                                        s.supervisor.estop_latched))
            elif action == "current_scale":
                d.set_current_scale(args[0], "script")
            elif action == "width_scale":
                d.set_pulse_width_scale(args[0], "script")
            elif action == "override":
                d.set_pulse_width_override(args[0], "script")
            elif action == "phase":
                d.set_phase(args[0])
            elif action == "clinical_caps":
                before = len(s.link.wire)
                d.set_clinical_caps(args[0])
                s.limits_log.append((before, s.supervisor.fes_limiter.limits))
            elif action == "load":
                d.load_profile(args[0])
        except (SafetyError, FesError):
            pass
        s.advance(TICK_S)
    s.advance(0.3)


def fitted(profile: FesProfile, limits: FesLimits) -> FesProfile:
    """``profile`` scaled per channel to within the caps and the r.m.s. limit (so sessions do stimulate)."""
    channels = {}
    for ch, cp in profile.channels.items():
        cap_c, cap_w, cap_rms = limits.caps_for(ch)
        peak_c = max(cp.current_ma.level, cp.current_ma.baseline)
        peak_w = max(cp.pulse_width_us.level, cp.pulse_width_us.baseline)
        kw = min(1.0, cap_w / peak_w) if peak_w > 0 else 1.0
        duty = 2e-6 * peak_w * kw * profile.frequency_hz * PulseMode(cp.mode).pulses
        rms = peak_c * math.sqrt(duty)
        kc = min(1.0, cap_c / peak_c if peak_c > 0 else 1.0, cap_rms / rms if rms > 0 else 1.0)
        kc, kw = kc * 0.999, kw * 0.999
        channels[ch] = replace(cp, current_ma=replace(cp.current_ma, level=cp.current_ma.level * kc,
                                                      baseline=cp.current_ma.baseline * kc),
                               pulse_width_us=replace(cp.pulse_width_us, level=cp.pulse_width_us.level * kw,
                                                      baseline=cp.pulse_width_us.baseline * kw))
    return replace(profile, channels=channels)


@FAST
@given(protocol=st.sampled_from(["sm1", "sm2"]), limits=limit_sets, profile=profiles(),
       fit=st.sampled_from([True, True, True, False]), script=actions, phase=st.floats(0, 1))
def test_nothing_outside_the_limits_reaches_the_wire(protocol: str, limits: FesLimits, profile: FesProfile,
                                                    fit: bool, script: list[tuple], phase: float) -> None:
    if fit:  # most sessions run a profile that is within the limits, so they do stimulate
        profile = fitted(profile, limits)
    s = session(protocol, limits)
    # the drawn calls, then (as a session would) a restart that runs for a while at some movement phase
    run(s, profile, [("start",), ("phase", phase), *script, ("reset",), ("start",), ("phase", phase), ("wait", 1.0)])
    assert violations(s) == []
    delivered = any(e.current_ma > 0 for e in s.link.core.log)
    event(f"{protocol}: current delivered" if delivered else f"{protocol}: nothing delivered")


# ── the property is not vacuous: in-limit sessions do stimulate, and the checker does catch ──────────


def demanding_profile() -> FesProfile:
    """Jumps straight to 30 mA / 300 µs at t = 0 (far faster than any rise limit)."""
    return FesProfile("steep", "time", {
        1: ChannelProfile(Trapezoid(30.0, (0.0, 0.0), (5.0, 5.0)), Trapezoid(300.0, (0.0, 0.0), (5.0, 5.0))),
        4: ChannelProfile(Trapezoid(20.0, (0.0, 0.1), (5.0, 5.0)), Trapezoid(250.0, (0.0, 0.1), (5.0, 5.0)),
                          mode=PulseMode.DOUBLET),
    }, 40.0)


def test_a_steep_profile_is_followed_within_the_limits(qtbot) -> None:
    for protocol in ("sm1", "sm2"):
        limits = FesLimits.from_config(AppConfig().safety.fes)
        s = session(protocol, limits)
        run(s, demanding_profile(), [("start",), ("wait", 0.3)])
        notes = {st_.channel: st_.note for st_ in s.driver.channel_status()}
        assert notes[1] in ("start ramp", "rate-limited")  # held back, and the panel says so
        run(s, demanding_profile(), [("wait", 2.0)])
        assert s.link.core.channel_state()[1] == PulseSetting(30, 300)
        assert violations(s) == []


def test_the_checker_catches_a_violation() -> None:
    limits = FesLimits.from_config(AppConfig().safety.fes)
    s = session("sm1", limits)
    run(s, demanding_profile(), [("start",), ("wait", 2.0)])
    assert violations(s) == []
    s.limits_log.append((len(s.link.wire), replace(limits, max_current_ma=25.0)))  # the checker's view only
    run(s, demanding_profile(), [("wait", 0.1)])
    found = violations(s)
    assert found and "above the cap 25 mA" in found[0]
    assert math.isfinite(s.clock[0])
