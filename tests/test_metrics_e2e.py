"""End to end: an exercise of known movements, recorded against the simulated devices, then the command line.

The trigger-reaching exercise (resources/exercises) is started as the Exercises tab starts it
(app.therapy.exercises.start_exercise on a ScriptRunner) with 3 movements of 0.24 m at 0.15 m/s, each triggered by
the simulated patient's grip. ``main.py --metrics`` must find the 3 repetitions with range and peak speed
within a few percent of the commanded ones, and a reaction time; ``--report`` and ``--progress`` write PDFs
whose every page pdftoppm renders into a picture that is not blank.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from app.core.config import AppConfig, UdpEndpoint
from app.session.metrics import repetitions, signals_from_session
from app.session.recording import load_session
from app.therapy.exercises import find_exercise, start_exercise

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
PATIENT = "PZ-E2E"
# 3 movements (4 before, ~4 s more of real time): the count, each movement's range, speed and smoothness and the
# segmentation without the marks are checked against the commanded ones either way.
PARAMS = {"movements": 3, "start_m": 0.12, "end_m": 0.36, "speed_m_s": 0.15, "acceleration_m_s2": 0.3,
          "trigger_threshold_n": 20.0, "trigger_timeout_s": 10.0, "rest_s": 0.5}
RANGE_M = 0.24
SPEED_M_S = 0.15


def config() -> AppConfig:
    cfg = AppConfig()
    return replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"),
                                        vr=UdpEndpoint(mode="off")))


def record_exercise(root: Path, qtbot: Any) -> Path:
    from app.manager import LinarmppManager
    from app.scripting.runner import ScriptRunner

    manager = LinarmppManager(config())
    output: list[tuple[str, str]] = []
    try:
        manager.start()
        qtbot.waitUntil(manager.all_connected, timeout=10000)
        manager.sim_patient().squeeze_periodically(period=1.3, duty=0.23)
        folder = manager.start_session(PATIENT, "dr_test", note="e2e", root=root)
        runner = ScriptRunner(manager, lambda stream, text: output.append((stream, text)))
        checked = start_exercise(runner, manager, find_exercise("trigger_reaching"), PARAMS)
        assert checked.ok, checked.errors
        qtbot.waitUntil(lambda: runner.result is not None, timeout=90000)
        assert runner.result.status == "finished", (runner.result, "".join(t for _, t in output))
    finally:
        manager.end_session("test finished")
        manager.shutdown()
    return folder


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(ROOT / "main.py"), *args], capture_output=True, text=True,
                          timeout=120, cwd=ROOT, env={**os.environ, "QT_QPA_PLATFORM": "offscreen", **(env or {})})


def rendered_pages(pdf: Path, out: Path) -> list[Path]:
    """pdftoppm each page to PNG; every picture must hold drawing (not a blank page)."""
    from PySide6.QtGui import QImage

    subprocess.run(["pdftoppm", "-r", "40", "-png", str(pdf), str(out / pdf.stem)], check=True, timeout=60)
    pages = sorted(out.glob(f"{pdf.stem}*.png"))
    for page in pages:
        img = QImage(str(page))
        assert not img.isNull()
        dark = sum(1 for y in range(0, img.height(), 3) for x in range(0, img.width(), 3)
                   if img.pixelColor(x, y).lightness() < 200)
        assert dark > 50, f"{page.name} looks blank"
    return pages


@pytest.mark.skipif(shutil.which("pdftoppm") is None, reason="poppler-utils (pdftoppm) is not installed")
def test_recorded_exercise_metrics_report_and_progress(tmp_path: Path, qtbot: Any) -> None:
    home = tmp_path / "home"
    folder = record_exercise(home / "sessions", qtbot)

    done = cli("--metrics", str(folder))
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    reps = result["repetitions"]
    assert len(reps) == PARAMS["movements"]
    for k, r in enumerate(reps):
        assert r["index"] == k + 1 and r["completed"] and r["source"] == "marks"
        assert r["range_m"] == pytest.approx(RANGE_M, rel=0.03), r
        assert r["peak_speed_m_s"] == pytest.approx(SPEED_M_S, rel=0.05), r
        assert r["path_length_m"] == pytest.approx(RANGE_M, rel=0.05), r
        assert r["speed_peaks"] == 1 and -2.5 < r["sparc"] < -1.3, r
        assert 0 <= r["start_s"] < r["movement_onset_s"] < r["end_s"]
        assert r["grip_at_start_n"] is not None and r["peak_force_n"] is not None
        # each movement began after the grip crossed 20 N: the robot's latency; the patient's reaction time
        # from the prompt, within a squeeze cycle — none when the (periodic) squeeze began before the prompt
        assert r["robot_latency_s"] is not None and 0.0 <= r["robot_latency_s"] < 0.5, r
        assert r["reaction_time_s"] is None or 0.0 <= r["reaction_time_s"] < 1.3, r
    summary = result["summary"]
    assert summary["repetitions"] == summary["completed"] == PARAMS["movements"] and summary["alarms"] == 0
    assert summary["exercise_params"]["speed_m_s"] == SPEED_M_S
    assert summary["range_m"]["mean"] == pytest.approx(RANGE_M, rel=0.03)

    assert [p["kind"] for p in result["positioning"]] == ["homing", "outside_repetitions"]  # to the start, apart

    # the same recording without the marks: segmentation finds the 3 movements; the move to the start began
    # before the exercise's first prompt: positioning, apart
    sig = signals_from_session(load_session(folder))
    sig.marks = []
    segmented = repetitions(sig)
    assert len(segmented) == PARAMS["movements"]
    for r in segmented:
        assert r.range_m == pytest.approx(RANGE_M, rel=0.03) and r.peak_speed_m_s == pytest.approx(SPEED_M_S, rel=0.05)

    pdf = tmp_path / "session.pdf"
    done = cli("--report", str(folder), "--out", str(pdf))
    assert done.returncode == 0, done.stderr
    pages = rendered_pages(pdf, tmp_path)
    assert len(pages) >= 1 and f"({len(pages)} page" in done.stderr

    progress = tmp_path / "progress.pdf"
    done = cli("--progress", PATIENT, "--out", str(progress), env={"LINARMPP_HOME": str(home)})
    assert done.returncode == 0, done.stderr
    assert rendered_pages(progress, tmp_path)


def test_cli_refuses_a_folder_that_is_not_a_session(tmp_path: Path) -> None:
    done = cli("--metrics", str(tmp_path))
    assert done.returncode == 2 and "not a session folder" in done.stderr
    done = cli("--report", str(tmp_path))
    assert done.returncode == 2 and "--out" in done.stderr
