"""The real-time process's priority (app/core/priority.py): raised where the system allows it, every thread of the
process (Linux's nice is per thread), the heavy work's worker at its own lower priority whatever it inherits, and
a plain sentence where it is not allowed."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from app.core import priority
from app.core.priority import REALTIME_NICE, raise_for_real_time

pytestmark = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="Linux's per-thread nice")


def _nice_of(tid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


def _may_raise() -> bool:
    """Whether this process may raise a thread to REALTIME_NICE: tried on a throwaway thread (root is not enough: a
    container may withhold CAP_SYS_NICE)."""
    allowed: list[bool] = []

    def probe() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, min(_nice_of(0), REALTIME_NICE))
            allowed.append(True)
        except PermissionError:
            allowed.append(False)

    thread = threading.Thread(target=probe)
    thread.start()
    thread.join()
    return allowed[0]


@pytest.fixture
def fresh_outcome():  # type: ignore[no-untyped-def]
    priority._reset_for_tests()
    yield
    priority._reset_for_tests()


def test_every_thread_is_raised_and_later_threads_inherit(fresh_outcome) -> None:  # type: ignore[no-untyped-def]
    if not _may_raise():
        pytest.skip("this user may not raise a priority (the denied case is tested below)")
    before: list[int] = []
    started, done = threading.Event(), threading.Event()

    def sleeper() -> None:
        before.append(threading.get_native_id())
        started.set()
        done.wait(5)

    thread = threading.Thread(target=sleeper)
    thread.start()
    try:
        assert started.wait(5)
        outcome = raise_for_real_time()
        assert outcome.raised and outcome.nice <= REALTIME_NICE, outcome
        assert _nice_of(0) <= REALTIME_NICE
        assert _nice_of(before[0]) <= REALTIME_NICE  # made before the call: raised too
        later: list[int] = []
        child = threading.Thread(target=lambda: later.append(_nice_of(0)))
        child.start()
        child.join(5)
        assert later and later[0] <= REALTIME_NICE  # made after: inherits
        assert raise_for_real_time() is outcome  # once per process
    finally:
        done.set()
        thread.join(5)


def test_where_it_is_not_allowed_the_process_runs_on_and_says_why(fresh_outcome, monkeypatch, caplog) -> None:  # type: ignore[no-untyped-def]
    def denied(*_args: int) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "getpriority", lambda *_a: 0)
    monkeypatch.setattr(priority.os, "setpriority", denied)
    with caplog.at_level("INFO", logger="app.core.priority"):
        outcome = raise_for_real_time()
    assert not outcome.raised and outcome.nice == 0
    assert "normal priority" in outcome.sentence and "RLIMIT_NICE" in outcome.sentence
    assert outcome.sentence in caplog.text


def test_the_worker_runs_at_its_own_lower_priority_whatever_it_inherits(fresh_outcome, qtbot) -> None:  # type: ignore[no-untyped-def]
    from app.worker import TaskService
    from app.worker.service import WORKER_NICE

    if _may_raise():
        raise_for_real_time()  # the worker is started from a raised thread, as in the application
    service = TaskService()
    try:
        service.warm()
        # "ready" is sent once the worker has set its priority
        qtbot.waitUntil(lambda: service._worker is not None and service._worker.ready_s is not None, timeout=20000)
        pid = service.worker_pid
        assert pid is not None and _nice_of(pid) == WORKER_NICE != _nice_of(0)
    finally:
        service.close()


def test_the_process_s_scheduling_group_is_raised_with_it() -> None:
    """Linux's autogroup: a thread's nice counts only inside its session's group; against a program of another session
    the group's nice decides. Run in a session of its own, so the suite's own group is left as it is."""
    import subprocess
    import sys

    if priority.group_nice() is None:
        pytest.skip("no scheduling groups (autogroup) on this system")
    code = ("from app.core import priority\n"
            "outcome = priority.raise_for_real_time()\n"
            "print(outcome.raised, priority.group_nice(), outcome.sentence)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          start_new_session=True, cwd=Path(__file__).resolve().parent.parent)
    raised, group, sentence = done.stdout.split(" ", 2)
    if raised == "True":
        assert int(group) == REALTIME_NICE, sentence
        assert "its scheduling group too" in sentence
    else:
        assert _may_raise() is False, sentence  # refused only where this user may not raise at all
        assert "normal priority" in sentence


def test_the_worker_s_group_sits_below_the_application_s(fresh_outcome, qtbot) -> None:  # type: ignore[no-untyped-def]
    from app.worker import TaskService
    from app.worker.service import WORKER_NICE

    ours = priority.group_nice()
    if ours is None:
        pytest.skip("no scheduling groups (autogroup) on this system")
    service = TaskService()
    try:
        service.warm()
        qtbot.waitUntil(lambda: service._worker is not None and service._worker.ready_s is not None, timeout=20000)
        pid = service.worker_pid
        assert pid is not None
        words = Path(f"/proc/{pid}/autogroup").read_text().split()
        assert int(words[words.index("nice") + 1]) == min(19, ours + WORKER_NICE)
    finally:
        service.close()
