"""The patient-model link: 40-byte frames out at ``rate_hz`` (100 Hz), replies carrying α in.

Modes (``devices.patient_model.mode`` in the config):

* ``embedded`` (default): our own model (app.devices.sim.patient_model.process) runs as a separate process on
  loopback ports chosen at start, so the real UDP link is exercised; the driver restarts it if it
  exits.  The process ends by itself when the manager dies.
* ``external``: a model started elsewhere (e.g. the Matlab model) at ``peer_host:peer_port``; the
  manager listens on ``bind_host:listen_port``.
* ``off``: no link.

``connected`` means "valid replies arrived in the last ``alive_timeout_s`` (0.5 s)"; right after the
socket is bound the driver reports "waiting for the patient model".  Datagrams from any other
sender (``UdpTransport.dropped_foreign``) and datagrams that do not decode (wrong size, header, CRC
or value; ``invalid_datagrams`` by reason) are dropped and counted.

What goes into each frame (``DeviceFrameSource``, reading the stream bus): the latest ``physio.main`` sample (NaN and no
PHYSIO_VALID flag when the physio link is down or silent), the latest ``linarm.vsa`` sample
(handlePos, handleVel, interactionForce; NaN when absent), the task (target, sub-task index,
state, time, score) from the VR link's ``task_snapshot()`` (``driver.vr_task``, handed in by the VR link's
``create``) — or from ``driver.task_source`` when
an exercise script sets one — and ``driver.clinical_score`` (set from the patient's profile or the
assistance panel; None = not available).

Each valid reply is published on "patient_model.main" as a ``PatientModelSample``: α, a_r, a_f
(with the current k_r, k_f: from the assistance controller the context hands in), TPI, MPI, PTI,
the α range, the decision path (code and text), the layer-5 level and the reply flags.  The script
API's ``patientModel.patientModelData`` is this sample.

This module also holds the small UDP-peer machinery the VR link shares (``UdpPeerDriver``,
``HelperProcess``, ``free_udp_port``).

Link security (issue #17; codec in app.wire.udp_frames): a helper process we start gets a fresh
key at every start, through an inherited pipe (``key_pipe``; never its environment), and every datagram
both ways carries a MAC; datagrams without a valid MAC, with a sequence number that does not increase (a
replay), or — for the patient model — acknowledging no frame sent in the last 0.5 s are dropped and counted
(``invalid_datagrams["mac" | "replay" | "stale ack"]``).  A helper that exits because it cannot bind its
port (exit code 3: another process holds it) is reported as ``helper_failed`` (a STOP alarm by the fault
policy) and the link never counts as reconnected through someone else's socket.  An ``external`` peer
speaks the plain seed layout unless ``authenticate: true`` with a ``key_file``; that the link is then not
authenticated is shown as a warning alarm.
"""

from __future__ import annotations

import collections
import functools
import logging
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from app.core import journal, streams
from app.core.bus import Channel, StreamBus, StreamSpec
from app.core.links import LOOPBACK
from app.devices.clock import CountedClock
from app.devices.driver import DeviceDriver
from app.devices.sim.patient_model.decision_tree import DEFAULT_CONFIG_PATH, decode_path_code
from app.devices.sim.patient_model.process import LINK_KEY_FD_ENV, key_pipe
from app.devices.transport import DatagramTransport, TransportError, UdpTransport
from app.wire.udp_frames import (
    ACK_WINDOW_S,
    KEY_SIZE,
    LINK_KEY_ENV,
    FrameError,
    PatientModelFrame,
    ReplyFlag,
    SequenceGuard,
    SystemFlag,
    TaskData,
    decode_patient_model_reply,
    encode_patient_model_frame,
    seal,
    unseal,
)

if TYPE_CHECKING:
    from app.core.config import AssistanceConfig
    from app.devices.registry import DeviceContext, DeviceHandle
    from app.safety.assistance import AssistanceLevels
    from app.safety.supervisor import SafetySupervisor

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
NAN = math.nan

PATIENT_MODEL_STREAM = StreamSpec(streams.PATIENT_MODEL_MAIN, (
    Channel("alpha", "", "Assistance level α"),
    Channel("a_r", "", "Robot assistance a_r"),
    Channel("a_f", "", "FES assistance a_f"),
    Channel("tpi", "", "Task Performance Index"),
    Channel("mpi", "", "Motor Performance Index"),
    Channel("pti", "", "Physiological Trend Index"),
), 100.0)


# ---------------------------------------------------------------------------------------------
# Shared UDP-peer machinery


def free_udp_port(host: str = LOOPBACK) -> int:
    """A UDP port free right now on ``host`` (the OS picks it; we release it for the real user)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class HelperProcess:
    """A Python module run as a child process (``python -m module args``), restartable.

    Looks like a ``subprocess.Popen`` to the manager (``terminate``, ``wait``, ``kill``, ``poll``),
    which stops everything in ``DeviceHandle.extras["processes"]`` at shutdown."""

    BIND_FAILED = 3  # the helpers' exit code when their port is taken

    def __init__(self, module: str, args: list[str], authenticate: bool = False) -> None:
        self.module = module
        self.args = list(args)
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0
        self.authenticate = authenticate
        self.key: bytes | None = None  # this start's link key (a new one at every start)

    @property
    def argv(self) -> list[str]:
        return [sys.executable, "-m", self.module, *self.args, "--parent-pid", str(os.getpid())]

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None

    def start(self) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
        env.pop(LINK_KEY_ENV, None)
        env.pop(LINK_KEY_FD_ENV, None)
        pass_fds: tuple[int, ...] = ()
        if self.authenticate:
            import secrets

            self.key = secrets.token_bytes(KEY_SIZE)
            # through a pipe: never the environment (readable in /proc/<pid>/environ all the helper's life)
            pass_fds = (key_pipe(self.key),)
            env[LINK_KEY_FD_ENV] = str(pass_fds[0])
        try:
            self.proc = subprocess.Popen(self.argv, cwd=str(ROOT), env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL, pass_fds=pass_fds)
        finally:
            for fd in pass_fds:
                os.close(fd)
        self.starts += 1
        log.info("started %s (pid %d)", self.module, self.proc.pid)

    def poll(self) -> int | None:
        return self.proc.poll() if self.proc else 0

    def terminate(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()

    def kill(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.kill()

    def wait(self, timeout: float | None = None) -> int | None:
        return self.proc.wait(timeout) if self.proc else 0

    def stop(self, timeout_s: float = 2.0) -> None:
        """terminate, wait, kill if needed (what tests call in teardown)."""
        if self.proc is None:
            return
        self.terminate()
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            self.proc.wait(timeout_s)


def _reason_kind(reason: str) -> str:
    for prefix, kind in (("wrong size", "size"), ("wrong header", "header"), ("bad CRC", "crc"),
                         ("not bytes", "size"), ("bad MAC", "mac"), ("replay", "replay"), ("stale ack", "stale ack")):
        if reason.startswith(prefix):
            return kind
    return "value"


class UdpPeerDriver(DeviceDriver):
    """A driver that sends one datagram per period to a UDP peer and decodes what comes back.

    Subclasses implement ``build_datagram(now)`` and ``handle_datagram(data, t)`` (raising
    ``FrameError`` on a bad datagram).  ``connected`` = a valid datagram within ``alive_timeout_s``.
    A helper process, when given, is restarted (with back-off) if it exits.

    The link is handed in (``transport``: a ``UdpTransport``, or an in-memory fake in tests).  Timing:
    a frame is due every period; a pass that comes late sends every frame it owes, up to
    ``CATCH_UP_S`` worth (a scheduling hiccup of the thread costs no frame); only a longer stall
    (debugger, suspend) restarts the schedule without a burst, and the frames skipped are counted
    (``skipped_sends``).  The loop makes one pass per period (``_pace``), which reads every datagram
    that arrived since the last, so replies never queue behind the sends."""

    CATCH_UP_S = 0.25  # a late pass sends the frames owed for up to this long (half the ack window: still fresh)
    MAX_READS_PER_PASS = 256  # a flood cannot keep the loop from sending
    MAX_SLEEP_S = 0.05

    def __init__(self, name: str, transport: DatagramTransport, rate_hz: float, *,
                 alive_timeout_s: float, process: HelperProcess | None = None,
                 bus: StreamBus | None = None, key: bytes | None = None) -> None:
        super().__init__(name, transport, bus=bus, read_timeout_s=0.0)  # paced by _pace
        self.static_key = key  # an external peer's shared key (None: plain frames unless our helper has one)
        self.seq_guard = SequenceGuard()
        self.helper_failures = 0
        self.udp: DatagramTransport = transport
        self.period_s = 1.0 / rate_hz
        self.skipped_sends = 0
        self._more_waiting = False
        self.alive_timeout_s = alive_timeout_s
        self.process = process
        self.datagrams_sent = 0
        self.datagrams_received = 0
        self.invalid_datagrams: collections.Counter[str] = collections.Counter()
        self.send_errors = 0
        self._next_send = 0.0
        self._last_valid = -math.inf
        self._peer_alive = False
        self._next_process_check = 0.0
        self._process_backoff_s = 1.0
        self._rate_t0 = time.monotonic()
        self._rate_counts = [0, 0]
        self.packet_rate_out = 0.0  # datagrams/s over the last second
        self.packet_rate_in = 0.0

    # ------------------------------------------------------------------ subclass API
    def build_datagram(self, now: float) -> bytes | None:
        raise NotImplementedError

    def handle_datagram(self, data: bytes, t: float) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ public
    @property
    def dropped_foreign(self) -> int:
        return self.udp.dropped_foreign

    @property
    def dropped_total(self) -> int:
        return self.udp.dropped_foreign + sum(self.invalid_datagrams.values())

    @property
    def peer_alive(self) -> bool:
        return self._peer_alive

    @property
    def key(self) -> bytes | None:
        """The link key in force: our helper's current one, else the configured one, else None (plain)."""
        if self.process is not None and self.process.authenticate:
            return self.process.key
        return self.static_key

    @property
    def authenticated(self) -> bool:
        return self.key is not None or (self.process is not None and self.process.authenticate)

    def check_seq(self, seq: int) -> None:
        """Raise FrameError unless ``seq`` is newer than the last accepted one (a replay otherwise)."""
        if not self.seq_guard.accept(seq):
            raise FrameError(f"replayed or old sequence number {seq} (last {self.seq_guard.last})")

    # ------------------------------------------------------------------ hooks
    def _set_connected(self, connected: bool, reason: str) -> None:
        # The base reports "connected" as soon as the socket is bound; for UDP that says nothing
        # about the peer, so until a valid datagram arrives we report that we are waiting.
        if connected and not self._peer_alive:
            peer = self.udp.peer
            where = f"{peer[0]}:{peer[1]}" if peer else "the peer"
            connected, reason = False, f"waiting for {self.name} at {where} ({reason})"
        super()._set_connected(connected, reason)

    def on_connect(self) -> None:
        self._next_send = time.monotonic()
        self._peer_alive = False

    def on_disconnect(self) -> None:
        self._peer_alive = False

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        self._more_waiting = True  # where one datagram was, more may wait: this pass drains them
        t = t_ns / 1e9
        try:
            if self.authenticated:
                key = self.key
                if key is None:
                    raise FrameError("bad MAC: no key yet")
                data = unseal(key, data)
            self.handle_datagram(data, t)
        except FrameError as exc:
            self.invalid_datagrams[_reason_kind(exc.reason)] += 1
            return
        self.datagrams_received += 1
        self._rate_counts[1] += 1
        self._last_valid = t
        if not self._peer_alive:
            self._peer_alive = True
            super()._set_connected(True, f"receiving from {self.udp.description}")

    def on_tick(self, now: float) -> None:
        if self._more_waiting:
            self._drain()
        late = now - self._next_send
        if late >= 0.0:
            owed = int(late / self.period_s) + 1
            if late > max(self.CATCH_UP_S, 4 * self.period_s):  # a stall (debugger, suspend): no burst
                self.skipped_sends += owed - 1
                owed, self._next_send = 1, now
            for _ in range(owed):
                self._send(now)
            self._next_send += owed * self.period_s
        if self._peer_alive and now - self._last_valid > self.alive_timeout_s:
            self._peer_alive = False
            if not self.authenticated:
                self.seq_guard.reset()  # a plain external peer may have restarted (authenticated: new key)
            super()._set_connected(False, f"no valid datagram from {self.name} for {self.alive_timeout_s:g} s")
        if now - self._rate_t0 >= 1.0:
            dt = now - self._rate_t0
            self.packet_rate_out, self.packet_rate_in = (c / dt for c in self._rate_counts)
            self._rate_counts = [0, 0]
            self._rate_t0 = now
        if self.process is not None and now >= self._next_process_check:
            self._supervise_process(now)
        self._pace()

    def _pace(self) -> None:
        """Sleep until the next frame is due: one loop pass per period, whose read (``read_timeout_s`` 0)
        and drain take the replies that came in meanwhile.  Waking for each reply as well doubled the
        passes, and a pass costs more than its datagram (#16); a reply waits at most one period (10 ms at
        100 Hz; α is applied at 10 Hz).  At most ``MAX_SLEEP_S`` so a stop request is seen promptly."""
        wait = self._next_send - time.monotonic()
        if wait > 0.0:
            time.sleep(min(wait, self.MAX_SLEEP_S))

    def _drain(self) -> None:
        """Handle every datagram already waiting (the base loop reads one per pass)."""
        read = self.udp.read
        for _ in range(self.MAX_READS_PER_PASS):
            data = read(0.0)
            if not data:
                break
            self.on_bytes(data, time.monotonic_ns())
        self._more_waiting = False

    def _send(self, now: float) -> None:
        try:
            data = self.build_datagram(now)
        except Exception:
            self.send_errors += 1
            if self.send_errors == 1 or self.send_errors % 1000 == 0:
                log.exception("%s: could not build a frame (%d so far)", self.name, self.send_errors)
            return
        if data is None:
            return
        key = self.key
        if key is not None:
            data = seal(key, data)
        elif self.authenticated:
            return  # our helper has no key yet: nothing leaves unauthenticated
        try:
            self.udp.write(data)
        except TransportError as exc:
            self.send_errors += 1
            if self.send_errors == 1:
                log.warning("%s: %s", self.name, exc)
            return
        self.datagrams_sent += 1
        self._rate_counts[0] += 1

    def _move_helper_port(self) -> None:
        assert self.process is not None
        args = self.process.args
        if "--listen" not in args or self.udp.peer is None:
            return
        i = args.index("--listen") + 1
        host = args[i].rpartition(":")[0]
        try:
            port = free_udp_port(host)
        except OSError:
            return
        args[i] = f"{host}:{port}"
        self.udp.set_peer((self.udp.peer[0], port))
        log.warning("%s: the helper will listen on port %d instead", self.name, port)

    def _supervise_process(self, now: float) -> None:
        assert self.process is not None
        self._next_process_check = now + 0.5
        code = self.process.poll()
        if code is None:
            if self._peer_alive:
                self._process_backoff_s = 1.0
            return
        log.warning("%s: helper process exited with code %s; restarting", self.name, code)
        self._fire_event(journal.DEVICE_ERROR_EVENT, f"{self.name}: helper process exited (code {code}); restarting")
        if code == HelperProcess.BIND_FAILED:
            # Someone else holds the helper's port: an alarm, never "reconnected" through their socket (its
            # datagrams carry no valid MAC), and the next start listens on a fresh port of ours.
            self.helper_failures += 1
            port = self.udp.peer[1] if self.udp.peer else "?"
            self._fire_event(journal.HELPER_FAILED,
                             f"the {self.name} process cannot bind its port {port} (taken by another program)")
            self._move_helper_port()
        # The link is down even if the restart is quicker than the silence timeout: say so (alarm, gap).
        self._peer_alive = False
        super()._set_connected(False, f"the {self.name} process exited (code {code}); restarting it")
        try:
            self.process.start()
            self.seq_guard.reset()  # a new process, a new key: its sequence numbers start again
        except OSError as exc:
            log.error("%s: cannot restart helper process: %s", self.name, exc)
        self._next_process_check = now + self._process_backoff_s
        self._process_backoff_s = min(10.0, self._process_backoff_s * 2)


# ---------------------------------------------------------------------------------------------
# Patient model


@dataclass(frozen=True)
class PatientModelSample:
    """One reply, as published on "patient_model.main" (and read by scripts as patientModelData)."""

    alpha: float          # -1 full resistance .. +1 full assistance
    a_r: float            # k_r · α
    a_f: float            # k_f · α
    tpi: float            # 0..1
    mpi: float
    pti: float
    alphaMin: float       # the final α range of layers 1-4
    alphaMax: float
    pathCode: int         # decision_tree.Decision.path_code
    path: str             # e.g. "assist/tpi_low/mpi_high/pti_low" ("" for an unknown code)
    level: float          # layer-5 support level inside the range, 0..1
    valid: bool           # the model had data for every index
    fallback: bool        # some index (or the clinical score) used its neutral value
    seq: int
    ackSeq: int
    roundTrip: float      # s from sending frame ackSeq to this reply (NaN if unknown)

    @property
    def alphaRange(self) -> tuple[float, float]:
        return (self.alphaMin, self.alphaMax)

    @property
    def group(self) -> str:
        return self.path.split("/", 1)[0] if self.path else ""


@functools.lru_cache(maxsize=256)
def path_text(code: int) -> str:
    decoded = decode_path_code(code)
    if decoded is None:
        return ""
    group, tpi_high, mpi_high, pti_high = decoded
    hl = ("low", "high")
    return f"{group}/tpi_{hl[tpi_high]}/mpi_{hl[mpi_high]}/pti_{hl[pti_high]}"


FrameSource = Callable[[int], PatientModelFrame]
TaskSource = Callable[[], tuple[float, TaskData]]  # (target position m, task data)
SplitSource = Callable[[float], tuple[float, float]]  # α -> (a_r, a_f)


class LinkState(Protocol):
    """What a frame needs of another device's driver: whether its samples are current."""

    @property
    def connected(self) -> bool: ...

    @property
    def silent(self) -> bool: ...


@dataclass(frozen=True)
class LinkInputs:
    """Where the UDP peers' frames read the other devices: their latest samples on the bus, whether their links
    are up (their drivers, from the context's peers), the FES stimulating, the e-stop latched."""

    bus: StreamBus
    peers: Mapping[str, LinkState]
    supervisor: SafetySupervisor | None = None


@dataclass(frozen=True)
class DeviceInputs:
    """What the UDP frames need from the other devices, read once per frame."""

    physio: Any          # latest physio.main sample, None when the link is down or silent
    vsa: Any             # latest linarm.vsa sample, None when the LINarm is not connected
    flags: int           # SystemFlag bits


def read_inputs(inputs: LinkInputs) -> DeviceInputs:
    bus, peers = inputs.bus, inputs.peers
    physio = peers.get(streams.PHYSIO)
    p = None
    if physio is not None and physio.connected and not physio.silent:
        p = bus.latest(streams.PHYSIO_MAIN)  # a stale sample must not look current to the model
    linarm = peers.get(streams.LINARM)
    robot_on = linarm is not None and linarm.connected
    v = bus.latest(streams.LINARM_VSA) if robot_on else None
    flags = 0
    if p is not None:
        flags |= SystemFlag.PHYSIO_VALID
    if robot_on:
        flags |= SystemFlag.ROBOT_ON
    fes = peers.get(streams.FES)
    if fes is not None and bool(getattr(fes, "stimulating", False)):  # an FesDriver
        flags |= SystemFlag.FES_ON
    if inputs.supervisor is not None and inputs.supervisor.estop_latched:
        flags |= SystemFlag.EMERGENCY_STOP
    return DeviceInputs(p, v, int(flags))


class DeviceFrameSource:
    """Builds each frame from the other devices' latest samples (see the module docstring)."""

    def __init__(self, inputs: LinkInputs, driver: PatientModelDriver) -> None:
        self.inputs = inputs
        self.driver = driver

    def __call__(self, seq: int) -> PatientModelFrame:
        inp = read_inputs(self.inputs)
        p, v = inp.physio, inp.vsa
        target, task = self._task()
        score = self.driver.clinical_score
        return PatientModelFrame(
            seq=seq, heartRate=_num(p, "heartRate"), skinConductance=_num(p, "skinConductance"),
            temperature=_num(p, "temperature"), force=_num(p, "force"),
            interactionForce=_num(v, "interactionForce"), robotVelocity=_num(v, "handleVel"),
            robotPosition=_num(v, "handlePos"), targetPosition=target, task=task,
            clinicalScore=score if score is not None and 0 <= score <= 254 else None, flags=inp.flags)

    def _task(self) -> tuple[float, TaskData]:
        source = self.driver.task_source or self.driver.vr_task
        if source is None:
            return NAN, TaskData()
        return source()


def _num(sample: Any, name: str) -> float:
    """An attribute as float, NaN when the sample or the attribute is missing."""
    if sample is None:
        return NAN
    try:
        return float(getattr(sample, name, NAN))
    except (TypeError, ValueError):
        return NAN


class PatientModelDriver(UdpPeerDriver):
    streams = (PATIENT_MODEL_STREAM,)

    def __init__(self, transport: DatagramTransport, rate_hz: float = 100.0, *,
                 frame_source: FrameSource | None = None, split: SplitSource | None = None,
                 process: HelperProcess | None = None, bus: StreamBus | None = None,
                 alive_timeout_s: float = 0.5, key: bytes | None = None) -> None:
        super().__init__(streams.PATIENT_MODEL, transport, rate_hz, alive_timeout_s=alive_timeout_s,
                         process=process, bus=bus, key=key)
        self.frame_source = frame_source
        self.split = split
        self.clinical_score: int | None = None  # set from the patient's profile / the assistance panel
        self.task_source: TaskSource | None = None  # overrides the VR link's task when set
        self.vr_task: TaskSource | None = None  # the VR link's task (app.devices.vr.create hands it in)
        self._seq = 0
        # When each sequence number was last sent, indexed by it: a reply is "fresh" when the frame it
        # acknowledges went out within ACK_WINDOW_S, at any rate (at 10× that is 500 frames; a table of
        # the last 256 sends refused legitimate replies that came back 0.13-0.26 s late, #16).
        self._sent_at: list[float] = [-math.inf] * 0x10000
        # No device clock in the replies: their arrival times, dejittered on the reply's sequence number at the
        # nominal rate (app.devices.clock), so a drained backlog does not put several replies on one instant.
        self.clock = CountedClock(rate_hz, wrap=0x10000)

    def build_datagram(self, now: float) -> bytes | None:
        if self.frame_source is None:
            return None
        seq = self._seq
        self._seq = (seq + 1) & 0xFFFF
        data = encode_patient_model_frame(self.frame_source(seq))
        self._sent_at[seq] = now
        return data

    def handle_datagram(self, data: bytes, t: float) -> None:
        r = decode_patient_model_reply(data)
        sent = self._sent_at[r.ackSeq]
        if not t - sent <= ACK_WINDOW_S:
            raise FrameError(f"stale ack: reply acknowledges frame {r.ackSeq}, not sent in the last {ACK_WINDOW_S:g} s")
        self.check_seq(r.seq)
        a_r, a_f = self.split(r.alpha) if self.split is not None else (NAN, NAN)
        flags = int(r.flags)
        self.publish(streams.PATIENT_MODEL_MAIN, self.clock.map(t, r.seq), PatientModelSample(
            alpha=r.alpha, a_r=a_r, a_f=a_f, tpi=r.tpi, mpi=r.mpi, pti=r.pti, alphaMin=r.alphaMin,
            alphaMax=r.alphaMax, pathCode=r.path, path=path_text(r.path), level=r.level,
            valid=bool(flags & _VALID), fallback=bool(flags & _FALLBACK), seq=r.seq,
            ackSeq=r.ackSeq, roundTrip=t - sent), t)


_VALID, _FALLBACK = int(ReplyFlag.VALID), int(ReplyFlag.FALLBACK)  # plain ints: IntFlag's & is slow per reply


def assistance_split(assistance: AssistanceLevels | None, config: AssistanceConfig | None = None) -> SplitSource:
    """α -> (a_r, a_f) with the gains in force: the assistance controller's when there is one (the manager
    always hands its own in), else ``config``'s (default: the default config's)."""
    if assistance is not None:
        return assistance.levels
    from app.core.config import AssistanceConfig
    from app.safety.assistance import AssistanceSplit

    c = config or AssistanceConfig()

    def split(alpha: float) -> tuple[float, float]:
        return AssistanceSplit.levels(alpha, c.k_r, c.k_f)

    return split


def link_key(cfg: Any) -> bytes | None:
    """An external peer's shared key (``key_file``, hex) when ``authenticate: true``; None otherwise."""
    if cfg.mode != "external" or not cfg.authenticated:
        return None
    try:
        key = bytes.fromhex(Path(cfg.key_file).expanduser().read_text(encoding="ascii").strip())
    except (OSError, ValueError) as exc:
        raise ValueError(f"key_file {cfg.key_file}: not a readable hex key ({exc})") from exc
    if len(key) < 16:
        raise ValueError(f"key_file {cfg.key_file}: the key is shorter than 16 bytes")
    return key


def warn_if_plain(supervisor: SafetySupervisor, name: str, cfg: Any) -> None:
    """An external peer on the plain seed layout: say so where the operator sees it (the alarms)."""
    if cfg.mode == "external" and not cfg.authenticated:
        from app.safety.supervisor import AlarmLevel

        supervisor.raise_alarm(AlarmLevel.WARNING, name, f"the {name} link to {cfg.peer_host}:"
                                       f"{cfg.peer_port} is not authenticated (plain frames, external peer)")


def embedded_process(host: str, model_port: int, manager_port: int, config_path: Path = DEFAULT_CONFIG_PATH,
                     extra: list[str] | None = None) -> HelperProcess:
    return HelperProcess("app.devices.sim.patient_model.process", [
        "--listen", f"{host}:{model_port}", "--peer", f"{host}:{manager_port}", "--config", str(config_path),
        *(extra or [])])


def create(ctx: DeviceContext) -> DeviceHandle | None:
    from app.devices.registry import DeviceHandle

    cfg = ctx.config
    if cfg.mode == "off":
        return None
    if cfg.mode not in ("embedded", "external"):
        raise ValueError(f"patient_model mode must be embedded, external or off, got {cfg.mode!r}")
    host = cfg.bind_host
    extras: dict[str, Any] = {}
    process = None
    if cfg.mode == "embedded":
        # The model is ours: both ends on the bind host (loopback by default), fresh ports each start.
        listen_port = cfg.listen_port or free_udp_port(host)
        peer = (host, cfg.peer_port or free_udp_port(host))
        process = embedded_process(host, peer[1], listen_port)
        extras.update(processes=[process], simulated=True)
    else:
        listen_port = cfg.listen_port
        peer = (cfg.peer_host, cfg.peer_port)
    if process is not None:
        process.authenticate = cfg.authenticated
    driver = PatientModelDriver(UdpTransport((host, listen_port), peer), cfg.rate_hz,
                                split=assistance_split(ctx.assistance),
                                process=process, bus=ctx.bus, key=link_key(cfg))
    driver.frame_source = DeviceFrameSource(LinkInputs(ctx.bus, ctx.peers, ctx.supervisor), driver)
    warn_if_plain(ctx.supervisor, streams.PATIENT_MODEL, cfg)
    if process is not None:
        process.start()
    return DeviceHandle(streams.PATIENT_MODEL, driver, None, extras)
