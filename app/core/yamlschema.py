"""Strict YAML → dataclass loading with errors that name the file, the key and the line.

Every user-edited YAML file of the application (config, patient profiles, ...) goes through here,
so a typo is reported the same way everywhere and nothing is ever half-applied: the whole file is
validated into new objects first, and only a complete, valid result is returned.

Field constraints live in dataclass field metadata: ``field(default=..., metadata=rng(0, 1))``.

Hostile or broken files are refused the same way, before anything is built (``check_yaml``): bytes that
are not UTF-8, a file above ``MAX_FILE_BYTES``, more than ``MAX_NODES`` nodes, nesting deeper than
``MAX_DEPTH``, a scalar longer than ``MAX_SCALAR_CHARS`` (a 5000-digit number), any tag other than
YAML's plain ones (``!!python/...`` anywhere, on a scalar, a list or a mapping) and anchors/aliases.
The walk is iterative (PyYAML's parser is a generator), so no input can exhaust the stack.

Parsing uses libyaml (PyYAML's C parser) when the installed PyYAML has it, as its wheels do: the same events,
nodes, tags and marks, ten times faster than the pure-Python parser. Saving a therapy plan reads every exercise
and the patient's profile on the window's thread, and with the pure-Python parser it held that thread for
0.3-0.7 s while the patient was being stimulated (the GUI watch's alarm, issue #37).
"""

from __future__ import annotations

import dataclasses
import enum
import types
import typing
from pathlib import Path
from typing import Any, TypeVar, cast

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from app.core.safe_files import DEFAULT_MAX_BYTES, UserFileError, decode_user_text, read_user_text

T = TypeVar("T")

MAX_FILE_BYTES = DEFAULT_MAX_BYTES  # app.core.safe_files: what its reader accepts
MAX_NODES = 50_000
MAX_DEPTH = 32
MAX_SCALAR_CHARS = 10_000
MAX_NUMBER_CHARS = 64
_PLAIN_TAGS = {f"tag:yaml.org,2002:{t}" for t in ("str", "int", "float", "bool", "null", "map", "seq")}
# libyaml when present (PyYAML's wheels have it), else PyYAML's own parser: same events, nodes and marks.
YAML_LOADER: type[yaml.SafeLoader] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def compose(text: str) -> Node | None:
    """The node tree of YAML ``text`` (tags resolved, marks kept); raises yaml.YAMLError. Run ``check_yaml``
    first on anything a user wrote."""
    return yaml.compose(text, Loader=YAML_LOADER)


class ConfigError(ValueError):
    """A user file is malformed. The message names the file, the line and the key path."""

    def __init__(self, filename: str, line: int | None, key: str, problem: str) -> None:
        self.filename = filename
        self.line = line
        self.key = key
        self.problem = problem
        where = f"{filename}:{line}" if line is not None else filename
        super().__init__(f"{where}: {key or '(top level)'}: {problem}")

    @classmethod
    def refused(cls, exc: UserFileError) -> ConfigError:
        """The safe reader's refusal (app.core.safe_files) as a ConfigError: the file, the line when it has one."""
        return cls(exc.path, exc.line, "", f"cannot read the file: {exc.problem}")


def rng(lo: float | None = None, hi: float | None = None, unit: str = "") -> dict[str, Any]:
    """Field metadata: an inclusive numeric range (and the unit, for messages and the UI)."""
    return {"min": lo, "max": hi, "unit": unit}


def _line(node: Node) -> int:
    return int(node.start_mark.line) + 1


_SCALARS = yaml.constructor.SafeConstructor()  # stateless for scalars: construct_<tag> reads the node only
_SCALAR_BUILDERS: dict[str, Any] = {
    "tag:yaml.org,2002:int": _SCALARS.construct_yaml_int,
    "tag:yaml.org,2002:float": _SCALARS.construct_yaml_float,
    "tag:yaml.org,2002:bool": _SCALARS.construct_yaml_bool,
    "tag:yaml.org,2002:null": _SCALARS.construct_yaml_null,
}


def _scalar_value(node: ScalarNode) -> Any:
    # The scalar by YAML's own rules (int, float, bool, null, str): the tag the composer resolved, built by
    # PyYAML's safe constructor (as yaml.safe_load would); any other tag stays the text (check_yaml refused it).
    build = _SCALAR_BUILDERS.get(node.tag)
    return build(node) if build is not None else node.value


class _Loader:
    def __init__(self, filename: str) -> None:
        self.filename = filename

    def fail(self, node: Node | None, key: str, problem: str) -> typing.NoReturn:
        raise ConfigError(self.filename, _line(node) if node is not None else None, key, problem)

    def build(self, tp: Any, node: Node, key: str, meta: dict[str, Any] | None = None) -> Any:
        origin = typing.get_origin(tp)
        args = typing.get_args(tp)
        if origin in (typing.Union, types.UnionType):
            non_none = [a for a in args if a is not type(None)]
            if isinstance(node, ScalarNode) and node.tag == "tag:yaml.org,2002:null":
                if len(non_none) != len(args):
                    return None
            if len(non_none) == 1:
                return self.build(non_none[0], node, key, meta)
            errors = []
            for alt in non_none:
                try:
                    return self.build(alt, node, key, meta)
                except ConfigError as exc:
                    errors.append(exc.problem)
            self.fail(node, key, " or ".join(errors))
        if dataclasses.is_dataclass(tp):
            return self.build_dataclass(cast("type[Any]", tp), node, key)  # a class here: a hint is never an instance
        if origin is list:
            if not isinstance(node, SequenceNode):
                self.fail(node, key, "expected a list")
            return [self.build(args[0], item, f"{key}[{i}]", meta) for i, item in enumerate(node.value)]
        if origin is dict:
            if not isinstance(node, MappingNode):
                self.fail(node, key, "expected a mapping")
            out: dict[Any, Any] = {}
            for knode, vnode in node.value:
                k = self.build(args[0], knode, key)
                if k in out:
                    self.fail(knode, f"{key}.{k}", "duplicate key")
                out[k] = self.build(args[1], vnode, f"{key}.{k}", meta)
            return out
        if origin is typing.Literal:
            if not isinstance(node, ScalarNode):
                self.fail(node, key, f"expected one of {', '.join(map(repr, args))}")
            value = _scalar_value(node)
            if value not in args:
                self.fail(node, key, f"expected one of {', '.join(map(repr, args))}, got {value!r}")
            return value
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            value = _scalar_value(node) if isinstance(node, ScalarNode) else None
            for member in tp:
                if value in (member.value, member.name):
                    return member
            self.fail(node, key, f"expected one of {', '.join(m.name for m in tp)}, got {value!r}")
        if not isinstance(node, ScalarNode):
            kind = "list" if isinstance(node, SequenceNode) else "mapping"
            wanted = "single value" if tp is Any else getattr(tp, "__name__", tp)
            self.fail(node, key, f"expected a {wanted}, got a {kind}")
        value = _scalar_value(node)
        return self.check_scalar(tp, value, node, key, meta or {})

    def check_scalar(self, tp: Any, value: Any, node: Node, key: str, meta: dict[str, Any]) -> Any:
        if tp is bool:
            if not isinstance(value, bool):
                self.fail(node, key, f"expected true or false, got {value!r}")
            return value
        if tp is int:
            if isinstance(value, bool) or not isinstance(value, int):
                self.fail(node, key, f"expected a whole number, got {value!r}")
        elif tp is float:
            if isinstance(value, bool) or not isinstance(value, int | float):
                self.fail(node, key, f"expected a number, got {value!r}")
            value = float(value)
            if value != value or value in (float("inf"), float("-inf")):
                self.fail(node, key, f"expected a finite number, got {value!r}")
        elif tp is str:
            if not isinstance(value, str):
                value = node.value  # e.g. a port named 12 is still a name
        elif tp is Path:
            if not isinstance(value, str):
                self.fail(node, key, f"expected a path, got {value!r}")
            value = Path(value).expanduser()
        elif tp is Any:
            return value
        else:  # pragma: no cover - schema error, not a user error
            raise TypeError(f"unsupported field type {tp!r} at {key}")
        lo, hi, unit = meta.get("min"), meta.get("max"), meta.get("unit", "")
        if isinstance(value, int | float) and not isinstance(value, bool):
            suffix = f" {unit}" if unit else ""
            if (lo is not None and value < lo) or (hi is not None and value > hi):
                bounds = f"{lo if lo is not None else '-∞'} .. {hi if hi is not None else '∞'}{suffix}"
                self.fail(node, key, f"{value}{suffix} is outside the allowed range {bounds}")
        return value

    def build_dataclass(self, cls: type[T], node: Node, key: str, base: T | None = None) -> T:
        if not isinstance(node, MappingNode):
            if isinstance(node, ScalarNode) and node.tag == "tag:yaml.org,2002:null":
                return base if base is not None else cls()  # an empty section keeps its defaults
            self.fail(node, key, "expected a mapping of keys to values")
        hints = typing.get_type_hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cast(Any, cls)) if f.init}  # a dataclass: the caller checked
        values: dict[str, Any] = {}
        for knode, vnode in node.value:
            name = knode.value
            path = f"{key}.{name}" if key else str(name)
            if name not in fields:
                self.fail(knode, path, f"unknown key; expected one of: {', '.join(fields)}")
            if name in values:
                self.fail(knode, path, "duplicate key")
            sub_base = getattr(base, name) if base is not None else None
            if dataclasses.is_dataclass(hints[name]) and sub_base is not None:
                values[name] = self.build_dataclass(hints[name], vnode, path, sub_base)
            else:
                values[name] = self.build(hints[name], vnode, path, dict(fields[name].metadata))
        try:
            obj = dataclasses.replace(cast(Any, base), **values) if base is not None else cls(**values)
        except TypeError as exc:
            missing = [n for n, f in fields.items() if n not in values and f.default is dataclasses.MISSING
                       and f.default_factory is dataclasses.MISSING]
            self.fail(node, key, f"missing required key(s): {', '.join(missing)}" if missing else str(exc))
        validate = getattr(obj, "validate", None)
        if callable(validate):
            try:
                validate()
            except ValueError as exc:
                self.fail(node, key, str(exc))
        return obj


def check_yaml(text: str, filename: str) -> None:
    """Refuse what no user file of ours needs (module docstring); ConfigError naming file and line."""
    if len(text) > MAX_FILE_BYTES:
        raise ConfigError(filename, None, "", f"the file is larger than {MAX_FILE_BYTES // 1024} KiB")
    depth = nodes = 0
    try:
        for ev in yaml.parse(text, Loader=YAML_LOADER):
            line = ev.start_mark.line + 1 if ev.start_mark is not None else None
            if isinstance(ev, yaml.AliasEvent) or getattr(ev, "anchor", None):
                raise ConfigError(filename, line, "", "anchors and aliases (&, *) are not allowed")
            tag = getattr(ev, "tag", None)
            if tag is not None and tag != "!" and tag not in _PLAIN_TAGS:
                raise ConfigError(filename, line, "", f"the tag {tag} is not allowed (plain values only)")
            if isinstance(ev, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_DEPTH:
                    raise ConfigError(filename, line, "", f"nested deeper than {MAX_DEPTH} levels")
            elif isinstance(ev, yaml.CollectionEndEvent):
                depth -= 1
            if isinstance(ev, yaml.NodeEvent):
                nodes += 1
                if nodes > MAX_NODES:
                    raise ConfigError(filename, line, "", f"more than {MAX_NODES} values")
            if isinstance(ev, yaml.ScalarEvent):
                value = ev.value
                if len(value) > MAX_SCALAR_CHARS:
                    raise ConfigError(filename, line, "", f"a value longer than {MAX_SCALAR_CHARS} characters")
                # a plain scalar's style: None from PyYAML's parser, '' from libyaml
                if not ev.style and len(value) > MAX_NUMBER_CHARS and value.lstrip("+-")[:1].isdigit() \
                        and value.replace("_", "").lstrip("+-").replace(".", "").replace("e", "").isdigit():
                    raise ConfigError(filename, line, "", f"a number of {len(value)} digits")
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        line = mark.line + 1 if mark else None
        if "maximum nesting depth" in str(exc.problem):  # libyaml's own bound (1000) met before ours
            raise ConfigError(filename, line, "", f"nested deeper than {MAX_DEPTH} levels") from exc
        raise ConfigError(filename, line, "", f"not valid YAML: {exc.problem}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(filename, None, "", f"not valid YAML: {exc}") from exc


def load_dataclass(cls: type[T], text: str, filename: str, base: T | None = None) -> T:
    """Parse YAML ``text`` into ``cls`` (over ``base`` when given). Raises ConfigError."""
    check_yaml(text, filename)
    try:
        node = compose(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        raise ConfigError(filename, mark.line + 1 if mark else None, "", f"not valid YAML: {exc.problem}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(filename, None, "", f"not valid YAML: {exc}") from exc
    loader = _Loader(filename)
    if node is None:
        return base if base is not None else cls()
    try:
        return loader.build_dataclass(cls, node, "", base)
    except ConfigError:
        raise
    except (yaml.YAMLError, ValueError, TypeError, RecursionError) as exc:  # never a traceback for a user file
        mark = getattr(exc, "problem_mark", None)
        raise ConfigError(filename, mark.line + 1 if mark else None, "", f"cannot read a value: {exc}") from exc


def decode_text(data: bytes | str, filename: str) -> str:
    """Text handed over in memory (a script's FES profile) as a file's would be read: ConfigError above
    ``MAX_FILE_BYTES`` or when not UTF-8 (naming the line)."""
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(filename, None, "", f"the file is larger than {MAX_FILE_BYTES // 1024} KiB")
    if isinstance(data, str):
        return data
    try:
        return decode_user_text(data, filename)
    except UserFileError as exc:
        raise ConfigError(filename, exc.line, "", exc.problem) from None


def load_file(cls: type[T], path: str | Path, base: T | None = None) -> T:
    """A user's YAML file (read by app.core.safe_files, the one safe reader) into ``cls``. Raises ConfigError."""
    path = Path(path)
    try:
        text = read_user_text(path, MAX_FILE_BYTES)
    except UserFileError as exc:
        raise ConfigError.refused(exc) from exc
    return load_dataclass(cls, text, str(path), base)


def to_plain(obj: Any) -> Any:
    """A dataclass tree as plain YAML-serialisable data (for saving and manifests)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_plain(v) for v in obj]
    if isinstance(obj, enum.Enum):
        return obj.name
    if isinstance(obj, Path):
        return str(obj)
    return obj
