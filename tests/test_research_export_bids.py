"""Research export (issue #41), acceptance 2: a BIDS dataset of three sessions of two patients passes the offline
BIDS validator (bids-validator-deno, the schema-driven validator published on PyPI) with no error; the check fails
when the validator reports one (shown on a broken copy). Plus what the dataset says of the patients."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from app.research_export.bids import BidsOptions, export_bids
from app.research_export.source import FolderSource, open_session
from tests.research_export_data import record_session

VALIDATOR = shutil.which("bids-validator-deno") or str(Path(sys.executable).with_name("bids-validator-deno"))


def validate(root: Path) -> list[dict]:
    """The validator's errors for ``root`` (all rows of every TSV checked); raises if it did not run."""
    if not Path(VALIDATOR).exists():
        pytest.fail("bids-validator-deno is not installed (pyproject.toml's test extras)")
    proc = subprocess.run([VALIDATOR, str(root), "--format", "json", "--max-rows", "-1"], capture_output=True,
                          text=True, timeout=180, check=False)
    try:
        report = json.loads(proc.stdout)
    except json.JSONDecodeError:
        pytest.fail(f"the validator gave no report (exit {proc.returncode}): {proc.stderr[-2000:]}")
    issues = report["issues"]["issues"]
    return [i for i in issues if i.get("severity") == "error"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> tuple[Path, list]:
    root = tmp_path_factory.mktemp("bids")
    mp = pytest.MonkeyPatch()
    profile = {"patient_id": "PZ-017", "full_name": "Maria Rossi", "birth_date": "1950-06-02",
               "affected_side": "left", "scores": {"fugl_meyer_ue": 31, "modified_ashworth": 1.5}}
    try:
        recs = [record_session(root / "a", "PZ-017", seconds=4.0, seed=1, estop_at=3.0, monkeypatch=mp),
                record_session(root / "b", "PZ-017", seconds=4.0, seed=2, estop_at=3.0, monkeypatch=mp),
                record_session(root / "c", "PZ-021", seconds=4.0, seed=3, estop_at=3.0, monkeypatch=mp)]
    finally:
        mp.undo()
    manifest_path = recs[0].folder / "manifest.json"  # the first session as the recorder writes it with a profile
    manifest = json.loads(manifest_path.read_text())
    manifest["patient"] = profile
    manifest_path.write_text(json.dumps(manifest))
    sessions = [open_session(FolderSource(r.folder)) for r in recs]
    out = root / "dataset"
    export_bids(sessions, out, BidsOptions(shift_days=365 * 100 + 25))
    return out, sessions


def test_three_sessions_of_two_patients_pass_the_bids_validator(dataset) -> None:
    root, _ = dataset
    errors = validate(root)
    assert errors == [], json.dumps(errors, indent=1)[:3000]
    assert sorted(p.name for p in root.glob("sub-*")) == ["sub-PZ017", "sub-PZ021"]
    assert sorted(p.name for p in (root / "sub-PZ017").glob("ses-*")) == ["ses-1", "ses-2"]


def test_the_check_fails_when_the_validator_reports_an_error(dataset, tmp_path) -> None:
    root, _ = dataset
    broken = tmp_path / "broken"
    shutil.copytree(root, broken)
    (broken / "dataset_description.json").write_text(json.dumps({"Name": "no BIDSVersion"}))
    events = next(broken.rglob("*_events.tsv"))
    events.write_text(events.read_text().replace("onset\t", "start\t", 1))
    assert validate(broken), "the validator must report the broken copy"


def test_participants_are_pseudonyms_ages_and_dates_shifted(dataset) -> None:
    root, _sessions = dataset
    participants = (root / "participants.tsv").read_text().splitlines()
    assert participants[0].split("\t")[:3] == ["participant_id", "pseudonym", "age"]
    row = participants[1].split("\t")
    assert row[:3] == ["sub-PZ017", "PZ-017", "75"] and "left" in row
    text = "".join(p.read_text(errors="replace") for p in root.rglob("*") if p.is_file() and p.suffix != ".gz")
    assert "Maria" not in text and "1950-06-02" not in text, "the full name and birth date are never exported"
    sessions_tsv = (root / "sub-PZ017" / "sub-PZ017_sessions.tsv").read_text().splitlines()
    assert sessions_tsv[1].split("\t")[1].startswith("1926-03-01T")  # 2026-03-01 less 36 525 days (100 years)
    assert "2026-" not in "".join(p.read_text() for p in root.rglob("*_scans.tsv"))
    events = "".join(p.read_text() for p in root.rglob("*_events.tsv"))
    assert "20260301" not in events and "2026-03" not in events  # no session folder path, no wall time


def test_names_only_when_asked(dataset, tmp_path) -> None:
    _, sessions = dataset
    out = tmp_path / "named"
    export_bids(sessions[:1], out, BidsOptions(include_names=True, metrics=False))
    assert "Maria Rossi" in (out / "participants.tsv").read_text()
    assert not (out / "derivatives").exists()
