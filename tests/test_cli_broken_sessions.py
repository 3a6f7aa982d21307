"""Issue #25, the record rows: ``--metrics`` / ``--report`` on a session that is incomplete or broken say
what is missing and exit 3 (the output covers what was recorded) instead of 0 with no word of it; a report
that cannot be written (a read-only folder) is one plain line and exit 1, never a traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from app.core.config import AppConfig
from app.manager import LinarmppManager
from tests.fakes import counter_factory

ROOT = Path(__file__).resolve().parents[1]


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(ROOT / "main.py"), *args], capture_output=True, text=True,
                          timeout=120, cwd=ROOT, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})


@pytest.fixture
def session(tmp_path: Path, qtbot: Any) -> Path:
    """A short real session (every device simulated but the physio board, a 1 kHz counter), stopped."""
    m = LinarmppManager(AppConfig(), factories={"physio": counter_factory(tmp_path, "physio")})
    m.start()
    try:
        qtbot.waitUntil(m.all_connected, timeout=15000)
        folder = m.start_session("CLI01", "tester", root=tmp_path / "sessions")
        m.record_event("marker", note="something happened")
        qtbot.waitUntil(lambda: all(n > 200 for n in m.recorder.counts().values()), timeout=10000)
        m.end_session("test")
    finally:
        m.shutdown()
    return folder


def manifest_of(folder: Path) -> dict[str, Any]:
    return json.loads((folder / "manifest.json").read_text(encoding="utf-8"))


def test_a_complete_session_gives_metrics_and_exit_0(session: Path) -> None:
    done = cli("--metrics", str(session))
    assert done.returncode == 0, done.stderr
    assert "Incomplete" not in done.stderr
    assert "summary" in json.loads(done.stdout)


def test_metrics_on_a_truncated_session_name_what_is_missing_and_exit_3(session: Path) -> None:
    manifest = manifest_of(session)
    name, info = next((n, i) for n, i in manifest["streams"].items() if manifest["counts"][n] > 100)
    path = session / info["file"]
    lines = path.read_bytes().split(b"\n")
    keep = len(lines) // 2
    path.write_bytes(b"\n".join(lines[:keep]) + b"\n")  # a copy cut half-way (a full USB stick, a bad sync)
    events = (session / "events.jsonl").read_text(encoding="utf-8").splitlines()
    (session / "events.jsonl").write_text("\n".join(events[:-2]) + "\n", encoding="utf-8")

    done = cli("--metrics", str(session))
    assert done.returncode == 3, (done.returncode, done.stderr)
    assert "Traceback" not in done.stderr
    assert f"Incomplete session {session}" in done.stderr
    missing = manifest["counts"][name] - (keep - 1)
    assert f"{name}: {missing} of {manifest['counts'][name]} samples missing" in done.stderr, done.stderr
    assert f"events: 2 of {manifest['event_count']} missing" in done.stderr, done.stderr
    assert "summary" in json.loads(done.stdout)  # what was recorded is still given

    pdf = session.parent / "report.pdf"
    done = cli("--report", str(session), "--out", str(pdf))
    assert done.returncode == 3 and f"{name}: {missing} of" in done.stderr, done.stderr
    assert pdf.read_bytes().startswith(b"%PDF")  # the report of what was recorded is still written


def test_metrics_on_a_crashed_or_failed_recording_say_so(session: Path) -> None:
    manifest = manifest_of(session)
    crashed = {**manifest, "status": "recording", "end": None}
    (session / "manifest.json").write_text(json.dumps(crashed), encoding="utf-8")
    done = cli("--metrics", str(session))
    assert done.returncode == 3 and "not stopped normally" in done.stderr, done.stderr

    failed = {**manifest, "status": "failed", "recording_failure": {
        "t_wall": "2026-01-01T10:00:00+01:00", "error": "No space left on device (errno 28)",
        "samples_lost": 1234, "events_not_written": 3}}
    (session / "manifest.json").write_text(json.dumps(failed), encoding="utf-8")
    done = cli("--metrics", str(session))
    assert done.returncode == 3, done.stderr
    assert "the recording failed at 2026-01-01T10:00:00+01:00: No space left on device" in done.stderr
    assert "1234 samples and 3 events could not be written" in done.stderr

    (session / "events.jsonl").unlink()
    (session / "manifest.json").write_text(json.dumps(manifest), encoding="utf-8")
    done = cli("--metrics", str(session))
    assert done.returncode == 3 and "events.jsonl is missing" in done.stderr, done.stderr


def test_a_damaged_manifest_is_one_line_not_a_traceback(session: Path) -> None:
    (session / "manifest.json").write_text("[1, 2, 3]\n", encoding="utf-8")
    done = cli("--metrics", str(session))
    assert done.returncode != 0 and "Traceback" not in done.stderr, done.stderr
    assert "manifest unreadable" in done.stderr


@pytest.fixture
def read_only_folder(tmp_path: Path):
    """A folder no one can write in: a read-only tmpfs for root (permission bits do not stop root), else
    a folder without write permission."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() == 0:
        if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)],
                          capture_output=True).returncode != 0:
            pytest.skip("root, and cannot mount a read-only tmpfs here")
        try:
            yield folder
        finally:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)
    else:
        folder.chmod(0o555)
        try:
            yield folder
        finally:
            folder.chmod(0o755)


def test_report_into_a_read_only_folder_is_a_plain_message_and_exit_1(session: Path, read_only_folder: Path) -> None:
    out = read_only_folder / "report.pdf"
    done = cli("--report", str(session), "--out", str(out))
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert "Traceback" not in done.stderr and not out.exists()
    assert f"Cannot write {out}" in done.stderr and "not writable" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_report_into_a_missing_folder_is_a_plain_message(session: Path, tmp_path: Path) -> None:
    out = tmp_path / "no" / "such" / "report.pdf"
    done = cli("--report", str(session), "--out", str(out))
    assert done.returncode == 1 and "does not exist" in done.stderr and "Traceback" not in done.stderr


def test_a_manifest_naming_a_file_outside_the_session_is_not_read(session: Path) -> None:
    """A session folder may come from elsewhere: its manifest pointing a stream at /dev/zero read forever."""
    manifest = manifest_of(session)
    name = next(iter(manifest["streams"]))
    manifest["streams"][name]["file"] = "../" * 12 + "dev/zero"
    (session / "manifest.json").write_text(json.dumps(manifest), encoding="utf-8")
    done = cli("--metrics", str(session))
    assert done.returncode == 3 and "Traceback" not in done.stderr, done.stderr
    assert f"{name}: file " in done.stderr and "not in the session's streams folder; not read" in done.stderr
