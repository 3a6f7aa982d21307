"""dev.py's worker count for the whole suite (#38): three when the cores are free, two when other programs already
keep them busy (a third worker then only starves the real-time tests), or what LINARMPP_TEST_WORKERS says."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]


def dev() -> ModuleType:
    spec = importlib.util.spec_from_file_location("dev_under_test", ROOT / "dev.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(("idle", "workers"), [(0.95, 3), (0.6, 3), (0.4, 2), (0.0, 2), (None, 3)])
def test_the_workers_follow_how_busy_the_cores_are(idle: float | None, workers: int,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    module = dev()
    monkeypatch.delenv("LINARMPP_TEST_WORKERS", raising=False)
    monkeypatch.setattr(module, "idle_share", lambda seconds=1.0: idle)
    assert module.test_workers() == workers


def test_the_environment_chooses_the_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    module = dev()
    monkeypatch.setattr(module, "idle_share", lambda seconds=1.0: 0.0)
    monkeypatch.setenv("LINARMPP_TEST_WORKERS", "4")
    assert module.test_workers() == 4


def test_the_idle_share_is_a_share() -> None:
    share = dev().idle_share(0.05)
    assert share is None or 0.0 <= share <= 1.0


def test_a_worker_that_crashes_ends_the_run_failed(tmp_path: Path) -> None:
    """A segmentation fault in a worker (the suite's Qt crash, #38) ends the whole-suite run with a failure naming
    the test; before, the replaced worker never got the crashed worker's group and the run hung (rc 124 here)."""
    import subprocess
    import sys

    (tmp_path / "pytest.ini").write_text("[pytest]\n", encoding="utf-8")
    (tmp_path / "test_toy.py").write_text(
        "import os\nimport pytest\n\n"
        "@pytest.mark.xdist_group('rig')\n@pytest.mark.parametrize('n', range(4))\n"
        "def test_grouped(n):\n    if n == 1:\n        os.abort()\n\n"
        "@pytest.mark.parametrize('n', range(4))\ndef test_free(n):\n    pass\n", encoding="utf-8")
    cmd = [sys.executable, "-m", "pytest", *dev().distribution(2), "-q", "-p", "no:randomly", "-p", "no:cacheprovider",
           "-p", "no:pytestqt", "-p", "no:rerunfailures", "-p", "no:timeout"]
    try:
        done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired as exc:
        raise AssertionError("the run did not end after a worker crashed") from exc
    assert done.returncode != 0
    assert "crashed while running 'test_toy.py::test_grouped[1]'" in done.stdout, done.stdout[-2000:]
