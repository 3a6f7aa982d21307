"""The suite's own rule (tests/conftest.py): a test marked ``realtime`` runs with its worker's threads at
REALTIME_TEST_NICE, ahead of workers running logic tests; a logic test runs at the worker's own priority."""

from __future__ import annotations

import os
import threading

import pytest

from tests.conftest import REALTIME_TEST_NICE


def _may_raise_to(nice: int) -> bool:
    """Tried on a throwaway thread, so nothing of the worker changes."""
    allowed: list[bool] = []

    def probe() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
            allowed.append(True)
        except PermissionError:
            allowed.append(False)

    thread = threading.Thread(target=probe)
    thread.start()
    thread.join()
    return allowed[0]


@pytest.mark.realtime
def test_a_realtime_test_runs_ahead_with_every_thread() -> None:
    if not _may_raise_to(REALTIME_TEST_NICE):
        pytest.skip("this user may not raise a priority: realtime tests run as the others")
    assert os.getpriority(os.PRIO_PROCESS, 0) == REALTIME_TEST_NICE
    seen: list[int] = []
    thread = threading.Thread(target=lambda: seen.append(os.getpriority(os.PRIO_PROCESS, 0)))
    thread.start()
    thread.join()
    assert seen == [REALTIME_TEST_NICE]  # threads the test starts inherit it


def test_a_logic_test_runs_at_the_workers_own_priority() -> None:
    assert os.getpriority(os.PRIO_PROCESS, 0) > REALTIME_TEST_NICE
