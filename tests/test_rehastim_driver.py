"""RehaStim driver + simulator over a real pty: serial settings, profile following, live scale knobs, acks,
SM2 keep-alive, limits at load/start, the channel stream."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import pytest
import serial

from app.core.config import AppConfig, FesSafety
from app.core.fes_profile import ChannelProfile, FesProfile, Trapezoid
from app.devices.rehastim import (
    SERIAL_SETTINGS,
    FesDriver,
    FesError,
    create,
    simulated_link_settings,
)
from app.devices.sim.adapters import RehaStimSimAdapter
from app.devices.sim.base import SerialSimulator
from app.devices.sim.rehastim_core import StimulationLogEntry
from app.devices.transport import SerialTransport
from app.safety.fes_limits import FesLimiter, FesLimits
from app.safety.supervisor import SafetyError, SafetySupervisor
from app.wire.sciencemode import PulseMode, PulseSetting, Sm2Result

# Default config limits: 40 mA / 300 µs caps, 40 mA/s and 500 µs/s rise, 1 s start ramp, 10 mA r.m.s.
DEFAULT_LIMITS = FesLimits.from_config(FesSafety())


def time_profile(level_ma: float = 20.0, width_us: float = 200.0, frequency_hz: float = 40.0) -> FesProfile:
    """Two channels; slopes (20 mA/s, 400 µs/s) inside the default rise limits, so nothing holds them back."""
    return FesProfile(
        "test time profile", "time",
        {
            1: ChannelProfile(Trapezoid(level_ma, (0.5, 1.5), (3.5, 4.5)),
                              Trapezoid(width_us, (0.5, 1.0), (4.0, 4.5)), "anterior deltoid"),
            5: ChannelProfile(Trapezoid(level_ma / 2, (1.0, 1.5), (3.0, 4.0)),
                              Trapezoid(width_us, (1.0, 1.5), (3.0, 4.0)), "biceps", PulseMode.DOUBLET),
        },
        frequency_hz,
    )


def phase_profile() -> FesProfile:
    channel = ChannelProfile(Trapezoid(10.0, (0.0, 0.2), (0.6, 0.8)), Trapezoid(100.0, (0.0, 0.1), (0.7, 0.8)))
    return FesProfile("test phase profile", "phase", {2: channel})


class Rig(SimpleNamespace):
    sim: SerialSimulator
    driver: FesDriver
    supervisor: SafetySupervisor

    def core(self, fn):  # type: ignore[no-untyped-def]
        return self.sim.with_core(fn)


@pytest.fixture(params=["sm1", "sm2"])
def rig(request, tmp_path, qtbot) -> Iterator[Rig]:
    with make_rig(request.param, tmp_path, qtbot) as r:
        yield r


@contextmanager
def make_rig(protocol: str, tmp_path, qtbot, limits: FesLimits = DEFAULT_LIMITS,
             ack_timeout_s: float = 0.3) -> Iterator[Rig]:
    supervisor = SafetySupervisor(AppConfig().safety)
    supervisor.fes_limiter = FesLimiter(limits)
    sim = SerialSimulator("fes", lambda: RehaStimSimAdapter(protocol), tmp_path / "fes.tty", tick_s=0.002)
    sim.keep_host_log = True
    sim.start()
    driver = FesDriver(SerialTransport(sim.url, simulated_link_settings(protocol)),  # type: ignore[arg-type]
                       supervisor, protocol=protocol, ack_timeout_s=ack_timeout_s)  # type: ignore[arg-type]
    faults: list[str] = []
    driver.fault.connect(faults.append)
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.device_ready, timeout=3000)
        yield Rig(sim=sim, driver=driver, supervisor=supervisor, faults=faults, protocol=protocol)
    finally:
        driver.stop(1.0)
        sim.stop()


def delivered_at(log: list[StimulationLogEntry], channel: int, t: float) -> PulseSetting:
    state = PulseSetting(0, 0)
    for e in log:
        if e.t > t:
            break
        if e.channel == channel and e.kind == "ccl":
            state = PulseSetting(e.current_ma, e.pulse_width_us, e.mode)
    return state


def wait_s(qtbot, seconds: float) -> None:
    t0 = time.monotonic()
    qtbot.waitUntil(lambda: time.monotonic() - t0 >= seconds, timeout=int(seconds * 1000) + 2000)


# ── link settings ──────────────────────────────────────────────────────────────────────────────────


def test_serial_settings_per_protocol() -> None:
    sm1, sm2 = SERIAL_SETTINGS["sm1"], SERIAL_SETTINGS["sm2"]
    assert (sm1.baudrate, sm1.bytesize, sm1.parity, sm1.stopbits, sm1.rtscts) == (
        115200, 8, serial.PARITY_NONE, serial.STOPBITS_TWO, True)
    assert (sm2.baudrate, sm2.bytesize, sm2.parity, sm2.stopbits, sm2.rtscts) == (
        460800, 8, serial.PARITY_EVEN, serial.STOPBITS_ONE, False)


@pytest.mark.parametrize("protocol", ["sm1", "sm2"])
def test_create_uses_the_protocols_settings_on_a_real_port(protocol: str) -> None:
    config = AppConfig()
    fes = replace(config.devices.fes, mode="serial", port="/dev/ttyUSB-not-there", protocol=protocol)
    config = replace(config, devices=replace(config.devices, fes=fes))
    supervisor = SafetySupervisor(config.safety)
    from pathlib import Path

    from app.core.bus import StreamBus
    from app.devices.registry import DeviceContext, SimulatorHosting

    ctx = DeviceContext("fes", config.devices.fes, config.safety, StreamBus(), supervisor, Path("/nonexistent"),
                        SimulatorHosting(config, Path("/nonexistent")), {})
    handle = create(ctx)
    assert handle is not None and handle.simulator is None
    assert handle.driver.transport.settings == SERIAL_SETTINGS[protocol]  # type: ignore[attr-defined]
    assert isinstance(supervisor.fes_limiter, FesLimiter)
    assert supervisor.fes_limiter.limits == DEFAULT_LIMITS
    assert [name for name, _ in supervisor._estop_actions] == ["FES stop"]
    for guardian in handle.extras["processes"]:  # the FES guardian, started with the driver (issue #25)
        guardian.close()


# ── acceptance 2: a profile runs for 5 s and the device delivers it ─────────────────────────────────


@pytest.mark.slow
def test_profile_runs_five_seconds_and_is_delivered_within_one_period(rig: Rig, qtbot) -> None:
    driver = rig.driver
    profile = time_profile()
    driver.load_profile(profile)
    driver.start_stimulation("test")
    assert driver.stimulating
    wait_s(qtbot, 5.0)
    t0 = driver.started_at
    log = list(rig.core(lambda c: list(c.log)))
    period = driver.channel_list.t1_ms / 1000.0
    slack = 0.025  # pty + thread scheduling between the driver's tick and the simulator's read (2 loaded cores)
    checked = 0
    for ch in (1, 5):
        for i in range(5, 480):
            t = t0 + i * 0.01
            got = delivered_at(log, ch, t)
            xs = [t - t0 - k * (period + slack) / 10 for k in range(11)]
            want_c = [profile.value_at(x)[ch][0] for x in xs]
            want_w = [profile.value_at(x)[ch][1] for x in xs]
            assert min(want_c) - 1 <= got.current_ma <= max(want_c) + 1, (ch, t - t0, got, want_c)
            if got.current_ma:
                assert min(want_w) - 1 <= got.pulse_width_us <= max(want_w) + 1, (ch, t - t0, got, want_w)
                assert got.mode == profile.channels[ch].mode
            checked += 1
    assert checked == 950
    assert max(e.current_ma for e in log if e.channel == 1) == 20  # the plateau was reached
    assert not rig.faults
    # time profile over: the driver stopped by itself and the device is off
    qtbot.waitUntil(lambda: not driver.stimulating, timeout=1500)
    qtbot.waitUntil(lambda: not rig.core(lambda c: c.running or bool(c.channel_state())), timeout=500)


def test_scale_knobs_change_delivery_live(rig: Rig, qtbot) -> None:
    driver = rig.driver
    driver.load_profile(time_profile())
    driver.start_stimulation("test")
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state().get(1, PulseSetting(0, 0)).current_ma) == 20,
                    timeout=3000)
    t = time.monotonic()
    assert driver.set_current_scale(0.5, "test") == 0.5
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()[1].current_ma) == 10, timeout=500)
    assert time.monotonic() - t < 0.1  # a decrease is never held back: next update
    assert driver.set_pulse_width_scale(0.5, "test") == 0.5
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()[1].pulse_width_us) == 100, timeout=500)
    assert driver.current_scale == 0.5 and driver.pulse_width_scale == 0.5
    # back up: the rise is limited to 40 mA/s, so 10 → 20 mA takes about a quarter second, not one step
    driver.set_current_scale(1.0, "test")
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()[1].current_ma) > 10, timeout=500)
    assert rig.core(lambda c: c.channel_state()[1].current_ma) <= 14
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()[1].current_ma) == 20, timeout=1000)
    assert not rig.faults


def test_scale_knob_stops_at_the_cap_and_says_so(rig: Rig, qtbot) -> None:
    driver = rig.driver
    driver.load_profile(time_profile())  # 20 mA peak, cap 40 mA, 200 µs peak, cap 300 µs
    said: list[tuple[str, float, str]] = []
    driver.scale_clamped.connect(lambda knob, applied, why: said.append((knob, applied, why)))
    assert driver.set_current_scale(3.0, "test") == pytest.approx(2.0)
    assert said[-1][0] == "current" and "stops at 2.00" in said[-1][2]
    assert driver.set_pulse_width_scale(3.0, "test") == pytest.approx(1.5)
    assert said[-1][0] == "pulse_width" and "pulse-width cap 300 µs" in said[-1][2]
    with pytest.raises(SafetyError, match="not a valid factor"):
        driver.set_current_scale(-1.0, "test")
    assert driver.current_scale == pytest.approx(2.0)


def test_phase_profile_follows_the_phase(rig: Rig, qtbot) -> None:
    driver = rig.driver
    driver.load_profile(phase_profile())
    driver.start_stimulation("test")
    wait_s(qtbot, 1.1)  # past the start ramp
    assert rig.core(lambda c: c.channel_state()) == {}  # no movement: the profile's start (0 mA)
    driver.set_phase(0.4)
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()) == {2: PulseSetting(10, 100)}, timeout=1500)
    driver.set_phase(0.9)
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()) == {}, timeout=300)
    driver.set_pulse_width_override(150.0)
    driver.set_phase(0.4)
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()) == {2: PulseSetting(10, 150)}, timeout=1500)
    qtbot.waitUntil(lambda: driver.latest("fes.channels").pulseWidth2 == 150.0, timeout=200)
    sample = driver.latest("fes.channels")
    assert (sample.current2, sample.pulseWidth2, sample.current1) == (10.0, 150.0, 0.0)  # what was sent
    with pytest.raises(SafetyError, match="above the cap of 300 µs"):
        driver.set_pulse_width_override(400.0)
    assert driver.pulse_width_override == 150.0
    driver.set_pulse_width_override(None)
    qtbot.waitUntil(lambda: rig.core(lambda c: c.channel_state()) == {2: PulseSetting(10, 100)}, timeout=500)


# ── refusals ─────────────────────────────────────────────────────────────────────────────────────────


def test_profile_above_the_caps_is_refused_and_nothing_changes(rig: Rig) -> None:
    driver = rig.driver
    driver.load_profile(time_profile())
    with pytest.raises(SafetyError, match=r"channel 1: the profile reaches 60 mA, above the cap of 40 mA"):
        driver.load_profile(time_profile(level_ma=60.0))
    rig.supervisor.fes_limiter.set_limits(replace(DEFAULT_LIMITS, max_rms_current_ma=5.0))
    with pytest.raises(SafetyError, match=r"channel 1: 40 mA at 300 µs and 40 Hz is 6\.2 mA r\.m\.s\., above"):
        driver.load_profile(time_profile(level_ma=40.0, width_us=300.0))
    assert driver.profile == time_profile()
    rig.supervisor.fes_limiter.set_limits(replace(DEFAULT_LIMITS, max_current_ma=15.0))  # e.g. a patient's cap
    with pytest.raises(SafetyError, match="above the cap of 15 mA"):
        driver.start_stimulation("test")
    assert not driver.stimulating
    assert rig.core(lambda c: c.running) is False


def test_start_needs_a_profile_and_no_latched_estop(rig: Rig) -> None:
    with pytest.raises(FesError, match="no stimulation profile"):
        rig.driver.start_stimulation("test")
    rig.driver.load_profile(time_profile())
    rig.supervisor.emergency_stop("test", "pressed")
    with pytest.raises(SafetyError, match="emergency stop is latched"):
        rig.driver.start_stimulation("test")
    rig.supervisor.reset_emergency_stop("operator")
    rig.driver.start_stimulation("test")
    assert rig.driver.stimulating


# ── acks ─────────────────────────────────────────────────────────────────────────────────────────────


def test_error_ack_is_a_fault_shown_to_the_user(rig: Rig, qtbot) -> None:
    driver = rig.driver
    driver.load_profile(time_profile())
    driver.start_stimulation("test")
    rig.core(lambda c: c.inject_error_ack(1, Sm2Result.BUSY))
    qtbot.waitUntil(lambda: bool(rig.faults), timeout=1000)
    assert "refused the update" in rig.faults[0]
    assert not driver.stimulating
    assert any(a.source == "FES" and "refused the update" in a.text for a in rig.supervisor.alarms())


def test_refused_init_is_reported_by_start(rig: Rig) -> None:
    rig.driver.load_profile(time_profile())
    rig.core(lambda c: c.inject_error_ack(1, Sm2Result.PARAMETER_ERROR))
    with pytest.raises(FesError, match="refused the channel list init"):
        rig.driver.start_stimulation("test")
    assert not rig.driver.stimulating


def test_missing_ack_is_a_fault(rig: Rig, qtbot) -> None:
    driver = rig.driver
    driver.load_profile(time_profile())
    driver.start_stimulation("test")
    rig.core(lambda c: c.inject_no_ack(1))
    t0 = time.monotonic()
    qtbot.waitUntil(lambda: bool(rig.faults), timeout=2000)
    assert "did not acknowledge the update within 0.3 s" in rig.faults[0]
    assert 0.3 <= time.monotonic() - t0 < 0.3 + 0.2
    assert not driver.stimulating


def test_sm1_device_that_went_dark_is_a_fault(tmp_path, qtbot) -> None:
    """SM1 reports its own emergency stop by silence: the next update's ack is missing."""
    with make_rig("sm1", tmp_path, qtbot) as r:
        r.driver.load_profile(time_profile())
        r.driver.start_stimulation("test")
        r.core(lambda c: c.press_emergency_stop(time.monotonic()))
        qtbot.waitUntil(lambda: bool(r.faults), timeout=2000)
        assert "did not acknowledge" in r.faults[0]


def test_sm2_stimulation_error_is_a_fault(tmp_path, qtbot) -> None:
    with make_rig("sm2", tmp_path, qtbot) as r:
        r.driver.load_profile(time_profile())
        r.driver.start_stimulation("test")
        reply = r.core(lambda c: c.inject_electrode_error(time.monotonic(), 1))
        r.sim.link.write(reply)  # the device sends StimulationError −2
        qtbot.waitUntil(lambda: bool(r.faults), timeout=1000)
        assert "electrode error" in r.faults[0]
        assert not r.driver.stimulating


def test_sm2_keep_alive_holds_the_device_watchdog(tmp_path, qtbot) -> None:
    with make_rig("sm2", tmp_path, qtbot) as r:
        wait_s(qtbot, 2.5)  # idle: only Watchdog packets keep the session
        assert r.core(lambda c: (c.watchdog_expiries, c.initialised)) == (0, True)
        r.driver.load_profile(time_profile())
        r.driver.start_stimulation("test")  # no re-handshake was needed
        assert r.driver.stimulating


def test_channel_stream_is_what_was_sent(rig: Rig, qtbot) -> None:
    driver = rig.driver
    qtbot.waitUntil(lambda: driver.latest("fes.channels") is not None, timeout=1000)
    assert driver.latest("fes.channels").current1 == 0.0
    driver.load_profile(time_profile())
    driver.start_stimulation("test")
    qtbot.waitUntil(lambda: driver.latest("fes.channels").current1 >= 10, timeout=3000)
    driver.stop_stimulation("test")
    sent = driver.latest("fes.channels")
    qtbot.waitUntil(lambda: driver.latest("fes.channels") is not sent, timeout=1000)
    assert driver.latest("fes.channels").current1 == 0.0
    data = driver.config_data()
    assert data["protocol"] == rig.protocol and data["channels"] == [1, 5] and data["frequencyHz"] == 40.0
    assert data["caps"][1]["maxCurrent"] == 40.0


def handled_after(driver: FesDriver, event: threading.Event, monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """Set once an update of the driver's thread that began after ``event`` has returned (whatever it did)."""
    update, returned = driver._update, threading.Event()

    def update_and_tell(now: float) -> None:
        update(now)
        if event.is_set():
            returned.set()

    monkeypatch.setattr(driver, "_update", update_and_tell)
    return returned


def test_an_update_refused_because_of_a_stop_meanwhile_is_not_a_fault_and_the_next_start_works(
        rig: Rig, qtbot, monkeypatch: pytest.MonkeyPatch) -> None:
    """An e-stop from another thread while the driver's thread checks an update: the check refuses it (the stop is
    latched) — the stop's own consequence, not a fault. Before, the driver then 'stopped' again with a fault
    alarm, and that late stop could land after the operator's reset and kill the next start ("stimulation was
    stopped while it was starting": the electrode set-up's repeated bursts, a quiet suite run)."""
    driver, sup = rig.driver, rig.supervisor
    driver.load_profile(time_profile())
    driver.start_stimulation("test")
    check = sup.check_fes_update
    refused = threading.Event()
    stoppers: list[threading.Thread] = []

    def check_while_stopped(*args: Any, **kwargs: Any) -> Any:
        if refused.is_set():
            return check(*args, **kwargs)
        # the e-stop's Stop, from another thread, in the middle of this check (it waits a moment for the lock
        # this thread holds, then goes anyway)
        generation = driver._stop_generation
        stopper = threading.Thread(target=driver.stop_stimulation, args=("emergency stop", "test"))
        stoppers.append(stopper)
        stopper.start()
        deadline = time.monotonic() + 2.0
        while driver._stop_generation == generation and time.monotonic() < deadline:
            time.sleep(0.001)  # the driver's thread, inside the fake: no Qt loop to wait on here
        refused.set()
        raise SafetyError("stimulation refused: the emergency stop is latched; reset it first")

    monkeypatch.setattr(sup, "check_fes_update", check_while_stopped)
    returned = handled_after(driver, refused, monkeypatch)
    qtbot.waitUntil(returned.is_set, timeout=3000)  # the refused update has been handled, whatever it did
    for stopper in stoppers:
        stopper.join(2.0)
    assert not driver.stimulating
    assert rig.faults == [] and not any(a.source == "FES" for a in sup.alarms()), rig.faults
    generation = driver._stop_generation
    monkeypatch.setattr(sup, "check_fes_update", check)
    driver.start_stimulation("test")  # the operator starts again: no late stop takes it back
    assert driver.stimulating and driver._stop_generation == generation


def test_an_update_refused_because_the_estop_latched_meanwhile_stops_without_a_fault_alarm(
        rig: Rig, qtbot, monkeypatch: pytest.MonkeyPatch) -> None:
    """The other order: the e-stop latched while the driver's thread checked an update, its FES stop not sent yet.
    The driver stops (it need not wait for the e-stop's own stop) but raises no fault alarm: the alarm's safe-state
    stop was a second, late stop that could land after the operator's reset and take back the next start (the
    final quiet run of session 10 failed on it after the first fix)."""
    driver, sup = rig.driver, rig.supervisor  # this rig's supervisor has no stop action: the latch alone
    driver.load_profile(time_profile())
    driver.start_stimulation("test")
    check = sup.check_fes_update
    latched = threading.Event()

    def check_after_the_latch(*args: Any, **kwargs: Any) -> Any:
        if latched.is_set():
            return check(*args, **kwargs)
        sup.emergency_stop("test", "pressed while an update was checked")
        latched.set()
        return check(*args, **kwargs)  # refuses: the e-stop is latched

    monkeypatch.setattr(sup, "check_fes_update", check_after_the_latch)
    returned = handled_after(driver, latched, monkeypatch)
    qtbot.waitUntil(returned.is_set, timeout=3000)
    qtbot.waitUntil(lambda: not driver.stimulating, timeout=1000)  # stopped all the same
    assert rig.faults == [] and not any(a.source == "FES" for a in sup.alarms()), rig.faults
    monkeypatch.setattr(sup, "check_fes_update", check)
    sup.reset_emergency_stop("operator")
    generation = driver._stop_generation
    driver.start_stimulation("test")
    assert driver.stimulating and driver._stop_generation == generation


# ── scheduling ─────────────────────────────────────────────────────────────────────────────────────
def _os_grants_round_robin() -> bool:
    """Whether this process may make a thread round-robin real-time (root, CAP_SYS_NICE, an RLIMIT_RTPRIO)."""
    granted: list[bool] = []

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
            granted.append(True)
        except (OSError, AttributeError):
            granted.append(False)
    thread = threading.Thread(target=attempt)
    thread.start()
    thread.join()
    return granted[0]


def test_the_drivers_loop_runs_real_time_just_below_the_linarms(tmp_path, qtbot) -> None:
    """Its passes are the FES guardian's heartbeats (0.3 s): at normal priority on busy cores the thread waited
    155-511 ms for a CPU and the guardian stopped the therapy (#38, session 12)."""
    from app.devices.linarm import LinarmDriver

    assert FesDriver.realtime_priority is not None
    assert FesDriver.realtime_priority < LinarmDriver.realtime_priority < LinarmDriver.heartbeat_priority
    with make_rig("sm2", tmp_path, qtbot) as r:
        granted = _os_grants_round_robin()
        assert r.driver.realtime == granted, "the driver's loop did not ask for the real-time priority it may have"
        tid = r.driver.native_thread_id
        assert tid is not None
        if granted:
            assert os.sched_getscheduler(tid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_RR
            assert os.sched_getparam(tid).sched_priority == FesDriver.realtime_priority
