"""The suite's xdist groups: the emulated board (qemu at SCHED_RR) never runs beside the clinician's day (#38)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PROBE = '''
def pytest_collection_finish(session):
    for item in session.items:
        mark = item.get_closest_marker("xdist_group")
        print("GROUP", item.nodeid.split("@")[0], "=", mark.kwargs.get("name") if mark else None)
'''


def test_the_emulated_board_and_the_clinicians_day_share_one_worker(tmp_path: Path) -> None:
    (tmp_path / "probe_groups.py").write_text(PROBE, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "probe_groups",
                          "-p", "no:randomly", "-p", "no:cacheprovider", "tests/test_clinician_day.py",
                          "tests/test_firmware_mcu.py"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=120).stdout
    groups = {line.split(" ", 2)[1]: line.rsplit(" = ", 1)[1] for line in out.splitlines()
              if line.startswith("GROUP ")}
    assert any(node.startswith("tests/test_clinician_day.py") for node in groups), out[-2000:]
    assert sum(node.startswith("tests/test_firmware_mcu.py") for node in groups) > 10, out[-2000:]
    assert len(set(groups.values())) == 1 and "None" not in groups.values(), groups  # one group, one worker
