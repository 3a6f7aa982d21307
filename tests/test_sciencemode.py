"""ScienceMode 1 and 2 codecs: golden vectors (reference §6), round trips, garbage, truncation, splits."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.wire.sciencemode import (
    MAX_CURRENT_MA,
    BadPacket,
    ChannelListConfig,
    PulseMode,
    PulseSetting,
    ScienceModeRangeError,
    Sm1Ack,
    Sm1AckDecoder,
    Sm1CommandDecoder,
    Sm1Ident,
    Sm1Init,
    Sm1SinglePulse,
    Sm1Stop,
    Sm1Update,
    Sm2Ack,
    Sm2Command,
    Sm2Decoder,
    Sm2Frame,
    Sm2FrameDecoder,
    Sm2GetStimulationMode,
    Sm2GetStimulationModeAck,
    Sm2Init,
    Sm2InitAck,
    Sm2InitChannelListMode,
    Sm2SinglePulse,
    Sm2StartChannelListMode,
    Sm2StimulationError,
    Sm2StimulationMode,
    Sm2StopChannelListMode,
    Sm2UnknownCommand,
    Sm2Watchdog,
    channel_list_config_for,
    crc8,
    decode_sm1_ack,
    encode_sm1,
    encode_sm1_ack,
    encode_sm1_init,
    encode_sm1_single_pulse,
    encode_sm1_stop,
    encode_sm1_update,
    encode_sm2,
    encode_sm2_frame,
    encode_sm2_start,
    min_t2_ms,
    sm2_stuff,
    sm2_unstuff,
    t1_ms_for_frequency,
    validate_channel_list,
)

FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
P = PulseSetting
H = bytes.fromhex

# ── reference §6.1: SM1 PC → RehaStim 1 ───────────────────────────────────────────────────────────
INIT_6 = ChannelListConfig(
    (1, 2, 5), t1_ms=50.0, t2_ms=5.0, low_frequency_channels=(5,), low_frequency_factor=1
)
INIT_7 = ChannelListConfig(
    (2, 3, 6, 8), t1_ms=16.5, t2_ms=6.0, low_frequency_channels=(2, 3), low_frequency_factor=2
)
UPDATE_12 = {
    2: P(52, 100),
    3: P(55, 200, PulseMode.TRIPLET),
    6: P(72, 300, PulseMode.DOUBLET),
    8: P(92, 400, PulseMode.DOUBLET),
}


def test_sm1_golden_single_pulses() -> None:
    assert encode_sm1_single_pulse(3, P(120, 200)) == H("E2 21 48 78")  # §6.1 #1 (PDF)
    assert encode_sm1_single_pulse(6, P(55, 221)) == H("F9 51 5D 37")  # §6.1 #2 (PDF)


def test_sm1_golden_inits() -> None:
    assert encode_sm1_init(INIT_6) == H("94 44 62 00 70 62")  # §6.1 #6
    assert encode_sm1_init(INIT_7) == H("99 29 40 61 10 1F")  # §6.1 #7


def test_sm1_golden_update_and_stop() -> None:
    # The update bytes do not depend on t1; but the spec's example pairs triplets with t1 = 16.5 ms, which
    # breaks its own rule t1 >= 3*t2 + 1.5 = 19.5 ms, so the validating encoder refuses it with init #7 ...
    with pytest.raises(ScienceModeRangeError, match="t1_ms"):
        encode_sm1_update(INIT_7, UPDATE_12)
    # ... and produces the §6.1 #12 bytes with a t1 that respects the rule.
    valid = ChannelListConfig((2, 3, 6, 8), 19.5, 6.0, (2, 3), 2)
    assert encode_sm1_update(valid, UPDATE_12) == H("BB 00 64 34 41 48 37 22 2C 48 23 10 5C")
    assert encode_sm1_stop() == H("C0")  # §6.1 #17


def test_sm1_golden_acks() -> None:
    expected = {
        Sm1Ident.INIT: (0x01, 0x00),
        Sm1Ident.UPDATE: (0x41, 0x40),
        Sm1Ident.STOP: (0x81, 0x80),
        Sm1Ident.SINGLE_PULSE: (0xC1, 0xC0),
    }
    for ident, (ok, err) in expected.items():
        assert encode_sm1_ack(ident, True) == bytes([ok])
        assert encode_sm1_ack(ident, False) == bytes([err])
        assert decode_sm1_ack(ok) == Sm1Ack(ident, True)
        assert decode_sm1_ack(err) == Sm1Ack(ident, False)
    assert decode_sm1_ack(0x43) is None  # undefined bits set


def test_sm1_decoder_reads_every_golden_vector() -> None:
    dec = Sm1CommandDecoder()
    stream = H(
        "E2 21 48 78 F9 51 5D 37 94 44 62 00 70 62 99 29 40 61 10 1F "
        "BB 00 64 34 41 48 37 22 2C 48 23 10 5C C0"
    )
    got = dec.feed(stream)
    assert got == [
        Sm1SinglePulse(3, P(120, 200)),
        Sm1SinglePulse(6, P(55, 221)),
        Sm1Init(INIT_6),
        Sm1Init(INIT_7),
        Sm1Update(tuple(UPDATE_12[ch] for ch in (2, 3, 6, 8))),
        Sm1Stop(),
    ]
    assert dec.bad_packets == 0 and dec.discarded_bytes == 0


# ── reference §6.2 / §6.3: SM2 ───────────────────────────────────────────────────────────────────
ONE_CH = ChannelListConfig((1,), t1_ms=33.0, t2_ms=1.5)

SM2_PC_TO_DEVICE = [
    (Sm2InitAck(0, 0), "F0 81 7F 81 56 00 02 00 0F"),  # #1
    (Sm2Watchdog(4), "F0 81 1D 81 57 04 04 0F"),  # #2
    (Sm2InitChannelListMode(2, ONE_CH, 1), "F0 81 17 81 5C 02 1E 00 01 00 00 00 40 01 0F"),  # #4
    (Sm2StartChannelListMode(3, (P(5, 350),)), "F0 81 E0 81 53 03 20 00 01 5E 05 0F"),  # #6
    (Sm2StopChannelListMode(5), "F0 81 FA 81 57 05 22 0F"),  # #8
    (Sm2StartChannelListMode(7, (P(15, 240),)), "F0 81 00 81 5D 07 20 00 00 81 A5 81 5A 0F"),  # #10 stuffing
]
SM2_DEVICE_TO_PC = [
    (Sm2Init(0, 1), "F0 81 47 81 56 00 01 01 0F"),
    (Sm2Ack(2, Sm2Command.INIT_CHANNEL_LIST_MODE_ACK, 0), "F0 81 17 81 56 02 1F 00 0F"),
    (Sm2Ack(2, Sm2Command.INIT_CHANNEL_LIST_MODE_ACK, -2), "F0 81 E3 81 56 02 1F FE 0F"),
    (Sm2Ack(3, Sm2Command.START_CHANNEL_LIST_MODE_ACK, 0), "F0 81 53 81 56 03 21 00 0F"),
    (Sm2Ack(3, Sm2Command.START_CHANNEL_LIST_MODE_ACK, -3), "F0 81 AE 81 56 03 21 FD 0F"),
    (Sm2Ack(5, Sm2Command.STOP_CHANNEL_LIST_MODE_ACK, 0), "F0 81 04 81 56 05 23 00 0F"),
    (Sm2Ack(6, Sm2Command.SINGLE_PULSE_ACK, 0), "F0 81 C7 81 56 06 25 00 0F"),
    (Sm2GetStimulationModeAck(1, 0, Sm2StimulationMode.STARTED), "F0 81 A1 81 51 01 0B 00 02 0F"),
    (Sm2GetStimulationModeAck(1, -8), "F0 81 4F 81 56 01 0B F8 0F"),
    (Sm2StimulationError(17, -1), "F0 81 BF 81 56 11 26 FF 0F"),
    (Sm2StimulationError(18, -2), "F0 81 05 81 56 12 26 FE 0F"),
    (Sm2UnknownCommand(9, 0x63), "F0 81 7E 81 56 09 03 63 0F"),
]


def test_crc8_check_value() -> None:
    assert crc8(b"123456789") == 0xF4


@pytest.mark.parametrize(("message", "hexbytes"), SM2_PC_TO_DEVICE + SM2_DEVICE_TO_PC)
def test_sm2_golden_encode(message: object, hexbytes: str) -> None:
    assert encode_sm2(message, ONE_CH) == H(hexbytes)  # type: ignore[arg-type]


@pytest.mark.parametrize(("message", "hexbytes"), SM2_PC_TO_DEVICE + SM2_DEVICE_TO_PC)
def test_sm2_golden_decode(message: object, hexbytes: str) -> None:
    dec = Sm2Decoder()
    got = dec.feed(H(hexbytes))
    if isinstance(message, Sm2InitChannelListMode):
        message = Sm2InitChannelListMode(2, ONE_CH, 1, t1_code=64)
    assert got == [message]
    assert dec.bad_packets == 0


def test_sm2_start_with_channel_mapping_matches_golden() -> None:
    assert encode_sm2_start(3, ONE_CH, {1: P(5, 350)}) == H("F0 81 E0 81 53 03 20 00 01 5E 05 0F")


def test_sm2_get_stimulation_mode_is_escaped_unlike_pysciencemode() -> None:
    # command 10 is not special, but packet number 0xF0 is: it must go out as 81 A5 (§3.4)
    frame = encode_sm2(Sm2GetStimulationMode(0xF0))
    assert H("81 A5 0A") in frame
    assert Sm2Decoder().feed(frame) == [Sm2GetStimulationMode(0xF0)]


# ── validation ───────────────────────────────────────────────────────────────────────────────────


@pytest.mark.parametrize(
    ("setting", "field"),
    [
        (P(127, 200), "current_ma"),
        (P(-1, 200), "current_ma"),
        (P(10, 501), "pulse_width_us"),
        (P(10, -5), "pulse_width_us"),
    ],
)
def test_pulse_ranges_are_refused_before_encoding(setting: PulseSetting, field: str) -> None:
    with pytest.raises(ScienceModeRangeError) as exc:
        encode_sm1_single_pulse(1, setting)
    assert exc.value.field.endswith(field)
    assert "0.." in exc.value.allowed
    with pytest.raises(ScienceModeRangeError):
        encode_sm2(Sm2SinglePulse(0, 1, setting))


def test_channel_and_timing_rules() -> None:
    with pytest.raises(ScienceModeRangeError, match="channel"):
        encode_sm1_single_pulse(9, P(10, 100))
    # 4 channels on module A need t2 >= 6 ms
    with pytest.raises(ScienceModeRangeError, match=r"t2_ms.*>= 6 ms"):
        encode_sm1_init(ChannelListConfig((1, 2, 3, 4), 20.0, 5.5))
    assert min_t2_ms((1, 2, 3, 4, 5)) == 6.0 and min_t2_ms((1, 5)) == 1.5
    # off the 0.5 ms grid is refused, not rounded
    with pytest.raises(ScienceModeRangeError, match=r"0\.5 ms steps"):
        encode_sm1_init(ChannelListConfig((1,), 20.25, 3.0))
    # SM1 text range t1 3..1023.5 ms; SM2 minimum t1 8 ms
    with pytest.raises(ScienceModeRangeError, match="t1_ms"):
        encode_sm1_init(ChannelListConfig((1,), 1024.0, 3.0))
    with pytest.raises(ScienceModeRangeError, match="t1_ms"):
        encode_sm2(Sm2InitChannelListMode(1, ChannelListConfig((1,), 7.5, 1.5)))
    # doublets need t1 >= 2*t2 + 1.5 on SM1, 2*t2 on SM2
    cfg = ChannelListConfig((1,), 10.0, 5.0)
    with pytest.raises(ScienceModeRangeError, match=r"t1_ms.*11\.5"):
        encode_sm1_update(cfg, {1: P(10, 100, PulseMode.DOUBLET)})
    assert encode_sm2_start(1, ChannelListConfig((1,), 10.0, 5.0), {1: P(10, 100, PulseMode.DOUBLET)})
    # the update must cover exactly the initialised channels
    with pytest.raises(ScienceModeRangeError, match="initialised channels"):
        encode_sm1_update(INIT_6, {1: P(1, 1), 2: P(1, 1)})
    with pytest.raises(ScienceModeRangeError, match="subset"):
        encode_sm1_init(ChannelListConfig((1,), 20.0, 3.0, low_frequency_channels=(2,)))
    with pytest.raises(ScienceModeRangeError, match="SINGLE"):
        encode_sm1_single_pulse(1, P(10, 100, PulseMode.DOUBLET))
    with pytest.raises(ScienceModeRangeError, match="packet_number"):
        encode_sm2_frame(256, 4)


def test_config_helpers() -> None:
    assert t1_ms_for_frequency(40.0) == 25.0 and t1_ms_for_frequency(60.0) == 16.5
    cfg = channel_list_config_for((6, 1, 2), 40.0, "sm1")
    assert cfg.channels == (1, 2, 6) and cfg.t2_ms == 3.0 and cfg.t1_ms == 25.0
    assert validate_channel_list(cfg, "sm1") == (48, 3)
    with pytest.raises(ScienceModeRangeError):
        channel_list_config_for(range(1, 9), 400.0, "sm1")


# ── strategies ───────────────────────────────────────────────────────────────────────────────────
settings_st = st.builds(
    P, st.integers(0, MAX_CURRENT_MA), st.integers(0, 500), st.sampled_from(list(PulseMode))
)


@st.composite
def valid_config_and_settings(
    draw: st.DrawFn, protocol: str
) -> tuple[ChannelListConfig, dict[int, PulseSetting]]:
    chans = tuple(sorted(draw(st.sets(st.integers(1, 8), min_size=1))))
    pulses = {ch: draw(settings_st) for ch in chans}
    lf = tuple(sorted(draw(st.sets(st.sampled_from(chans)))))
    t2_lo = max(3.0 if protocol == "sm1" else 1.5, min_t2_ms(chans))
    t2 = draw(st.integers(int(t2_lo * 2), 32 if protocol == "sm1" else 258)) / 2
    group = max(p.mode.pulses for p in pulses.values())
    t1_lo = max(group * t2 + (1.5 if protocol == "sm1" else 0.0), 3.0 if protocol == "sm1" else 8.0)
    t1 = draw(st.integers(int(t1_lo * 2), 2047 if protocol == "sm1" else 2050)) / 2
    return ChannelListConfig(chans, t1, t2, lf, draw(st.integers(0, 7))), pulses


# ── SM1 properties ───────────────────────────────────────────────────────────────────────────────


@FAST
@given(valid_config_and_settings("sm1"))
def test_sm1_round_trip(case: tuple[ChannelListConfig, dict[int, PulseSetting]]) -> None:
    config, pulses = case
    dec = Sm1CommandDecoder()
    stream = encode_sm1_init(config) + encode_sm1_update(config, pulses) + encode_sm1_stop()
    got = dec.feed(stream)
    assert got == [Sm1Init(config), Sm1Update(tuple(pulses[ch] for ch in config.channels)), Sm1Stop()]
    assert encode_sm1(got[1], config) == encode_sm1_update(config, pulses)  # type: ignore[arg-type]


@FAST
@given(st.integers(1, 8), st.integers(0, MAX_CURRENT_MA), st.integers(0, 500), st.data())
def test_sm1_single_pulse_split_reads(channel: int, current: int, width: int, data: st.DataObject) -> None:
    raw = encode_sm1_single_pulse(channel, P(current, width)) * 3
    cuts = sorted(data.draw(st.lists(st.integers(0, len(raw)), max_size=6)))
    dec = Sm1CommandDecoder()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(raw)], strict=True):
        got += dec.feed(raw[a:b])
    assert got == [Sm1SinglePulse(channel, P(current, width))] * 3


@FAST
@given(st.binary(max_size=300))
def test_sm1_garbage_never_raises_and_resyncs(garbage: bytes) -> None:
    dec = Sm1CommandDecoder()
    dec.feed(garbage)
    # whatever came before, a complete packet after it is decoded
    good = encode_sm1_single_pulse(2, P(30, 250))
    assert dec.feed(good)[-1] == Sm1SinglePulse(2, P(30, 250))


def test_sm1_truncated_packet_is_counted_and_next_one_decoded() -> None:
    dec = Sm1CommandDecoder()
    cut = encode_sm1_single_pulse(3, P(120, 200))[:2]
    got = dec.feed(cut + encode_sm1_stop())
    assert (
        isinstance(got[0], BadPacket)
        and got[0].kind == "truncated"
        and got[0].command == Sm1Ident.SINGLE_PULSE
    )
    assert got[1] == Sm1Stop()
    assert dec.bad_packets == 1


def test_sm1_bad_checksum_is_reported_with_ident() -> None:
    dec = Sm1CommandDecoder()
    raw = bytearray(H("E2 21 48 78"))
    raw[3] ^= 0x01  # one mA more, checksum unchanged
    (bad,) = dec.feed(bytes(raw))
    assert isinstance(bad, BadPacket) and bad.kind == "checksum" and bad.command == Sm1Ident.SINGLE_PULSE
    assert dec.feed(H("C1")) == [BadPacket("checksum", "stop checksum is not 0", H("C1"), command=2)]


def test_sm1_update_before_init_is_reported_and_its_bytes_skipped() -> None:
    dec = Sm1CommandDecoder()
    got = dec.feed(H("BB 00 64 34 41 48 37 22 2C 48 23 10 5C") + encode_sm1_stop())
    assert [type(g) for g in got] == [BadPacket, Sm1Stop]
    assert got[0].kind == "no_context"  # type: ignore[union-attr]
    assert dec.discarded_bytes == 12


def test_sm1_ack_decoder_flags_non_acks() -> None:
    dec = Sm1AckDecoder()
    got = dec.feed(H("41 7E C1"))
    assert got[0] == Sm1Ack(Sm1Ident.UPDATE, True) and isinstance(got[1], BadPacket)
    assert got[2] == Sm1Ack(Sm1Ident.SINGLE_PULSE, True) and dec.bad_packets == 1


# ── SM2 properties ───────────────────────────────────────────────────────────────────────────────


@FAST
@given(st.binary(max_size=60))
def test_sm2_stuffing_round_trip(data: bytes) -> None:
    stuffed = sm2_stuff(data)
    assert not {0xF0, 0x0F} & set(stuffed)
    assert sm2_unstuff(stuffed) == data


@FAST
@given(st.integers(0, 255), st.integers(0, 255), st.binary(max_size=60))
def test_sm2_frame_round_trip(pn: int, cmd: int, data: bytes) -> None:
    assert Sm2FrameDecoder().feed(encode_sm2_frame(pn, cmd, data)) == [Sm2Frame(pn, cmd, data)]


@FAST
@given(valid_config_and_settings("sm2"), st.integers(0, 255), st.integers(0, 1))
def test_sm2_message_round_trip(
    case: tuple[ChannelListConfig, dict[int, PulseSetting]], pn: int, ex: int
) -> None:
    config, pulses = case
    init = encode_sm2(Sm2InitChannelListMode(pn, config, ex))
    start = encode_sm2_start(pn, config, pulses)
    got = Sm2Decoder().feed(init + start)
    assert isinstance(got[0], Sm2InitChannelListMode)
    assert (got[0].config, got[0].channel_execution, got[0].packet_number) == (config, ex, pn)
    assert got[1] == Sm2StartChannelListMode(pn, tuple(pulses[ch] for ch in config.channels))


device_messages = st.one_of(
    st.builds(Sm2Init, st.integers(0, 255), st.integers(0, 255)),
    st.builds(
        Sm2Ack,
        st.integers(0, 255),
        st.sampled_from(
            [
                Sm2Command.INIT_CHANNEL_LIST_MODE_ACK,
                Sm2Command.START_CHANNEL_LIST_MODE_ACK,
                Sm2Command.STOP_CHANNEL_LIST_MODE_ACK,
                Sm2Command.SINGLE_PULSE_ACK,
            ]
        ),
        st.integers(-128, 127),
    ),
    st.builds(Sm2StimulationError, st.integers(0, 255), st.integers(-3, -1)),
    st.builds(Sm2UnknownCommand, st.integers(0, 255), st.integers(0, 255)),
    st.builds(
        Sm2GetStimulationModeAck, st.integers(0, 255), st.just(0), st.sampled_from(list(Sm2StimulationMode))
    ),
    st.builds(
        Sm2SinglePulse,
        st.integers(0, 255),
        st.integers(1, 8),
        st.builds(P, st.integers(0, 126), st.integers(0, 500)),
    ),
    st.builds(Sm2Watchdog, st.integers(0, 255)),
)


@FAST
@given(st.lists(device_messages, min_size=1, max_size=5), st.binary(max_size=40), st.data())
def test_sm2_garbage_split_reads_and_resync(msgs: list, garbage: bytes, data: st.DataObject) -> None:
    # garbage, then a stop byte to close any packet the garbage opened, then good packets in random chunks
    stream = garbage + b"\x0f" + b"".join(encode_sm2(m) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    dec = Sm2Decoder()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        got += dec.feed(stream[a:b])
    good = [g for g in got if not isinstance(g, BadPacket)]
    assert good[-len(msgs) :] == msgs


@FAST
@given(st.binary(max_size=400))
def test_sm2_garbage_never_raises(garbage: bytes) -> None:
    dec = Sm2Decoder()
    out = dec.feed(garbage)
    assert dec.bad_packets >= sum(isinstance(o, BadPacket) for o in out)


@FAST
@given(device_messages, st.integers(min_value=1))
def test_sm2_corrupted_byte_is_never_accepted_silently(msg: object, where: int) -> None:
    raw = bytearray(encode_sm2(msg))  # type: ignore[arg-type]
    i = 5 + where % (len(raw) - 6)  # a byte of the stuffed body
    raw[i] ^= 0x01
    got = Sm2Decoder().feed(bytes(raw))
    assert msg not in got


def test_sm2_truncated_then_good() -> None:
    good = encode_sm2(Sm2Watchdog(4))
    dec = Sm2Decoder()
    got = dec.feed(good[:5] + good)
    assert isinstance(got[0], BadPacket) and got[0].kind == "truncated"
    assert got[1] == Sm2Watchdog(4) and dec.bad_packets == 1


def test_sm2_bad_crc_keeps_packet_number_and_command() -> None:
    raw = bytearray(H("F0 81 17 81 5C 02 1E 00 01 00 00 00 40 01 0F"))
    raw[2] ^= 0x10
    (bad,) = Sm2Decoder().feed(bytes(raw))
    assert isinstance(bad, BadPacket)
    assert (bad.kind, bad.packet_number, bad.command) == ("checksum", 2, Sm2Command.INIT_CHANNEL_LIST_MODE)


def test_sm2_wrong_parameter_count_and_unknown_command() -> None:
    dec = Sm2Decoder()
    got = dec.feed(
        encode_sm2_frame(7, Sm2Command.START_CHANNEL_LIST_MODE, b"\x00\x01\x00")
        + encode_sm2_frame(8, 99, b"")
    )
    assert [(g.kind, g.packet_number, g.command) for g in got] == [  # type: ignore[union-attr]
        ("parameter", 7, Sm2Command.START_CHANNEL_LIST_MODE),
        ("unknown_command", 8, 99),
    ]
    assert dec.bad_packets == 2


def test_sm2_decoder_accepts_over_escaped_data() -> None:
    # pysciencemode also escapes 0x55 and 0x0A; the device side must tolerate it (§3.4)
    body = bytes([3, Sm2Command.SINGLE_PULSE, 0x81, 0x0A ^ 0x55, 0x00, 0x81, 0x55 ^ 0x55, 0x05])
    frame = bytes([0xF0, 0x81, crc8(body) ^ 0x55, 0x81, len(body) ^ 0x55]) + body + b"\x0f"
    assert Sm2Decoder().feed(frame) == [Sm2SinglePulse(3, 11, P(5, 0x55))]


def test_sm2_escaped_crc_equal_to_delimiters_does_not_break_framing() -> None:
    # find packets whose xored CRC byte is 0x0F or 0xF0 and check they still decode
    found = 0
    for pn in range(256):
        frame = encode_sm2(Sm2Watchdog(pn))
        if frame[2] in (0x0F, 0xF0):
            found += 1
            assert Sm2Decoder().feed(frame) == [Sm2Watchdog(pn)]
    assert found > 0


def test_sm2_stray_escape_does_not_swallow_the_next_packet() -> None:
    good = encode_sm2(Sm2Watchdog(4))
    dec = Sm2Decoder()
    got = dec.feed(good[:7] + b"\x81" + good)  # a packet cut after a stray escape byte
    assert got[-1] == Sm2Watchdog(4)
    assert dec.bad_packets == 1
