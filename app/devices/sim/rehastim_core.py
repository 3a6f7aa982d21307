"""Pure simulator core of a Hasomed RehaStim (ScienceMode 1 or 2): bytes in, reply bytes out.

No I/O and no clock: the owner passes the time ``t`` (s) with every call and wraps the core on a pty.
It decodes every packet with the codecs of ``app.wire.sciencemode``, checks checksums/CRC, ranges and
the timing rules, answers with acks / error acks, and keeps a log of what was delivered.

Behaviour the reference leaves open, as chosen here (docs/fes.md):
- SM1: a bad checksum, an out-of-range value or a timing violation gets the error ack of that Ident;
  an update before a (valid) init or after a stop gets an error ack; a single pulse while the channel
  list runs gets an error ack; a stop always gets an OK ack; a rejected init leaves the previous state.
- SM2: commands before InitAck get WRONG_MODE; Stop always OK and returns to mode START (re-init needed);
  SinglePulse only outside CCL; one-shot mode (MSI 0) is refused as a parameter error; a pulse width
  below 20 µs with a non-zero current is delivered as 20 µs (firmware note in the reference §4).
- An update takes effect at the time it is received (the device applies it from the next pass, ≤ t1 later).
- No host: SM1 keeps stimulating for ever (it has no watchdog; a closed link or a dead PC changes nothing),
  SM2 stops 1.2 s after its last valid packet (its watchdog) and announces itself again. Issue #25's
  dead man's switch (app/devices/fes_guardian.py) is tested against exactly this.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

from app.wire.sciencemode import (
    CHANNELS,
    CHANNELS_TEXT,
    MAX_CURRENT_MA,
    MAX_PULSE_WIDTH_US,
    SM2_ACK_FOR,
    SM2_INIT_REPETITION_S,
    SM2_MIN_DELIVERED_PULSE_WIDTH_US,
    SM2_PROTOCOL_MAX_CURRENT_MA,
    SM2_WATCHDOG_TIMEOUT_S,
    BadPacket,
    ChannelListConfig,
    PulseMode,
    PulseSetting,
    ScienceModeRangeError,
    Sm1CommandDecoder,
    Sm1Ident,
    Sm1Init,
    Sm1SinglePulse,
    Sm1Stop,
    Sm1Update,
    Sm2Ack,
    Sm2Command,
    Sm2Decoder,
    Sm2GetStimulationMode,
    Sm2GetStimulationModeAck,
    Sm2Init,
    Sm2InitAck,
    Sm2InitChannelListMode,
    Sm2Message,
    Sm2Result,
    Sm2SinglePulse,
    Sm2StartChannelListMode,
    Sm2StimulationError,
    Sm2StimulationErrorCode,
    Sm2StimulationMode,
    Sm2StopChannelListMode,
    Sm2UnknownCommand,
    Sm2Watchdog,
    encode_sm1_ack,
    encode_sm2,
    validate_channel_list,
)

_OFF = PulseSetting(0, 0)


class StimulationObserver(Protocol):
    """Who hears what the simulated stimulator delivers (the simulated patient, issue #32): every change of a
    channel's delivered current or pulse width, at the device's time ``t``; 0 mA = the channel is off."""

    def stimulation(self, t: float, channel: int, current_ma: float, pulse_width_us: float) -> None: ...


@dataclass(frozen=True)
class StimulationLogEntry:
    """From ``t`` on ``channel`` delivers this (kind 'ccl'), or one pulse was delivered at ``t``."""

    t: float
    channel: int
    current_ma: int
    pulse_width_us: int
    mode: PulseMode = PulseMode.SINGLE
    kind: Literal["ccl", "single"] = "ccl"


class RehaStimSimCore:
    def __init__(self, protocol: Literal["sm1", "sm2"] = "sm1", *, init_version: int = 1,
                 observer: StimulationObserver | None = None) -> None:
        if protocol not in ("sm1", "sm2"):
            raise ValueError(f"protocol = {protocol!r}; allowed: 'sm1' or 'sm2'")
        self.protocol = protocol
        self.observer = observer
        self.log: list[StimulationLogEntry] = []
        self.events: list[tuple[float, str]] = []  # refusals, faults, watchdog: for tests and the UI
        self.config: ChannelListConfig | None = None
        self.running = False
        self._state: dict[int, PulseSetting] = {}  # delivered
        self._commanded: dict[int, PulseSetting] = {}
        self._no_ack: int | None = 0  # packets still to ignore; None = all
        self._error_ack: int = 0
        self._error_result: int = Sm2Result.BUSY
        self._dead = False  # SM1 after the emergency stop: no acks until power_cycle()
        self._blocked_channels: set[int] = set()  # SM1 electrode error: pulses not delivered
        self._sm1 = Sm1CommandDecoder()
        self._sm2 = Sm2Decoder()
        # SM2 session
        self.init_version = init_version
        self.initialised = False
        self.mode = Sm2StimulationMode.START
        self._device_pn = 0
        self._next_init_t: float | None = 0.0 if protocol == "sm2" else None
        self._last_valid_t = 0.0
        self.watchdog_expiries = 0

    # ── observation ─────────────────────────────────────────────────────────────────────────────
    def channel_state(self) -> dict[int, PulseSetting]:
        """What each channel delivers now (channels at zero omitted)."""
        return {ch: s for ch, s in sorted(self._state.items()) if s.current_ma > 0}

    @property
    def bad_packets(self) -> int:
        return self._sm1.bad_packets if self.protocol == "sm1" else self._sm2.bad_packets

    # ── faults ──────────────────────────────────────────────────────────────────────────────────
    def inject_no_ack(self, count: int | None = 1) -> None:
        """Ignore the next ``count`` packets entirely (None: every packet until clear_faults)."""
        self._no_ack = count

    def inject_error_ack(self, count: int = 1, result: int = Sm2Result.BUSY) -> None:
        """Refuse the next ``count`` commands with an error ack (SM2: ``result``), without executing them."""
        self._error_ack, self._error_result = count, result

    def inject_electrode_error(self, t: float, channel: int = 1) -> bytes:
        """SM2: stop, go to START and send StimulationError −2. SM1 cannot report it: the channel's pulses
        are silently blocked (the skin-resistance check) until clear_faults()."""
        if self.protocol == "sm1":
            self._blocked_channels.add(channel)
            self.events.append((t, f"electrode error on channel {channel} (not reported by SM1)"))
            self._apply(t, self._commanded)
            return b""
        return self._stimulation_error(t, Sm2StimulationErrorCode.ELECTRODE)

    def press_emergency_stop(self, t: float) -> bytes:
        """SM2: stop and send StimulationError −1. SM1: the device turns off: stimulation stops and nothing
        answers until power_cycle()."""
        if self.protocol == "sm1":
            self._stop(t)
            self._dead = True
            self.events.append((t, "emergency stop: device off"))
            return b""
        return self._stimulation_error(t, Sm2StimulationErrorCode.EMERGENCY_SWITCH)

    def clear_faults(self) -> None:
        self._no_ack, self._error_ack = 0, 0
        self._blocked_channels.clear()

    def power_cycle(self, t: float) -> None:
        self.__init__(self.protocol, init_version=self.init_version, observer=self.observer)  # type: ignore[misc]
        self._next_init_t = t if self.protocol == "sm2" else None

    # ── the byte interface ──────────────────────────────────────────────────────────────────────
    def handle_bytes(self, data: bytes, t: float) -> bytes:
        """Feed PC bytes received at time ``t``; return what the device sends back (including any periodic
        SM2 Init that became due)."""
        if self.protocol == "sm1":
            return self._handle_sm1(data, t)
        out = bytearray(self.tick(t))
        for item in self._sm2.feed(data):
            if self._swallow():
                continue
            out += self._sm2_reply(item, t)
        return bytes(out)

    def next_event_time(self) -> float | None:
        """When the device next acts on its own (ScienceMode 2: its watchdog's expiry, a repeated Init), on the
        clock of ``t``; None when it only answers (ScienceMode 1)."""
        if self.protocol == "sm1":
            return None
        if self.initialised:
            return self._last_valid_t + SM2_WATCHDOG_TIMEOUT_S + 1e-4  # expired strictly after the timeout
        return self._next_init_t

    def tick(self, t: float) -> bytes:
        """Time passes: the SM2 watchdog may expire, and Init is repeated every 500 ms until InitAck."""
        if self.protocol == "sm1":
            return b""
        if self.initialised and t - self._last_valid_t > SM2_WATCHDOG_TIMEOUT_S:
            self.watchdog_expiries += 1
            self.events.append((t, "watchdog expired: stimulation stopped"))
            self._stop(t)
            self.initialised = False
            self._next_init_t = t
        out = bytearray()
        if not self.initialised and self._next_init_t is not None and t >= self._next_init_t:
            out += encode_sm2(Sm2Init(self._next_device_pn(), self.init_version))
            self._next_init_t = t + SM2_INIT_REPETITION_S
        return bytes(out)

    # ── shared state changes ────────────────────────────────────────────────────────────────────
    def _delivered(self, ch: int, s: PulseSetting) -> PulseSetting:
        if ch in self._blocked_channels:
            return PulseSetting(0, 0, s.mode)
        if (
            self.protocol == "sm2"
            and s.current_ma > 0
            and s.pulse_width_us < SM2_MIN_DELIVERED_PULSE_WIDTH_US
        ):
            return PulseSetting(s.current_ma, SM2_MIN_DELIVERED_PULSE_WIDTH_US, s.mode)
        return s

    def _apply(self, t: float, commanded: dict[int, PulseSetting]) -> None:
        self._commanded = dict(commanded)
        new = {ch: self._delivered(ch, s) for ch, s in commanded.items()}
        for ch in sorted(set(new) | set(self._state)):
            before, after = self._state.get(ch, _OFF), new.get(ch, _OFF)
            if (before.current_ma, before.pulse_width_us, before.mode) != (
                after.current_ma,
                after.pulse_width_us,
                after.mode,
            ):
                self.log.append(
                    StimulationLogEntry(t, ch, after.current_ma, after.pulse_width_us, after.mode)
                )
                if self.observer is not None:
                    self.observer.stimulation(t, ch, after.current_ma, after.pulse_width_us)
        self._state = new

    def _stop(self, t: float) -> None:
        self._apply(t, {})
        self.running = False
        self.mode = Sm2StimulationMode.START
        self.config = None

    def _swallow(self) -> bool:
        if self._dead:
            return True
        if self._no_ack is None:
            return True
        if self._no_ack > 0:
            self._no_ack -= 1
            return True
        return False

    def _take_error_ack(self) -> bool:
        if self._error_ack > 0:
            self._error_ack -= 1
            return True
        return False

    def _refuse(self, t: float, why: str) -> None:
        self.events.append((t, why))

    @staticmethod
    def _check_pulse(channel: int, s: PulseSetting, max_current: int) -> str:
        if channel not in CHANNELS:
            return f"channel {channel} outside {CHANNELS_TEXT}"
        if s.current_ma > max_current:
            return f"channel {channel}: {s.current_ma} mA > {max_current} mA"
        if s.pulse_width_us > MAX_PULSE_WIDTH_US:
            return f"channel {channel}: {s.pulse_width_us} µs > {MAX_PULSE_WIDTH_US} µs"
        return ""

    # ── ScienceMode 1 ───────────────────────────────────────────────────────────────────────────
    def _handle_sm1(self, data: bytes, t: float) -> bytes:
        out = bytearray()
        for item in self._sm1.feed(data):
            if self._swallow():
                continue
            if isinstance(item, BadPacket):
                self._refuse(t, f"SM1 bad packet: {item.reason}")
                if item.command is not None:
                    out += encode_sm1_ack(item.command, False)
                continue
            ident = {
                Sm1Init: Sm1Ident.INIT,
                Sm1Update: Sm1Ident.UPDATE,
                Sm1Stop: Sm1Ident.STOP,
                Sm1SinglePulse: Sm1Ident.SINGLE_PULSE,
            }[type(item)]
            if self._take_error_ack():
                self._refuse(t, f"injected error ack for {ident.name}")
                out += encode_sm1_ack(ident, False)
                continue
            why = self._sm1_execute(item, t)
            if why:
                self._refuse(t, f"SM1 {ident.name} refused: {why}")
            out += encode_sm1_ack(ident, not why)
        return bytes(out)

    def _sm1_execute(self, item: Sm1Init | Sm1Update | Sm1Stop | Sm1SinglePulse, t: float) -> str:
        if isinstance(item, Sm1Init):
            try:
                validate_channel_list(item.config, "sm1")
            except ScienceModeRangeError as exc:
                self._sm1.update_channels = self.config.channels if self.config else None
                return str(exc)
            self.config, self.running = item.config, True
            self._apply(t, {ch: _OFF for ch in item.config.channels})
            return ""
        if isinstance(item, Sm1Update):
            if not self.running or self.config is None:
                return "no channel list running (init first)"
            if len(item.settings) != len(self.config.channels):
                return f"{len(item.settings)} channel settings for {len(self.config.channels)} channels"
            commanded = dict(zip(self.config.channels, item.settings, strict=True))
            for ch, s in commanded.items():
                why = self._check_pulse(ch, s, MAX_CURRENT_MA)
                if why:
                    return why
            try:
                validate_channel_list(self.config, "sm1", (s.mode for s in item.settings))
            except ScienceModeRangeError as exc:
                return str(exc)
            self._apply(t, commanded)
            return ""
        if isinstance(item, Sm1Stop):
            self._stop(t)
            return ""
        if self.running:
            return "single pulse while the channel list runs"
        why = self._check_pulse(item.channel, item.setting, MAX_CURRENT_MA)
        if why:
            return why
        self._log_single(t, item.channel, item.setting)
        return ""

    def _log_single(self, t: float, channel: int, s: PulseSetting) -> None:
        d = self._delivered(channel, s)
        if d.current_ma > 0:
            self.log.append(StimulationLogEntry(t, channel, d.current_ma, d.pulse_width_us, d.mode, "single"))

    # ── ScienceMode 2 ───────────────────────────────────────────────────────────────────────────
    def _next_device_pn(self) -> int:
        pn = self._device_pn
        self._device_pn = (pn + 1) % 256
        return pn

    def _stimulation_error(self, t: float, code: Sm2StimulationErrorCode) -> bytes:
        self._stop(t)
        self.events.append((t, f"stimulation error {code.name}: stimulation stopped"))
        return encode_sm2(Sm2StimulationError(self._next_device_pn(), code))

    def _sm2_reply(self, item: Sm2Message | BadPacket, t: float) -> bytes:
        if isinstance(item, BadPacket):
            self._refuse(t, f"SM2 bad packet: {item.reason}")
            if item.kind == "unknown_command" and item.command is not None:
                return encode_sm2(Sm2UnknownCommand(item.packet_number or 0, item.command))
            if item.command is None or item.packet_number is None:
                return b""
            try:
                command = Sm2Command(item.command)
            except ValueError:
                return b""
            result = Sm2Result.PARAMETER_ERROR if item.kind == "parameter" else Sm2Result.TRANSFER_ERROR
            return self._ack(item.packet_number, command, result)
        self._last_valid_t = t  # any valid packet feeds the watchdog
        if isinstance(item, Sm2InitAck):
            if item.result == Sm2Result.OK:
                self.initialised, self._next_init_t = True, None
            return b""
        if isinstance(
            item, Sm2Init | Sm2Ack | Sm2GetStimulationModeAck | Sm2StimulationError | Sm2UnknownCommand
        ):
            cmd = {
                Sm2Init: Sm2Command.INIT,
                Sm2GetStimulationModeAck: Sm2Command.GET_STIMULATION_MODE_ACK,
                Sm2StimulationError: Sm2Command.STIMULATION_ERROR,
                Sm2UnknownCommand: Sm2Command.UNKNOWN_COMMAND,
            }.get(type(item))
            if isinstance(item, Sm2Ack):
                cmd = item.command
            return encode_sm2(Sm2UnknownCommand(item.packet_number, int(cmd or 0)))  # device-only commands
        if isinstance(item, Sm2Watchdog):
            return b""
        pn = item.packet_number
        command = {
            Sm2GetStimulationMode: Sm2Command.GET_STIMULATION_MODE,
            Sm2InitChannelListMode: Sm2Command.INIT_CHANNEL_LIST_MODE,
            Sm2StartChannelListMode: Sm2Command.START_CHANNEL_LIST_MODE,
            Sm2StopChannelListMode: Sm2Command.STOP_CHANNEL_LIST_MODE,
            Sm2SinglePulse: Sm2Command.SINGLE_PULSE,
        }[type(item)]
        if not self.initialised:
            self._refuse(t, f"SM2 {command.name} before InitAck")
            return self._ack(pn, command, Sm2Result.WRONG_MODE)
        if self._take_error_ack():
            self._refuse(t, f"injected error ack for {command.name}")
            return self._ack(pn, command, self._error_result)
        result, why = self._sm2_execute(item, t)
        if why:
            self._refuse(t, f"SM2 {command.name} refused: {why}")
        return self._ack(pn, command, result)

    def _ack(self, pn: int, command: Sm2Command, result: int) -> bytes:
        ack = SM2_ACK_FOR.get(command)
        if ack is None:
            return b""
        if ack == Sm2Command.GET_STIMULATION_MODE_ACK:
            return encode_sm2(
                Sm2GetStimulationModeAck(pn, result, self.mode if result == Sm2Result.OK else None)
            )
        return encode_sm2(Sm2Ack(pn, ack, result))

    def _sm2_execute(self, item: Sm2Message, t: float) -> tuple[int, str]:
        ok, param, wrong = Sm2Result.OK, Sm2Result.PARAMETER_ERROR, Sm2Result.WRONG_MODE
        if isinstance(item, Sm2GetStimulationMode):
            return ok, ""
        if isinstance(item, Sm2InitChannelListMode):
            if self.mode == Sm2StimulationMode.STARTED:
                return wrong, "init while the channel list runs"
            if item.t1_code == 0:
                return param, "one-shot mode (MSI 0) is not supported"
            if item.channel_execution not in (0, 1):
                return param, f"channel execution {item.channel_execution} not 0/1"
            try:
                validate_channel_list(item.config, "sm2")
            except ScienceModeRangeError as exc:
                return param, str(exc)
            self.config, self.mode = item.config, Sm2StimulationMode.INITIALISED
            return ok, ""
        if isinstance(item, Sm2StartChannelListMode):
            if self.mode == Sm2StimulationMode.START or self.config is None:
                return wrong, "start before InitChannelListMode"
            if len(item.settings) != len(self.config.channels):
                return (
                    param,
                    f"{len(item.settings)} channel settings for {len(self.config.channels)} channels",
                )
            commanded = dict(zip(self.config.channels, item.settings, strict=True))
            for ch, s in commanded.items():
                why = self._check_pulse(ch, s, SM2_PROTOCOL_MAX_CURRENT_MA)
                if why:
                    return param, why
            try:
                validate_channel_list(self.config, "sm2", (s.mode for s in item.settings))
            except ScienceModeRangeError as exc:
                return param, str(exc)
            self.mode, self.running = Sm2StimulationMode.STARTED, True
            self._apply(t, commanded)
            return ok, ""
        if isinstance(item, Sm2StopChannelListMode):
            self._stop(t)
            return ok, ""
        if isinstance(item, Sm2SinglePulse):
            if self.mode == Sm2StimulationMode.STARTED:
                return wrong, "single pulse while the channel list runs"
            why = self._check_pulse(item.channel, item.setting, SM2_PROTOCOL_MAX_CURRENT_MA)
            if why:
                return param, why
            self._log_single(t, item.channel, item.setting)
            return ok, ""
        return param, f"unexpected {item!r}"  # pragma: no cover - every PC command is handled above
