"""Issue #17 point 5: every hostile or broken YAML file is refused with file:line (exit 2 from main),
never a traceback; values the schema cannot see are checked at load; one unreadable patient file is
listed as unreadable and the others stay usable."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from app.config import ConfigError, load_config
from app.patients import PatientProfile, list_patients, save_patient

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
    from app.patient_model.decision_tree import PatientModelConfigError, load_tree_config

    path = tmp_path / "tree.yaml"
    path.write_bytes(data)
    with pytest.raises(PatientModelConfigError) as info:
        load_tree_config(path)
    assert words in str(info.value) and info.value.line >= 1
