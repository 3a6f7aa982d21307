"""The app owns its ports (#25): a second open of the robot's tty fails, naming the process that holds it, and
a second client on a simulator's loopback port is refused while the driver keeps its connection. Before, a
second process opened the tty beside the app (and drove the robot with the e-stop latched), and a new TCP
client replaced the driver's connection (the app was kicked 187 times in 20 s)."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import serial

from app.core.bus import Subscription
from app.core.config import AppConfig, SimulationConfig
from app.core.journal import Record
from app.devices import linarm, transport
from app.devices.transport import PtyLink, SerialTransport, SocketLink, TransportError
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.wire import linarm_protocol as proto

ROOT = Path(__file__).resolve().parent.parent

HOLDER = textwrap.dedent("""
    import sys, time
    from app.devices.transport import SerialTransport
    t = SerialTransport(sys.argv[1])
    t.open()
    print("open", flush=True)
    sys.stdin.readline()
    t.close()
""")

# A plain open() with no lock asked, as `cat`, `screen` or a careless script would do.
PLAIN_OPEN = textwrap.dedent("""
    import os, sys
    try:
        os.close(os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY))
        print("opened")
    except OSError as exc:
        print("refused", exc.errno)
""")
LOCKING_OPEN = textwrap.dedent("""
    import serial, sys
    try:
        serial.Serial(sys.argv[1], exclusive=True)
        print("opened")
    except serial.SerialException as exc:
        print("refused", exc)
""")


def _connects(link_events: Subscription, device: str) -> list[bool]:
    """The device's connection changes (True: connected) since the subscription began."""
    return [item.kind == "connected" for item in link_events.drain()
            if isinstance(item, Record) and item.origin == device and item.kind in ("connected", "disconnected")]


def _python(code: str, *args: str, **kwargs) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-c", code, *args], env=env, text=True, cwd=str(ROOT), **kwargs)


def _without_cap_sys_admin(code: str, *args: str) -> str | None:
    """Run ``code`` in a process without CAP_SYS_ADMIN (which may open an exclusive tty anyway): as root,
    through setpriv; as another user, directly. None when that cannot be arranged here."""
    if os.geteuid() != 0:
        cmd = [sys.executable, "-c", code, *args]
    elif shutil.which("setpriv"):
        cmd = ["setpriv", "--bounding-set", "-sys_admin", "--inh-caps", "-sys_admin", "--", sys.executable, "-c",
               code, *args]
    else:
        return None
    return subprocess.run(cmd, capture_output=True, text=True, timeout=20, check=True).stdout.strip()


# ------------------------------------------------------------------------------------------ the robot's tty
def test_a_second_open_of_a_held_tty_fails_and_names_the_holder(tmp_path) -> None:
    link = PtyLink(tmp_path / "linarm.tty")
    holder = _python(HOLDER, link.url, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "open"
        second = SerialTransport(link.url)
        with pytest.raises(TransportError) as refused:
            second.open()
        message = str(refused.value)
        assert f"pid {holder.pid}" in message and "in use by another program" in message, message
        assert "python" in message  # the holder's command line, not just a number
        # Any program that asks for the lock (pyserial's exclusive) is refused too, not only LINarm++.
        with pytest.raises(serial.SerialException):
            serial.Serial(link.url, exclusive=True).close()
        # The pty's far end (the simulator holding the master) is not named as a holder.
        assert [pid for pid, _ in transport.port_holders(link.url)] == [holder.pid]
    finally:
        holder.communicate("\n", timeout=10)
        link.close()
    assert holder.returncode == 0


def test_a_tty_that_goes_away_while_it_is_opened_is_a_transport_error(monkeypatch) -> None:
    """The simulator killed while the driver reconnects: tcflush raised termios.error (EIO), which is not an
    OSError, out of the driver's thread (a teardown error in a quiet suite). It is a failed open, retried."""
    import termios

    master, slave = os.openpty()
    try:
        def gone(self: serial.Serial) -> None:
            raise termios.error(errno.EIO, "Input/output error")

        monkeypatch.setattr(serial.Serial, "reset_input_buffer", gone)
        link = SerialTransport(os.ttyname(slave))
        with pytest.raises(TransportError, match="went away"):
            link.open()
        assert link._port is None
        monkeypatch.undo()
        link.open()  # the tty is free again: the failed open left no exclusive flag behind
        link.close()
    finally:
        os.close(slave)
        os.close(master)


def test_a_plain_open_is_refused_while_the_app_holds_the_tty_and_allowed_after(tmp_path) -> None:
    """TIOCEXCL: a program that asks for no lock gets EBUSY (unless it has CAP_SYS_ADMIN); our close clears it,
    so our own reconnect (and anyone after us) can open the port again."""
    link = PtyLink(tmp_path / "linarm.tty")
    app_side = SerialTransport(link.url)
    try:
        app_side.open()
        answer = _without_cap_sys_admin(PLAIN_OPEN, link.url)
        if answer is None:
            pytest.skip("cannot run a process without CAP_SYS_ADMIN here (no setpriv)")
        assert answer == f"refused {errno.EBUSY}", answer
        app_side.close()
        assert _without_cap_sys_admin(PLAIN_OPEN, link.url) == "opened"
        app_side.open()  # our own reopen after a close
        assert app_side.is_open
    finally:
        app_side.close()
        link.close()


@pytest.mark.realtime
def test_the_apps_robot_tty_cannot_be_opened_a_second_time(qtbot) -> None:
    """As with real hardware (``simulation: {link: pty}``): while the app drives the LINarm, a second program
    cannot open its tty, and the app's link is untouched."""
    config = AppConfig(simulation=SimulationConfig(link="pty"))
    manager = LinarmppManager(config, factories={"linarm": linarm.create})
    manager.start()
    try:
        driver = manager.driver("linarm")
        qtbot.waitUntil(lambda: driver.connected and driver.latest("linarm.state") is not None, timeout=10000)
        url = driver.transport.url
        assert not url.startswith("socket://")
        link_events = driver.bus.subscribe("test connects", (), events=True)
        probe = _python(LOCKING_OPEN, url, stdout=subprocess.PIPE)
        out, _ = probe.communicate(timeout=20)
        assert out.startswith("refused"), out
        answer = _without_cap_sys_admin(PLAIN_OPEN, url)
        assert answer in (None, f"refused {errno.EBUSY}"), answer
        # Nobody else holds it: the simulator process (the pty's master, the device's end) is not counted.
        assert transport.port_holders(url) == []
        before = driver.total_samples("linarm.vsa")
        qtbot.waitUntil(lambda: driver.total_samples("linarm.vsa") > before + 50, timeout=5000)
        connects = _connects(link_events, driver.name)
        assert driver.connected and connects == []
    finally:
        manager.shutdown()


HOLD_PLAIN = textwrap.dedent("""
    import os, select, sys
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    print("open", flush=True)
    stolen = 0
    # Reads some of what the controller sends, now and then, until told to stop (as a terminal program left open
    # on the port does between keystrokes). A reader that drains the tty as fast as it can takes most frames and
    # the handshake's answer under load: that link cannot stay up, and only the alarm naming it is owed.
    while not select.select([sys.stdin], [], [], 0.2)[0]:
        if select.select([fd], [], [], 0.1)[0]:
            try:
                stolen += len(os.read(fd, 64))
            except BlockingIOError:
                pass
    print("stolen", stolen, flush=True)
""")


@pytest.mark.realtime
def test_a_program_holding_the_robots_tty_at_connect_is_named_in_a_stop_alarm(qtbot) -> None:
    """A program that asked for no lock and opened the tty first (or a privileged one, which TIOCEXCL does not
    stop), and reads from it: the app connects, names it in a STOP alarm (one), the robot is held IDLE until it
    is acknowledged, and the app stays connected (bytes the other reader took are not a lost link)."""
    config = AppConfig(simulation=SimulationConfig(link="pty"))
    manager = LinarmppManager(config, factories={"linarm": linarm.create})
    manager.start()
    holder = None
    try:
        driver = manager.driver("linarm")
        driver.reconnect_backoff_s = (0.05, 0.2)
        qtbot.waitUntil(lambda: driver.connected, timeout=10000)
        manager.set_device_running("linarm", False)
        holder = _python(HOLD_PLAIN, driver.transport.url, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert holder.stdout is not None and holder.stdout.readline().strip() == "open"
        manager.set_device_running("linarm", True)
        qtbot.waitUntil(lambda: any(f"pid {holder.pid}" in a.text for a in manager.supervisor.alarms()),
                        timeout=5000)
        qtbot.waitUntil(lambda: driver.connected, timeout=5000)
        link_events = driver.bus.subscribe("test connects", (), events=True)
        before = driver.total_samples("linarm.vsa")
        qtbot.waitUntil(lambda: driver.total_samples("linarm.vsa") > before + 100, timeout=5000)
        named = [a for a in manager.supervisor.alarms() if f"pid {holder.pid}" in a.text]
        assert len(named) == 1 and named[0].level == AlarmLevel.STOP, [a.text for a in named]
        assert named[0].text.startswith("Another program has the LINarm's port open") and "python" in named[0].text
        assert manager.supervisor.robot_hold_reason()
        connects = _connects(link_events, driver.name)
        assert connects == [] and driver.connected
    finally:
        if holder is not None:
            out, _ = holder.communicate("\n", timeout=10)
            print(out.strip())  # "stolen N": the bytes it took (none when the app read them all first)
        manager.shutdown()


def test_a_program_holding_the_robots_tty_is_named_even_when_the_controller_does_not_identify(qtbot) -> None:
    """The holder may take the controller's answer to the handshake (it reads the same tty): the app, never
    identified, used to drop the link and retry without naming it (the holder was named only once connected —
    under load 1 run in 3 of the test above timed out waiting for the alarm). With the simulator stopped the
    controller never answers: the holder is named in the STOP alarm all the same."""
    config = AppConfig(simulation=SimulationConfig(link="pty"))
    manager = LinarmppManager(config, factories={"linarm": linarm.create})
    manager.start()
    holder = None
    simulator = None
    try:
        driver = manager.driver("linarm")
        driver.reconnect_backoff_s = (0.05, 0.2)
        qtbot.waitUntil(lambda: driver.connected, timeout=10000)
        simulator = manager.simulators.process.pid
        assert simulator is not None
        manager.set_device_running("linarm", False)
        holder = _python(HOLD_PLAIN, driver.transport.url, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert holder.stdout is not None and holder.stdout.readline().strip() == "open"
        os.kill(simulator, signal.SIGSTOP)  # no answer to the handshake: the link is never identified
        manager.set_device_running("linarm", True)
        qtbot.waitUntil(lambda: any(f"pid {holder.pid}" in a.text for a in manager.supervisor.alarms()),
                        timeout=5000)
        assert not driver.connected
        named = [a for a in manager.supervisor.alarms() if f"pid {holder.pid}" in a.text]
        assert len(named) == 1 and named[0].level == AlarmLevel.STOP, [a.text for a in named]
    finally:
        if simulator is not None:
            os.kill(simulator, signal.SIGCONT)
        if holder is not None:
            holder.communicate("\n", timeout=10)
        manager.shutdown()


# ------------------------------------------------------------------------------------ the simulator's socket
def _connect(url: str) -> socket.socket:
    host, _, port = url[len("socket://"):].partition(":")
    return socket.create_connection((host, int(port)), timeout=2.0)


def _refused(sock: socket.socket, timeout: float = 2.0) -> bool:
    """True when the server ends this connection (EOF or reset) within ``timeout``."""
    sock.settimeout(timeout)
    try:
        while True:
            data = sock.recv(4096)
            if not data:
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False
    finally:
        sock.close()


def _intrude(url: str) -> bool:
    """A second controller connects and sends setCtrlState ON; True when the link refused it (reset or closed
    at connect, or closed before it heard anything), False when it was served device data."""
    try:
        intruder = _connect(url)
    except (ConnectionResetError, ConnectionRefusedError):
        return True
    try:
        intruder.sendall(proto.encode_command("setCtrlState", 1, int(proto.ControlState.ON_CTRL_STATE)) * 20)
        intruder.settimeout(1.0)
        return not intruder.recv(4096)
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False
    finally:
        intruder.close()


def test_a_socket_link_keeps_its_driver_and_refuses_a_second_client_until_the_driver_leaves() -> None:
    link = SocketLink()
    try:
        driver = _connect(link.url)
        link.wait_readable(0.2)  # accepts the driver
        assert link.clients_accepted == 1
        try:
            intruder: socket.socket | None = _connect(link.url)
        except ConnectionResetError:
            intruder = None
        deadline = time.monotonic() + 2.0
        while link.clients_refused == 0 and time.monotonic() < deadline:
            link.wait_readable(0.05)
        assert intruder is None or _refused(intruder)
        link.write(b"still yours;")
        driver.settimeout(2.0)
        assert driver.recv(64) == b"still yours;"
        # The driver's own reconnect after a real loss: its old connection is gone, the new one is accepted.
        driver.close()
        again = _connect(link.url)
        deadline = time.monotonic() + 2.0
        while link.clients_accepted < 2 and time.monotonic() < deadline:
            link.wait_readable(0.05)
        link.write(b"welcome back;")
        again.settimeout(2.0)
        assert again.recv(64) == b"welcome back;"
        again.close()
    finally:
        link.close()
    assert link.clients_refused == 1 and link.clients_accepted == 2


@pytest.mark.realtime
def test_a_second_client_on_the_simulators_port_is_refused_and_the_driver_keeps_its_link(qtbot) -> None:
    """The simulator process's loopback link (the default): 50 intruding clients in a row; the app's driver is
    never kicked (before: each new client replaced the driver's connection)."""
    config = AppConfig(simulation=SimulationConfig(link="socket"))
    manager = LinarmppManager(config, factories={"linarm": linarm.create})
    manager.start()
    try:
        driver = manager.driver("linarm")
        qtbot.waitUntil(lambda: driver.connected and driver.latest("linarm.state") is not None, timeout=10000)
        url = driver.transport.url
        assert url.startswith("socket://")
        link_events = driver.bus.subscribe("test connects", (), events=True)
        refused = sum(_intrude(url) for _ in range(50))
        before = driver.total_samples("linarm.vsa")
        qtbot.waitUntil(lambda: driver.total_samples("linarm.vsa") > before + 100, timeout=5000)
        connects = _connects(link_events, driver.name)
        assert driver.connected and connects == [], connects
        assert refused == 50
        # The far end agrees: the simulator process accepted one client (the driver) and refused the 50.
        stats = manager.simulators.process.call("link_stats", device="linarm")
        assert stats == {"accepted": 1, "refused": 50}, stats
        assert int(driver.latest("linarm.state").controlState) == 0  # nothing the intruders sent was executed
    finally:
        manager.shutdown()
