"""One safe reader (issue #40): every file a user or a script names — configuration, patient profile, exercise,
FES profile, the patient model's tree — is read by ``app.core.safe_files`` and refused in plain words: too big, not
UTF-8 (with the line), a folder, missing. The YAML loaders show the same refusal as their ConfigError, naming
the file (and line)."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.core import safe_files, yamlschema
from app.core.config import AppConfig, ConfigError
from app.core.safe_files import UserFileError, read_user_text
from app.therapy.exercises import ExerciseError, load_exercise
from app.therapy.patients import PatientError, load_patient

ROOT = Path(__file__).resolve().parents[1]


def _refusal(path: Path, max_bytes: int = safe_files.DEFAULT_MAX_BYTES) -> str:
    with pytest.raises(UserFileError) as exc:
        read_user_text(path, max_bytes, 1.0)
    return str(exc.value)


def test_the_reader_refuses_in_plain_words(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a: 1\n" * 100)
    assert _refusal(big, 64) == f"{big}: the file is 500 bytes, more than the 64 allowed (refused)"

    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes(b"title: x\nname: Caf\xe9\n")
    assert _refusal(latin1) == f"{latin1}: line 2: not UTF-8 text (byte 0xe9 at offset 18)"

    assert _refusal(tmp_path) == f"{tmp_path}: a folder, not a regular file (refused)"
    assert _refusal(tmp_path / "absent.yaml") == f"{tmp_path / 'absent.yaml'}: no such file"

    good = tmp_path / "good.yaml"
    good.write_text("name: Café\n", encoding="utf-8")
    assert read_user_text(good) == "name: Café\n"


def test_the_yaml_loaders_show_the_same_refusal_with_file_and_line(tmp_path: Path) -> None:
    latin1 = tmp_path / "P001.yaml"
    latin1.write_bytes(b"patient_id: P001\nnotes: caf\xe9\n")
    with pytest.raises(PatientError) as patient:
        load_patient("P001", folder=tmp_path)
    assert patient.value.line == 2 and str(patient.value).startswith(f"{latin1}:2: (top level): cannot read the file: "
                                                                     "not UTF-8 text")

    with pytest.raises(ConfigError, match=r"big\.yaml: \(top level\): cannot read the file: the file is \d+ bytes, "
                                          r"more than the 1048576 allowed \(refused\)"):
        big = tmp_path / "big.yaml"
        big.write_bytes(b"#" * (safe_files.DEFAULT_MAX_BYTES + 1))
        yamlschema.load_file(AppConfig, big)

    with pytest.raises(ExerciseError, match=r"absent\.yaml: \(top level\): cannot read the file: no such file"):
        load_exercise(tmp_path / "absent.yaml")
    with pytest.raises(ConfigError, match="cannot read the file: a folder, not a regular file"):
        yamlschema.load_file(AppConfig, tmp_path)


def test_there_is_one_reader() -> None:
    """No module but app/core/safe_files.py opens a user's file itself (the non-blocking open a FIFO needs is its
    mark), and the YAML loader's old reader is gone."""
    assert not hasattr(yamlschema, "read_text")
    assert yamlschema.MAX_FILE_BYTES == safe_files.DEFAULT_MAX_BYTES
    openers = [str(path.relative_to(ROOT)) for path in sorted((ROOT / "app").rglob("*.py"))
               if path.name != "safe_files.py" and "O_NONBLOCK" in path.read_text(encoding="utf-8")]
    assert not openers, f"a second reader of user files: {openers}"
