"""Every user file is read through libyaml when PyYAML has it (issue #37: saving a therapy plan held the window
0.3-0.7 s while stimulating, most of it PyYAML's pure-Python parser and one parse per scalar), and libyaml reads
them exactly as PyYAML's own parser did: the same values, the same refusals with the same lines."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from app.core import config, fes_profile, yamlschema
from app.therapy import exercises

ROOT = Path(__file__).resolve().parent.parent
PARSERS = {"PyYAML": yaml.SafeLoader, "libyaml": getattr(yaml, "CSafeLoader", None)}


def test_the_application_reads_yaml_with_libyaml_when_pyyaml_has_it() -> None:
    assert yaml.__with_libyaml__, "PyYAML without libyaml: every user file is read ten times slower"
    assert yamlschema.YAML_LOADER is yaml.CSafeLoader


def _read_everything(monkeypatch: Any, parser: str) -> list[Any]:
    loader = PARSERS[parser]
    if loader is None:
        pytest.skip("this PyYAML has no libyaml")
    monkeypatch.setattr(yamlschema, "YAML_LOADER", loader)
    out: list[Any] = [config.load_config(ROOT / "resources" / "config.default.yaml")]
    out += [fes_profile.load_profile(p) for p in sorted((ROOT / "resources" / "fes_profiles").glob("*.yaml"))]
    library, problems = exercises.load_library(ROOT / "resources" / "exercises")
    assert library and not problems, problems
    out += library
    return out


def test_both_parsers_read_every_shipped_file_to_the_same_values(monkeypatch: Any) -> None:
    pure = _read_everything(monkeypatch, "PyYAML")
    fast = _read_everything(monkeypatch, "libyaml")
    assert fast == pure


SCALARS = """\
an_int: 12
a_negative: -3
a_float: 0.25
an_exponent: 1.0e-3
yes_word: yes
a_bool: true
nothing: ~
a_null: null
a_date_like: 2026-11-27
quoted_number: "12"
a_string: anterior deltoid
an_infinity: .inf
"""


@pytest.mark.parametrize("parser", ["PyYAML", "libyaml"])
def test_scalars_are_resolved_as_yaml_safe_load_resolves_them(monkeypatch: Any, parser: str) -> None:
    loader = PARSERS[parser]
    if loader is None:
        pytest.skip("this PyYAML has no libyaml")
    monkeypatch.setattr(yamlschema, "YAML_LOADER", loader)
    node = yamlschema.compose(SCALARS)
    assert isinstance(node, yaml.MappingNode)
    built = {k.value: yamlschema._scalar_value(v) for k, v in node.value}
    expected = yaml.safe_load(SCALARS)
    expected["a_date_like"] = "2026-11-27"  # a timestamp tag is no plain value of ours: the text stays
    assert built == expected
    assert type(built["an_int"]) is int and type(built["a_float"]) is float and built["nothing"] is None


HOSTILE = [
    ("deep nesting", "a: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper", 1),
    ("a long number", "a: " + "9" * 5000 + "\n", "a number of 5000 digits", 1),
    ("an alias", "a: &x 1\nb: *x\n", "anchors and aliases", 1),
    ("a python tag", "a: 1\nb: !!python/name:os.system x\n", "tag", 2),
    ("broken", "a: 1\nb: [1, 2\n", "not valid YAML", 3),
]


@pytest.mark.parametrize("parser", ["PyYAML", "libyaml"])
@pytest.mark.parametrize(("name", "text", "words", "line"), HOSTILE, ids=[h[0] for h in HOSTILE])
def test_both_parsers_refuse_the_same_files_naming_the_line(monkeypatch: Any, parser: str, name: str,
                                                             text: str, words: str, line: int) -> None:
    loader = PARSERS[parser]
    if loader is None:
        pytest.skip("this PyYAML has no libyaml")
    monkeypatch.setattr(yamlschema, "YAML_LOADER", loader)
    with pytest.raises(yamlschema.ConfigError) as err:
        yamlschema.check_yaml(text, "x.yaml")
        yamlschema.compose(text)
    assert words in str(err.value) and err.value.line == line, (name, str(err.value))
