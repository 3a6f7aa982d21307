"""The embedded patient model as its own process, on the same UDP link an external model would use.

    python -m app.devices.sim.patient_model.process --listen HOST:PORT --peer HOST:PORT
           [--config resources/patient_model.yaml] [--clinical-score N] [--time-limit S]
           [--tolerance M] [--idle-exit S] [--parent-pid PID]

It receives the manager's 40-byte frames (app.wire.udp_frames), keeps the three indices
(app.devices.sim.patient_model.indices) up to date from them, walks the decision tree and answers every valid
frame with one reply carrying α, the indices, the final α range, the decision-path code and the
layer-5 level.  Datagrams from any sender other than ``--peer`` and datagrams that do not decode
are dropped and counted (the counts are logged at exit).

How a sub-task is judged from the stream (``SubtaskJudge``): a sub-task is the task data's
``subTask`` index while its state is MOVING or HOLDING; the model starts following it (movement
metrics for the MPI) the first time it sees that index active.  It ends, once:

* in success when the state becomes REACHED (the game's verdict; duration = ``subTaskTime`` or the
  model's own clock);
* in failure when the state becomes FAILED, or when it is still active after ``--time-limit`` s
  (default: the TPI's ``maxTime``, 12 s, after which a reach earns no time credit anyway);
* when the index changes while it was still open: success if the handle was within
  ``--tolerance`` m of the target in the last frame, failure otherwise.

Each judged sub-task feeds the TPI, closes the movement for the MPI, and moves layer 5 (the support
level rises after a failure and falls after a success).  The clinical score comes from the frames;
while they carry "not available" the ``--clinical-score`` value is used (default: the middle of
the in-between band), and the reply is flagged FALLBACK, as it is while any index still has no
data (its neutral value is used).

When the manager started it with a link key (through an inherited pipe named by ``LINARMPP_LINK_KEY_FD``; never
on the command line), every frame must carry a valid MAC and a sequence number newer than the last
(app.wire.udp_frames ``unseal`` / ``SequenceGuard``), and every reply is sealed; others are dropped and
counted ("invalid", "replay").  Exit code 3: the ``--listen`` port cannot be bound.

The process exits by itself when its parent (``--parent-pid``, default the parent at start) dies or when no frame has
arrived for ``--idle-exit`` s (default 10; 0 = never), so a crashed manager leaves nothing behind.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import socket
import sys
import time
from dataclasses import dataclass

from app.devices.sim.patient_model.decision_tree import DEFAULT_CONFIG_PATH, Decision, DecisionTree, load_tree_config
from app.devices.sim.patient_model.indices import MotorPerformance, PhysiologicalTrend, TaskPerformance, TpiNorms
from app.devices.transport import enlarge_receive_buffer
from app.wire.udp_frames import (
    LINK_KEY_ENV,
    FrameError,
    PatientModelFrame,
    PatientModelReply,
    ReplyFlag,
    SequenceGuard,
    TaskState,
    decode_patient_model_frame,
    encode_patient_model_reply,
    seal,
    unseal,
)

log = logging.getLogger("patient_model.process")

ACTIVE_STATES = (TaskState.MOVING, TaskState.HOLDING)
DEFAULT_TOLERANCE_M = 0.01
DEFAULT_IDLE_EXIT_S = 10.0


@dataclass(frozen=True)
class SubtaskResult:
    subTask: int
    success: bool
    duration: float  # s
    reason: str      # "reached", "failed", "time limit", "abandoned"


class SubtaskJudge:
    """Turns the stream of task data into judged sub-tasks (rules in the module docstring)."""

    def __init__(self, time_limit_s: float, tolerance_m: float) -> None:
        self.time_limit_s = time_limit_s
        self.tolerance_m = tolerance_m
        self.reset()

    def reset(self) -> None:
        self._open: int | None = None   # index of the sub-task being followed
        self._t0 = 0.0
        self._judged: int | None = None  # last index judged (each is judged once)
        self._in_target = False

    @property
    def open_subtask(self) -> int | None:
        return self._open

    def _elapsed(self, frame: PatientModelFrame, t: float) -> float:
        st = frame.task.subTaskTime
        return st if math.isfinite(st) else t - self._t0

    def feed(self, frame: PatientModelFrame, t: float) -> tuple[SubtaskResult | None, bool]:
        """(the sub-task judged by this frame or None, True when a new sub-task started)."""
        task = frame.task
        result: SubtaskResult | None = None
        started = False
        if self._open is not None and task.subTask != self._open:
            result = SubtaskResult(self._open, self._in_target, t - self._t0, "abandoned")
            self._judged, self._open = self._open, None
        if self._open is None and task.taskState in ACTIVE_STATES and task.subTask != self._judged:
            self._open, self._t0, started = task.subTask, t, True
        if self._open is not None and result is None:
            elapsed = self._elapsed(frame, t)
            verdict: tuple[bool, str] | None = None
            if task.taskState == TaskState.REACHED:
                verdict = (True, "reached")
            elif task.taskState == TaskState.FAILED:
                verdict = (False, "failed")
            elif elapsed > self.time_limit_s:
                verdict = (False, "time limit")
            if verdict is not None:
                result = SubtaskResult(self._open, verdict[0], elapsed, verdict[1])
                self._judged, self._open = self._open, None
        pos, target = frame.robotPosition, frame.targetPosition
        self._in_target = (math.isfinite(pos) and math.isfinite(target)
                           and abs(pos - target) <= self.tolerance_m)
        return result, started


class EmbeddedPatientModel:
    """The model without its socket: frames in, replies out (pure, testable)."""

    def __init__(self, tree: DecisionTree | None = None, default_clinical_score: float | None = None,
                 time_limit_s: float | None = None, tolerance_m: float = DEFAULT_TOLERANCE_M) -> None:
        self.tree = tree or DecisionTree()
        c = self.tree.config
        self.default_clinical_score = (sum(c.scoreThresholds) / 2.0 if default_clinical_score is None
                                       else float(default_clinical_score))
        self.tpi = TaskPerformance(TpiNorms())
        self.mpi = MotorPerformance()
        self.pti = PhysiologicalTrend()
        self.judge = SubtaskJudge(self.tpi.norms.maxTime if time_limit_s is None else time_limit_s,
                                  tolerance_m)
        self.results: list[SubtaskResult] = []
        self.last_decision: Decision | None = None
        self._seq = 0

    def on_frame(self, frame: PatientModelFrame, t: float) -> PatientModelReply:
        self.pti.add_sample(t, frame.heartRate, frame.skinConductance, frame.temperature)
        result, started = self.judge.feed(frame, t)
        if result is not None:
            self.tpi.add_subtask(result.success, result.duration)
            self.mpi.end_movement()
            self.tree.record_subtask(result.success)
            self.results.append(result)
        if started:
            self.mpi.start_movement(frame.robotPosition, frame.targetPosition)
        self.mpi.add_sample(t, frame.robotVelocity, frame.interactionForce)

        c = self.tree.config
        fallback = False
        score: float
        if frame.clinicalScore is None:
            score, fallback = self.default_clinical_score, True
        else:
            score = float(frame.clinicalScore)
            if not c.scoreMin <= score <= c.scoreMax:
                score, fallback = min(c.scoreMax, max(c.scoreMin, score)), True
        pti_usable = any(math.isfinite(s) for s in self.pti.slopes().values())
        if self.tpi.count == 0 or self.mpi.count == 0 or not pti_usable:
            fallback = True
        decision = self.tree.decide(score, self.tpi.value, self.mpi.value, self.pti.value)
        self.last_decision = decision
        self._seq = (self._seq + 1) & 0xFFFF
        lo, hi = decision.alphaRange
        return PatientModelReply(
            seq=self._seq, ackSeq=frame.seq, alpha=_unit(decision.alpha, -1.0), tpi=_unit(self.tpi.value, 0.0),
            mpi=_unit(self.mpi.value, 0.0), pti=_unit(self.pti.value, 0.0), alphaMin=_unit(lo, -1.0),
            alphaMax=_unit(hi, -1.0), path=decision.path_code, level=_unit(decision.level, 0.0),
            flags=ReplyFlag.FALLBACK if fallback else ReplyFlag.VALID)


def _unit(x: float, lo: float) -> float:
    return min(1.0, max(lo, x))


# ---------------------------------------------------------------------------------------------
# The process


def parse_address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


class ParentWatch:
    """True once the process that started us is gone (we were re-parented).  The parent passes its
    pid (``--parent-pid``): reading our own parent pid at start-up would race with a parent that
    dies while we are still importing."""

    def __init__(self, parent_pid: int | None = None) -> None:
        self.parent = os.getppid() if parent_pid is None else parent_pid

    def parent_gone(self) -> bool:
        return os.getppid() != self.parent


LINK_KEY_FD_ENV = "LINARMPP_LINK_KEY_FD"  # the number of an inherited pipe holding the key (not the key)
_NO_ONE_HAS = b"\x00" * 32  # a key nobody has: fail closed


def key_pipe(key: bytes) -> int:
    """A pipe already holding ``key`` (hex) for a helper about to start: its read end (pass it to the child in
    ``pass_fds`` and its number in LINK_KEY_FD_ENV, then close it here). A key in the environment stays
    readable in /proc/<pid>/environ for the helper's whole life, even after ``os.environ.pop`` (that is the
    block the process started with); a pipe is read once and is gone. 64 bytes never fill a pipe, so the
    write cannot block."""
    read_end, write_end = os.pipe()
    try:
        os.write(write_end, key.hex().encode("ascii"))
    finally:
        os.close(write_end)
    return read_end


def take_link_key() -> bytes | None:
    """The key the manager passed through a pipe (LINK_KEY_FD_ENV names the descriptor; read to its end
    and closed, so no child inherits it). A key in the environment itself is refused: it cannot be taken
    back from /proc/<pid>/environ."""
    if os.environ.pop(LINK_KEY_ENV, None) is not None:
        log.error("a link key came in the environment (%s), readable by any process of this user: refusing "
                  "every frame", LINK_KEY_ENV)
        return _NO_ONE_HAS
    fd_text = os.environ.pop(LINK_KEY_FD_ENV, "")
    if not fd_text:
        return None
    try:
        fd = int(fd_text)
        chunks: list[bytes] = []
        while sum(map(len, chunks)) < 4096:
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            chunks.append(chunk)
        os.close(fd)
        text = b"".join(chunks).decode("ascii").strip()
        return bytes.fromhex(text)
    except (ValueError, OSError, UnicodeDecodeError) as exc:
        log.error("the link key could not be read from the pipe %s (%s): refusing every frame", fd_text, exc)
        return _NO_ONE_HAS


def serve(sock: socket.socket, peer: tuple[str, int], model: EmbeddedPatientModel,
          idle_exit_s: float, watch: ParentWatch, key: bytes | None = None) -> dict[str, int]:
    """Answer frames until the parent dies or the link is idle; returns the counters."""
    peer_ip = socket.gethostbyname(peer[0])
    counts = {"frames": 0, "replies": 0, "foreign": 0, "invalid": 0, "replay": 0}
    guard = SequenceGuard()
    last_frame = time.monotonic()
    sock.settimeout(0.2)
    while True:
        now = time.monotonic()
        if watch.parent_gone():
            log.info("parent process gone: exiting")
            break
        if idle_exit_s > 0 and now - last_frame > idle_exit_s:
            log.info("no frame for %.1f s: exiting", idle_exit_s)
            break
        try:
            data, sender = sock.recvfrom(2048)
        except TimeoutError:
            continue
        except OSError:  # ICMP port unreachable from a manager that is not up yet
            continue
        t = time.monotonic()
        if sender[0] != peer_ip or sender[1] != peer[1]:
            counts["foreign"] += 1
            continue
        try:
            frame = decode_patient_model_frame(unseal(key, data) if key is not None else data)
        except FrameError as exc:
            counts["invalid"] += 1
            log.debug("dropped datagram: %s", exc.reason)
            continue
        if not guard.accept(frame.seq):
            counts["replay"] += 1
            continue
        counts["frames"] += 1
        last_frame = t
        reply = model.on_frame(frame, t)
        try:
            out = encode_patient_model_reply(reply)
            sock.sendto(seal(key, out) if key is not None else out, peer)
            counts["replies"] += 1
        except OSError:
            pass  # the manager is momentarily not listening; the next frame gets an answer
    return counts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m app.devices.sim.patient_model.process",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--listen", type=parse_address, required=True, help="HOST:PORT to receive frames on")
    ap.add_argument("--peer", type=parse_address, required=True, help="HOST:PORT of the manager")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="decision-tree YAML")
    ap.add_argument("--clinical-score", type=float, default=None,
                    help="used while the frames carry no clinical score")
    ap.add_argument("--time-limit", type=float, default=None, help="s before an open sub-task counts as failed")
    ap.add_argument("--tolerance", type=float, default=DEFAULT_TOLERANCE_M, help="m, 'in the target'")
    ap.add_argument("--idle-exit", type=float, default=DEFAULT_IDLE_EXIT_S,
                    help="exit after this many s without a frame (0 = never)")
    ap.add_argument("--parent-pid", type=int, default=None, help="exit when this process is gone")
    args = ap.parse_args(argv)
    key = take_link_key()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="patient model: %(message)s")
    try:
        tree = DecisionTree(load_tree_config(args.config))
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    model = EmbeddedPatientModel(tree, args.clinical_score, args.time_limit, args.tolerance)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    enlarge_receive_buffer(sock)  # a descheduled model must not lose frames in the kernel
    try:
        sock.bind(args.listen)
    except OSError as exc:
        log.error("cannot bind %s:%d: %s", args.listen[0], args.listen[1], exc.strerror)
        return 3
    try:
        counts = serve(sock, args.peer, model, args.idle_exit, ParentWatch(args.parent_pid), key)
    except KeyboardInterrupt:
        counts = {}
    finally:
        sock.close()
    log.info("stopped: %s", ", ".join(f"{k} {v}" for k, v in counts.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
