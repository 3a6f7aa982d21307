"""Byte transports: serial (pyserial, any URL) and UDP, plus the far-side links simulators sit on.

Drivers own one transport each; nothing else opens ports. Reads take a timeout so a driver's loop
notices a stop request promptly; writes are serialised by a lock so any thread may send (the
emergency stop must not wait behind a queue).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import serial

from app.core.links import DEFAULT_BAUDRATE, LOOPBACK, socket_link_url

log = logging.getLogger(__name__)

try:  # pyserial applies settings with termios; its error is not an OSError
    import termios
    from termios import error as termios_error
except ImportError:  # Windows
    termios = None  # type: ignore[assignment]

    class termios_error(Exception):  # noqa: N801 - stands in for termios.error
        pass

try:
    import fcntl
except ImportError:  # Windows: COM ports are exclusive by default
    fcntl = None  # type: ignore[assignment]

# A second open of the robot's port is refused (#25): pyserial's `exclusive` (flock: another LINarm++ or any
# program that asks for the lock) plus TIOCEXCL (the kernel refuses any further open() of the tty with EBUSY,
# except to a process with CAP_SYS_ADMIN). The errnos those refusals come back with:
_PORT_BUSY_ERRNOS = frozenset({errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK})


class TransportError(OSError):
    """The link is gone or cannot be opened; the message says why in plain words."""


class Transport(Protocol):
    description: str

    def open(self) -> None: ...
    def close(self) -> None: ...
    def read(self, timeout: float) -> bytes: ...
    def write(self, data: bytes) -> None: ...
    @property
    def is_open(self) -> bool: ...


@dataclass(frozen=True)
class SerialSettings:
    baudrate: int = DEFAULT_BAUDRATE
    bytesize: int = serial.EIGHTBITS
    parity: str = serial.PARITY_NONE
    stopbits: float = serial.STOPBITS_ONE
    rtscts: bool = False


class SerialTransport:
    """A pyserial port opened by URL: /dev/ttyACM0, COM3, a pty slave path, socket://host:port."""

    def __init__(self, url: str, settings: SerialSettings | None = None) -> None:
        self.url = url
        self.settings = settings or SerialSettings()
        self.description = f"serial {url} @ {self.settings.baudrate} Bd"
        self._port: serial.SerialBase | None = None
        self._write_lock = threading.Lock()
        # Other processes found holding the tty at our open (Linux; a process with CAP_SYS_ADMIN passes TIOCEXCL
        # and asks no lock): the driver raises it as an alarm naming them, it does not give the port up.
        self.shared_with: list[tuple[int, str]] = []
        self._holders_checked_at = 0.0

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        if self.url.startswith("socket://"):
            self._port = _LoopbackPort.connect(self.url)
            return
        s = self.settings
        device = "://" not in self.url and os.name == "posix"  # a tty path (not loop://, rfc2217://, ...)
        try:
            port = serial.serial_for_url(
                self.url, do_not_open=True, baudrate=s.baudrate, bytesize=s.bytesize,
                parity=s.parity, stopbits=s.stopbits, rtscts=s.rtscts, timeout=0.02, write_timeout=1.0,
                **({"exclusive": True} if device else {}),
            )
            port.open()
        except (serial.SerialException, OSError, ValueError, termios_error) as exc:
            if getattr(exc, "errno", None) in _PORT_BUSY_ERRNOS:
                raise TransportError(f"cannot open {self.url}: {port_in_use_message(self.url)}") from exc
            raise TransportError(f"cannot open {self.url}: {exc}") from exc
        if device:
            _set_tty_exclusive(port, True)
            self.shared_with = port_holders(self.url)
            if self.shared_with:
                log.warning("%s is also open in %s", self.url, ", ".join(f"pid {p} ({c})" for p, c in self.shared_with))
        try:
            port.reset_input_buffer()  # stale bytes from before we connected are not trustworthy
        except termios_error as exc:  # tcflush on a tty whose far end has just gone (EIO): not an OSError
            _set_tty_exclusive(port, False)
            with contextlib.suppress(Exception):
                port.close()
            raise TransportError(f"cannot open {self.url}: the link went away while it was opened ({exc})") from exc
        except (serial.SerialException, OSError):
            pass
        self._port = port

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            # The exclusive flag lives on the tty, not on our descriptor: a pty's stays set while its far end
            # is open, and would refuse our own reopen (a non-root app) after this close.
            _set_tty_exclusive(port, False)
            with contextlib.suppress(Exception):
                port.close()

    def read(self, timeout: float) -> bytes:
        port = self._port
        if port is None:
            raise TransportError(f"{self.url} is not open")
        try:
            if port.timeout != timeout:
                port.timeout = timeout
            waiting = port.in_waiting
            if waiting:
                return port.read(waiting)
            data = port.read(1)  # blocks up to `timeout` for the first byte
            if data and (more := port.in_waiting):
                data += port.read(more)
            return data
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            if "readiness to read" in str(exc) and self._another_reader():
                return b""  # another process read those bytes first: the link is there, shared (an alarm says so)
            # TypeError/AttributeError: pyserial's internals after a concurrent close().
            raise TransportError(f"{self.url}: the link was lost ({exc})") from exc

    def _another_reader(self) -> bool:
        """pyserial saw the tty readable and then read nothing: an unplugged device, or another process that read
        the bytes first. Another process holding the tty (checked at most every 0.5 s) means the second; the driver
        stays connected (it can still send IDLE) and names it in an alarm (``shared_with``)."""
        now = time.monotonic()
        if now - self._holders_checked_at >= 0.5:
            self._holders_checked_at = now
            holders = port_holders(self.url)
            if holders != self.shared_with:
                self.shared_with = holders
        return bool(self.shared_with)

    def write(self, data: bytes) -> None:
        port = self._port
        if port is None:
            raise TransportError(f"{self.url} is not open")
        with self._write_lock:
            try:
                port.write(data)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                raise TransportError(f"{self.url}: write failed ({exc})") from exc


def _set_tty_exclusive(port: serial.SerialBase, exclusive: bool) -> None:
    """TIOCEXCL / TIOCNXCL on an open pyserial port (POSIX ttys; a no-op elsewhere)."""
    fd = getattr(port, "fd", None)
    if fd is None or fcntl is None or termios is None:
        return
    with contextlib.suppress(OSError, AttributeError):
        fcntl.ioctl(fd, termios.TIOCEXCL if exclusive else termios.TIOCNXCL)


def port_holders(path: str) -> list[tuple[int, str]]:
    """(pid, command line) of the other processes that have ``path`` (a tty) open, from Linux's /proc; [] where
    the OS does not tell (other systems, or processes this user may not inspect). For a pty slave the process
    holding its master (a simulator: the device's end of the link) is left out."""
    proc = Path("/proc")
    try:
        target = os.path.realpath(path)
        pts_index = int(target.rsplit("/", 1)[1]) if target.startswith("/dev/pts/") else None
        entries = [e for e in os.scandir(proc) if e.name.isdigit()] if proc.is_dir() else []
    except (OSError, ValueError):
        return []
    me = os.getpid()
    holders: list[tuple[int, str]] = []
    for entry in entries:
        pid = int(entry.name)
        if pid == me:
            continue
        holds = far_end = False
        try:
            with os.scandir(proc / entry.name / "fd") as fds:
                for fd in fds:
                    try:
                        link = os.readlink(fd.path)
                    except OSError:
                        continue
                    if link == target:
                        holds = True
                    elif link == "/dev/ptmx" and pts_index is not None:
                        info = (proc / entry.name / "fdinfo" / fd.name).read_text()
                        far_end = far_end or f"tty-index:\t{pts_index}\n" in info
        except OSError:
            continue
        if holds and not far_end:
            holders.append((pid, _command_line(pid)))
    return holders


def _command_line(pid: int) -> str:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
        text = " ".join(raw.replace(b"\0", b" ").decode("utf-8", "replace").split())
        return (text[:77] + "...") if len(text) > 80 else text or Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return "?"


def port_in_use_message(path: str) -> str:
    """A plain sentence for a port another program holds, naming it where the OS can tell."""
    holders = port_holders(path)
    if not holders:
        return "it is in use by another program (the system does not say which); close it and try again"
    named = ", ".join(f"pid {pid} ({cmd})" for pid, cmd in holders[:4])
    more = f" and {len(holders) - 4} more" if len(holders) > 4 else ""
    return f"it is in use by another program: {named}{more}; close it and try again"


class _LoopbackPort:
    """The few pyserial port calls SerialTransport makes, on a plain TCP socket: the simulators' loopback
    links (``socket://host:port``). pyserial's own socket handler polls byte by byte and cost the app
    twice the CPU and its 10x headroom (bench_headroom, #16)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.timeout: float | None = 0.02
        self.is_open = True

    @classmethod
    def connect(cls, url: str) -> _LoopbackPort:
        host, _, port = url[len("socket://"):].partition(":")
        try:
            sock = socket.create_connection((host, int(port)), timeout=1.0)
        except (OSError, ValueError) as exc:
            raise TransportError(f"cannot open {url}: {exc}") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # the host's commands too (see SocketLink)
        sock.setblocking(False)
        return cls(sock)

    @property
    def in_waiting(self) -> int:
        return 0  # read() drains whatever is there

    def read(self, _size: int = 1) -> bytes:
        try:
            ready, _, _ = select.select([self._sock], [], [], self.timeout or 0.0)
            if not ready:
                return b""
            data = self._sock.recv(65536)
        except BlockingIOError:
            return b""
        except OSError as exc:
            raise serial.SerialException(str(exc)) from exc
        if not data:
            raise serial.SerialException("the peer closed the link")
        return data

    def write(self, data: bytes) -> None:
        try:
            self._sock.setblocking(True)
            self._sock.settimeout(1.0)
            self._sock.sendall(data)
        except OSError as exc:
            raise serial.SerialException(str(exc)) from exc
        finally:
            with contextlib.suppress(OSError):
                self._sock.setblocking(False)

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False
        self._sock.close()


UDP_RECEIVE_BUFFER_BYTES = 1 << 20
"""Receive buffer asked for on every UDP link socket (ours and our helpers'): Linux's default (208 KiB) holds
only ~250 small datagrams (each costs ~830 bytes of buffer), i.e. 0.25 s at 10× the patient model's rate; a
process descheduled that long under CPU load lost datagrams in the kernel.  The kernel caps it at rmem_max."""


def enlarge_receive_buffer(sock: socket.socket, size: int = UDP_RECEIVE_BUFFER_BYTES) -> None:
    with contextlib.suppress(OSError):  # best effort: a smaller buffer still works
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


class DatagramTransport(Transport, Protocol):
    """What a UDP peer driver needs of its link (``UdpTransport``, or a fake in tests): one datagram per
    ``read`` (``read(0)`` does not wait), the peer it sends to (movable: a restarted helper may listen on
    another port) and the count of datagrams dropped because another sender sent them."""

    peer: tuple[str, int] | None
    dropped_foreign: int

    def set_peer(self, peer: tuple[str, int]) -> None: ...


class UdpTransport:
    """A UDP socket bound locally and aimed at one peer. Datagrams from any other sender are
    dropped and counted: on a clinical network a stray packet must not steer the robot."""

    def __init__(self, bind: tuple[str, int], peer: tuple[str, int] | None, accept_any_port: bool = False) -> None:
        self.bind_addr = bind
        self.peer = peer
        self.accept_any_port = accept_any_port
        self.description = f"udp {bind[0]}:{bind[1]} → {peer[0]}:{peer[1]}" if peer else f"udp {bind[0]}:{bind[1]}"
        self.dropped_foreign = 0
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._peer_ip: str | None = None  # the peer's host resolved once (not per datagram)
        self._poller: select.poll | None = None

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    @property
    def local_address(self) -> tuple[str, int]:
        if self._sock is None:
            raise TransportError("UDP socket is not open")
        return self._sock.getsockname()[:2]

    def open(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        enlarge_receive_buffer(sock)
        try:
            sock.bind(self.bind_addr)
        except OSError as exc:
            sock.close()
            raise TransportError(f"cannot bind UDP {self.bind_addr[0]}:{self.bind_addr[1]}: {exc.strerror}") from exc
        # Non-blocking for good, waited on with poll(): a read costs poll + recvfrom, not a mode switch
        # (settimeout is an ioctl) and an exception on every timeout, hundreds of times a second.
        sock.setblocking(False)
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        self._sock, self._poller = sock, poller
        host, port = sock.getsockname()[:2]
        self.description = f"udp {host}:{port}" + (f" → {self.peer[0]}:{self.peer[1]}" if self.peer else "")

    def close(self) -> None:
        sock, self._sock, self._poller = self._sock, None, None
        if sock is not None:
            sock.close()

    def set_peer(self, peer: tuple[str, int]) -> None:
        self.peer = peer
        self._peer_ip = None

    def _resolved_peer_ip(self, host: str) -> str:
        ip = self._peer_ip
        if ip is None:
            try:
                ip = self._peer_ip = socket.gethostbyname(host)
            except OSError as exc:
                raise TransportError(f"cannot resolve the UDP peer {host}: {exc}") from exc
        return ip

    def read(self, timeout: float) -> bytes:
        """One datagram from the peer, or b"" on timeout (``timeout`` ≤ 0: only what is already there)."""
        sock, poller = self._sock, self._poller
        if sock is None or poller is None:
            raise TransportError("UDP socket is not open")
        if not poller.poll(max(0.0, timeout) * 1000.0):
            return b""
        try:
            data, sender = sock.recvfrom(65535)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno in (errno.ECONNREFUSED, errno.ECONNRESET):
                return b""  # ICMP port unreachable from a peer that is not up yet
            raise TransportError(f"UDP receive failed: {exc}") from exc
        peer = self.peer
        if peer is not None:
            host_ok = sender[0] == self._resolved_peer_ip(peer[0]) if peer[0] else True
            port_ok = self.accept_any_port or sender[1] == peer[1]
            if not (host_ok and port_ok):
                self.dropped_foreign += 1
                return b""
        return data

    def write(self, data: bytes) -> None:
        sock, peer = self._sock, self.peer
        if sock is None or peer is None:
            raise TransportError("UDP socket is not open or has no peer")
        with self._lock:
            try:
                sock.sendto(data, peer)
            except OSError as exc:
                if exc.errno in (errno.ECONNREFUSED, errno.ECONNRESET):
                    return
                raise TransportError(f"UDP send failed: {exc}") from exc


# --------------------------------------------------------------------------- far-side links
class SimLink(Protocol):
    """The device end of a serial link, on which a simulator reads and writes."""

    url: str  # what the driver opens

    def wait_readable(self, timeout: float) -> bool: ...
    def read(self) -> bytes: ...
    def write(self, data: bytes) -> None: ...
    def close(self) -> None: ...


class PtyLink:
    """A pty pair: the simulator holds the master, the driver opens the slave like a real port.

    ``link_path`` (optional) is a stable symlink to the slave, so a driver can reconnect after the
    simulator is restarted with a new pty, as it would to a replugged device.
    """

    def __init__(self, link_path: Path | None = None) -> None:
        import tty

        self.master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes pass untouched
        self.slave_name = os.ttyname(slave)
        self._slave_fd = slave  # kept open so writes before the driver connects do not fail with EIO
        os.set_blocking(self.master, False)
        self.link_path = link_path
        if link_path is not None:
            tmp = link_path.with_name(link_path.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, link_path)
        self.url = str(link_path) if link_path is not None else self.slave_name
        self._closed = False

    def wait_readable(self, timeout: float) -> bool:
        if self._closed:
            return False
        r, _, _ = select.select([self.master], [], [], max(0.0, timeout))
        return bool(r)

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # no one has the slave open right now
                return b""
            raise

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._closed:
            try:
                n = os.write(self.master, view)
                view = view[n:]
            except BlockingIOError:
                # The driver is not reading (or not connected): a real UART would drop bytes too.
                select.select([], [self.master], [], 0.01)
                if not select.select([], [self.master], [], 0)[1]:
                    return
            except OSError as exc:
                if exc.errno == errno.EIO:
                    return
                raise

    def close(self) -> None:
        """Like pulling the USB cable: the driver's next read fails."""
        if self._closed:
            return
        self._closed = True
        if self.link_path is not None:
            with contextlib.suppress(OSError):
                if os.readlink(self.link_path) == self.slave_name:
                    self.link_path.unlink()
        for fd in (self.master, self._slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)


class SocketLink:
    """A localhost TCP server standing in for a serial device (pyserial ``socket://``), for
    platforms without ptys. One client (the driver) at a time: while it is connected, any other client is
    refused (accepted and reset at once), as a serial port opened exclusively refuses a second open. A new
    client used to replace the driver's connection, and a second program kicked the app 187 times in 20 s
    (#25). Once the driver's connection has ended (it closed, or the link broke) the next client is accepted:
    the driver's own reconnect."""

    def __init__(self, port: int = 0) -> None:
        self._server = socket.create_server((LOOPBACK, port))
        self._server.setblocking(False)
        self.url = socket_link_url(self._server.getsockname()[1])
        self._client: socket.socket | None = None
        self._closed = False
        self.clients_accepted = 0
        self.clients_refused = 0

    def _client_alive(self) -> bool:
        """Whether the held client is still there (an EOF or error not yet read ends it now)."""
        client = self._client
        if client is None:
            return False
        try:
            if client.recv(1, socket.MSG_PEEK):
                return True  # data waiting: alive (its EOF, if any, is read after the data)
        except BlockingIOError:
            return True
        except OSError:
            pass
        client.close()
        self._client = None
        return False

    def _accept(self) -> None:
        with contextlib.suppress(BlockingIOError):
            client, peer = self._server.accept()
            if self._client_alive():
                self.clients_refused += 1
                if self.clients_refused in (1, 10, 100) or self.clients_refused % 1000 == 0:
                    log.warning("%s: refused a second client from %s:%d (%d so far): the driver holds the link",
                                self.url, peer[0], peer[1], self.clients_refused)
                with contextlib.suppress(OSError):  # a reset, not a polite close: nothing it sent is read
                    client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                client.close()
                return
            # Each frame goes out when written: without TCP_NODELAY, Nagle's algorithm held the device's small
            # writes until the driver's delayed ACK (~40 ms on Linux loopback), bunching 8-9 LINarm frames (#27).
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client.setblocking(False)
            self.clients_accepted += 1
            self._client = client

    def wait_readable(self, timeout: float) -> bool:
        if self._closed:
            return False
        socks = [self._server] + ([self._client] if self._client else [])
        r, _, _ = select.select(socks, [], [], max(0.0, timeout))
        if self._server in r:
            self._accept()
        return self._client is not None and self._client in r

    def read(self) -> bytes:
        if self._client is None:
            return b""
        try:
            data = self._client.recv(65536)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:
            self._client.close()
            self._client = None
        return data

    def write(self, data: bytes) -> None:
        if self._client is None:
            self._accept()
        if self._client is None:
            return
        try:
            self._client.sendall(data)
        except OSError:
            self._client.close()
            self._client = None

    def close(self) -> None:
        self._closed = True
        if self._client is not None:
            self._client.close()
        self._server.close()


def make_sim_link(link_path: Path | None = None) -> PtyLink | SocketLink:
    """A pty where the OS has them (the driver opens it exactly like a real port), else a socket."""
    if hasattr(os, "openpty"):
        return PtyLink(link_path)
    return SocketLink()
