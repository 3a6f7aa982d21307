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
