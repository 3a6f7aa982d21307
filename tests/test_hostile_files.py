"""Issue #17 point 5: every hostile or broken YAML file is refused with file:line (exit 2 from main),
never a traceback; values the schema cannot see are checked at load; one unreadable patient file is
listed as unreadable and the others stay usable."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from app.core.config import ConfigError, load_config
from app.therapy.patients import PatientProfile, list_patients, save_patient

ROOT = Path(__file__).resolve().parents[1]

HOSTILE: list[tuple[str, bytes, str]] = [
    ("non-utf8", b"ui:\n  palette: \xff\xfe\n", "not UTF-8"),
    ("5000-digit number", b"safety:\n  silence_periods: " + b"9" * 5000 + b"\n", "digits"),
    ("5000-deep nesting", b"ui: " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested deeper"),
    ("python/name tag", b"ui:\n  palette: !!python/name:os.system\n", "tag"),
    ("python tag on a mapping", b"ui: !!python/object:argparse.Namespace\n  palette: dark\n", "tag"),
    ("python tag in a list", b"safety:\n  fes:\n    channels: !!python/tuple [1]\n", "tag"),
    ("alias bomb", b"a: &a [1, 1]\nb: [*a, *a]\n", "aliases"),
    ("FES channel 99", b"safety:\n  fes:\n    channels:\n      99: {max_current_ma: 10}\n", "channel 99"),
    ("bind_host 256.1.1.1", b"devices:\n  patient_model:\n    bind_host: 256.1.1.1\n", "not an IP address"),
]


@pytest.mark.parametrize(("name", "data", "words"), HOSTILE, ids=[h[0] for h in HOSTILE])
def test_hostile_config_is_refused_with_file_and_line(tmp_path, name: str, data: bytes, words: str) -> None:
    path = tmp_path / "config.yaml"
    path.write_bytes(data)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text = str(info.value)
    assert words in text, text
    assert text.startswith(f"{path}:") and info.value.line is not None, text


@pytest.mark.parametrize(("name", "data", "words"), [HOSTILE[0], HOSTILE[2], HOSTILE[4], HOSTILE[7]],
                         ids=[HOSTILE[i][0] for i in (0, 2, 4, 7)])
def test_main_exits_2_with_one_message_and_no_traceback(tmp_path, name: str, data: bytes, words: str) -> None:
    path = tmp_path / "config.yaml"
    path.write_bytes(data)
    script = tmp_path / "s.py"
    script.write_text("print('ran')\n", encoding="utf-8")
    proc = subprocess.run([sys.executable, str(ROOT / "main.py"), "--config", str(path), "--headless", "--script",
                           str(script)], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env={**__import__("os").environ, "QT_QPA_PLATFORM": "offscreen"})
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and "ran" not in proc.stdout
    assert f"{path}:" in proc.stderr and words in proc.stderr


def test_one_unreadable_patient_file_leaves_the_others_usable(tmp_path) -> None:
    save_patient(PatientProfile(patient_id="GOOD01"), tmp_path)
    (tmp_path / "BAD01.yaml").write_bytes(b"patient_id: BAD01\nnotes: \xff\n")
    (tmp_path / "BAD02.yaml").write_bytes(b"patient_id: !!python/name:os.system BAD02\n")
    entries = {e.patient_id: e for e in list_patients(tmp_path)}
    assert entries["GOOD01"].profile is not None
    assert entries["BAD01"].profile is None and "not UTF-8" in entries["BAD01"].error
    assert entries["BAD02"].profile is None and "tag" in entries["BAD02"].error


@pytest.mark.parametrize(("data", "words"), [(b"version: !!python/name:os.system 1\n", "tag"),
                                             (b"version: 1\n\xff\n", "not UTF-8")])
def test_hostile_decision_tree_file_is_refused_with_its_line(tmp_path, data: bytes, words: str) -> None:
    from app.devices.sim.patient_model.decision_tree import PatientModelConfigError, load_tree_config

    path = tmp_path / "tree.yaml"
    path.write_bytes(data)
    with pytest.raises(PatientModelConfigError) as info:
        load_tree_config(path)
    assert words in str(info.value) and info.value.line >= 1


# ------------------------------------------------------------------------------------------------------------
# Issue #25, "exercise YAML": exercise files and FES profiles through the config's strict loader.
GOOD_EXERCISE = (b"title: Good\nscript: good.py\nparameters:\n"
                 b"  - {name: rest_s, label: Rest, type: float, unit: s, min: 0, max: 30, default: 0.5}\n")

BILLION_LAUGHS = b"".join([
    b"title: laughs\n",
    b"a: &a [\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\"]\n",
    *[f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},"
      f"*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)}]\n".encode() for i in range(8)],
    b"description: *i\n",
])

HOSTILE_EXERCISES: list[tuple[str, bytes, str, int | None]] = [
    # (name, file, words in the message, the line named)
    ("billion laughs", BILLION_LAUGHS, "anchors and aliases", 2),
    ("non-utf8", b"title: ok\ndescription: caf\xe9\n", "not UTF-8", 2),
    ("script ../..", b"title: x\nscript: ../../x.py\n", "not a path", 2),
    ("script absolute", b"title: x\nscript: /bin/sh\n", "not a path", 2),
    ("script not python", b"title: x\nscript: x.yaml\n", "not a Python script", 2),
    ("negative rest", b"title: x\nparameters:\n  - {name: rest_s, type: float, unit: s, min: -5, max: 30, "
                      b"default: -1}\n", "a duration cannot be negative", 3),
    ("rest below its min", b"title: x\nparameters:\n  - {name: rest_s, type: float, unit: s, min: 0, max: 30, "
                           b"default: -1}\n", "the default is refused", 3),
    ("unbounded number", b"title: x\nparameters:\n  - {name: speed, type: float, default: 1}\n", "both min and max", 3),
    ("huge max", b"title: x\nparameters:\n  - {name: speed, type: float, min: 0, max: 1.0e+300, default: 1}\n",
     "outside the allowed range", 3),
    ("infinite max", b"title: x\nparameters:\n  - {name: speed, type: float, min: 0, max: .inf, default: 1}\n",
     "finite", 3),
    ("min above max", b"title: x\nparameters:\n  - {name: n, type: int, min: 5, max: 1, default: 3}\n", "above max", 3),
    ("order out of range", b"title: x\norder: -7\n", "outside the allowed range", 2),
    ("5000-digit number", b"title: x\norder: " + b"9" * 5000 + b"\n", "digits", 2),
    ("deep nesting", b"title: x\ndescription: " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested deeper", 2),
    ("python tag", b"title: !!python/name:os.system x\n", "tag", 1),
    ("default a list", b"title: x\nparameters:\n  - {name: a, type: bool, default: [1]}\n", "single value", 3),
]


@pytest.mark.parametrize(("name", "data", "words", "line"), HOSTILE_EXERCISES, ids=[h[0] for h in HOSTILE_EXERCISES])
def test_hostile_exercise_is_refused_quickly_with_file_and_line(tmp_path, name: str, data: bytes, words: str,
                                                                  line: int | None) -> None:
    import time

    from app.therapy.exercises import ExerciseError, load_exercise

    (tmp_path / "x.py").write_text("pass\n", encoding="utf-8")
    path = tmp_path / "x.yaml"
    path.write_bytes(data)
    t0 = time.monotonic()
    with pytest.raises(ExerciseError) as info:
        load_exercise(path)
    elapsed = time.monotonic() - t0
    text = str(info.value)
    assert words in text, text
    assert text.startswith(f"{path}:{line}:"), text
    # The billion laughs took > 20 s: now refused at its first anchor (~15 ms). Deep flow nesting costs
    # PyYAML's scanner ~0.15 s on an idle machine (its look-ahead over one long line), ~1 s under load.
    assert elapsed < (1.0 if name == "billion laughs" else 5.0), f"{elapsed:.2f} s"


def test_a_script_link_out_of_the_library_is_refused(tmp_path) -> None:
    from app.therapy.exercises import ExerciseError, load_exercise

    outside = tmp_path / "outside.py"
    outside.write_text("import os\n", encoding="utf-8")
    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "x.py").symlink_to(outside)
    (lib / "x.yaml").write_bytes(b"title: x\nscript: x.py\n")
    with pytest.raises(ExerciseError, match=r"x.yaml:2: script: .*leads out of the exercise's folder"):
        load_exercise(lib / "x.yaml")


def test_a_fifo_in_the_library_is_listed_not_waited_for(tmp_path) -> None:
    import os

    from app.therapy.exercises import load_library

    (tmp_path / "good.py").write_text("pass\n", encoding="utf-8")
    (tmp_path / "good.yaml").write_bytes(GOOD_EXERCISE)
    os.mkfifo(tmp_path / "pipe.yaml")
    library, problems = load_library(tmp_path)
    assert [e.ident for e in library] == ["good"]
    assert problems == [f"{tmp_path / 'pipe.yaml'}: (top level): cannot read the file: a named pipe, "
                        "not a regular file (refused)"]


@pytest.fixture
def bad_library(tmp_path, monkeypatch):
    """An exercise library with one good exercise and three bad files, as the window's default library."""
    from app.therapy import exercises

    (tmp_path / "good.py").write_text("pass\n", encoding="utf-8")
    (tmp_path / "good.yaml").write_bytes(GOOD_EXERCISE)
    (tmp_path / "latin1.yaml").write_bytes(b"title: Caf\xe9\n")
    (tmp_path / "escape.yaml").write_bytes(b"title: x\nscript: ../../etc/x.py\n")
    (tmp_path / "laughs.yaml").write_bytes(BILLION_LAUGHS)
    monkeypatch.setattr(exercises, "EXERCISES_DIR", tmp_path)
    monkeypatch.setattr(exercises.load_library, "__defaults__", (tmp_path,))  # the old signature bound it early
    return tmp_path


def test_one_bad_exercise_file_leaves_the_others_usable(bad_library) -> None:
    from app.therapy.exercises import load_library

    library, problems = load_library()
    assert [e.ident for e in library] == ["good"]
    assert len(problems) == 3
    text = "\n".join(problems)
    assert f"{bad_library / 'latin1.yaml'}:1:" in text and "not UTF-8" in text
    assert f"{bad_library / 'escape.yaml'}:2:" in text and f"{bad_library / 'laughs.yaml'}:2:" in text


def test_the_exercises_tab_starts_with_a_bad_file_and_lists_it(qtbot, bad_library) -> None:
    from PySide6.QtWidgets import QLabel

    from app.ui.exercises_panel import ExercisesPanel
    from tests.test_exercises_panel import FakeRunner, StubManager

    panel = ExercisesPanel(StubManager(), runner=FakeRunner())  # raised UnicodeDecodeError: the window died (134)
    qtbot.addWidget(panel)
    assert [e.ident for e in panel.library] == ["good"]
    notes = [w.text() for w in panel.findChildren(QLabel) if w.text().startswith("Not loaded:")]
    assert len(notes) == 1 and "latin1.yaml:1:" in notes[0] and "not UTF-8" in notes[0]


HOSTILE_PROFILES: list[tuple[str, bytes, str, int]] = [
    ("non-utf8", b"version: 1\nname: caf\xe9\naxis: time\nchannels: {}\n", "not UTF-8", 2),
    ("deep nesting", b"version: 1\nname: x\naxis: time\nchannels: " + b"[" * 10000 + b"]" * 10000 + b"\n",
     "nested deeper", 4),
    ("alias bomb", b"version: 1\nname: &n x\naxis: time\nchannels: {}\ndescription: *n\n", "aliases", 2),
]


@pytest.mark.parametrize(("name", "data", "words", "line"), HOSTILE_PROFILES, ids=[h[0] for h in HOSTILE_PROFILES])
def test_hostile_fes_profile_is_refused_with_file_and_line(tmp_path, name: str, data: bytes, words: str,
                                                           line: int) -> None:
    from app.core.fes_profile import FesProfileError, load_profile, parse_profile

    path = tmp_path / "p.yaml"
    path.write_bytes(data)
    with pytest.raises(FesProfileError) as info:
        load_profile(path)
    text = str(info.value)
    assert words in text and text.startswith(f"{path}:{line}:"), text
    with pytest.raises(FesProfileError) as info:  # the parse step alone, from the bytes a safe read returns
        parse_profile(data, "named.yaml")
    assert str(info.value).startswith(f"named.yaml:{line}:") and words in str(info.value)
