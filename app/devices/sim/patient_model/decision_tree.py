"""The patient model's five-layer decision tree (D2.1, "Patient model").

alpha is the robot support: +1 full assistance .. -1 full resistance.  Starting from [-1, 1]:

1. the clinical score puts the patient in a group -- assist, in_between or resist -- each with its
   own alpha range (three branches);
2. TPI (task performance), 3. MPI (motor performance), 4. PTI (physiological trend): each node
   compares its index with a threshold and takes the "high" or "low" branch; a branch keeps a part
   of the parent's range (the more-support part or the less-support part, overlapping unless the
   narrowing is 0.5 or more).  PTI narrows least: physiology is the least reliable input;
5. the sub-task layer picks one alpha in the final range [lo, hi]: alpha = lo + level*(hi - lo).
   The level starts at the minimal support (``start_level``, 0), rises by ``step_up`` after each
   failed sub-task up to the maximal support, and falls by ``step_down`` after each success.

Thresholds, ranges and steps come from resources/patient_model.yaml; ``load_tree_config`` checks
it and names the line of any mistake.  ``DecisionTree.decide`` returns alpha with the decision path
so a viewer can draw it (``branch_ranges`` gives every node's range for drawing the whole tree).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import yaml

from app.core.resources import PATIENT_MODEL_FILE

GROUPS: Final = ("assist", "in_between", "resist")
INDEX_LAYERS: Final = ("tpi", "mpi", "pti")
LESS_SUPPORT: Final = "less_support"
MORE_SUPPORT: Final = "more_support"
DEFAULT_CONFIG_PATH: Final = PATIENT_MODEL_FILE


class PatientModelConfigError(ValueError):
    """A mistake in the decision-tree file; ``line`` is 1-based (0 when unknown)."""

    def __init__(self, source: str, line: int, message: str) -> None:
        where = f"{source} line {line}" if line else source
        super().__init__(f"{where}: {message}")
        self.source = source
        self.line = line
        self.message = message


# ---------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class IndexLayer:
    threshold: float
    narrowing: float
    highIndexMeans: str = LESS_SUPPORT
    nodeThresholds: dict[str, float] = field(default_factory=dict)

    def threshold_at(self, node: str) -> float:
        return self.nodeThresholds.get(node, self.threshold)


@dataclass(frozen=True)
class TreeConfig:
    scoreName: str
    scoreMin: float
    scoreMax: float
    higherIsBetter: bool
    scoreThresholds: tuple[float, float]
    groupRanges: dict[str, tuple[float, float]]
    layers: dict[str, IndexLayer]
    startLevel: float = 0.0
    stepUp: float = 0.2
    stepDown: float = 0.1


def node_paths(layer: str) -> list[str]:
    """Paths of the nodes deciding on ``layer`` ('tpi' has 3, 'mpi' 6, 'pti' 12)."""
    paths = list(GROUPS)
    for name in INDEX_LAYERS[:INDEX_LAYERS.index(layer)]:
        paths = [f"{p}/{name}_{b}" for p in paths for b in ("low", "high")]
    return paths


# -- YAML with line numbers ---------------------------------------------------------------------


class _Map(dict):
    line: int = 0
    lines: dict[Any, int]


class _Seq(list):
    line: int = 0


class _Loader(yaml.SafeLoader):
    pass


def _construct_map(loader: _Loader, node: yaml.MappingNode) -> _Map:
    loader.flatten_mapping(node)
    out = _Map()
    out.line = node.start_mark.line + 1
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in out:
            raise PatientModelConfigError("", key_node.start_mark.line + 1, f"'{key}' appears twice")
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = value_node.start_mark.line + 1
    return out


def _construct_seq(loader: _Loader, node: yaml.SequenceNode) -> _Seq:
    out = _Seq(loader.construct_object(n, deep=True) for n in node.value)
    out.line = node.start_mark.line + 1
    return out


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_map)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_seq)


class _Checker:
    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, line: int, message: str) -> PatientModelConfigError:
        return PatientModelConfigError(self.source, line, message)

    def mapping(self, parent: _Map, key: str, where: str, allowed: set[str], required: set[str]) -> _Map:
        value = parent.get(key)
        line = parent.lines.get(key, parent.line)
        if not isinstance(value, _Map):
            raise self.fail(line, f"{where} must be a mapping")
        for k in value:
            if k not in allowed:
                raise self.fail(value.lines[k], f"unknown key '{k}' in {where} (expected one of:"
                                f" {', '.join(sorted(allowed))})")
        for k in sorted(required - set(value)):
            raise self.fail(value.line, f"{where}.{k} is missing")
        return value

    def number(self, m: _Map, key: str, where: str, lo: float = -math.inf, hi: float = math.inf,
               default: float | None = None) -> float:
        if key not in m and default is not None:
            return default
        v = m.get(key)
        line = m.lines.get(key, m.line)
        if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi:
            rng = f" in {lo:g}..{hi:g}" if math.isfinite(lo) or math.isfinite(hi) else ""
            raise self.fail(line, f"{where}.{key} must be a number{rng}, got {v!r}")
        return float(v)

    def pair(self, m: _Map, key: str, where: str, lo: float, hi: float) -> tuple[float, float]:
        v = m.get(key)
        line = m.lines.get(key, m.line)
        if (not isinstance(v, list) or len(v) != 2
                or any(isinstance(x, bool) or not isinstance(x, int | float) for x in v)):
            raise self.fail(line, f"{where}.{key} must be a pair of numbers [low, high], got {v!r}")
        a, b = float(v[0]), float(v[1])
        if not lo <= a <= b <= hi:
            raise self.fail(line, f"{where}.{key} must satisfy {lo:g} <= low <= high <= {hi:g}, got {v!r}")
        return a, b


def parse_tree_config(text: str, source: str = "patient_model.yaml") -> TreeConfig:
    """Parse and check the decision-tree YAML; errors name the line."""
    from app.core.yamlschema import ConfigError, check_yaml

    try:  # the same limits as every user file: tags, aliases, size, depth (issue #17)
        check_yaml(text, source)
    except ConfigError as exc:
        raise PatientModelConfigError(source, exc.line or 0, exc.problem) from None
    try:
        doc = yaml.load(text, Loader=_Loader)  # a SafeLoader subclass: no arbitrary objects
    except PatientModelConfigError as exc:
        raise PatientModelConfigError(source, exc.line, exc.message) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        detail = f"not valid YAML: {exc.problem or exc}"
        if exc.context and exc.context_mark and mark and exc.context_mark.line != mark.line:
            detail += f" ({exc.context} started on line {exc.context_mark.line + 1})"
        raise PatientModelConfigError(source, mark.line + 1 if mark else 0, detail) from None
    except yaml.YAMLError as exc:
        raise PatientModelConfigError(source, 0, f"not valid YAML: {exc}") from None
    ck = _Checker(source)
    if not isinstance(doc, _Map):
        raise ck.fail(1, "the file must be a mapping with clinical_score, groups, layers, subtask")
    root = _Map({"root": doc})
    root.line, root.lines = 1, {"root": 1}
    top = ck.mapping(root, "root", "the file", {"version", "clinical_score", "groups", "layers", "subtask"},
                     {"version", "clinical_score", "groups", "layers", "subtask"})
    if top["version"] != 1:
        raise ck.fail(top.lines["version"], f"version must be 1, got {top['version']!r}")

    cs = ck.mapping(top, "clinical_score", "clinical_score",
                    {"name", "min", "max", "higher_is_better", "thresholds"}, {"min", "max", "thresholds"})
    name = cs.get("name", "clinical score")
    if not isinstance(name, str):
        raise ck.fail(cs.lines["name"], "clinical_score.name must be text")
    smin = ck.number(cs, "min", "clinical_score")
    smax = ck.number(cs, "max", "clinical_score")
    if smax <= smin:
        raise ck.fail(cs.lines["max"], f"clinical_score.max must be greater than min ({smin:g})")
    hib = cs.get("higher_is_better", True)
    if not isinstance(hib, bool):
        raise ck.fail(cs.lines["higher_is_better"], f"clinical_score.higher_is_better must be true or false,"
                      f" got {hib!r}")
    thresholds = ck.pair(cs, "thresholds", "clinical_score", smin, smax)

    gm = ck.mapping(top, "groups", "groups", set(GROUPS), set(GROUPS))
    ranges: dict[str, tuple[float, float]] = {}
    for g in GROUPS:
        entry = ck.mapping(gm, g, f"groups.{g}", {"alpha"}, {"alpha"})
        ranges[g] = ck.pair(entry, "alpha", f"groups.{g}", -1.0, 1.0)

    lm = ck.mapping(top, "layers", "layers", set(INDEX_LAYERS), set(INDEX_LAYERS))
    layers: dict[str, IndexLayer] = {}
    for name_ in INDEX_LAYERS:
        entry = ck.mapping(lm, name_, f"layers.{name_}",
                           {"threshold", "narrowing", "high_index_means", "node_thresholds"},
                           {"threshold", "narrowing", "high_index_means"})
        where = f"layers.{name_}"
        thr = ck.number(entry, "threshold", where, 0.0, 1.0)
        narrowing = ck.number(entry, "narrowing", where, 0.0, 0.95)
        means = entry["high_index_means"]
        if means not in (LESS_SUPPORT, MORE_SUPPORT):
            raise ck.fail(entry.lines["high_index_means"],
                          f"{where}.high_index_means must be {LESS_SUPPORT} or {MORE_SUPPORT}, got {means!r}")
        per_node: dict[str, float] = {}
        if "node_thresholds" in entry:
            nt = ck.mapping(entry, "node_thresholds", f"{where}.node_thresholds",
                            set(node_paths(name_)), set())
            for path in nt:
                per_node[path] = ck.number(nt, path, f"{where}.node_thresholds", 0.0, 1.0)
        layers[name_] = IndexLayer(thr, narrowing, means, per_node)
    if layers["pti"].narrowing > min(layers["tpi"].narrowing, layers["mpi"].narrowing):
        raise ck.fail(lm["pti"].lines["narrowing"], "layers.pti.narrowing must not exceed the tpi and mpi"
                      " narrowing: physiology is the least reliable input (D2.1)")

    st = ck.mapping(top, "subtask", "subtask", {"start_level", "step_up", "step_down"},
                    {"step_up", "step_down"})
    start = ck.number(st, "start_level", "subtask", 0.0, 1.0, default=0.0)
    up = ck.number(st, "step_up", "subtask", 0.0, 1.0)
    if up <= 0.0:
        raise ck.fail(st.lines["step_up"], "subtask.step_up must be greater than 0")
    down = ck.number(st, "step_down", "subtask", 0.0, 1.0)
    return TreeConfig(name, smin, smax, hib, thresholds, ranges, layers, start, up, down)


def load_tree_config(path: str | Path = DEFAULT_CONFIG_PATH) -> TreeConfig:
    p = Path(path)
    from app.core.safe_files import UserFileError, read_user_text

    try:
        text = read_user_text(p)
    except UserFileError as exc:
        raise PatientModelConfigError(str(p), exc.line or 0, f"cannot read the file: {exc.problem}") from None
    return parse_tree_config(text, str(p))


# ---------------------------------------------------------------------------------------------
# Decisions


@dataclass(frozen=True)
class DecisionStep:
    """One layer's decision: at ``node`` the ``quantity`` had ``value``; it took ``branch``."""

    layer: int                       # 1..5
    quantity: str                    # clinical_score, tpi, mpi, pti, subtask
    node: str                        # path of the deciding node ("" for the root)
    value: float
    threshold: tuple[float, ...]     # the thresholds compared with (empty for layer 5)
    branch: str                      # assist/in_between/resist, low/high, or "level"
    alphaRange: tuple[float, float]  # the range after this layer


@dataclass(frozen=True)
class Decision:
    alpha: float
    alphaRange: tuple[float, float]
    level: float                     # layer-5 position inside the range, 0 = minimal support
    path: tuple[DecisionStep, ...]

    @property
    def group(self) -> str:
        return self.path[0].branch

    @property
    def leaf(self) -> str:
        """Path of the final range, e.g. 'assist/tpi_low/mpi_high/pti_low'."""
        return self.path[3].node + f"/pti_{self.path[3].branch}"

    @property
    def path_code(self) -> int:
        """One byte for the UDP reply: bits 0-1 group (0 assist, 1 in_between, 2 resist),
        bit 2 TPI high, bit 3 MPI high, bit 4 PTI high."""
        code = GROUPS.index(self.group)
        for bit, step in zip((2, 3, 4), self.path[1:4], strict=True):
            if step.branch == "high":
                code |= 1 << bit
        return code


def decode_path_code(code: int) -> tuple[str, bool, bool, bool] | None:
    """(group, tpi high, mpi high, pti high), or None for a code no tree produces."""
    g = code & 0x03
    if g >= len(GROUPS) or code & ~0x1F:
        return None
    return GROUPS[g], bool(code & 0x04), bool(code & 0x08), bool(code & 0x10)


def _split(lo: float, hi: float, narrowing: float, more_support: bool) -> tuple[float, float]:
    cut = narrowing * (hi - lo)
    return (lo + cut, hi) if more_support else (lo, hi - cut)


class DecisionTree:
    """The tree plus the layer-5 state (support level after the sub-tasks seen so far)."""

    def __init__(self, config: TreeConfig | None = None) -> None:
        self.config = config or load_tree_config()
        self.level = self.config.startLevel

    @classmethod
    def from_yaml(cls, text: str, source: str = "patient_model.yaml") -> DecisionTree:
        return cls(parse_tree_config(text, source))

    def reset(self) -> None:
        """New session or new exercise: back to the minimal support."""
        self.level = self.config.startLevel

    def record_subtask(self, success: bool) -> float:
        """Layer 5: a sub-task ended; returns the new level (0..1 of the final range)."""
        c = self.config
        self.level = max(0.0, self.level - c.stepDown) if success else min(1.0, self.level + c.stepUp)
        return self.level

    def group_of(self, clinical_score: float) -> str:
        c = self.config
        if not c.scoreMin <= clinical_score <= c.scoreMax:  # also rejects NaN
            raise ValueError(f"{c.scoreName} {clinical_score!r} outside {c.scoreMin:g}..{c.scoreMax:g}")
        low, high = c.scoreThresholds
        if c.higherIsBetter:
            return "assist" if clinical_score < low else "in_between" if clinical_score < high else "resist"
        return "assist" if clinical_score > high else "in_between" if clinical_score > low else "resist"

    def decide(self, clinical_score: float, tpi: float, mpi: float, pti: float) -> Decision:
        """Walk the tree; indices are clipped to 0..1 (NaN is refused: substitute before calling)."""
        c = self.config
        group = self.group_of(clinical_score)
        lo, hi = c.groupRanges[group]
        steps = [DecisionStep(1, "clinical_score", "", float(clinical_score), c.scoreThresholds, group,
                              (lo, hi))]
        node = group
        for name, raw in zip(INDEX_LAYERS, (tpi, mpi, pti), strict=True):
            if math.isnan(raw):
                raise ValueError(f"{name} is NaN")
            value = min(1.0, max(0.0, float(raw)))
            layer = c.layers[name]
            thr = layer.threshold_at(node)
            high = value >= thr
            more_support = high == (layer.highIndexMeans == MORE_SUPPORT)
            lo, hi = _split(lo, hi, layer.narrowing, more_support)
            branch = "high" if high else "low"
            layer_no = 2 + INDEX_LAYERS.index(name)
            steps.append(DecisionStep(layer_no, name, node, value, (thr,), branch, (lo, hi)))
            node = f"{node}/{name}_{branch}"
        alpha = lo + self.level * (hi - lo)
        steps.append(DecisionStep(5, "subtask", node, self.level, (), "level", (alpha, alpha)))
        return Decision(alpha, (lo, hi), self.level, tuple(steps))

    def branch_ranges(self) -> dict[str, tuple[float, float]]:
        """The alpha range after every branch of layers 1-4, keyed by path (3 + 6 + 12 + 24)."""
        c = self.config
        out: dict[str, tuple[float, float]] = {g: c.groupRanges[g] for g in GROUPS}
        frontier = list(GROUPS)
        for name in INDEX_LAYERS:
            layer = c.layers[name]
            nxt = []
            for node in frontier:
                lo, hi = out[node]
                for branch in ("low", "high"):
                    more = (branch == "high") == (layer.highIndexMeans == MORE_SUPPORT)
                    out[f"{node}/{name}_{branch}"] = _split(lo, hi, layer.narrowing, more)
                    nxt.append(f"{node}/{name}_{branch}")
            frontier = nxt
        return out
