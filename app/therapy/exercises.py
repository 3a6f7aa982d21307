"""Exercises as forms: a script plus a declared parameter schema.

An exercise is ``resources/exercises/<id>.yaml`` (title, description, script, parameters) next to its script
``<id>.py``. Each parameter declares name, label, type (``int`` | ``float`` | ``bool`` | ``choice``), unit,
range, default and help; the Exercises tab draws the form from it and :func:`validate` checks what was typed:
a value out of its range is refused with the reason and nothing is started.

The files are read by the config's strict loader (app/core/yamlschema.py: file:line errors, unknown keys, size,
depth, anchors, tags, UTF-8): the script is a ``.py`` file in the exercise's own folder (no path, no link out
of it); a number parameter declares both ``min`` and ``max`` (within ±1e6), a duration (unit s/ms/min/h or a
name ending ``_s``/``_ms``) never below 0, and its default within them. :func:`load_library` lists a file it
cannot load (file:line and why) and loads the others. The script reads its values as
the global ``exerciseParams`` (ScriptRunner.start's ``params``) and marks its repetitions with
``linarmppManager.startRepetition / endRepetition``.

:func:`start_exercise` records ``exercise_start {exercise, title, script, params}`` as a session event (the
metrics and the reports read the parameters from it) and starts the script on the window's runner.
"""

from __future__ import annotations

import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from yaml.nodes import MappingNode, SequenceNode

from app.core import journal, streams, yamlschema
from app.core.resources import RESOURCES
from app.core.safe_files import UserFileError, read_user_text
from app.core.yamlschema import ConfigError, load_dataclass, rng

if TYPE_CHECKING:
    from app.core.runs import RunSource
    from app.therapy.services import EventHost, ExerciseRunner

EXERCISES_DIR = RESOURCES / "exercises"
PARAMETER_TYPES = ("int", "float", "bool", "choice")
# What a number parameter is checked against besides its own range (the patient's limits, when the plan is
# saved, the session starts and the run starts): its ``limit`` key.
PARAMETER_LIMITS = ("position", "velocity", "acceleration", "stiffness")


class ExerciseError(ValueError):
    """An exercise definition is malformed (file and key named)."""


@dataclass(frozen=True)
class Parameter:
    name: str
    label: str
    type: str
    default: Any
    unit: str = ""
    min: float | None = None
    max: float | None = None
    help: str = ""
    options: tuple[str, ...] = ()
    limit: str = ""  # "position" | "velocity" | "acceleration" | "stiffness": also within the patient's limits

    def describe_range(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.type == "choice":
            return "one of " + ", ".join(self.options)
        if self.min is not None and self.max is not None:
            return f"{_num(self.min)} … {_num(self.max)}{unit}"
        if self.min is not None:
            return f"≥ {_num(self.min)}{unit}"
        if self.max is not None:
            return f"≤ {_num(self.max)}{unit}"
        return ""

    def check(self, value: Any) -> tuple[Any, str]:
        """(the value converted to the parameter's type, "" or why it is refused)."""
        if self.type == "bool":
            if isinstance(value, bool):
                return value, ""
            if isinstance(value, str) and value.strip().lower() in ("true", "yes", "1", "false", "no", "0"):
                return value.strip().lower() in ("true", "yes", "1"), ""
            return value, "must be yes or no"
        if self.type == "choice":
            if str(value) in self.options:
                return str(value), ""
            return value, "must be one of " + ", ".join(self.options)
        try:
            if isinstance(value, bool):
                raise ValueError
            number = float(str(value).strip().replace(",", ".")) if isinstance(value, str) else float(value)
        except (TypeError, ValueError):
            return value, f"'{value}' is not a number"
        if not math.isfinite(number):
            return value, "must be a finite number"
        if self.type == "int":
            if number != int(number):
                return value, "must be a whole number"
            number = int(number)
        unit = f" {self.unit}" if self.unit else ""
        if self.min is not None and number < self.min:
            return number, f"{_num(number)}{unit} is below the minimum {_num(self.min)}{unit}"
        if self.max is not None and number > self.max:
            return number, f"{_num(number)}{unit} is above the maximum {_num(self.max)}{unit}"
        return number, ""


@dataclass(frozen=True)
class Exercise:
    ident: str  # the file name without .yaml
    title: str
    description: str
    script: Path
    parameters: tuple[Parameter, ...]
    order: int = 100
    fes_profile: str = ""  # the parameter naming the FES profile it stimulates with ("" = it does not stimulate)
    fes_enabled: str = ""  # the yes/no parameter switching that stimulation on ("" = always on)
    repetitions: str = ""  # the parameter counting its repetitions (Recover's "continue with the remaining")
    composition: tuple[Mapping[str, Any], ...] = ()  # what it lets other sources set (app/core/ownership.py)

    def defaults(self) -> dict[str, Any]:
        return {p.name: p.default for p in self.parameters}

    def stimulates(self, params: Mapping[str, Any]) -> bool:
        return bool(self.fes_profile) and (not self.fes_enabled or bool(params.get(self.fes_enabled)))

    def holds(self, params: Mapping[str, Any]) -> tuple[str, ...]:
        """The devices a run of it holds: the robot, and the stimulator when it stimulates."""
        return ("robot", "stimulator") if self.stimulates(params) else ("robot",)

    def compositions(self, params: Mapping[str, Any]) -> tuple[Any, ...]:
        """Its declared composition with the run's values (app.core.ownership.Composition)."""
        from app.core.ownership import compositions_from

        return compositions_from(self.composition, params)

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)


@dataclass
class Validation:
    params: dict[str, Any] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)  # parameter name → reason

    @property
    def ok(self) -> bool:
        return not self.errors

    def message(self, exercise: Exercise) -> str:
        return "; ".join(f"{exercise.parameter(n).label}: {why}" for n, why in self.errors.items())


def _num(x: float) -> str:
    return f"{x:g}"


def validate(exercise: Exercise, values: Mapping[str, Any]) -> Validation:
    """Every parameter checked; a missing one takes its default, an unknown one is refused."""
    out = Validation()
    for name in values:
        if not any(p.name == name for p in exercise.parameters):
            out.errors[name] = f"{exercise.title} has no parameter '{name}'"
    for p in exercise.parameters:
        value, why = p.check(values.get(p.name, p.default))
        out.params[p.name] = value
        if why:
            out.errors[p.name] = why
    return out


# ------------------------------------------------------------------------------------------- the patient
FES_PROFILES_DIR = RESOURCES / "fes_profiles"


def fes_profile_path(name: str) -> Path:
    """A profile named by an exercise's choice: a file of the bundled profiles (or a path)."""
    path = Path(name)
    return path if path.is_absolute() else FES_PROFILES_DIR / name


def prescription_problems(exercise: Exercise, params: Mapping[str, Any], *, robot: Any = None,
                          fes_limits: Any = None, district_channels: Mapping[str, int] | None = None,
                          patient: str = "") -> dict[str, str]:
    """What in these (already range-checked) values the patient's *current* limits refuse, as
    {parameter name: sentence}, empty when nothing: a position outside the patient's range, a speed,
    acceleration or stiffness above their limit (``robot``: app.core.config.RobotLimits, the patient's narrowed
    ones); the FES profile the exercise stimulates with above a cap (``fes_limits``: app.safety.fes_limits.FesLimits
    with the patient's clinical caps), or naming a muscle district with no chosen electrode combination
    (``district_channels``). Checked when the plan is saved, when the session starts and when the run starts,
    before anything moves (issue #36)."""
    out: dict[str, str] = {}
    if robot is not None:
        for p in exercise.parameters:
            if not p.limit or p.name not in params:
                continue
            try:
                value = float(params[p.name])
            except (TypeError, ValueError):
                continue
            unit = f" {p.unit}" if p.unit else ""
            if p.limit == "position" and not (robot.position_min_m <= value <= robot.position_max_m):
                out[p.name] = (f"{value:g}{unit} is outside this patient's range of movement "
                               f"{robot.position_min_m:g} … {robot.position_max_m:g} m")
            else:
                limit = {"velocity": robot.max_velocity_m_s, "acceleration": robot.max_acceleration_m_s2,
                         "stiffness": robot.max_stiffness_n_m}.get(p.limit)
                if limit is not None and value > limit + 1e-12:
                    out[p.name] = f"{value:g}{unit} is above this patient's limit of {limit:g}{unit}"
    if exercise.stimulates(params) and exercise.fes_profile in params:
        why = fes_profile_problem(str(params[exercise.fes_profile]), fes_limits, district_channels, patient)
        if why:
            out[exercise.fes_profile] = why
    return out


def fes_profile_problem(name: str, fes_limits: Any = None, district_channels: Mapping[str, int] | None = None,
                        patient: str = "") -> str:
    """Why the profile ``name`` cannot stimulate this patient ("" when it can), in words."""
    from app.core.fes_profile import FesProfileError, load_profile
    from app.safety.fes_limits import profile_limit_problems

    try:
        profile = load_profile(fes_profile_path(name))
    except FesProfileError as exc:
        return f"the FES profile {name} cannot be read ({exc.problem})"
    except OSError as exc:
        return f"the FES profile {name} cannot be read ({exc.strerror or exc})"
    if profile.districts:
        if district_channels is None:
            district_channels = {}
        try:
            profile = profile.resolve_districts(district_channels)
        except FesProfileError:
            missing = [d for d in profile.districts
                       if str(d).strip().lower() not in {k.strip().lower() for k in district_channels}]
            muscles = " and ".join(missing) if missing else "a district"
            return (f"“{profile.name}” stimulates by muscle district, and no electrode combination is chosen for "
                    f"the {muscles} of this patient yet: run the electrode set-up (FES tab) first")
    if fes_limits is None:
        return ""
    problems = profile_limit_problems(fes_limits, profile.peaks(scaled=True), patient)
    if problems:
        muscles = {ch: cp.muscle for ch, cp in profile.channels.items()}
        first = problems[0]
        for ch, muscle in muscles.items():
            if muscle and first.startswith(f"Channel {ch}:"):
                first = first.replace(f"Channel {ch}:", f"channel {ch} ({muscle}):", 1)
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        return f"“{profile.name}” goes above this patient's caps: {first.rstrip('.')}{more}"
    return ""


# ------------------------------------------------------------------------------------------- loading
# The file format as schema classes read by app.core.yamlschema, the config's strict loader: file:line errors,
# unknown keys, types and ranges, and its limits on hostile files (size, depth, anchors, tags, encoding).
_DURATION_UNITS = ("s", "ms", "min", "h")
_MAX_BOUND = 1e6  # no parameter of a rehabilitation exercise needs more (positions in m, forces in N, s)


@dataclass(frozen=True)
class _ParameterFile:
    name: str
    default: Any = None
    label: str = ""
    type: str = "float"
    unit: str = ""
    min: float | None = field(default=None, metadata=rng(-_MAX_BOUND, _MAX_BOUND))
    max: float | None = field(default=None, metadata=rng(-_MAX_BOUND, _MAX_BOUND))
    help: str = ""
    options: list[str] = field(default_factory=list)
    limit: str = ""

    def validate(self) -> None:
        name = self.name
        if self.limit and (self.limit not in PARAMETER_LIMITS or self.type not in ("int", "float")):
            raise ValueError(f"({name}): limit must be one of {', '.join(PARAMETER_LIMITS)}, on a number")
        if not name.isidentifier():
            raise ValueError(f"'name' must be an identifier, got {name!r}")
        if self.type not in PARAMETER_TYPES:
            raise ValueError(f"({name}): type must be one of {', '.join(PARAMETER_TYPES)}, got {self.type!r}")
        if self.default is None:
            raise ValueError(f"({name}): a default is required")
        if len(self.label) > 100 or len(self.unit) > 20:
            raise ValueError(f"({name}): the label (100) or the unit (20 characters) is too long")
        if self.type == "choice":
            if not self.options:
                raise ValueError(f"({name}): a choice needs options")
            if len(self.options) > 100:
                raise ValueError(f"({name}): more than 100 options")
        elif self.options:
            raise ValueError(f"({name}): options are for a choice, not a {self.type}")
        if self.type in ("int", "float"):
            if self.min is None or self.max is None:
                raise ValueError(f"({name}): a number needs both min and max (what the form may accept)")
            if self.min > self.max:
                raise ValueError(f"({name}): min {_num(self.min)} is above max {_num(self.max)}")
            duration = self.unit in _DURATION_UNITS or name.endswith(("_s", "_ms"))
            if duration and self.min < 0:
                raise ValueError(f"({name}): a duration cannot be negative (min {_num(self.min)}"
                                 f"{' ' + self.unit if self.unit else ''})")
        elif self.min is not None or self.max is not None:
            raise ValueError(f"({name}): min and max are for numbers, not a {self.type}")

    def parameter(self) -> Parameter:
        p = Parameter(name=self.name, label=self.label or self.name, type=self.type, default=self.default,
                      unit=self.unit, min=self.min, max=self.max, help=self.help, options=tuple(self.options),
                      limit=self.limit)
        value, why = p.check(p.default)
        if why:
            raise ValueError(f"({self.name}): the default is refused: {why}")
        return Parameter(**{**p.__dict__, "default": value})


@dataclass(frozen=True)
class _FesFile:
    """``fes: {profile: <parameter>, enabled: <parameter>}``: the exercise stimulates with the FES profile its
    parameter ``profile`` names (a choice), when its yes/no parameter ``enabled`` is on."""

    profile: str = ""
    enabled: str = ""


@dataclass(frozen=True)
class _CompositionFile:
    """One item of ``composition``: ``source`` (VR task | assistance) may set ``sets`` (assistance_target |
    robot_gains | pulse_width) while the run holds the device, ``within`` the range of two parameters."""

    source: str = ""
    sets: str = ""
    within: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class _ExerciseFile:
    title: str = ""
    description: str = ""
    script: str = ""
    parameters: list[_ParameterFile] = field(default_factory=list)
    order: int = field(default=100, metadata=rng(0, 10_000))
    fes: _FesFile | None = None
    repetitions: str = ""
    composition: list[_CompositionFile] = field(default_factory=list)

    def validate(self) -> None:
        from app.core.ownership import COMPOSABLE_SOURCES, SETS

        if len(self.title) > 200:
            raise ValueError("the title is longer than 200 characters")
        if len(self.parameters) > 100:
            raise ValueError("more than 100 parameters")
        names = [p.name for p in self.parameters]
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise ValueError(f"a parameter name is repeated: {', '.join(repeated)}")
        by_name = {p.name: p for p in self.parameters}

        def needs(key: str, name: str, types: tuple[str, ...]) -> None:
            p = by_name.get(name)
            if p is None or p.type not in types:
                raise ValueError(f"{key}: {name!r} is not a {' or '.join(types)} parameter of this exercise")

        if self.fes is not None:
            needs("fes.profile", self.fes.profile, ("choice",))
            if self.fes.enabled:
                needs("fes.enabled", self.fes.enabled, ("bool",))
        if self.repetitions:
            needs("repetitions", self.repetitions, ("int",))
        for k, c in enumerate(self.composition):
            if c.source not in COMPOSABLE_SOURCES:
                raise ValueError(f"composition[{k}].source must be one of {', '.join(COMPOSABLE_SOURCES)}, "
                                 f"got {c.source!r}")
            if c.sets not in SETS:
                raise ValueError(f"composition[{k}].sets must be one of {', '.join(SETS)}, got {c.sets!r}")
            if c.within:
                if len(c.within) != 2:
                    raise ValueError(f"composition[{k}].within names two parameters (the range's ends)")
                for w in c.within:
                    needs(f"composition[{k}].within", w, ("float", "int"))


def _key_line(text: str, key: str, index: int | None = None) -> int | None:
    """The line of a top-level key, or of item ``index`` of its list (the text already passed check_yaml:
    composing it is safe)."""
    try:
        root = yamlschema.compose(text)
    except yaml.YAMLError:
        return None
    if isinstance(root, MappingNode):
        for knode, vnode in root.value:
            if knode.value != key:
                continue
            if index is None:
                return knode.start_mark.line + 1
            if isinstance(vnode, SequenceNode) and index < len(vnode.value):
                return vnode.value[index].start_mark.line + 1
    return None
    if isinstance(root, MappingNode):
        for knode, _ in root.value:
            if knode.value == key:
                return knode.start_mark.line + 1
    return None


def _script_path(path: Path, text: str, script: str) -> Path:
    """The exercise's script: a ``.py`` file directly in the exercise's own folder (never ``../``, an
    absolute path, or a link out of it: the library is what the clinic installed, nothing else runs)."""
    name = script or f"{path.stem}.py"

    def refuse(problem: str) -> typing.NoReturn:
        line = _key_line(text, "script") if script else None
        where = f"{path}:{line}" if line else str(path)
        raise ExerciseError(f"{where}: script: {problem}")

    if Path(name).name != name or name in (".", "..") or "\\" in name or Path(name).is_absolute():
        refuse(f"{name!r} must be a file name in the exercise's folder {path.parent}, not a path")
    if not name.endswith(".py"):
        refuse(f"{name!r} is not a Python script (.py)")
    candidate = path.parent / name
    folder = path.parent.resolve()
    try:
        resolved = candidate.resolve()
    except (OSError, RuntimeError) as exc:  # a link loop
        refuse(f"{name!r} cannot be resolved: {exc}")
    if resolved.parent != folder:
        refuse(f"{name!r} leads out of the exercise's folder {path.parent} (to {resolved})")
    if not resolved.is_file():
        refuse(f"script {name} not found in {path.parent}")
    return candidate


def load_exercise(path: str | Path) -> Exercise:
    """One exercise file through the config's strict loader. Raises ExerciseError naming the file and line."""
    path = Path(path)
    try:
        text = read_user_text(path)
        raw = load_dataclass(_ExerciseFile, text, str(path))
    except UserFileError as exc:
        raise ExerciseError(str(ConfigError.refused(exc))) from None
    except ConfigError as exc:
        raise ExerciseError(str(exc)) from None
    script = _script_path(path, text, raw.script)
    params = []
    for k, p in enumerate(raw.parameters):
        try:
            params.append(p.parameter())
        except ValueError as exc:  # the default outside the declared range: the parameter's own line
            line = _key_line(text, "parameters", k)
            raise ExerciseError(f"{path}:{line}: parameters[{k}]: {exc}" if line else f"{path}: {exc}") from None
    fes = raw.fes or _FesFile()
    composition = tuple({"source": c.source, "sets": c.sets, "within": list(c.within)} for c in raw.composition)
    return Exercise(path.stem, raw.title or path.stem, raw.description.strip(), script, tuple(params), raw.order,
                    fes_profile=fes.profile, fes_enabled=fes.enabled, repetitions=raw.repetitions,
                    composition=composition)


def load_library(folder: Path | None = None) -> tuple[list[Exercise], list[str]]:
    """(the exercises in their order, one line per file that could not be loaded: file:line and why).

    One bad file never stops the others (nor the window): it is listed, the rest load."""
    folder = EXERCISES_DIR if folder is None else folder
    out, problems = [], []
    try:
        paths = sorted(folder.glob("*.yaml"))
    except OSError as exc:
        return [], [f"{folder}: cannot list the exercises: {exc.strerror or exc}"]
    for path in paths:
        try:
            out.append(load_exercise(path))
        except ExerciseError as exc:
            problems.append(str(exc))
        except Exception as exc:  # whatever else a file does, it is this file's problem
            problems.append(f"{path}: cannot be loaded: {type(exc).__name__}: {exc}")
    out.sort(key=lambda e: (e.order, e.title))
    return out, problems


def find_exercise(ident: str, library: list[Exercise] | None = None) -> Exercise:
    for e in library if library is not None else load_library()[0]:
        if e.ident == ident:
            return e
    raise KeyError(f"no exercise '{ident}'")


# ------------------------------------------------------------------------------------------- starting
def exercise_program(exercise: Exercise, source: str | None = None) -> Any:
    """The exercise as a run's Program: its id, title, version (hash of its YAML + script as loaded) and the
    hash of the script's text (Recover refuses to restart it when the file changed since)."""
    from app.core.runs import Program, text_hash

    source = exercise.script.read_text(encoding="utf-8") if source is None else source
    yaml_path = exercise.script.parent / f"{exercise.ident}.yaml"
    try:
        yaml_text = yaml_path.read_text(encoding="utf-8")
    except OSError:
        yaml_text = ""
    version = text_hash(yaml_text + "\n" + source)[:16]
    return Program("exercise", exercise.ident, exercise.title, text_hash(source), version=version,
                   path=str(exercise.script))


def run_parameters(exercise: Exercise, params: Mapping[str, Any]) -> tuple[Any, ...]:
    """The checked values with their labels and units, in the form's order (the record a report prints)."""
    from app.core.runs import RunParameter

    return tuple(RunParameter(p.name, p.label, params[p.name], p.unit) for p in exercise.parameters
                 if p.name in params)


def run_problems(manager: EventHost, exercise: Exercise, params: Mapping[str, Any]) -> dict[str, str]:
    """:func:`prescription_problems` against what is in force now: the supervisor's robot limits (the session
    patient's), the stimulator's limits (their clinical caps as they are now) and their chosen electrodes."""
    sup = getattr(manager, "supervisor", None)
    limiter = getattr(sup, "fes_limiter", None)
    driver = getattr(manager, "driver", None)
    fes = driver(streams.FES) if callable(driver) else None
    profile = getattr(manager, "patient_profile", None)
    return prescription_problems(exercise, params, robot=getattr(sup, "robot", None),
                                 fes_limits=getattr(limiter, "limits", None),
                                 district_channels=getattr(fes, "district_channels", None),
                                 patient=getattr(profile, "patient_id", "") or "")


def start_exercise(runner: ExerciseRunner, manager: EventHost, exercise: Exercise, values: Mapping[str, Any], *,
                   source: RunSource = "exercises_tab", restart_of: str | None = None,
                   continues: str | None = None) -> Validation:
    """Validate and, only when every value is accepted — by the exercise's ranges and by the patient's limits,
    caps and electrode choices in force now (:func:`run_problems`) — record ``exercise_start`` and start the
    script on ``runner`` with the values as ``exerciseParams``, as a run (app/core/runs.py) of kind "exercise" with
    the parameters' labels and units, started from ``source`` (``restart_of``: the run Recover restarts;
    ``continues``: the interrupted run whose remaining repetitions this one does). The run holds the robot (and
    the stimulator when it stimulates) and composes what the exercise declares (app/core/ownership.py).
    Returns the validation (``ok`` False: nothing started). Raises RuntimeError when a script already runs, a
    STOP holds the robot or another holds the devices (nothing started, nothing recorded)."""
    from app.core.ownership import start_problem

    checked = validate(exercise, values)
    if not checked.ok:
        return checked
    checked.errors.update(run_problems(manager, exercise, checked.params))
    if not checked.ok:
        return checked
    if runner.running:
        raise RuntimeError("a script is running: stop it before starting an exercise")
    problem = start_problem(manager, exercise.holds(checked.params))
    if problem:
        raise RuntimeError(problem)
    text = exercise.script.read_text(encoding="utf-8")
    data = {"exercise": exercise.ident, "title": exercise.title, "script": exercise.script.name,
            "params": dict(checked.params)}
    manager.record_event(journal.EXERCISE_START, "", **data)  # the record of what the clinician chose
    runner.start(text, str(exercise.script), dict(checked.params), program=exercise_program(exercise, text),
                 parameters=run_parameters(exercise, checked.params), run_source=source,
                 restart_of=restart_of, continues=continues, holds=exercise.holds(checked.params),
                 compose=exercise.compositions(checked.params))
    return checked
