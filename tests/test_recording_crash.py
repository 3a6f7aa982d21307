"""SIGKILL mid-session: every file stays readable and at most the last second is missing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from app.session.recording import load_session, summarize_session
from tests.conftest import ROOT

CHILD = r"""
import sys, time
from pathlib import Path
from PySide6.QtCore import QCoreApplication
from app.core.config import AppConfig
from app.devices import physio
from app.manager import LinarmppManager
from app.session.recording import SessionRecorder
from tests.fakes import counter_factory

tmp = Path(sys.argv[1])
app = QCoreApplication([])
manager = LinarmppManager(AppConfig(), factories={"physio": physio.create, "counter": counter_factory(tmp)})
manager.start()
deadline = time.monotonic() + 20
while not (manager.all_connected() and manager.driver("physio").total_samples("physio.main") > 0):
    if time.monotonic() > deadline:
        sys.exit("devices did not start")
    time.sleep(0.01)
recorder = SessionRecorder()
folder = recorder.start(manager, "P-crash", "op", root=tmp / "sessions")
recorder.event("script_start", "op", name="crash.py", text="while True: pass\n")
print("FOLDER", folder, flush=True)
while True:
    time.sleep(0.1)
    print("ALIVE", time.monotonic(), flush=True)
"""


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="SIGKILL is POSIX-only")
def test_sigkill_mid_session_loses_at_most_the_last_second(tmp_path) -> None:
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", TMPDIR=str(tmp_path), LINARMPP_HOME=str(tmp_path / "home"))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("FOLDER "), line + (proc.stderr.read() if proc.poll() is not None else "")
        folder = tmp_path / line.split(" ", 1)[1].strip()
        started = time.monotonic()
        while time.monotonic() - started < 4.0:  # the child's heartbeat paces the wait
            assert proc.stdout.readline().startswith("ALIVE"), "the recording process died early"
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()

    session = load_session(folder)  # must not raise on any file
    assert not session.complete and session.manifest["end"] is None
    assert session.manifest["patient_id"] == "P-crash" and session.manifest["config"]
    assert set(session.streams) == {"physio.main", "counter.main"}
    for name, stream in session.streams.items():
        assert len(stream) > 0, name
        assert np.all(np.diff(stream.t) >= 0), name
        missing = t_kill - stream.t[-1]
        assert missing <= 1.0, f"{name}: the last {missing:.2f} s before the kill are missing"
        span = stream.t[-1] - stream.t[0]
        assert abs(len(stream) - stream.nominal_rate_hz * span) <= max(3, 0.02 * stream.nominal_rate_hz * span)
    assert np.all(np.diff(session.streams["counter.main"].data["count"]) == 1), "samples lost before the kill"
    kinds = [e["kind"] for e in session.events]
    assert kinds[:2] == ["session_start", "script_start"]
    summary = summarize_session(folder)
    assert not summary.complete and summary.exercises == ("crash.py",) and summary.duration_s >= 3.0
