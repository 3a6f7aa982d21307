"""FES profiles: trapezoid interpolation, scales, YAML load/save, errors that name the file and the line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from app.core.fes_profile import (
    ChannelProfile,
    FesProfile,
    FesProfileError,
    Trapezoid,
    load_profile,
    parse_profile,
    profile_to_yaml,
    save_profile,
)
from app.wire.sciencemode import PulseMode, PulseSetting

FAST = settings(max_examples=200, deadline=None)
RESOURCES = Path(__file__).resolve().parents[1] / "resources" / "fes_profiles"


def test_trapezoid_shape() -> None:
    t = Trapezoid(level=30.0, ramp_up=(0.1, 0.3), ramp_down=(0.6, 0.8), baseline=2.0)
    assert t.value_at(0.0) == 2.0
    assert t.value_at(0.2) == pytest.approx(16.0)
    assert t.value_at(0.3) == 30.0 and t.value_at(0.6) == 30.0
    assert t.value_at(0.7) == pytest.approx(16.0)
    assert t.value_at(0.8) == 2.0 and t.value_at(5.0) == 2.0
    step = Trapezoid(10.0, (0.5, 0.5), (0.7, 0.7))  # zero-length ramps are steps, not a division by zero
    assert (step.value_at(0.49), step.value_at(0.5), step.value_at(0.7)) == (0.0, 10.0, 0.0)


@FAST
@given(st.lists(st.floats(0, 1), min_size=4, max_size=4).map(sorted), st.floats(0, 126), st.floats(0, 1))
@example([0.0, 0.0, 0.3125, 0.9375], 5e-324, 0.875)  # found by hypothesis: rounding gave -5e-324
def test_trapezoid_stays_between_baseline_and_level(points: list[float], level: float, x: float) -> None:
    t = Trapezoid(level, (points[0], points[1]), (points[2], points[3]))
    assert 0.0 <= t.value_at(x) <= level + 1e-9


def _profile(**kw: object) -> FesProfile:
    ch = ChannelProfile(
        Trapezoid(20.0, (0.0, 0.5), (0.5, 1.0)),
        Trapezoid(200.0, (0.0, 0.25), (0.75, 1.0)),
        "anterior deltoid",
        PulseMode.DOUBLET,
    )
    args: dict[str, object] = {"name": "t", "axis": "phase", "channels": {1: ch}}
    args.update(kw)
    return FesProfile(**args)  # type: ignore[arg-type]


def test_value_at_scales_and_settings() -> None:
    p = _profile()
    assert p.value_at(0.25) == {1: (10.0, 200.0)}
    assert p.value_at(-3.0) == {1: (0.0, 0.0)} and p.value_at(7.0) == {1: (0.0, 0.0)}  # phase is clamped
    scaled = p.with_scales(current_scale=0.5, pulse_width_scale=1.5)
    assert scaled.value_at(0.5) == {1: (10.0, 300.0)}
    assert scaled.settings_at(0.5) == {1: PulseSetting(10, 300, PulseMode.DOUBLET)}
    assert p.peaks() == {1: (20.0, 200.0)} and scaled.peaks(scaled=True) == {1: (10.0, 300.0)}
    with pytest.raises(ValueError, match="finite"):
        p.value_at(math.nan)


def test_invalid_profile_objects_are_refused() -> None:
    with pytest.raises(FesProfileError, match="current_scale"):
        _profile(current_scale=3.0)
    with pytest.raises(FesProfileError, match=r"channels\.9"):
        _profile(channels={9: _profile().channels[1]})
    bad = ChannelProfile(Trapezoid(200.0, (0, 0.1), (0.2, 0.3)), Trapezoid(100.0, (0, 0.1), (0.2, 0.3)))
    with pytest.raises(FesProfileError, match=r"current_ma\.level.*0 \.\. 126 mA"):
        _profile(channels={1: bad})


def test_example_profiles_load() -> None:
    reach = load_profile(RESOURCES / "frontal_reaching.yaml")
    assert reach.axis == "phase" and set(reach.channels) == {1, 2, 5, 6}
    forward, back = reach.value_at(0.3), reach.value_at(0.75)
    assert forward[1][0] > 0 and forward[2][0] > 0 and forward[5][0] == 0 and forward[6][0] == 0
    assert back[5][0] > 0 and back[6][0] > 0 and back[1][0] == 0 and back[2][0] == 0
    timed = load_profile(RESOURCES / "wrist_extension_time.yaml")
    assert timed.axis == "time" and timed.end == 7.5 and timed.value_at(4.0)[3] == (20.0, 200.0)


def test_save_and_load_round_trip(tmp_path: Path) -> None:
    p = _profile(description="d", frequency_hz=35.0).with_scales(0.8, 0.9)
    path = tmp_path / "p.yaml"
    save_profile(p, path)
    assert load_profile(path) == p
    assert "version: 1" in path.read_text(encoding="utf-8")


GOOD = """version: 1
name: test
axis: phase
channels:
  1:
    current_ma: {level: 20, ramp_up: [0.0, 0.2], ramp_down: [0.5, 0.6]}
    pulse_width_us: {level: 200, ramp_up: [0.0, 0.2], ramp_down: [0.5, 0.6]}
"""


def _broken(old: str, new: str) -> str:
    assert old in GOOD
    return GOOD.replace(old, new)


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        (_broken("version: 1", "version: 2"), 1, "unsupported version"),
        (_broken("version: 1\n", ""), 1, "version"),
        (_broken("axis: phase", "axis: space"), 3, "axis"),
        (_broken("level: 20,", "level: 200,"), 6, "current_ma.level"),
        (_broken("level: 200,", "level: 600,"), 7, "pulse_width_us.level"),
        (_broken("ramp_down: [0.5, 0.6]}\n    pulse", "ramp_down: [0.5, 1.6]}\n    pulse"), 6, "0 .. 1"),
        (
            _broken(
                "ramp_up: [0.0, 0.2], ramp_down: [0.5, 0.6]}\n    pulse",
                "ramp_up: [0.0, 0.7], ramp_down: [0.5, 0.6]}\n    pulse",
            ),
            6,
            "must not decrease",
        ),
        (
            _broken(
                "ramp_up: [0.0, 0.2], ramp_down: [0.5, 0.6]}\n    pulse",
                "ramp_up: [0.0], ramp_down: [0.5, 0.6]}\n    pulse",
            ),
            6,
            "two points",
        ),
        (_broken("  1:\n", "  1:\n    colour: red\n"), 6, "unknown key"),
        (_broken("  1:", "  12:"), 5, "channels.12"),
        (_broken("level: 20,", "level: twenty,"), 6, "number"),
        (GOOD + "  bad: [\n", 9, "not valid YAML"),
        (
            _broken("    pulse_width_us: {level: 200, ramp_up: [0.0, 0.2], ramp_down: [0.5, 0.6]}\n", ""),
            6,
            "missing required key",
        ),
    ],
)
def test_malformed_files_name_file_and_line(tmp_path: Path, text: str, line: int, words: str) -> None:
    path = tmp_path / "bad_profile.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(FesProfileError) as exc:
        load_profile(path)
    message = str(exc.value)
    assert message.startswith(f"{path}:{line}:"), message
    assert words in message


def test_good_text_parses_and_unreadable_file_is_reported(tmp_path: Path) -> None:
    assert parse_profile(GOOD).channels[1].current_ma.level == 20.0
    with pytest.raises(FesProfileError, match="cannot read"):
        load_profile(tmp_path / "missing.yaml")


def test_time_axis_allows_seconds_beyond_one() -> None:
    text = GOOD.replace("axis: phase", "axis: time").replace("[0.5, 0.6]", "[3.0, 4.5]")
    p = parse_profile(text)
    assert p.end == 4.5 and p.value_at(3.75)[1] == (10.0, 100.0)


def test_yaml_text_round_trip_keeps_mode() -> None:
    p = _profile()
    assert "mode: doublet" in profile_to_yaml(p)
    assert parse_profile(profile_to_yaml(p)).channels[1].mode == PulseMode.DOUBLET
