"""Jobs for the task service's tests (run in the worker process: ``"tests.worker_jobs:name"``)."""

from __future__ import annotations

import os
import signal
import time
from typing import Any


def echo(ctx: Any, *args: Any, **kwargs: Any) -> tuple[tuple[Any, ...], dict[str, Any], int]:
    return args, kwargs, os.getpid()


def count(ctx: Any, steps: int, step_s: float) -> int:
    """Progress at every step; stops when cancelled (as the real jobs do)."""
    for k in range(steps):
        ctx.step(k / steps, f"step {k}")
        time.sleep(step_s)
    return steps


def stuck(ctx: Any, seconds: float) -> str:
    """Native code that never looks at its cancel flag (a stuck HDF5 call)."""
    time.sleep(seconds)
    return "woke"


def crash(ctx: Any, how: str = "segv") -> None:
    if how == "segv":
        os.kill(os.getpid(), signal.SIGSEGV)
    os._exit(3)


def fail(ctx: Any) -> None:
    raise ValueError("this task cannot be done")


def fail_and_retire(ctx: Any) -> None:
    """A failure in native code: this worker should not run another task."""
    ctx.retire = True
    raise OSError(28, "No space left on device")
