"""One place per fact (issue #40): the facts below are defined once and read everywhere else. This test reads
``app/`` with ``ast`` and fails on a literal copy, naming the file and line:

* the stimulator's maximum current (``sciencemode.MAX_CURRENT_MA``, 126 mA): no number 126, no "126 mA" in a
  text, outside ``app/wire/sciencemode.py``;
* its channels (``sciencemode.CHANNELS``, 1..8): no ``1 <= ch <= 8``, ``range(1, 9)``, ``range(8)``,
  ``rng(1, 8)``, ``X_CHANNELS = 8``, and no "1..8" / "8 channels" in a message (messages are built from
  ``CHANNELS_TEXT``);
* the robot's limit ranges (``config.ROBOT_LIMIT_RANGES``, read from the constants table
  ``app/wire/linarm_constants.py``): a robot-limit field (position_min_m, max_velocity_m_s, ...) is never
  given a range of typed numbers; and a pulse-width field's range never types ``MAX_PULSE_WIDTH_US``;
* the device ids (``app/core/streams.py``: LINARM, PHYSIO, FES, PATIENT_MODEL, VR): no string literal "linarm",
  "fes", "physio", "patient_model", "vr" as a call's argument, a comparison's operand or a dict's key outside
  ``app/core/streams.py`` (the script API's object names in ``app/scripting/`` are the seed's public API, not ids);
  the few literals that are not device ids are listed below with the reason.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from functools import cache
from pathlib import Path

from app.core import streams
from app.core.config import ROBOT_LIMIT_RANGES
from app.wire import sciencemode

ROOT = Path(__file__).resolve().parents[1]
APP = ROOT / "app"

# (file, the line's text contains) -> why this literal is not a copy of a device id.
NOT_DEVICE_IDS: dict[tuple[str, str], str] = {
    ("app/archive/patient_form.py", '"fes": {"profile"'): "the profile file's 'fes' section (its format)",
    ("app/archive/cli.py", '"fes": "--cap"'): "the profile file's 'fes' section, named by the option that sets it",
    ("app/archive/store.py", '"fes": {"profile"'): "the profile file's 'fes' section (its format)",
    ("app/session/metrics.py", '.get("fes")'): "the recorded configuration's 'fes' section (its format)",
    ("app/research_export/bids.py", '"physio")'): "a BIDS data type (the BIDS specification's word)",
    ("app/session/clinical_words.py", '_API_WORDS = {"linarm": "robot", "fes": "stimulator"'):
        "the script API's object names (the seed's public API)",
}


@cache
def _sources() -> dict[str, tuple[str, ast.Module]]:
    out = {}
    for path in sorted(APP.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        text = path.read_text(encoding="utf-8")
        out[rel] = (text, ast.parse(text, rel))
    return out


def _line(rel: str, node: ast.AST) -> str:
    text = _sources()[rel][0].splitlines()[node.lineno - 1].strip()  # type: ignore[attr-defined]
    return f"{rel}:{node.lineno}: {text}"  # type: ignore[attr-defined]


def _number(node: ast.AST) -> float | None:
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(node.value, bool):
        return float(node.value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        inner = _number(node.operand)
        return None if inner is None else -inner
    return None


def _strings(tree: ast.Module) -> Iterator[ast.Constant]:
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node


def _call_name(node: ast.Call) -> str:
    f = node.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""


def test_the_maximum_current_is_typed_once() -> None:
    assert sciencemode.MAX_CURRENT_MA == 126  # the fact this test looks for
    found = []
    for rel, (_text, tree) in _sources().items():
        if rel == "app/wire/sciencemode.py":
            continue
        for node in ast.walk(tree):
            if _number(node) == sciencemode.MAX_CURRENT_MA and isinstance(node, ast.Constant):
                found.append(_line(rel, node))
        found += [_line(rel, s) for s in _strings(tree) if re.search(r"\b126\s*mA\b", s.value)]
    assert not found, "126 mA typed again (read sciencemode.MAX_CURRENT_MA):\n" + "\n".join(found)


_CHANNEL_WORDS = re.compile(r"\b1\s*\.\.\s*8\b|\b1 to 8\b|\b8 channels\b|\ball 8\b", re.IGNORECASE)


def test_the_channels_are_typed_once() -> None:
    first, last = sciencemode.CHANNELS[0], sciencemode.CHANNELS[-1]
    assert (first, last, len(sciencemode.CHANNELS)) == (1, 8, 8)
    found = []
    for rel, (_text, tree) in _sources().items():
        if rel == "app/wire/sciencemode.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Compare) and len(node.comparators) == 2:
                bounds = (_number(node.left), _number(node.comparators[1]))
                if bounds == (first, last):
                    found.append(_line(rel, node))
            elif isinstance(node, ast.Call) and _call_name(node) in ("range", "rng"):
                args = [_number(a) for a in node.args[:2]]
                crc_bits = rel == "app/wire/physio_codec.py"  # range(8): the 8 bits of a CRC byte
                if _call_name(node) == "range" and (args == [first, last + 1] or (args == [last] and not crc_bits)):
                    found.append(_line(rel, node))
                elif _call_name(node) == "rng" and args == [first, last]:
                    found.append(_line(rel, node))
            elif isinstance(node, ast.Assign) and _number(node.value) == last and any(
                    isinstance(t, ast.Name) and "CHANNEL" in t.id for t in node.targets):
                found.append(_line(rel, node))
        found += [_line(rel, s) for s in _strings(tree) if _CHANNEL_WORDS.search(s.value)]
    assert not found, ("the stimulator's channels typed again (read sciencemode.CHANNELS / CHANNELS_TEXT):\n"
                       + "\n".join(found))


def _fields(tree: ast.Module) -> Iterator[tuple[str, ast.Call]]:
    """(field name, the ``rng(...)`` call of its metadata) for every dataclass field typed with one."""
    for node in ast.walk(tree):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(node.value, ast.Call):
            for kw in node.value.keywords:
                if kw.arg == "metadata" and isinstance(kw.value, ast.Call) and _call_name(kw.value) == "rng":
                    yield node.target.id, kw.value


def test_the_robot_limit_ranges_and_pulse_width_cap_are_typed_once() -> None:
    found = []
    for rel, (_text, tree) in _sources().items():
        for name, call in _fields(tree):
            numbers = [_number(a) for a in call.args[:2]]
            if name in ROBOT_LIMIT_RANGES and any(n is not None for n in numbers):
                found.append(f"{_line(rel, call)}  (use config.ROBOT_LIMIT_RANGES[{name!r}])")
            if "pulse_width" in name and sciencemode.MAX_PULSE_WIDTH_US in numbers:
                found.append(f"{_line(rel, call)}  (use sciencemode.MAX_PULSE_WIDTH_US)")
    assert not found, "a robot limit's range or the pulse-width cap typed again:\n" + "\n".join(found)


def test_device_ids_are_spelled_in_one_place() -> None:
    ids = set(streams.DEVICES)
    assert ids == {"linarm", "physio", "fes", "patient_model", "vr"}
    found = []
    used: set[tuple[str, str]] = set()
    for rel, (text, tree) in _sources().items():
        if rel == "app/core/streams.py" or rel.startswith("app/scripting/"):
            continue
        lines = text.splitlines()
        candidates: list[ast.AST] = []
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                candidates += [*node.args, *(kw.value for kw in node.keywords)]
            elif isinstance(node, ast.Compare):
                candidates += [node.left, *node.comparators]
            elif isinstance(node, ast.Dict):
                candidates += [k for k in node.keys if k is not None]
            elif isinstance(node, ast.match_case) and isinstance(node.pattern, ast.MatchValue):
                candidates.append(node.pattern.value)
        for node in candidates:
            if isinstance(node, ast.Constant) and node.value in ids:
                line = lines[node.lineno - 1]
                excused = [key for key in NOT_DEVICE_IDS if key[0] == rel and key[1] in line]
                if excused:
                    used.update(excused)
                else:
                    found.append(_line(rel, node))
    assert not found, "a device id typed as a string (use streams.LINARM, FES, ...):\n" + "\n".join(found)
    assert used == set(NOT_DEVICE_IDS), f"stale entries in NOT_DEVICE_IDS: {set(NOT_DEVICE_IDS) - used}"
