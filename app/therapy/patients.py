"""Patient profiles: one YAML file per patient in ``paths.patients_dir()``, named from its pseudonym.

A profile holds what the clinician decides for one patient: an identifier or pseudonym, clinical
scores, the assistance gains k_r and k_f, the FES profile and clinical caps, robot limits and notes.
Files are read with app.core.yamlschema (unknown keys, wrong types and out-of-range values are refused with
the file, the line and the key). A profile may only *narrow* the configured safety limits: a robot
limit or FES cap looser than the configuration is refused by :func:`check_against`, naming the key,
because the configuration is the site's safety envelope and a patient file must not widen it.
"""

from __future__ import annotations

import datetime as _dt
import os
import re
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal, Protocol

import yaml
from yaml.nodes import MappingNode, Node

from app.core import paths, yamlschema
from app.core.config import (
    FES_CHANNEL_RANGE,
    FES_CURRENT_RANGE,
    FES_PULSE_WIDTH_RANGE,
    ROBOT_LIMIT_RANGES,
    RobotLimits,
    SafetyConfig,
    unknown_channel,
)
from app.core.safe_files import UserFileError, read_user_text
from app.core.yamlschema import ConfigError, load_dataclass, rng, to_plain

PROFILE_VERSION = 1
# Letters, digits, '-' and '_' only: the pseudonym is the file name and the sessions folder name, so it
# must be portable (Windows, macOS, Linux) and must not carry a path.
_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")


@dataclass(frozen=True)
class ClinicalScores:
    """Standard upper-limb scales; None = not assessed."""

    fugl_meyer_ue: int | None = field(default=None, metadata=rng(0, 66, "points"))
    modified_ashworth: float | None = field(default=None, metadata=rng(0, 4, "grade"))
    action_research_arm_test: int | None = field(default=None, metadata=rng(0, 57, "points"))
    box_and_block: int | None = field(default=None, metadata=rng(0, 150, "blocks/min"))
    assessed_on: str = ""  # ISO date of the assessment
    other: dict[str, float] = field(default_factory=dict)  # further scales by name


@dataclass(frozen=True)
class PatientAssistance:
    """The patient's gains of the assistance split (robot share k_r, FES share k_f)."""

    k_r: float = field(default=0.5, metadata=rng(0, 1))
    k_f: float = field(default=0.5, metadata=rng(0, 1))


@dataclass(frozen=True)
class ClinicalChannelCap:
    max_current_ma: float = field(default=40.0, metadata=FES_CURRENT_RANGE)
    max_pulse_width_us: float = field(default=300.0, metadata=FES_PULSE_WIDTH_RANGE)
    max_rms_current_ma: float | None = field(default=None, metadata=FES_CURRENT_RANGE)


@dataclass(frozen=True)
class ElectrodeChoice:
    """The electrode combination chosen for one muscular district (issue #32): its stimulator channel, which
    electrodes of the array it is, when and by whom it was chosen, and what the set-up measured for it."""

    channel: int = field(default=1, metadata=FES_CHANNEL_RANGE)
    electrodes: str = ""
    chosen_at: str = ""  # ISO time with zone
    chosen_by: str = ""  # the therapist (the session's operator)
    proposed_channel: int | None = field(default=None, metadata=FES_CHANNEL_RANGE)  # what the set-up proposed
    response_per_ma: float | None = field(default=None, metadata=rng(0, 1000, "N/mA"))
    motor_threshold_ma: float | None = field(default=None, metadata=FES_CURRENT_RANGE)
    discomfort: int | None = field(default=None, metadata=rng(0, 10))  # the patient's rating, 0..10
    session: str = ""  # the session folder's name, when chosen during a session


@dataclass(frozen=True)
class PatientFes:
    """``profile``: an FES profile file (name in resources/fes_profiles or a path); empty = none chosen.
    ``caps``: clinical caps per stimulator channel (sciencemode.CHANNELS). ``electrodes``: the chosen combination
    per muscular district (FES profiles that name a district stimulate its channel)."""

    profile: str = ""
    caps: dict[int, ClinicalChannelCap] = field(default_factory=dict)
    electrodes: dict[str, ElectrodeChoice] = field(default_factory=dict)

    def validate(self) -> None:
        problem = unknown_channel("caps", self.caps)
        if problem:
            raise ValueError(problem)

    def district_channels(self) -> dict[str, int]:
        """The chosen channel of each district (what a district-addressed FES profile stimulates)."""
        return {name: choice.channel for name, choice in self.electrodes.items()}


@dataclass(frozen=True)
class PatientRobotLimits:
    """Per-patient robot limits; None = the configured limit. Each may only be tighter than the config."""

    position_min_m: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["position_min_m"])
    position_max_m: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["position_max_m"])
    max_velocity_m_s: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["max_velocity_m_s"])
    max_acceleration_m_s2: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["max_acceleration_m_s2"])
    max_interaction_force_n: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["max_interaction_force_n"])
    max_stiffness_n_m: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["max_stiffness_n_m"])
    max_delta_m: float | None = field(default=None, metadata=ROBOT_LIMIT_RANGES["max_delta_m"])

    def validate(self) -> None:
        lo, hi = self.position_min_m, self.position_max_m
        if lo is not None and hi is not None and lo >= hi:
            raise ValueError(f"position_min_m ({lo}) must be below position_max_m ({hi})")


@dataclass(frozen=True)
class PlannedExercise:
    """One step of a therapy plan: an exercise of the library (``resources/exercises/<exercise>.yaml``) and
    the values for its form (checked against the exercise's schema when it is offered, app/therapy/exercises.py)."""

    exercise: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    note: str = ""


@dataclass(frozen=True)
class PatientProfile:
    patient_id: str = ""  # identifier or pseudonym; also the file and sessions-folder name
    version: int = field(default=PROFILE_VERSION, metadata=rng(PROFILE_VERSION, PROFILE_VERSION))
    # Identification for the printed record (session report); all optional: a pseudonymous profile leaves them
    # empty and the clinic's own key links the pseudonym to the person.
    full_name: str = ""
    birth_date: str = ""  # ISO date YYYY-MM-DD
    record_number: str = ""  # the clinic's medical record number
    affected_side: Literal["left", "right", "both", "unknown"] = "unknown"
    scores: ClinicalScores = field(default_factory=ClinicalScores)
    assistance: PatientAssistance = field(default_factory=PatientAssistance)
    fes: PatientFes = field(default_factory=PatientFes)
    robot: PatientRobotLimits = field(default_factory=PatientRobotLimits)
    notes: str = ""
    therapy_plan: list[PlannedExercise] = field(default_factory=list)  # offered in order by the Exercises tab
    created: str = ""  # ISO time with zone, set on first save
    updated: str = ""

    def validate(self) -> None:
        if not self.patient_id:
            raise ValueError("patient_id is required (an identifier or pseudonym)")
        if not _SAFE_ID.match(self.patient_id):
            raise ValueError(f"patient_id {self.patient_id!r} may hold only letters, digits, '-' and '_' "
                             "(at most 64, starting with a letter or digit)")
        if self.birth_date:
            try:
                _dt.date.fromisoformat(self.birth_date)
            except ValueError:
                raise ValueError(f"birth_date {self.birth_date!r} is not a date: write it as YYYY-MM-DD, "
                                 "e.g. 1956-04-23") from None


class PatientError(ConfigError):
    """A patient file is invalid or does not fit the configured limits (file, line, key named)."""


# ---------------------------------------------------------------------------------------------- limits
_ROBOT_UPPER = ("max_velocity_m_s", "max_acceleration_m_s2", "max_interaction_force_n", "max_stiffness_n_m",
                "max_delta_m")


def limit_problems(profile: PatientProfile, safety: SafetyConfig) -> list[tuple[str, str]]:
    """(key path, problem) for every profile limit that is looser than the configuration; empty when none."""
    out: list[tuple[str, str]] = []
    r, cfg = profile.robot, safety.robot
    if r.position_min_m is not None and r.position_min_m < cfg.position_min_m:
        out.append(("robot.position_min_m", f"{r.position_min_m} m is below the configured minimum "
                                            f"{cfg.position_min_m} m; a patient may only narrow the range"))
    if r.position_max_m is not None and r.position_max_m > cfg.position_max_m:
        out.append(("robot.position_max_m", f"{r.position_max_m} m is above the configured maximum "
                                            f"{cfg.position_max_m} m; a patient may only narrow the range"))
    lo = r.position_min_m if r.position_min_m is not None else cfg.position_min_m
    hi = r.position_max_m if r.position_max_m is not None else cfg.position_max_m
    if lo >= hi and not out:
        out.append(("robot.position_min_m", f"the range {lo} .. {hi} m is empty with the configured limits"))
    for key in _ROBOT_UPPER:
        value, limit = getattr(r, key), getattr(cfg, key)
        if value is not None and value > limit:
            out.append((f"robot.{key}", f"{value} exceeds the configured limit {limit}; a patient limit may only "
                                        "be tighter"))
    fes = safety.fes
    for ch, cap in sorted(profile.fes.caps.items()):
        site = fes.channels.get(ch)
        max_current = min(fes.max_current_ma, site.max_current_ma) if site else fes.max_current_ma
        max_width = min(fes.max_pulse_width_us, site.max_pulse_width_us) if site else fes.max_pulse_width_us
        if cap.max_current_ma > max_current:
            out.append((f"fes.caps.{ch}.max_current_ma", f"{cap.max_current_ma} mA exceeds the configured cap "
                                                        f"{max_current} mA"))
        if cap.max_pulse_width_us > max_width:
            out.append((f"fes.caps.{ch}.max_pulse_width_us", f"{cap.max_pulse_width_us} µs exceeds the configured "
                                                            f"cap {max_width} µs"))
        if cap.max_rms_current_ma is not None and cap.max_rms_current_ma > fes.max_rms_current_ma:
            out.append((f"fes.caps.{ch}.max_rms_current_ma", f"{cap.max_rms_current_ma} mA exceeds the configured "
                                                            f"r.m.s. limit {fes.max_rms_current_ma} mA"))
    return out


def effective_robot_limits(profile: PatientProfile, robot: RobotLimits) -> RobotLimits:
    """The configured robot limits narrowed by the patient's (never widened: min/max are taken anyway)."""
    r = profile.robot
    changes: dict[str, float] = {}
    if r.position_min_m is not None:
        changes["position_min_m"] = max(r.position_min_m, robot.position_min_m)
    if r.position_max_m is not None:
        changes["position_max_m"] = min(r.position_max_m, robot.position_max_m)
    for key in _ROBOT_UPPER:
        value = getattr(r, key)
        if value is not None:
            changes[key] = min(value, getattr(robot, key))
    return replace(robot, **changes)


def clinical_caps(profile: PatientProfile) -> dict:
    """The FES clinical caps as app.safety.fes_limits.ChannelCaps per channel (for FesLimits.from_config)."""
    from app.safety.fes_limits import ChannelCaps

    return {ch: ChannelCaps(c.max_current_ma, c.max_pulse_width_us, c.max_rms_current_ma)
            for ch, c in profile.fes.caps.items()}


# ---------------------------------------------------------------------------------------------- files
def patient_file(patient_id: str, folder: Path | None = None) -> Path:
    if not _SAFE_ID.match(patient_id):
        raise ValueError(f"{patient_id!r} is not a valid patient identifier (letters, digits, '-', '_')")
    return (folder or paths.patients_dir()) / f"{patient_id}.yaml"


def _line_of(text: str, key: str) -> int | None:
    """The line of a dotted key path in YAML text (for messages), or None."""
    try:
        node: Node | None = yamlschema.compose(text)
    except yaml.YAMLError:
        return None
    line = None
    for part in key.split("."):
        if not isinstance(node, MappingNode):
            break
        for knode, vnode in node.value:
            if str(knode.value) == part:
                node, line = vnode, knode.start_mark.line + 1
                break
        else:
            break
    return line


def parse_profile(text: str, filename: str, safety: SafetyConfig | None = None) -> PatientProfile:
    """Validate YAML text into a profile; with ``safety``, also refuse limits looser than the config."""
    try:
        profile = load_dataclass(PatientProfile, text, filename)
    except ConfigError as exc:
        raise PatientError(exc.filename, exc.line, exc.key, exc.problem) from exc
    if safety is not None:
        problems = limit_problems(profile, safety)
        if problems:
            key, problem = problems[0]
            raise PatientError(filename, _line_of(text, key), key, problem)
    return profile


def load_patient(patient_id: str, safety: SafetyConfig | None = None, folder: Path | None = None) -> PatientProfile:
    """The patient's profile from ``folder``'s YAML file; without a folder, from the station's archive when the
    application has one (app.archive.station), else from the patients folder. Raises PatientError (no such
    patient, an invalid profile, a limit looser than ``safety``, the archive cannot be reached)."""
    if folder is None and _store is not None:
        return _store.load(patient_id, safety)
    path = patient_file(patient_id, folder)
    try:
        text = read_user_text(path)
    except UserFileError as exc:
        raise PatientError.refused(exc) from exc
    profile = parse_profile(text, str(path), safety)
    if profile.patient_id != path.stem:
        raise PatientError(str(path), _line_of(text, "patient_id"), "patient_id",
                           f"{profile.patient_id!r} does not match the file name {path.name!r}")
    return profile


class PatientStore(Protocol):
    """Where patients live when not in YAML files: the application's archive (app.archive.station installs it with
    :func:`use_store`; this module never imports the archive)."""

    def load(self, patient_id: str, safety: SafetyConfig | None) -> PatientProfile:
        """Raises PatientError (no such patient, an invalid record, a limit looser than ``safety``, unreachable)."""
        ...

    def entries(self, safety: SafetyConfig | None) -> list[PatientEntry]: ...


_store: PatientStore | None = None


def use_store(store: PatientStore | None) -> None:
    """``load_patient`` and ``list_patients`` without a folder read ``store`` from now on (None: the YAML folder)."""
    global _store
    _store = store


def profile_to_yaml(profile: PatientProfile) -> str:
    header = ("# LINarm++ patient profile. Edit in the application (Patients menu) or by hand; it is validated\n"
              "# on load. Robot limits and FES caps may only be tighter than the configuration.\n")
    data = to_plain(profile)
    # to_plain writes mapping keys as strings; channel numbers must stay integers to load back.
    data["fes"]["caps"] = {int(ch): cap for ch, cap in data["fes"]["caps"].items()}
    return header + yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


def now_iso() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def save_patient(profile: PatientProfile, folder: Path | None = None, safety: SafetyConfig | None = None) -> Path:
    """Validate and write atomically (a crash leaves the old file or the new one, never half of one)."""
    stamp = now_iso()
    profile = replace(profile, created=profile.created or stamp, updated=stamp)
    path = patient_file(profile.patient_id, folder)
    text = profile_to_yaml(profile)
    parse_profile(text, str(path), safety)  # the file we write must load back
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@dataclass(frozen=True)
class PatientEntry:
    """One file in the patients folder: its profile, or the reason it cannot be loaded."""

    patient_id: str
    path: Path
    profile: PatientProfile | None
    error: str = ""
    version: int = 0  # the archive record's version it was read at (0: a YAML file, unversioned)


def list_patients(folder: Path | None = None, safety: SafetyConfig | None = None) -> list[PatientEntry]:
    """Every patient of ``folder`` (a file that cannot be loaded listed with its reason); without a folder, the
    station's archive when the application has one (:func:`use_store`; empty when it cannot be reached)."""
    if folder is None and _store is not None:
        return _store.entries(safety)
    folder = folder or paths.patients_dir()
    return yaml_entries(sorted(folder.glob("*.yaml"), key=lambda p: p.stem.lower()), folder, safety)


def yaml_entries(files: Iterable[Path], folder: Path, safety: SafetyConfig | None = None) -> list[PatientEntry]:
    """The entries of these profile files of ``folder``, a file that cannot be loaded listed with its reason."""
    out: list[PatientEntry] = []
    for path in files:
        if not _SAFE_ID.match(path.stem):
            out.append(PatientEntry(path.stem, path, None, f"{path.name}: the file name is not a valid identifier"))
            continue
        try:
            out.append(PatientEntry(path.stem, path, load_patient(path.stem, safety, folder)))
        except ConfigError as exc:
            out.append(PatientEntry(path.stem, path, None, str(exc)))
        except Exception as exc:  # one unreadable file must never hide the others
            out.append(PatientEntry(path.stem, path, None, f"{path}: unreadable: {exc}"))
    return out


def matches(entry: PatientEntry, text: str) -> bool:
    """Whether a search ``text`` finds this patient: in the id, the name, the record number or the notes
    (case-insensitive; every word of the search must be found)."""
    p = entry.profile
    haystack = " ".join([entry.patient_id] + ([p.full_name, p.record_number, p.notes] if p is not None else []))
    haystack = haystack.lower()
    return all(word in haystack for word in text.lower().split())


# ---------------------------------------------------------------------------------------------- therapy plans
@dataclass(frozen=True)
class PlanProblem:
    step: int  # from 1, in the plan's order
    parameter: str  # "" for the step itself (an exercise that is not in the library)
    text: str  # in plain words, naming the step, the exercise and the parameter's label

    def __str__(self) -> str:
        return self.text


def plan_problems(plan: list[PlannedExercise], library: list[Any] | None = None) -> list[PlanProblem]:
    """Every step checked against its exercise's own parameter ranges (app.therapy.exercises.validate): what is out of
    range, not a number, unknown or not in the library, said in words. Empty when the plan can be saved."""
    from app.therapy.exercises import load_library, validate

    exercises = {e.ident: e for e in (library if library is not None else load_library()[0])}
    out: list[PlanProblem] = []
    for k, step in enumerate(plan, start=1):
        exercise = exercises.get(step.exercise)
        if exercise is None:
            out.append(PlanProblem(k, "", f"Step {k}: there is no exercise '{step.exercise}' in the library"))
            continue
        result = validate(exercise, step.params)
        for name, why in result.errors.items():
            label = next((p.label for p in exercise.parameters if p.name == name), name)
            out.append(PlanProblem(k, name, f"Step {k}, {exercise.title} — {label}: {why}"))
    return out


def prescription_problems(plan: list[PlannedExercise], profile: PatientProfile, safety: SafetyConfig | None = None,
                          library: list[Any] | None = None) -> list[PlanProblem]:
    """Every step checked against this patient as the profile says now (issue #36, checked when the plan is
    saved and when the session starts): positions, speeds and stiffness within their robot limits, the FES
    profile a step stimulates with within their caps, and its muscle districts with a chosen electrode
    combination. Steps whose values their own ranges refuse are left to :func:`plan_problems`."""
    from app.safety.fes_limits import FesLimits
    from app.therapy.exercises import load_library, validate
    from app.therapy.exercises import prescription_problems as step_problems

    safety = safety or SafetyConfig()
    robot = effective_robot_limits(profile, safety.robot)
    fes = FesLimits.from_config(safety.fes, clinical_caps(profile))
    exercises = {e.ident: e for e in (library if library is not None else load_library()[0])}
    out: list[PlanProblem] = []
    for k, step in enumerate(plan, start=1):
        exercise = exercises.get(step.exercise)
        if exercise is None:
            continue
        checked = validate(exercise, step.params)
        if not checked.ok:
            continue
        found = step_problems(exercise, checked.params, robot=robot, fes_limits=fes,
                              district_channels=profile.fes.district_channels(), patient=profile.patient_id)
        for name, why in found.items():
            label = next((p.label for p in exercise.parameters if p.name == name), name)
            out.append(PlanProblem(k, name, f"Step {k}, {exercise.title} — {label}: {why}"))
    return out


def profile_changes(old: PatientProfile | None, new: PatientProfile) -> list[str]:
    """What changed between two versions of a profile that the running session applies, in words: the FES caps,
    the robot limits, the assistance gains, the chosen electrodes and the plan's length."""
    if old is None:
        return ["the profile"]
    out: list[str] = []
    for ch in sorted(set(old.fes.caps) | set(new.fes.caps)):
        a, b = old.fes.caps.get(ch), new.fes.caps.get(ch)
        for key, unit, what in (("max_current_ma", "mA", "current cap"),
                                ("max_pulse_width_us", "µs", "pulse-width cap")):
            va = getattr(a, key) if a is not None else None
            vb = getattr(b, key) if b is not None else None
            if va != vb:
                out.append(f"channel {ch} {what} {_or_none(va, unit)} → {_or_none(vb, unit)}")
    for f in fields(PatientRobotLimits):
        va, vb = getattr(old.robot, f.name), getattr(new.robot, f.name)
        if va != vb:
            out.append(f"robot {f.name.replace('_', ' ')} {_or_none(va)} → {_or_none(vb)}")
    if (old.assistance.k_r, old.assistance.k_f) != (new.assistance.k_r, new.assistance.k_f):
        out.append(f"assistance gains k_r {old.assistance.k_r:g}, k_f {old.assistance.k_f:g} → "
                   f"k_r {new.assistance.k_r:g}, k_f {new.assistance.k_f:g}")
    if old.fes.district_channels() != new.fes.district_channels():
        out.append("the chosen electrodes")
    if len(old.therapy_plan) != len(new.therapy_plan) or old.therapy_plan != new.therapy_plan:
        out.append(f"the therapy plan ({len(new.therapy_plan)} step(s))")
    return out


def _or_none(value: Any, unit: str = "") -> str:
    if value is None:
        return "none"
    return f"{value:g} {unit}".strip() if isinstance(value, int | float) else str(value)


def profile_field_names() -> list[str]:
    return [f.name for f in fields(PatientProfile)]


__all__ = [
    "ClinicalChannelCap", "ClinicalScores", "ElectrodeChoice", "PatientAssistance", "PatientEntry", "PatientError",
    "PatientFes", "PatientProfile", "PatientRobotLimits", "PatientStore", "PlanProblem", "PlannedExercise",
    "clinical_caps", "effective_robot_limits", "limit_problems", "list_patients", "load_patient", "matches",
    "parse_profile", "patient_file", "plan_problems", "prescription_problems", "profile_changes", "profile_to_yaml",
    "save_patient", "use_store",
]
