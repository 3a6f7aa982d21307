"""The VR link: the manager's task, the stand-in game's rules, and both over loopback UDP."""

from __future__ import annotations

import math
import socket
import time
from dataclasses import dataclass

import pytest

from app.core import streams
from app.core.bus import StreamBus
from app.devices.linarm import VSA_STREAM
from app.devices.patient_model import LinkInputs, free_udp_port
from app.devices.sim.vr_standin import StandinGame
from app.devices.transport import UdpTransport
from app.devices.vr import VrDriver, VrTask, standin_process
from app.ui.vr_standin_window import make_window
from app.wire.udp_frames import (
    TaskData,
    TaskFlag,
    TaskState,
    VrEvent,
    VrEventFrame,
    VrFrame,
    encode_vr_event,
)

HOST = "127.0.0.1"


def frame(subtask: int, state: TaskState, pos: float, target: float, t_in: float = math.nan) -> VrFrame:
    return VrFrame(0, 0.0, 0.0, 0.0, pos, target, TaskData(subtask, state, 0, t_in, 0))


# ------------------------------------------------------------------ the stand-in's rules


def test_game_reaches_a_target_after_the_hold_time_once() -> None:
    g = StandinGame(tolerance_m=0.01, hold_s=0.3, time_limit_s=12.0)
    started = g.on_frame(frame(0, TaskState.MOVING, 0.2, 0.4), 0.0)
    assert [e.event for e in started] == [VrEvent.SUBTASK_STARTED]
    assert g.on_frame(frame(0, TaskState.HOLDING, 0.405, 0.4), 1.0) == []
    assert g.on_frame(frame(0, TaskState.HOLDING, 0.405, 0.4), 1.2) == []
    [ev] = g.on_frame(frame(0, TaskState.HOLDING, 0.401, 0.4), 1.31)
    assert ev.event == VrEvent.TARGET_REACHED and ev.subTask == 0
    assert ev.timeToTarget == pytest.approx(1.31)
    assert ev.score == 100 + 43  # 50 - 5 · 1.31 s, rounded
    assert g.on_frame(frame(0, TaskState.REACHED, 0.4, 0.4), 1.5) == []


def test_leaving_the_target_restarts_the_hold() -> None:
    g = StandinGame(hold_s=0.3)
    g.on_frame(frame(2, TaskState.MOVING, 0.395, 0.4), 0.0)
    g.on_frame(frame(2, TaskState.MOVING, 0.37, 0.4), 0.2)
    assert g.on_frame(frame(2, TaskState.MOVING, 0.4, 0.4), 0.4) == []
    assert g.on_frame(frame(2, TaskState.MOVING, 0.4, 0.4), 0.6) == []
    assert [e.event for e in g.on_frame(frame(2, TaskState.MOVING, 0.4, 0.4), 0.71)] == [VrEvent.TARGET_REACHED]


def test_game_misses_a_target_after_the_time_limit() -> None:
    g = StandinGame(time_limit_s=2.0)
    g.on_frame(frame(5, TaskState.MOVING, 0.1, 0.4, t_in=0.0), 0.0)
    assert g.on_frame(frame(5, TaskState.MOVING, 0.1, 0.4, t_in=1.9), 1.9) == []
    [ev] = g.on_frame(frame(5, TaskState.MOVING, 0.1, 0.4, t_in=2.05), 2.05)
    assert ev.event == VrEvent.TARGET_MISSED and ev.score == 0
    assert g.missed == 1


def test_game_sends_the_score_once_a_second() -> None:
    g = StandinGame()
    assert [e.event for e in g.tick(10.0)] == [VrEvent.SCORE]
    assert g.tick(10.5) == []
    assert len(g.tick(11.01)) == 1


# ------------------------------------------------------------------ the manager's task


def test_task_advances_to_the_next_target_after_the_rest() -> None:
    task = VrTask((0.10, 0.40), rest_s=0.5)
    task.tick(0.0, 0.3)
    target, data = task.snapshot(0.0)
    assert (target, data.subTask, data.taskState) == (0.10, 0, TaskState.MOVING)
    task.tick(1.0, 0.101)
    assert task.snapshot(1.0)[1].taskState == TaskState.HOLDING
    assert task.snapshot(1.0)[1].taskFlags & TaskFlag.IN_TARGET
    task.on_event(VrEventFrame(1, VrEvent.TARGET_REACHED, 0, 140, 1.0), 1.2)
    assert task.snapshot(1.3)[1].taskState == TaskState.REACHED and task.targetsReached == 1
    task.tick(1.5, 0.1)
    assert task.snapshot(1.5)[1].taskState == TaskState.REACHED  # still resting
    task.tick(1.71, 0.1)
    target, data = task.snapshot(1.71)
    assert (target, data.subTask, data.taskState, data.score) == (0.40, 1, TaskState.MOVING, 140)


def test_task_ignores_events_for_another_subtask() -> None:
    task = VrTask()
    task.tick(0.0, 0.3)
    task.on_event(VrEventFrame(1, VrEvent.TARGET_REACHED, 7, 100, 1.0), 0.5)
    assert task.targetsReached == 0 and task.snapshot(0.5)[1].taskState == TaskState.MOVING


# ------------------------------------------------------------------ over UDP with the stand-in process


@dataclass
class Vsa:
    handlePos: float = 0.25
    handleVel: float = 0.0
    interactionForce: float = 0.0


class FakeLinarm:
    """The LINarm as the VR frames read it: its link up (its driver), its VSA samples on the bus."""

    connected, silent = True, False

    def __init__(self, bus: StreamBus) -> None:
        self.bus = bus
        bus.declare([VSA_STREAM])
        self.sample = Vsa()

    @property
    def sample(self) -> Vsa:
        return self.bus.latest(streams.LINARM_VSA)

    @sample.setter
    def sample(self, value: Vsa) -> None:
        self.bus.publish(streams.LINARM_VSA, time.monotonic(), value)


class FakeDevices:
    """The other devices of the VR link: the LINarm only, no assistance controller, no supervisor."""

    def __init__(self) -> None:
        self.bus = StreamBus()
        self.linarm = FakeLinarm(self.bus)
        self.inputs = LinkInputs(self.bus, {streams.LINARM: self.linarm})


@pytest.fixture
def vr_link(qtbot):
    manager_port, standin_port = free_udp_port(HOST), free_udp_port(HOST)
    proc = standin_process(HOST, standin_port, manager_port, extra=["--hold", "0.1", "--time-limit", "30"])
    manager = FakeDevices()
    driver = VrDriver(UdpTransport((HOST, manager_port), (HOST, standin_port)), 50.0, inputs=manager.inputs,
                      bus=manager.bus, task=VrTask((0.10, 0.40), rest_s=0.2))
    proc.start()
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=10000)
        yield driver, manager, proc
    finally:
        driver.stop()
        proc.stop()


def test_frames_go_out_at_50_hz_and_the_heartbeat_keeps_the_link_up(qtbot, vr_link) -> None:
    driver, _manager, proc = vr_link
    n0, t0 = driver.datagrams_sent, time.monotonic()
    qtbot.waitUntil(lambda: time.monotonic() - t0 >= 2.0, timeout=4000)
    rate = (driver.datagrams_sent - n0) / (time.monotonic() - t0)
    assert 45.0 <= rate <= 55.0, rate
    assert driver.connected and proc.poll() is None
    assert driver.latest("vr.main").lastEvent in ("SCORE", "SUBTASK_STARTED", "HELLO")


def test_reaching_the_targets_scores_and_alternates_them(qtbot, vr_link) -> None:
    driver, manager, _proc = vr_link
    seen: list[float] = []
    for _ in range(3):
        target, _data = driver.task_snapshot()
        seen.append(target)
        reached = driver.task.targetsReached
        manager.linarm.sample = Vsa(handlePos=target)
        qtbot.waitUntil(lambda reached=reached: driver.task.targetsReached == reached + 1, timeout=5000)
        qtbot.waitUntil(lambda target=target: driver.task_snapshot()[0] != target, timeout=5000)
    assert seen == [0.10, 0.40, 0.10]
    qtbot.waitUntil(lambda: driver.latest("vr.main").targetsReached == 3, timeout=2000)
    s = driver.latest("vr.main")
    assert s.score >= 300 and s.timeToTarget < 5.0


def test_events_from_a_foreign_sender_are_dropped_and_counted(qtbot, vr_link) -> None:
    driver, _manager, _proc = vr_link
    port = driver.udp.local_address[1]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stray:
        stray.sendto(encode_vr_event(VrEventFrame(1, VrEvent.TARGET_REACHED, 0, 9999, 0.5)), (HOST, port))
        qtbot.waitUntil(lambda: driver.dropped_foreign == 1, timeout=3000)
    assert driver.task.score < 9999 and driver.task.targetsReached == 0


def test_standin_window_draws_offscreen(qtbot) -> None:
    g = StandinGame()
    g.on_frame(frame(0, TaskState.MOVING, 0.2, 0.4), 0.0)
    win = make_window(g)
    qtbot.addWidget(win)
    win.resize(520, 160)
    image = win.grab().toImage()
    assert image.width() == 520
    centre = image.pixelColor(int(30 + 460 * 0.4 / 0.5), int(160 * 0.6))  # the target zone
    assert (centre.red(), centre.green(), centre.blue()) == (0xF0, 0xA0, 0x30)


def test_vr_viewer_shows_the_sample(qtbot) -> None:
    from app.devices.vr import VrSample
    from app.ui.vr_viewer import VrViewer

    viewer = VrViewer()
    qtbot.addWidget(viewer)
    viewer.show_sample(VrSample(targetPos=0.4, score=245.0, targetsReached=2.0, targetsMissed=1, subTask=3,
                                taskState=int(TaskState.REACHED), handlePos=0.398, lastEvent="TARGET_REACHED",
                                timeToTarget=1.25, packetRateOut=50.0, packetRateIn=2.0))
    assert viewer.fields["target"].text() == "400 mm"
    assert viewer.fields["score"].text() == "245"
    assert viewer.fields["targets"].text() == "2 reached, 1 missed"
    assert "1.25 s" in viewer.fields["event"].text()
    assert viewer.rail.reached and viewer.rail.target == 0.4
