"""The FES dead man's switch (issue #25): when the app stops serving the stimulator — stopped (SIGSTOP),
killed — stimulation ends within BOUND_S, on ScienceMode 1 (which has no watchdog: the guardian process,
app.devices.fes_guardian) and ScienceMode 2 (the guardian first, the device's own 1.2 s watchdog behind it).

* the simulator models the danger: a RehaStim 1 keeps stimulating with no host; a RehaStim 2 stops 1.2 s after
  its last valid packet, as the reference says (/work/shared/reference/sciencemode.md §3.1, §3.3);
* the guardian on its own (a socket pair stands in for the link);
* the real app (main.py --headless) stopped for 2 s / killed while stimulating, seen on the simulator's wire.
"""

from __future__ import annotations

import os
import signal
import socket
import time
from pathlib import Path

import pytest

from app.devices import fes_guardian
from app.devices.fes_guardian import FesGuardian
from app.devices.sim.rehastim_core import RehaStimSimCore
from app.wire.sciencemode import (
    SM2_WATCHDOG_TIMEOUT_S,
    ChannelListConfig,
    PulseSetting,
    Sm2Decoder,
    Sm2Init,
    Sm2InitAck,
    Sm2Result,
    encode_sm1_init,
    encode_sm1_stop,
    encode_sm1_update,
    encode_sm2,
    encode_sm2_init_channel_list,
    encode_sm2_start,
)
from tests.app_process import AppProcess, last_fes_update_before

pytestmark = [pytest.mark.sim_homed, pytest.mark.slow]  # homed from the start: the homing is tested on its own

BOUND_S = 0.5  # docs/fes.md "Dead man's switch": trips after 0.3 s without a heartbeat
CCL = ChannelListConfig(channels=(1,), t1_ms=33.0, t2_ms=3.0)
ON = {1: PulseSetting(10, 150)}


# ============================================================================ the simulator models the danger
def test_sm1_keeps_stimulating_with_no_host() -> None:
    core = RehaStimSimCore("sm1")
    core.handle_bytes(encode_sm1_init(CCL), 0.0)
    core.handle_bytes(encode_sm1_update(CCL, ON), 0.01)
    for t in (1.0, 10.0, 600.0):
        assert core.tick(t) == b""
        assert core.channel_state() == ON  # no watchdog: nothing stops it but Stop (or its own e-stop)
    core.handle_bytes(encode_sm1_stop(), 600.5)
    assert core.channel_state() == {}


def _sm2_stimulating() -> RehaStimSimCore:
    core = RehaStimSimCore("sm2")
    init = Sm2Decoder().feed(core.tick(0.0))
    assert isinstance(init[0], Sm2Init)
    core.handle_bytes(encode_sm2(Sm2InitAck(init[0].packet_number, Sm2Result.OK)), 0.01)
    core.handle_bytes(encode_sm2_init_channel_list(1, CCL), 0.02)
    core.handle_bytes(encode_sm2_start(2, CCL, ON), 0.03)
    assert core.channel_state() == ON
    return core


def test_sm2_watchdog_as_the_reference_says() -> None:
    """1200 ms without a valid packet: stimulation stops, modes reset, Init is sent again (every 500 ms)."""
    core = _sm2_stimulating()
    last_valid = 0.03
    core.handle_bytes(b"\xf0\x81\x00\x81\x00\x00\x0f", last_valid + 0.5)  # a bad packet does not feed it
    assert core.tick(last_valid + SM2_WATCHDOG_TIMEOUT_S - 0.01) == b""
    assert core.channel_state() == ON
    out = Sm2Decoder().feed(core.tick(last_valid + SM2_WATCHDOG_TIMEOUT_S + 0.01))
    assert core.channel_state() == {} and not core.running and core.watchdog_expiries == 1
    assert [type(m) for m in out] == [Sm2Init]
    assert core.tick(last_valid + SM2_WATCHDOG_TIMEOUT_S + 0.3) == b""
    assert [type(m) for m in Sm2Decoder().feed(core.tick(last_valid + SM2_WATCHDOG_TIMEOUT_S + 0.52))] == [Sm2Init]


def test_sm2_any_valid_packet_feeds_the_watchdog() -> None:
    core = _sm2_stimulating()
    t = 0.03
    for _ in range(5):  # updates every second: never 1.2 s of silence
        t += 1.0
        core.handle_bytes(encode_sm2_start(3, CCL, ON), t)
        assert core.tick(t + 0.1) == b""
    assert core.channel_state() == ON and core.watchdog_expiries == 0


# ============================================================================ the guardian on its own
@pytest.fixture
def link():  # type: ignore[no-untyped-def]
    """A socket pair standing in for the stimulator's link: the app's end, the device's end."""
    app_end, device_end = socket.socketpair()
    device_end.settimeout(3.0)
    yield app_end, device_end
    app_end.close()
    device_end.close()


@pytest.fixture
def guardian():  # type: ignore[no-untyped-def]
    g = FesGuardian().start()
    yield g
    g.close()
    assert g.proc is not None and g.proc.poll() is not None


def _read_for(sock: socket.socket, seconds: float) -> bytes:
    sock.settimeout(0.05)
    end, data = time.monotonic() + seconds, b""
    while time.monotonic() < end:
        try:
            chunk = sock.recv(4096)
        except TimeoutError:
            continue
        if not chunk:
            break
        data += chunk
    return data


@pytest.mark.realtime
def test_guardian_sends_stop_when_the_heartbeat_stops(guardian: FesGuardian, link) -> None:  # type: ignore[no-untyped-def]
    app_end, device_end = link
    guardian.arm(app_end.fileno(), encode_sm1_stop())
    t_end = time.monotonic() + 1.0
    while time.monotonic() < t_end:  # a live driver: heartbeats, no Stop
        guardian.heartbeat()
        time.sleep(0.01)
    assert _read_for(device_end, 0.0) == b""
    device_end.settimeout(3.0)
    t0 = time.monotonic()  # the driver falls silent
    last_heartbeat = guardian._last_heartbeat  # sent at most HEARTBEAT_PERIOD_S before
    first = device_end.recv(1)
    t_stop = time.monotonic()
    assert first == encode_sm1_stop()
    assert t_stop - last_heartbeat >= fes_guardian.TRIP_AFTER_S - 0.005, "tripped before the heartbeat was late"
    assert t_stop - t0 <= BOUND_S, f"Stop {(t_stop - t0) * 1000:.0f} ms after the driver fell silent"
    rest = _read_for(device_end, 0.2)
    assert rest == encode_sm1_stop() * (fes_guardian.STOP_REPEATS - 1)
    deadline = time.monotonic() + 2.0
    why = ""
    while not why and time.monotonic() < deadline:
        why = guardian.tripped()
        time.sleep(0.01)
    assert "no heartbeat" in why and not guardian.armed


@pytest.mark.realtime
def test_guardian_sends_stop_at_once_when_the_app_is_gone(link) -> None:  # type: ignore[no-untyped-def]
    app_end, device_end = link
    g = FesGuardian().start()
    try:
        g.arm(app_end.fileno(), b"STOP")
        t0 = time.monotonic()
        assert g._control is not None
        g._control.close()  # what the kernel does to every descriptor of a process that dies
        assert device_end.recv(4) == b"STOP"
        assert time.monotonic() - t0 < 0.2
        g.proc.wait(2.0)  # type: ignore[union-attr]
    finally:
        g._control = None
        g.close()


@pytest.mark.realtime
def test_a_disarmed_guardian_lets_go_of_the_link(guardian: FesGuardian, link) -> None:  # type: ignore[no-untyped-def]
    app_end, device_end = link
    guardian.arm(app_end.fileno(), b"STOP")
    guardian.heartbeat()
    guardian.disarm()
    time.sleep(0.1)  # the guardian closes its duplicate within its poll period (10 ms)
    app_end.close()  # the driver closes the link: the device sees it closed, nothing else held it open
    assert device_end.recv(16) == b""
    assert _read_for(device_end, fes_guardian.TRIP_AFTER_S + 0.2) == b""  # and no Stop came


# ============================================================================ the real app, stopped or killed
@pytest.fixture
def app_for(tmp_path: Path):  # type: ignore[no-untyped-def]
    apps: list[AppProcess] = []

    def make(protocol: str) -> AppProcess:
        app = AppProcess(tmp_path, protocol)
        apps.append(app)
        return app

    yield make
    for app in apps:
        app.close()


@pytest.mark.realtime
@pytest.mark.parametrize("protocol", ["sm1", "sm2"])
def test_sigstop_of_the_app_ends_stimulation_within_the_bound(app_for, protocol: str) -> None:  # type: ignore[no-untyped-def]
    app = app_for(protocol)
    app.start_headless()
    app.wait_stimulating()
    t_on = time.monotonic()
    while time.monotonic() < t_on + 1.0:  # a live app: the guardian stays quiet
        time.sleep(0.05)
    assert app.fes_stop_after(t_on) is None and app.stimulating_on_the_device()
    t0 = time.monotonic()
    os.kill(app.pid, signal.SIGSTOP)
    try:
        deadline = t0 + 2.0
        while app.fes_stop_after(t0) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        stop = app.fes_stop_after(t0)
        still_on = app.stimulating_on_the_device()
        while time.monotonic() < deadline:  # stopped for 2 s
            time.sleep(0.05)
    finally:
        os.kill(app.pid, signal.SIGCONT)
    assert stop is not None, f"{protocol}: the device was still stimulating 2 s into the stop"
    last_update = last_fes_update_before(app.fes_sim, protocol, t0 + 1.0)
    assert last_update is not None and last_update <= t0 + 0.05  # the app really was silent
    delay = stop - t0
    assert delay <= BOUND_S, f"{protocol}: Stop {delay * 1000:.0f} ms after SIGSTOP"
    assert not still_on
    print(f"{protocol}: Stop on the wire {delay * 1000:.0f} ms after SIGSTOP")
    # Resumed, the app learns what happened, stops the script (a STOP alarm: exit 3) and ends cleanly.
    code = app.wait_exit(20.0)
    assert code == 3, f"exit {code}:\n{app.text()[-3000:]}"
    assert "the FES guardian sent Stop" in app.text()
    assert not app.stimulating_on_the_device()


@pytest.mark.realtime
def test_sigkill_of_the_app_ends_stimulation_at_once(app_for) -> None:  # type: ignore[no-untyped-def]
    app = app_for("sm1")
    app.start_headless()
    app.wait_stimulating()
    t0 = time.monotonic()
    os.kill(app.pid, signal.SIGKILL)
    assert app.wait_exit(5.0) == -signal.SIGKILL
    deadline = t0 + 2.0
    while app.fes_stop_after(t0) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    stop = app.fes_stop_after(t0)
    assert stop is not None and stop - t0 <= BOUND_S, "no Stop after the app was killed"
    assert not app.stimulating_on_the_device()
