"""A file is written only when it is right (issue #37): reports and exports to a full disk or a read-only folder
give one sentence and exit 1, never a traceback or a false "written", and leave nothing behind; a data folder that
cannot be written is one line at start-up. On the code before #37: the report to a full disk said "written" with
exit 0, the CSV export left a partial folder, HDF5 killed the process (SIGSEGV), a read-only data folder was a
traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from app.core.outputs import OutputError, pdf_page_count
from app.session.export import export_csv
from app.session.recording import load_session
from tests.mounts import entries, full_disk, read_only
from tests.run_sessions import clinic_day_runs, write_run_session

ROOT = Path(__file__).resolve().parents[1]


def cli(*args: str, home: Path, stdout: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "LINARMPP_HOME": str(home), "QT_QPA_PLATFORM": "offscreen"}
    out = open(stdout, "w") if stdout is not None else subprocess.PIPE  # closed below
    try:
        return subprocess.run([sys.executable, "main.py", *args], cwd=ROOT, env=env, stdout=out,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        if stdout is not None:
            out.close()  # type: ignore[union-attr]


def one_sentence(stderr: str) -> str:
    """The lines a user reads, checked to be a plain message (no traceback)."""
    assert "Traceback" not in stderr and "Error:" not in stderr.split(":", 1)[0], stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip() and "INFO" not in ln and "WARNING" not in ln]
    assert len(lines) == 1, stderr
    return lines[0]


@pytest.fixture
def session(tmp_path: Path) -> Path:
    return write_run_session(tmp_path / "sessions" / "P1" / "20260301-100000", clinic_day_runs())


def test_reports_and_metrics_to_a_full_disk_or_a_read_only_folder(session: Path, tmp_path: Path) -> None:
    home = tmp_path / "home"
    with full_disk(tmp_path / "full") as full:
        r = cli("--report", str(session), "--out", str(full / "r.pdf"), home=home)
        assert r.returncode == 1, r.stderr  # before #37: 0 and "Session report written" with a cut PDF
        line = one_sentence(r.stderr)
        assert line == f"The session report {full / 'r.pdf'} was not written: the disk is full (no space left in " \
                       f"{full}).", line
        assert entries(full) == []  # no file, no temporary
        r = cli("--progress", "P1", "--out", str(full / "p.pdf"), home=home)
        # --progress reads the patient's sessions from the data folder: none here, so point it at them
        assert r.returncode == 2 and "no session of patient P1" in r.stderr
        r = cli("--metrics", str(session), home=home, stdout=full / "m.json")
        assert r.returncode == 1 and entries(full) == ["m.json"]
        assert one_sentence(r.stderr).startswith("Cannot write the standard output: No space left on device")
    with read_only(tmp_path / "ro") as ro:
        r = cli("--report", str(session), "--out", str(ro / "r.pdf"), home=home)
        assert r.returncode == 1 and "read-only" in one_sentence(r.stderr).lower() and entries(ro) == []


def test_progress_report_to_a_full_disk(session: Path, tmp_path: Path) -> None:
    config = tmp_path / "config.yaml"
    config.write_text(f"recording:\n  folder: {session.parent.parent}\n", encoding="utf-8")
    with full_disk(tmp_path / "full") as full:
        r = cli("--config", str(config), "--progress", "P1", "--out", str(full / "p.pdf"), home=tmp_path / "home")
        assert r.returncode == 1, r.stderr
        assert one_sentence(r.stderr) == f"The progress report {full / 'p.pdf'} was not written: the disk is full " \
                                          f"(no space left in {full})."
        assert entries(full) == []
    r = cli("--config", str(config), "--progress", "P1", "--out", str(tmp_path / "p.pdf"), home=tmp_path / "home")
    assert r.returncode == 0 and pdf_page_count(tmp_path / "p.pdf") >= 1  # said written: it is, whole


def test_exports_to_a_full_disk_or_a_read_only_folder(session: Path, tmp_path: Path) -> None:
    home = tmp_path / "home"
    with full_disk(tmp_path / "full", size_kib=1024, leave_bytes=16 * 1024) as full:
        r = cli("--export", str(session), "--out", str(full / "s.h5"), home=home)
        assert r.returncode == 1, r.stderr  # HDF5 to a full disk: SIGSEGV before #37, in the writing process
        line = one_sentence(r.stderr)
        assert "disk is full" in line and "s.h5" in line, line
        assert entries(full) == []
        r = cli("--export", str(session), "--out", str(full / "csv"), home=home)
        assert r.returncode == 1 and "disk is full" in one_sentence(r.stderr) and entries(full) == []
    with read_only(tmp_path / "ro") as ro:
        r = cli("--export", str(session), "--out", str(ro / "s.h5"), home=home)
        assert r.returncode == 1 and "not writable" in one_sentence(r.stderr) and entries(ro) == []
    r = cli("--export", str(session), "--out", str(tmp_path / "s.h5"), home=home)
    assert r.returncode == 0 and "verified" in r.stderr and (tmp_path / "s.h5").stat().st_size > 0


def test_a_csv_export_to_a_full_disk_leaves_no_partial_folder(session: Path, tmp_path: Path) -> None:
    loaded = load_session(session)
    with full_disk(tmp_path / "full", size_kib=1024, leave_bytes=64 * 1024) as full:
        with pytest.raises(OutputError) as refused:
            export_csv(loaded, full / "csv")
        assert str(refused.value) == f"The CSV export {full / 'csv'} was not written: the disk is full (no space " \
                                     f"left in {full})."
        assert entries(full) == []  # before #37: a folder with the first stream files in it


def test_a_read_only_data_folder_is_one_line_at_start(session: Path, tmp_path: Path) -> None:
    with read_only(tmp_path / "data") as data:
        for args, code in ((("--metrics", str(session)), 1), (("--headless", "--script", "x.py"), 4), ((), 1)):
            r = cli(*args, home=data)
            assert r.returncode == code, (args, r.stderr)  # before #37: a traceback from logging_setup
            line = one_sentence(r.stderr)
            assert line.startswith(f"LINarm++ Manager cannot use its data folder: the folder {data / 'logs'} "
                                   "cannot be written (Read-only file system)"), line
