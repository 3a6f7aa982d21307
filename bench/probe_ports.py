"""#25's port and LINarm-link rows, re-run: a second process opens the robot's tty, a new client on a simulator's
TCP port, garbage and forged frames on the LINarm link. Prints figures (docs/fault-policy.md has a run).

    .venv/bin/python bench/probe_ports.py [tty] [tcp] [garbage]

Simulated devices on loopback only. ``tty``: the simulator on a pty (``simulation: {link: pty}``, as with real
hardware); a locking open, a plain open without CAP_SYS_ADMIN and a second LINarm++ transport are tried, then a
privileged intruder (it passes TIOCEXCL) re-homes and switches the robot ON every 50 ms for 10 s with F12 latched
while reading the tty; the time the controller spent out of IDLE comes from the simulator process's state events.
``tcp``: ~9 clients a second for 20 s on the simulator's loopback port, each sending goToHome and ON.
``garbage``: 600 KB of bytes that are no frame, then 12 forged frames (over-speed vsa + errorEvent) in 0.1 s.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ["LINARMPP_HOME"] = tempfile.mkdtemp(prefix="probe-ports-home-")

from PySide6.QtCore import QCoreApplication  # noqa: E402

from app.core.bus import Subscription  # noqa: E402
from app.core.config import AppConfig, SimulationConfig  # noqa: E402
from app.core.journal import Record  # noqa: E402
from app.devices import linarm  # noqa: E402
from app.devices.transport import SerialTransport, TransportError  # noqa: E402
from app.manager import LinarmppManager  # noqa: E402
from app.session.recording import load_session  # noqa: E402
from app.wire import linarm_protocol as proto  # noqa: E402

app = QCoreApplication.instance() or QCoreApplication([])

LOCKING_OPEN = textwrap.dedent("""
    import serial, sys
    try:
        serial.Serial(sys.argv[1], exclusive=True)
        print("opened")
    except serial.SerialException as exc:
        print("refused:", exc)
""")
PLAIN_OPEN = textwrap.dedent("""
    import os, sys
    try:
        os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY)
        print("opened")
    except OSError as exc:
        print("refused:", exc)
""")
HOLDER = textwrap.dedent("""
    import os, sys
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY)
    print("holding", flush=True)
    sys.stdin.readline()
""")
INTRUDER = textwrap.dedent("""
    import os, sys, time
    sys.path.insert(0, sys.argv[2])
    from app.wire import linarm_protocol as proto
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    print("opened", flush=True)
    seq = 100
    def send(name, *args):
        global seq
        seq = proto.next_seq(seq)
        try:
            os.write(fd, b";" + proto.encode_command(name, seq, *args))
        except OSError:
            pass
    end = time.monotonic() + float(sys.argv[3])
    stolen = 0
    while time.monotonic() < end:
        send("heartbeat")
        send("resetError")
        send("goToHome")
        send("setCtrlState", 2)
        send("setCtrlMode", 1)
        send("moveCentreTo", 0.35 if int(time.monotonic()) % 2 else 0.15, 0.1, 0.5, 0.0, False)
        try:
            stolen += len(os.read(fd, 65536))
        except BlockingIOError:
            pass
        time.sleep(0.05)
    print("stole", stolen, "bytes", flush=True)
""")


def pump(seconds: float, until: Callable[[], bool] | None = None) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        app.processEvents()
        if until is not None and until():
            return
        time.sleep(0.002)


def start(link: str, host: str = "process") -> LinarmppManager:
    os.environ["LINARMPP_SIM_HOST"] = host
    manager = LinarmppManager(AppConfig(simulation=SimulationConfig(link=link)), factories={"linarm": linarm.create})
    manager.start()
    driver = manager.driver("linarm")
    pump(10, lambda: driver.connected and driver.latest("linarm.state") is not None)
    if not driver.connected:
        raise SystemExit("the LINarm did not connect")
    return manager


def disconnects(link_events: Subscription) -> list[str]:
    """The LINarm driver's disconnections (their reasons) since the subscription began."""
    return [item.detail for item in link_events.drain()
            if isinstance(item, Record) and item.origin == "linarm" and item.kind == "disconnected"]


def out_of_idle(events: list[dict[str, Any]], t0: float, t1: float) -> tuple[float, float]:
    """(total, longest) seconds the controller reported a state other than IDLE within [t0, t1]."""
    total = longest = 0.0
    state, since = 0, t0
    for e in events:
        if e.get("event") != "linarm_state":
            continue
        t, s = e["t"], e["control_state"]
        if t < t0:
            state = s
            continue
        if t > t1:
            break
        if state != 0:
            total, longest = total + t - since, max(longest, t - since)
        state, since = s, t
    if state != 0:
        total, longest = total + t1 - since, max(longest, t1 - since)
    return total, longest


def describe_alarms(alarms: list[Any]) -> list[str]:
    counts: dict[str, list[int]] = {}
    for a in alarms:
        row = counts.setdefault(a.text[:90], [0, 0])
        row[0] += 1
        row[1] += getattr(a, "repeats", 0)
    return [f"alarm x{n} (+{r} repeats counted): {text}" for text, (n, r) in counts.items()]


def child(code: str, *args: str, **kwargs: Any) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-c", code, *args], text=True, **kwargs)


def row_tty(seconds: float = 10.0) -> None:
    print("== a second process opens the robot's tty (simulation: {link: pty})")
    manager = start("pty")
    driver = manager.driver("linarm")
    url = driver.transport.url
    link_events = manager.bus.subscribe("probe link events", (), events=True)
    locking = subprocess.run([sys.executable, "-c", LOCKING_OPEN, url], capture_output=True, text=True)
    print("  a locking open (pyserial exclusive):", locking.stdout.strip())
    if shutil.which("setpriv"):
        plain = subprocess.run(["setpriv", "--bounding-set", "-sys_admin", "--inh-caps", "-sys_admin", "--",
                                sys.executable, "-c", PLAIN_OPEN, url], capture_output=True, text=True)
        print("  a plain open() without CAP_SYS_ADMIN:", plain.stdout.strip())
    holder = child(HOLDER, url, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert holder.stdout is not None
    holder.stdout.readline()
    try:
        SerialTransport(url).open()
        print("  a second LINarm++ transport: opened")
    except TransportError as exc:
        print(f"  a second LINarm++ transport (pid {holder.pid} holds the tty as well): {exc}")
    holder.communicate("\n", timeout=10)
    sup = manager.supervisor
    sup.emergency_stop("probe", "F12")
    n_alarms = len(sup.alarms())
    t0 = time.monotonic()
    intruder = child(INTRUDER, url, str(ROOT), str(seconds), stdout=subprocess.PIPE)
    assert intruder.stdout is not None
    opened = intruder.stdout.readline().strip()
    pump(seconds + 1.0)
    said = intruder.communicate(timeout=10)[0].strip()
    total, longest = out_of_idle(list(manager.simulators.process.events), t0, time.monotonic())
    print(f"  a privileged intruder (CAP_SYS_ADMIN passes TIOCEXCL): {opened}, {said}; {seconds:.0f} s, F12 latched:")
    print(f"    robot out of IDLE {total:.3f} s in total, longest stretch {longest * 1000:.0f} ms; "
          f"driver disconnects: {len(disconnects(link_events))}")
    for line in describe_alarms(sup.alarms()[n_alarms:]):
        print("   ", line)
    manager.shutdown()


def row_tcp(seconds: float = 20.0) -> None:
    print("== a new client on a simulator's TCP port")
    manager = start("socket")
    driver = manager.driver("linarm")
    host, _, port = driver.transport.url[len("socket://"):].partition(":")
    link_events = manager.bus.subscribe("probe link events", (), events=True)
    manager.supervisor.emergency_stop("probe", "F12")
    tries = refused = served = 0
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        tries += 1
        try:
            with socket.create_connection((host, int(port)), timeout=1.0) as intruder:
                on = int(proto.ControlState.ON_CTRL_STATE)
                home_then_on = proto.encode_command("goToHome", 5) + proto.encode_command("setCtrlState", 6, on)
                intruder.sendall(b";" + home_then_on)
                intruder.settimeout(0.2)
                if intruder.recv(4096):
                    served += 1
                else:
                    refused += 1
        except (ConnectionResetError, ConnectionRefusedError, BrokenPipeError):
            refused += 1
        except TimeoutError:
            served += 1
        pump(0.1)
    total, _ = out_of_idle(list(manager.simulators.process.events), t0, time.monotonic())
    kicked = len(disconnects(link_events))
    print(f"  {tries} intruding clients in {seconds:.0f} s: {refused} refused, {served} served; driver kicked "
          f"{kicked} times; robot out of IDLE {total:.3f} s; driver connected at the end: {driver.connected}")
    manager.shutdown()


def row_garbage() -> None:
    print("== garbage on the LINarm link")
    manager = start("pty", host="thread")
    folder = manager.start_session("PROBE", "probe", root=Path(tempfile.mkdtemp()) / "sessions")
    sim = manager.devices["linarm"].simulator
    junk = bytes(b for b in range(256) if b not in b";/") * 4
    sent = 0
    t0 = time.monotonic()
    while sent < 600_000:
        sim.link.write(junk + b";")
        sent += len(junk) + 1
        pump(0.001)
    spent = time.monotonic() - t0
    vsa = sim.core.core.vsa_state()
    fields = {f: getattr(vsa, f) for f in vsa.__slots__}
    forged_vsa = proto.encode_vsa_state(proto.VsaState(**{**fields, "handle_vel": 5.0}))
    forged_error = proto.encode_error_event(
        proto.ErrorEvent(1, proto.ErrorState.TRACKING_ERROR, proto.ControlState.IDLE_CTRL_STATE, "forged"))
    n_alarms = len(manager.supervisor.alarms())
    for _ in range(12):
        sim.link.write(forged_vsa + forged_error)
        pump(0.008)
    pump(1.5)
    alarms = manager.supervisor.alarms()[n_alarms:]
    manager.end_session()
    records = [e["data"] for e in load_session(folder).events if e["kind"] == "link_garbage"]
    last = records[-1] if records else {}
    print(f"  {sent / 1000:.0f} KB of garbage in {spent:.1f} s: {len(records)} link_garbage records; last: "
          f"bad_frames={last.get('bad_frames')} bytes_discarded={last.get('bytes_discarded')} "
          f"undecodable={last.get('undecodable_frames')}")
    print(f"  12 forged frames (over-speed vsa + errorEvent) in ~0.1 s: {len(alarms)} alarms")
    for line in describe_alarms(alarms):
        print("   ", line)
    manager.shutdown()


if __name__ == "__main__":
    rows = {"tty": row_tty, "tcp": row_tcp, "garbage": row_garbage}
    for name in sys.argv[1:] or list(rows):
        rows[name]()
    os._exit(0)  # nothing of the probe's to wait for: every manager was shut down
