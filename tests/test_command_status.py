"""A command's status completes once (issue #40), as ophyd's Status: a second completion raises, and the paths
that race for a status legitimately (the reply against its timeout, the link lost or the queue closing against
the reply, a caller's cancel against the reply) claim it first, so exactly one of them decides and nothing
raises in normal use."""

from __future__ import annotations

import random
import threading
from collections import Counter
from concurrent import futures

import pytest

from app.core.config import SafetyConfig
from app.devices.command_queue import CommandQueue, CommandStatus, Priority, StatusAlreadyDone
from app.devices.linarm import LinarmDriver, LinarmTimeout
from app.safety.supervisor import SafetySupervisor
from tests.test_command_queue import (
    ScriptedController,
    linarm,  # noqa: F401 - the fixture: a LINarm driver on a scripted controller
)


def _status() -> CommandStatus:
    return CommandStatus("setMaxForce", "test", Priority.NORMAL)


def test_a_second_completion_raises() -> None:
    s = _status()
    s.resolve({"maxForce": 40.0})
    with pytest.raises(StatusAlreadyDone, match="setMaxForce: completed twice"):
        s.resolve({"maxForce": 50.0})
    with pytest.raises(StatusAlreadyDone):
        s.fail(TimeoutError("late"))
    assert s.result(0) == {"maxForce": 40.0}  # the first outcome stands

    failed = _status()
    failed.fail(TimeoutError("no ACK"))
    with pytest.raises(StatusAlreadyDone):
        failed.resolve({})
    assert isinstance(failed.exception(0), TimeoutError)


def test_a_cancelled_status_refuses_a_late_completion_and_settle_does_not_raise() -> None:
    s = _status()
    assert s.cancel()
    with pytest.raises(StatusAlreadyDone, match="cancelled"):
        s.resolve({})
    assert s.settle({}) is False and s.cancelled()


def test_only_the_claiming_thread_completes() -> None:
    s = _status()
    assert s.claim()
    assert not s.claim() and not s.cancel()  # claimed: a second claimant and a cancel both lose
    errors: list[BaseException] = []

    def other() -> None:
        try:
            s.resolve("from another thread")
        except StatusAlreadyDone as exc:
            errors.append(exc)

    t = threading.Thread(target=other)
    t.start()
    t.join(2.0)
    assert len(errors) == 1 and "did not claim" in str(errors[0]) and not s.done()
    s.resolve("mine")
    assert s.result(0) == "mine"


def test_racing_claims_are_won_once() -> None:
    """Reply, timeout and cancel released together on the same status, 300 times: exactly one wins each time
    and none of them raises."""
    winners: Counter[str] = Counter()
    errors: list[BaseException] = []
    for _ in range(300):
        s = _status()
        gate = threading.Barrier(3)
        won: list[str] = []

        def reply(s: CommandStatus = s, gate: threading.Barrier = gate, won: list[str] = won) -> None:
            gate.wait()
            if s.claim():
                won.append("reply")
                s.resolve({"ok": 1})

        def timeout(s: CommandStatus = s, gate: threading.Barrier = gate, won: list[str] = won) -> None:
            gate.wait()
            if s.settle(exc=TimeoutError("no ACK")):
                won.append("timeout")

        def cancel(s: CommandStatus = s, gate: threading.Barrier = gate, won: list[str] = won) -> None:
            gate.wait()
            if s.cancel():
                won.append("cancel")

        threads = [threading.Thread(target=f) for f in (reply, timeout, cancel)]
        old_hook = threading.excepthook
        threading.excepthook = lambda args: errors.append(args.exc_value)  # type: ignore[assignment,misc]
        try:
            for t in threads:
                t.start()
            for t in threads:
                t.join(2.0)
        finally:
            threading.excepthook = old_hook
        assert len(won) == 1 and s.done(), won
        winners[won[0]] += 1
        outcome = "cancel" if s.cancelled() else "timeout" if s.exception(0) is not None else "reply"
        assert outcome == won[0]
    assert not errors
    assert sum(winners.values()) == 300


def test_the_queue_timeout_and_a_late_reply_decide_once() -> None:
    """An exclusive command whose reply comes about when its timeout expires, 150 times through a real queue: each
    status ends once, as the reply or as the timeout; the timeout's resync (on_timeout) runs exactly for those the
    timeout won (never for a command whose reply won), and nothing raises on the queue's thread."""
    resyncs: list[CommandStatus] = []
    errors: list[BaseException] = []
    queue = CommandQueue("race", on_timeout=lambda st: resyncs.append(st) or None)  # type: ignore[func-returns-value]
    replies: list[threading.Thread] = []
    rnd = random.Random(40)

    def reply_later(status: CommandStatus, delay: float) -> None:
        threading.Event().wait(delay)  # the controller's latency, around the timeout
        if status.claim():
            status.resolve({"ok": 1})

    def write(status: CommandStatus) -> None:
        t = threading.Thread(target=reply_later, args=(status, rnd.uniform(0.0, 0.004)))
        replies.append(t)
        t.start()

    old_hook = threading.excepthook
    threading.excepthook = lambda args: errors.append(args.exc_value)  # type: ignore[assignment,misc]
    queue.start()
    try:
        statuses = [queue.submit(f"cmd{i}", write, timeout_s=0.002) for i in range(150)]
        for st in statuses:
            st.exception(5.0)  # waits until done (result or error)
    finally:
        queue.close()
        for t in replies:
            t.join(2.0)
        threading.excepthook = old_hook
    assert not errors
    timed_out = [st for st in statuses if st.exception(0) is not None]
    assert all(isinstance(st.exception(0), TimeoutError) for st in timed_out)
    assert [id(s) for s in resyncs] == [id(s) for s in timed_out]
    assert all(st.result(0) == {"ok": 1} for st in statuses if st not in timed_out)


def test_the_linarm_ack_and_its_timeout_decide_once(linarm, qtbot) -> None:  # type: ignore[no-untyped-def]  # noqa: F811
    """The LINarm driver: an ACK released about when its command times out, 30 times. Each command ends once, as
    the ACK's values or as LinarmTimeout; the parser resync (';') is written once for each timeout the queue won
    and never for a command whose ACK won; nothing raises on the driver's threads."""
    driver, controller, _supervisor = linarm
    controller.hold = {"resetError"}
    rnd = random.Random(29)
    errors: list[BaseException] = []
    old_hook = threading.excepthook
    threading.excepthook = lambda args: errors.append(args.exc_value)  # type: ignore[assignment,misc]
    outcomes: Counter[str] = Counter()
    resyncs_before = sum(1 for _t, n, _a in controller.log if n == ";")
    try:
        for _ in range(30):
            status = driver.submit("resetError", source="test", timeout_s=0.02)
            assert status.wait_written(2.0)  # held by the controller: its timeout runs from now
            threading.Event().wait(rnd.uniform(0.005, 0.035))  # the controller's latency, around the 20 ms timeout
            controller.release()
            exc = status.exception(2.0)
            outcomes["timeout" if isinstance(exc, LinarmTimeout) else "ack" if exc is None else repr(exc)] += 1
    finally:
        threading.excepthook = old_hook
    resyncs = sum(1 for _t, n, _a in controller.log if n == ";") - resyncs_before
    assert not errors
    assert set(outcomes) <= {"ack", "timeout"} and sum(outcomes.values()) == 30, outcomes
    assert resyncs == outcomes["timeout"], (resyncs, outcomes)


class AckDuringResync(ScriptedController):
    """A controller whose held ACK arrives exactly while the host resyncs after giving up on it: the write of the
    timeout's ';' releases the ACK and returns only once the host has dealt with it (or after 0.3 s)."""

    def __init__(self) -> None:
        super().__init__()
        self.status: CommandStatus | None = None
        self.resyncs = 0

    def write(self, data: bytes) -> None:
        super().write(data)
        if data == b";" and self.status is not None:
            self.resyncs += 1
            self.release()
            futures.wait([self.status], 0.3)


def test_an_ack_arriving_during_the_timeouts_resync_does_not_undo_the_timeout(qtbot) -> None:  # type: ignore[no-untyped-def]
    """The old queue checked 'not done' and then ran the timeout's resync: an ACK read in between completed the
    command as acknowledged, after the host had resynced the controller's parser for a command it gave up on
    (and the timeout's failure was dropped silently). Now the timeout claims the command first: the late ACK is
    ignored and the command ends as the timeout it was."""
    controller = AckDuringResync()
    driver = LinarmDriver(controller, SafetySupervisor(SafetyConfig()), command_timeout_s=1.0,  # type: ignore[arg-type]
                          heartbeat_period_s=0.05)
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=3000)
        controller.hold = {"resetError"}
        status = driver.submit("resetError", source="test", timeout_s=0.05)
        controller.status = status
        exc = status.exception(3.0)
    finally:
        driver.stop()
    assert controller.resyncs == 1
    ended = exc if exc is not None else status.result(0)
    assert isinstance(exc, LinarmTimeout), f"resynced for a timeout, but the command ended as {ended!r}"
