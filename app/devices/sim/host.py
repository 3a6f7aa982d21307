"""Where simulated serial devices run: in a process of their own (the default), or in the app's process.

With real hardware the app's process holds drivers, recorder and GUI, and the devices run elsewhere. The
simulators keep it that way: :class:`SimulatorProcess` starts ``python -m app.devices.sim.host``, which
builds the simulated patient and the LINarm, physiological-board and FES simulators on the same pty links
as before, and answers a small control channel (JSON lines on its stdin/stdout: the Simulation panel's
grip, arm, sensor faults, unplug / replug). The child never outlives the app by more than ``linger_s``:
it watches its stdin (EOF when the parent dies, however it dies) and has PR_SET_PDEATHSIG as a backstop.
Lingering a moment is what a real robot does when the PC dies: its controller keeps running and its
host watchdog stops the motors; the SIGKILL test watches exactly that through the child's state events.

``host: thread`` (``simulation.host`` in the config, or ``LINARMPP_SIM_HOST``) keeps the old in-process
hosting for tests that reach into a simulator core.

The LINarm may be the Python model or the firmware's software-in-the-loop executable (``linarm: firmware``,
built from firmware/host with CMake): the real controller code on its simulated plant. ``linarm: mcu`` runs
the firmware's ARM image for the emulated MPS2 AN385 board under ``qemu-system-arm`` instead (the same plant
inside the image) and talks to it through the board's UART0, a TCP character device of qemu.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from app.core import streams
from app.core.links import LOOPBACK, simulator_link, socket_link_url
from app.devices.sim.base import DEVICE_CONTROLS, SerialSimulator, linarm_starts_homed

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[3]
FIRMWARE_BUILD_DIRS = (ROOT / "firmware" / "build", ROOT / "firmware" / "build" / "pytest")
HOST_ENV = "LINARMPP_SIM_HOST"
EVENTS_ENV = "LINARMPP_SIM_EVENTS"  # a file the simulator process appends its device state events to
SIMULATOR_RT_PRIORITY = 10  # the SIL firmware's, as SerialSimulator's: below the LINarm link (20, 21)
PR_SET_PDEATHSIG = 1

PATIENT_METHODS = frozenset({"idle", "squeeze", "squeeze_periodically", "squeeze_at_targets", "set_peak_force",
                             "passive", "push_to", "fail_weak", "fail_stop_early", "set_electrode_distances"})


def find_firmware_sil() -> Path | None:
    """The firmware's SIL executable, when it has been built (``cmake --build firmware/build``)."""
    for folder in FIRMWARE_BUILD_DIRS:
        for candidate in (folder / "linarm_sil", folder / "sim" / "linarm_sil"):
            if candidate.is_file() and os.access(candidate, os.X_OK):
                return candidate
    return None


MCU_IMAGE_PATHS = (ROOT / "firmware" / "build" / "due" / "linarm_mps2.elf",
                   ROOT / "firmware" / "build" / "pytest-due" / "linarm_mps2.elf")
QEMU_SYSTEM_ARM = "qemu-system-arm"


def find_mcu_image() -> Path | None:
    """The firmware's image for the emulated MPS2 AN385 board, when built
    (``cmake --build firmware/build/due --target linarm_mps2.elf``)."""
    return next((p for p in MCU_IMAGE_PATHS if p.is_file()), None)


def qemu_mps2_command(image: Path, uart0_port: int, uart1: str = "null", icount: int | None = None) -> list[str]:
    """qemu-system-arm running ``image`` on the MPS2 AN385 board, UART0 (the protocol) on a loopback TCP
    server; ``uart1`` (the board console) is any qemu chardev spec. ``icount``: count instructions
    (virtual time = 2^icount ns per instruction) instead of following the host's clock."""
    cmd = [QEMU_SYSTEM_ARM, "-M", "mps2-an385", "-nographic", "-monitor", "none", "-kernel", str(image),
           "-serial", f"tcp:{LOOPBACK}:{uart0_port},server=on,wait=off,nodelay=on", "-serial", uart1]
    if icount is not None:
        cmd += ["-icount", f"shift={icount},sleep=on"]
    return cmd


def free_tcp_port() -> int:
    """A loopback TCP port free right now (the simulator process binds it a moment later)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((LOOPBACK, 0))
        return int(sock.getsockname()[1])


def die_with_parent() -> None:
    """In a child, before exec: SIGTERM when the parent thread dies (Linux; a no-op elsewhere)."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def firmware_child_setup() -> None:
    """The SIL firmware: dies with the simulator process, and runs its 1 kHz loop real-time when allowed."""
    die_with_parent()
    if os.environ.get("LINARMPP_REALTIME") != "0":
        with contextlib.suppress(Exception):
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(SIMULATOR_RT_PRIORITY))


# ============================================================================================ the child process
class SilCore:
    """The firmware's SIL executable as a simulator core: host bytes to its stdin, its stdout polled."""

    def __init__(self, executable: Path, centre: float = 0.20) -> None:
        args = [str(executable), "--centre", repr(centre)]
        if linarm_starts_homed():  # as the Python model (LinarmSimAdapter): homed, IDLE at the home position
            from app.wire.linarm_constants import K

            args = [str(executable), "--centre", repr(K["HOME_CENTRE"]), "--delta", repr(K["HOME_DELTA"]),
                    "--start-homed"]
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, bufsize=0,
                                     preexec_fn=firmware_child_setup)
        assert self.proc.stdout is not None and self.proc.stdin is not None
        os.set_blocking(self.proc.stdout.fileno(), False)

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        with contextlib.suppress(OSError):
            self.proc.stdin.write(data)  # type: ignore[union-attr]
        return self.poll(t)

    def poll(self, t: float) -> bytes:
        try:
            return self.proc.stdout.read(65536) or b""  # type: ignore[union-attr]
        except (BlockingIOError, ValueError):
            return b""

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.proc.stdin.close()  # type: ignore[union-attr]
        try:
            self.proc.wait(1.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(1.0)
        with contextlib.suppress(Exception):
            self.proc.stdout.close()  # type: ignore[union-attr]


class McuCore:
    """The firmware's image on the emulated MPS2 AN385 board as a simulator core: qemu-system-arm with the
    board's UART0 on a loopback TCP port; host bytes go to that socket, the board's output is polled from it."""

    def __init__(self, image: Path, connect_timeout_s: float = 10.0) -> None:
        port, console_port = free_tcp_port(), free_tcp_port()
        self.sock: Any = None
        self.console: Any = None
        self.proc = subprocess.Popen(
            qemu_mps2_command(image, port, f"tcp:{LOOPBACK}:{console_port},server=on,wait=off,nodelay=on"),
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            preexec_fn=firmware_child_setup)
        deadline = time.monotonic() + connect_timeout_s
        try:
            self.sock = self._connect(port, deadline)
            self.console = self._connect(console_port, deadline)
            # The board greets on its console once its UARTs are enabled; bytes sent to UART0 before that may
            # stay in qemu's socket (its CMSDK UART refuses them while receive is off).
            greeting = b""
            while b"HELLO" not in greeting:
                self.console.settimeout(max(0.05, deadline - time.monotonic()))
                chunk = self.console.recv(256)
                if not chunk:
                    raise OSError("the board's console closed")
                greeting += chunk
            self.console.sendall(b"\n")  # heard: the greetings stop
        except OSError as exc:
            self.close()
            raise RuntimeError(f"the emulated board did not come up: {exc}") from exc
        self.sock.setblocking(False)

    def _connect(self, port: int, deadline: float) -> Any:
        import socket

        while True:  # qemu listens a moment after it starts
            try:
                sock = socket.create_connection((LOOPBACK, port), timeout=1.0)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                return sock
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        with contextlib.suppress(OSError):
            try:
                self.sock.setblocking(True)  # a few host bytes: the board takes them at once
                self.sock.sendall(data)
            finally:
                self.sock.setblocking(False)
        return self.poll(t)

    def poll(self, t: float) -> bytes:
        try:
            return self.sock.recv(65536)
        except (BlockingIOError, OSError, AttributeError):
            return b""

    def close(self) -> None:
        for sock in (self.sock, self.console):
            if sock is not None:
                with contextlib.suppress(Exception):
                    sock.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2.0)


class LinarmStateWatch:
    """Reports the simulated controller's control/error state, as it sends it, when it changes: the observable
    'did the robot go safe' for the SIGKILL test and for the log. ``sent`` (the Python model's
    ``sent_control_and_error``) says it without decoding; otherwise (the firmware's SIL, the emulated board) the
    stream is decoded. Decoding every frame of the 200 Hz stream cost the model's thread ~13 % of its CPU (#38)."""

    def __init__(self, emit: Callable[[dict[str, Any]], None],
                 sent: Callable[[], tuple[int, int] | None] | None = None) -> None:
        from app.wire.cmdmessenger import CmdMessengerDecoder

        self.decoder = CmdMessengerDecoder()
        self.emit = emit
        self.sent = sent
        self.last: tuple[int, int] | None = None

    def feed(self, data: bytes) -> None:
        if self.sent is not None:
            now = self.sent()
            if now is not None:
                self._report(now)
            return
        from app.wire import linarm_protocol as proto

        for frame in self.decoder.feed(data):
            try:
                msg = proto.decode_controller_frame(frame)
            except proto.ProtocolError:
                continue
            if isinstance(msg, proto.LinarmState):
                self._report((int(msg.control_state), int(msg.error_state)))

    def _report(self, now: tuple[int, int]) -> None:
        if now != self.last:
            self.last = now
            self.emit({"event": "linarm_state", "t": time.monotonic(), "control_state": now[0],
                       "error_state": now[1]})


class _Watched:
    """A core whose output is also fed to a watch (the simulator thread calls it)."""

    def __init__(self, core: Any, watch: LinarmStateWatch) -> None:
        self.core = core
        self.watch = watch

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        out = self.core.handle_host_bytes(data, t)
        if out:
            self.watch.feed(out)
        return out

    def poll(self, t: float) -> bytes:
        out = self.core.poll(t)
        if out:
            self.watch.feed(out)
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self.core, name)


def build_simulators(spec: dict[str, Any], patient: Any, emit: Callable[[dict[str, Any]], None] | None = None
                     ) -> dict[str, Any]:
    """The SerialSimulators of ``spec["devices"]`` (name → parameters), not yet started."""
    runtime = Path(spec["runtime_dir"])
    sims: dict[str, Any] = {}
    for name, params in spec["devices"].items():
        kind = params["kind"]
        link = simulator_link(runtime, name)
        link_factory = None
        if params.get("tcp_port"):
            from app.devices.transport import SocketLink

            def link_factory(port: int = int(params["tcp_port"])) -> Any:
                return SocketLink(port)
        if kind == streams.LINARM:
            from app.devices.sim.adapters import LINARM_POLL_S, LinarmSimAdapter

            def linarm_core(patient: Any = patient) -> Any:
                core = LinarmSimAdapter(patient)
                return _Watched(core, LinarmStateWatch(emit, core.core.sent_control_and_error)) if emit else core

            sims[name] = SerialSimulator(name, linarm_core, link, tick_s=LINARM_POLL_S, link_factory=link_factory)
        elif kind == "linarm_firmware":
            executable = Path(params["executable"])

            def sil_core(executable: Path = executable) -> Any:
                core = SilCore(executable)
                return _Watched(core, LinarmStateWatch(emit)) if emit else core

            sims[name] = SerialSimulator(name, sil_core, link, tick_s=0.002, link_factory=link_factory)
        elif kind == "linarm_mcu":
            image = Path(params["image"])

            def mcu_core(image: Path = image) -> Any:
                core = McuCore(image)
                return _Watched(core, LinarmStateWatch(emit)) if emit else core

            sims[name] = SerialSimulator(name, mcu_core, link, tick_s=0.002, link_factory=link_factory)
        elif kind == streams.PHYSIO:
            from app.devices.sim.adapters import PHYSIO_POLL_S, PhysioSimCore
            from app.wire.physio_codec import Calibration, ChannelCalibration

            cal = Calibration(**{k: ChannelCalibration(*v) for k, v in params["calibration"].items()})
            rate = float(params["rate_hz"])
            sims[name] = SerialSimulator(name, lambda rate=rate, cal=cal: PhysioSimCore(patient, rate, cal), link,
                                         tick_s=PHYSIO_POLL_S, link_factory=link_factory)
        elif kind == streams.FES:
            from app.devices.sim.adapters import FES_POLL_S, RehaStimSimAdapter

            protocol = params["protocol"]
            sims[name] = SerialSimulator(name, lambda protocol=protocol: RehaStimSimAdapter(protocol, observer=patient),
                                         link, tick_s=FES_POLL_S, link_factory=link_factory)
        else:
            raise ValueError(f"unknown simulator kind {kind!r}")
    return sims


def close_simulator(sim: Any) -> None:
    sim.stop()
    core = getattr(sim.core, "core", sim.core)
    if hasattr(core, "close"):
        core.close()


def patient_settings_dict(settings: Any) -> dict[str, Any]:
    return {k: (v.value if hasattr(v, "value") else list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(settings).items()}


def patient_settings_from(data: dict[str, Any]) -> Any:
    from app.devices.sim.patient import GripMode, HandleMode, PatientSettings

    return PatientSettings(**{**data, "gripMode": GripMode(data["gripMode"]),
                              "handleMode": HandleMode(data["handleMode"]), "targets": tuple(data["targets"])})


def serve(spec: dict[str, Any], commands: Any, replies: Any) -> int:
    """The child's main loop: build, report ready, answer commands until told to quit or the parent is gone."""
    from app.devices.sim.patient import SimulatedPatient

    out_lock = threading.Lock()
    # State events also go to a file when asked (LINARMPP_SIM_EVENTS): what the device did after the app died
    events_file = open(spec["events_file"], "a", encoding="utf-8") if spec.get("events_file") else None

    def emit(message: dict[str, Any]) -> None:
        with out_lock:
            if events_file is not None and "event" in message:
                events_file.write(json.dumps(message) + "\n")
                events_file.flush()
            try:
                replies.write(json.dumps(message) + "\n")
                replies.flush()
            except (OSError, ValueError):
                pass  # the parent is gone: keep simulating until the linger ends

    patient = SimulatedPatient(seed=int(spec.get("patient_seed", 7)))
    sims = build_simulators(spec, patient, emit)
    for sim in sims.values():
        sim.start()  # real-time device threads (SerialSimulator.realtime_priority)
    emit({"ready": {name: sim.url for name, sim in sims.items()}, "pid": os.getpid()})
    # Set from the SIGTERM handler, so a plain flag, never a lock: a handler that set a threading.Event was
    # interrupted by the next SIGTERM, whose handler then waited for the Event's lock forever (a wedged
    # simulator process, found left running after a test run, py-spy showing three nested Event.set calls).
    parent_gone = [False]

    def on_sigterm(*_args: Any) -> None:
        parent_gone[0] = True

    signal.signal(signal.SIGTERM, on_sigterm)
    fd = commands.fileno()
    buffer = b""
    quit_now = False
    while not quit_now and not parent_gone[0]:
        ready, _, _ = select.select([fd], [], [], 0.2)
        if not ready:
            continue
        chunk = os.read(fd, 65536)
        if not chunk:
            parent_gone[0] = True
            break
        buffer += chunk
        while b"\n" in buffer:
            line, buffer = buffer.split(b"\n", 1)
            if not line.strip():
                continue
            request = json.loads(line)
            if request.get("op") == "quit":
                quit_now = True
                emit({"id": request.get("id"), "ok": True, "result": None})
                break
            emit(_answer(request, sims, patient))
    if parent_gone[0] and not quit_now:
        # As a real device would: keep running a moment after the host vanished (its watchdog acts).
        linger = float(spec.get("linger_s", 1.0))
        deadline = time.monotonic() + linger
        while time.monotonic() < deadline:
            time.sleep(0.02)
    for sim in sims.values():
        close_simulator(sim)
    if events_file is not None:
        events_file.close()
    return 0


def _answer(request: dict[str, Any], sims: dict[str, Any], patient: Any) -> dict[str, Any]:
    ident, op = request.get("id"), request.get("op")
    try:
        result: Any = None
        if op == "patient":
            method = request["method"]
            if method not in PATIENT_METHODS:
                raise ValueError(f"no patient behaviour {method!r}")
            getattr(patient, method)(*request.get("args", []), **request.get("kwargs", {}))
            result = patient_settings_dict(patient.settings())
        elif op == "patient_settings":
            result = patient_settings_dict(patient.settings())
        elif op == "status":
            result = {name: sim.running for name, sim in sims.items()}
        elif op == "kill":
            sim = sims[request["device"]]
            sim.kill()
        elif op == "restart":
            sim = sims[request["device"]]
            old = getattr(sim.core, "core", sim.core)
            if hasattr(old, "close"):
                old.close()
            sim.restart()
        elif op == "host_log":  # tests: the bytes the driver sent, as this end of the link received them
            sim = sims[request["device"]]
            if "keep" in request:
                sim.keep_host_log = bool(request["keep"])
            if request.get("clear"):
                sim.host_bytes_log.clear()
            log_now = list(sim.host_bytes_log)
            since = int(request.get("since", 0))
            since = since if 0 <= since <= len(log_now) else 0  # a restarted simulator began a new log
            result = {"from": since, "rows": [[t, data.hex()] for t, data in log_now[since:]]}
        elif op == "device_log":  # benchmarks: the bytes the device wrote, stamped in this process
            sim = sims[request["device"]]
            if "keep" in request:
                sim.keep_device_log = bool(request["keep"])
            log_now = list(sim.device_bytes_log)
            since = int(request.get("since", 0))
            since = since if 0 <= since <= len(log_now) else 0
            result = {"from": since, "rows": [[t, data.hex()] for t, data in log_now[since:]]}
        elif op == "link_stats":  # clients the device's loopback link accepted / refused (a pty has none)
            link = sims[request["device"]].link
            result = {"accepted": int(getattr(link, "clients_accepted", 0)),
                      "refused": int(getattr(link, "clients_refused", 0))}
        elif op == "packages":  # the top-level packages this process has loaded (tests: no Qt in here)
            result = sorted({name.partition(".")[0] for name in list(sys.modules)})
        elif op == "control":
            sim = sims[request["device"]]
            fn = DEVICE_CONTROLS[request["name"]]
            result = sim.with_core(lambda core: fn(getattr(core, "core", core) if isinstance(core, _Watched)
                                                   else core, *request.get("args", [])))
        else:
            raise ValueError(f"unknown control operation {op!r}")
        return {"id": ident, "ok": True, "result": result}
    except (KeyError, ValueError, TypeError) as exc:
        return {"id": ident, "ok": False, "error": f"{type(exc).__name__}: {exc}"}


def child_main() -> int:
    logging.basicConfig(level=logging.WARNING, format="sim-host %(levelname)s %(message)s")
    spec = json.loads(sys.stdin.buffer.readline())
    return serve(spec, sys.stdin.buffer, sys.stdout)


# ============================================================================================ the app's side
class SimulatorProcessError(RuntimeError):
    pass


class SimulatorProcess:
    """The app's handle on the simulator process: start, control calls, state events, stop."""

    def __init__(self, spec: dict[str, Any], python: str = sys.executable) -> None:
        self.spec = spec
        self.python = python
        self.proc: subprocess.Popen[bytes] | None = None
        self.urls: dict[str, str] = {}
        self.events: list[dict[str, Any]] = []  # state events (bounded)
        self.event_listeners: list[Callable[[dict[str, Any]], None]] = []
        self._lock = threading.Lock()
        self._seq = 0
        self._waiting: dict[int, tuple[threading.Event, list[dict[str, Any]]]] = {}
        self._reader: threading.Thread | None = None

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self, timeout_s: float = 15.0) -> dict[str, str]:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        env.pop("QT_QPA_PLATFORM", None)
        self.proc = subprocess.Popen([self.python, "-m", "app.devices.sim.host"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, cwd=str(ROOT), env=env, preexec_fn=die_with_parent)
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write((json.dumps(self.spec) + "\n").encode())
        self.proc.stdin.flush()
        ready = self._read_line(timeout_s)
        if ready is None or "ready" not in ready:
            self.stop()
            raise SimulatorProcessError(f"the simulator process did not start within {timeout_s:.0f} s")
        self.urls = dict(ready["ready"])
        self._reader = threading.Thread(target=self._read_loop, name="sim-host reader", daemon=True)
        self._reader.start()
        return self.urls

    def _read_line(self, timeout_s: float) -> dict[str, Any] | None:
        assert self.proc is not None and self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout_s
        line = b""
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                return None
            byte = os.read(fd, 1)
            if not byte:
                return None
            line += byte
        return json.loads(line)

    def _read_loop(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for raw in self.proc.stdout:
            try:
                message = json.loads(raw)
            except ValueError:
                continue
            if "event" in message:
                self.events = [*self.events[-999:], message]
                for fn in self.event_listeners:
                    with contextlib.suppress(Exception):
                        fn(message)
                continue
            with self._lock:
                waiter = self._waiting.pop(message.get("id"), None)
            if waiter is not None:
                waiter[1].append(message)
                waiter[0].set()
        with self._lock:  # the child ended: nobody answers any more
            for event, _box in self._waiting.values():
                event.set()
            self._waiting.clear()

    def call(self, op: str, timeout_s: float = 3.0, **fields: Any) -> Any:
        """One control request; returns its result or raises SimulatorProcessError / ValueError."""
        if not self.alive:
            raise SimulatorProcessError("the simulator process is not running")
        done, box = threading.Event(), []
        with self._lock:
            self._seq += 1
            ident = self._seq
            self._waiting[ident] = (done, box)
            try:
                self.proc.stdin.write((json.dumps({"id": ident, "op": op, **fields}) + "\n").encode())  # type: ignore[union-attr]
                self.proc.stdin.flush()  # type: ignore[union-attr]
            except OSError as exc:
                self._waiting.pop(ident, None)
                raise SimulatorProcessError(f"the simulator process is gone: {exc}") from exc
        if not done.wait(timeout_s) or not box:
            raise SimulatorProcessError(f"the simulator process did not answer {op} within {timeout_s:.1f} s")
        reply = box[0]
        if not reply.get("ok"):
            raise ValueError(reply.get("error", "refused"))
        return reply.get("result")

    def stop(self, timeout_s: float = 2.0) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        with contextlib.suppress(OSError, ValueError):
            proc.stdin.write(b'{"op": "quit"}\n')  # type: ignore[union-attr]
            proc.stdin.flush()  # type: ignore[union-attr]
        with contextlib.suppress(OSError, ValueError):
            proc.stdin.close()  # type: ignore[union-attr]
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
        if self._reader is not None:
            self._reader.join(timeout_s)
        with contextlib.suppress(OSError, ValueError):
            proc.stdout.close()  # type: ignore[union-attr]


class RemoteSimulator:
    """One device's simulator in the simulator process, with the in-process simulator's controls."""

    def __init__(self, name: str, process: SimulatorProcess, link_path: Path, tcp_port: int | None = None) -> None:
        self.name = name
        self.process = process
        self.link_path = link_path  # the stable path the simulator process puts its pty behind
        self.tcp_port = tcp_port  # or the loopback port it listens on
        self._running = True
        self._keep_host_log = False
        self._host_log: list[tuple[float, bytes]] = []  # what has been fetched so far (only new rows travel)

    @property
    def url(self) -> str:
        return socket_link_url(self.tcp_port) if self.tcp_port else str(self.link_path)

    @property
    def running(self) -> bool:
        return self._running and self.process.alive

    def start(self) -> None:
        """Started with the process (the manager's start() call is a no-op)."""

    def stop(self) -> None:
        """Stopped with the process."""

    def kill(self) -> None:
        self.process.call("kill", device=self.name)
        self._running = False

    def restart(self, fresh_state: bool = True) -> None:
        self.process.call("restart", device=self.name)
        self._running = True

    def control(self, name: str, *args: Any) -> Any:
        return self.process.call("control", device=self.name, name=name, args=list(args))

    # For tests that look at the far end of the link, as with the in-process simulator.
    @property
    def keep_host_log(self) -> bool:
        return self._keep_host_log

    @keep_host_log.setter
    def keep_host_log(self, keep: bool) -> None:
        self.process.call("host_log", device=self.name, keep=bool(keep))
        self._keep_host_log = bool(keep)

    def clear_host_log(self) -> None:
        """Forget the bytes logged so far (a shared test rig between tests)."""
        self.process.call("host_log", device=self.name, clear=True)
        self._host_log.clear()

    @property
    def host_bytes_log(self) -> list[tuple[float, bytes]]:
        """(monotonic time, bytes) of every read the simulator made while keep_host_log was on; a copy."""
        answer = self.process.call("host_log", device=self.name, since=len(self._host_log), timeout_s=10.0)
        del self._host_log[int(answer["from"]):]
        self._host_log.extend((float(t), bytes.fromhex(h)) for t, h in answer["rows"])
        return list(self._host_log)


    def device_log(self, since: int = 0, keep: bool | None = None) -> tuple[int, list[tuple[float, bytes]]]:
        """(first row's index, rows) of what the device wrote since row ``since`` (monotonic time, bytes),
        stamped in the simulator process; ``keep`` switches the log on or off (benchmarks)."""
        fields: dict[str, Any] = {"since": since}
        if keep is not None:
            fields["keep"] = bool(keep)
        answer = self.process.call("device_log", device=self.name, timeout_s=10.0, **fields)
        return int(answer["from"]), [(float(t), bytes.fromhex(h)) for t, h in answer["rows"]]


class ThreadHostedControls:
    """``control()`` for the in-process SerialSimulator (same names as the remote one)."""

    @staticmethod
    def control(sim: Any, name: str, *args: Any) -> Any:
        fn = DEVICE_CONTROLS[name]
        return sim.with_core(lambda core: fn(core, *args))


class RemotePatient:
    """The simulated patient in the simulator process: the SimulatedPatient behaviours the panel uses."""

    def __init__(self, process: SimulatorProcess) -> None:
        self.process = process
        self._settings: Any = None  # the behaviours change only through these calls: no polling

    def settings(self) -> Any:
        if self._settings is None:
            self._settings = patient_settings_from(self.process.call("patient_settings"))
        return self._settings

    def __getattr__(self, method: str) -> Callable[..., None]:
        if method not in PATIENT_METHODS:
            raise AttributeError(method)

        def call(*args: Any, **kwargs: Any) -> None:  # as the in-process patient's methods take them
            self._settings = patient_settings_from(self.process.call("patient", method=method, args=list(args),
                                                                     kwargs=dict(kwargs)))

        return call


if __name__ == "__main__":
    sys.exit(child_main())
