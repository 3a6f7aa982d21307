"""LINarm2 driver: CmdMessenger frames ⇄ typed state samples and acknowledged commands.

Every command goes through :meth:`LinarmDriver.command`, the one place that encodes host frames,
and that place asks the safety supervisor first. Commands block until the controller's ACK (or
ERROR, raised as :class:`LinarmCommandError` with the controller's code) or a timeout; one is in
flight at a time, except the emergency stop's IDLE, which is written at once.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from PySide6.QtCore import Signal

from app.core import journal, streams
from app.core.bus import BusItem, Channel, SampleItem, StreamBus, StreamSpec
from app.core.config import LinarmDevice
from app.core.links import simulator_link
from app.devices.clock import DeviceClock
from app.devices.command_queue import CommandQueue, CommandQueueClosed, CommandStatus, Priority
from app.devices.driver import DeviceDriver
from app.devices.sim.base import SerialSimulator
from app.devices.transport import SerialSettings, SerialTransport, Transport, TransportError
from app.safety.supervisor import SafetyError
from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import ControlState, ReplyError

if TYPE_CHECKING:
    from app.devices.registry import DeviceContext, DeviceHandle
    from app.safety.supervisor import SafetySupervisor

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- samples
# Field names are the seed script API's (linarm.linarmVsaState.equilibriumPos, ...); units SI.
@dataclass(frozen=True, slots=True)
class LinarmStateSample:
    controlState: int
    controlMode: int
    homeState: int
    errorState: int
    triggerMode: int
    initialized: bool
    trajectoryType: int
    demo: bool
    virtualVsa: bool
    endstrokesDisabled: bool
    controllerTime: float  # s, controller clock
    timestamp: float = 0.0  # s, host monotonic clock: the controller's time of this state (app.devices.clock)


@dataclass(frozen=True, slots=True)
class MotorSample:
    index: int
    position: float
    velocity: float
    current: float
    target: float
    controllerTime: float
    timestamp: float = 0.0  # s, host monotonic clock (the controller's clock mapped)


@dataclass(frozen=True, slots=True)
class VsaSample:
    equilibriumPos: float  # the centre
    delta: float
    stiffness: float
    handlePos: float
    handleVel: float
    interactionForce: float
    controllerTime: float
    timestamp: float = 0.0  # s, host monotonic clock (the controller's clock mapped)

    @property
    def centre(self) -> float:
        return self.equilibriumPos


STATE_STREAM = StreamSpec(streams.LINARM_STATE, (
    Channel("controlState", "", "Control state"), Channel("controlMode", "", "Control mode"),
    Channel("homeState", "", "Home state"), Channel("errorState", "", "Error state"),
    Channel("triggerMode", "", "Trigger mode"), Channel("initialized", "", "Initialised"),
), 20.0)
VSA_STREAM = StreamSpec(streams.LINARM_VSA, (
    Channel("equilibriumPos", "m", "Centre (equilibrium)"), Channel("delta", "m", "Delta"),
    Channel("stiffness", "N/m", "Stiffness"), Channel("handlePos", "m", "Handle position"),
    Channel("handleVel", "m/s", "Handle velocity"), Channel("interactionForce", "N", "Interaction force"),
), 200.0)


def _motor_stream(i: int) -> StreamSpec:
    return StreamSpec(streams.LINARM_MOTORS[i], (
        Channel("position", "m", f"Motor {i} position"), Channel("velocity", "m/s", f"Motor {i} velocity"),
        Channel("current", "A", f"Motor {i} current"), Channel("target", "m", f"Motor {i} target"),
    ), 200.0)


# How long the reading loop may go without a pass before the heartbeat thread stops beating. Longer than the
# kernel stalls measured under load (#16), short enough that a wedged reader stops the robot within 0.75 s.
HEARTBEAT_READER_GRACE_S = 0.5
# A heartbeat written this long after the one before is said in the log (at most once a second, with the count
# since): the controller stops the motors after proto.WATCHDOG_TIMEOUT without one, and that stop must not read as
# a fault of the robot. Where the OS refuses the queue's thread real-time scheduling (a container without
# CAP_SYS_NICE, a user without rtprio), a busy machine delays it: measured on the 2-core machine at load 8, beats
# 0.15-0.27 s apart and the watchdog's stop in 3 of 14 homings; granted, none in 36.
HEARTBEAT_LATE_S = 1.5 * proto.HEARTBEAT_PERIOD
HEARTBEAT_LATE_LOG_EVERY_S = 1.0


class LinarmCommandError(RuntimeError):
    """The controller refused a command; ``code`` is its ReplyError."""

    def __init__(self, command: str, code: ReplyError, message: str = "") -> None:
        self.command = command
        self.code = code
        self.message = message
        detail = f": {message}" if message else ""
        super().__init__(f"LINarm refused {command}: {code.name}{detail}")


class LinarmTimeout(TimeoutError):
    pass


LIMITS_ATTEMPTS = 3  # apply_limits: tries of the whole (idempotent) sequence after a timeout
# Garbage on the link (bad frames, discarded bytes, undecodable frames) reaches the session record as counts,
# at most this often while it lasts and once more when the link closes: never one line per frame (#25).
GARBAGE_RECORD_PERIOD_S = 1.0


# emergency_idle waits this long for its IDLE to be written by the queue's thread (it is written ahead of anything
# queued; the bound only covers a wedged write), then reports it as not sent.
ESTOP_WRITE_BOUND_S = 0.1


@dataclass
class _Pending:
    """A command written and awaiting its ACK (at most one: the queue keeps commands exclusive)."""

    seq: int
    name: str
    status: CommandStatus
    source: str = ""
    args: dict[str, Any] | None = None


# ---------------------------------------------------------------------------------------------- driver
class LinarmDriver(DeviceDriver):
    streams = (STATE_STREAM, VSA_STREAM, _motor_stream(0), _motor_stream(1))
    # The reading loop runs real-time too: the heartbeat beats only while it passes (0.5 s), and at normal
    # priority it was measured stalling 0.5-0.6 s under load (#16). The FES driver runs just below (19: its
    # passes are the FES guardian's heartbeats); the other drivers stay at normal priority.
    realtime_priority = 20
    heartbeat_priority = 21  # the command queue's thread (it beats): it feeds the controller's 250 ms host watchdog
    controller_error = Signal(str)  # an ERROR_EVENT from the controller, as a sentence (the bus record's Qt face)
    EVENT_SIGNALS: ClassVar[dict[str, str]] = {journal.CONTROLLER_ERROR: "controller_error"}

    def __init__(self, transport: Transport, supervisor: SafetySupervisor, *,
                 stream_period_s: float = proto.DEFAULT_STREAM_PERIOD, command_timeout_s: float = 1.0,
                 heartbeat_period_s: float = proto.HEARTBEAT_PERIOD, bus: StreamBus | None = None,
                 silence_timeout_s: float | None = None) -> None:
        super().__init__(streams.LINARM, transport, bus=bus, silence_timeout_s=silence_timeout_s)
        self.supervisor = supervisor
        self.stream_period_s = stream_period_s
        self.command_timeout_s = command_timeout_s
        self.heartbeat_period_s = heartbeat_period_s
        self.decoder = CmdMessengerDecoder()
        # The controller's micros() (t_us, wrapping at 2**32 µs) mapped to the host's clock: every state sample
        # is stamped when the controller sampled it, not when the read that carried it returned (#27).
        self.clock = DeviceClock(wrap_s=proto.T_US_WRAP_S)
        self.firmware_version = ""
        self.protocol_errors = 0
        self._seq = 0
        self._pending: dict[int, _Pending] = {}  # by seq; written by the queue's thread, completed by the reader
        self.centre_target_m: float | None = None  # the last accepted moveCentreTo target (m)
        self._identify_seq: int | None = None
        self._identified = threading.Event()
        self._last_heartbeat = 0.0
        self._reader_alive = 0.0
        self._withheld = False  # the heartbeat withheld for a stale reading loop (said once an episode)
        self._late_beats = 0
        self._longest_late = 0.0
        self._late_logged_at = float("-inf")
        self._reader_ident: int | None = None
        self._beating = False
        # The one command path (#29): every write to the controller — commands, limits, handshake, heartbeat (its
        # periodic), e-stop IDLE — is made by this queue's thread, real-time at the heartbeat's priority.
        self.commands = CommandQueue(streams.LINARM, periodic=self._beat, period_s=heartbeat_period_s,
                                     realtime_priority=self.heartbeat_priority,
                                     on_timeout=self._on_command_timeout)
        self._envelope_locked = False  # per connection: the controller may have restarted in between
        self.envelope: dict[str, Any] = {}  # the controller's locked envelope, as its ACK reported it
        self._garbage_recorded = (0, 0, 0)  # (bad frames, discarded bytes, undecodable frames) last recorded
        self._garbage_recorded_at = 0.0
        self._last_error_logged = ("", 0.0)
        self._shared_seen: Any = None  # the transport's shared_with last alarmed about

    # ------------------------------------------------------------------ commands (any thread)
    def submit(self, name: str, *args: Any, source: str = "", priority: Priority = Priority.NORMAL,
               timeout_s: float | None = None) -> CommandStatus:
        """Queue ``name(*args)`` (seed API names and argument order) and return at once. The status holds the
        ACK's values, or fails with SafetyError (refused by the supervisor: nothing was sent), LinarmCommandError
        (the controller refused it), LinarmTimeout, TransportError (no link) or CommandQueueClosed; ValueError /
        TypeError for a name or arguments the protocol does not have (raised here, not through the status)."""
        spec = proto.COMMANDS_BY_NAME.get(name)
        if spec is None:
            raise ValueError(f"unknown LINarm command {name!r}")
        if len(args) != len(spec.args):
            names = ", ".join(a.name for a in spec.args)
            raise TypeError(f"{name} takes {len(spec.args)} argument(s) ({names}), got {len(args)}")
        named = {a.name: v for a, v in zip(spec.args, args, strict=True)}
        try:
            self.supervisor.check_robot_command(name, named, source)
        except SafetyError as exc:
            return CommandStatus.failed(name, exc, source, priority)
        if name == "moveCentreTo":  # where the robot is taking the handle: the exercise's target (3D view)
            self.centre_target_m = float(named["targetPos"])
        if not self.connected and priority != Priority.LINK:  # the handshake's own commands go before `connected`
            return CommandStatus.failed(name, TransportError("the LINarm is not connected"), source, priority)
        proto.encode_command(name, 0, *args)  # values the wire cannot carry are refused here, not on the wire
        timeout = self.command_timeout_s if timeout_s is None else timeout_s

        def write(status: CommandStatus) -> None:  # the queue's thread
            seq = self._next_seq()
            frame = proto.encode_command(name, seq, *args)
            self._pending[seq] = _Pending(seq, name, status, source, named)  # before the write: the ACK may win
            status.add_done_callback(lambda _s: self._pending.pop(seq, None))
            self.transport.write(frame)

        return self.commands.submit(name, write, source=source, priority=priority, exclusive=True,
                                    timeout_s=timeout)

    def command(self, name: str, *args: Any, source: str = "", timeout_s: float | None = None) -> dict[str, Any]:
        """:meth:`submit`, then wait for the ACK and return its values (scripts, the runner, tests; never the GUI
        thread). Raises what the status holds: SafetyError, LinarmCommandError, LinarmTimeout, TransportError."""
        if threading.get_ident() in (self._reader_ident, self._queue_ident()):
            raise RuntimeError("LinarmDriver.command must not wait on the driver's own threads; use submit")
        status = self.submit(name, *args, source=source, timeout_s=timeout_s)
        timeout = self.command_timeout_s if timeout_s is None else timeout_s
        # The queue completes every status (ACK, its timeout, the link lost, the queue closed); the bound here
        # only guards against a bug: the commands queued ahead may each take their own timeout first.
        try:
            return status.result(timeout + self.command_timeout_s * (self.commands.pending() + 1) + 5.0)
        except CommandQueueClosed as exc:
            raise TransportError(f"{name} not sent: {exc}") from exc
        except FutureTimeout as exc:
            if status.done():  # the status's own LinarmTimeout
                raise
            status.cancel()
            raise LinarmTimeout(f"LINarm did not acknowledge {name} within {timeout:.2f} s") from exc

    def command_async(self, name: str, *args: Any, source: str = "") -> CommandStatus:
        """The GUI's form: the same as :meth:`submit` (the status holds the ACK values or the error)."""
        return self.submit(name, *args, source=source)

    def apply_limits(self, limits: Any) -> CommandStatus:
        """Make the controller's own limits the configured ones (its defaults may be wider): speed and
        acceleration of jog ramps and timed moves, the force limit, the allowed range.

        The first call on a connection first sends the site's limits (the supervisor's configuration) and locks
        them as the controller's safety envelope (``lockEnvelope``): until the controller restarts nothing can
        widen them, whatever this host does later. ``limits`` (e.g. a patient's narrower profile) then follow,
        inside the envelope. Returns at once: the commands go one after the other through the queue at LINK
        priority (each after the previous one's ACK); the status fails with the first refusal and holds the
        locked envelope (the ACK's values) on success. A timeout (a busy link at connect) tries the whole
        (idempotent) sequence again, LIMITS_ATTEMPTS times in all."""
        overall = CommandStatus("apply_limits", "limits", Priority.LINK)
        attempts = {"n": 0}

        def steps() -> list[tuple[str, tuple[Any, ...]]]:
            out: list[tuple[str, tuple[Any, ...]]] = []
            if not self._envelope_locked:
                site = getattr(getattr(self.supervisor, "config", None), "robot", None) or limits
                out += self._limit_commands(site)
                out.append(("lockEnvelope", ()))
                if limits == site:
                    return out
            return out + self._limit_commands(limits)

        def run(todo: list[tuple[str, tuple[Any, ...]]]) -> None:
            if overall.done():
                return
            if not todo:
                overall.settle(self.envelope)  # settle: its caller may cancel it meanwhile
                return
            name, args = todo[0]
            try:
                status = self.submit(name, *args, source="limits", priority=Priority.LINK)
            except Exception as exc:  # a value the wire cannot carry
                overall.settle(exc=exc)
                return
            status.add_done_callback(lambda st: after(name, st, todo[1:]))

        def after(name: str, status: Future, rest: list[tuple[str, tuple[Any, ...]]]) -> None:
            exc = status.exception() if not status.cancelled() else CommandQueueClosed("cancelled")
            if exc is None:
                if name == "lockEnvelope":
                    self.envelope = status.result()
                    self._envelope_locked = True
                    log.info("LINarm safety envelope locked: %s", self.envelope)
                run(rest)
            elif isinstance(exc, LinarmTimeout) and attempts["n"] < LIMITS_ATTEMPTS - 1 and self.connected:
                attempts["n"] += 1
                log.warning("LINarm limits: a command timed out; trying again")
                run(steps())
            else:
                overall.settle(exc=exc)

        run(steps())
        return overall

    def _send_limits(self, limits: Any) -> list[CommandStatus]:
        """The four limit commands, queued at LINK priority (their statuses, in order)."""
        return [self.submit(name, *args, source="limits", priority=Priority.LINK)
                for name, args in self._limit_commands(limits)]

    @staticmethod
    def _limit_commands(limits: Any) -> list[tuple[str, tuple[Any, ...]]]:
        return [("setMaxVelocity", (float(limits.max_velocity_m_s),)),
                ("setMaxAcceleration", (float(limits.max_acceleration_m_s2),)),
                ("setMaxForce", (float(limits.max_interaction_force_n),)),
                ("setPosLimit", (float(limits.position_min_m), float(limits.position_max_m)))]

    def emergency_idle(self, reason: str = "") -> CommandStatus:
        """Motors off now: IDLE at the queue's ESTOP priority, written ahead of (and between) anything queued
        or awaiting its ACK, with a ';' first to flush the controller's parser. Waits only until the bytes are
        written (ESTOP_WRITE_BOUND_S). Raises TransportError when they could not be written (no link open, the
        queue not running, the write failed), so the caller records the action as not done (``ok: false``)
        instead of believing an IDLE nobody sent (#25). The supervisor records the e-stop, as before."""
        if not self.transport.is_open:  # open, not `connected`: IDLE is also sent during the handshake
            why = self._last_reason or "never connected"
            raise TransportError(f"IDLE not sent: the LINarm link is not open ({why})")

        def write(_status: CommandStatus) -> None:
            self.transport.write(b";" + proto.encode_command("setCtrlState", self._next_seq(),
                                                             int(ControlState.IDLE_CTRL_STATE)))

        status = self.commands.submit("emergency_idle", write, source=reason or "emergency stop",
                                      priority=Priority.ESTOP, exclusive=False)
        if not status.wait_written(ESTOP_WRITE_BOUND_S):
            # Not cancelled: an IDLE written late is still welcome; the record says it was not written in time.
            exc = status.exception(0) if status.done() else None
            if isinstance(exc, TransportError):
                raise exc
            detail = f": {exc}" if exc is not None else f" within {ESTOP_WRITE_BOUND_S * 1000:.0f} ms"
            raise TransportError(f"IDLE not written{detail}")
        return status

    def _queue_ident(self) -> int | None:
        thread = self.commands._thread
        return thread.ident if thread is not None else None

    def _on_command_timeout(self, status: CommandStatus) -> BaseException:
        """An ACK that did not come (the queue's thread): resync the controller's parser (a lone ';' flushes its
        buffer) before the next command."""
        try:
            self.transport.write(b";")
        except TransportError:
            pass
        for seq, pending in list(self._pending.items()):
            if pending.status is status:
                self._pending.pop(seq, None)
        return LinarmTimeout(f"LINarm did not acknowledge {status.name} within {status.timeout_s:.2f} s")

    # ------------------------------------------------------------------ driver thread
    def on_connect(self) -> None:
        self._reader_ident = threading.get_ident()
        self._envelope_locked = False
        self._beating = False
        self.decoder.reset()
        self.clock.reset()  # a reconnect may be a restarted controller
        self._identified.clear()
        self.firmware_version = ""
        self.commands.start()
        # Another program holding the tty (found at open) is named before the handshake: it may take the
        # controller's answer, and a link never identified must not leave it unnamed (#38's loaded runs).
        self._check_port_shared()
        # Flush the controller's parser, then identify (command 0 is harmless by design): through the queue.
        self._link_write("identify", lambda seq: b";" + proto.encode_command("identify", seq))
        deadline = time.monotonic() + 2.0
        while not self._identified.is_set():
            if time.monotonic() > deadline:
                self._check_port_shared()  # a holder found while reading (bytes taken) is named too
                raise TransportError("the LINarm controller did not identify itself within 2 s")
            data = self.transport.read(0.02)
            if data:
                self._handle_frames(data, time.monotonic_ns(), during_connect=True)
        # A (re)connect while the e-stop is latched or a STOP alarm is open: IDLE first, whatever the robot did
        # while the link was down (another controller may have switched it ON); its first state sample is
        # checked too (SafetySupervisor.check_robot_state).
        self._check_port_shared()
        hold = getattr(self.supervisor, "robot_hold_reason", lambda: "")()
        if hold:
            self.emergency_idle(hold)
            self.supervisor.record(journal.ROBOT_IDLE_ON_CONNECT, reason=hold, ok=True)
        period = float(self.stream_period_s)
        self._link_write("startDataStream", lambda seq: proto.encode_command("startDataStream", seq, period))
        self._last_heartbeat = self._reader_alive = time.monotonic()
        self._beating = True  # the queue's periodic heartbeat from now on

    def _link_write(self, name: str, frame: Callable[[int], bytes]) -> None:
        """A handshake frame through the queue (LINK priority), waited for until written (driver thread)."""
        status = self.commands.submit(name, lambda _s: self.transport.write(frame(self._next_seq())),
                                      source="handshake", priority=Priority.LINK, exclusive=False)
        if not status.wait_written(2.0):
            exc = status.exception(0) if status.done() else None
            if isinstance(exc, TransportError):
                raise exc
            raise TransportError(f"the LINarm {name} could not be written" + (f": {exc}" if exc else ""))

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        self._handle_frames(data, t_ns)

    def on_tick(self, now_s: float) -> None:
        self._reader_alive = now_s  # the heartbeat thread beats only while this loop runs
        if getattr(self.transport, "shared_with", None) is not self._shared_seen:
            self._check_port_shared()

    def _check_port_shared(self) -> None:
        """Another process holds the robot's tty (found at open, or when it read bytes meant for us): a STOP alarm
        naming it, one per cause. It was let in anyway (a privileged program passes the tty's exclusivity, or it
        opened first without asking for the lock); the STOP alarm holds the robot IDLE until acknowledged."""
        shared = self._shared_seen = getattr(self.transport, "shared_with", None)
        if not shared:
            return
        from app.safety.supervisor import AlarmLevel

        named = ", ".join(f"pid {pid} ({cmd})" for pid, cmd in shared[:4])
        self.supervisor.raise_alarm(AlarmLevel.STOP, self.name, f"Another program has the LINarm's port open: "
                                    f"{named}; it can command the robot. Close it.",
                                    key=("port shared", self.name, tuple(pid for pid, _ in shared)))

    # ------------------------------------------------------------------ the heartbeat path
    def _beat(self) -> None:
        """The queue's periodic (its real-time thread, heartbeat_priority): the heartbeat never waits for the
        reading loop (on a tty it may wait in the kernel for the receive worker, and listeners run on it) nor
        for a command awaiting its ACK (docs/decisions.md, #16)."""
        if not self._beating:
            return
        # A wedged reading loop (the supervisor's robot monitor runs on it) must not be hidden from the
        # controller: without a loop pass for HEARTBEAT_READER_GRACE_S the beats stop and its watchdog acts.
        now = time.monotonic()
        if now - self._reader_alive > HEARTBEAT_READER_GRACE_S:
            if not self._withheld:
                self._withheld = True
                log.warning("LINarm heartbeat withheld: the reading loop has not run for %.2f s (the controller "
                            "stops the motors %.2f s after the last heartbeat)", now - self._reader_alive,
                            proto.WATCHDOG_TIMEOUT)
            return
        self._withheld = False
        gap = now - self._last_heartbeat
        try:
            self.transport.write(proto.encode_command("heartbeat", self._next_seq()))
            self._last_heartbeat = time.monotonic()
        except TransportError:
            self._beating = False
            return
        if gap > HEARTBEAT_LATE_S:
            self._late_beats += 1
            self._longest_late = max(self._longest_late, gap)
            if now - self._late_logged_at >= HEARTBEAT_LATE_LOG_EVERY_S:
                log.warning("LINarm heartbeat late: %.3f s after the one before (%d late, the longest %.3f s, since "
                            "the last such line; the controller stops the motors after %.2f s without one)%s", gap,
                            self._late_beats, self._longest_late, proto.WATCHDOG_TIMEOUT,
                            "" if self.commands.realtime else ": the OS refused real-time scheduling")
                self._late_logged_at = now
                self._late_beats, self._longest_late = 0, 0.0

    def on_disconnect(self) -> None:
        self._beating = False
        self._record_garbage(force=True)
        lost = TransportError("the LINarm link was lost")
        self.commands.close("the LINarm link was lost", error=lost)  # fails the one in flight (if its ACK lost)
        for pending in list(self._pending.values()):
            pending.status.settle(exc=lost)  # the same status: close() or its ACK may have completed it
        self._pending.clear()

    def stop(self, timeout_s: float = 1.0) -> bool:
        done = super().stop(timeout_s)
        self.commands.close("the LINarm driver stopped")
        return done

    # ------------------------------------------------------------------ decoding
    def _handle_frames(self, data: bytes, t_ns: int, during_connect: bool = False) -> None:
        t = t_ns / 1e9
        for frame in self.decoder.feed(data):
            try:
                msg = proto.decode_controller_frame(frame)
            except proto.ProtocolError as exc:
                self.protocol_errors += 1
                log.debug("linarm: bad frame %r: %s", frame, exc)
                continue
            self._dispatch(msg, t)
        decoder = self.decoder
        if (decoder.frames_bad, decoder.bytes_discarded, self.protocol_errors) != self._garbage_recorded:
            self._record_garbage()

    @property
    def garbage(self) -> dict[str, int]:
        """What this link has dropped since the driver was made: frames the decoder refused (bad id, overlong),
        the bytes it discarded with them, and frames with a valid id that did not decode."""
        d = self.decoder
        return {"bad_frames": d.frames_bad, "bytes_discarded": d.bytes_discarded,
                "undecodable_frames": self.protocol_errors, "frames_ok": d.frames_ok}

    def record_link_counts(self) -> None:
        """The garbage counted since the last record, into the record now (a session's end: its record must hold
        every frame dropped while it ran, not those up to the last periodic record). Any thread: the counts are
        plain integers the driver's thread updates."""
        self._record_garbage(force=True)

    def _record_garbage(self, force: bool = False) -> None:
        """Counts of dropped garbage to the session record (supervisor event ``link_garbage``, cumulative), at
        most every GARBAGE_RECORD_PERIOD_S while it arrives, and at disconnect if anything is unrecorded."""
        d = self.decoder
        now_counts = (d.frames_bad, d.bytes_discarded, self.protocol_errors)
        if now_counts == self._garbage_recorded:
            return
        now = time.monotonic()
        if not force and now - self._garbage_recorded_at < GARBAGE_RECORD_PERIOD_S:
            return
        first = self._garbage_recorded == (0, 0, 0)
        new_frames = now_counts[0] - self._garbage_recorded[0] + now_counts[2] - self._garbage_recorded[2]
        self._garbage_recorded, self._garbage_recorded_at = now_counts, now
        if first:
            log.warning("linarm: garbage on the link (%s); counted in the session record", d.last_error)
        self.supervisor.record(journal.LINK_GARBAGE, device=self.name, new_frames=new_frames, **self.garbage,
                              last_error=d.last_error or "")

    def _dispatch(self, msg: Any, t: float) -> None:
        """``t``: when the read carrying ``msg`` returned (monotonic s)."""
        if isinstance(msg, proto.VsaState):
            # The interaction force is read from the spring elongations, which mean nothing until homing
            # has referenced the encoders: show it as unknown rather than as a huge number.
            state = self.latest(streams.LINARM_STATE)
            force = msg.force if state is not None and state.initialized else float("nan")
            taken = self.clock.map(msg.t_us * 1e-6, t)
            self.publish(streams.LINARM_VSA, taken, VsaSample(msg.equilibrium_pos, msg.delta, msg.stiffness,
                                                              msg.handle_pos, msg.handle_vel, force, msg.t_us / 1e6,
                                                              taken), t)
        elif isinstance(msg, proto.MotorState):
            taken = self.clock.map(msg.t_us * 1e-6, t)
            self.publish(streams.LINARM_MOTORS[msg.index], taken, MotorSample(
                msg.index, msg.position, msg.velocity, msg.current, msg.target, msg.t_us / 1e6, taken), t)
        elif isinstance(msg, proto.LinarmState):
            taken = self.clock.map(msg.t_us * 1e-6, t)
            self.publish(streams.LINARM_STATE, taken, LinarmStateSample(
                int(msg.control_state), int(msg.control_mode), int(msg.home_state), int(msg.error_state),
                int(msg.trigger_mode), bool(msg.initialized), int(msg.trajectory_type), bool(msg.demo),
                bool(msg.virtual_vsa), bool(msg.endstrokes_disabled), msg.t_us / 1e6, taken), t)
        elif isinstance(msg, proto.Ack):
            pending = self._pending.get(msg.seq)
            if pending is not None and pending.status.claim():  # else its timeout (or a cancel) came first
                # Recorded before the status completes: whoever waits on it finds the record written.
                self.supervisor.record(journal.ROBOT_COMMAND, source=pending.source, command=pending.name,
                                      args=pending.args, ok=True)
                pending.status.resolve(dict(msg.values))
        elif isinstance(msg, proto.ErrorReply):
            pending = self._pending.get(msg.seq)
            if pending is None:
                log.info("linarm: unsolicited error reply %s", msg)
            elif pending.status.claim():  # else its timeout (or a cancel) came first
                pending.status.fail(LinarmCommandError(pending.name, msg.code, msg.message))
        elif isinstance(msg, proto.Identify):
            if msg.protocol_version != proto.PROTOCOL_VERSION:
                raise TransportError(f"the controller speaks protocol {msg.protocol_version}, "
                                     f"this application {proto.PROTOCOL_VERSION}")
            self.firmware_version = msg.firmware_version
            self._identified.set()
        elif isinstance(msg, proto.ErrorEvent):
            detail = f" ({msg.message})" if msg.message else ""
            text = f"LINarm error: {proto.ErrorState(msg.error_state).name}{detail}"
            now = time.monotonic()
            if text != self._last_error_logged[0] or now - self._last_error_logged[1] > 1.0:
                log.warning(text)  # the alarm is one per cause; so is the log line (not one per repeated frame)
            self._last_error_logged = (text, now)
            self._fire_event(journal.CONTROLLER_ERROR, text)  # the bus record and the controller_error signal

    def _next_seq(self) -> int:
        """Sequence numbers are taken on the queue's thread only (every write is made there): no lock."""
        self._seq = proto.next_seq(self._seq)
        return self._seq


def create(ctx: DeviceContext) -> DeviceHandle | None:
    """The LINarm from its context: driver on its serial link (or the simulator's), the supervisor's robot
    probes and monitor, and the robot's stop action."""
    from app.devices.registry import DeviceHandle
    from app.devices.sim.adapters import LINARM_POLL_S, LinarmSimAdapter
    from app.safety.supervisor import RobotProbes

    cfg: LinarmDevice = ctx.config
    if cfg.mode == "off":
        return None
    simulator = None
    url = cfg.port
    if cfg.mode == "simulated":
        link = simulator_link(ctx.runtime_dir, streams.LINARM)
        simulator = ctx.simulators.serial(
            streams.LINARM, streams.LINARM,
            lambda patient: SerialSimulator(streams.LINARM, lambda: LinarmSimAdapter(patient), link,
                                            tick_s=LINARM_POLL_S))
        url = simulator.url
    supervisor = ctx.supervisor
    link = SerialTransport(url, SerialSettings(baudrate=cfg.baudrate))
    driver = LinarmDriver(link, supervisor, stream_period_s=1.0 / cfg.state_rate_hz,
                          command_timeout_s=cfg.command_timeout_s, heartbeat_period_s=cfg.heartbeat_period_s,
                          bus=ctx.bus, silence_timeout_s=ctx.silence_timeout(cfg.state_rate_hz))
    bus = ctx.bus

    def centre() -> float | None:
        vsa = bus.latest(streams.LINARM_VSA)
        return vsa.equilibriumPos if vsa is not None else None

    def delta() -> float | None:
        vsa = bus.latest(streams.LINARM_VSA)
        return vsa.delta if vsa is not None else None

    def homed() -> bool:
        state = bus.latest(streams.LINARM_STATE)
        return bool(state is not None and state.initialized)

    def monitor(item: BusItem) -> None:
        # The supervisor's robot monitor sees every sample on the driver thread, before any other consumer.
        if isinstance(item, SampleItem):
            if item.stream == streams.LINARM_VSA:
                supervisor.check_robot_sample(item.sample)
            else:
                # ON or homing while the e-stop is latched or a STOP alarm is open: IDLE within one state
                # period, one alarm per cause (a second controller may have switched it ON behind the app's back).
                supervisor.check_robot_state(item.sample, driver.emergency_idle)
        elif isinstance(item, journal.Record) and item.origin == streams.LINARM and item.kind == journal.CONNECTED:
            # The controller's safety envelope is locked at every connect (apply_limits only queues the
            # commands): a safety action, so it rides on the safety monitor's inline subscription.
            future = driver.apply_limits(supervisor.robot)
            future.add_done_callback(lambda f: f.exception() and log.error(
                "LINarm limits not applied: %s", f.exception()))

    ctx.set_robot_probes(RobotProbes(centre, delta, homed))
    bus.subscribe_inline("safety", monitor, (streams.LINARM_VSA, streams.LINARM_STATE), events=True)
    ctx.add_stop_action("robot IDLE", driver.emergency_idle, robot=True)
    return DeviceHandle(streams.LINARM, driver, simulator)
