"""Issue #28, acceptance 1: recorded sessions of known truth (tests/data/metrics, made headless on the simulated
devices by make_sessions.py; see tests/metrics_truth.py for the truth) through ``session_metrics`` — the
``main.py --metrics`` code path: every count equals the truth, range within 2 mm, peak speed within 3 %,
movement time within 0.1 s, the patient's reaction time within 0.1 s of the simulated patient's delay, and the
robot's positioning moves reported apart. Variants: the handle's recorded position with noise (0.1 mm SD) or a
tremor (8 Hz, ±0.15 mm); a large tremor (6 Hz, ±0.5 mm) keeps counts, ranges and times, but adds its own speed
(±19 mm/s) to the peak speed, which no speed measure can tell from the movement's (docs/metrics.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.session.metrics import session_metrics
from tests.metrics_truth import load_case, truth_movements, variant, write_session

PASSIVE = ["reaches6_v015", "reaches6_v030", "reaches12_v015", "mixed_v015", "mixed_v030"]
CASES = [*PASSIVE, "sway_3s", "trigger_rt04", "trigger_rt16"]


def metrics_of(name: str, kind: str, tmp_path: Path) -> tuple[dict, dict, list[dict]]:
    case = load_case(name)
    folder = write_session(case, tmp_path / f"{name}-{kind}", variant(case, kind))
    return case, session_metrics(folder), truth_movements(case)


@pytest.mark.parametrize("kind", ["clean", "noisy", "tremor"])
@pytest.mark.parametrize("name", CASES)
def test_counts_and_kinematics_equal_the_truth(name: str, kind: str, tmp_path: Path) -> None:
    case, result, truth = metrics_of(name, kind, tmp_path)
    reps = result["repetitions"]
    assert len(truth) == case["truth"]["count"]  # the labels themselves: one per commanded movement
    assert len(reps) == case["truth"]["count"], [(r["start_s"], r["end_s"]) for r in reps]
    for r, t in zip(reps, truth, strict=True):
        assert r["range_m"] == pytest.approx(t["range_m"], abs=0.002), (r["index"], r["range_m"], t)
        assert r["peak_speed_m_s"] == pytest.approx(t["peak_speed_m_s"], rel=0.03), (r["index"], t)
        assert r["movement_time_s"] == pytest.approx(t["duration_s"], abs=0.1), (r["index"], t)
        assert r["completed"]
    kinds = [p["kind"] for p in result["positioning"]]
    assert kinds.count("homing") == 1  # the runner homes first: apart, never a repetition
    if case["truth"]["kind"] == "passive":
        assert kinds.count("to_start") == 1  # the move to the first point, before the exercise's start prompt
    if case["truth"]["kind"] == "trigger":
        assert kinds.count("outside_repetitions") == 1  # the move to the start point, before repetition 1
    if case["truth"]["kind"] == "sway":
        assert kinds == ["homing"]  # the patient's first sway starts at the prompt: a repetition
    assert result["summary"]["repetitions"] == case["truth"]["count"]


@pytest.mark.parametrize("kind", ["clean", "noisy", "tremor", "tremor_large"])
@pytest.mark.parametrize("name", ["trigger_rt04", "trigger_rt16"])
def test_reaction_time_is_the_patients(name: str, kind: str, tmp_path: Path) -> None:
    case, result, _ = metrics_of(name, kind, tmp_path)
    prompts = [e["t_s"] for e in case["events"] if e["kind"] == "prompt"]
    squeezes = [c[0] for c in case["truth"]["patient_commands"] if c[1] == "squeeze"]
    delays = [s - p for p, s in zip(prompts, squeezes, strict=True)]  # as commanded: nominal + timer jitter
    assert all(abs(d - case["truth"]["reaction_s"]) < 0.15 for d in delays)
    reps = result["repetitions"]
    assert len(reps) == len(delays)
    for r, d in zip(reps, delays, strict=True):
        assert r["reaction_time_s"] == pytest.approx(d, abs=0.1), r
        # the robot's own start-up, apart: from the grip through 20 N to the handle's onset
        assert 0.0 < r["robot_latency_s"] < 0.3, r
        assert r["grip_at_trigger_n"] == pytest.approx(38.0, abs=3.0)  # the squeeze's peak, not the resting grip
        assert r["prompt_s"] == pytest.approx(prompts[r["index"] - 1], abs=1e-3)


@pytest.mark.parametrize("name", CASES)
def test_large_tremor_keeps_counts_ranges_and_times(name: str, tmp_path: Path) -> None:
    case, result, truth = metrics_of(name, "tremor_large", tmp_path)
    reps = result["repetitions"]
    assert len(reps) == case["truth"]["count"]
    for r, t in zip(reps, truth, strict=True):
        assert r["range_m"] == pytest.approx(t["range_m"], abs=0.002)
        assert r["movement_time_s"] == pytest.approx(t["duration_s"], abs=0.1)
        # ±19 mm/s of tremor on top of the movement's speed: over, but by no more than the tremor's own speed
        assert t["peak_speed_m_s"] * 0.9 < r["peak_speed_m_s"] < t["peak_speed_m_s"] + 0.02


def test_runs_key_numbers_repetitions_within_each_run(tmp_path: Path) -> None:
    _, result, _ = metrics_of("trigger_rt04", "clean", tmp_path)
    (run,) = result["runs"]
    assert [r["index"] for r in run["repetitions"]] == [1, 2, 3, 4]
    assert run["summary"]["repetitions"] == 4 and run["summary"]["completed"] == 4
    assert run["summary"]["not_started"] is False and run["summary"]["positioning_moves"] == 1
