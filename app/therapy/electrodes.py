"""Electrode arrays (issue #32): muscular districts, their candidate electrode combinations, and the set-up
procedure that finds each district's best combination.

The D2.1 design puts four electrodes per district in a fabric array so that "suboptimal alignment can be
improved by software choice of the best combination of electrodes". Each candidate combination (an electrode
pair of the array) is wired to its own stimulator channel (``devices.fes.electrodes`` in the configuration).

The procedure (:class:`ElectrodeSetup`) is Qt-free and device-free: it works through small ports
(:class:`SetupPorts`: start a test burst, stop stimulation, hold/release the arm, read the handle, the clock,
the supervisor's hold reason, the session record), so it runs on a virtual clock in tests and is wired to the
application in one place (:func:`app_ports`). For one district, with the robot holding the arm still, every
candidate combination gets short ramped test bursts from ``start_ma`` up to the therapist's ceiling (never
above the patient's caps: :func:`combination_ceiling`), each measured as the change of the LINarm's
interaction force (baseline-subtracted, in the district's direction) and the handle's motion. The proposal is
the combination with the largest response per mA (:func:`response_per_ma`, docs/fes.md "Electrode set-up").
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from app.safety.fes_limits import FesLimits, rms_current_ma
from app.wire.sciencemode import MAX_CURRENT_MA, MAX_PULSE_WIDTH_US

log = logging.getLogger(__name__)

Direction = Literal["positive", "negative", "either"]
MIN_READINGS = 3  # distinct LINarm readings a baseline or a measurement needs
# How long a measurement waits past its window for readings stamped in it (a driver that read late; the stream
# is in order, so a reading stamped after the window says none is still coming): longer than any read delay a
# working computer gives, short beside a burst's rest.
LATE_READINGS_S = 0.5
# The plan's bounds (#37: a step of 1e-12 mA looped without end, a pulse width of 1e6 µs "gave no response"):
MIN_STEP_MA = 1.0  # the stimulator takes whole mA: a smaller step only repeats a current
DEFAULT_STEP_MA = 2.0
# Per combination: the stimulator's whole range in default steps (63; ~3 s a burst with its rest). The default
# plan to 40 mA gives 18; a 1 mA step to the range's top (121) is refused: raise the step or lower the ceiling.
MAX_BURSTS = math.ceil(MAX_CURRENT_MA / DEFAULT_STEP_MA)
DISCOMFORT_MAX = 10  # the patient's rating: 0 = no discomfort .. 10 = the worst imaginable (numeric scale)


# ---------------------------------------------------------------------------------------------- the arrays
@dataclass(frozen=True)
class Combination:
    """One candidate: the stimulator channel its electrode pair is wired to, and which electrodes they are."""

    channel: int
    electrodes: str = ""

    @property
    def label(self) -> str:
        pair = f"electrodes {self.electrodes}, " if self.electrodes else ""
        return f"{pair}channel {self.channel}"


@dataclass(frozen=True)
class District:
    name: str
    combinations: tuple[Combination, ...]
    direction: Direction = "either"

    def combination_on(self, channel: int) -> Combination | None:
        return next((c for c in self.combinations if c.channel == channel), None)


def districts_from_config(electrodes: Mapping[str, Any]) -> dict[str, District]:
    """``devices.fes.electrodes`` (app.core.config.ElectrodeDistrictConfig per name) as :class:`District` objects."""
    return {name: District(name, tuple(Combination(int(c.channel), str(c.electrodes)) for c in d.combinations),
                           d.direction)
            for name, d in electrodes.items()}


# ---------------------------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class SetupPlan:
    """How the test bursts are given. Currents in mA, times in s."""

    ceiling_ma: float  # the therapist's ceiling; the patient's caps may lower it per channel
    start_ma: float = 6.0
    step_ma: float = DEFAULT_STEP_MA
    pulse_width_us: float = 250.0
    frequency_hz: float = 40.0
    ramp_s: float = 1.0  # at least; longer when the limiter's start ramp or rate of rise needs it
    hold_s: float = 0.6
    ramp_down_s: float = 0.2
    measure_s: float = 0.3  # the end of the hold that is averaged (the muscle has risen by then)
    baseline_s: float = 0.3  # averaged just before each burst
    rest_s: float = 1.0  # between bursts
    detect_n: float = 0.5  # a smaller response is no response (noise, a twitch of something else)
    stop_at_n: float | None = None  # stop climbing a combination once its response reaches this
    max_discomfort: int = 6  # combinations rated above this are not proposed
    sample_period_s: float = 0.01

    def __post_init__(self) -> None:
        for name in ("ceiling_ma", "start_ma", "step_ma", "pulse_width_us", "frequency_hz", "hold_s", "measure_s",
                     "sample_period_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        for name in ("ramp_s", "ramp_down_s", "baseline_s", "rest_s", "detect_n"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be 0 or more, got {value!r}")
        if self.measure_s > self.hold_s:
            raise ValueError(f"measure_s ({self.measure_s} s) must not be longer than hold_s ({self.hold_s} s)")
        if not 0 <= self.max_discomfort <= DISCOMFORT_MAX:
            raise ValueError(f"max_discomfort must be within 0..{DISCOMFORT_MAX}")
        # Within the stimulator's range and a bounded number of bursts, refused before anything starts (#37).
        if self.ceiling_ma > MAX_CURRENT_MA:
            raise ValueError(f"the ceiling of {self.ceiling_ma:g} mA is above the stimulator's range "
                             f"(at most {MAX_CURRENT_MA} mA)")
        if self.start_ma > self.ceiling_ma:
            raise ValueError(f"the start current ({self.start_ma:g} mA) is above the ceiling ({self.ceiling_ma:g} mA): "
                             "no test burst would be given")
        if self.step_ma < MIN_STEP_MA:
            raise ValueError(f"the step of {self.step_ma:g} mA is too small: the stimulator takes whole mA, so the "
                             f"step must be at least {MIN_STEP_MA:g} mA")
        if self.pulse_width_us > MAX_PULSE_WIDTH_US:
            raise ValueError(f"the pulse width of {self.pulse_width_us:g} µs is outside the stimulator's range "
                             f"(at most {MAX_PULSE_WIDTH_US} µs)")
        bursts = self.burst_count(self.ceiling_ma)
        if bursts > MAX_BURSTS:
            raise ValueError(f"{bursts} test bursts per combination (from {self.start_ma:g} to {self.ceiling_ma:g} mA "
                             f"in {self.step_ma:g} mA steps) is more than the {MAX_BURSTS} allowed: raise the step or "
                             "lower the ceiling")

    def burst_count(self, ceiling_ma: float) -> int:
        """How many steps fit from start_ma up to ``ceiling_ma`` (the ladder's length at most), computed, not
        counted."""
        if ceiling_ma + 1e-9 < self.start_ma:
            return 0
        return math.floor((ceiling_ma - self.start_ma) / self.step_ma + 1e-9) + 1

    def ladder(self, ceiling_ma: float) -> list[int]:
        """The test currents (whole mA, as the stimulator takes them) from start_ma up to ``ceiling_ma``."""
        out: list[int] = []
        for k in range(min(self.burst_count(ceiling_ma), MAX_BURSTS)):
            current = math.floor(self.start_ma + k * self.step_ma + 1e-9)
            if current > ceiling_ma + 1e-9:
                break
            if not out or current > out[-1]:
                out.append(current)
        return out


def combination_ceiling(plan: SetupPlan, limits: FesLimits, channel: int) -> tuple[int, str]:
    """The highest test current (whole mA) on ``channel`` and what sets it: the therapist's ceiling, the
    channel's cap (site or patient, the tightest: FesLimits.caps_for) or its r.m.s. limit at the test pulse
    width and frequency. 0 when the test pulse width itself is above the channel's cap."""
    cap_current, cap_width, cap_rms = limits.caps_for(channel)
    if plan.pulse_width_us > cap_width + 1e-9:
        return 0, f"the test pulse width {plan.pulse_width_us:g} µs is above the cap of {cap_width:g} µs"
    rms_per_ma = rms_current_ma(1.0, plan.pulse_width_us, plan.frequency_hz)
    rms_ceiling = cap_rms / rms_per_ma if rms_per_ma > 0 else math.inf
    candidates = [(plan.ceiling_ma, "the therapist's ceiling"), (cap_current, "the channel's cap"),
                  (rms_ceiling, "the r.m.s. limit")]
    value, why = min(candidates, key=lambda c: c[0])
    return max(0, math.floor(value + 1e-9)), why


# ---------------------------------------------------------------------------------------------- bursts
@dataclass(frozen=True)
class Burst:
    """One test burst: a current trapezoid on one channel (0 → current over ramp_s, hold, → 0 over ramp_down_s)
    at a constant pulse width and frequency."""

    channel: int
    current_ma: int
    pulse_width_us: int
    frequency_hz: float
    ramp_s: float
    hold_s: float
    ramp_down_s: float

    @property
    def duration_s(self) -> float:
        return self.ramp_s + self.hold_s + self.ramp_down_s


def burst_ramp_s(plan: SetupPlan, limits: FesLimits, channel: int, current_ma: float) -> float:
    """The ramp a burst needs so that the limiter never holds it back: the plan's ramp, or longer when the
    start ramp (caps rise from 0 over start_ramp_s) or the rates of rise need it; one update period spare."""
    cap_current, cap_width, _ = limits.caps_for(channel)
    needed = [plan.ramp_s, current_ma / limits.max_current_rise_ma_s,
              plan.pulse_width_us / limits.max_pulse_width_rise_us_s]
    if limits.start_ramp_s > 0:
        needed += [limits.start_ramp_s * current_ma / max(cap_current, 1e-9),
                   limits.start_ramp_s * plan.pulse_width_us / max(cap_width, 1e-9)]
    return max(needed) + 1.0 / plan.frequency_hz


@dataclass(frozen=True)
class ArmReading:
    """The handle now: the LINarm's interaction force (N, + toward +x) and position (m)."""

    t: float
    force_n: float
    position_m: float


@dataclass(frozen=True)
class BurstResult:
    district: str
    channel: int
    electrodes: str
    current_ma: int
    pulse_width_us: int
    baseline_n: float
    response_n: float  # baseline-subtracted, in the district's direction (either: its size)
    motion_mm: float  # largest handle displacement from the baseline position during the measurement
    samples: int

    def record(self) -> dict[str, Any]:
        return {"district": self.district, "channel": self.channel, "electrodes": self.electrodes,
                "current_ma": self.current_ma, "pulse_width_us": self.pulse_width_us,
                "baseline_n": round(self.baseline_n, 3), "response_n": round(self.response_n, 3),
                "motion_mm": round(self.motion_mm, 2), "samples": self.samples}


@dataclass
class CombinationResult:
    combination: Combination
    ceiling_ma: int
    ceiling_reason: str
    bursts: list[BurstResult] = field(default_factory=list)
    discomfort: int | None = None  # the patient's rating, entered by the therapist

    def response_per_ma(self, detect_n: float) -> float:
        return response_per_ma(self.bursts, detect_n)

    def motor_threshold_ma(self, detect_n: float) -> int | None:
        return next((b.current_ma for b in self.bursts if b.response_n >= detect_n), None)

    @property
    def max_current_ma(self) -> int:
        return max((b.current_ma for b in self.bursts), default=0)


def response_per_ma(bursts: Sequence[BurstResult], detect_n: float) -> float:
    """The figure the proposal ranks by: the largest response per mA (N/mA) among a combination's bursts
    whose response reached ``detect_n`` (0 when none did). The best of its own bursts, so that a combination
    saturating early is not penalised for being tested further up its curve."""
    return max((b.response_n / b.current_ma for b in bursts if b.response_n >= detect_n and b.current_ma > 0),
               default=0.0)


@dataclass(frozen=True)
class Proposal:
    channel: int | None  # None: no combination gave a response (or none was acceptable)
    reason: str
    ranking: tuple[tuple[int, float], ...]  # (channel, response per mA), best first, acceptable ones only


def propose(results: Sequence[CombinationResult], plan: SetupPlan) -> Proposal:
    """The combination with the largest response per mA among those that responded and whose discomfort rating
    (if given) is at most ``plan.max_discomfort``; ties go to the lower motor threshold, then the lower channel."""
    ranked: list[tuple[float, float, int]] = []
    excluded: list[str] = []
    for r in results:
        eff = r.response_per_ma(plan.detect_n)
        if r.discomfort is not None and r.discomfort > plan.max_discomfort:
            excluded.append(f"channel {r.combination.channel} rated {r.discomfort}/10")
            continue
        if eff <= 0:
            continue
        threshold = r.motor_threshold_ma(plan.detect_n)
        ranked.append((eff, -(threshold if threshold is not None else math.inf), -r.combination.channel))
    ranked.sort(reverse=True)
    ranking = tuple((-ch, eff) for eff, _thr, ch in ranked)
    if not ranking:
        why = f"no combination gave a response of at least {plan.detect_n:g} N"
        if excluded:
            why += " at an acceptable discomfort (" + ", ".join(excluded) + ")"
        return Proposal(None, why, ())
    best, eff = ranking[0]
    reason = f"channel {best}: the largest response per mA ({eff:.3f} N/mA)"
    if len(ranking) > 1:
        reason += f", {100 * (eff / ranking[1][1] - 1):.0f} % above the next (channel {ranking[1][0]})" \
            if ranking[1][1] > 0 else ""
    if excluded:
        reason += "; not proposed for discomfort: " + ", ".join(excluded)
    return Proposal(best, reason, ranking)


@dataclass
class SetupResult:
    district: District
    plan: SetupPlan
    combinations: list[CombinationResult]
    proposal: Proposal | None = None
    aborted: str = ""  # why it ended early ('' = completed)

    def combination(self, channel: int) -> CombinationResult | None:
        return next((r for r in self.combinations if r.combination.channel == channel), None)

    def repropose(self) -> Proposal:
        """The proposal again (after a discomfort rating changed)."""
        self.proposal = propose(self.combinations, self.plan)
        return self.proposal


# ---------------------------------------------------------------------------------------------- ports
class SetupAborted(Exception):
    """The procedure ended early; ``reason`` says why (Stop, the e-stop, a refused burst, a lost device)."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


@dataclass(frozen=True)
class SetupPorts:
    """What the procedure needs from the world, as plain callables.

    ``start_burst(burst)`` starts one test burst through the stimulator's checked path (raises with a reason
    when refused) and returns at once; ``stimulating()`` says whether it is still running; ``stop(reason)``
    stops stimulation at once and never raises. ``hold_arm()`` puts the robot in position hold where it is;
    ``release_arm()`` puts it back as it was. ``read_arm()`` is the latest handle reading (or None);
    ``arm_readings()``, when given, every reading that came since its last call (the stream's queue): a
    measurement then counts every reading stamped in its window, however late this thread polls (a busy
    computer), instead of the latest one at each poll. ``close()`` ends what the ports hold (that queue).
    ``hold_reason()`` is the supervisor's: '' unless the e-stop is latched or a STOP alarm is open. ``now`` /
    ``sleep`` are the clock. ``record(kind, data)`` puts an event in the session record."""

    start_burst: Callable[[Burst], None]
    stimulating: Callable[[], bool]
    stop: Callable[[str], None]
    hold_arm: Callable[[], None]
    release_arm: Callable[[], None]
    read_arm: Callable[[], ArmReading | None]
    hold_reason: Callable[[], str]
    arm_readings: Callable[[], list[ArmReading]] | None = None
    close: Callable[[], None] = lambda: None
    now: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    record: Callable[[str, dict[str, Any]], None] = lambda _kind, _data: None


# Progress for a dialog or a script: ("started" | "burst" | "combination" | "finished" | "aborted", payload)
ProgressListener = Callable[[str, Any], None]


class ElectrodeSetup:
    """The set-up of one district. ``run()`` blocks (a worker thread in the app, the test's thread on a virtual
    clock); ``stop(reason)`` from any thread stops stimulation at once and makes ``run()`` end."""

    def __init__(self, district: District, plan: SetupPlan, limits: FesLimits, ports: SetupPorts,
                 listener: ProgressListener | None = None) -> None:
        if not district.combinations:
            raise ValueError(f"district {district.name!r} has no electrode combinations")
        self.district = district
        self.plan = plan
        self.limits = limits
        self.ports = ports
        self.listener = listener
        self._stop_reason = ""
        self._lock = threading.Lock()
        self.result = SetupResult(district, plan, [
            CombinationResult(c, *combination_ceiling(plan, limits, c.channel)) for c in district.combinations])

    # ------------------------------------------------------------------ control (any thread)
    def stop(self, reason: str = "stopped by the therapist") -> None:
        with self._lock:
            if not self._stop_reason:
                self._stop_reason = reason
        self.ports.stop(reason)  # at once, from the caller's thread: not when the worker next looks

    @property
    def stopping(self) -> bool:
        return bool(self._stop_reason)

    # ------------------------------------------------------------------ the procedure
    def run(self) -> SetupResult:
        p, ports, district = self.plan, self.ports, self.district
        result = self.result
        ports.record("electrode_setup_started", {
            "district": district.name, "ceiling_ma": p.ceiling_ma, "start_ma": p.start_ma, "step_ma": p.step_ma,
            "pulse_width_us": p.pulse_width_us, "frequency_hz": p.frequency_hz,
            "combinations": [{"channel": r.combination.channel, "electrodes": r.combination.electrodes,
                              "ceiling_ma": r.ceiling_ma, "ceiling_set_by": r.ceiling_reason}
                             for r in result.combinations]})
        self._emit("started", result)
        held = False
        try:
            self._check()
            held = True  # a hold that fails half-way is still undone
            try:
                ports.hold_arm()
            except SetupAborted:
                raise
            except Exception as exc:  # refused by the supervisor, the controller, or no link
                raise SetupAborted(f"the robot could not hold the arm: {getattr(exc, 'reason', exc)}") from exc
            for combo in result.combinations:
                for current in p.ladder(combo.ceiling_ma):
                    burst = self._burst(combo, current)
                    combo.bursts.append(burst)
                    ports.record("electrode_burst", burst.record())
                    self._emit("burst", burst)
                    if p.stop_at_n is not None and burst.response_n >= p.stop_at_n:
                        break
                    self._wait(p.rest_s)
                self._emit("combination", combo)
            result.repropose()
            proposal = result.proposal
            assert proposal is not None
            ports.record("electrode_setup_result", {
                "district": district.name, "proposed_channel": proposal.channel, "reason": proposal.reason,
                "ranking": [{"channel": ch, "response_per_ma": round(eff, 4)} for ch, eff in proposal.ranking],
                "motor_thresholds_ma": {r.combination.channel: r.motor_threshold_ma(p.detect_n)
                                        for r in result.combinations}})
            self._emit("finished", result)
        except Exception as exc:  # SetupAborted, or anything unexpected: stimulation stops either way
            reason = exc.reason if isinstance(exc, SetupAborted) else f"the set-up failed: {exc}"
            if not isinstance(exc, SetupAborted):
                log.exception("electrode set-up failed")
            result.aborted = reason
            ports.stop(reason)
            result.repropose()
            ports.record("electrode_setup_aborted", {"district": district.name, "reason": reason,
                                                     "bursts": sum(len(r.bursts) for r in result.combinations)})
            self._emit("aborted", result)
        finally:
            if held:
                try:
                    ports.release_arm()
                except Exception as exc:  # the robot is still held: say so, the therapist releases it
                    log.warning("electrode set-up: the arm could not be released: %s", exc)
                    ports.record("electrode_setup_release_failed", {"district": district.name, "error": str(exc)})
            ports.close()
        return result

    def _burst(self, combo: CombinationResult, current: int) -> BurstResult:
        p, ports = self.plan, self.ports
        channel = combo.combination.channel
        baseline = self._sample(p.baseline_s)
        if len(baseline) < MIN_READINGS:
            raise SetupAborted(f"too few LINarm readings before the burst ({len(baseline)}): is it connected and "
                               "streaming?")
        f0 = sum(r.force_n for r in baseline) / len(baseline)
        x0 = sum(r.position_m for r in baseline) / len(baseline)
        burst = Burst(channel, current, round(p.pulse_width_us), p.frequency_hz,
                      burst_ramp_s(p, self.limits, channel, current), p.hold_s, p.ramp_down_s)
        self._check()
        try:
            ports.start_burst(burst)
        except Exception as exc:
            raise SetupAborted(f"the test burst of {current} mA on channel {channel} was refused: "
                               f"{getattr(exc, 'reason', exc)}") from exc
        t0 = ports.now()
        plateau_end = t0 + burst.ramp_s + burst.hold_s
        self._wait_until(plateau_end - p.measure_s)
        window = self._sample(p.measure_s, since=plateau_end - p.measure_s)
        if not ports.stimulating() and ports.now() < t0 + burst.duration_s:
            raise SetupAborted(f"stimulation on channel {channel} ended before the burst did (stopped elsewhere)")
        self._wait_until(t0 + burst.duration_s)
        window = self._late(window, plateau_end - p.measure_s, plateau_end)
        if len(window) < MIN_READINGS:
            raise SetupAborted(f"too few LINarm readings during the burst ({len(window)}): the LINarm stopped "
                               "sending, or this computer is too busy to measure")
        mean = sum(r.force_n for r in window) / len(window)
        change = mean - f0
        direction = self.district.direction
        response = change if direction == "positive" else -change if direction == "negative" else abs(change)
        motion = max(abs(r.position_m - x0) for r in window) * 1000.0
        return BurstResult(self.district.name, channel, combo.combination.electrodes, current, burst.pulse_width_us,
                           f0, response, motion, len(window))

    # ------------------------------------------------------------------ waiting, always interruptible
    def _check(self) -> None:
        if self._stop_reason:
            raise SetupAborted(self._stop_reason)
        why = self.ports.hold_reason()
        if why:
            raise SetupAborted(f"stopped: {why}")

    def _wait_until(self, deadline: float) -> None:
        ports = self.ports
        while True:
            self._check()
            left = deadline - ports.now()
            if left <= 1e-9:
                return
            ports.sleep(min(left, self.plan.sample_period_s))

    def _wait(self, seconds: float) -> None:
        self._wait_until(self.ports.now() + seconds)

    def _sample(self, seconds: float, since: float | None = None) -> list[ArmReading]:
        """The distinct readings stamped from ``since`` (default: now) for ``seconds``: a reading read twice
        counts once, and one stamped outside the window (read late, on a busy computer) not at all."""
        ports = self.ports
        start = ports.now() if since is None else since
        end = start + seconds
        out: dict[float, ArmReading] = {}
        queued = ports.arm_readings is not None
        newest = -math.inf
        while True:
            self._check()
            reading = ports.read_arm()
            if reading is not None and start - 1e-9 <= reading.t <= end + 1e-9:
                out[reading.t] = reading
            newest = max(newest, self._take_queued(out, start, end))
            now = ports.now()
            # With the stream queued, the window is complete once a reading stamped after it has come (the stream
            # is in order): a driver that read late still delivers the window's readings, up to LATE_READINGS_S.
            if now >= end - 1e-9 and (not queued or newest > end or now >= end + LATE_READINGS_S):
                return list(out.values())
            period = self.plan.sample_period_s
            ports.sleep(min(end - now, period) if now < end else period)  # past the window: late readings

    def _take_queued(self, out: dict[float, ArmReading], start: float, end: float) -> float:
        """The queued readings stamped in [start, end] into ``out`` (the rest are dropped: they are older than
        the window, or too new for it and a later window starts after them); returns the newest stamp seen."""
        if self.ports.arm_readings is None:
            return -math.inf
        newest = -math.inf
        for reading in self.ports.arm_readings():
            newest = max(newest, reading.t)
            if start - 1e-9 <= reading.t <= end + 1e-9:
                out[reading.t] = reading
        return newest

    def _late(self, window: list[ArmReading], start: float, end: float) -> list[ArmReading]:
        """``window`` with the readings stamped in it that were read after it closed (a driver read late on a
        busy computer; the samples carry the time they were taken)."""
        out = {r.t: r for r in window}
        self._take_queued(out, start, end)
        return list(out.values())

    def _emit(self, kind: str, payload: Any) -> None:
        if self.listener is not None:
            try:
                self.listener(kind, payload)
            except Exception:
                log.exception("electrode set-up listener failed")


# ---------------------------------------------------------------------------------------------- the choice
def choice_for(result: SetupResult, channel: int, operator: str, session: str = "") -> Any:
    """The patient profile's record of choosing ``channel`` for the result's district (app.therapy.patients)."""
    from app.therapy.patients import ElectrodeChoice

    combo = result.combination(channel)
    if combo is None:
        raise ValueError(f"channel {channel} is not a combination of {result.district.name!r}")
    proposal = result.proposal or result.repropose()
    threshold = combo.motor_threshold_ma(result.plan.detect_n)
    eff = combo.response_per_ma(result.plan.detect_n)
    return ElectrodeChoice(channel, combo.combination.electrodes,
                           _dt.datetime.now().astimezone().isoformat(timespec="seconds"), operator,
                           proposal.channel, round(eff, 4) if eff > 0 else None,
                           float(threshold) if threshold is not None else None, combo.discomfort, session)


def with_choice(profile: Any, district: str, choice: Any) -> Any:
    """``profile`` (app.therapy.patients.PatientProfile) with ``choice`` as the district's combination."""
    electrodes = {**profile.fes.electrodes, district: choice}
    return replace(profile, fes=replace(profile.fes, electrodes=electrodes))


# ---------------------------------------------------------------------------------------------- the app's ports
def burst_profile(burst: Burst, muscle: str = "") -> Any:
    """A test burst as a one-channel time profile (app.core.fes_profile), which the FES driver runs through its one
    checked path (its limits, the supervisor) and stops by itself at its end."""
    from app.core.fes_profile import ChannelProfile, FesProfile, Trapezoid
    from app.wire.sciencemode import PulseMode

    up, down = (0.0, burst.ramp_s), (burst.ramp_s + burst.hold_s, burst.duration_s)
    channel = ChannelProfile(Trapezoid(float(burst.current_ma), up, down),
                             Trapezoid(float(burst.pulse_width_us), up, down), muscle, PulseMode.SINGLE)
    return FesProfile(f"electrode test: channel {burst.channel}, {burst.current_ma} mA", "time",
                      {burst.channel: channel}, burst.frequency_hz)


class _Robot:
    """Position hold through the LINarm driver's checked ``command`` (the safety supervisor), and back."""

    def __init__(self, command: Callable[..., Any], latest: Callable[[str], Any], source: str) -> None:
        self.command = command
        self.latest = latest
        self.source = source
        self.before: tuple[int, int] | None = None

    def hold(self) -> None:
        from app.core import streams
        from app.wire.linarm_protocol import ControlMode, ControlState

        state = self.latest(streams.LINARM_STATE)
        if state is None:
            raise SetupAborted("the LINarm has sent no state yet: is it connected?")
        if not state.initialized:
            raise SetupAborted("the LINarm is not homed: home it (Robot tab) before the electrode set-up")
        self.before = (int(state.controlState), int(state.controlMode))
        # Motors on in target-position mode with no move pending: the controller holds the centre where it is
        # (a bumpless start), so the handle stays put and the muscle's pull shows as interaction force.
        if int(state.controlMode) != int(ControlMode.POS_REF_BY_TARGET_POS):
            self.command("setCtrlMode", ControlMode.POS_REF_BY_TARGET_POS, source=self.source)
        if int(state.controlState) != int(ControlState.ON_CTRL_STATE):
            self.command("setCtrlState", ControlState.ON_CTRL_STATE, source=self.source)

    def release(self) -> None:
        from app.wire.linarm_protocol import ControlMode, ControlState

        if self.before is None:
            return
        control, mode = self.before
        self.before = None
        if control == int(ControlState.IDLE_CTRL_STATE):
            self.command("setCtrlState", ControlState.IDLE_CTRL_STATE, source=self.source)
        if mode != int(ControlMode.POS_REF_BY_TARGET_POS):
            self.command("setCtrlMode", ControlMode(mode), source=self.source)


def app_ports(fes: Any, robot_command: Callable[..., Any], latest: Callable[[str], Any],
              hold_reason: Callable[[], str], record: Callable[[str, dict[str, Any]], None], muscle: str = "",
              source: str = "electrode set-up", stopped: Callable[[], bool] = lambda: False,
              bus: Any = None) -> SetupPorts:
    """The procedure's ports on the application's devices: ``fes`` (app.devices.rehastim.FesDriver: load_profile,
    start_stimulation, stop_stimulation, stimulating), the LINarm's checked ``command``, ``latest(stream)`` (the
    bus's or the driver's latest sample), the supervisor's ``robot_hold_reason`` and the session record.
    ``stopped()`` true ends the procedure too (a script's Stop). With ``bus`` (app.core.bus.StreamBus) the
    measurements read the LINarm's stream from a queue of their own (every reading, stamped when taken), closed
    by the ports' ``close()``."""
    from app.core import streams
    from app.core.bus import SampleItem

    robot = _Robot(robot_command, latest, source)
    queue = bus.subscribe("electrode set-up", [streams.LINARM_VSA]) if bus is not None else None

    def arm_readings() -> list[ArmReading]:
        assert queue is not None
        return [ArmReading(item.t, float(item.sample.interactionForce), float(item.sample.handlePos))
                for item in queue.drain() if isinstance(item, SampleItem)]

    def close() -> None:
        if queue is not None:
            queue.close()

    def start_burst(burst: Burst) -> None:
        fes.load_profile(burst_profile(burst, muscle), source)
        fes.start_stimulation(source)

    def read_arm() -> ArmReading | None:
        vsa = latest(streams.LINARM_VSA)
        if vsa is None:
            return None
        stamp = float(getattr(vsa, "timestamp", 0.0) or 0.0) or time.monotonic()  # unstamped: taken as now
        return ArmReading(stamp, float(vsa.interactionForce), float(vsa.handlePos))

    def release_arm() -> None:
        if hold_reason():  # the e-stop or a STOP alarm has put the robot in its safe state: leave it there
            robot.before = None
            return
        robot.release()

    def why_not() -> str:
        return "the script was stopped" if stopped() else hold_reason()

    return SetupPorts(start_burst=start_burst, stimulating=lambda: bool(fes.stimulating),
                      stop=lambda reason: fes.stop_stimulation(reason, source), hold_arm=robot.hold,
                      release_arm=release_arm, read_arm=read_arm, hold_reason=why_not, record=record,
                      arm_readings=arm_readings if queue is not None else None, close=close)


def choice_event(result: SetupResult, choice: Any) -> dict[str, Any]:
    """The session record's ``electrode_choice`` event for ``choice`` (app.therapy.patients.ElectrodeChoice)."""
    return {"district": result.district.name, "channel": choice.channel, "electrodes": choice.electrodes,
            "proposed_channel": choice.proposed_channel, "accepted_proposal": choice.channel == choice.proposed_channel,
            "response_per_ma": choice.response_per_ma, "motor_threshold_ma": choice.motor_threshold_ma,
            "discomfort": choice.discomfort, "chosen_by": choice.chosen_by, "chosen_at": choice.chosen_at}


def run_district_setup(fes: Any, robot: Any, supervisor: Any, latest: Callable[[str], Any],
                       record: Callable[[str, dict[str, Any]], None], district: District, plan: SetupPlan,
                       stopped: Callable[[], bool] = lambda: False, listener: ProgressListener | None = None,
                       source: str = "electrode set-up", bus: Any = None) -> SetupResult:
    """The set-up of ``district`` on the application's devices, blocking (the script API's form; the dialog runs
    the same on a worker thread): ``fes`` the FesDriver, ``robot`` the LinarmDriver, ``supervisor`` the
    SafetySupervisor (its FES limits and hold reason). ``stopped()`` true ends it (a script's Stop). The profile
    the stimulator had loaded is loaded again afterwards."""
    limiter = getattr(supervisor, "fes_limiter", None)
    if limiter is None:
        raise SetupAborted("no FES limits are configured")
    if getattr(fes, "stimulating", False):
        raise SetupAborted("stop the running stimulation first")

    ports = app_ports(fes, robot.command, latest, supervisor.robot_hold_reason, record, district.name, source,
                      stopped, bus)
    previous = getattr(fes, "profile", None)
    try:
        return ElectrodeSetup(district, plan, limiter.limits, ports, listener).run()
    finally:
        if previous is not None and not getattr(fes, "stimulating", False):
            try:
                fes.load_profile(previous, source)
            except Exception as exc:
                log.warning("electrode set-up: the previous profile could not be loaded again: %s", exc)


def result_summary(result: SetupResult) -> dict[str, Any]:
    """A plain summary of a set-up (for a script)."""
    p = result.plan
    proposal = result.proposal or result.repropose()
    return {"district": result.district.name, "proposedChannel": proposal.channel, "reason": proposal.reason,
            "aborted": result.aborted,
            "combinations": [{"channel": r.combination.channel, "electrodes": r.combination.electrodes,
                              "ceilingMa": r.ceiling_ma, "thresholdMa": r.motor_threshold_ma(p.detect_n),
                              "responsePerMa": round(r.response_per_ma(p.detect_n), 4),
                              "bursts": [[b.current_ma, round(b.response_n, 3)] for b in r.bursts]}
                             for r in result.combinations]}
