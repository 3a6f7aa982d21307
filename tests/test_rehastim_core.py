"""RehaStim simulator core: accepts what the encoders send, error-acks bad input, watchdog, faults."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.devices.sim.rehastim_core import RehaStimSimCore, StimulationLogEntry
from app.wire.sciencemode import (
    ChannelListConfig,
    PulseMode,
    PulseSetting,
    Sm1Ack,
    Sm1AckDecoder,
    Sm1Ident,
    Sm2Ack,
    Sm2Command,
    Sm2Decoder,
    Sm2GetStimulationMode,
    Sm2GetStimulationModeAck,
    Sm2Init,
    Sm2InitAck,
    Sm2InitChannelListMode,
    Sm2Result,
    Sm2SinglePulse,
    Sm2StimulationError,
    Sm2StimulationMode,
    Sm2StopChannelListMode,
    Sm2UnknownCommand,
    Sm2Watchdog,
    encode_sm1_init,
    encode_sm1_single_pulse,
    encode_sm1_stop,
    encode_sm1_update,
    encode_sm2,
    encode_sm2_frame,
    encode_sm2_start,
)

FAST = settings(max_examples=200, deadline=None)
P = PulseSetting
H = bytes.fromhex
CFG = ChannelListConfig((1, 2, 5), t1_ms=25.0, t2_ms=3.0)


def acks(data: bytes) -> list:
    return Sm1AckDecoder().feed(data)


# ── SM1 ─────────────────────────────────────────────────────────────────────────────────────────


def test_sm1_session_acks_and_log() -> None:
    sim = RehaStimSimCore("sm1")
    assert acks(sim.handle_bytes(encode_sm1_init(CFG), 0.0)) == [Sm1Ack(Sm1Ident.INIT, True)]
    assert sim.running and sim.channel_state() == {}
    upd = encode_sm1_update(CFG, {1: P(20, 200), 2: P(0, 0), 5: P(15, 300, PulseMode.DOUBLET)})
    assert acks(sim.handle_bytes(upd, 0.5)) == [Sm1Ack(Sm1Ident.UPDATE, True)]
    assert sim.channel_state() == {1: P(20, 200), 5: P(15, 300, PulseMode.DOUBLET)}
    assert acks(sim.handle_bytes(encode_sm1_stop(), 1.0)) == [Sm1Ack(Sm1Ident.STOP, True)]
    assert not sim.running and sim.channel_state() == {}
    assert sim.log == [
        StimulationLogEntry(0.5, 1, 20, 200),
        StimulationLogEntry(0.5, 5, 15, 300, PulseMode.DOUBLET),
        StimulationLogEntry(1.0, 1, 0, 0),
        StimulationLogEntry(1.0, 5, 0, 0),
    ]


def test_sm1_single_pulse_outside_ccl_and_refused_during_ccl() -> None:
    sim = RehaStimSimCore("sm1")
    assert sim.handle_bytes(H("E2 21 48 78"), 0.0) == H("C1")  # the spec's example single pulse
    assert sim.log == [StimulationLogEntry(0.0, 3, 120, 200, kind="single")]
    sim.handle_bytes(encode_sm1_init(CFG), 1.0)
    assert sim.handle_bytes(encode_sm1_single_pulse(1, P(10, 100)), 1.1) == H("C0")


def test_sm1_error_acks_for_bad_input() -> None:
    sim = RehaStimSimCore("sm1")
    # update before init
    assert sim.handle_bytes(encode_sm1_update(CFG, {1: P(1, 1), 2: P(1, 1), 5: P(1, 1)}), 0.0) == H("40")
    # bad checksum on a single pulse
    bad = bytearray(H("E2 21 48 78"))
    bad[3] ^= 1
    assert sim.handle_bytes(bytes(bad), 0.1) == H("C0")
    # spec init #7 then spec update #12: the triplet breaks t1 >= 3*t2 + 1.5 ms -> error ack, no output
    assert sim.handle_bytes(H("99 29 40 61 10 1F"), 0.2) == H("01")
    assert sim.handle_bytes(H("BB 00 64 34 41 48 37 22 2C 48 23 10 5C"), 0.3) == H("40")
    assert sim.channel_state() == {}
    # init of channels 1-4 with t2 = 3 ms (4 channels on module A need 6 ms): refused, previous list kept
    assert sim.handle_bytes(H("80 03 60 00 30 26"), 0.4) == H("00")
    assert sim.config is not None and sim.config.channels == (2, 3, 6, 8)
    # 127 mA (the 7-bit field allows it, the device does not)
    upd = bytearray(encode_sm1_update(ChannelListConfig((1,), 20.0, 3.0), {1: P(126, 100)}))
    sim.handle_bytes(encode_sm1_init(ChannelListConfig((1,), 20.0, 3.0)), 0.5)
    upd[3] = 127
    upd[0] = 0xA0 | ((100 + 127) % 32)
    assert sim.handle_bytes(bytes(upd), 0.6) == H("40")
    assert sim.bad_packets >= 1 and any("127 mA" in why for _, why in sim.events)


def test_sm1_faults() -> None:
    sim = RehaStimSimCore("sm1")
    sim.inject_no_ack(1)
    assert sim.handle_bytes(encode_sm1_init(CFG), 0.0) == b""
    assert not sim.running  # the packet was lost, not executed
    sim.inject_error_ack(1)
    assert sim.handle_bytes(encode_sm1_init(CFG), 0.1) == H("00")
    assert sim.handle_bytes(encode_sm1_init(CFG), 0.2) == H("01")
    sim.handle_bytes(encode_sm1_update(CFG, {1: P(20, 200), 2: P(10, 100), 5: P(0, 0)}), 0.3)
    assert sim.inject_electrode_error(0.4, channel=2) == b""  # SM1 cannot report it
    assert sim.channel_state() == {1: P(20, 200)}
    assert sim.press_emergency_stop(0.5) == b""
    assert sim.channel_state() == {} and not sim.running
    assert sim.handle_bytes(encode_sm1_stop(), 0.6) == b""  # device off: no ack
    sim.power_cycle(1.0)
    assert sim.handle_bytes(encode_sm1_stop(), 1.1) == H("81")


@FAST
@given(st.binary(max_size=200))
def test_sm1_sim_survives_garbage_then_works(garbage: bytes) -> None:
    sim = RehaStimSimCore("sm1")
    sim.handle_bytes(garbage, 0.0)
    assert sim.handle_bytes(encode_sm1_stop(), 0.1)[-1:] == H("81")
    assert sim.handle_bytes(encode_sm1_init(CFG), 0.2)[-1:] == H("01")


@FAST
@given(
    st.lists(
        st.tuples(st.integers(0, 126), st.integers(0, 500), st.sampled_from(list(PulseMode))),
        min_size=3,
        max_size=3,
    )
)
def test_sm1_sim_accepts_every_valid_update(values: list) -> None:
    cfg = ChannelListConfig((1, 2, 5), t1_ms=20.0, t2_ms=3.0)  # t1 >= 3*3 + 1.5 for triplets
    pulses = {ch: P(*v) for ch, v in zip(cfg.channels, values, strict=True)}
    sim = RehaStimSimCore("sm1")
    assert sim.handle_bytes(encode_sm1_init(cfg) + encode_sm1_update(cfg, pulses), 0.0) == H("01 41")
    assert sim.channel_state() == {ch: p for ch, p in pulses.items() if p.current_ma > 0}


# ── SM2 ─────────────────────────────────────────────────────────────────────────────────────────


def sm2(data: bytes) -> list:
    return Sm2Decoder().feed(data)


def connected(t: float = 0.0) -> RehaStimSimCore:
    sim = RehaStimSimCore("sm2")
    first = sm2(sim.tick(t))
    assert first == [Sm2Init(0, 1)]
    assert sim.handle_bytes(encode_sm2(Sm2InitAck(first[0].packet_number)), t) == b""
    assert sim.initialised
    return sim


def test_sm2_init_repeats_every_500_ms_until_init_ack() -> None:
    sim = RehaStimSimCore("sm2")
    assert sm2(sim.tick(0.0)) == [Sm2Init(0, 1)]
    assert sim.tick(0.3) == b""
    assert sm2(sim.tick(0.5)) == [Sm2Init(1, 1)]
    # commands before InitAck: wrong mode
    assert sm2(sim.handle_bytes(encode_sm2(Sm2StopChannelListMode(9)), 0.6)) == [
        Sm2Ack(9, Sm2Command.STOP_CHANNEL_LIST_MODE_ACK, Sm2Result.WRONG_MODE)
    ]
    sim.handle_bytes(encode_sm2(Sm2InitAck(1)), 0.7)
    assert sim.tick(1.5) == b""


def test_sm2_session_and_watchdog() -> None:
    sim = connected(0.0)
    out = sim.handle_bytes(encode_sm2(Sm2InitChannelListMode(1, CFG)), 0.1)
    assert sm2(out) == [Sm2Ack(1, Sm2Command.INIT_CHANNEL_LIST_MODE_ACK, 0)]
    out = sim.handle_bytes(encode_sm2_start(2, CFG, {1: P(20, 200), 2: P(5, 10), 5: P(0, 0)}), 0.2)
    assert sm2(out) == [Sm2Ack(2, Sm2Command.START_CHANNEL_LIST_MODE_ACK, 0)]
    assert sim.channel_state() == {1: P(20, 200), 2: P(5, 20)}  # firmware: pw < 20 µs is delivered as 20 µs
    assert sm2(sim.handle_bytes(encode_sm2(Sm2GetStimulationMode(3)), 0.3)) == [
        Sm2GetStimulationModeAck(3, 0, Sm2StimulationMode.STARTED)
    ]
    # keep-alive within 1.2 s keeps it running
    for i in range(1, 6):
        assert sim.handle_bytes(encode_sm2(Sm2Watchdog(3 + i)), 0.3 + 0.9 * i) == b""
    assert sim.channel_state() != {}
    # silence > 1.2 s: stimulation stops, the device starts sending Init again
    out = sim.tick(4.8 + 1.21)
    assert sim.channel_state() == {} and not sim.initialised and sim.watchdog_expiries == 1
    assert isinstance(sm2(out)[0], Sm2Init)
    assert sim.log[-2:] == [StimulationLogEntry(6.01, 1, 0, 0), StimulationLogEntry(6.01, 2, 0, 0)]


def test_the_simulator_thread_wakes_when_the_device_acts_on_its_own() -> None:
    """``next_event_time``: the simulator's thread sleeps until then (at most its poll period): ScienceMode 2's
    watchdog expires at it and not before, and its Init is repeated at it; ScienceMode 1 never acts alone."""
    assert RehaStimSimCore("sm1").next_event_time() is None
    sim = connected(0.0)
    sim.handle_bytes(encode_sm2(Sm2InitChannelListMode(1, CFG)), 0.1)
    sim.handle_bytes(encode_sm2_start(2, CFG, {1: P(20, 200), 2: P(5, 10), 5: P(0, 0)}), 0.2)
    due = sim.next_event_time()
    assert due is not None and due == pytest.approx(0.2 + 1.2, abs=1e-3)
    assert sim.tick(due - 1e-3) == b"" and sim.initialised and sim.channel_state() != {}
    out = sim.tick(due)
    assert not sim.initialised and sim.watchdog_expiries == 1 and isinstance(sm2(out)[0], Sm2Init)
    again = sim.next_event_time()
    assert again is not None and sim.tick(again - 1e-3) == b"" and isinstance(sm2(sim.tick(again))[0], Sm2Init)


def test_sm2_error_acks() -> None:
    sim = connected()
    # start before init: wrong mode
    assert sm2(sim.handle_bytes(encode_sm2_start(1, CFG, {1: P(1, 1), 2: P(1, 1), 5: P(1, 1)}), 0.1)) == [
        Sm2Ack(1, Sm2Command.START_CHANNEL_LIST_MODE_ACK, Sm2Result.WRONG_MODE)
    ]
    # t1 below the 8 ms firmware minimum (built by hand: the encoder refuses it)
    data = bytes([0, 0x01, 0, 0, 0, 10, 0])  # MSI 10 -> 6 ms
    assert sm2(sim.handle_bytes(encode_sm2_frame(2, Sm2Command.INIT_CHANNEL_LIST_MODE, data), 0.2)) == [
        Sm2Ack(2, Sm2Command.INIT_CHANNEL_LIST_MODE_ACK, Sm2Result.PARAMETER_ERROR)
    ]
    # bad CRC: transfer error with the echoed packet number
    raw = bytearray(encode_sm2(Sm2InitChannelListMode(3, CFG)))
    raw[2] ^= 0x01
    assert sm2(sim.handle_bytes(bytes(raw), 0.3)) == [
        Sm2Ack(3, Sm2Command.INIT_CHANNEL_LIST_MODE_ACK, Sm2Result.TRANSFER_ERROR)
    ]
    sim.handle_bytes(encode_sm2(Sm2InitChannelListMode(4, CFG)), 0.4)
    # wrong number of channel settings, 131 mA, triplet too long for t1
    assert (
        sm2(
            sim.handle_bytes(
                encode_sm2_frame(5, Sm2Command.START_CHANNEL_LIST_MODE, bytes([0, 0, 100, 10])), 0.5
            )
        )[0].result
        == Sm2Result.PARAMETER_ERROR
    )
    over = bytes([0, 0, 100, 131]) * 3
    assert sm2(sim.handle_bytes(encode_sm2_frame(6, Sm2Command.START_CHANNEL_LIST_MODE, over), 0.6))[
        0
    ].result == (Sm2Result.PARAMETER_ERROR)
    triplets = bytes([2, 0, 100, 10]) * 3  # 3 * t2 (3 ms) = 9 <= 25: fine
    assert (
        sm2(sim.handle_bytes(encode_sm2_frame(7, Sm2Command.START_CHANNEL_LIST_MODE, triplets), 0.7))[
            0
        ].result
        == Sm2Result.OK
    )
    # single pulse during CCL: wrong mode; unknown command: UnknownCommand
    assert (
        sm2(sim.handle_bytes(encode_sm2(Sm2SinglePulse(8, 1, P(10, 100))), 0.8))[0].result
        == Sm2Result.WRONG_MODE
    )
    assert sm2(sim.handle_bytes(encode_sm2_frame(9, 77), 0.9)) == [Sm2UnknownCommand(9, 77)]
    assert sim.bad_packets == 2


def test_sm2_faults() -> None:
    sim = connected()
    sim.handle_bytes(encode_sm2(Sm2InitChannelListMode(1, CFG)), 0.1)
    sim.handle_bytes(encode_sm2_start(2, CFG, {1: P(20, 200), 2: P(0, 0), 5: P(0, 0)}), 0.2)
    sim.inject_error_ack(1, Sm2Result.BUSY)
    assert sm2(sim.handle_bytes(encode_sm2(Sm2StopChannelListMode(3)), 0.3)) == [
        Sm2Ack(3, Sm2Command.STOP_CHANNEL_LIST_MODE_ACK, Sm2Result.BUSY)
    ]
    assert sim.channel_state() == {1: P(20, 200)}  # not executed
    sim.inject_no_ack(1)
    assert sim.handle_bytes(encode_sm2(Sm2GetStimulationMode(4)), 0.4) == b""
    out = sm2(sim.inject_electrode_error(0.5))
    assert len(out) == 1 and isinstance(out[0], Sm2StimulationError) and out[0].code == -2
    assert sim.channel_state() == {} and sim.mode == Sm2StimulationMode.START
    # after the error a Start needs a new init
    assert (
        sm2(sim.handle_bytes(encode_sm2_start(5, CFG, {1: P(20, 200), 2: P(0, 0), 5: P(0, 0)}), 0.6))[
            0
        ].result
        == Sm2Result.WRONG_MODE
    )
    assert sm2(sim.press_emergency_stop(0.7))[0].code == -1


@FAST
@given(st.binary(max_size=200))
def test_sm2_sim_survives_garbage_then_works(garbage: bytes) -> None:
    sim = connected()
    sim.handle_bytes(garbage, 0.1)
    out = sm2(sim.handle_bytes(b"\x0f" + encode_sm2(Sm2StopChannelListMode(200)), 0.2))
    assert out[-1] == Sm2Ack(200, Sm2Command.STOP_CHANNEL_LIST_MODE_ACK, 0)


@pytest.mark.parametrize("protocol", ["sm1", "sm2"])
def test_unknown_protocol_is_refused(protocol: str) -> None:
    assert RehaStimSimCore(protocol).protocol == protocol  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="protocol"):
        RehaStimSimCore("sm3")  # type: ignore[arg-type]
