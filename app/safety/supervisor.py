"""The safety supervisor: the one place where limits, alarms and the emergency stop live.

Every command that can move the robot or put current through a muscle passes through here,
whoever sends it (GUI, script, patient model, assistance split): the drivers call
:meth:`SafetySupervisor.check_robot_command` / :meth:`check_fes_update` from their single
command-encoding path, so there is no way around it. A command outside limits is refused with a
plain reason (:class:`SafetyError`), logged and recorded; nothing is silently changed,
except the patient model's outputs, which are clamped and the clamp logged.

Qt-free: what the supervisor decides it publishes as journal records on the stream bus (:mod:`app.core.journal`,
origin ``safety``: ``alarm``, ``alarm_acknowledged``, ``emergency_stop``, ``emergency_stop_reset``,
``command_refused``, ``lease_taken`` / ``lease_released`` / ``lease_refused``, …) through :meth:`record`, the one
way the application writes to the journal. The window's adapter (``app/ui/qt_bus.py``) turns them into Qt
signals on its tick; the fault policy hears them inline, on the thread that raised them.

The emergency stop is a command, not an event: :meth:`emergency_stop` runs the registered stop actions (FES Stop,
robot IDLE) directly in the calling thread, then latches until an operator resets it; its records follow.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from app.core import journal
from app.core.bus import StreamBus
from app.core.config import RobotLimits, SafetyConfig
from app.core.ownership import DEVICE_WORDS, ROBOT, STIMULATOR, Composition, Lease, clamp_to, refusal
from app.wire.linarm_constants import K

log = logging.getLogger(__name__)

# The robot monitor (check_robot_sample) is the controller's envelope check one layer up, with the same margins:
# they are read from the constants table the firmware and the simulator are built from, never written here.
ENVELOPE_VELOCITY_FACTOR = K["ENVELOPE_VELOCITY_FACTOR"]  # handle speed above this x max_velocity_m_s: stop
ENVELOPE_POSITION_MARGIN = K["ENVELOPE_POSITION_MARGIN"]  # m outside [position_min_m, position_max_m]: stop


class SafetyError(RuntimeError):
    """A command was refused. ``reason`` is a sentence a clinician can read."""

    def __init__(self, reason: str, source: str = "") -> None:
        self.reason = reason
        self.source = source
        super().__init__(reason)


class EmergencyStopLatched(SafetyError):
    pass


class AlarmLevel(enum.IntEnum):
    """Graded after IEC 60601-1-8 / Project MARCH: information < warning < stop < fatal."""

    INFO = 0
    WARNING = 1
    STOP = 2
    FATAL = 3


@dataclass
class Alarm:
    level: AlarmLevel
    source: str
    text: str
    t_wall: float = field(default_factory=time.time)
    acknowledged: bool = False
    ident: int = 0
    key: Any = None  # the cause: a repeat of it while this alarm is open is counted here, not raised again
    repeats: int = 0  # further occurrences of the same cause merged into this alarm
    t_last_mono: float = field(default_factory=time.monotonic)  # the cause's latest occurrence


@dataclass(frozen=True)
class StopAction:
    """Something that makes a device safe, run on every emergency stop and safe-state request.
    ``run(reason)`` must be quick, thread-safe and never block. ``robot``: the robot monitor runs only
    these (an excursion of the handle stops the robot, not the stimulation)."""

    name: str
    run: Callable[[str], None]
    robot: bool = False


@dataclass(frozen=True)
class RobotProbes:
    """The measured robot state the command checks need: centre and delta (m, None when unknown) and
    whether the encoders are referenced. Given by the LINarm device when it is built."""

    centre_m: Callable[[], float | None]
    delta_m: Callable[[], float | None]
    homed: Callable[[], bool]
ROBOT_MONITOR_GRACE_SAMPLES = 5
# One alarm per cause, not one per frame: an occurrence of a cause whose alarm is still unacknowledged and was
# last seen less than this long ago is counted on that alarm (a forged or repeated frame raised the same STOP
# alarm 12 times in 0.1 s, #25). Acknowledging the alarm (Recover) makes the next occurrence a new alarm.
ALARM_REPEAT_HOLD_S = 2.0
ALARM_REPEAT_RECORD_S = 1.0  # repeats reach the session record as a count at most this often per alarm

# Commands that only read, stop or make things safer: allowed even while the e-stop is latched.
# Commands that move the encoders' zero or scale: service only, never during therapy.
CALIBRATION_COMMANDS = {"setMotorOffset", "setMobileOffset", "setMotorRatio", "setMobileRatio"}

_ALWAYS_ALLOWED = {
    "identify", "heartbeat", "getPidTunings", "getAdmittanceParameter", "getAssistanceParameter",
    "getAssistanceTargetPos", "getIsInitialized", "stopDataStream", "startDataStream", "resetError",
    # Aligning the controller's own limits with ours (still range-checked below), and locking them there.
    "setMaxVelocity", "setMaxAcceleration", "setMaxForce", "setPosLimit", "lockEnvelope",
}


class SafetySupervisor:
    """Limits, leases, alarms and the e-stop latch (see the module docstring). ``bus``: the stream bus its records
    go to (the manager's; a supervisor of its own, e.g. in a test, makes a bus of its own)."""

    def __init__(self, config: SafetyConfig, bus: StreamBus | None = None) -> None:
        self.config = config
        self.robot: RobotLimits = config.robot
        self.bus = bus if bus is not None else StreamBus()
        self._stop_actions: list[StopAction] = []
        self._estop_lock = threading.RLock()
        self._estop_latched = False
        self._estop_reason = ""
        self._alarms: list[Alarm] = []
        self._alarm_seq = 0
        self._alarm_by_key: dict[Any, Alarm] = {}  # each cause's latest alarm
        self._open_stop: dict[int, Alarm] = {}  # unacknowledged STOP/FATAL alarms, by ident
        self._repeat_recorded: dict[int, float] = {}  # alarm ident -> when its repeat count was last recorded
        self._lock = threading.Lock()
        self.fes_limiter: Any = None  # set by the FES device (app.safety.fes_limits.FesLimiter)
        self.latest_centre_m: Callable[[], float | None] = lambda: None
        self.latest_delta_m: Callable[[], float | None] = lambda: None
        self.robot_homed: Callable[[], bool] = lambda: False
        self._robot_excursion = False
        self._samples_homed = 0
        # One owner of each device during a run (app/core/ownership.py): device -> the lease holding it. Replaced whole
        # (never mutated in place), so the command checks read it without a lock.
        self._leases: dict[str, Lease] = {}
        # Why stimulation is withheld for now ('' when it is not): the session's patient record is this station's
        # copy, read while the archive answered (#39): a cap lowered on another station since would not be known.
        self.stimulation_withheld = ""
        self._lease_lock = threading.Lock()

    # ------------------------------------------------------------------ the journal
    def record(self, kind: str, **data: Any) -> None:
        """One journal record of origin ``safety`` (``kind`` from :mod:`app.core.journal`) on the bus, on this
        thread."""
        log.info("record %s %s", kind, data)
        self.bus.record(journal.SAFETY, kind, data)

    def set_robot_probes(self, probes: RobotProbes) -> None:
        self.latest_centre_m = probes.centre_m
        self.latest_delta_m = probes.delta_m
        self.robot_homed = probes.homed

    def refuse(self, source: str, reason: str) -> SafetyError:
        self.record(journal.COMMAND_REFUSED, source=source, reason=reason)
        return SafetyError(reason, source)

    # ------------------------------------------------------------------ one owner during a run (#36)
    def take_lease(self, lease: Lease) -> None:
        """``lease.holder`` holds ``lease.devices`` from now on. Raises SafetyError (recorded as a refused lease)
        when another holds one of them: one owner at a time."""
        with self._lease_lock:
            taken = {d: self._leases[d].holder for d in sorted(lease.devices) if d in self._leases
                     and self._leases[d].key != lease.key}
            if taken:
                busy = "; ".join(f"{DEVICE_WORDS[d]} is held by {who}" for d, who in taken.items())
                self.record(journal.LEASE_REFUSED, holder=lease.holder, source=lease.holder, what="the devices",
                           reason=busy)
                raise SafetyError(f"{lease.holder} cannot start: {busy}", lease.holder)
            self._leases = {**self._leases, **{d: lease for d in lease.devices}}
        self.record(journal.LEASE_TAKEN, **lease.record())

    def release_lease(self, key: str, reason: str = "") -> Lease | None:
        """End the lease ``key`` (a run's id), if it is held; returns it."""
        with self._lease_lock:
            held = next((lease for lease in self._leases.values() if lease.key == key), None)
            if held is None:
                return None
            self._leases = {d: lease for d, lease in self._leases.items() if lease.key != key}
        self.record(journal.LEASE_RELEASED, key=key, holder=held.holder, run_id=held.run_id, reason=reason,
                    **({"refused": dict(held.refused)} if held.refused else {}))
        return held

    def lease(self, device: str = ROBOT) -> Lease | None:
        return self._leases.get(device)

    def holder(self, device: str = ROBOT) -> str:
        """Who holds ``device`` in words ("" when nobody)."""
        lease = self._leases.get(device)
        return lease.holder if lease is not None else ""

    def lease_problem(self, device: str, what: str, source: str, value: float | None = None) -> str:
        """Why ``what`` from ``source`` may not act on ``device`` now ("" when it may); nothing recorded."""
        return refusal(self._leases.get(device), device, source, what, value)

    def check_lease(self, device: str, what: str, source: str, value: float | None = None) -> None:
        """Raise SafetyError when another holds ``device`` and does not compose ``what`` from ``source``. The first
        refusal of each source and action per lease is recorded (``lease_refused``); the rest are counted on the
        lease and recorded with its release (a VR task sends a new target every few seconds)."""
        lease = self._leases.get(device)
        problem = refusal(lease, device, source, what, value)
        if not problem:
            return
        assert lease is not None
        key = f"{source}: {what}"
        first = key not in lease.refused
        lease.refused[key] = lease.refused.get(key, 0) + 1
        if first:
            # The window shows a refusal from its source (a lease refusal, like command_refused, says who and why).
            self.record(journal.LEASE_REFUSED, holder=lease.holder, run_id=lease.run_id, source=source, what=what,
                        reason=problem, **({"value": value} if value is not None else {}))
        raise SafetyError(problem, source)

    def composed_target(self, source: str, value: float) -> float | None:
        """The assistance target ``value`` from ``source`` as the robot's holder lets it through: unchanged when
        nobody holds the robot, clamped to the run's range and the patient's limits when the holder composes
        it (the clamp recorded), None when refused (recorded once, see :meth:`check_lease`)."""
        lease = self._leases.get(ROBOT)
        if lease is None or lease.acts_for(source):
            return value
        comp = lease.composition(source, "setAssistanceTargetPos")
        if comp is None:
            try:
                self.check_lease(ROBOT, "setAssistanceTargetPos", source, value)
            except SafetyError:
                return None
            return value
        applied = clamp_to(comp, value, (self.robot.position_min_m, self.robot.position_max_m))
        if applied != value:
            self.record(journal.CLAMPED, source=source, quantity="assistance target", requested=value, applied=applied,
                       holder=lease.holder)
        return applied

    def composes(self, device: str, source: str, what: str) -> Composition | None:
        lease = self._leases.get(device)
        return lease.composition(source, what) if lease is not None else None

    # ------------------------------------------------------------------ robot
    def check_robot_command(self, name: str, args: dict[str, Any], source: str = "") -> None:
        """Raise SafetyError if the LINarm command ``name`` (seed API name) with ``args`` is unsafe."""
        if self._estop_latched and name not in _ALWAYS_ALLOWED:
            if not (name == "setCtrlState" and int(args.get("controlState", args.get("state", -1))) == 0):
                raise self.refuse(source, f"{name} refused: the emergency stop is latched; reset it first")
        if _starts_the_robot(name, args) and (open_stop := self.open_stop_alarm()) is not None:
            # The state monitor would send IDLE at the next state sample anyway (check_robot_state): say why now.
            raise self.refuse(source, f"{name} refused: a STOP alarm is open ({open_stop.source}: {open_stop.text}); "
                                      "acknowledge it (Recover) first")
        if self._leases and name not in _ALWAYS_ALLOWED and not _makes_safe(name, args):
            value = _f(args, "Apos", "targetPos") if name == "setAssistanceTargetPos" else None
            self.check_lease(ROBOT, name, source, value)
        lim = self.robot
        if name in CALIBRATION_COMMANDS and not lim.allow_calibration:
            raise self.refuse(source, f"{name} refused: encoder calibration changes the position reference; "
                                      "it is a service operation (safety.robot.allow_calibration)")
        problem = _robot_problem(name, args, lim, self.latest_centre_m(), self.latest_delta_m())
        if problem:
            raise self.refuse(source, f"{name} refused: {problem}")

    def check_robot_sample(self, vsa: Any) -> None:
        """Per-cycle check of the measured robot state (after CORC): a handle faster than the velocity
        limit times ENVELOPE_VELOCITY_FACTOR (a margin for measurement noise), an interaction force above its
        limit, or a handle more than ENVELOPE_POSITION_MARGIN outside the allowed range stops the robot and
        raises a STOP alarm, once per excursion (the margins are the controller's, from its constants table).
        Runs on the LINarm driver thread for every state sample; it must stay cheap."""
        lim = self.robot
        problem = kind = ""
        # Before homing the encoders are not referenced: positions and the force read from the spring
        # elongations mean nothing yet (the firmware's own limits cover homing). Speed is valid always.
        homed = self.robot_homed()
        self._samples_homed = self._samples_homed + 1 if homed else 0
        # The first samples after referencing may still carry the old reference: skip a few (25 ms at 200 Hz).
        homed = self._samples_homed > ROBOT_MONITOR_GRACE_SAMPLES
        if abs(vsa.handleVel) > ENVELOPE_VELOCITY_FACTOR * lim.max_velocity_m_s:
            kind = "speed"
            problem = f"handle speed {abs(vsa.handleVel):.3f} m/s above the limit {lim.max_velocity_m_s:.3f} m/s"
        elif homed and abs(vsa.interactionForce) > lim.max_interaction_force_n:
            kind = "force"
            problem = (f"interaction force {abs(vsa.interactionForce):.1f} N above the limit "
                       f"{lim.max_interaction_force_n:.1f} N")
        elif homed and not (lim.position_min_m - ENVELOPE_POSITION_MARGIN <= vsa.handlePos
                            <= lim.position_max_m + ENVELOPE_POSITION_MARGIN):
            kind = "range"
            problem = f"handle at {vsa.handlePos:.3f} m, outside {lim.position_min_m:.3f} .. {lim.position_max_m:.3f} m"
        if problem and not self._robot_excursion:
            self._robot_excursion = True
            for action in self._stop_actions:
                if action.robot:
                    try:
                        action.run(problem)
                    except Exception as exc:
                        log.warning("robot stop failed: %s", exc)
            # One alarm per cause: forged frames between genuine ones each start a new excursion (and are
            # each stopped), but raise one alarm, whose repeats are counted.
            self.raise_alarm(AlarmLevel.STOP, "robot monitor", f"Robot stopped: {problem}", key=("robot monitor", kind))
        elif not problem:
            self._robot_excursion = False

    def robot_hold_reason(self) -> str:
        """Why the robot must stay IDLE right now ('' when nothing holds it): a latched e-stop or an open
        (unacknowledged) STOP/FATAL alarm."""
        if self._estop_latched:
            return "the emergency stop is latched"
        alarm = self.open_stop_alarm()
        return f"a STOP alarm is open ({alarm.source}: {alarm.text})" if alarm is not None else ""

    def open_stop_alarm(self) -> Alarm | None:
        """The oldest unacknowledged STOP/FATAL alarm, or None."""
        if not self._open_stop:
            return None
        with self._lock:
            return min(self._open_stop.values(), key=lambda a: a.ident, default=None)

    def check_robot_state(self, state: Any, stop: Callable[[str], None]) -> bool:
        """Every LINarm state sample (and so every (re)connect, whose first sample follows within one state
        period): a robot found ON or homing while the e-stop is latched or a STOP alarm is open is sent IDLE
        (``stop(reason)``, which raises when it cannot be sent) and raised as a STOP alarm, one per cause.
        IDLE is sent on every such sample (a controller switched ON behind the app's back again is idled
        again); the alarm is one per cause. True when the robot had to be stopped."""
        control = int(getattr(state, "controlState", 0))
        if control == 0:
            return False
        reason = self.robot_hold_reason()
        if not reason:
            return False
        what = "ON" if control == 2 else "homing" if control == 1 else f"in control state {control}"
        problem = f"robot found {what} while {reason}"
        ok, error = True, ""
        try:
            stop(problem)
        except Exception as exc:  # the link is gone: the controller's own watchdog is what remains
            ok, error = False, str(exc)
            log.warning("robot IDLE not sent: %s", exc)
        held_by = "the emergency stop is latched" if self._estop_latched else "a STOP alarm is open"
        text = f"Robot found {what} while {held_by}: " + ("sent IDLE" if ok else f"IDLE could not be sent ({error})")
        alarm = self.raise_alarm(AlarmLevel.STOP, "robot monitor", text, key=("robot held", what, held_by))
        if alarm.repeats == 0:
            self.record(journal.ROBOT_HELD_IDLE, state=control, reason=reason, ok=ok,
                        **({"error": error} if error else {}))
        return True

    # ------------------------------------------------------------------ FES
    def check_fes_update(self, update: Any, now: float, source: str = "") -> None:
        """Raise SafetyError unless ``update`` (app.safety.fes_limits.FesUpdate: the channel list and every
        channel's setting) is within the FES limits at monotonic time ``now``. An accepted update is
        remembered by the limiter (rate of increase); a refused one changes nothing."""
        from app.safety.fes_limits import FesLimitError

        if self._estop_latched and any(s.current_ma > 0 for s in update.settings.values()):
            raise self.refuse(source, "stimulation refused: the emergency stop is latched; reset it first")
        if self.fes_limiter is None:
            raise self.refuse(source, "stimulation refused: no FES limits are configured")
        try:
            self.fes_limiter.check(update, now)
        except FesLimitError as exc:
            raise self.refuse(source, f"stimulation refused: {exc.reason}") from exc

    def check_fes_command(self, what: str, source: str) -> None:
        """The stimulator's lease at a start, a profile load, a scale change or the pulse-width override (the
        FES driver's entry points): refused while another holds the stimulator and does not compose it, and while
        stimulation is withheld (``stimulation_withheld``)."""
        withheld = self.stimulation_withheld
        if withheld:
            raise SafetyError(f"{what} refused: stimulation is withheld: {withheld}", source)
        if self._leases:
            self.check_lease(STIMULATOR, what, source)

    def clamp_assistance(self, name: str, value: float, lo: float, hi: float, source: str = "patient model") -> float:
        """Patient-model outputs are clamped, not refused (the loop must keep running); log the clamp."""
        clamped = min(max(value, lo), hi)
        if clamped != value:
            self.record(journal.CLAMPED, source=source, quantity=name, requested=value, applied=clamped)
        return clamped

    # ------------------------------------------------------------------ emergency stop
    def add_stop_action(self, action: StopAction) -> None:
        """``action.run(reason)`` runs in the caller's thread on every emergency stop and safe-state
        request, in the order added."""
        self._stop_actions = [*self._stop_actions, action]

    def register_estop_action(self, name: str, action: Callable[[str], None]) -> None:
        """The named form of :meth:`add_stop_action` (contract 3: the script runner's "script")."""
        self.add_stop_action(StopAction(name, action, robot=name == "robot IDLE"))

    def stop_actions(self) -> list[StopAction]:
        return list(self._stop_actions)

    @property
    def _estop_actions(self) -> list[tuple[str, Callable[[str], None]]]:  # the old (name, fn) form
        return [(a.name, a.run) for a in self._stop_actions]

    @property
    def estop_latched(self) -> bool:
        return self._estop_latched

    def emergency_stop(self, source: str, reason: str = "emergency stop pressed") -> None:
        with self._estop_lock:
            first = not self._estop_latched
            self._estop_latched = True
            self._estop_reason = f"{reason} ({source})"
            # Stop actions run even when already latched: pressing again must re-send the stops.
            for action in self._stop_actions:
                try:
                    action.run(self._estop_reason)
                    self.record(journal.ESTOP_ACTION, action=action.name, ok=True)
                except Exception as exc:
                    log.exception("emergency-stop action %s failed", action.name)
                    self.record(journal.ESTOP_ACTION, action=action.name, ok=False, error=str(exc))
        self.record(journal.EMERGENCY_STOP, source=source, reason=reason)
        if first:
            self.raise_alarm(AlarmLevel.STOP, source, f"Emergency stop: {reason}")

    def bring_to_safe_state(self, reason: str) -> None:
        """Run the stop actions without latching: script end, app close, device loss."""
        for action in self._stop_actions:
            try:
                action.run(reason)
                self.record(journal.SAFE_STATE_ACTION, action=action.name, reason=reason, ok=True)
            except Exception as exc:
                log.warning("safe-state action %s failed: %s", action.name, exc)
                self.record(journal.SAFE_STATE_ACTION, action=action.name, reason=reason, ok=False, error=str(exc))

    def reset_emergency_stop(self, operator: str) -> None:
        with self._estop_lock:
            if not self._estop_latched:
                return
            self._estop_latched = False
        self.record(journal.EMERGENCY_STOP_RESET, operator=operator)
        self.raise_alarm(AlarmLevel.INFO, operator or "operator", "Emergency stop reset")

    # ------------------------------------------------------------------ alarms
    def raise_alarm(self, level: AlarmLevel, source: str, text: str, key: Any = None) -> Alarm:
        """Raise an alarm, or count a repeat: ``key`` names the cause (by default level, source and text); an
        occurrence of a cause whose alarm is still unacknowledged and was seen within ALARM_REPEAT_HOLD_S is
        counted on that alarm (``repeats``; an ``alarm_repeated`` event at most every ALARM_REPEAT_RECORD_S)
        and returned, with no new alarm, no signal and no second safe-state run."""
        cause = key if key is not None else (int(level), source, text)
        now = time.monotonic()
        record_repeat = False
        with self._lock:
            previous = self._alarm_by_key.get(cause)
            if (previous is not None and not previous.acknowledged and previous.level == level
                    and now - previous.t_last_mono < ALARM_REPEAT_HOLD_S):
                previous.repeats += 1
                previous.t_last_mono = now
                if now - self._repeat_recorded.get(previous.ident, 0.0) >= ALARM_REPEAT_RECORD_S:
                    self._repeat_recorded[previous.ident] = now
                    record_repeat = True
                alarm = None
            else:
                self._alarm_seq += 1
                alarm = Alarm(level, source, text, ident=self._alarm_seq, key=cause, t_last_mono=now)
                self._alarms.append(alarm)
                self._alarm_by_key[cause] = alarm
                if level >= AlarmLevel.STOP:
                    self._open_stop = {**self._open_stop, alarm.ident: alarm}
        if alarm is None:
            assert previous is not None
            log.debug("alarm repeated (%d) %s: %s", previous.repeats, source, text)
            if record_repeat:
                self.record(journal.ALARM_REPEATED, ident=previous.ident, level=level.name, source=source,
                           text=previous.text, repeats=previous.repeats)
            return previous
        log.log(logging.WARNING if level >= AlarmLevel.WARNING else logging.INFO, "alarm %s %s: %s",
                level.name, source, text)
        self.record(journal.ALARM, level=level.name, source=source, text=text, ident=alarm.ident)
        return alarm

    def acknowledge(self, ident: int, operator: str = "") -> None:
        with self._lock:
            for alarm in self._alarms:
                if alarm.ident == ident and not alarm.acknowledged:
                    alarm.acknowledged = True
                    if ident in self._open_stop:
                        self._open_stop = {i: a for i, a in self._open_stop.items() if i != ident}
                    repeats = {"repeats": alarm.repeats} if alarm.repeats else {}
                    self.record(journal.ALARM_ACKNOWLEDGED, ident=ident, operator=operator, **repeats)

    def alarm(self, ident: int) -> Alarm | None:
        """The alarm ``ident`` (an ``alarm`` record's ``ident``), or None."""
        with self._lock:
            return next((a for a in self._alarms if a.ident == ident), None)

    def alarms(self) -> list[Alarm]:
        with self._lock:
            return list(self._alarms)


def _makes_safe(name: str, args: dict[str, Any]) -> bool:
    """The safe state: IDLE passes whoever holds the robot."""
    return name == "setCtrlState" and int(args.get("controlState", args.get("state", -1))) == 0


def _starts_the_robot(name: str, args: dict[str, Any]) -> bool:
    """Commands that switch the motors on: homing, or a control state other than IDLE."""
    if name == "goToHome":
        return True
    if name == "setCtrlState":
        return int(args.get("controlState", args.get("state", 0))) != 0
    return False


def _f(args: dict[str, Any], *names: str) -> float | None:
    for n in names:
        if n in args and args[n] is not None:
            return float(args[n])
    return None


def _robot_problem(name: str, args: dict[str, Any], lim: RobotLimits, centre: float | None,
                   delta: float | None = None) -> str:
    """The reason ``name(args)`` would exceed a robot limit, or '' when it is within all of them."""

    for key, value in args.items():
        if isinstance(value, float) and not math.isfinite(value):
            return f"{key} must be a finite number, got {value}"
    pos_lo, pos_hi = lim.position_min_m, lim.position_max_m

    def position(key: str, value: float | None) -> str:
        if value is not None and not (pos_lo <= value <= pos_hi):
            return f"{key} {value:.3f} m is outside the allowed range {pos_lo:.3f} .. {pos_hi:.3f} m"
        return ""

    def speed(key: str, value: float | None, allow_zero: bool = True) -> str:
        if value is None:
            return ""
        if value < 0 or (value == 0 and not allow_zero):
            return f"{key} must be positive, got {value}"
        if value > lim.max_velocity_m_s:
            return f"{key} {value:.3f} m/s exceeds the velocity limit {lim.max_velocity_m_s:.3f} m/s"
        return ""

    def accel(key: str, value: float | None) -> str:
        if value is None:
            return ""
        if value <= 0:
            return f"{key} must be positive, got {value}"
        if value > lim.max_acceleration_m_s2:
            return f"{key} {value:.3f} m/s² exceeds the acceleration limit {lim.max_acceleration_m_s2:.3f} m/s²"
        return ""

    if name in ("moveCentreTo", "moveDeltaTo", "setStiffness"):
        target = _f(args, "targetPos", "targetDeltaPos", "stiffness")
        v, a, t_exec = _f(args, "maxVel"), _f(args, "maxAcc"), _f(args, "execTime") or 0.0
        if name == "moveCentreTo":
            if p := position("targetPos", target):
                return p
        elif name == "moveDeltaTo":
            if target is None or not (0.0 <= target <= lim.max_delta_m):
                return f"delta {target} m is outside 0 .. {lim.max_delta_m} m"
        elif target is None or not (0.0 <= target <= lim.max_stiffness_n_m):
            return f"stiffness {target} N/m is outside 0 .. {lim.max_stiffness_n_m} N/m"
        if t_exec < 0:
            return f"execTime must not be negative, got {t_exec}"
        if t_exec == 0:
            return speed("maxVel", v, allow_zero=False) or accel("maxAcc", a)
        # A timed move: maxVel/maxAcc may be 0 (the controller's own limits, aligned to these at connect),
        # but never above the limits; and the time itself must not ask for more. The distance is from the
        # measured position when known, else the whole travel (conservative). Bounds of the steeper
        # profile, the cycloid: peak speed 2D/T, peak acceleration 2πD/T².
        if (v or 0.0) > 0 and (p := speed("maxVel", v)):
            return p
        if (a or 0.0) > 0 and (p := accel("maxAcc", a)):
            return p
        if name == "moveCentreTo":
            start = centre if centre is not None else None
            distance = abs(target - start) if start is not None and target is not None else pos_hi - pos_lo
        elif name == "moveDeltaTo" and delta is not None and target is not None:
            distance = abs(target - delta)
        else:  # setStiffness: the delta it needs depends on the spring law; assume the whole delta range
            distance = lim.max_delta_m
        peak_v = 2.0 * distance / t_exec
        peak_a = 2.0 * math.pi * distance / t_exec**2
        if peak_v > lim.max_velocity_m_s:
            return (f"moving {distance:.3f} m in {t_exec:.2f} s needs up to {peak_v:.3f} m/s, "
                    f"above the velocity limit {lim.max_velocity_m_s:.3f} m/s")
        if peak_a > lim.max_acceleration_m_s2:
            return (f"moving {distance:.3f} m in {t_exec:.2f} s needs up to {peak_a:.3f} m/s², "
                    f"above the acceleration limit {lim.max_acceleration_m_s2:.3f} m/s²")
        return ""
    if name in ("setCentreVelocity", "setDeltaVelocity"):
        v = _f(args, "centreVelocity", "deltaVelocity", "velocity")
        return speed(name, abs(v) if v is not None else None)
    if name == "setAssistanceTargetPos":
        return position("Apos", _f(args, "Apos", "targetPos"))
    if name == "setAdmittanceParameter":
        ka = _f(args, "Ka")
        if ka is None or ka < 0:
            return f"Ka must be ≥ 0, got {ka}"
        if ka * lim.max_interaction_force_n > lim.max_velocity_m_s:
            return (f"Ka {ka} m/(N·s) would reach {ka * lim.max_interaction_force_n:.3f} m/s at the force limit, "
                    f"above the velocity limit {lim.max_velocity_m_s} m/s")
        return ""
    if name == "setAssistanceParameter":
        kt = _f(args, "Kt", "Kf", "Ka")
        if kt is None or not (0.0 <= kt <= lim.max_stiffness_n_m):
            return f"assistance gain {kt} N/m is outside 0 .. {lim.max_stiffness_n_m} N/m"
        return ""
    if name == "setPosLimit":
        lo, hi = _f(args, "minPos", "min"), _f(args, "maxPos", "max")
        if lo is None or hi is None or lo >= hi:
            return "setPosLimit needs min < max"
        return position("min", lo) or position("max", hi)
    if name == "setMaxVelocity":
        return speed("maxVel", _f(args, "maxVel", "value"), allow_zero=False)
    if name == "setMaxAcceleration":
        return accel("maxAcc", _f(args, "maxAcc", "value"))
    if name == "setMaxForce":
        f = _f(args, "maxForce", "value")
        if f is None or not (0 < f <= lim.max_interaction_force_n):
            return f"force limit {f} N is outside 0 .. {lim.max_interaction_force_n} N"
        return ""
    if name == "disableEndstrokes" and args.get("disable") and not lim.allow_disable_endstrokes:
        return "endstroke switches protect the patient at the ends of the rail; disabling them is not allowed"
    if name == "setHomeParameter":
        home, home_delta, homing_v = _f(args, "homeCentre"), _f(args, "homeDelta"), _f(args, "homingVelocity")
        if p := position("homeCentre", home):
            return p
        if home_delta is None or not (0.0 <= home_delta <= lim.max_delta_m):
            return f"homeDelta {home_delta} m is outside 0 .. {lim.max_delta_m} m"
        return speed("homingVelocity", homing_v, allow_zero=False)
    if name == "setVirtualVsaSpringDisplacement":
        d = _f(args, "disp")
        if d is None or abs(d) > lim.max_delta_m:
            return f"displacement {d} m is outside ±{lim.max_delta_m} m"
    return ""
