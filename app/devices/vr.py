"""The VR renderer link: 32-byte frames out at ``rate_hz`` (50 Hz), the game's events in.

Who decides what (the protocol as we define it; the codec is app.wire.udp_frames):

* The manager owns the exercise's target sequence (``VrTask``; default alternating 0.10 / 0.40 m):
  every frame carries the current target, the sub-task index and state, the time in the sub-task
  and the score, with the handle's position, velocity and force and the α being applied.  The
  manager must know the target — the LINarm's assistive controller pulls toward it and the patient
  model judges sub-tasks against it — and the event frame carries no position, so the target
  cannot come from the game.
* The renderer (the Unity game, or our stand-in) is the judge: it says when the target is reached
  (handle held within its tolerance for its hold time) or missed (time limit), keeps the game score,
  sends ``SUBTASK_STARTED`` when it sees a new sub-task index, and sends a ``SCORE`` event at least
  once a second — the heartbeat by which ``connected`` is judged (a valid event within 2.5 s).
* On ``TARGET_REACHED`` / ``TARGET_MISSED`` for the current sub-task the manager shows REACHED /
  FAILED for ``rest_s`` (0.5 s), then starts the next sub-task with the next target.

Modes: ``standin`` (default) runs ``python -m app.devices.sim.vr_standin`` as a separate process on loopback
ports chosen at start — headless, so nothing pops up; set the environment variable
``LINARMPP_VR_WINDOW=1`` to have it open its small window showing the target and the handle.
``external`` talks to a renderer at ``peer_host:peer_port``; ``off`` disables the link.
(``embedded`` is treated as ``standin``.)

Published on "vr.main" at the frame rate: ``VrSample`` (targetPos m, score, targetsReached, and
what the script API's ``VRUnity.VRUnityData`` reads: sub-task, state, last event, time to target,
packet rates).
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from app.core import streams
from app.core.bus import Channel, StreamBus, StreamSpec
from app.devices.clock import CountedClock
from app.devices.patient_model import (
    HelperProcess,
    LinkInputs,
    PatientModelDriver,
    UdpPeerDriver,
    free_udp_port,
    link_key,
    read_inputs,
    warn_if_plain,
)
from app.devices.transport import DatagramTransport, UdpTransport
from app.wire.udp_frames import (
    TaskData,
    TaskFlag,
    TaskState,
    VrEvent,
    VrEventFrame,
    VrFrame,
    decode_vr_event,
    encode_vr_frame,
)

if TYPE_CHECKING:
    from app.devices.registry import DeviceContext, DeviceHandle
    from app.safety.assistance import AssistanceLevels

NAN = math.nan

VR_STREAM = StreamSpec(streams.VR_MAIN, (
    Channel("targetPos", "m", "Target position"),
    Channel("score", "", "Game score"),
    Channel("targetsReached", "", "Targets reached"),
), 50.0)

DEFAULT_TARGETS = (0.10, 0.40)
WINDOW_ENV = "LINARMPP_VR_WINDOW"


@dataclass(frozen=True)
class VrSample:
    targetPos: float       # m
    score: float
    targetsReached: float
    targetsMissed: int
    subTask: int
    taskState: int         # TaskState
    handlePos: float       # m (NaN when the LINarm is not connected)
    lastEvent: str         # VrEvent name of the last event ("" before any)
    timeToTarget: float    # s, of the last reached target (NaN before any)
    packetRateOut: float   # frames/s to the renderer
    packetRateIn: float    # events/s from the renderer


class VrTask:
    """The manager's side of the exercise: target sequence, sub-task index and state.  Thread-safe."""

    def __init__(self, targets: tuple[float, ...] = DEFAULT_TARGETS, rest_s: float = 0.5,
                 tolerance_m: float = 0.01) -> None:
        if not targets:
            raise ValueError("the target sequence is empty")
        self._lock = threading.Lock()
        self.targets = tuple(float(x) for x in targets)
        self.rest_s = rest_s
        self.tolerance_m = tolerance_m
        self.running = True
        self.subTask = 0
        self.state = TaskState.MOVING
        self.score = 0
        self.targetsReached = 0
        self.targetsMissed = 0
        self.lastEvent = ""
        self.timeToTarget = NAN
        self.handlePos = NAN
        self._t_start: float | None = None
        self._t_state = 0.0

    @property
    def target(self) -> float:
        return self.targets[self.subTask % len(self.targets)]

    def set_running(self, running: bool, now: float | None = None) -> None:
        with self._lock:
            self.running = running
            if running and self.state == TaskState.IDLE:
                self._start_next(time.monotonic() if now is None else now, advance=False)
            elif not running:
                self.state = TaskState.IDLE

    def set_targets(self, targets: tuple[float, ...]) -> None:
        if not targets:
            raise ValueError("the target sequence is empty")
        with self._lock:
            self.targets = tuple(float(x) for x in targets)

    def _start_next(self, now: float, advance: bool = True) -> None:
        if advance:
            self.subTask = (self.subTask + 1) & 0xFFFF
        self.state = TaskState.MOVING
        self._t_start = now
        self._t_state = now

    def tick(self, now: float, handle_pos: float) -> None:
        with self._lock:
            self.handlePos = handle_pos
            if self._t_start is None:
                self._t_start = now
            if self.state in (TaskState.REACHED, TaskState.FAILED) and now - self._t_state >= self.rest_s:
                if self.running:
                    self._start_next(now)
            elif self.state in (TaskState.MOVING, TaskState.HOLDING):
                inside = math.isfinite(handle_pos) and abs(handle_pos - self.target) <= self.tolerance_m
                self.state = TaskState.HOLDING if inside else TaskState.MOVING

    def on_event(self, ev: VrEventFrame, now: float) -> None:
        with self._lock:
            self.lastEvent = ev.event.name
            if ev.event in (VrEvent.TARGET_REACHED, VrEvent.TARGET_MISSED, VrEvent.SCORE):
                self.score = ev.score
            current = ev.subTask == self.subTask and self.state in (TaskState.MOVING, TaskState.HOLDING)
            if ev.event == VrEvent.TARGET_REACHED and current:
                self.state, self._t_state = TaskState.REACHED, now
                self.targetsReached += 1
                self.timeToTarget = ev.timeToTarget
            elif ev.event == VrEvent.TARGET_MISSED and current:
                self.state, self._t_state = TaskState.FAILED, now
                self.targetsMissed += 1

    def snapshot(self, now: float | None = None) -> tuple[float, TaskData]:
        """(target m, task data) for the UDP frames."""
        with self._lock:
            now = time.monotonic() if now is None else now
            flags = 0
            if math.isfinite(self.handlePos) and abs(self.handlePos - self.target) <= self.tolerance_m:
                flags |= TaskFlag.IN_TARGET
            t_in = now - self._t_start if self._t_start is not None and self.state != TaskState.IDLE else NAN
            return self.target, TaskData(self.subTask, self.state, int(flags), t_in, min(self.score, 0xFFFF))


class VrDriver(UdpPeerDriver):
    streams = (VR_STREAM,)

    def __init__(self, transport: DatagramTransport, rate_hz: float = 50.0, *,
                 inputs: LinkInputs | None = None, assistance: AssistanceLevels | None = None,
                 task: VrTask | None = None, process: HelperProcess | None = None,
                 bus: StreamBus | None = None, alive_timeout_s: float = 2.5,
                 key: bytes | None = None) -> None:
        super().__init__(streams.VR, transport, rate_hz, alive_timeout_s=alive_timeout_s, process=process,
                         bus=bus, key=key)
        self.inputs = inputs  # the other devices' samples for the frames (None: NaN, no flags)
        self.assistance = assistance  # the α being applied (None: the patient model's last α on the bus)
        self.task = task or VrTask()
        self._seq = 0
        self.events_received = 0
        # The frames' own schedule, dejittered on their sequence number (app.devices.clock): a catch-up after a
        # late pass sends several frames at one instant, but each stands for its own period.
        self.clock = CountedClock(rate_hz, wrap=0x10000)

    def task_snapshot(self) -> tuple[float, TaskData]:
        """The task as the patient model's frames carry it (any thread)."""
        return self.task.snapshot()

    def _alpha(self) -> float:
        alpha = self.assistance.alpha if self.assistance is not None else None
        if alpha is None:
            sample = self.bus.latest(streams.PATIENT_MODEL_MAIN)
            alpha = getattr(sample, "alpha", None)
        if alpha is None or math.isnan(alpha):
            return 0.0
        return min(1.0, max(-1.0, float(alpha)))

    def build_datagram(self, now: float) -> bytes | None:
        p = v = None
        flags = 0
        if self.inputs is not None:
            inp = read_inputs(self.inputs)
            p, v, flags = inp.physio, inp.vsa, inp.flags
        handle = _num(v, "handlePos")
        self.task.tick(now, handle)
        target, task = self.task.snapshot(now)
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFFFF
        data = encode_vr_frame(VrFrame(
            seq=seq, force=_num(p, "force"), interactionForce=_num(v, "interactionForce"),
            robotVelocity=_num(v, "handleVel"), robotPosition=handle, targetPosition=target, task=task,
            alpha=self._alpha(), flags=flags))
        t = self.task
        self.publish(streams.VR_MAIN, self.clock.map(now, seq), VrSample(
            targetPos=target, score=float(t.score), targetsReached=float(t.targetsReached),
            targetsMissed=t.targetsMissed, subTask=task.subTask, taskState=int(task.taskState),
            handlePos=handle, lastEvent=t.lastEvent, timeToTarget=t.timeToTarget,
            packetRateOut=self.packet_rate_out, packetRateIn=self.packet_rate_in), now)
        return data

    def handle_datagram(self, data: bytes, t: float) -> None:
        ev = decode_vr_event(data)
        self.check_seq(ev.seq)
        self.events_received += 1
        self.task.on_event(ev, t)


def _num(sample: Any, name: str) -> float:
    if sample is None:
        return NAN
    try:
        return float(getattr(sample, name, NAN))
    except (TypeError, ValueError):
        return NAN


def standin_process(host: str, standin_port: int, manager_port: int, window: bool = False,
                    extra: list[str] | None = None) -> HelperProcess:
    args = ["--listen", f"{host}:{standin_port}", "--peer", f"{host}:{manager_port}", *(extra or [])]
    if window:
        args.append("--window")
    return HelperProcess("app.ui.vr_standin_window" if window else "app.devices.sim.vr_standin", args)


def create(ctx: DeviceContext) -> DeviceHandle | None:
    from app.devices.registry import DeviceHandle

    cfg = ctx.config
    if cfg.mode == "off":
        return None
    host = cfg.bind_host
    extras: dict[str, Any] = {}
    process = None
    if cfg.mode in ("standin", "embedded"):
        listen_port = cfg.listen_port or free_udp_port(host)
        peer = (host, cfg.peer_port or free_udp_port(host))
        process = standin_process(host, peer[1], listen_port, window=os.environ.get(WINDOW_ENV) == "1")
        extras.update(processes=[process], simulated=True)
    else:
        listen_port = cfg.listen_port
        peer = (cfg.peer_host, cfg.peer_port)
    if process is not None:
        process.authenticate = cfg.authenticated
    driver = VrDriver(UdpTransport((host, listen_port), peer), cfg.rate_hz,
                      inputs=LinkInputs(ctx.bus, ctx.peers, ctx.supervisor), assistance=ctx.assistance,
                      process=process, bus=ctx.bus, key=link_key(cfg))
    model = ctx.peers.get(streams.PATIENT_MODEL)
    if isinstance(model, PatientModelDriver):
        model.vr_task = driver.task_snapshot  # the patient model's frames carry the VR task
    warn_if_plain(ctx.supervisor, streams.VR, cfg)
    if process is not None:
        process.start()
    return DeviceHandle(streams.VR, driver, None, extras)
