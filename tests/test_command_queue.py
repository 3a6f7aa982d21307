"""One command path per device (#29): the CommandQueue's ordering rules on their own, then the LINarm driver's
writes through it against a scripted controller that can hold an ACK back: a command submitted while another
is in flight is written after that one's ACK, the e-stop's IDLE passes a command in flight, the heartbeat
keeps beating while a command waits, a timeout resyncs the parser, a refusal sends nothing."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from app.core.config import SafetyConfig
from app.devices.command_queue import CommandQueue, CommandQueueClosed, CommandStatus, Priority
from app.devices.linarm import ESTOP_WRITE_BOUND_S, LinarmDriver, LinarmTimeout
from app.devices.transport import TransportError
from app.safety.supervisor import SafetyError, SafetySupervisor
from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import ArduinoReceiver
from app.wire.linarm_protocol import ControlState

IDLE = int(ControlState.IDLE_CTRL_STATE)


# ---------------------------------------------------------------------------------------------- the queue alone
@pytest.fixture
def queue() -> Iterator[CommandQueue]:
    q = CommandQueue("test")
    q.start()
    yield q
    q.close()


def _writer(log: list[str], name: str, gate: threading.Event | None = None):  # type: ignore[no-untyped-def]
    def write(_status: CommandStatus) -> None:
        if gate is not None:
            gate.wait(2.0)
        log.append(name)
    return write


def test_exclusive_commands_go_one_at_a_time_in_priority_order(queue: CommandQueue) -> None:
    log: list[str] = []
    first = queue.submit("first", _writer(log, "first"))
    assert first.wait_written(1.0)
    # queued while `first` awaits its reply: written in priority order once it is answered
    normal = queue.submit("normal", _writer(log, "normal"))
    link = queue.submit("link", _writer(log, "link"), priority=Priority.LINK)
    threading.Event().wait(0.05)  # nothing may be written while `first` is in flight: give it the chance
    assert log == ["first"] and not normal.written and not link.written
    first.resolve({"ok": 1})
    assert link.wait_written(1.0) and log[:2] == ["first", "link"]
    link.resolve(None)
    assert normal.wait_written(1.0) and log == ["first", "link", "normal"]
    normal.resolve(None)
    assert first.result(0) == {"ok": 1}


def test_the_estop_and_the_periodic_pass_a_command_in_flight() -> None:
    beats: list[float] = []
    five_more = threading.Event()
    mark = {"n": 10**9}

    def beat() -> None:
        beats.append(time.monotonic())
        if len(beats) >= mark["n"] + 5:
            five_more.set()

    q = CommandQueue("test", periodic=beat, period_s=0.02)
    q.start()
    try:
        log: list[str] = []
        held = q.submit("held", _writer(log, "held"), timeout_s=5.0)
        assert held.wait_written(1.0)
        mark["n"] = len(beats)
        estop = q.submit("estop", _writer(log, "estop"), priority=Priority.ESTOP, exclusive=False)
        assert estop.wait_written(0.5) and estop.result(0.5) is None
        assert five_more.wait(2.0), "the periodic stopped while a command awaited its reply"
        assert log == ["held", "estop"] and not held.done()
    finally:
        q.close()
    assert isinstance(held.exception(0), CommandQueueClosed)


def test_a_reply_that_never_comes_times_out_through_the_hook_and_frees_the_queue() -> None:
    seen: list[str] = []

    def on_timeout(status: CommandStatus) -> BaseException:
        seen.append(status.name)
        return LinarmTimeout(f"{status.name} timed out")

    q = CommandQueue("test", on_timeout=on_timeout)
    q.start()
    try:
        log: list[str] = []
        lost = q.submit("lost", _writer(log, "lost"), timeout_s=0.05)
        after = q.submit("after", _writer(log, "after"))
        with pytest.raises(LinarmTimeout):
            lost.result(1.0)
        assert after.wait_written(1.0) and seen == ["lost"] and log == ["lost", "after"]
        after.resolve(None)
    finally:
        q.close()


def test_a_queue_not_running_fails_at_once_and_close_fails_what_waits() -> None:
    q = CommandQueue("test")
    status = q.submit("x", lambda _s: None)
    assert isinstance(status.exception(0), CommandQueueClosed) and not status.wait_written(0)
    q.start()
    gate = threading.Event()
    log: list[str] = []
    blocker = q.submit("blocker", _writer(log, "blocker", gate), exclusive=False)
    waiting = q.submit("waiting", _writer(log, "waiting"))
    gate.set()
    assert blocker.wait_written(1.0)
    waiting.wait_written(1.0)
    q.close("closing", error=TransportError("link lost"))
    assert isinstance(waiting.exception(0), TransportError)


def test_an_idle_queue_rests_its_thread_and_the_next_submit_wakes_it() -> None:
    q = CommandQueue("resting", idle_exit_s=0.05)
    q.start()
    try:
        first = q.submit("first", lambda _s: None, exclusive=False)
        assert first.result(1.0) is None
        thread = q._thread
        assert thread is not None
        thread.join(2.0)
        assert not thread.is_alive() and q.running  # resting, still accepting
        again = q.submit("again", lambda _s: None, exclusive=False)
        assert again.result(1.0) is None and again.written
    finally:
        q.close()


# ---------------------------------------------------------------------------------------------- the LINarm
class ScriptedController:
    """A Transport that answers like the controller: Identify for identify, an ACK for every other command but
    the heartbeat, except commands named in ``hold`` (their ACK waits for ``release``). Logs every host write."""

    description = "scripted LINarm"

    def __init__(self) -> None:
        self.is_open = False
        self.log: list[tuple[float, str, dict]] = []  # (time written, command name or ';', args)
        self.hold: set[str] = set()
        self.held: list[tuple[int, str]] = []
        self._receiver = ArduinoReceiver()
        self._out = bytearray()
        self._cond = threading.Condition()

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def read(self, timeout: float) -> bytes:
        with self._cond:
            if not self._out:
                self._cond.wait(timeout)
            data, self._out = bytes(self._out), bytearray()
            return data

    def write(self, data: bytes) -> None:
        if not self.is_open:
            raise TransportError("closed")
        now = time.monotonic()
        if data == b";":
            self.log.append((now, ";", {}))
        for msg in self._receiver.feed(data):
            try:
                cmd = proto.read_host_message(msg)
            except proto.CommandRejected:
                continue
            self.log.append((now, cmd.name, dict(cmd.args)))
            if cmd.name == "identify":
                self._reply(proto.encode_identify(cmd.seq, "scripted"))
            elif cmd.name == "heartbeat":
                pass
            elif cmd.name in self.hold:
                self.held.append((cmd.seq, cmd.name))
            else:
                self._reply(proto.encode_ack(cmd.seq, cmd.name))

    def release(self) -> None:
        held, self.held = self.held, []
        for seq, name in held:
            self._reply(proto.encode_ack(seq, name))

    def _reply(self, frame: bytes) -> None:
        with self._cond:
            self._out += frame
            self._cond.notify()

    def names(self) -> list[str]:
        return [name for _t, name, _a in self.log if name != "heartbeat"]

    def time_of(self, name: str) -> float:
        return next(t for t, n, _a in self.log if n == name)


@pytest.fixture
def linarm(qtbot) -> Iterator[tuple[LinarmDriver, ScriptedController, SafetySupervisor]]:
    controller = ScriptedController()
    supervisor = SafetySupervisor(SafetyConfig())
    driver = LinarmDriver(controller, supervisor, command_timeout_s=1.0, heartbeat_period_s=0.05)  # type: ignore[arg-type]
    driver.start()
    qtbot.waitUntil(lambda: driver.connected, timeout=3000)
    yield driver, controller, supervisor
    driver.stop()


def test_a_command_submitted_while_another_is_in_flight_is_written_after_its_ack(linarm, qtbot) -> None:
    driver, controller, _ = linarm
    controller.hold = {"resetError"}
    first = driver.submit("resetError", source="test")
    second = driver.submit("setDemo", False, source="test")
    qtbot.waitUntil(lambda: bool(controller.held), timeout=2000)
    qtbot.wait(100)  # the second must not go while the first awaits its ACK
    assert "setDemo" not in controller.names() and not second.written and not first.done()
    released_at = time.monotonic()
    controller.release()
    assert first.result(2.0) == {} and second.result(2.0) == {}
    assert controller.time_of("setDemo") >= released_at
    assert controller.names()[-2:] == ["resetError", "setDemo"]


def test_the_estop_passes_a_command_in_flight(linarm, qtbot) -> None:
    driver, controller, _ = linarm
    controller.hold = {"resetError"}
    pending = driver.submit("resetError", source="test")
    queued = driver.submit("setDemo", False, source="test")
    qtbot.waitUntil(lambda: bool(controller.held), timeout=2000)
    t0 = time.monotonic()
    status = driver.emergency_idle("test")  # returns once written
    assert time.monotonic() - t0 < ESTOP_WRITE_BOUND_S and status.written
    idle = [(t, a) for t, n, a in controller.log if n == "setCtrlState"]
    assert idle and idle[-1][1]["controlState"] == IDLE
    assert not pending.done() and not queued.written, "the IDLE waited for nothing and overtook nothing else"
    controller.release()
    assert pending.result(2.0) == {} and queued.result(2.0) == {}


def test_the_heartbeat_keeps_beating_while_a_command_waits_for_its_ack(linarm, qtbot) -> None:
    driver, controller, _ = linarm
    controller.hold = {"resetError"}
    pending = driver.submit("resetError", source="test")
    qtbot.waitUntil(lambda: bool(controller.held), timeout=2000)
    t0 = time.monotonic()
    qtbot.wait(400)  # 0.4 s > the controller's 250 ms watchdog
    beats = [t for t, n, _a in controller.log if n == "heartbeat" and t >= t0]
    assert len(beats) >= 4, f"{len(beats)} heartbeats in 0.4 s while a command awaited its ACK"
    assert not pending.done()
    controller.release()
    assert pending.result(2.0) == {}


def test_a_timed_out_command_resyncs_the_parser_and_fails_its_status(linarm, qtbot) -> None:
    driver, controller, _ = linarm
    controller.hold = {"resetError"}
    with pytest.raises(LinarmTimeout):
        driver.command("resetError", source="test", timeout_s=0.1)
    qtbot.waitUntil(lambda: controller.names()[-1:] == [";"], timeout=1000)
    controller.hold = set()
    assert driver.command("setDemo", False, source="test") == {}  # the queue is free again


def test_a_refusal_is_a_failed_status_and_nothing_is_sent(linarm) -> None:
    driver, controller, supervisor = linarm
    events: list[tuple[str, dict]] = []
    supervisor.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    before = len(controller.names())
    status = driver.submit("moveCentreTo", 0.49, 0.1, 0.1, 0.0, False, source="test")
    assert isinstance(status.exception(0), SafetyError) and not status.written
    assert len(controller.names()) == before
    assert driver.command("setDemo", False, source="test") == {}
    assert ("robot_command", {"source": "test", "command": "setDemo", "args": {"demo": False}, "ok": True}) in events


def test_the_estop_without_a_link_raises_transport_error(qtbot) -> None:
    driver = LinarmDriver(ScriptedController(), SafetySupervisor(SafetyConfig()))  # type: ignore[arg-type]
    with pytest.raises(TransportError):
        driver.emergency_idle("test")
