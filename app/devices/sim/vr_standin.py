"""A stand-in for the Unity VR renderer, so the whole loop runs without Unity.

    python -m app.devices.sim.vr_standin --listen HOST:PORT --peer HOST:PORT [--window]
           [--tolerance M] [--hold S] [--time-limit S] [--idle-exit S] [--parent-pid PID]

It answers like the game (see app.devices.vr for who decides what): it shows the target the manager
sends, says ``SUBTASK_STARTED`` when a new sub-task index appears, ``TARGET_REACHED`` when the handle
has stayed within ``--tolerance`` of the target for ``--hold`` s (with the time to target and the new
score), ``TARGET_MISSED`` when the sub-task has run ``--time-limit`` s, and sends the score once a
second as the heartbeat.  Scoring: 100 points per target plus a speed bonus of up to 50 points
(50 − 5 per second taken).

Headless by default (the app starts it so); with a window (``python -m app.ui.vr_standin_window``, the same
options) a small PySide6 window draws the rail, the target zone and the handle — this module stays Qt-free.
It exits when its parent dies or when no frame has come for
``--idle-exit`` s (default 10; 0 = never).
"""

from __future__ import annotations

import argparse
import logging
import math
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from app.devices.sim.patient_model.process import ParentWatch, parse_address, take_link_key
from app.devices.transport import enlarge_receive_buffer
from app.wire.udp_frames import (
    FrameError,
    SequenceGuard,
    TaskState,
    VrEvent,
    VrEventFrame,
    VrFrame,
    decode_vr_frame,
    encode_vr_event,
    seal,
    unseal,
)

log = logging.getLogger("vr_standin")

ACTIVE = (TaskState.MOVING, TaskState.HOLDING)
HEARTBEAT_S = 1.0


@dataclass
class StandinGame:
    """The game's rules without the socket or the window (pure, testable)."""

    tolerance_m: float = 0.01
    hold_s: float = 0.3
    time_limit_s: float = 12.0
    score: int = 0
    subTask: int | None = None
    judged: set[int] = field(default_factory=set)
    last_frame: VrFrame | None = None
    reached: int = 0
    missed: int = 0
    _t0: float = 0.0
    _hold_since: float | None = None
    _seq: int = 0
    _next_heartbeat: float = 0.0

    def _event(self, kind: VrEvent, subtask: int, time_to_target: float = math.nan) -> VrEventFrame:
        self._seq = (self._seq + 1) & 0xFFFF
        return VrEventFrame(self._seq, kind, subtask & 0xFFFF, self.score, time_to_target)

    def hello(self) -> VrEventFrame:
        return self._event(VrEvent.HELLO, 0)

    def on_frame(self, frame: VrFrame, t: float) -> list[VrEventFrame]:
        self.last_frame = frame
        task = frame.task
        out: list[VrEventFrame] = []
        if task.taskState in ACTIVE and task.subTask != self.subTask and task.subTask not in self.judged:
            self.subTask, self._t0, self._hold_since = task.subTask, t, None
            out.append(self._event(VrEvent.SUBTASK_STARTED, task.subTask))
        if self.subTask is None or self.subTask in self.judged or task.subTask != self.subTask:
            return out
        elapsed = task.subTaskTime if math.isfinite(task.subTaskTime) else t - self._t0
        pos, target = frame.robotPosition, frame.targetPosition
        inside = math.isfinite(pos) and math.isfinite(target) and abs(pos - target) <= self.tolerance_m
        if inside:
            if self._hold_since is None:
                self._hold_since = t
            if t - self._hold_since >= self.hold_s:
                self.score += 100 + max(0, round(50 - 5 * elapsed))
                self.reached += 1
                self.judged.add(self.subTask)
                out.append(self._event(VrEvent.TARGET_REACHED, self.subTask, min(elapsed, 65.534)))
                return out
        else:
            self._hold_since = None
        if elapsed > self.time_limit_s:
            self.missed += 1
            self.judged.add(self.subTask)
            out.append(self._event(VrEvent.TARGET_MISSED, self.subTask))
        if len(self.judged) > 1000:  # indices wrap at 65536; keep only the recent ones
            self.judged = {self.subTask}
        return out

    def tick(self, t: float) -> list[VrEventFrame]:
        """The once-a-second score (the heartbeat)."""
        if t < self._next_heartbeat:
            return []
        self._next_heartbeat = t + HEARTBEAT_S
        return [self._event(VrEvent.SCORE, self.subTask or 0)]


class StandinLink:
    """The socket side: frames from the peer only, events back to it."""

    def __init__(self, listen: tuple[str, int], peer: tuple[str, int], game: StandinGame,
                 key: bytes | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        enlarge_receive_buffer(self.sock)
        self.sock.bind(listen)
        self.peer = peer
        self.peer_ip = socket.gethostbyname(peer[0])
        self.game = game
        self.counts = {"frames": 0, "events": 0, "foreign": 0, "invalid": 0, "replay": 0}
        self.key = key  # with a key: MAC on every datagram both ways (app.wire.udp_frames)
        self.guard = SequenceGuard()
        self.last_frame_t = time.monotonic()

    def send(self, events: list[VrEventFrame]) -> None:
        for ev in events:
            try:
                out = encode_vr_event(ev)
                self.sock.sendto(seal(self.key, out) if self.key is not None else out, self.peer)
                self.counts["events"] += 1
            except OSError:
                pass  # the manager is not listening yet

    def receive(self, timeout: float) -> None:
        """Handle at most one datagram (waiting up to ``timeout``), then the heartbeat."""
        self.sock.settimeout(timeout)
        try:
            data, sender = self.sock.recvfrom(2048)
        except (TimeoutError, BlockingIOError):
            data = None
        except OSError:
            data = None
        t = time.monotonic()
        if data is not None:
            if sender[0] != self.peer_ip or sender[1] != self.peer[1]:
                self.counts["foreign"] += 1
            else:
                try:
                    frame = decode_vr_frame(unseal(self.key, data) if self.key is not None else data)
                except FrameError:
                    self.counts["invalid"] += 1
                else:
                    if not self.guard.accept(frame.seq):
                        self.counts["replay"] += 1
                        self.send(self.game.tick(t))
                        return
                    self.counts["frames"] += 1
                    self.last_frame_t = t
                    self.send(self.game.on_frame(frame, t))
        self.send(self.game.tick(t))

    def close(self) -> None:
        self.sock.close()


def run_headless(link: StandinLink, idle_exit_s: float, watch: ParentWatch) -> None:
    while not watch.parent_gone():
        if idle_exit_s > 0 and time.monotonic() - link.last_frame_t > idle_exit_s:
            log.info("no frame for %.1f s: exiting", idle_exit_s)
            return
        link.receive(0.1)


WindowRunner = Callable[["StandinLink", float, "ParentWatch"], int]


def main(argv: list[str] | None = None, run_window: WindowRunner | None = None) -> int:
    """The stand-in's process. ``--window`` needs ``run_window`` (app.ui.vr_standin_window passes it): this
    module stays Qt-free, so the headless process never loads Qt."""
    ap = argparse.ArgumentParser(prog="python -m app.devices.sim.vr_standin", description=__doc__.splitlines()[0])
    ap.add_argument("--listen", type=parse_address, required=True, help="HOST:PORT to receive frames on")
    ap.add_argument("--peer", type=parse_address, required=True, help="HOST:PORT of the manager")
    ap.add_argument("--window", action="store_true", help="show the stand-in window")
    ap.add_argument("--tolerance", type=float, default=0.01, help="m")
    ap.add_argument("--hold", type=float, default=0.3, help="s in the target to reach it")
    ap.add_argument("--time-limit", type=float, default=12.0, help="s before a target is missed")
    ap.add_argument("--idle-exit", type=float, default=10.0, help="s without a frame before exiting (0 = never)")
    ap.add_argument("--parent-pid", type=int, default=None, help="exit when this process is gone")
    args = ap.parse_args(argv)
    key = take_link_key()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="vr stand-in: %(message)s")
    game = StandinGame(tolerance_m=args.tolerance, hold_s=args.hold, time_limit_s=args.time_limit)
    try:
        link = StandinLink(args.listen, args.peer, game, key)
    except OSError as exc:
        log.error("cannot bind %s:%d: %s", args.listen[0], args.listen[1], exc.strerror)
        return 3
    watch = ParentWatch(args.parent_pid)
    link.send([game.hello()])
    try:
        if args.window:
            if run_window is None:
                log.error("--window: start python -m app.ui.vr_standin_window for the window")
                return 2
            return run_window(link, args.idle_exit, watch)
        run_headless(link, args.idle_exit, watch)
    except KeyboardInterrupt:
        pass
    finally:
        link.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
