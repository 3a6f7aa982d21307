"""Exercises as forms: a script plus a declared parameter schema.

An exercise is ``resources/exercises/<id>.yaml`` (title, description, script, parameters) next to its script
``<id>.py``. Each parameter declares name, label, type (``int`` | ``float`` | ``bool`` | ``choice``), unit,
range, default and help; the Exercises tab draws the form from it and :func:`validate` checks what was typed:
a value out of its range is refused with the reason and nothing is started. The script reads its values as
the global ``exerciseParams`` (ScriptRunner.start's ``params``) and marks its repetitions with
``linarmppManager.startRepetition / endRepetition``.

:func:`start_exercise` records ``exercise_start {exercise, title, script, params}`` as a session event (the
metrics and the reports read the parameters from it) and starts the script on the window's runner.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from app.resources import RESOURCES

EXERCISES_DIR = RESOURCES / "exercises"
PARAMETER_TYPES = ("int", "float", "bool", "choice")
_PARAMETER_KEYS = {"name", "label", "type", "unit", "min", "max", "default", "help", "options"}
_EXERCISE_KEYS = {"title", "description", "script", "parameters", "order"}


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

    def defaults(self) -> dict[str, Any]:
        return {p.name: p.default for p in self.parameters}

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


# ------------------------------------------------------------------------------------------- loading
def _parameter(raw: Any, where: str) -> Parameter:
    if not isinstance(raw, dict):
        raise ExerciseError(f"{where}: a parameter must be a mapping")
    unknown = set(raw) - _PARAMETER_KEYS
    if unknown:
        raise ExerciseError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}")
    name = raw.get("name")
    if not isinstance(name, str) or not name.isidentifier():
        raise ExerciseError(f"{where}: 'name' must be an identifier, got {name!r}")
    kind = raw.get("type", "float")
    if kind not in PARAMETER_TYPES:
        raise ExerciseError(f"{where} ({name}): type must be one of {', '.join(PARAMETER_TYPES)}")
    options = tuple(str(o) for o in raw.get("options") or ())
    if kind == "choice" and not options:
        raise ExerciseError(f"{where} ({name}): a choice needs options")
    for bound in ("min", "max"):
        if raw.get(bound) is not None and not isinstance(raw[bound], int | float):
            raise ExerciseError(f"{where} ({name}): {bound} must be a number")
    if "default" not in raw:
        raise ExerciseError(f"{where} ({name}): a default is required")
    p = Parameter(name=name, label=str(raw.get("label") or name), type=kind, default=raw["default"],
                  unit=str(raw.get("unit") or ""), min=raw.get("min"), max=raw.get("max"),
                  help=str(raw.get("help") or ""), options=options)
    value, why = p.check(p.default)
    if why:
        raise ExerciseError(f"{where} ({name}): the default is refused: {why}")
    return Parameter(**{**p.__dict__, "default": value})


def load_exercise(path: str | Path) -> Exercise:
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ExerciseError(f"{path}: {exc}") from exc
    if not isinstance(raw, dict):
        raise ExerciseError(f"{path}: an exercise must be a mapping")
    unknown = set(raw) - _EXERCISE_KEYS
    if unknown:
        raise ExerciseError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}")
    script = path.parent / str(raw.get("script") or f"{path.stem}.py")
    if not script.is_file():
        raise ExerciseError(f"{path}: script {script.name} not found")
    params = tuple(_parameter(p, f"{path}: parameters[{k}]") for k, p in enumerate(raw.get("parameters") or []))
    names = [p.name for p in params]
    if len(set(names)) != len(names):
        raise ExerciseError(f"{path}: a parameter name is repeated")
    return Exercise(path.stem, str(raw.get("title") or path.stem), str(raw.get("description") or "").strip(),
                    script, params, int(raw.get("order", 100)))


def load_library(folder: Path = EXERCISES_DIR) -> tuple[list[Exercise], list[str]]:
    """(the exercises in their order, problems with files that could not be loaded)."""
    out, problems = [], []
    for path in sorted(folder.glob("*.yaml")):
        try:
            out.append(load_exercise(path))
        except ExerciseError as exc:
            problems.append(str(exc))
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
    from app.runs import Program, text_hash

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
    from app.runs import RunParameter

    return tuple(RunParameter(p.name, p.label, params[p.name], p.unit) for p in exercise.parameters
                 if p.name in params)


def start_exercise(runner: Any, manager: Any, exercise: Exercise, values: Mapping[str, Any], *,
                   source: str = "exercises_tab", restart_of: str | None = None) -> Validation:
    """Validate and, only when every value is accepted, record ``exercise_start`` and start the script on
    ``runner`` with the values as ``exerciseParams``, as a run (app/runs.py) of kind "exercise" with the
    parameters' labels and units, started from ``source`` (``restart_of``: the run Recover restarts).
    Returns the validation (``ok`` False: nothing started). Raises RuntimeError when a script already runs
    (nothing started either)."""
    checked = validate(exercise, values)
    if not checked.ok:
        return checked
    if runner.running:
        raise RuntimeError("a script is running: stop it before starting an exercise")
    text = exercise.script.read_text(encoding="utf-8")
    data = {"exercise": exercise.ident, "title": exercise.title, "script": exercise.script.name,
            "params": dict(checked.params)}
    record = getattr(manager, "record_event", None)
    sup = getattr(manager, "supervisor", None)
    if callable(record) and getattr(manager, "recorder", None) is not None:
        record("exercise_start", "", **data)  # the session's own record of what the clinician chose
    elif sup is not None:
        sup.event("exercise_start", **data)
    if _takes_run(runner):
        runner.start(text, str(exercise.script), dict(checked.params), program=exercise_program(exercise, text),
                     parameters=run_parameters(exercise, checked.params), run_source=source,
                     restart_of=restart_of)
    else:  # a runner without run records (a test's stand-in)
        runner.start(text, str(exercise.script), dict(checked.params))
    return checked


def _takes_run(runner: Any) -> bool:
    import inspect

    try:
        params = inspect.signature(runner.start).parameters
    except (TypeError, ValueError):
        return False
    return "program" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
