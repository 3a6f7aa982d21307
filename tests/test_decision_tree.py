"""The patient model's five-layer decision tree and its therapist-editable YAML."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.devices.sim.patient_model.decision_tree import (
    DEFAULT_CONFIG_PATH,
    GROUPS,
    DecisionTree,
    PatientModelConfigError,
    decode_path_code,
    load_tree_config,
    node_paths,
    parse_tree_config,
)

SETTINGS = settings(max_examples=200, deadline=None)
YAML = DEFAULT_CONFIG_PATH.read_text(encoding="utf-8")
unit = st.floats(0.0, 1.0)


def line_of(text: str, fragment: str) -> int:
    [n] = [i + 1 for i, line in enumerate(text.splitlines()) if fragment in line]
    return n


@pytest.fixture
def tree() -> DecisionTree:
    return DecisionTree(load_tree_config())


def test_default_file_loads() -> None:
    cfg = load_tree_config()
    assert cfg.scoreThresholds == (30.0, 50.0)
    assert cfg.groupRanges["assist"] == (0.2, 1.0)
    assert cfg.layers["pti"].narrowing < cfg.layers["mpi"].narrowing < cfg.layers["tpi"].narrowing
    assert [len(node_paths(n)) for n in ("tpi", "mpi", "pti")] == [3, 6, 12]  # as in D2.1


@pytest.mark.parametrize("score,group", [(0, "assist"), (29.9, "assist"), (30, "in_between"),
                                         (49, "in_between"), (50, "resist"), (66, "resist")])
def test_clinical_score_picks_the_group(tree: DecisionTree, score: float, group: str) -> None:
    d = tree.decide(score, 0.5, 0.5, 0.5)
    lo, hi = tree.config.groupRanges[group]
    assert d.group == group and d.path[0].branch == group
    assert lo <= d.alpha <= hi


def test_changing_the_clinical_score_moves_alpha_between_groups(tree: DecisionTree) -> None:
    alphas = [tree.decide(score, 0.3, 0.3, 0.3).alpha for score in (10, 40, 60)]
    assert alphas[0] > alphas[1] > alphas[2]
    assert alphas[0] >= 0.2 and alphas[2] <= 0.0


def test_scale_where_higher_means_worse() -> None:
    text = YAML.replace("higher_is_better: true", "higher_is_better: false")
    tree = DecisionTree.from_yaml(text)
    assert tree.decide(60, 0.5, 0.5, 0.5).group == "assist"
    assert tree.decide(40, 0.5, 0.5, 0.5).group == "in_between"
    assert tree.decide(10, 0.5, 0.5, 0.5).group == "resist"


@SETTINGS
@given(score=st.floats(0, 66), tpi=unit, mpi=unit, pti=unit, failures=st.integers(0, 8))
def test_each_layer_narrows_inside_its_parent(score: float, tpi: float, mpi: float, pti: float,
                                              failures: int) -> None:
    tree = DecisionTree(load_tree_config())
    for _ in range(failures):
        tree.record_subtask(False)
    d = tree.decide(score, tpi, mpi, pti)
    assert [s.layer for s in d.path] == [1, 2, 3, 4, 5]
    assert [s.quantity for s in d.path] == ["clinical_score", "tpi", "mpi", "pti", "subtask"]
    ranges = [(-1.0, 1.0)] + [s.alphaRange for s in d.path]
    for (plo, phi), (lo, hi) in itertools.pairwise(ranges):
        assert plo - 1e-12 <= lo <= hi <= phi + 1e-12
    assert d.alphaRange[0] <= d.alpha <= d.alphaRange[1]
    assert tree.branch_ranges()[d.leaf] == pytest.approx(d.alphaRange)
    assert decode_path_code(d.path_code) == (d.group, d.path[1].branch == "high", d.path[2].branch == "high",
                                             d.path[3].branch == "high")


def test_good_performance_means_less_support_and_pti_weighs_least(tree: DecisionTree) -> None:
    base = tree.decide(40, 0.2, 0.2, 0.2)
    better_tpi = tree.decide(40, 0.9, 0.2, 0.2)
    better_mpi = tree.decide(40, 0.2, 0.9, 0.2)
    strained = tree.decide(40, 0.2, 0.2, 0.9)
    assert better_tpi.alpha < base.alpha and better_mpi.alpha < base.alpha
    assert strained.alphaRange[1] >= base.alphaRange[1] and strained.alphaRange[0] > base.alphaRange[0]
    shift = {name: abs(sum(d.alphaRange) - sum(base.alphaRange))
             for name, d in (("tpi", better_tpi), ("mpi", better_mpi), ("pti", strained))}
    assert shift["pti"] < shift["mpi"] < shift["tpi"]


def test_failed_subtasks_raise_support_gradually_within_the_range(tree: DecisionTree) -> None:
    lo, hi = tree.decide(20, 0.3, 0.3, 0.3).alphaRange
    alphas = [tree.decide(20, 0.3, 0.3, 0.3).alpha]
    assert alphas[0] == pytest.approx(lo)  # starts at the minimal support
    for _ in range(8):
        tree.record_subtask(False)
        alphas.append(tree.decide(20, 0.3, 0.3, 0.3).alpha)
    steps = [b - a for a, b in itertools.pairwise(alphas)]
    assert all(s >= -1e-12 for s in steps)
    assert steps[0] == pytest.approx(0.2 * (hi - lo))  # one step, not a jump to the maximum
    assert alphas[-1] == pytest.approx(hi)  # capped at the maximal support
    tree.record_subtask(True)
    after_success = tree.decide(20, 0.3, 0.3, 0.3).alpha
    assert after_success == pytest.approx(hi - 0.1 * (hi - lo))
    tree.reset()
    assert tree.decide(20, 0.3, 0.3, 0.3).alpha == pytest.approx(lo)


def test_node_threshold_override(tree: DecisionTree) -> None:
    # the default file sets the TPI threshold of the assist node to 0.4 (others 0.5)
    assert tree.decide(10, 0.45, 0.5, 0.5).path[1].branch == "high"
    assert tree.decide(40, 0.45, 0.5, 0.5).path[1].branch == "low"


def test_bad_inputs_are_refused(tree: DecisionTree) -> None:
    with pytest.raises(ValueError, match="outside"):
        tree.decide(80, 0.5, 0.5, 0.5)
    with pytest.raises(ValueError, match="tpi"):
        tree.decide(20, math.nan, 0.5, 0.5)
    assert tree.decide(20, 1.7, -3.0, 0.5).path[1].value == 1.0  # clipped to 0..1


# -- the YAML file: errors name the line ---------------------------------------------------------

BROKEN = [
    ("narrowing: 0.35", "narrowing: lots", "layers.mpi.narrowing must be a number"),
    ("  step_up: 0.2", "  step_upp: 0.2", "unknown key 'step_upp'"),
    ("    alpha: [-1.0, 0.0]", "    alpha: [0.5, 0.0]", "groups.resist.alpha must satisfy"),
    ("    alpha: [0.2, 1.0]", "    alpha: [0.2, 1.5]", "groups.assist.alpha must satisfy"),
    ("    alpha: [-0.4, 0.6]", "    alpha: -0.4", "groups.in_between.alpha must be a pair"),
    ("    threshold: 0.6", "    threshold: 1.6", "layers.pti.threshold must be a number in 0..1"),
    ("    narrowing: 0.15", "    narrowing: 0.45", "pti.narrowing must not exceed"),
    ("      assist: 0.4", "      assist/tpi_low: 0.4", "unknown key 'assist/tpi_low'"),
    ("    high_index_means: more_support", "    high_index_means: more", "high_index_means must be"),
    ("  thresholds: [30, 50]", "  thresholds: [30, 80]", "clinical_score.thresholds must satisfy"),
    ("  higher_is_better: true", "  higher_is_better: yes please", "must be true or false"),
    ("version: 1", "version: 2", "version must be 1"),
    ("  max: 66", "  max: 66\n  max: 70", "'max' appears twice"),
    ("    alpha: [0.2, 1.0]", "    alpha: [0.2, 1.0", "not valid YAML"),
]


@pytest.mark.parametrize("old,new,message", BROKEN)
def test_yaml_errors_name_the_line(old: str, new: str, message: str) -> None:
    assert YAML.count(old) == 1
    text = YAML.replace(old, new)
    with pytest.raises(PatientModelConfigError) as info:
        parse_tree_config(text, "therapist.yaml")
    err = info.value
    assert message in str(err)
    assert str(err).startswith(f"therapist.yaml line {err.line}: ")
    first_new_line = line_of(text, new.splitlines()[-1]) if "appears" in message else line_of(text, new)
    # YAML syntax errors are reported where the parser noticed them: at most a line later
    assert first_new_line <= err.line <= first_new_line + (1 if "YAML" in message else 0)


def test_missing_section_names_its_parent_line() -> None:
    start = YAML.index("subtask:\n")
    text = YAML[:start]
    with pytest.raises(PatientModelConfigError, match=r"the file\.subtask is missing"):
        parse_tree_config(text)
    with pytest.raises(PatientModelConfigError, match="must be a mapping"):
        parse_tree_config("- just\n- a list\n")


def test_unreadable_file_is_reported(tmp_path: Path) -> None:
    with pytest.raises(PatientModelConfigError, match="cannot read"):
        load_tree_config(tmp_path / "absent.yaml")


def test_branch_ranges_cover_the_whole_tree(tree: DecisionTree) -> None:
    ranges = tree.branch_ranges()
    assert len(ranges) == 3 + 6 + 12 + 24
    for path, (lo, hi) in ranges.items():
        assert -1.0 <= lo <= hi <= 1.0
        if "/" in path:
            plo, phi = ranges[path.rsplit("/", 1)[0]]
            assert plo <= lo <= hi <= phi
    assert set(GROUPS) <= set(ranges)
