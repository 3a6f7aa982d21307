"""The real application as a subprocess (``main.py``), its LINarm and FES simulated in a simulator process the
test owns, so that the test reads what reached the devices' side of the wire after the app stopped, froze
or died (issue #25). The app opens the simulators' loopback ports as it would open real serial ports
(``mode: serial``, ``socket://``); the physiological board and the UDP peers are off."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from app.core.links import simulator_link
from app.wire.cmdmessenger import ArduinoReceiver
from app.wire.linarm_protocol import CommandRejected, read_host_message
from app.wire.sciencemode import (
    Sm1CommandDecoder,
    Sm1Stop,
    Sm1Update,
    Sm2Decoder,
    Sm2StartChannelListMode,
    Sm2StopChannelListMode,
)

ROOT = Path(__file__).resolve().parent.parent

# Stimulates from 0.25 s on at 10 mA / 150 µs and runs far longer than any test.
PROFILE_YAML = """\
version: 1
name: signals test profile
axis: time
frequency_hz: 30.0
channels:
  1:
    muscle: test
    mode: single
    current_ma: {level: 10.0, ramp_up: [0.0, 0.25], ramp_down: [100.0, 101.0], baseline: 0.0}
    pulse_width_us: {level: 150.0, ramp_up: [0.0, 0.25], ramp_down: [100.0, 101.0], baseline: 0.0}
"""

# An exercise with FES: the robot ON and moving, stimulation on, until stopped.
EXERCISE = """\
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
fes.loadFile({profile!r})
fes.start()
print("STIMULATING", flush=True)
while True:
    linarm.moveCentreTo(0.30, 0.1, 0.2, 0, False)
    wait(0.5)
    linarm.moveCentreTo(0.20, 0.1, 0.2, 0, False)
    wait(0.5)
"""

# The window, as `python main.py --config FILE` runs it, with a session recording and the exercise above
# started once every device is connected (as the Exercises panel would start it).
WINDOW_LAUNCHER = r"""
import sys
from pathlib import Path
from PySide6.QtCore import QTimer
from app import manager as manager_module

script, sessions = Path(sys.argv[1]), Path(sys.argv[2])
original_start = manager_module.LinarmppManager.start


def start(self):
    original_start(self)

    def begin():
        fes = self.driver("fes")
        if not (self.all_connected() and fes is not None and fes.device_ready):
            QTimer.singleShot(50, begin)
            return
        from app.scripting.runner import ScriptRunner

        self.start_session("signals-test", "test", root=sessions)
        runner = ScriptRunner(self, lambda stream, text: (sys.stdout.write(text), sys.stdout.flush()))
        self._test_runner = runner
        runner.start(script.read_text(), str(script))

    QTimer.singleShot(0, begin)


manager_module.LinarmppManager.start = start
from app.cli import main

sys.exit(main(["--config", sys.argv[3]]))
"""


def wire(sim: Any, protocol: str) -> list[tuple[float, object]]:
    """(time the device read it, command) for everything the app sent to the stimulator."""
    decoder = Sm1CommandDecoder() if protocol == "sm1" else Sm2Decoder()
    out: list[tuple[float, object]] = []
    for t, data in list(sim.host_bytes_log):
        out += [(t, msg) for msg in decoder.feed(data)]
    return out


def first_fes_stop_after(sim: Any, protocol: str, t0: float) -> float | None:
    return next((t for t, msg in wire(sim, protocol) if t >= t0 and isinstance(msg, Sm1Stop | Sm2StopChannelListMode)),
                None)


def last_fes_update_before(sim: Any, protocol: str, t0: float) -> float | None:
    times = [t for t, msg in wire(sim, protocol) if t < t0 and isinstance(msg, Sm1Update | Sm2StartChannelListMode)]
    return times[-1] if times else None


def robot_idle_after(sim: Any, t0: float) -> float | None:
    receiver = ArduinoReceiver()
    for t, data in list(sim.host_bytes_log):
        for msg in receiver.feed(data):
            try:
                cmd = read_host_message(msg)
            except CommandRejected:
                continue
            if t >= t0 and cmd.name == "setCtrlState" and cmd.args["controlState"] == 0:
                return t
    return None


class AppProcess:
    """The devices' simulator process (owned by the test) and the app under test."""

    def __init__(self, tmp_path: Path, protocol: str = "sm1") -> None:
        from app.devices.sim.host import RemoteSimulator, SimulatorProcess, free_tcp_port

        self.tmp = tmp_path
        self.protocol = protocol
        ports = {"linarm": free_tcp_port(), "fes": free_tcp_port()}
        spec = {"runtime_dir": str(tmp_path / "sim"), "patient_seed": 7, "linger_s": 0.0,
                "devices": {"linarm": {"kind": "linarm", "tcp_port": ports["linarm"]},
                            "fes": {"kind": "fes", "protocol": protocol, "tcp_port": ports["fes"]}}}
        (tmp_path / "sim").mkdir(exist_ok=True)
        self.sims_process = SimulatorProcess(spec)
        self.sims_process.start()
        links = tmp_path / "sim"
        self.robot_sim = RemoteSimulator("linarm", self.sims_process, simulator_link(links, "linarm"), ports["linarm"])
        self.fes_sim = RemoteSimulator("fes", self.sims_process, simulator_link(links, "fes"), ports["fes"])
        self.robot_sim.keep_host_log = True
        self.fes_sim.keep_host_log = True
        self.config = tmp_path / "config.yaml"
        self.config.write_text(
            "version: 1\n"
            "devices:\n"
            f"  linarm: {{mode: serial, port: 'socket://127.0.0.1:{ports['linarm']}'}}\n"
            "  physio: {mode: 'off'}\n"
            f"  fes: {{mode: serial, port: 'socket://127.0.0.1:{ports['fes']}', protocol: {protocol}}}\n"
            "  patient_model: {mode: 'off'}\n"
            "  vr: {mode: 'off'}\n"
            "ui: {ask_session_on_start: false}\n", encoding="utf-8")
        profile = tmp_path / "profile.yaml"
        profile.write_text(PROFILE_YAML, encoding="utf-8")
        self.script = tmp_path / "exercise.py"
        self.script.write_text(EXERCISE.format(profile=str(profile)), encoding="utf-8")
        self.sessions = tmp_path / "sessions"
        self.proc: subprocess.Popen[str] | None = None
        self.output: list[str] = []
        self._reader: threading.Thread | None = None

    # ------------------------------------------------------------------ the app
    def _env(self) -> dict[str, str]:
        env = {**os.environ, "PYTHONPATH": str(ROOT), "LINARMPP_HOME": str(self.tmp / "home"),
               "PYTHONUNBUFFERED": "1"}
        env.pop("LINARMPP_SIM_HOST", None)
        return env

    def start_headless(self) -> None:
        self._spawn([sys.executable, str(ROOT / "main.py"), "--headless", "--config", str(self.config),
                     "--script", str(self.script), "--record", str(self.sessions)])

    def start_window(self) -> None:
        self._spawn([sys.executable, "-c", WINDOW_LAUNCHER, str(self.script), str(self.sessions), str(self.config)])

    def _spawn(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     env=self._env(), cwd=str(ROOT))

        def read() -> None:
            assert self.proc is not None and self.proc.stdout is not None
            for line in self.proc.stdout:
                self.output.append(line)

        self._reader = threading.Thread(target=read, name="app output", daemon=True)
        self._reader.start()

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def wait_stimulating(self, timeout_s: float = 40.0) -> None:
        """Until the script said so and the stimulator delivers current."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc is not None and self.proc.poll() is not None:
                raise AssertionError(f"the app ended ({self.proc.returncode}):\n{self.text()[-3000:]}")
            if any("STIMULATING" in line for line in self.output) and self.fes_sim.control("fes_channel_state"):
                return
            time.sleep(0.05)
        raise AssertionError(f"the app did not start stimulating within {timeout_s:.0f} s:\n{self.text()[-3000:]}")

    def text(self) -> str:
        return "".join(self.output)

    def wait_exit(self, timeout_s: float) -> int | None:
        assert self.proc is not None
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def manifests(self) -> list[dict[str, Any]]:
        return [json.loads(p.read_text(encoding="utf-8")) for p in self.sessions.rglob("manifest.json")]

    # ------------------------------------------------------------------ what reached the devices
    def fes_stop_after(self, t0: float) -> float | None:
        return first_fes_stop_after(self.fes_sim, self.protocol, t0)

    def robot_idle_after(self, t0: float) -> float | None:
        return robot_idle_after(self.robot_sim, t0)

    def stimulating_on_the_device(self) -> bool:
        return bool(self.fes_sim.control("fes_channel_state"))

    def close(self) -> None:
        if self.proc is not None:
            if self.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.proc.pid, signal.SIGCONT)
                self.proc.kill()
            self.proc.wait(10)
            if self._reader is not None:
                self._reader.join(5)
            if self.proc.stdout is not None:
                self.proc.stdout.close()
        self.sims_process.stop()
        if self.proc is not None:
            left = wait_guardians_gone(self.proc.pid)
            assert not left, f"the app's FES guardian outlived it: {left}"


def guardians_of(app_pid: int) -> list[int]:
    """The FES guardian processes (app.devices.fes_guardian) started by the app ``app_pid``."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
            state = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z" and any(a.endswith(b"fes_guardian.py") for a in argv) and str(app_pid).encode() in argv:
            found.append(int(entry))
    return found


def wait_guardians_gone(app_pid: int, timeout_s: float = 3.0) -> list[int]:
    """A guardian ends by itself when its app has gone; kill any left after ``timeout_s`` and return them."""
    deadline = time.monotonic() + timeout_s
    while (left := guardians_of(app_pid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return left


def burst(pid: int, signum: int, count: int = 200, gap_s: float = 0.002) -> float:
    """``count`` signals ``gap_s`` apart; returns the time of the first."""
    t0 = time.monotonic()
    for _ in range(count):
        try:
            os.kill(pid, signum)
        except ProcessLookupError:
            break
        time.sleep(gap_s)
    return t0
