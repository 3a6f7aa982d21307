"""The assistance split (D2.2 §1, Fig. 2): the patient model's level α → robot and FES assistance.

    a_r = k_r · α        a_f = k_f · α        0 ≤ k_r, k_f ≤ 1 (per patient, set in the GUI)

α ∈ [-1, 1]: +1 full assistance, 0 neutral, −1 full resistance.  a_r sets three LINarm parameters
and a_f the FES pulse width through the therapist's maps (``AssistanceConfig``: each map takes
[0, 1] linearly onto [at_zero, at_one]).

Negative levels (resistance) stay inside the therapist's ranges; nothing is extrapolated:

* a_r ≥ 0 (assistance): k_m, k_a and k_t each = at_zero + a_r · (at_one − at_zero);
* a_r < 0 (resistance): k_t = at_zero — the assistive controller is off; it never pushes the
  handle away from the target (a negative gain would); k_a = at_zero — the lowest admittance the
  therapist allowed, so the handle feels heaviest; k_m = at_zero + |a_r| · (at_one − at_zero) — the
  VSA stiffens with resistance, so the slow admittance motion reaches the handle instead of being
  absorbed by a soft spring.  Every parameter is continuous at α = 0.
* a_f ≤ 0: pulse width at the map's floor (at_zero) — FES can only assist.

``AssistanceController`` applies the targets live through two injected callables (the lead wires
them to the LINarm and FES drivers, whose command paths run the safety checks): at most
``max_update_rate_hz``, only when a value moved by more than a small deadband, never the robot when
k_r = 0 (the robot parameters stay as the therapist set them), and not at all once the emergency
stop is latched.  α from the patient model passes through ``SafetySupervisor.clamp_assistance``.

Pure Python: no Qt, no I/O; thread-safe (α arrives on the patient-model driver thread, gains and
maps change from the GUI).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

from app.core.config import AssistanceConfig, AssistanceMap

if TYPE_CHECKING:
    from app.safety.supervisor import SafetySupervisor

log = logging.getLogger(__name__)

DEADBAND: float = 0.002  # fraction of a map's span below which a change is not sent again


@dataclass(frozen=True)
class AssistanceTargets:
    alpha: float           # the level after clamping, -1..1
    a_r: float             # robot assistance level, -1..1
    a_f: float             # FES assistance level, -1..1
    k_m: float             # VSA stiffness, N/m
    k_a: float             # admittance gain, m/(s·N)
    k_t: float             # assistive gain, N/m
    pulse_width_us: float  # FES pulse width, µs


def map_level(m: AssistanceMap, level: float) -> float:
    """``level`` in [0, 1] (clipped) onto [at_zero, at_one]."""
    x = min(1.0, max(0.0, level))
    return m.at_zero + x * (m.at_one - m.at_zero)


class AssistanceSplit:
    """The pure split + maps."""

    def __init__(self, config: AssistanceConfig | None = None) -> None:
        self.config = config or AssistanceConfig()

    @staticmethod
    def levels(alpha: float, k_r: float, k_f: float) -> tuple[float, float]:
        """(a_r, a_f) alone: what a patient-model sample carries, at its rate, without the maps."""
        alpha = min(1.0, max(-1.0, alpha))
        return min(1.0, max(0.0, k_r)) * alpha, min(1.0, max(0.0, k_f)) * alpha

    def compute(self, alpha: float, k_r: float, k_f: float) -> AssistanceTargets:
        if any(math.isnan(x) for x in (alpha, k_r, k_f)):
            raise ValueError(f"NaN in the assistance split: alpha={alpha}, k_r={k_r}, k_f={k_f}")
        alpha = min(1.0, max(-1.0, alpha))
        k_r = min(1.0, max(0.0, k_r))
        k_f = min(1.0, max(0.0, k_f))
        c = self.config
        a_r = k_r * alpha
        a_f = k_f * alpha
        assist = max(a_r, 0.0)
        return AssistanceTargets(
            alpha=alpha, a_r=a_r, a_f=a_f,
            k_m=map_level(c.k_m_stiffness_n_m, abs(a_r)),
            k_a=map_level(c.k_a_admittance_m_s_n, assist),
            k_t=map_level(c.k_t_assistive_n_m, assist),
            pulse_width_us=map_level(c.fes_pulse_width_us, max(a_f, 0.0)),
        )


RobotApply = Callable[[float, float, float], None]  # (k_m N/m, k_a m/(s·N), k_t N/m)
FesApply = Callable[[float | None], None]           # pulse width µs; None = the profile's (α lost)


class AssistanceLevels(Protocol):
    """What a device's frames need of the assistance (the patient model's a_r, a_f; the VR frame's α): the
    last α applied and the split with the gains in force. :class:`AssistanceController` is one."""

    @property
    def alpha(self) -> float | None: ...

    def levels(self, alpha: float) -> tuple[float, float]: ...


class AssistanceInactive(Exception):
    """An apply callable's way to say "not now" (e.g. the robot is not in an assisted mode): not an
    error, nothing counted; the targets are applied once the device takes them again."""


class AssistanceController:
    """Applies the split live.  The manager holds one at ``manager.assistance``.

    ``update_alpha`` (any thread, e.g. a patient-model sample listener) and ``set_gains`` /
    ``set_config`` (GUI) recompute the targets; changes are sent at most ``max_update_rate_hz``;
    a change that arrives too soon is kept pending and sent by the next call or by ``flush`` (call it
    from a timer if α may stop arriving).
    """

    def __init__(self, config: AssistanceConfig, apply_robot: RobotApply | None,
                 apply_fes_pulse_width: FesApply | None, supervisor: SafetySupervisor | None = None,
                 clock: Callable[[], float] = time.monotonic, alpha_max_age_s: float = 0.4) -> None:
        self._lock = threading.RLock()
        self._split = AssistanceSplit(config)
        self._apply_robot = apply_robot
        self._apply_fes = apply_fes_pulse_width
        self._supervisor = supervisor
        self._clock = clock
        self._k_r = config.k_r
        self._k_f = config.k_f
        self._alpha: float | None = None
        self._alpha_time = -math.inf
        # α older than this is not applied, whatever triggers it (a gain change, a flush): at 100 Hz from
        # the model, an old α means the model is gone — before the link is even declared lost (0.5 s).
        self.alpha_max_age_s = alpha_max_age_s
        self._targets: AssistanceTargets | None = None
        self._pending = False
        self._last_apply = -math.inf
        self.applied_robot: tuple[float, float, float] | None = None
        self.applied_pulse_width_us: float | None = None
        self.apply_count = 0
        self.errors = 0
        self.last_error = ""
        self.ignored_nan = 0

    # ------------------------------------------------------------------ state
    @property
    def config(self) -> AssistanceConfig:
        return self._split.config

    @property
    def k_r(self) -> float:
        return self._k_r

    @property
    def k_f(self) -> float:
        return self._k_f

    @property
    def alpha(self) -> float | None:
        """The last α received (after clamping), None before the first."""
        return self._alpha

    @property
    def targets(self) -> AssistanceTargets | None:
        """The targets of the current α and gains (None without an α); computed when first needed."""
        with self._lock:
            if self._targets is None and self._alpha is not None:
                self._targets = self._split.compute(self._alpha, self._k_r, self._k_f)
            return self._targets

    def preview(self, alpha: float) -> AssistanceTargets:
        """What ``alpha`` would give with the current gains and maps (nothing is applied)."""
        return self._split.compute(alpha, self._k_r, self._k_f)

    def levels(self, alpha: float) -> tuple[float, float]:
        """(a_r, a_f) that ``alpha`` gives with the current gains: ``preview`` without the maps."""
        return AssistanceSplit.levels(alpha, self._k_r, self._k_f)

    # ------------------------------------------------------------------ inputs
    def update_alpha(self, alpha: float, now: float | None = None) -> None:
        if math.isnan(alpha):
            self.ignored_nan += 1
            return
        if self._supervisor is not None:
            alpha = self._supervisor.clamp_assistance("alpha", alpha, -1.0, 1.0)
        else:
            alpha = min(1.0, max(-1.0, alpha))
        with self._lock:
            self._alpha = alpha
            self._alpha_time = self._clock() if now is None else now
            self._recompute(now)

    def invalidate(self) -> None:
        """The patient model is lost: forget α, so no later gain or map change re-applies a stale one, and
        return what α had set to its non-α value: the FES pulse width to the profile's (override None),
        the robot's parameters to the split at α = 0 (assistive gain at its floor: no pull from a model
        that is gone)."""
        with self._lock:
            self._alpha = None
            self._targets = None
            self._pending = False
            if self.applied_pulse_width_us is not None and self._apply_fes is not None:
                if self._call("FES", self._apply_fes, None):
                    self.applied_pulse_width_us = None
            if self.applied_robot is not None and self._apply_robot is not None:
                neutral = self._split.compute(0.0, self._k_r, self._k_f)
                if self._call("robot", self._apply_robot, neutral.k_m, neutral.k_a, neutral.k_t):
                    self.applied_robot = None

    def forget_applied(self, robot: bool = False, fes: bool = False) -> None:
        """Another owner has taken the robot's gains or the stimulator's pulse width (a run, #36): what this
        controller applied last is no longer what the device has, so the next α applies it again in full."""
        with self._lock:
            if robot:
                self.applied_robot = None
            if fes:
                self.applied_pulse_width_us = None

    def set_gains(self, k_r: float, k_f: float, now: float | None = None) -> None:
        for name, v in (("k_r", k_r), ("k_f", k_f)):
            if not 0.0 <= v <= 1.0:  # also refuses NaN
                raise ValueError(f"{name} must be in 0..1, got {v!r}")
        with self._lock:
            self._k_r, self._k_f = float(k_r), float(k_f)
            self._split = AssistanceSplit(replace(self._split.config, k_r=self._k_r, k_f=self._k_f))
            self._recompute(now)

    def set_config(self, config: AssistanceConfig, now: float | None = None) -> None:
        """New maps / rate (and gains) from the GUI."""
        with self._lock:
            self._split = AssistanceSplit(config)
            self._k_r, self._k_f = config.k_r, config.k_f
            self._recompute(now)

    def flush(self, now: float | None = None) -> bool:
        """Send a pending change if the rate allows it; True when something was applied."""
        with self._lock:
            return self._apply_if_due(self._clock() if now is None else now)

    # ------------------------------------------------------------------ internals
    def _recompute(self, now: float | None) -> None:
        if self._alpha is None:
            return
        self._targets = None  # the maps run when the targets are due to be applied (or read), not per α
        self._pending = True
        self._apply_if_due(self._clock() if now is None else now)

    def _apply_if_due(self, now: float) -> bool:
        if not self._pending or self._alpha is None:
            return False
        if now - self._alpha_time > self.alpha_max_age_s:
            self._pending = False  # a stale α is never applied
            return False
        if now - self._last_apply < 1.0 / self.config.max_update_rate_hz:
            return False
        self._pending = False
        if self._supervisor is not None and self._supervisor.estop_latched:
            return False  # after an emergency stop nothing is re-energised from here
        tg = self.targets
        assert tg is not None
        c = self.config
        applied = attempted = False
        robot = (tg.k_m, tg.k_a, tg.k_t)
        if self._k_r > 0.0 and self._apply_robot is not None and _moved(
                self.applied_robot, robot,
                (c.k_m_stiffness_n_m, c.k_a_admittance_m_s_n, c.k_t_assistive_n_m)):
            attempted = True
            if self._call("robot", self._apply_robot, *robot):
                self.applied_robot = robot
                applied = True
        if self._apply_fes is not None and _moved(
                None if self.applied_pulse_width_us is None else (self.applied_pulse_width_us,),
                (tg.pulse_width_us,), (c.fes_pulse_width_us,)):
            attempted = True
            if self._call("FES", self._apply_fes, tg.pulse_width_us):
                self.applied_pulse_width_us = tg.pulse_width_us
                applied = True
        if attempted:
            # Refused ("not now": robot not in an assisted mode, no FES) counts too: it is retried at the
            # update rate, not at every α (100 Hz of maps and exceptions for nothing).
            self._last_apply = now
        if applied:
            self.apply_count += 1
        return applied

    def _call(self, what: str, fn: Callable[..., None], *args: float | None) -> bool:
        try:
            fn(*args)
        except AssistanceInactive:
            return False
        except Exception as exc:  # refused by safety, link down: the loop keeps running
            self.errors += 1
            self.last_error = f"{what}: {exc}"
            log.warning("assistance: %s update refused: %s", what, exc)
            return False
        return True


def _moved(old: tuple[float, ...] | None, new: tuple[float, ...], maps: tuple[AssistanceMap, ...]) -> bool:
    if old is None:
        return True
    for a, b, m in zip(old, new, maps, strict=True):
        span = abs(m.at_one - m.at_zero)
        at_end = b in (m.at_zero, m.at_one)  # the ends of a map are always reached exactly
        if abs(a - b) > DEADBAND * span or (a != b and (span == 0.0 or at_end)):
            return True
    return False
