"""A kernel's API calls (issue #29): never run on the thread that reads the kernel's requests, in the order the
script made them; the script's e-stop never waits behind a command whose acknowledgement is slow."""

from __future__ import annotations

import re
import threading
import time
from typing import Any

import pytest

from app.scripting.runner import ScriptRunner
from tests.test_script_runner import FakeDriver, FakeManager, FakeSupervisor, Output, close_runners, started, wait_for

__all__ = ["close_runners"]  # the fixture, used by every test here (autouse)

ESTOP_BUDGET_S = 0.020  # bench/bench_estop.py's target (p99), from the script's call to the supervisor's e-stop
SLOW_ACK_S = 1.0


class SlowAckDriver(FakeDriver):
    """A LINarm whose controller takes ``ack_delay_s`` to acknowledge a move; records who ran each command."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.ack_delay_s = 0.0
        self.threads: list[tuple[str, str]] = []  # (command, thread name)
        self.move_in_flight = threading.Event()
        self.move_acked_at: float | None = None
        self._release = threading.Event()

    def command(self, name: str, *args: Any, source: str = "", timeout_s: float | None = None) -> dict[str, Any]:
        self.threads.append((name, threading.current_thread().name))
        if name == "moveCentreTo" and self.ack_delay_s:
            self.move_in_flight.set()
            self._release.wait(self.ack_delay_s)  # the controller's ACK comes late
            self.move_acked_at = time.monotonic()
        return super().command(name, *args, source=source, timeout_s=timeout_s)


class EstopSupervisor(FakeSupervisor):
    def __init__(self) -> None:
        super().__init__()
        self.estop_at: float | None = None

    def emergency_stop(self, source: str, reason: str = "") -> None:
        self.estop_at = time.monotonic()
        self.record("emergency_stop", source=source, reason=reason)


@pytest.fixture
def manager() -> FakeManager:
    m = FakeManager()
    linarm = SlowAckDriver("linarm", m.bus)
    linarm.samples.update(m.linarm.samples)
    m.linarm = linarm
    m.supervisor = EstopSupervisor()
    return m


@pytest.fixture
def output() -> Output:
    return Output()


def test_calls_run_in_order_on_a_call_thread_never_on_a_reader(manager: FakeManager, output: Output) -> None:
    """Fails on the code before #29: each call ran on the reader thread that read it (kernel-N-readerK)."""
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start("print('started')\nfor i in range(20):\n    linarm.setAssistanceTargetPos(0.1 + i * 0.001)\n",
                 "<test>")
    started(runner, output)
    assert runner.wait(10.0) and runner.result is not None and runner.result.status == "finished", output.text()
    linarm = manager.linarm
    moves = [(n, t) for n, t in linarm.threads if n == "setAssistanceTargetPos"]
    assert len(moves) == 20
    names = {t for _n, t in moves}
    assert not any("reader" in t for t in names), names
    assert len(names) == 1 and names.pop().endswith("-calls")
    targets = [args[0] for name, args, _src in linarm.commands if name == "setAssistanceTargetPos"]
    assert targets == [pytest.approx(0.1 + i * 0.001) for i in range(20)]  # in the order the script made them


@pytest.mark.realtime
def test_the_script_estop_is_not_queued_behind_a_slow_command(manager: FakeManager, output: Output) -> None:
    linarm = manager.linarm
    linarm.ack_delay_s = SLOW_ACK_S
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start("import threading, time\nprint('started')\n"
                 "threading.Thread(target=linarm.moveCentreTo, args=(0.3, 0.1, 0.1, 0, False), daemon=True).start()\n"
                 "time.sleep(0.3)\n"  # the move waits for its ACK meanwhile
                 "print(f'T0 {time.monotonic()!r}', flush=True)\n"
                 "linarmppManager.emergencyStop('test: e-stop during a slow move')\n", "<test>")
    started(runner, output)
    assert wait_for(lambda: manager.supervisor.estop_at is not None, 5.0), output.text()
    assert linarm.move_in_flight.is_set() and linarm.move_acked_at is None, "the e-stop came after the ACK"
    match = re.search(r"T0 ([0-9.]+)", output.text())
    assert match, output.text()
    latency = manager.supervisor.estop_at - float(match.group(1))  # one monotonic clock for both processes
    assert latency <= ESTOP_BUDGET_S, f"the script's e-stop took {latency * 1000:.1f} ms"
    runner.stop(wait_s=2.0)
    assert runner.wait(5.0)
    linarm._release.set()
