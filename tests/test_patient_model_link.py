"""The patient-model link end to end: the driver and the embedded model as its own process over
loopback UDP; plus the model's sub-task judge and the process's own dropping and exit rules."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import pytest

from app.core import streams
from app.core.bus import StreamBus
from app.core.config import AppConfig
from app.devices.linarm import VSA_STREAM
from app.devices.patient_model import (
    DeviceFrameSource,
    LinkInputs,
    PatientModelDriver,
    embedded_process,
    free_udp_port,
    path_text,
)
from app.devices.physio import PHYSIO_STREAM
from app.devices.sim.patient_model.decision_tree import DecisionTree
from app.devices.sim.patient_model.process import EmbeddedPatientModel, ParentWatch, SubtaskJudge, serve
from app.devices.transport import UdpTransport
from app.safety.assistance import AssistanceSplit
from app.wire.udp_frames import (
    PatientModelFrame,
    PatientModelReply,
    TaskData,
    TaskState,
    decode_patient_model_reply,
    encode_patient_model_frame,
    encode_patient_model_reply,
)

HOST = "127.0.0.1"


# ------------------------------------------------------------------ fakes of the other devices


@dataclass
class PhysioSample:
    heartRate: float = 72.0
    skinConductance: float = 5.0
    temperature: float = 33.0
    force: float = 2.0


@dataclass
class VsaSample:
    handlePos: float = 0.10
    handleVel: float = 0.0
    interactionForce: float = 0.0


class FakeLink:
    """Another device's link state, as its driver reports it."""

    def __init__(self) -> None:
        self.connected, self.silent = True, False


def fake_inputs() -> LinkInputs:
    """The other devices as the frames read them: their latest samples on the bus, their links up."""
    bus = StreamBus()
    bus.declare([PHYSIO_STREAM, VSA_STREAM])
    bus.publish(streams.PHYSIO_MAIN, 0.0, PhysioSample())
    bus.publish(streams.LINARM_VSA, 0.0, VsaSample())
    return LinkInputs(bus, {streams.PHYSIO: FakeLink(), streams.LINARM: FakeLink()})


class ScriptedTask:
    """The task data the test steers: (target, sub-task index, state)."""

    def __init__(self) -> None:
        self.target = 0.40
        self.task = TaskData()

    def set(self, subtask: int, state: TaskState) -> None:
        self.task = TaskData(subtask, state, 0, math.nan, 0)

    def __call__(self) -> tuple[float, TaskData]:
        return self.target, self.task


@pytest.fixture
def link(qtbot):
    manager_port, model_port = free_udp_port(HOST), free_udp_port(HOST)
    proc = embedded_process(HOST, model_port, manager_port, extra=["--idle-exit", "5"])
    split = AssistanceSplit(AppConfig().assistance)
    inputs = fake_inputs()
    driver = PatientModelDriver(UdpTransport((HOST, manager_port), (HOST, model_port)), 100.0,
                                split=lambda a: (lambda t: (t.a_r, t.a_f))(split.compute(a, 0.5, 0.5)),
                                bus=inputs.bus)
    driver.frame_source = DeviceFrameSource(inputs, driver)
    task = ScriptedTask()
    driver.task_source = task
    driver.clinical_score = 40
    proc.start()
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.connected, timeout=10000)
        yield driver, task, inputs, proc
    finally:
        driver.stop()
        proc.stop()


def latest(driver: PatientModelDriver):
    return driver.latest("patient_model.main")


def wait_for_reply_to_current(qtbot, driver: PatientModelDriver) -> None:
    """Wait until a reply acknowledges a frame sent after this call (so it reflects the current inputs)."""
    sent = driver.datagrams_sent
    qtbot.waitUntil(lambda: latest(driver) is not None and latest(driver).ackSeq >= sent + 1, timeout=3000)


# ------------------------------------------------------------------ end to end


def test_alpha_arrives_at_about_100_hz(qtbot, link) -> None:
    driver, _task, _manager, proc = link
    assert proc.poll() is None
    n0, t0 = driver.datagrams_received, time.monotonic()
    qtbot.waitUntil(lambda: time.monotonic() - t0 >= 2.0, timeout=4000)
    rate = (driver.datagrams_received - n0) / (time.monotonic() - t0)
    assert 90.0 <= rate <= 110.0, rate
    s = latest(driver)
    assert -1.0 <= s.alpha <= 1.0
    q15 = 1.0 / 32767  # the range travels as Q15
    assert s.alphaMin - q15 <= s.alpha <= s.alphaMax + q15
    assert s.path.startswith("in_between/")  # clinical score 40
    assert s.a_r == pytest.approx(0.5 * s.alpha)
    assert 0.0 <= s.roundTrip < 0.1
    assert sum(driver.invalid_datagrams.values()) == 0 and driver.dropped_foreign == 0


def test_changing_the_clinical_score_moves_alpha_to_another_group(qtbot, link) -> None:
    driver, _task, _manager, _proc = link
    driver.clinical_score = 10
    qtbot.waitUntil(lambda: latest(driver).group == "assist", timeout=3000)
    assist = latest(driver)
    q15 = 1.0 / 32767
    assert 0.2 - q15 <= assist.alphaMin <= assist.alpha + q15 and assist.alpha <= 1.0
    driver.clinical_score = 60
    qtbot.waitUntil(lambda: latest(driver).group == "resist", timeout=3000)
    resist = latest(driver)
    assert -1.0 <= resist.alpha <= resist.alphaMax + q15 and resist.alphaMax <= q15
    assert resist.alpha < assist.alpha


def test_failed_subtasks_raise_alpha_as_the_tree_says(qtbot, link) -> None:
    driver, task, _manager, _proc = link
    wait_for_reply_to_current(qtbot, driver)
    before = latest(driver)
    assert before.level == 0.0
    alphas = [before.alpha]
    for i in range(3):
        task.set(i, TaskState.MOVING)
        wait_for_reply_to_current(qtbot, driver)
        task.set(i, TaskState.FAILED)
        qtbot.waitUntil(lambda i=i: latest(driver).level == pytest.approx(0.2 * (i + 1), abs=0.005),
                        timeout=3000)
        alphas.append(latest(driver).alpha)
    s = latest(driver)
    assert s.tpi == 0.0  # three failures: no success, no time credit
    assert "/tpi_low/" in s.path  # poor task performance: the more-support branch
    assert alphas == sorted(alphas) and alphas[-1] > alphas[0]
    tree = DecisionTree()
    tree.level = s.level
    expected = tree.decide(40, s.tpi, s.mpi, s.pti)
    assert s.alpha == pytest.approx(expected.alpha, abs=1e-5)
    assert (s.alphaMin, s.alphaMax) == pytest.approx(expected.alphaRange, abs=1e-4)
    assert s.path == expected.leaf

    # A success lowers the support level by step_down.
    task.set(3, TaskState.MOVING)
    wait_for_reply_to_current(qtbot, driver)
    task.set(3, TaskState.REACHED)
    qtbot.waitUntil(lambda: latest(driver).level == pytest.approx(0.5, abs=0.005), timeout=3000)
    assert latest(driver).tpi > 0.0


def test_foreign_and_malformed_datagrams_are_dropped_and_counted(qtbot) -> None:
    """A test socket plays the model so it can also send malformed replies from the right address."""
    manager_port = free_udp_port(HOST)
    model = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stray = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    model.bind((HOST, 0))
    stray.bind((HOST, 0))
    driver = PatientModelDriver(UdpTransport((HOST, manager_port), model.getsockname()), 100.0)
    driver.frame_source = lambda seq: PatientModelFrame(seq, 70, 5, 33, 2, 0, 0, 0.1, 0.4)
    driver.start()
    good = encode_patient_model_reply(PatientModelReply(1, 0, 0.3, 0.5, 0.5, 0.0, 0.2, 0.6, 12, 0.0))
    try:
        qtbot.waitUntil(lambda: driver.datagrams_sent > 0, timeout=3000)
        stray.sendto(encode_patient_model_reply(PatientModelReply(1, 0, -0.9, 0.5, 0.5, 0.0, -1, 0, 2, 0)),
                     (HOST, manager_port))
        model.sendto(good[:-1], (HOST, manager_port))
        model.sendto(good + b"\0", (HOST, manager_port))
        model.sendto(good[:-2] + bytes([good[-2] ^ 0xFF, good[-1]]), (HOST, manager_port))
        model.sendto(good, (HOST, manager_port))
        qtbot.waitUntil(lambda: driver.datagrams_received == 1, timeout=3000)
        qtbot.waitUntil(lambda: driver.dropped_foreign == 1, timeout=3000)
        assert driver.invalid_datagrams == {"size": 2, "crc": 1}
        assert driver.dropped_total == 4
        assert latest(driver).alpha == pytest.approx(0.3)  # the stray -0.9 never got through
        assert driver.connected
    finally:
        driver.stop()
        model.close()
        stray.close()


# ------------------------------------------------------------------ the process on its own


class _NeverGone(ParentWatch):
    def parent_gone(self) -> bool:
        return False


def test_the_process_drops_foreign_and_malformed_frames_and_answers_valid_ones() -> None:
    model_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    manager = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stray = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for s in (model_sock, manager, stray):
        s.bind((HOST, 0))
    manager.settimeout(3.0)
    result: dict[str, int] = {}
    th = threading.Thread(target=lambda: result.update(
        serve(model_sock, manager.getsockname(), EmbeddedPatientModel(), 0.5, _NeverGone())))
    th.start()
    try:
        frame = encode_patient_model_frame(PatientModelFrame(7, 70, 5, 33, 2, 0, 0, 0.1, 0.4, clinicalScore=60))
        stray.sendto(frame, model_sock.getsockname())
        manager.sendto(frame[:39], model_sock.getsockname())
        manager.sendto(frame, model_sock.getsockname())
        reply = decode_patient_model_reply(manager.recv(64))
        assert reply.ackSeq == 7
        assert path_text(reply.path).startswith("resist/")
        th.join(timeout=5.0)  # idle for 0.5 s: serve returns
        assert not th.is_alive()
        assert result == {"frames": 1, "replies": 1, "foreign": 1, "invalid": 1, "replay": 0}
    finally:
        th.join(timeout=5.0)
        for s in (model_sock, manager, stray):
            s.close()


def test_the_process_exits_when_no_frame_comes() -> None:
    proc = embedded_process(HOST, free_udp_port(HOST), free_udp_port(HOST), extra=["--idle-exit", "0.5"])
    proc.start()
    try:
        assert proc.wait(timeout=15.0) == 0
    finally:
        proc.stop()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_process_exits_when_its_parent_dies() -> None:
    code = ("import os, subprocess, sys;"
            "p = subprocess.Popen([sys.executable, '-m', 'app.devices.sim.patient_model.process',"
            " '--listen', sys.argv[1],"
            " '--peer', sys.argv[2], '--idle-exit', '0', '--parent-pid', str(os.getpid())], stdout=subprocess.DEVNULL,"
            " stderr=subprocess.DEVNULL);"
            "print(p.pid, flush=True)")
    args = [f"{HOST}:{free_udp_port(HOST)}", f"{HOST}:{free_udp_port(HOST)}"]
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=30,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))), check=True)
    pid = int(out.stdout.split()[0])

    def gone() -> bool:
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] == "Z"  # a zombie nobody reaps
        except FileNotFoundError:
            return True

    deadline = time.monotonic() + 15.0
    try:
        while not gone() and time.monotonic() < deadline:
            time.sleep(0.05)  # polling another process's state: there is no event to wait on
        assert gone()
    finally:
        if not gone():
            os.kill(pid, 9)


def test_the_manager_starts_and_stops_the_embedded_model(qtbot) -> None:
    from app.devices import patient_model
    from app.manager import LinarmppManager

    manager = LinarmppManager(AppConfig(), factories={"patient_model": patient_model.create})
    manager.start()
    handle = manager.devices["patient_model"]
    proc = handle.extras["processes"][0]
    try:
        assert handle.simulated
        qtbot.waitUntil(lambda: handle.driver.latest("patient_model.main") is not None, timeout=10000)
        assert handle.driver.connected
    finally:
        manager.shutdown()
        proc.stop()
    assert proc.poll() is not None


# ------------------------------------------------------------------ the sub-task judge alone


def _frame(subtask: int, state: TaskState, pos: float = 0.2, target: float = 0.4,
           t_in: float = math.nan) -> PatientModelFrame:
    return PatientModelFrame(0, 70, 5, 33, 2, 0, 0, pos, target, TaskData(subtask, state, 0, t_in, 0))


def test_judge_reports_each_subtask_once() -> None:
    j = SubtaskJudge(time_limit_s=12.0, tolerance_m=0.01)
    assert j.feed(_frame(0, TaskState.IDLE), 0.0) == (None, False)
    assert j.feed(_frame(1, TaskState.MOVING), 1.0) == (None, True)
    r, _ = j.feed(_frame(1, TaskState.REACHED), 3.5)
    assert r is not None and r.success and r.duration == pytest.approx(2.5) and r.reason == "reached"
    assert j.feed(_frame(1, TaskState.REACHED), 3.6) == (None, False)  # the rest period repeats the state


def test_judge_fails_a_subtask_after_the_time_limit() -> None:
    j = SubtaskJudge(time_limit_s=2.0, tolerance_m=0.01)
    j.feed(_frame(4, TaskState.MOVING, t_in=0.0), 0.0)
    assert j.feed(_frame(4, TaskState.MOVING, t_in=1.9), 1.9)[0] is None
    r, _ = j.feed(_frame(4, TaskState.MOVING, t_in=2.1), 2.1)
    assert r is not None and not r.success and r.reason == "time limit"


def test_judge_an_abandoned_subtask_by_the_last_position() -> None:
    j = SubtaskJudge(time_limit_s=12.0, tolerance_m=0.01)
    j.feed(_frame(0, TaskState.MOVING), 0.0)
    j.feed(_frame(0, TaskState.HOLDING, pos=0.395), 1.0)
    r, started = j.feed(_frame(1, TaskState.MOVING), 1.5)
    assert r is not None and r.success and r.reason == "abandoned" and started
    r, _ = j.feed(_frame(2, TaskState.MOVING), 2.0)
    assert r is not None and not r.success


def test_missing_clinical_score_uses_the_default_and_flags_fallback() -> None:
    model = EmbeddedPatientModel(default_clinical_score=10)
    reply = model.on_frame(_frame(0, TaskState.IDLE), 0.0)
    assert path_text(reply.path).startswith("assist/")
    assert reply.flags & 0x02
