"""Hasomed ScienceMode codecs: ScienceMode 1 (RehaStim 1, the seed's device) and ScienceMode 2 (RehaStim 2).

Pure: bytes in, typed messages out, and back. No I/O, no Qt, no clocks.

Both directions are here (PC → device and device → PC) because the simulator speaks the device side.
Encoders validate every value *before* building a byte and raise ``ScienceModeRangeError`` (a
``ValueError``) naming the field and the allowed range. Decoders never raise on garbage: they resync,
count what they dropped and return ``BadPacket`` items for things that looked like packets but were not.

Units: current in mA and pulse width in µs as the device speaks them; the main period t1 and the
group period t2 in ms because the protocol codes them in 0.5 ms steps (``t1_ms``/``t2_ms``).
Channels are numbered 1..8 everywhere in code; the 0-based wire numbering and bit masks stay in here.

Byte-level reference: /work/shared/reference/sciencemode.md (sections cited as §).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

Protocol = Literal["sm1", "sm2"]

# ── device facts (one place) ──────────────────────────────────────────────────────────────────────
CHANNELS: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8)
CHANNELS_TEXT = f"{CHANNELS[0]}..{CHANNELS[-1]}"  # how messages name them: "1..8"
MODULE_A: tuple[int, ...] = (1, 2, 3, 4)  # one current source multiplexed to 4 outputs (§2.4)
MODULE_B: tuple[int, ...] = (5, 6, 7, 8)
CHANNEL_SLOT_MS = 1.5  # every selected channel gets a 1.5 ms slot per pass (§2.4)
SM1_MODULE_COMM_MS = 1.5  # SM1: main-to-module communication time, t1 >= npg*t2 + 1.5 ms (§2.4)

MAX_CURRENT_MA = (
    126  # RehaStim 1 hardware maximum; also Hasomed's RehaStim 2 figure (§4). We never encode more.
)
SM2_PROTOCOL_MAX_CURRENT_MA = 130  # what RehaStim 2 firmware accepts (§4); only the simulator uses it
MAX_PULSE_WIDTH_US = 500
SM2_MIN_DELIVERED_PULSE_WIDTH_US = 20  # RehaStim 2 firmware: "pw < 20 -> 20" (§4)
MAX_LOW_FREQUENCY_FACTOR = 7

# SM1 t1/t2: the spec's text ranges (narrower than what the fields could code) (§2.4, §4).
SM1_T1_RANGE_MS = (3.0, 1023.5)
SM1_T2_RANGE_MS = (3.0, 16.0)
# SM2: t1 coded 0..2048 (t1 = v*0.5 + 1 ms, 0 = one-shot, not supported here), min 8 ms in current SW;
# t2 coded 0..255 (t2 = v*0.5 + 1.5 ms) (§3.2, §4).
SM2_T1_RANGE_MS = (8.0, 1025.0)
SM2_T2_RANGE_MS = (1.5, 129.0)

# SM2 timing (§3.1)
SM2_INIT_REPETITION_S = 0.5
SM2_WATCHDOG_TIMEOUT_S = 1.2
SM2_KEEPALIVE_PERIOD_S = 0.8  # how often the PC sends Watchdog when idle (pysciencemode uses 0.8 s)
SM2_MAX_RESPONSE_S = 0.1
SM2_MAX_PACKET_BYTES = 150  # spec: data < 61 bytes; worst case fully stuffed frame is well below this


class PulseMode(IntEnum):
    """Pulse group per period: the list is run 1, 2 or 3 times at interval t2 (§2.2)."""

    SINGLE = 0
    DOUBLET = 1
    TRIPLET = 2

    @property
    def pulses(self) -> int:
        return int(self) + 1


class ScienceModeRangeError(ValueError):
    """A value cannot be sent: names the field, the value and what is allowed."""

    def __init__(self, field: str, value: object, allowed: str) -> None:
        self.field = field
        self.value = value
        self.allowed = allowed
        super().__init__(f"{field} = {value!r} is not allowed; allowed: {allowed}")


@dataclass(frozen=True)
class PulseSetting:
    """What one channel delivers: current (mA), pulse width (µs, per phase) and the pulse group."""

    current_ma: int
    pulse_width_us: int
    mode: PulseMode = PulseMode.SINGLE


@dataclass(frozen=True)
class ChannelListConfig:
    """Continuous Channel List initialisation (both protocols).

    ``channels``: active channels (1..8). ``low_frequency_channels``: the subset stimulated only every
    (low_frequency_factor + 1)-th period. ``t1_ms``: main period (1/frequency). ``t2_ms``: interval
    between the passes of a doublet/triplet (and the time one pass through the list may take).
    Not validated on construction (decoders build these from any bytes); ``validate_channel_list``
    is what encoders call.
    """

    channels: tuple[int, ...]
    t1_ms: float
    t2_ms: float
    low_frequency_channels: tuple[int, ...] = ()
    low_frequency_factor: int = 0

    @property
    def frequency_hz(self) -> float:
        return 1000.0 / self.t1_ms

    def channel_frequency_hz(self, channel: int) -> float:
        """Periods per second of one channel (low-frequency channels skip ``low_frequency_factor``)."""
        if channel in self.low_frequency_channels:
            return self.frequency_hz / (self.low_frequency_factor + 1)
        return self.frequency_hz


@dataclass(frozen=True)
class BadPacket:
    """Something that started like a packet but could not be used. ``command``/``packet_number`` are
    set when they could be read (the device answers those with an error ack)."""

    kind: Literal["checksum", "length", "truncated", "oversize", "parameter", "unknown_command", "no_context"]
    reason: str
    raw: bytes
    command: int | None = None
    packet_number: int | None = None


# ── shared validation ─────────────────────────────────────────────────────────────────────────────


def _check_int(field: str, value: object, lo: int, hi: int, unit: str = "") -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ScienceModeRangeError(field, value, f"whole number {lo}..{hi}{' ' + unit if unit else ''}")
    return value


def _check_channel(field: str, channel: object) -> int:
    return _check_int(field, channel, CHANNELS[0], CHANNELS[-1])


def _code_half_ms(field: str, value_ms: object, offset_ms: float, lo_ms: float, hi_ms: float) -> int:
    """ms → protocol code (value = code*0.5 + offset). Off the 0.5 ms grid is refused, not rounded."""
    allowed = f"{lo_ms:g}..{hi_ms:g} ms in 0.5 ms steps"
    if isinstance(value_ms, bool) or not isinstance(value_ms, int | float) or not math.isfinite(value_ms):
        raise ScienceModeRangeError(field, value_ms, allowed)
    if not lo_ms <= value_ms <= hi_ms:
        raise ScienceModeRangeError(field, value_ms, allowed)
    code = (value_ms - offset_ms) / 0.5
    if abs(code - round(code)) > 1e-9:
        raise ScienceModeRangeError(field, value_ms, allowed)
    return round(code)


def validate_pulse(channel: int, setting: PulseSetting, *, field: str = "") -> None:
    """Range checks common to both protocols: channel 1..8, 0..126 mA, 0..500 µs, mode 0/1/2."""
    prefix = field or f"channel {channel}"
    _check_channel(f"{prefix}: channel", channel)
    _check_int(f"{prefix}: current_ma", setting.current_ma, 0, MAX_CURRENT_MA, "mA")
    _check_int(f"{prefix}: pulse_width_us", setting.pulse_width_us, 0, MAX_PULSE_WIDTH_US, "µs")
    if isinstance(setting.mode, bool) or setting.mode not in tuple(PulseMode):
        raise ScienceModeRangeError(f"{prefix}: mode", setting.mode, "0 single, 1 doublet, 2 triplet")


def min_t2_ms(channels: Iterable[int]) -> float:
    """ScienceMode 1's shortest t2 that fits one pass: 1.5 ms per channel on the busier module (§2.4).
    ScienceMode 2 has no such rule (see ``validate_channel_list``); the config builder still uses it as a
    conservative default for both."""
    chans = set(channels)
    return CHANNEL_SLOT_MS * max(len(chans & set(MODULE_A)), len(chans & set(MODULE_B)))


def min_t1_ms(protocol: Protocol, t2_ms: float, largest_group: int) -> float:
    """Shortest t1 for the largest pulse group in use (SM1: npg*t2 + 1.5 ms; SM2: npg*t2) (§2.4, §4)."""
    extra = SM1_MODULE_COMM_MS if protocol == "sm1" else 0.0
    return largest_group * t2_ms + extra


def _ranges(protocol: Protocol) -> tuple[tuple[float, float], tuple[float, float]]:
    if protocol == "sm1":
        return SM1_T1_RANGE_MS, SM1_T2_RANGE_MS
    if protocol == "sm2":
        return SM2_T1_RANGE_MS, SM2_T2_RANGE_MS
    raise ScienceModeRangeError("protocol", protocol, "'sm1' or 'sm2'")


def validate_channel_list(
    config: ChannelListConfig, protocol: Protocol, modes: Iterable[PulseMode] = ()
) -> tuple[int, int]:
    """Check an initialisation (and, with ``modes``, the pulse groups an update uses against it).

    Returns the coded (t1, t2). Raises ScienceModeRangeError naming the first offending field.
    """
    (t1_lo, t1_hi), (t2_lo, t2_hi) = _ranges(protocol)
    if not isinstance(config.channels, tuple) or not config.channels:
        raise ScienceModeRangeError("channels", config.channels, "a non-empty tuple of channels 1..8")
    for ch in config.channels:
        _check_channel("channels", ch)
    if list(config.channels) != sorted(set(config.channels)):
        raise ScienceModeRangeError("channels", config.channels, "increasing order, no repeats")
    for ch in config.low_frequency_channels:
        _check_channel("low_frequency_channels", ch)
        if ch not in config.channels:
            raise ScienceModeRangeError(
                "low_frequency_channels",
                config.low_frequency_channels,
                f"a subset of channels {config.channels}",
            )
    _check_int("low_frequency_factor", config.low_frequency_factor, 0, MAX_LOW_FREQUENCY_FACTOR)
    t2_code = _code_half_ms("t2_ms", config.t2_ms, 1.5, t2_lo, t2_hi)
    t1_code = _code_half_ms("t1_ms", config.t1_ms, 1.0, t1_lo, t1_hi)
    # SM1 only: S1 §4 (reference/sciencemode.md §2.4) sets t2 >= 1.5 ms per channel on the busier module.
    # ScienceMode 2 states no such rule: t2 is 1.5..129 ms (S4 §3.2, §4.3; reference §3.2 and the "group
    # time t2" row of §4) and t1 >= npg*t2 (S4 §1.3); pysciencemode accepts t2 from 2 ms (reference §4).
    need_t2 = min_t2_ms(config.channels) if protocol == "sm1" else t2_lo
    if config.t2_ms < need_t2:
        raise ScienceModeRangeError(
            "t2_ms",
            config.t2_ms,
            f">= {need_t2:g} ms (1.5 ms per channel on the busier module) for channels {config.channels}",
        )
    largest = max((PulseMode(m).pulses for m in modes), default=1)
    need_t1 = min_t1_ms(protocol, config.t2_ms, largest)
    if config.t1_ms < need_t1:
        raise ScienceModeRangeError(
            "t1_ms",
            config.t1_ms,
            f">= {need_t1:g} ms for pulse groups of {largest} at t2 = {config.t2_ms:g} ms",
        )
    return t1_code, t2_code


def _validate_settings(
    config: ChannelListConfig, settings: Mapping[int, PulseSetting], protocol: Protocol
) -> list[PulseSetting]:
    keys = tuple(sorted(settings))
    if keys != tuple(config.channels):
        raise ScienceModeRangeError("channels", keys, f"exactly the initialised channels {config.channels}")
    ordered = [settings[ch] for ch in keys]
    for ch, s in zip(keys, ordered, strict=False):
        validate_pulse(ch, s)
    validate_channel_list(config, protocol, (s.mode for s in ordered))
    return ordered


def t1_ms_for_frequency(frequency_hz: float) -> float:
    """The main period on the 0.5 ms grid nearest to 1/frequency."""
    if not math.isfinite(frequency_hz) or frequency_hz <= 0:
        raise ScienceModeRangeError("frequency_hz", frequency_hz, "> 0 Hz")
    return round(2000.0 / frequency_hz) / 2.0


def channel_list_config_for(
    channels: Iterable[int],
    frequency_hz: float,
    protocol: Protocol = "sm1",
    *,
    low_frequency_channels: Iterable[int] = (),
    low_frequency_factor: int = 0,
    largest_group: int = 1,
) -> ChannelListConfig:
    """A valid configuration for ``channels`` at about ``frequency_hz``: the shortest allowed t2, t1 on the
    0.5 ms grid. Raises ScienceModeRangeError when the frequency cannot be reached."""
    chans = tuple(sorted(set(channels)))
    (_, _), (t2_lo, _) = _ranges(protocol)
    t2 = max(t2_lo, min_t2_ms(chans))
    config = ChannelListConfig(
        chans,
        t1_ms_for_frequency(frequency_hz),
        t2,
        tuple(sorted(set(low_frequency_channels))),
        low_frequency_factor,
    )
    validate_channel_list(config, protocol, [PulseMode(largest_group - 1)])
    return config


def _mask(channels: Iterable[int]) -> int:
    m = 0
    for ch in channels:
        m |= 1 << (ch - 1)
    return m


def _unmask(mask: int) -> tuple[int, ...]:
    return tuple(ch for ch in CHANNELS if mask >> (ch - 1) & 1)


# ══ ScienceMode 1 ══════════════════════════════════════════════════════════════════════════════


class Sm1Ident(IntEnum):
    INIT = 0
    UPDATE = 1
    STOP = 2
    SINGLE_PULSE = 3


@dataclass(frozen=True)
class Sm1Init:
    config: ChannelListConfig


@dataclass(frozen=True)
class Sm1Update:
    """Settings in the order of the initialised channels (the wire carries no channel numbers)."""

    settings: tuple[PulseSetting, ...]


@dataclass(frozen=True)
class Sm1Stop:
    pass


@dataclass(frozen=True)
class Sm1SinglePulse:
    channel: int
    setting: PulseSetting


@dataclass(frozen=True)
class Sm1Ack:
    ident: Sm1Ident
    ok: bool


Sm1Command = Sm1Init | Sm1Update | Sm1Stop | Sm1SinglePulse


def _pack7(fields: Sequence[tuple[int, int]]) -> bytes:
    """Concatenate (value, bits) MSB first, cut into 7-bit groups, mark the first with bit 7 (§2.1)."""
    acc = 0
    nbits = 0
    for value, bits in fields:
        acc = acc << bits | (value & ((1 << bits) - 1))
        nbits += bits
    assert nbits % 7 == 0, "SM1 packets are whole 7-bit groups"
    n = nbits // 7
    out = bytearray((acc >> (7 * (n - 1 - i))) & 0x7F for i in range(n))
    out[0] |= 0x80
    return bytes(out)


def _unpack7(raw: bytes) -> int:
    acc = 0
    for b in raw:
        acc = acc << 7 | (b & 0x7F)
    return acc


def _sm1_init_check(n: int, stim: int, lf: int, group: int, main: int) -> int:
    return (n + stim + lf + group + main) % 8


def encode_sm1_init(config: ChannelListConfig) -> bytes:
    """Channel list mode initialisation, 6 bytes."""
    t1_code, t2_code = validate_channel_list(config, "sm1")
    stim, lf = _mask(config.channels), _mask(config.low_frequency_channels)
    n = config.low_frequency_factor
    check = _sm1_init_check(n, stim, lf, t2_code, t1_code)
    return _pack7(
        [(Sm1Ident.INIT, 2), (check, 3), (n, 3), (stim, 8), (lf, 8), (0, 2), (t2_code, 5), (t1_code, 11)]
    )


def encode_sm1_update(config: ChannelListConfig, settings: Mapping[int, PulseSetting]) -> bytes:
    """Channel list mode update for exactly the initialised channels, 1 + 3n bytes."""
    ordered = _validate_settings(config, settings, "sm1")
    check = sum(int(s.mode) + s.pulse_width_us + s.current_ma for s in ordered) % 32
    fields: list[tuple[int, int]] = [(Sm1Ident.UPDATE, 2), (check, 5)]
    for s in ordered:
        fields += [(int(s.mode), 2), (0, 3), (s.pulse_width_us, 9), (s.current_ma, 7)]
    return _pack7(fields)


def encode_sm1_stop() -> bytes:
    return _pack7([(Sm1Ident.STOP, 2), (0, 5)])


def encode_sm1_single_pulse(channel: int, setting: PulseSetting) -> bytes:
    """One single pulse on ``channel`` (mode must be SINGLE: the command has no mode field)."""
    validate_pulse(channel, setting)
    if setting.mode != PulseMode.SINGLE:
        raise ScienceModeRangeError("mode", setting.mode, "SINGLE (a single pulse has no group)")
    number = channel - 1
    check = (number + setting.pulse_width_us + setting.current_ma) % 32
    return _pack7(
        [
            (Sm1Ident.SINGLE_PULSE, 2),
            (check, 5),
            (number, 3),
            (0, 2),
            (setting.pulse_width_us, 9),
            (setting.current_ma, 7),
        ]
    )


def encode_sm1(command: Sm1Command, config: ChannelListConfig | None = None) -> bytes:
    """Encode any SM1 command; an update needs the ``config`` of the last init."""
    if isinstance(command, Sm1Init):
        return encode_sm1_init(command.config)
    if isinstance(command, Sm1Update):
        if config is None:
            raise ScienceModeRangeError("config", None, "the ChannelListConfig of the last init")
        if len(command.settings) != len(config.channels):
            raise ScienceModeRangeError("settings", len(command.settings), f"{len(config.channels)} settings")
        return encode_sm1_update(config, dict(zip(config.channels, command.settings, strict=False)))
    if isinstance(command, Sm1Stop):
        return encode_sm1_stop()
    if isinstance(command, Sm1SinglePulse):
        return encode_sm1_single_pulse(command.channel, command.setting)
    raise TypeError(f"not an SM1 command: {command!r}")


def encode_sm1_ack(ident: Sm1Ident | int, ok: bool) -> bytes:
    """Device → PC: one byte, Ident in bits 7-6, bit 0 = 1 OK / 0 error (§2.3)."""
    ident = Sm1Ident(_check_int("ident", int(ident), 0, 3))
    return bytes([ident << 6 | (1 if ok else 0)])


def decode_sm1_ack(byte: int) -> Sm1Ack | None:
    """One ack byte, or None if bits 5-1 (undefined, always 0 in the spec) are set."""
    if byte & 0x3E:
        return None
    return Sm1Ack(Sm1Ident(byte >> 6), bool(byte & 1))


class Sm1AckDecoder:
    """PC side: every byte is an ack. Bytes with undefined bits set are counted and reported."""

    def __init__(self) -> None:
        self.bad_packets = 0

    def feed(self, data: bytes) -> list[Sm1Ack | BadPacket]:
        out: list[Sm1Ack | BadPacket] = []
        for b in data:
            ack = decode_sm1_ack(b)
            if ack is None:
                self.bad_packets += 1
                out.append(BadPacket("parameter", f"0x{b:02X} is not an SM1 ack (bits 5-1 set)", bytes([b])))
            else:
                out.append(ack)
        return out


_SM1_FIXED_LENGTH = {Sm1Ident.INIT: 6, Sm1Ident.STOP: 1, Sm1Ident.SINGLE_PULSE: 4}


class Sm1CommandDecoder:
    """Device side: PC → RehaStim 1 byte stream to commands.

    A byte with bit 7 set always starts a packet; continuation bytes outside a packet are dropped
    (``discarded_bytes``). The update length depends on the channel count of the last init: by default
    the decoder follows every checksum-valid init it decodes; the owner may override
    ``update_channels`` (e.g. set None after refusing an init).
    """

    def __init__(self) -> None:
        self.update_channels: tuple[int, ...] | None = None
        self.bad_packets = 0
        self.discarded_bytes = 0
        self._buf = bytearray()
        self._want = 0

    def _length(self, ident: Sm1Ident) -> int | None:
        if ident == Sm1Ident.UPDATE:
            return None if self.update_channels is None else 1 + 3 * len(self.update_channels)
        return _SM1_FIXED_LENGTH[ident]

    def _bad(self, kind: str, reason: str, raw: bytes, ident: int | None) -> BadPacket:
        self.bad_packets += 1
        return BadPacket(kind, reason, raw, command=ident)  # type: ignore[arg-type]

    def feed(self, data: bytes) -> list[Sm1Command | BadPacket]:
        out: list[Sm1Command | BadPacket] = []
        for b in data:
            if b & 0x80:
                if self._buf:
                    ident = self._buf[0] >> 5 & 3
                    out.append(
                        self._bad(
                            "truncated",
                            f"{Sm1Ident(ident).name} cut short after {len(self._buf)} of {self._want} bytes",
                            bytes(self._buf),
                            ident,
                        )
                    )
                    self._buf.clear()
                ident = Sm1Ident(b >> 5 & 3)
                want = self._length(ident)
                if want is None:
                    out.append(
                        self._bad(
                            "no_context", "update before any init: channel count unknown", bytes([b]), ident
                        )
                    )
                    continue  # its continuation bytes are dropped as stray bytes
                self._buf.append(b)
                self._want = want
            elif self._buf:
                self._buf.append(b)
            else:
                self.discarded_bytes += 1
                continue
            if len(self._buf) == self._want:
                raw = bytes(self._buf)
                self._buf.clear()
                out.append(self._decode(raw))
        return out

    def _decode(self, raw: bytes) -> Sm1Command | BadPacket:
        ident = Sm1Ident(raw[0] >> 5 & 3)
        bits = _unpack7(raw)
        nbits = 7 * len(raw)

        def field(start: int, width: int) -> int:  # start counted from the MSB of the packet
            return bits >> (nbits - start - width) & ((1 << width) - 1)

        if ident == Sm1Ident.STOP:
            if field(2, 5) != 0:
                return self._bad("checksum", "stop checksum is not 0", raw, ident)
            return Sm1Stop()
        if ident == Sm1Ident.SINGLE_PULSE:
            check, number, pw, current = field(2, 5), field(7, 3), field(12, 9), field(21, 7)
            if check != (number + pw + current) % 32:
                return self._bad(
                    "checksum", f"single pulse checksum {check} != {(number + pw + current) % 32}", raw, ident
                )
            return Sm1SinglePulse(number + 1, PulseSetting(current, pw))
        if ident == Sm1Ident.INIT:
            check, n, stim, lf = field(2, 3), field(5, 3), field(8, 8), field(16, 8)
            group, main = field(26, 5), field(31, 11)
            expect = _sm1_init_check(n, stim, lf, group, main)
            if check != expect:
                return self._bad("checksum", f"init checksum {check} != {expect}", raw, ident)
            config = ChannelListConfig(_unmask(stim), main * 0.5 + 1.0, group * 0.5 + 1.5, _unmask(lf), n)
            self.update_channels = config.channels
            return Sm1Init(config)
        check = field(2, 5)
        settings = []
        total = 0
        for i in range((len(raw) - 1) // 3):
            base = 7 + 21 * i
            mode, pw, current = field(base, 2), field(base + 5, 9), field(base + 14, 7)
            total += mode + pw + current
            if mode > PulseMode.TRIPLET:
                return self._bad("parameter", f"update: mode {mode} is not 0/1/2", raw, ident)
            settings.append(PulseSetting(current, pw, PulseMode(mode)))
        if check != total % 32:
            return self._bad("checksum", f"update checksum {check} != {total % 32}", raw, ident)
        return Sm1Update(tuple(settings))


# ══ ScienceMode 2 ══════════════════════════════════════════════════════════════════════════════

SM2_START = 0xF0
SM2_STOP = 0x0F
SM2_STUFFING = 0x81
SM2_STUFFING_KEY = 0x55
_SM2_ESCAPED = frozenset({SM2_START, SM2_STOP, SM2_STUFFING})


class Sm2Command(IntEnum):
    INIT = 1
    INIT_ACK = 2
    UNKNOWN_COMMAND = 3
    WATCHDOG = 4
    GET_STIMULATION_MODE = 10
    GET_STIMULATION_MODE_ACK = 11
    INIT_CHANNEL_LIST_MODE = 30
    INIT_CHANNEL_LIST_MODE_ACK = 31
    START_CHANNEL_LIST_MODE = 32
    START_CHANNEL_LIST_MODE_ACK = 33
    STOP_CHANNEL_LIST_MODE = 34
    STOP_CHANNEL_LIST_MODE_ACK = 35
    SINGLE_PULSE = 36
    SINGLE_PULSE_ACK = 37
    STIMULATION_ERROR = 38


# Which ack answers which command (commands without an entry get no ack).
SM2_ACK_FOR: dict[Sm2Command, Sm2Command] = {
    Sm2Command.GET_STIMULATION_MODE: Sm2Command.GET_STIMULATION_MODE_ACK,
    Sm2Command.INIT_CHANNEL_LIST_MODE: Sm2Command.INIT_CHANNEL_LIST_MODE_ACK,
    Sm2Command.START_CHANNEL_LIST_MODE: Sm2Command.START_CHANNEL_LIST_MODE_ACK,
    Sm2Command.STOP_CHANNEL_LIST_MODE: Sm2Command.STOP_CHANNEL_LIST_MODE_ACK,
    Sm2Command.SINGLE_PULSE: Sm2Command.SINGLE_PULSE_ACK,
}


class Sm2Result(IntEnum):
    """Signed result byte of every ack (§3.3)."""

    OK = 0
    TRANSFER_ERROR = -1  # bad CRC or length
    PARAMETER_ERROR = -2  # value out of range, too many/few parameters
    WRONG_MODE = -3
    INCOMPATIBLE = -5  # InitAck only: protocol version not supported
    BUSY = -8


class Sm2StimulationErrorCode(IntEnum):
    EMERGENCY_SWITCH = -1  # pressed or not connected
    ELECTRODE = -2
    STIMULATION_MODULE = -3


class Sm2StimulationMode(IntEnum):
    START = 0
    INITIALISED = 1
    STARTED = 2


def _crc8_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c << 1 ^ 0x07) & 0xFF if c & 0x80 else c << 1 & 0xFF
        table.append(c)
    return tuple(table)


_CRC8 = _crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8, polynomial 0x07, init 0, no reflection, no final XOR (check("123456789") = 0xF4)."""
    c = 0
    for b in data:
        c = _CRC8[c ^ b]
    return c


def sm2_stuff(data: bytes) -> bytes:
    """Escape 0xF0, 0x0F and 0x81 as 0x81, b^0x55 (§3.1)."""
    out = bytearray()
    for b in data:
        if b in _SM2_ESCAPED:
            out += bytes((SM2_STUFFING, b ^ SM2_STUFFING_KEY))
        else:
            out.append(b)
    return bytes(out)


def sm2_unstuff(data: bytes) -> bytes | None:
    """Undo stuffing; an escape is honoured on any byte (tolerant of over-escaping encoders).
    None if the data ends on a lone escape byte."""
    out = bytearray()
    it = iter(data)
    for b in it:
        if b == SM2_STUFFING:
            nxt = next(it, None)
            if nxt is None:
                return None
            out.append(nxt ^ SM2_STUFFING_KEY)
        else:
            out.append(b)
    return bytes(out)


@dataclass(frozen=True)
class Sm2Frame:
    """One framed SM2 packet after CRC/length checks and unstuffing."""

    packet_number: int
    command: int
    data: bytes


def encode_sm2_frame(packet_number: int, command: int, data: bytes = b"") -> bytes:
    """``F0 81 crc^55 81 len^55 stuffed(PN CMD DATA) 0F``; CRC and length cover the stuffed bytes."""
    _check_int("packet_number", packet_number, 0, 255)
    _check_int("command", command, 0, 255)
    if len(data) > 60:
        raise ScienceModeRangeError("data", len(data), "at most 60 bytes")
    body = sm2_stuff(bytes([packet_number, command]) + data)
    return (
        bytes(
            [
                SM2_START,
                SM2_STUFFING,
                crc8(body) ^ SM2_STUFFING_KEY,
                SM2_STUFFING,
                len(body) ^ SM2_STUFFING_KEY,
            ]
        )
        + body
        + bytes([SM2_STOP])
    )


class Sm2FrameDecoder:
    """Frames from an SM2 byte stream (either direction). The escaped CRC and length (``81 x`` at the
    fixed positions 1-4) may be 0xF0/0x0F without breaking framing; elsewhere 0xF0 always starts and
    0x0F always ends a packet. A start byte inside a packet discards what came before (§3.3); bytes
    outside packets are counted in ``discarded_bytes``."""

    def __init__(self) -> None:
        self.bad_packets = 0
        self.discarded_bytes = 0
        self._buf = bytearray()
        self._in_packet = False
        self._escaped = False

    def _bad(self, kind: str, reason: str, raw: bytes, frame_head: bytes | None = None) -> BadPacket:
        self.bad_packets += 1
        pn = cmd = None
        if frame_head is not None and len(frame_head) >= 2:
            pn, cmd = frame_head[0], frame_head[1]
        return BadPacket(kind, reason, raw, command=cmd, packet_number=pn)  # type: ignore[arg-type]

    def feed(self, data: bytes) -> list[Sm2Frame | BadPacket]:
        out: list[Sm2Frame | BadPacket] = []
        for b in data:
            if not self._in_packet:
                if b == SM2_START:
                    self._in_packet, self._escaped = True, False
                    self._buf = bytearray([b])
                else:
                    self.discarded_bytes += 1
                continue
            if self._escaped and len(self._buf) in (2, 4):
                # the escaped CRC/length may take any value, 0xF0 and 0x0F included
                self._buf.append(b)
                self._escaped = False
            elif b == SM2_START:
                out.append(self._bad("truncated", "start byte inside a packet", bytes(self._buf)))
                self._buf = bytearray([b])
                self._escaped = False
            elif b == SM2_STOP:
                self._buf.append(b)
                self._in_packet = self._escaped = False
                out.append(self._decode(bytes(self._buf)))
                self._buf = bytearray()
            else:
                # in the body an escaped byte is never 0xF0/0x0F (stuffing yields A5/5A/D4), so those
                # two stay delimiters there: a stray 0x81 cannot swallow the next packet's start
                self._buf.append(b)
                self._escaped = b == SM2_STUFFING and not self._escaped
            if self._in_packet and len(self._buf) > SM2_MAX_PACKET_BYTES:
                out.append(
                    self._bad(
                        "oversize", f"no stop byte within {SM2_MAX_PACKET_BYTES} bytes", bytes(self._buf)
                    )
                )
                self._in_packet = False
                self._buf = bytearray()
        return out

    def _decode(self, raw: bytes) -> Sm2Frame | BadPacket:
        # raw = F0 81 c 81 l body... 0F
        if len(raw) < 8 or raw[1] != SM2_STUFFING or raw[3] != SM2_STUFFING:
            return self._bad("length", "too short or CRC/length not escaped", raw)
        crc, length, body = raw[2] ^ SM2_STUFFING_KEY, raw[4] ^ SM2_STUFFING_KEY, raw[5:-1]
        plain = sm2_unstuff(body)
        if length != len(body):
            return self._bad("length", f"length field {length} != {len(body)} bytes", raw, plain)
        if crc != crc8(body):
            return self._bad("checksum", f"CRC 0x{crc:02X} != 0x{crc8(body):02X}", raw, plain)
        if plain is None or len(plain) < 2:
            return self._bad("length", "no packet number and command", raw, plain)
        return Sm2Frame(plain[0], plain[1], plain[2:])


# ── SM2 messages ─────────────────────────────────────────────────────────────────────────────────
# Every message carries its packet number: the PC numbers its commands, the device echoes that number
# in the ack and numbers what it originates (Init, StimulationError) with its own counter.


@dataclass(frozen=True)
class Sm2Init:  # device → PC, repeated every 500 ms until InitAck
    packet_number: int
    version: int = 1


@dataclass(frozen=True)
class Sm2InitAck:  # PC → device
    packet_number: int
    result: int = Sm2Result.OK


@dataclass(frozen=True)
class Sm2UnknownCommand:  # device → PC
    packet_number: int
    command: int


@dataclass(frozen=True)
class Sm2Watchdog:  # PC → device keep-alive
    packet_number: int


@dataclass(frozen=True)
class Sm2GetStimulationMode:
    packet_number: int


@dataclass(frozen=True)
class Sm2GetStimulationModeAck:
    packet_number: int
    result: int
    mode: Sm2StimulationMode | None = None  # present only when result == 0


@dataclass(frozen=True)
class Sm2InitChannelListMode:
    packet_number: int
    config: ChannelListConfig
    channel_execution: int = 0  # 0: fixed 1.5 ms slots, 1: as fast as possible ("not yet implemented")
    t1_code: int | None = None  # set by the decoder (the raw MSI, 0 = one-shot mode)


@dataclass(frozen=True)
class Sm2StartChannelListMode:
    """Start or update: settings in the order of the initialised channels."""

    packet_number: int
    settings: tuple[PulseSetting, ...]


@dataclass(frozen=True)
class Sm2StopChannelListMode:
    packet_number: int


@dataclass(frozen=True)
class Sm2SinglePulse:
    packet_number: int
    channel: int
    setting: PulseSetting


@dataclass(frozen=True)
class Sm2Ack:
    """InitChannelListModeAck / StartChannelListModeAck / StopChannelListModeAck / SinglePulseAck."""

    packet_number: int
    command: Sm2Command
    result: int = Sm2Result.OK


@dataclass(frozen=True)
class Sm2StimulationError:  # device → PC
    packet_number: int
    code: int


Sm2Message = (
    Sm2Init
    | Sm2InitAck
    | Sm2UnknownCommand
    | Sm2Watchdog
    | Sm2GetStimulationMode
    | Sm2GetStimulationModeAck
    | Sm2InitChannelListMode
    | Sm2StartChannelListMode
    | Sm2StopChannelListMode
    | Sm2SinglePulse
    | Sm2Ack
    | Sm2StimulationError
)

_ACK_COMMANDS = frozenset(SM2_ACK_FOR.values()) - {Sm2Command.GET_STIMULATION_MODE_ACK}


def _signed(b: int) -> int:
    return b - 256 if b > 127 else b


def _result_byte(field: str, value: int) -> int:
    return _check_int(field, value, -128, 127) & 0xFF


def _sm2_pulse_bytes(setting: PulseSetting) -> bytes:
    return bytes(
        [int(setting.mode), setting.pulse_width_us >> 8, setting.pulse_width_us & 0xFF, setting.current_ma]
    )


def encode_sm2_init_channel_list(
    packet_number: int, config: ChannelListConfig, channel_execution: int = 0
) -> bytes:
    t1_code, t2_code = validate_channel_list(config, "sm2")
    _check_int("channel_execution", channel_execution, 0, 1)
    data = bytes(
        [
            config.low_frequency_factor,
            _mask(config.channels),
            _mask(config.low_frequency_channels),
            t2_code,
            t1_code >> 8,
            t1_code & 0xFF,
            channel_execution,
        ]
    )
    return encode_sm2_frame(packet_number, Sm2Command.INIT_CHANNEL_LIST_MODE, data)


def encode_sm2_start(
    packet_number: int, config: ChannelListConfig, settings: Mapping[int, PulseSetting]
) -> bytes:
    """StartChannelListMode (start and every update) for exactly the initialised channels."""
    ordered = _validate_settings(config, settings, "sm2")
    data = b"".join(_sm2_pulse_bytes(s) for s in ordered)
    return encode_sm2_frame(packet_number, Sm2Command.START_CHANNEL_LIST_MODE, data)


def encode_sm2_single_pulse(packet_number: int, channel: int, setting: PulseSetting) -> bytes:
    validate_pulse(channel, setting)
    data = bytes(
        [channel - 1, setting.pulse_width_us >> 8, setting.pulse_width_us & 0xFF, setting.current_ma]
    )
    return encode_sm2_frame(packet_number, Sm2Command.SINGLE_PULSE, data)


def encode_sm2(message: Sm2Message, config: ChannelListConfig | None = None) -> bytes:
    """Encode any SM2 message (either direction). A Start needs the ``config`` of the last init."""
    pn = message.packet_number
    m = message
    if isinstance(m, Sm2InitChannelListMode):
        return encode_sm2_init_channel_list(pn, m.config, m.channel_execution)
    if isinstance(m, Sm2StartChannelListMode):
        if config is None:
            raise ScienceModeRangeError("config", None, "the ChannelListConfig of the last init")
        if len(m.settings) != len(config.channels):
            raise ScienceModeRangeError("settings", len(m.settings), f"{len(config.channels)} settings")
        return encode_sm2_start(pn, config, dict(zip(config.channels, m.settings, strict=False)))
    if isinstance(m, Sm2SinglePulse):
        return encode_sm2_single_pulse(pn, m.channel, m.setting)
    if isinstance(m, Sm2Init):
        return encode_sm2_frame(pn, Sm2Command.INIT, bytes([_check_int("version", m.version, 0, 255)]))
    if isinstance(m, Sm2InitAck):
        return encode_sm2_frame(pn, Sm2Command.INIT_ACK, bytes([_result_byte("result", m.result)]))
    if isinstance(m, Sm2UnknownCommand):
        return encode_sm2_frame(
            pn, Sm2Command.UNKNOWN_COMMAND, bytes([_check_int("command", m.command, 0, 255)])
        )
    if isinstance(m, Sm2Watchdog):
        return encode_sm2_frame(pn, Sm2Command.WATCHDOG)
    if isinstance(m, Sm2GetStimulationMode):
        return encode_sm2_frame(pn, Sm2Command.GET_STIMULATION_MODE)
    if isinstance(m, Sm2GetStimulationModeAck):
        data = bytes([_result_byte("result", m.result)])
        if m.result == Sm2Result.OK:
            if m.mode is None:
                raise ScienceModeRangeError("mode", None, "0 start, 1 initialised, 2 started (result OK)")
            data += bytes([Sm2StimulationMode(m.mode)])
        return encode_sm2_frame(pn, Sm2Command.GET_STIMULATION_MODE_ACK, data)
    if isinstance(m, Sm2StopChannelListMode):
        return encode_sm2_frame(pn, Sm2Command.STOP_CHANNEL_LIST_MODE)
    if isinstance(m, Sm2Ack):
        if m.command not in _ACK_COMMANDS:
            raise ScienceModeRangeError(
                "command", m.command, ", ".join(c.name for c in sorted(_ACK_COMMANDS))
            )
        return encode_sm2_frame(pn, m.command, bytes([_result_byte("result", m.result)]))
    if isinstance(m, Sm2StimulationError):
        return encode_sm2_frame(pn, Sm2Command.STIMULATION_ERROR, bytes([_result_byte("code", m.code)]))
    raise TypeError(f"not an SM2 message: {message!r}")


_SM2_DATA_LENGTH: dict[int, tuple[int, ...]] = {
    Sm2Command.INIT: (1,),
    Sm2Command.INIT_ACK: (1,),
    Sm2Command.UNKNOWN_COMMAND: (1,),
    Sm2Command.WATCHDOG: (0,),
    Sm2Command.GET_STIMULATION_MODE: (0,),
    Sm2Command.GET_STIMULATION_MODE_ACK: (1, 2),
    Sm2Command.INIT_CHANNEL_LIST_MODE: (7,),
    Sm2Command.STOP_CHANNEL_LIST_MODE: (0,),
    Sm2Command.SINGLE_PULSE: (4,),
    Sm2Command.STIMULATION_ERROR: (1,),
    **{c: (1,) for c in _ACK_COMMANDS},
}


def decode_sm2_frame(frame: Sm2Frame) -> Sm2Message | BadPacket:
    """A frame to a typed message. Wrong parameter counts give a BadPacket('parameter'); values are not
    range-checked here (the device side decides what it accepts)."""
    pn, cmd, d = frame.packet_number, frame.command, frame.data
    raw = encode_sm2_frame(pn, cmd, d) if len(d) <= 60 else d

    def bad(kind: str, reason: str) -> BadPacket:
        return BadPacket(kind, reason, raw, command=cmd, packet_number=pn)  # type: ignore[arg-type]

    try:
        command = Sm2Command(cmd)
    except ValueError:
        return bad("unknown_command", f"unknown command {cmd}")
    if command == Sm2Command.START_CHANNEL_LIST_MODE:
        if not d or len(d) % 4 or len(d) > 4 * len(CHANNELS):
            return bad(
                "parameter", f"{command.name}: {len(d)} data bytes is not 4 per channel for 1..8 channels"
            )
        settings = []
        for i in range(0, len(d), 4):
            if d[i] > PulseMode.TRIPLET:
                return bad("parameter", f"{command.name}: mode {d[i]} is not 0/1/2")
            settings.append(PulseSetting(d[i + 3], d[i + 1] << 8 | d[i + 2], PulseMode(d[i])))
        return Sm2StartChannelListMode(pn, tuple(settings))
    if len(d) not in _SM2_DATA_LENGTH[command]:
        return bad("parameter", f"{command.name}: {len(d)} data bytes, expected {_SM2_DATA_LENGTH[command]}")
    if command == Sm2Command.INIT:
        return Sm2Init(pn, d[0])
    if command == Sm2Command.INIT_ACK:
        return Sm2InitAck(pn, _signed(d[0]))
    if command == Sm2Command.UNKNOWN_COMMAND:
        return Sm2UnknownCommand(pn, d[0])
    if command == Sm2Command.WATCHDOG:
        return Sm2Watchdog(pn)
    if command == Sm2Command.GET_STIMULATION_MODE:
        return Sm2GetStimulationMode(pn)
    if command == Sm2Command.GET_STIMULATION_MODE_ACK:
        result = _signed(d[0])
        if (result == Sm2Result.OK) != (len(d) == 2):
            return bad("parameter", "GET_STIMULATION_MODE_ACK: mode byte present iff result is 0")
        if len(d) == 2 and d[1] not in tuple(Sm2StimulationMode):
            return bad("parameter", f"GET_STIMULATION_MODE_ACK: mode {d[1]} is not 0/1/2")
        return Sm2GetStimulationModeAck(pn, result, Sm2StimulationMode(d[1]) if len(d) == 2 else None)
    if command == Sm2Command.INIT_CHANNEL_LIST_MODE:
        lff, active, lf, ipi, msi = d[0], d[1], d[2], d[3], d[4] << 8 | d[5]
        config = ChannelListConfig(_unmask(active), msi * 0.5 + 1.0, ipi * 0.5 + 1.5, _unmask(lf), lff)
        return Sm2InitChannelListMode(pn, config, d[6], msi)
    if command == Sm2Command.STOP_CHANNEL_LIST_MODE:
        return Sm2StopChannelListMode(pn)
    if command == Sm2Command.SINGLE_PULSE:
        return Sm2SinglePulse(pn, d[0] + 1, PulseSetting(d[3], d[1] << 8 | d[2]))
    if command == Sm2Command.STIMULATION_ERROR:
        return Sm2StimulationError(pn, _signed(d[0]))
    return Sm2Ack(pn, command, _signed(d[0]))


class Sm2Decoder:
    """SM2 byte stream (either direction) to typed messages; bad frames come out as BadPacket."""

    def __init__(self) -> None:
        self.frames = Sm2FrameDecoder()
        self._bad_messages = 0

    @property
    def bad_packets(self) -> int:
        return self.frames.bad_packets + self._bad_messages

    @property
    def discarded_bytes(self) -> int:
        return self.frames.discarded_bytes

    def feed(self, data: bytes) -> list[Sm2Message | BadPacket]:
        out: list[Sm2Message | BadPacket] = []
        for item in self.frames.feed(data):
            if isinstance(item, BadPacket):
                out.append(item)
                continue
            msg = decode_sm2_frame(item)
            if isinstance(msg, BadPacket):
                self._bad_messages += 1
            out.append(msg)
        return out
