"""RehaStim FES driver (ScienceMode 1 or 2) and its simulated device.

The driver runs a loaded :class:`~app.core.fes_profile.FesProfile` on the stimulator's Continuous Channel
List: every main period t1 it computes each channel's target (profile × live scale factors, at the
elapsed time or at the movement phase fed by :meth:`FesDriver.set_phase`), follows it within the start
ramp and the rate of increase (decreases at once), passes the whole update through
``SafetySupervisor.check_fes_update`` — the one gate to the encoder — and writes it. Every command's
ack is checked; an error ack, a missing ack (``ack_timeout_s``) or a device-reported error is a fault:
Stop is sent, the user is told (``fault`` signal + alarm) and stimulation must be started again.

Stop goes out at once, from the calling thread, on every exit path: :meth:`stop_stimulation` (stop
button, script), the e-stop action ("FES stop") and the safe-state actions (script end, app close),
a fault, the driver ending or losing its link, and the LINarm or physiological link being lost while
stimulating (:func:`create` subscribes to those drivers' events).

Names: ``QThread.start()`` and ``DeviceDriver.stop(timeout_s)`` already mean "run / end the driver
thread", so stimulation is started and stopped with :meth:`start_stimulation` /
:meth:`stop_stimulation`. ``start("source")`` and ``stop("reason")`` (with a string) are aliases.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import serial
from PySide6.QtCore import QThread, Signal

from app.core import journal, streams
from app.core.bus import BusItem, Channel, StreamBus, StreamSpec
from app.core.config import FesDevice
from app.core.fes_profile import MAX_SCALE, FesProfile
from app.core.links import simulator_link
from app.devices.command_queue import CommandQueue, CommandQueueClosed, CommandStatus, Priority
from app.devices.driver import DeviceDriver
from app.devices.fes_guardian import FesGuardian, GuardianError
from app.devices.fes_guardian import available as fes_guardian_available
from app.devices.sim.base import SerialSimulator
from app.devices.transport import SerialSettings, SerialTransport, Transport
from app.safety.fes_limits import ChannelCaps, FesLimiter, FesLimits, FesUpdate, rms_current_ma
from app.safety.supervisor import AlarmLevel, SafetyError
from app.wire.sciencemode import (
    CHANNELS,
    SM2_KEEPALIVE_PERIOD_S,
    SM2_MIN_DELIVERED_PULSE_WIDTH_US,
    BadPacket,
    ChannelListConfig,
    PulseMode,
    PulseSetting,
    ScienceModeRangeError,
    Sm1Ack,
    Sm1AckDecoder,
    Sm1Ident,
    Sm2Ack,
    Sm2Decoder,
    Sm2Init,
    Sm2InitAck,
    Sm2Result,
    Sm2StimulationError,
    Sm2StimulationErrorCode,
    Sm2StopChannelListMode,
    Sm2UnknownCommand,
    Sm2Watchdog,
    channel_list_config_for,
    encode_sm1_init,
    encode_sm1_stop,
    encode_sm1_update,
    encode_sm2,
    encode_sm2_init_channel_list,
    encode_sm2_start,
)

if TYPE_CHECKING:
    from app.devices.registry import DeviceContext, DeviceHandle
    from app.safety.supervisor import SafetySupervisor

log = logging.getLogger(__name__)

Protocol = Literal["sm1", "sm2"]

# The link settings are fixed by the device (reference §1), not a user choice.
SERIAL_SETTINGS: dict[str, SerialSettings] = {
    "sm1": SerialSettings(115200, serial.EIGHTBITS, serial.PARITY_NONE, serial.STOPBITS_TWO, rtscts=True),
    "sm2": SerialSettings(460800, serial.EIGHTBITS, serial.PARITY_EVEN, serial.STOPBITS_ONE, rtscts=False),
}
IDLE_PUBLISH_PERIOD_S = 0.1  # the channel stream keeps flowing (zeros) while not stimulating
# The loop sleeps in the link's read until the next update on the t1 grid is due, but never longer than this:
# a stimulation started from another thread begins within it. (A fixed 2 ms poll cost 0.9 % of a core idle, #16.)
MAX_WAKE_PERIOD_S = 0.01
MIN_WAKE_PERIOD_S = 0.0005
STOP_LOCK_WAIT_S = 0.02  # Stop waits at most this long for an update being written, then goes anyway
STOP_RESENDS = 3  # a Stop that is not acknowledged is sent again this many times
# The packet number of the SM2 Stop the guardian holds (app.devices.fes_guardian): it is only ever sent when the
# app has stopped serving the device, so its ack is counted as unexpected, never credited to a command.
GUARDIAN_SM2_PN = 255

_E = 1e-9


def _channel_fields() -> tuple[Channel, ...]:
    return tuple(Channel(f"current{ch}", "mA", f"Current ch {ch}") for ch in CHANNELS) + tuple(
        Channel(f"pulseWidth{ch}", "µs", f"Pulse width ch {ch}") for ch in CHANNELS
    )


FES_STREAM = StreamSpec(streams.FES_CHANNELS, _channel_fields(), 40.0)


@dataclass(frozen=True, slots=True)
class FesChannelsSample:
    """What was last sent to each channel (0 when not in the list or not stimulating)."""

    current1: float = 0.0
    current2: float = 0.0
    current3: float = 0.0
    current4: float = 0.0
    current5: float = 0.0
    current6: float = 0.0
    current7: float = 0.0
    current8: float = 0.0
    pulseWidth1: float = 0.0
    pulseWidth2: float = 0.0
    pulseWidth3: float = 0.0
    pulseWidth4: float = 0.0
    pulseWidth5: float = 0.0
    pulseWidth6: float = 0.0
    pulseWidth7: float = 0.0
    pulseWidth8: float = 0.0

    @classmethod
    def from_settings(cls, settings: dict[int, PulseSetting]) -> FesChannelsSample:
        kw: dict[str, float] = {}
        for ch, s in settings.items():
            kw[f"current{ch}"] = float(s.current_ma)
            kw[f"pulseWidth{ch}"] = float(s.pulse_width_us)
        return cls(**kw)


class FesError(RuntimeError):
    """The stimulator could not do what was asked; ``reason`` is a sentence for the user."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


@dataclass(frozen=True)
class ChannelStatus:
    """One channel as the FES panel shows it."""

    channel: int
    muscle: str
    peak_current_ma: float  # profile peak × scale: what the knob setting amounts to
    peak_pulse_width_us: float
    target_current_ma: float  # what the profile asks for now
    target_pulse_width_us: float
    sent_current_ma: int  # what was last sent
    sent_pulse_width_us: int
    cap_current_ma: float
    cap_pulse_width_us: float
    note: str  # off | following | start ramp | rate-limited | r.m.s. limit


@dataclass
class _Pending:
    """A command waiting for its ack (SM1: matched by Ident in order; SM2: by packet number)."""

    key: int
    what: str
    sent_at: float
    done: threading.Event = field(default_factory=threading.Event)
    ok: bool | None = None
    problem: str = ""
    waited: bool = False  # a caller is blocked on it and reports the failure itself


_SM2_ERRORS = {
    Sm2StimulationErrorCode.EMERGENCY_SWITCH: "the stimulator's emergency switch is pressed (or not connected)",
    Sm2StimulationErrorCode.ELECTRODE: "electrode error (check the electrodes and cables)",
    Sm2StimulationErrorCode.STIMULATION_MODULE: "stimulation module error",
}


def scale_clamp_text(knob: str, applied: float, reason: str) -> str:
    """What the clinician reads when a scale knob stopped at its cap (the ``fes_scale`` record's ``reason``)."""
    return f"{knob.replace('_', '-')} scale stops at {applied:.2f}: {reason}"


def _sm2_result_text(result: int) -> str:
    try:
        return Sm2Result(result).name.lower().replace("_", " ")
    except ValueError:
        return f"error {result}"


class FesDriver(DeviceDriver):
    """The RehaStim driver. Public methods are thread-safe."""

    streams = (FES_STREAM,)
    # The loop runs real-time, just below the LINarm's (20, its heartbeat 21): its passes are the FES guardian's
    # heartbeats (app/devices/fes_guardian.py, 0.3 s), and at normal priority, with the cores busy, the thread was
    # measured runnable and not run for 155-511 ms (the guardian stopped the therapy; the interpreter lock was not
    # the cause); at 19, the longest gap was 97 ms at load 13-17 (docs/decisions.md, #38 session 12). It wakes at
    # most every MAX_WAKE_PERIOD_S and holds the lock briefly each time.
    realtime_priority = 19

    # The Qt faces of the driver's journal records, emitted by the same call that records them (_record); the
    # window takes the records from its adapter.
    fault = Signal(str)  # a fault stopped (or prevented) stimulation; shown to the user
    stimulation_changed = Signal(bool)
    scale_clamped = Signal(str, float, str)  # knob ("current" | "pulse_width"), applied factor, why
    RECORD_SIGNALS: ClassVar[dict[str, str]] = {
        journal.FES_FAULT: "fault", journal.FES_STARTED: "stimulation_changed",
        journal.FES_STOPPED: "stimulation_changed", journal.FES_SCALE: "scale_clamped"}

    def __init__(
        self,
        transport: Transport,
        supervisor: SafetySupervisor,
        *,
        protocol: Protocol = "sm1",
        ack_timeout_s: float = 0.5,
        bus: StreamBus | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if protocol not in SERIAL_SETTINGS:
            raise ValueError(f"protocol = {protocol!r}; allowed: 'sm1' or 'sm2'")
        super().__init__(streams.FES, transport, bus=bus, read_timeout_s=MAX_WAKE_PERIOD_S)
        self.supervisor = supervisor
        self.protocol: Protocol = protocol
        self.ack_timeout_s = ack_timeout_s
        self.clock = clock
        self._lock = threading.RLock()  # state below; never held while waiting for an ack
        self._pn_lock = threading.Lock()
        self._pn = 0
        self._profile: FesProfile | None = None
        self._ccl: ChannelListConfig | None = None
        self._stimulating = False
        self._stop_generation = 0
        self._generation_lock = threading.Lock()  # a stop's "has anyone stopped since?" and its count, as one step
        self._started_at = 0.0
        self._next_update = 0.0
        self._next_publish = 0.0
        self._phase: float | None = None
        self._pw_override: float | None = None
        self._sent: dict[int, PulseSetting] = {}
        self._changed_at: dict[int, tuple[float, float]] = {}
        self._targets: dict[int, tuple[float, float]] = {}
        self._notes: dict[int, str] = {}
        self._pending: list[_Pending] = []
        self._stop_resends = 0
        self._sm1_acks = Sm1AckDecoder()
        self._sm2 = Sm2Decoder()
        self._sm2_ready = False
        self._last_write = 0.0
        self._driver_thread: int | None = None
        self.last_fault = ""
        self.unexpected_acks = 0
        # The dead man's switch (app.devices.fes_guardian): armed while stimulating, fed from this driver's
        # thread. ``create`` starts one and requires it; a driver built bare (unit tests) runs without.
        self.guardian: FesGuardian | None = None
        self.require_guardian = False
        # Start's path (#29): the channel list's init and start wait for the stimulator's acks on this queue's
        # thread, never on the caller's (the GUI's). Stop is written at once from any thread (stop_stimulation);
        # the channel-list updates and keep-alives stay on the driver thread's t1 grid.
        self.commands = CommandQueue(streams.FES, idle_exit_s=1.0)
        self.district_channels: dict[str, int] = {}  # district -> chosen channel (set_district_channels)

    # ================================================================== public API (any thread)
    @property
    def stimulating(self) -> bool:
        return self._stimulating

    @property
    def profile(self) -> FesProfile | None:
        return self._profile

    @property
    def channel_list(self) -> ChannelListConfig | None:
        return self._ccl

    @property
    def current_scale(self) -> float:
        return self._profile.current_scale if self._profile else 1.0

    @property
    def pulse_width_scale(self) -> float:
        return self._profile.pulse_width_scale if self._profile else 1.0

    @property
    def pulse_width_override(self) -> float | None:
        return self._pw_override

    @property
    def started_at(self) -> float:
        """Clock time (s) of the last start of stimulation (time profiles count from here)."""
        return self._started_at

    @property
    def device_ready(self) -> bool:
        """Connected, and for SM2 the device has announced itself (Init answered)."""
        return self.connected and (self.protocol == "sm1" or self._sm2_ready)

    @property
    def limiter(self) -> FesLimiter:
        lim = self.supervisor.fes_limiter
        if lim is None:
            raise FesError("no FES limits are configured")
        return lim

    def set_district_channels(self, channels: Mapping[str, int]) -> None:
        """The patient's chosen electrode combination per muscular district (issue #32): the channel a profile
        that names a district stimulates, from the next ``load_profile``."""
        self.district_channels = dict(channels)
        self.supervisor.record(journal.FES_DISTRICT_CHANNELS, channels=dict(channels))

    def load_profile(self, profile: FesProfile, source: str = "") -> None:
        """Use ``profile`` (with its own scale factors) from the next start. Refused while stimulating,
        when the channel list cannot be built at its frequency, or when its peaks exceed the limits. A profile
        naming districts is put on their chosen channels (``set_district_channels``). ``source``: who loads it
        (refused while another holds the stimulator, issue #36)."""
        _check_lease(self.supervisor, "load profile", source)
        if self._stimulating:
            raise FesError("stop stimulation before loading another profile")
        if profile.districts:
            try:
                profile = profile.resolve_districts(self.district_channels)
            except ValueError as exc:  # FesProfileError: no combination chosen, or a channel used twice
                raise FesError(str(getattr(exc, "problem", exc))) from exc
        ccl = self._channel_list_for(profile)
        self._check_within_limits(profile, ccl, self._pw_override, "load profile")
        with self._lock:
            self._profile, self._ccl = profile, ccl
            self._targets, self._notes = {}, {}
        self.supervisor.record(journal.FES_PROFILE_LOADED, name=profile.name, channels=list(ccl.channels),
                              frequency_hz=ccl.frequency_hz)

    def submit_start(self, source: str = "") -> CommandStatus:
        """Start running the loaded profile, without waiting: returns at once with a status. The quick checks
        (e-stop, profile, link, limits) are made here and a refusal fails the status at once (SafetyError /
        FesError, nothing sent); the channel list's init and start, which wait for the stimulator's acks, run on
        the FES command queue's thread. The status completes (None) once stimulation runs, or fails with why
        not. A Stop from any thread meanwhile (its generation) cancels the start."""
        try:
            if self._driver_thread == threading.get_ident() or threading.get_ident() == self._queue_ident():
                raise FesError("start_stimulation must not be called from the FES driver's threads")
            if self._stimulating:
                return CommandStatus.done_now("start", None, source, written=False)
            self._check_start(source)
        except (SafetyError, FesError) as exc:
            return CommandStatus.failed("start", exc, source)
        generation = self._stop_generation  # a Stop after this click wins, even before the queue takes it
        status = self.commands.submit("start", lambda _s: self._start_now(source, generation), source=source,
                                      exclusive=False)
        if status.done() and isinstance(status.exception(0), CommandQueueClosed):
            return CommandStatus.failed("start", FesError("the stimulator is not connected"), source)
        return status

    def start_stimulation(self, source: str = "") -> None:
        """:meth:`submit_start` and wait for the outcome (scripts, tests; never the GUI thread). Raises
        SafetyError (limits, e-stop) or FesError (no profile, device not ready, init refused or not
        acknowledged)."""
        status = self.submit_start(source)
        try:
            status.result(4 * self.ack_timeout_s + 5.0)  # init + start, each bounded by ack_timeout_s
        except CommandQueueClosed as exc:
            raise FesError(f"stimulation not started: {exc}") from exc
        except TimeoutError as exc:
            if status.done():
                raise
            status.cancel()
            self.stop_stimulation("the start did not finish", source)
            raise FesError("stimulation did not start in time; Stop was sent") from exc

    def _check_start(self, source: str) -> None:
        """The start's checks that need no reply from the stimulator (any thread)."""
        if self.supervisor.estop_latched:
            raise self.supervisor.refuse(source, "stimulation refused: the emergency stop is latched; reset it first")
        _check_lease(self.supervisor, "start", source)
        profile, ccl = self._profile, self._ccl
        if profile is None or ccl is None:
            raise FesError("no stimulation profile is loaded")
        if not self.connected:
            raise FesError("the stimulator is not connected")
        if not self.device_ready:
            raise FesError("the stimulator has not announced itself yet (no ScienceMode 2 Init received)")
        self._check_within_limits(profile, ccl, self._pw_override, source)

    def _start_now(self, source: str, generation: int) -> None:
        """Initialise the channel list and start (the FES command queue's thread: it waits for acks)."""
        if self._stimulating:
            return
        if generation != self._stop_generation:
            raise FesError("stimulation was stopped while it was starting")
        self._check_start(source)  # again: the e-stop or the link may have changed while it was queued
        profile, ccl = self._profile, self._ccl
        assert profile is not None and ccl is not None  # _check_start
        self._arm_guardian()  # before the first byte that could start stimulation
        limiter = self.limiter
        with self._lock:
            now = self.clock()
            limiter.start(now)
            zeros = {ch: PulseSetting(0, 0, profile.channels[ch].mode) for ch in ccl.channels}
        try:
            if self.protocol == "sm1":
                self._send_and_wait(Sm1Ident.INIT, "channel list init", lambda _pn: encode_sm1_init(ccl))
            else:
                self._send_and_wait(None, "channel list init",
                                    lambda pn: encode_sm2_init_channel_list(pn, ccl))
                self.supervisor.check_fes_update(FesUpdate(ccl, zeros), self.clock(), source or "fes start")
                self._send_and_wait(None, "channel list start", lambda pn: encode_sm2_start(pn, ccl, zeros))
        except (FesError, SafetyError) as exc:
            reason = exc.reason
            self._send_stop()
            if self.guardian is not None:
                self.guardian.disarm()
            with self._lock:
                limiter.stop()
            self.supervisor.record(journal.FES_START_FAILED, reason=reason, source=source)
            raise
        with self._lock:
            if generation != self._stop_generation:
                self._send_stop()
                if self.guardian is not None:
                    self.guardian.disarm()
                raise FesError("stimulation was stopped while it was starting")
            now = self.clock()
            self._sent = dict(zeros)
            self._changed_at = {ch: (now, now) for ch in ccl.channels}
            self._started_at = now
            self._next_update = now
            self._stimulating = True
            self._stop_resends = 0
            self.last_fault = ""
        self._record(journal.FES_STARTED, (True,), profile=profile.name, source=source,
                     current_scale=profile.current_scale, pulse_width_scale=profile.pulse_width_scale)

    def _queue_ident(self) -> int | None:
        thread = self.commands._thread
        return thread.ident if thread is not None else None

    def stop_stimulation(self, reason: str = "", source: str = "") -> CommandStatus:
        """Send Stop at once, from the calling thread (also when not stimulating: it is always safe): the
        stimulator's e-stop is never queued behind a start waiting for its acks. Never raises; the returned
        status is done, ``written`` when Stop left (its ack is checked by the driver loop, a missing one is a
        fault)."""
        was = self._end_generation()  # never None here: no generation to compare with
        return self._send_the_stop(bool(was), reason, source)

    def _stop_unless_stopped_since(self, generation: int, reason: str, source: str) -> bool:
        """Stop as :meth:`stop_stimulation` does — unless a stop came since ``generation`` (then a start after
        it may be running, which this late stop must not take back). True when it stopped."""
        was = self._end_generation(unless_stopped_since=generation)
        if was is None:
            return False
        self._send_the_stop(was, reason, source)
        return True

    def _end_generation(self, unless_stopped_since: int | None = None) -> bool | None:
        """End this stimulation's generation: the update loop sends nothing more, and a start queued before now
        does not begin. Whether it was stimulating; None, and nothing ended, when ``unless_stopped_since`` is
        given and a stop came since that generation."""
        with self._generation_lock:
            if unless_stopped_since is not None and unless_stopped_since != self._stop_generation:
                return None
            was = self._stimulating
            self._stimulating = False
            self._stop_generation += 1
            return was

    def _send_the_stop(self, was: bool, reason: str, source: str) -> CommandStatus:
        written = False
        got = self._lock.acquire(timeout=STOP_LOCK_WAIT_S)  # let an update being written finish first
        try:
            written = self._send_stop()
            if self.guardian is not None:
                self.guardian.disarm()  # after Stop went out: its duplicate of the link is closed at once
            if got:
                try:
                    if self.supervisor.fes_limiter is not None:
                        self.supervisor.fes_limiter.stop()
                except Exception:  # the limiter must not keep Stop from taking effect
                    log.exception("fes: limiter stop failed")
                self._sent = {}
                self._notes = {}
        finally:
            if got:
                self._lock.release()
        if was:
            self._record(journal.FES_STOPPED, (False,), reason=reason, source=source)
        return CommandStatus.done_now("stop", None, source, written=written, priority=Priority.ESTOP)

    def set_current_scale(self, factor: float, source: str = "") -> float:
        return self._set_scale("current", factor, source)

    def set_pulse_width_scale(self, factor: float, source: str = "") -> float:
        return self._set_scale("pulse_width", factor, source)

    def set_pulse_width_override(self, pulse_width_us: float | None, source: str = "") -> None:
        """Every channel's pulse width from now on (the assistance split, from a_f); None = the profile's.
        Refused (SafetyError) when it exceeds a channel's cap or, with the profile's peak currents, the
        r.m.s. limit."""
        if pulse_width_us is not None:
            _check_lease(self.supervisor, "pulse width override", source)
            if not (isinstance(pulse_width_us, int | float) and math.isfinite(pulse_width_us)
                    and pulse_width_us >= 0):
                raise self.supervisor.refuse(source, f"pulse width {pulse_width_us!r} µs is not a valid value")
            if self._profile is not None and self._ccl is not None:
                self._check_within_limits(self._profile, self._ccl, float(pulse_width_us), source)
        with self._lock:
            before, self._pw_override = self._pw_override, None if pulse_width_us is None else float(pulse_width_us)
        if (before is None) != (pulse_width_us is None):  # the therapist's pulse width overridden, or given back
            self.supervisor.record(journal.FES_PULSE_WIDTH_OVERRIDE, pulse_width_us=pulse_width_us, source=source)

    def set_clinical_caps(self, caps: Mapping[int, ChannelCaps]) -> None:
        """The patient's clinical caps (per channel) from now on. If the running profile exceeds them,
        stimulation is stopped and the user told why (the profile must be scaled down first)."""
        lim = self.limiter
        with self._lock:
            lim.set_limits(replace(lim.limits, clinical_caps=dict(caps)))
        self.supervisor.record(journal.FES_CLINICAL_CAPS, caps={ch: asdict(c) for ch, c in caps.items()})
        profile, ccl = self._profile, self._ccl
        if self._stimulating and profile is not None and ccl is not None:
            try:
                self._check_within_limits(profile, ccl, self._pw_override, "clinical caps")
            except SafetyError as exc:
                self._fault(f"The new clinical caps are below the running profile; stimulation stopped: {exc.reason}")

    def set_phase(self, phase: float | None) -> None:
        """The movement phase 0..1 (phase profiles); None: no movement, the profile's start (rest)."""
        if phase is not None and not math.isfinite(phase):
            return
        self._phase = None if phase is None else min(1.0, max(0.0, float(phase)))

    def channel_status(self) -> list[ChannelStatus]:
        with self._lock:
            profile, ccl = self._profile, self._ccl
            if profile is None or ccl is None:
                return []
            lim = self.supervisor.fes_limiter
            peaks = profile.peaks(scaled=True)
            out = []
            for ch in ccl.channels:
                cap_c, cap_w = lim.limits.caps_for(ch)[:2] if lim is not None else (0.0, 0.0)
                sent = self._sent.get(ch, PulseSetting(0, 0))
                target = self._targets.get(ch, (0.0, 0.0))
                peak_w = self._pw_override if self._pw_override is not None else peaks[ch][1]
                out.append(ChannelStatus(
                    ch, profile.channels[ch].muscle, peaks[ch][0], peak_w, target[0], target[1],
                    sent.current_ma, sent.pulse_width_us, cap_c, cap_w,
                    self._notes.get(ch, "following" if self._stimulating else "off"),
                ))
            return out

    def config_data(self) -> dict[str, Any]:
        """The script API's fes.getConfigData(): device, protocol, profile, scales and limits."""
        profile, ccl = self._profile, self._ccl
        lim = self.supervisor.fes_limiter
        data: dict[str, Any] = {
            "protocol": self.protocol,
            "connected": self.connected,
            "stimulating": self._stimulating,
            "profile": profile.name if profile else None,
            "axis": profile.axis if profile else None,
            "frequencyHz": ccl.frequency_hz if ccl else None,
            "channels": list(ccl.channels) if ccl else [],
            "currentScale": self.current_scale,
            "pulseWidthScale": self.pulse_width_scale,
            "pulseWidthOverride": self._pw_override,
        }
        if lim is not None:
            data["caps"] = {ch: dict(zip(("maxCurrent", "maxPulseWidth", "maxRmsCurrent"), lim.limits.caps_for(ch),
                                         strict=True)) for ch in CHANNELS}
        return data

    # -- contract aliases: start("source") / stop("reason"); the bare QThread/DeviceDriver forms still work
    def start(self, source: Any = None, *args: Any) -> None:  # type: ignore[override]
        """``start("who")`` starts stimulation (and waits for it: start_stimulation); ``start()`` (or a QThread
        priority) runs the driver thread."""
        if isinstance(source, str):
            self.start_stimulation(source)
        elif source is None:
            QThread.start(self)
        else:
            QThread.start(self, source, *args)

    def stop(self, reason: str | float | None = None, source: str = "") -> bool:  # type: ignore[override]
        """``stop("why")`` stops stimulation; ``stop()`` / ``stop(timeout_s)`` stops stimulation and then
        ends the driver thread (the DeviceDriver meaning)."""
        if isinstance(reason, str):
            self.stop_stimulation(reason, source)
            return True
        self.stop_stimulation("FES driver stopping", source or "fes driver")
        return super().stop(1.0 if reason is None else float(reason))

    # ================================================================== driver thread hooks
    def on_connect(self) -> None:
        self._driver_thread = threading.get_ident()
        self.commands.start()
        with self._lock:
            self._sm1_acks = Sm1AckDecoder()
            self._sm2 = Sm2Decoder()
            self._sm2_ready = False
            self._fail_pending("the link was re-opened")
        if self.protocol == "sm1":
            # SM1 has no watchdog: a device left stimulating by an earlier session is stopped now.
            self._send_stop()
        self._next_publish = self.clock()

    def on_disconnect(self) -> None:
        if self._stimulating:
            self.stop_stimulation("the FES link was lost", "fes driver")
            self._report_fault("The FES link was lost while stimulating; Stop was sent if the link allowed it")
        if self.guardian is not None:
            self.guardian.disarm()  # the link closes next: the guardian must not keep it open
        with self._lock:
            self._sm2_ready = False
            self._fail_pending("the link was lost")
        # A start waiting for its acks has just been failed (above); one still queued fails here.
        self.commands.close("the FES link was lost", error=FesError("the FES link was lost"))

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        faults: list[str] = []
        with self._lock:
            if self.protocol == "sm1":
                for item in self._sm1_acks.feed(data):
                    if isinstance(item, Sm1Ack):
                        faults += self._on_sm1_ack(item)
                    else:
                        log.warning("fes: %s", item.reason)
            else:
                for msg in self._sm2.feed(data):
                    faults += self._on_sm2_message(msg)
        for text in faults:
            self._fault(text)

    def on_tick(self, now_s: float) -> None:
        now = self.clock()
        if self.guardian is not None:
            self.guardian.heartbeat(now_s)  # this thread is alive and serving the stimulator
            tripped = self.guardian.tripped(now_s)
            if tripped:
                text = (f"The application stopped serving the stimulator ({tripped}): the FES guardian sent Stop; "
                        "stimulation must be started again")
                if self._stimulating:
                    self._fault(text)
                else:
                    self._report_fault(text)
            if self.guardian.dead:
                self._guardian_died()
        if self.protocol == "sm2" and self._sm2_ready and now - self._last_write >= SM2_KEEPALIVE_PERIOD_S:
            self._write_numbered(lambda pn: encode_sm2(Sm2Watchdog(pn)))
        self._check_ack_timeouts(now)
        if self._stimulating and now >= self._next_update:
            self._update(now)
        elif not self._stimulating and now >= self._next_publish:
            self._publish(now)
            self._next_publish = now + IDLE_PUBLISH_PERIOD_S
        due = self._next_update if self._stimulating else self._next_publish
        self.read_timeout_s = min(MAX_WAKE_PERIOD_S, max(MIN_WAKE_PERIOD_S, due - self.clock()))

    # ================================================================== internals
    def _guardian_died(self) -> None:
        """The guardian process died (driver thread; seen by its ``tripped``): watched like every other helper
        (#37). Stimulating, Stop goes out at once and a STOP alarm says why — without the guardian a frozen app
        would leave a ScienceMode 1 stimulator running (docs/fes.md, "The guardian is watched"). Either way the
        death is an alarm, and a new guardian is started on the command queue's thread, before any next start."""
        guardian = self.guardian
        if guardian is None:
            return
        was = self._stimulating
        if was:
            self.stop_stimulation("the FES guardian died", "fes driver")  # first: nothing below may delay Stop
        why = guardian.death()
        if not why:
            return  # already reported
        log.error("fes: %s", why)
        self.supervisor.record(journal.FES_GUARDIAN_DIED, reason=why, stimulating=was)
        if was:
            self._report_fault(f"The FES dead man's switch stopped working ({why}); stimulation stopped. It is "
                               "restarted before stimulation can start again")
        else:
            self.supervisor.raise_alarm(AlarmLevel.WARNING, "FES",
                                        f"The FES dead man's switch stopped working ({why}); it is restarted "
                                        "before stimulation can start again")
        self.commands.submit("restart the FES guardian", lambda _s: self._restart_guardian(), source="fes driver",
                             exclusive=False)

    def _restart_guardian(self) -> None:
        """A new guardian in place of a dead one (the FES command queue's thread: starting it takes ~50 ms)."""
        guardian = self.guardian
        if guardian is None or guardian.alive:
            return
        try:
            guardian.restart()
        except GuardianError as exc:
            log.error("fes: %s", exc)
            self.supervisor.record(journal.DEVICE_ERROR, device=streams.FES, error=str(exc))
            raise FesError(f"{exc}; stimulation refused") from exc
        log.info("fes: the FES guardian was restarted (pid %s)", guardian.pid)
        self.supervisor.record(journal.FES_GUARDIAN_RESTARTED, pid=guardian.pid)

    def _arm_guardian(self) -> None:
        """Hand the guardian this link's descriptor and this protocol's Stop; refuse to stimulate without it.
        A guardian that died is started again first."""
        guardian = self.guardian
        if guardian is None:
            if self.require_guardian:
                raise FesError("the FES guardian (the dead man's switch) is not running; stimulation refused")
            return
        if not guardian.alive:
            self._restart_guardian()
        fd = link_descriptor(self.transport)
        if fd is None:
            raise FesError("the FES guardian cannot reach this link; stimulation refused")
        stop = encode_sm1_stop() if self.protocol == "sm1" else encode_sm2(Sm2StopChannelListMode(GUARDIAN_SM2_PN))
        try:
            guardian.arm(fd, stop)
        except GuardianError as exc:
            raise FesError(f"{exc}; stimulation refused") from exc

    def _channel_list_for(self, profile: FesProfile) -> ChannelListConfig:
        largest = max(PulseMode(cp.mode).pulses for cp in profile.channels.values())
        try:
            return channel_list_config_for(profile.channels, profile.frequency_hz, self.protocol,
                                           largest_group=largest)
        except ScienceModeRangeError as exc:
            raise FesError(f"profile {profile.name!r} cannot run on this stimulator: {exc}") from exc

    def _check_within_limits(self, profile: FesProfile, ccl: ChannelListConfig, pw_override: float | None,
                             source: str) -> None:
        """Refuse (SafetyError) a profile whose scaled peaks exceed a cap or the r.m.s. limit."""
        lim = self.supervisor.fes_limiter
        if lim is None:
            raise self.supervisor.refuse(source, "stimulation refused: no FES limits are configured")
        for ch, (peak_c, peak_w) in profile.peaks(scaled=True).items():
            width = peak_w if pw_override is None else pw_override
            cap_c, cap_w, cap_rms = lim.limits.caps_for(ch)
            mode = profile.channels[ch].mode
            if peak_c > cap_c + _E:
                problem = f"channel {ch}: the profile reaches {peak_c:g} mA, above the cap of {cap_c:g} mA"
            elif width > cap_w + _E:
                problem = f"channel {ch}: the pulse width reaches {width:g} µs, above the cap of {cap_w:g} µs"
            elif (rms := rms_current_ma(peak_c, width, ccl.channel_frequency_hz(ch), mode)) > cap_rms + _E:
                problem = (f"channel {ch}: {peak_c:g} mA at {width:g} µs and {ccl.channel_frequency_hz(ch):g} Hz "
                           f"is {rms:.1f} mA r.m.s., above the limit of {cap_rms:g} mA")
            else:
                continue
            raise self.supervisor.refuse(source, f"profile {profile.name!r} refused: {problem}")

    def _set_scale(self, knob: Literal["current", "pulse_width"], factor: float, source: str) -> float:
        if not (isinstance(factor, int | float) and math.isfinite(factor) and factor >= 0):
            raise self.supervisor.refuse(source, f"{knob.replace('_', '-')} scale {factor!r} is not a valid "
                                                 "factor (0 or more)")
        held = self._profile
        if held is None or factor > (held.current_scale if knob == "current" else held.pulse_width_scale):
            _check_lease(self.supervisor, "scale", source)  # lowering is always allowed, whoever holds it
        with self._lock:
            profile, ccl = self._profile, self._ccl
            if profile is None or ccl is None:
                raise FesError("no stimulation profile is loaded")
            applied, reason = float(factor), ""
            if applied > MAX_SCALE:
                applied, reason = MAX_SCALE, f"the knob's maximum {MAX_SCALE:g}"
            lim = self.limiter
            peaks = profile.peaks(scaled=False)
            if knob == "current":
                other = profile.pulse_width_scale
                if self._pw_override is not None:  # the width is the override, not the scaled profile
                    peaks = {ch: (c, self._pw_override) for ch, (c, _w) in peaks.items()}
                    other = 1.0
            else:
                other = profile.current_scale
            modes = {ch: cp.mode for ch, cp in profile.channels.items()}
            # peaks far below what the device can resolve are 0 (and would underflow the limit arithmetic)
            peaks = {ch: (c if c >= 1e-6 else 0.0, w if w >= 1e-6 else 0.0) for ch, (c, w) in peaks.items()}
            try:
                clamp = lim.clamp_scale(knob, applied, other_scale=other, peaks=peaks, config=ccl, modes=modes)
            except ArithmeticError as exc:
                raise FesError(f"the {knob.replace('_', '-')} scale limit could not be computed ({exc}); "
                               "the scale is unchanged") from exc
            if clamp.clamped:
                applied, reason = clamp.scale, clamp.reason
            applied = min(applied, MAX_SCALE)
            self._profile = (profile.with_scales(current_scale=applied) if knob == "current"
                             else profile.with_scales(pulse_width_scale=applied))
        self._record(journal.FES_SCALE, (knob, applied, scale_clamp_text(knob, applied, reason)) if reason else None,
                     knob=knob, requested=factor, applied=applied, reason=reason, source=source)
        return applied

    def _targets_at(self, profile: FesProfile, now: float) -> dict[int, tuple[float, float]]:
        if profile.axis == "time":
            x = now - self._started_at
        else:
            x = 0.0 if self._phase is None else self._phase
        values = profile.value_at(x)
        if self._pw_override is not None:
            values = {ch: (c, self._pw_override) for ch, (c, _w) in values.items()}
        return values

    def _follow(self, ch: int, target: tuple[float, float], now: float, mode: PulseMode,
                ccl: ChannelListConfig) -> tuple[PulseSetting, str]:
        """The setting nearest the target that the limits allow now: the start-ramp ceiling and the rate
        of increase bound a rise (as FesLimiter measures them); a fall is never limited."""
        lim = self.limiter
        limits = lim.limits
        ceil_c, ceil_w = lim.ceiling(ch, now)
        _cap_c, _cap_w, cap_rms = limits.caps_for(ch)
        prev = self._sent.get(ch, PulseSetting(0, 0, mode))
        t_c, t_w = self._changed_at.get(ch, (now, now))
        step_c = limits.max_current_rise_ma_s * min(now - t_c, limits.max_step_interval_s)
        step_w = limits.max_pulse_width_rise_us_s * min(now - t_w, limits.max_step_interval_s)
        want_c, want_w = round(target[0]), round(target[1])
        note = "following"
        c, w = want_c, want_w
        if c > prev.current_ma and c > prev.current_ma + math.floor(step_c + _E):
            c, note = prev.current_ma + math.floor(step_c + _E), "rate-limited"
        if w > prev.pulse_width_us and w > prev.pulse_width_us + math.floor(step_w + _E):
            w, note = prev.pulse_width_us + math.floor(step_w + _E), "rate-limited"
        if c > math.floor(ceil_c + _E) or w > math.floor(ceil_w + _E):
            c, w = min(c, math.floor(ceil_c + _E)), min(w, math.floor(ceil_w + _E))
            note = "start ramp" if lim.ceiling(ch, now + 3600)[0] > ceil_c + _E else "at cap"
        if self.protocol == "sm2" and c > 0 and w < SM2_MIN_DELIVERED_PULSE_WIDTH_US:
            # RehaStim 2 delivers pw < 20 µs as 20 µs: hold the current until the width is deliverable, so
            # the device never gives more than was commanded
            c, note = 0, "below 20 µs"
        freq = ccl.channel_frequency_hz(ch)
        if c > 0 and rms_current_ma(c, w, freq, mode) > cap_rms + _E:
            c = math.floor(cap_rms / math.sqrt(2e-6 * w * freq * PulseMode(mode).pulses) + _E)
            note = "r.m.s. limit"
        return PulseSetting(max(0, c), max(0, w), mode), note

    def _update(self, now: float) -> None:
        """One channel-list update (driver thread)."""
        finished = False
        problem = ""
        with self._lock:
            profile, ccl = self._profile, self._ccl
            if not self._stimulating or profile is None or ccl is None:
                return
            generation = self._stop_generation
            period = ccl.t1_ms / 1000.0
            self._next_update += period
            if self._next_update < now:  # fell behind (a stall): resume on the grid from now
                self._next_update = now + period
            if profile.axis == "time" and now - self._started_at > profile.end + period:
                finished = True
            elif self.protocol == "sm1" and any(p.key == Sm1Ident.UPDATE for p in self._pending):
                # SM1 acks carry no number: with one update in flight an ack cannot be credited to the
                # wrong update, so a lost one ages until it times out (a few ms is normal; a period is not)
                return
            else:
                targets = self._targets_at(profile, now)
                settings: dict[int, PulseSetting] = {}
                notes: dict[int, str] = {}
                for ch in ccl.channels:
                    settings[ch], notes[ch] = self._follow(ch, targets[ch], now, profile.channels[ch].mode, ccl)
                try:
                    self.supervisor.check_fes_update(FesUpdate(ccl, settings), now, "fes profile")
                    if self.protocol == "sm1":
                        self._write_acked(Sm1Ident.UPDATE, "update", lambda _pn: encode_sm1_update(ccl, settings))
                    else:
                        self._write_acked(None, "update", lambda pn: encode_sm2_start(pn, ccl, settings))
                except SafetyError as exc:
                    problem = f"An FES update was refused and stimulation stopped: {exc.reason}"
                except ScienceModeRangeError as exc:
                    problem = f"An FES update could not be encoded and stimulation stopped: {exc}"
                else:
                    if not self._stimulating:  # stopped from inside the write (a fault ack)
                        return
                    for ch, s in settings.items():
                        old = self._sent.get(ch, PulseSetting(0, 0))
                        t_c, t_w = self._changed_at.get(ch, (now, now))
                        self._changed_at[ch] = (now if s.current_ma != old.current_ma else t_c,
                                                now if s.pulse_width_us != old.pulse_width_us else t_w)
                    self._sent = settings
                    self._targets = targets
                    self._notes = notes
        if finished:
            self.stop_stimulation("the time profile finished", "fes profile")
            return
        if problem:
            # Stopped meanwhile (an e-stop from another thread while this update was checked): the refusal is that
            # stop's consequence, not a fault — and a stop from here could land after the operator's reset and
            # take back the next start ("stimulation was stopped while it was starting").
            stopped_here = self._stop_unless_stopped_since(generation, problem, "fes driver")
            if stopped_here and not getattr(self.supervisor, "estop_latched", False):
                self._report_fault(problem)
            else:
                # Refused because the e-stop latched meanwhile (its own stop action sends Stop, its alarm says why):
                # no fault alarm of ours — its safe-state stop could land after the operator's reset.
                log.info("fes: an update refused as stimulation stopped (%s)", problem)
            return
        self._publish(now)

    def _publish(self, now: float) -> None:
        sent = self._sent if self._stimulating else {}
        self.publish(streams.FES_CHANNELS, now, FesChannelsSample.from_settings(sent))

    # -- writing
    def _next_pn(self) -> int:
        with self._pn_lock:
            pn = self._pn
            self._pn = (pn + 1) % 256
            return pn

    def _write_numbered(self, build: Callable[[int], bytes]) -> None:
        self.transport.write(build(self._next_pn()))
        self._last_write = self.clock()

    def _write_acked(self, ident: int | None, what: str, build: Callable[[int], bytes],
                     waited: bool = False) -> _Pending:
        """Register the expected ack, then write (the ack may arrive before write() returns)."""
        pn = self._next_pn() if ident is None else 0
        data = build(pn)
        pending = _Pending(pn if ident is None else ident, what, self.clock(), waited=waited)
        with self._lock:
            self._pending.append(pending)
        try:
            self.transport.write(data)
        except Exception:
            with self._lock:
                if pending in self._pending:
                    self._pending.remove(pending)
            raise
        self._last_write = self.clock()
        return pending

    def _send_and_wait(self, ident: int | None, what: str, build: Callable[[int], bytes]) -> None:
        try:
            pending = self._write_acked(ident, what, build, waited=True)
        except OSError as exc:
            raise FesError(f"could not send the {what}: {exc}") from exc
        if not pending.done.wait(self.ack_timeout_s):
            with self._lock:
                if pending in self._pending:
                    self._pending.remove(pending)
            raise FesError(f"the stimulator did not acknowledge the {what} within {self.ack_timeout_s:g} s")
        if not pending.ok:
            raise FesError(f"the stimulator refused the {what}: {pending.problem}")

    def _send_stop(self) -> bool:
        """Write Stop now; never raises (nothing to stop on a link that is gone). True when it was written."""
        if not self.transport.is_open and not self._stimulating:
            return False  # closed link, nothing running (e.g. the second Stop of a shutdown): nothing to say
        try:
            if self.protocol == "sm1":
                self._write_acked(Sm1Ident.STOP, "stop", lambda _pn: encode_sm1_stop())
            else:
                self._write_acked(None, "stop", lambda pn: encode_sm2(Sm2StopChannelListMode(pn)))
        except Exception as exc:
            log.warning("fes: Stop could not be sent: %s", exc)
            return False
        return True

    # -- acks and device messages (under the lock, driver thread); return fault texts
    def _resolve(self, match: Callable[[_Pending], bool], ok: bool, problem: str) -> _Pending | None:
        for pending in self._pending:
            if match(pending):
                self._pending.remove(pending)
                pending.ok, pending.problem = ok, problem
                pending.done.set()
                return pending
        self.unexpected_acks += 1
        return None

    def _ack_fault(self, pending: _Pending | None, problem: str) -> list[str]:
        if pending is None or pending.waited:
            return []
        if pending.what == "stop":
            return [f"The stimulator refused Stop ({problem}); switch it off if it is still stimulating"]
        return [f"The stimulator refused the {pending.what} ({problem}); stimulation stopped"]

    def _on_sm1_ack(self, ack: Sm1Ack) -> list[str]:
        pending = self._resolve(lambda p: p.key == ack.ident, ack.ok, "" if ack.ok else "error ack")
        if pending is None:
            log.warning("fes: unexpected SM1 ack %s", ack)
            return []
        return [] if ack.ok else self._ack_fault(pending, "error ack")

    def _on_sm2_message(self, msg: object) -> list[str]:
        if isinstance(msg, BadPacket):
            log.warning("fes: bad packet from the stimulator: %s", msg.reason)
            return []
        if isinstance(msg, Sm2Init):
            was_ready = self._sm2_ready
            try:
                self.transport.write(encode_sm2(Sm2InitAck(msg.packet_number, Sm2Result.OK)))
                self._last_write = self.clock()
                self._sm2_ready = True
            except OSError as exc:
                log.warning("fes: InitAck could not be sent: %s", exc)
            if self._stimulating:
                return ["The stimulator restarted (watchdog or power); stimulation stopped"]
            if was_ready:
                log.warning("fes: the stimulator announced itself again (watchdog or power cycle)")
            return []
        if isinstance(msg, Sm2Ack):
            ok = msg.result == Sm2Result.OK
            if msg.result == Sm2Result.WRONG_MODE and any(
                p.key == msg.packet_number and p.what == "stop" for p in self._pending
            ):
                ok = True  # Stop before the channel list was initialised: nothing was running
            text = _sm2_result_text(msg.result)
            pending = self._resolve(lambda p: p.key == msg.packet_number, ok, text)
            return [] if ok else self._ack_fault(pending, text)
        if isinstance(msg, Sm2StimulationError):
            why = _SM2_ERRORS.get(msg.code, f"stimulation error {msg.code}")  # type: ignore[call-overload]
            return [f"The stimulator stopped: {why}"]
        if isinstance(msg, Sm2UnknownCommand):
            return [f"The stimulator did not understand command {msg.command}; stimulation stopped"]
        return []

    def _check_ack_timeouts(self, now: float) -> None:
        late: list[_Pending] = []
        with self._lock:
            for pending in list(self._pending):
                if not pending.waited and now - pending.sent_at > self.ack_timeout_s:
                    self._pending.remove(pending)
                    late.append(pending)
        for pending in late:
            if pending.what == "stop":
                if self._stop_resends < STOP_RESENDS:
                    self._stop_resends += 1
                    self._send_stop()
                self._report_fault(f"The stimulator did not acknowledge Stop within {self.ack_timeout_s:g} s; "
                                   "check that it is on and connected")
            else:
                self._fault(f"The stimulator did not acknowledge the {pending.what} within "
                            f"{self.ack_timeout_s:g} s; stimulation stopped")

    def _fail_pending(self, why: str) -> None:
        for pending in self._pending:
            pending.ok, pending.problem = False, why
            pending.done.set()
        self._pending = []

    def _fault(self, text: str) -> None:
        """Stop, then tell the user."""
        self.stop_stimulation(text, "fes driver")
        self._report_fault(text)

    def _report_fault(self, text: str) -> None:
        if text == self.last_fault and not self._stimulating:
            log.info("fes: %s (again)", text)
            return
        self.last_fault = text
        log.error("fes: %s", text)
        self._record(journal.FES_FAULT, (text,), text=text)
        self.supervisor.raise_alarm(AlarmLevel.STOP, "FES", text)

    def _record(self, kind: str, signal_args: tuple[Any, ...] | None = None, **data: Any) -> None:
        """One of the stimulator's journal records (through the supervisor: origin ``safety``, as the session record
        has always had them) and, with ``signal_args``, its Qt face (``RECORD_SIGNALS``): one call, two faces."""
        self.supervisor.record(kind, **data)
        signal = self.RECORD_SIGNALS.get(kind)
        if signal is not None and signal_args is not None:
            getattr(self, signal).emit(*signal_args)


def _check_lease(supervisor: Any, what: str, source: str) -> None:
    """The stimulator's owner during a run (#36): SafetySupervisor.check_fes_command (a bare stand-in has none)."""
    check = getattr(supervisor, "check_fes_command", None)
    if check is not None:
        check(what, source)


def simulated_link_settings(protocol: Protocol) -> SerialSettings:
    """The device's settings without parity: a pty has no UART, and Linux refuses to re-apply PARENB to a
    pty (EINVAL on the next tcsetattr, e.g. when the read timeout changes)."""
    return replace(SERIAL_SETTINGS[protocol], parity=serial.PARITY_NONE)


def link_descriptor(transport: Any) -> int | None:
    """The OS descriptor under a transport's open link (a serial port, or a loopback socket), or None."""
    port = getattr(transport, "_port", None)
    if port is None:
        return None
    sock = getattr(port, "_sock", None)  # app.devices.transport._LoopbackPort
    try:
        if sock is not None:
            return int(sock.fileno())
        fileno = getattr(port, "fileno", None)  # pyserial's Serial (POSIX)
        return int(fileno()) if callable(fileno) else None
    except (OSError, ValueError, TypeError, AttributeError):
        return None


def watch_link(bus: StreamBus, source: str, fes: FesDriver, label: str) -> None:
    """Stop stimulation when device ``source`` disconnects or goes silent: a safety monitor, inline on the
    bus (it runs on the source's driver thread as the event is published, before any queued consumer)."""

    def on_event(item: BusItem) -> None:
        if not isinstance(item, journal.Record) or item.origin != source:
            return
        if item.kind in ("disconnected", "silent") and fes.stimulating:
            what = "was lost" if item.kind == "disconnected" else "went silent"
            text = f"The {label} link {what} while stimulating; stimulation stopped"
            fes.stop_stimulation(text, label)
            fes._report_fault(text + (f" ({item.detail})" if item.detail else ""))

    bus.subscribe_inline("safety", on_event, (), events=True)


def create(ctx: DeviceContext) -> DeviceHandle | None:
    from app.devices.registry import DeviceHandle
    from app.devices.sim.adapters import FES_POLL_S, RehaStimSimAdapter

    cfg: FesDevice = ctx.config
    if cfg.mode == "off":
        return None
    protocol: Protocol = cfg.protocol
    wanted = SERIAL_SETTINGS[protocol].baudrate
    if cfg.baudrate not in (wanted, FesDevice().baudrate):
        log.warning("fes: baudrate %d in the config is ignored; %s always runs at %d Bd",
                    cfg.baudrate, protocol, wanted)
    simulator = None
    url = cfg.port
    settings = SERIAL_SETTINGS[protocol]
    if cfg.mode == "simulated":
        link = simulator_link(ctx.runtime_dir, streams.FES)
        simulator = ctx.simulators.serial(
            streams.FES, streams.FES, lambda patient: SerialSimulator(
                streams.FES, lambda: RehaStimSimAdapter(protocol, observer=patient), link, tick_s=FES_POLL_S),
            protocol=protocol)
        url = simulator.url
        settings = simulated_link_settings(protocol)
    supervisor = ctx.supervisor
    if supervisor.fes_limiter is None:
        supervisor.fes_limiter = FesLimiter(FesLimits.from_config(ctx.safety.fes))
    driver = FesDriver(SerialTransport(url, settings), supervisor, protocol=protocol,
                       ack_timeout_s=cfg.ack_timeout_s, bus=ctx.bus)
    processes: list[Any] = []
    if fes_guardian_available():
        driver.require_guardian = True  # where it can run, never stimulate without it
        try:  # started with the app, so that a stimulation never waits for it
            driver.guardian = FesGuardian().start()
            processes.append(driver.guardian)
        except GuardianError as exc:
            log.error("fes: %s; stimulation will be refused", exc)
            supervisor.record(journal.DEVICE_ERROR, device=streams.FES, error=str(exc))
    else:  # Windows: SM2's own watchdog (1.2 s) only; SM1 stops only on Stop (docs/fes.md)
        log.warning("fes: no dead man's switch on this platform: a frozen app's stimulation is not stopped by it")
    ctx.add_stop_action("FES stop", lambda reason: driver.stop_stimulation(reason, "safety supervisor"))
    for name, label in ((streams.LINARM, "LINarm"), (streams.PHYSIO, "physiological sensors")):
        if name in ctx.peers:
            watch_link(ctx.bus, name, driver, label)
    return DeviceHandle(streams.FES, driver, simulator, {"safe_stop": lambda reason: driver.stop_stimulation(reason),
                                                   "processes": processes})
