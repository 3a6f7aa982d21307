"""An in-memory datagram link for the UDP peer drivers (``app.devices.transport.DatagramTransport``):
what the driver writes is kept in ``sent``; ``deliver`` queues a datagram for the driver's next read."""

from __future__ import annotations

import collections
import threading

from app.devices.transport import TransportError


class FakeUdpTransport:
    def __init__(self, peer: tuple[str, int] = ("127.0.0.1", 9)) -> None:
        self.peer: tuple[str, int] | None = peer
        self.dropped_foreign = 0
        self.description = "in-memory datagrams"
        self.sent: list[bytes] = []
        self._inbox: collections.deque[bytes] = collections.deque()
        self._cond = threading.Condition()
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def set_peer(self, peer: tuple[str, int]) -> None:
        self.peer = peer

    def deliver(self, *datagrams: bytes) -> None:
        with self._cond:
            self._inbox.extend(datagrams)
            self._cond.notify_all()

    def read(self, timeout: float) -> bytes:
        with self._cond:
            if not self._inbox and timeout > 0:
                self._cond.wait(timeout)
            return self._inbox.popleft() if self._inbox else b""

    def write(self, data: bytes) -> None:
        if not self._open:
            raise TransportError("fake UDP link is not open")
        with self._cond:
            self.sent.append(bytes(data))

    @property
    def pending(self) -> int:
        with self._cond:
            return len(self._inbox)
