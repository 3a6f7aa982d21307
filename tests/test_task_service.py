"""The task service (issue #37): heavy work in a worker process, its progress, its result or one sentence, Cancel,
and a crash there that is a failed task while the application goes on."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import pytest

from app.worker import TaskFailed, TaskService, TaskStatus

JOBS = "tests.worker_jobs"


def until(condition, timeout: float = 10.0) -> bool:  # type: ignore[no-untyped-def]
    """Wait for ``condition`` (no Qt loop here: the service is Qt-free)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


@pytest.fixture
def service() -> Iterator[TaskService]:
    s = TaskService(cancel_grace_s=0.5, nice=0)  # the mechanism here, not the priority (tests/test_heavy_work_window)
    yield s
    s.close()


def test_a_task_reports_progress_and_its_result_from_another_process(service: TaskService) -> None:
    seen: list[tuple[str, float]] = []
    updates = threading.Event()

    def update(task) -> None:  # type: ignore[no-untyped-def]
        seen.append((task.status.value, task.fraction))
        if task.done:
            updates.set()

    task = service.submit(f"{JOBS}:count", 5, 0.02, title="Counting", on_update=update)
    assert task.value(60) == 5 and task.status is TaskStatus.DONE
    assert updates.wait(30)
    assert ("running", 0.0) in seen and seen[-1] == ("done", 1.0)
    assert any(0.0 < f < 1.0 for s, f in seen if s == "running"), seen
    args, kwargs, pid = service.run(f"{JOBS}:echo", 1, "a", key=[2.5], timeout=60)
    assert (args, kwargs) == ((1, "a"), {"key": [2.5]}) and pid != os.getpid() and pid == service.worker_pid
    # a failure is one sentence (the traceback is kept apart, for the log) and the worker goes on
    failed = service.submit(f"{JOBS}:fail")
    with pytest.raises(TaskFailed, match="this task cannot be done"):
        failed.value(60)
    assert "\n" not in failed.error and "Traceback" in failed.detail
    assert service.run(f"{JOBS}:echo", timeout=60)[2] == pid  # the same warm worker
    unknown = service.submit("no_such_job")
    assert not unknown.wait(60) or unknown.status is TaskStatus.FAILED
    assert "no task called" in unknown.error


def test_a_crash_in_the_worker_is_a_failed_task_and_the_next_task_gets_a_new_worker(service: TaskService) -> None:
    first = service.run(f"{JOBS}:echo", timeout=60)[2]
    crash = service.submit(f"{JOBS}:crash", "segv", title="Exporting to HDF5")
    queued_after = service.submit(f"{JOBS}:echo")  # waits behind the crash, then runs in a new worker
    with pytest.raises(TaskFailed) as failed:
        crash.value(60)
    assert crash.status is TaskStatus.FAILED
    assert str(failed.value) == "Exporting to HDF5 failed: the worker process stopped unexpectedly (signal SIGSEGV)."
    second = queued_after.value(60)[2]
    assert second != first and service.crashes == 1 and service.spawns == 2
    # a worker whose native code failed retires after its answer; the task after it runs in a new one
    retired = service.submit(f"{JOBS}:fail_and_retire")
    after = service.submit(f"{JOBS}:echo")
    with pytest.raises(TaskFailed, match="No space left on device"):
        retired.value(60)
    assert after.value(60)[2] not in (first, second) and service.crashes == 1


def test_cancel_stops_a_running_task_or_kills_a_stuck_worker(service: TaskService) -> None:
    running = service.submit(f"{JOBS}:count", 500, 0.01)
    queued = service.submit(f"{JOBS}:echo")
    queued.cancel()
    assert queued.status is TaskStatus.CANCELLED and queued.done  # dropped at once, never run
    assert until(lambda: running.fraction > 0)  # it runs, and reports
    pid = service.worker_pid
    running.cancel()
    assert running.wait(30) and running.status is TaskStatus.CANCELLED
    assert service.worker_pid == pid  # it stopped at its next progress: the worker stays
    stuck = service.submit(f"{JOBS}:stuck", 60.0)
    stuck.cancel()  # it never looks: the worker is killed after the grace
    assert stuck.wait(30) and stuck.status is TaskStatus.CANCELLED  # killed after the grace (0.5 s)
    assert service.run(f"{JOBS}:echo", timeout=60)[2] != pid


def test_close_ends_the_worker_and_cancels_what_is_left() -> None:
    service = TaskService(nice=0)
    running = service.submit(f"{JOBS}:stuck", 60.0)
    left = service.submit(f"{JOBS}:echo")
    assert until(lambda: service.last_start_s is not None)  # the worker runs the stuck task
    service.close()
    assert running.status is TaskStatus.CANCELLED and left.status is TaskStatus.CANCELLED
    late = service.submit(f"{JOBS}:echo")
    assert late.status is TaskStatus.CANCELLED and "closing" in late.error
    # the autouse fixture checks that no process or thread is left
