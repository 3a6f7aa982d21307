"""The one simulated patient, shared by the LINarm simulator and the physiological-board simulator.

Two things a patient does to the devices:

* grips the handle: ``grip_force(t)`` (N) follows a behaviour -- idle, squeeze now for a duration,
  squeeze periodically, or squeeze when the handle reaches one of some target positions -- through
  first-order muscle dynamics (rise tau 0.1 s: > 20 N about 70 ms after the command; peak ~38 N;
  release tau 0.15 s) plus small noise;
* pushes the handle: ``handle_force(t, pos, vel)`` (N, + toward +x) -- passive (a small damping),
  push toward a target with a given force, or fail the sub-task (too weak, or stops early) so the
  patient-model tests can watch the assistance rise.

Time is the simulators' clock (s): every caller must use the same clock (the app uses
time.monotonic()); an older ``t`` than already seen just returns the current value.
Behaviours may be changed from any thread (GUI panel, test, script): every public method takes
the same lock.  Deterministic for a given seed and call sequence.
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Grip dynamics (one place).
GRIP_REST_N = 1.0         # hand resting on the handle
GRIP_PEAK_N = 38.0        # voluntary squeeze plateau
GRIP_RISE_TAU_S = 0.10
GRIP_FALL_TAU_S = 0.15
GRIP_NOISE_N = 0.3        # per-sample standard deviation
_GRIP_STEP_S = 0.005      # integration sub-step so periodic edges are resolved

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
        self._gave_up = False

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

    def push_to(self, target: float, force: float = 15.0) -> None:
        with self._lock:
            self._start_push(HandleMode.PUSH, target, force)

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
            noise = float(self._rng.normal(0.0, HANDLE_NOISE_N))
            damping = -HANDLE_DAMPING_NS_M * handle_vel
            mode = self._handle_mode
            if mode is HandleMode.PASSIVE or (mode is HandleMode.STOP_EARLY and self._gave_up):
                return damping + noise
            if self._push_start is None:
                self._push_start = handle_pos
            error = self._handle_target - handle_pos
            if mode is HandleMode.STOP_EARLY:
                total = self._handle_target - self._push_start
                done = (handle_pos - self._push_start) / total if total != 0.0 else 1.0
                if done >= self._stop_fraction:
                    self._gave_up = True
                    return damping + noise
            gain = self._weak_fraction if mode is HandleMode.WEAK else 1.0
            push = gain * self._push_force * max(-1.0, min(1.0, error / HANDLE_PUSH_RAMP_M))
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
        while now < t:
            step = min(_GRIP_STEP_S, t - now)
            on = self._commanded(now)
            goal = self._peak if on else GRIP_REST_N
            tau = GRIP_RISE_TAU_S if on else GRIP_FALL_TAU_S
            # exact first-order response over a step with a constant command
            self._grip = goal + (self._grip - goal) * math.exp(-step / tau)
            now += step
        self._t = t
