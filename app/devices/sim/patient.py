"""The one simulated patient, shared by the LINarm simulator and the physiological-board simulator.

Two things a patient does to the devices:

* grips the handle: ``grip_force(t)`` (N) follows a behaviour -- idle, squeeze now for a duration,
  squeeze periodically, or squeeze when the handle reaches one of some target positions -- through
  first-order muscle dynamics (rise tau 0.1 s: > 20 N about 70 ms after the command; peak ~38 N;
  release tau 0.15 s) plus small noise;
* pushes the handle: ``handle_force(t, pos, vel)`` (N, + toward +x) -- passive (a small damping),
  push toward a target with a given force, or fail the sub-task (too weak, or stops early) so the
  patient-model tests can watch the assistance rise;
* answers electrical stimulation (issue #32): the RehaStim simulator tells it what each channel delivers
  (``stimulation``); each channel is one electrode combination of an array, at some distance from its
  muscle's motor point (``ElectrodeSite``: random per seed, or set with ``set_electrode_distances``). The
  evoked force has a motor threshold that rises with the distance and a saturating recruitment curve, and is
  added to ``handle_force`` through first-order muscle dynamics.

Time is the simulators' clock (s): every caller must use the same clock (the app uses
time.monotonic()); an older ``t`` than already seen just returns the current value.
Behaviours may be changed from any thread (GUI panel, test, script): every public method takes
the same lock.  Deterministic for a given seed and call sequence.
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from app.wire.sciencemode import CHANNELS

# Grip dynamics (one place).
GRIP_REST_N = 1.0         # hand resting on the handle
GRIP_PEAK_N = 38.0        # voluntary squeeze plateau
GRIP_RISE_TAU_S = 0.10
GRIP_FALL_TAU_S = 0.15
GRIP_NOISE_N = 0.3        # per-sample standard deviation
_GRIP_STEP_S = 0.005      # integration sub-step so periodic edges are resolved

# Evoked response (issue #32, docs/fes.md "Electrode set-up"). A simple model, not physiology: the threshold
# current of a pair centred on the motor point is THRESHOLD_AT_MOTOR_POINT_MA (at 250 µs), it rises with the
# square of the distance (doubled THRESHOLD_DOUBLING_CM away), and with shorter pulses (strength-duration,
# chronaxie CHRONAXIE_US). Above threshold F = F_max (1 - exp(-(I/I_th - 1) / RECRUITMENT_SPREAD)), so the
# force per mA of a combination scales with 1/I_th: a pair with a 20 % lower threshold gives 20 % more force
# per mA.
THRESHOLD_AT_MOTOR_POINT_MA = 8.0
THRESHOLD_DOUBLING_CM = 1.5
CHRONAXIE_US = 300.0
REFERENCE_PULSE_WIDTH_US = 250.0
RECRUITMENT_SPREAD = 0.5
EVOKED_MAX_FORCE_N = 12.0   # a fully recruited muscle, as the handle feels it under the position hold
EVOKED_RISE_TAU_S = 0.08
EVOKED_FALL_TAU_S = 0.12
SITE_DISTANCE_RANGE_CM = (0.2, 2.5)  # random distances per simulated patient seed

HANDLE_DAMPING_NS_M = 2.0  # passive arm: N per m/s
HANDLE_NOISE_N = 0.1
HANDLE_PUSH_RAMP_M = 0.01  # the push fades out within 1 cm of the target (no chatter)


class GripMode(enum.Enum):
    IDLE = "idle"
    SQUEEZE = "squeeze"          # squeeze now, for a duration
    PERIODIC = "periodic"        # squeeze for duty*period every period
    AT_TARGET = "at_target"      # squeeze on arriving within tolerance of a target position


class HandleMode(enum.Enum):
    PASSIVE = "passive"          # holds the handle, small damping
    PUSH = "push"                # pushes toward a target with a given force
    WEAK = "weak"                # pushes with only a fraction of the force (fails the sub-task)
    STOP_EARLY = "stop_early"    # pushes, then gives up after a fraction of the distance


@dataclass(frozen=True)
class PatientSettings:
    """A snapshot of the current behaviours (for a GUI panel)."""

    gripMode: GripMode
    squeezeDuration: float
    period: float
    duty: float
    targets: tuple[float, ...]
    tolerance: float
    reactionDelay: float
    peakForce: float
    handleMode: HandleMode
    handleTarget: float
    pushForce: float
    weakFraction: float
    stopFraction: float


@dataclass(frozen=True)
class ElectrodeSite:
    """One stimulator channel = one electrode combination: how far its current path is from the motor point of
    the muscle it lies on, which way that muscle pushes the handle (+1 toward +x, -1) and its full force."""

    distance_cm: float
    direction: float = 1.0
    max_force_n: float = EVOKED_MAX_FORCE_N

    def threshold_ma(self, pulse_width_us: float) -> float:
        """The motor threshold (mA) at this pulse width."""
        pw = max(pulse_width_us, 1.0)
        strength_duration = (1.0 + CHRONAXIE_US / pw) / (1.0 + CHRONAXIE_US / REFERENCE_PULSE_WIDTH_US)
        return THRESHOLD_AT_MOTOR_POINT_MA * (1.0 + (self.distance_cm / THRESHOLD_DOUBLING_CM) ** 2) \
            * strength_duration

    def force_n(self, current_ma: float, pulse_width_us: float) -> float:
        """The steady evoked force (N, signed) at this current and pulse width."""
        if current_ma <= 0.0 or pulse_width_us <= 0.0:
            return 0.0
        ratio = current_ma / self.threshold_ma(pulse_width_us)
        if ratio <= 1.0:
            return 0.0
        return self.direction * self.max_force_n * (1.0 - math.exp(-(ratio - 1.0) / RECRUITMENT_SPREAD))


def random_electrode_sites(seed: int, channels: Sequence[int] = CHANNELS) -> dict[int, ElectrodeSite]:
    """Each channel's site for a simulated patient: distances uniform in SITE_DISTANCE_RANGE_CM from a generator
    of its own (the grip and handle noise of a seed stay as they were)."""
    rng = np.random.default_rng([int(seed), 32])
    lo, hi = SITE_DISTANCE_RANGE_CM
    return {int(ch): ElectrodeSite(float(rng.uniform(lo, hi))) for ch in channels}


class SimulatedPatient:
    def __init__(self, seed: int = 0, peak_force: float = GRIP_PEAK_N) -> None:
        self._lock = threading.RLock()
        self._rng = np.random.default_rng(seed)
        self._t: float | None = None
        self._grip = GRIP_REST_N  # noise-free muscle state
        self._pos = 0.0
        self._vel = 0.0
        self._peak = peak_force
        # grip behaviour
        self._grip_mode = GripMode.IDLE
        self._mode_t0: float | None = None  # when the behaviour took effect (patient clock)
        self._duration = 0.0
        self._period = 2.0
        self._duty = 0.5
        self._targets: tuple[float, ...] = ()
        self._tolerance = 0.005
        self._delay = 0.2
        self._arrived_at: float | None = None  # time of arrival at a target (AT_TARGET)
        self._armed = True                     # re-arms after leaving every target
        # handle behaviour
        self._handle_mode = HandleMode.PASSIVE
        self._handle_target = 0.0
        self._push_force = 15.0
        self._weak_fraction = 0.2
        self._stop_fraction = 0.5
        self._push_start: float | None = None  # handle position when the push began
        self._push_rise_s = 0.0  # the push's force builds up over this long (0: at once)
        self._push_t0: float | None = None  # the patient's time when the push began (taken with _push_start)
        self._gave_up = False
        # evoked response to stimulation
        self._sites = random_electrode_sites(seed)
        self._stim: dict[int, tuple[float, float]] = {}  # channel -> (mA, µs) being delivered
        self._evoked = 0.0  # noise-free evoked force (N), the muscle state

    # -- behaviours (any thread) --------------------------------------------------------------

    def idle(self) -> None:
        with self._lock:
            self._set_grip(GripMode.IDLE)

    def squeeze(self, duration: float = 1.0) -> None:
        """Squeeze now (from the patient's latest time) for ``duration`` s."""
        with self._lock:
            self._duration = max(0.0, duration)
            self._set_grip(GripMode.SQUEEZE)

    def squeeze_periodically(self, period: float = 2.0, duty: float = 0.5) -> None:
        if period <= 0.0 or not 0.0 <= duty <= 1.0:
            raise ValueError("period must be > 0 and duty within 0..1")
        with self._lock:
            self._period, self._duty = period, duty
            self._set_grip(GripMode.PERIODIC)

    def squeeze_at_targets(self, targets: Sequence[float], tolerance: float = 0.005,
                           duration: float = 1.0, reaction_delay: float = 0.2) -> None:
        """Squeeze for ``duration`` s, ``reaction_delay`` s after the handle arrives within
        ``tolerance`` (m) of any target; re-arms once the handle has left every target."""
        with self._lock:
            self._targets = tuple(float(x) for x in targets)
            self._tolerance = abs(tolerance)
            self._duration = max(0.0, duration)
            self._delay = max(0.0, reaction_delay)
            self._arrived_at = None
            self._armed = True
            self._set_grip(GripMode.AT_TARGET)

    def set_peak_force(self, newtons: float) -> None:
        with self._lock:
            self._peak = max(0.0, newtons)

    def passive(self) -> None:
        with self._lock:
            self._handle_mode = HandleMode.PASSIVE

    def push_to(self, target: float, force: float = 15.0, rise_s: float = 0.0) -> None:
        """Push the handle toward ``target`` with ``force`` newtons, built up linearly over ``rise_s`` seconds of the
        patient's own clock (an arm's force rises; a caller that stepped it from a thread of its own had its steps
        arrive together on a busy machine — a step of 15 N shook the handle past the speed envelope)."""
        with self._lock:
            self._start_push(HandleMode.PUSH, target, force)
            self._push_rise_s = max(0.0, rise_s)

    def fail_weak(self, target: float, force: float = 15.0, fraction: float = 0.2) -> None:
        """Push toward ``target`` with only ``fraction`` of ``force``."""
        with self._lock:
            self._weak_fraction = min(1.0, max(0.0, fraction))
            self._start_push(HandleMode.WEAK, target, force)

    def fail_stop_early(self, target: float, force: float = 15.0, fraction: float = 0.5) -> None:
        """Push toward ``target`` but give up (go passive) after ``fraction`` of the distance."""
        with self._lock:
            self._stop_fraction = min(1.0, max(0.0, fraction))
            self._start_push(HandleMode.STOP_EARLY, target, force)

    def set_electrode_distances(self, distances: Mapping[int | str, float],
                                directions: Mapping[int | str, float] | None = None) -> None:
        """Electrode-to-motor-point distance (cm) of each channel's combination (others keep theirs);
        ``directions``: +1 / -1 per channel (the way its muscle pushes the handle)."""
        with self._lock:
            for ch, d in distances.items():
                old = self._sites.get(int(ch), ElectrodeSite(0.0))
                self._sites[int(ch)] = ElectrodeSite(max(0.0, float(d)), old.direction, old.max_force_n)
            for ch, sign in (directions or {}).items():
                old = self._sites.get(int(ch), ElectrodeSite(1.0))
                self._sites[int(ch)] = ElectrodeSite(old.distance_cm, 1.0 if float(sign) >= 0 else -1.0,
                                                     old.max_force_n)

    def electrode_sites(self) -> dict[int, ElectrodeSite]:
        with self._lock:
            return dict(self._sites)

    def stimulation(self, t: float, channel: int, current_ma: float, pulse_width_us: float) -> None:
        """The stimulator delivers this on ``channel`` from ``t`` on (0 mA: nothing). Called by the RehaStim
        simulator for every change (app/devices/sim/rehastim_core.py)."""
        with self._lock:
            self._advance(t)
            if current_ma > 0 and pulse_width_us > 0:
                self._stim[int(channel)] = (float(current_ma), float(pulse_width_us))
            else:
                self._stim.pop(int(channel), None)

    def evoked_force(self, t: float) -> float:
        """The force (N) the stimulated muscles add on the handle at ``t`` (noise-free)."""
        with self._lock:
            self._advance(t)
            return self._evoked

    def settings(self) -> PatientSettings:
        with self._lock:
            return PatientSettings(self._grip_mode, self._duration, self._period, self._duty, self._targets,
                                   self._tolerance, self._delay, self._peak, self._handle_mode,
                                   self._handle_target, self._push_force, self._weak_fraction,
                                   self._stop_fraction)

    # -- what the simulators call --------------------------------------------------------------

    def update_handle(self, t: float, pos: float, vel: float) -> None:
        """Tell the patient where the handle is (LINarm simulator, every control step)."""
        with self._lock:
            self._advance(t)
            self._pos, self._vel = pos, vel
            self._track_arrival()

    def grip_force(self, t: float) -> float:
        """Grip force (N) at time ``t``."""
        with self._lock:
            self._advance(t)
            return max(0.0, self._grip + float(self._rng.normal(0.0, GRIP_NOISE_N)))

    def handle_force(self, t: float, handle_pos: float, handle_vel: float) -> float:
        """Force (N, + toward +x) the patient's arm applies on the handle."""
        with self._lock:
            self._advance(t)
            self._pos, self._vel = handle_pos, handle_vel
            self._track_arrival()
            # the stimulated muscles' force adds to whatever the patient does (noise included)
            noise = float(self._rng.normal(0.0, HANDLE_NOISE_N)) + self._evoked
            damping = -HANDLE_DAMPING_NS_M * handle_vel
            mode = self._handle_mode
            if mode is HandleMode.PASSIVE or (mode is HandleMode.STOP_EARLY and self._gave_up):
                return damping + noise
            if self._push_start is None:
                self._push_start, self._push_t0 = handle_pos, self._t
            error = self._handle_target - handle_pos
            if mode is HandleMode.STOP_EARLY:
                total = self._handle_target - self._push_start
                done = (handle_pos - self._push_start) / total if total != 0.0 else 1.0
                if done >= self._stop_fraction:
                    self._gave_up = True
                    return damping + noise
            gain = self._weak_fraction if mode is HandleMode.WEAK else 1.0
            push = gain * self._push_force * max(-1.0, min(1.0, error / HANDLE_PUSH_RAMP_M))
            if self._push_rise_s > 0.0 and self._push_t0 is not None and self._t is not None:
                push *= min(1.0, (self._t - self._push_t0) / self._push_rise_s)
            return push + damping + noise

    # -- internals (lock held) -----------------------------------------------------------------

    def _set_grip(self, mode: GripMode) -> None:
        self._grip_mode = mode
        self._mode_t0 = self._t

    def _start_push(self, mode: HandleMode, target: float, force: float) -> None:
        self._handle_mode = mode
        self._handle_target = target
        self._push_force = abs(force)
        self._push_start = None  # taken at the next handle_force call
        self._push_rise_s = 0.0
        self._gave_up = False

    def _track_arrival(self) -> None:
        if self._grip_mode is not GripMode.AT_TARGET:
            return
        near = any(abs(self._pos - x) <= self._tolerance for x in self._targets)
        if near and self._armed:
            self._arrived_at = self._t  # the patient's clock: robust to a caller a little behind
            self._armed = False
        elif not near:
            self._armed = True

    def _commanded(self, t: float) -> bool:
        """Whether the behaviour asks for a squeeze at time ``t``."""
        mode = self._grip_mode
        t0 = self._mode_t0 if self._mode_t0 is not None else t
        if mode is GripMode.SQUEEZE:
            return t0 <= t < t0 + self._duration
        if mode is GripMode.PERIODIC:
            return ((t - t0) % self._period) < self._duty * self._period
        if mode is GripMode.AT_TARGET and self._arrived_at is not None:
            start = self._arrived_at + self._delay
            return start <= t < start + self._duration
        return False

    def _evoked_goal(self) -> float:
        return sum(self._sites.get(ch, ElectrodeSite(SITE_DISTANCE_RANGE_CM[1])).force_n(i, w)
                   for ch, (i, w) in self._stim.items())

    def _advance(self, t: float) -> None:
        if self._t is None:
            self._t = t
            if self._mode_t0 is None:
                self._mode_t0 = t
            return
        if t <= self._t:
            return
        if self._mode_t0 is None:
            self._mode_t0 = self._t
        now = self._t
        evoked_goal = self._evoked_goal()
        evoked_tau = EVOKED_RISE_TAU_S if abs(evoked_goal) > abs(self._evoked) else EVOKED_FALL_TAU_S
        while now < t:
            step = min(_GRIP_STEP_S, t - now)
            on = self._commanded(now)
            goal = self._peak if on else GRIP_REST_N
            tau = GRIP_RISE_TAU_S if on else GRIP_FALL_TAU_S
            # exact first-order response over a step with a constant command
            self._grip = goal + (self._grip - goal) * math.exp(-step / tau)
            now += step
        if evoked_goal != 0.0 or self._evoked != 0.0:  # the stimulation is constant between two calls
            self._evoked = evoked_goal + (self._evoked - evoked_goal) * math.exp(-(t - self._t) / evoked_tau)
        self._t = t
