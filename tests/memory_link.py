"""An in-memory Transport for driver tests: no pty, no socket, no simulator thread."""

from __future__ import annotations

import queue
from collections.abc import Callable

from app.devices.transport import TransportError


class MemoryLink:
    """A Transport: what the driver writes reaches ``on_host_bytes`` at once (its reply is queued for the
    driver), and the test pushes the device's stream with :meth:`push`."""

    description = "in-memory link"

    def __init__(self, on_host_bytes: Callable[[bytes], bytes] = lambda _data: b"") -> None:
        self.on_host_bytes = on_host_bytes
        self.written: list[bytes] = []
        self._inbox: queue.Queue[bytes] = queue.Queue()
        self.is_open = False

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def read(self, timeout: float) -> bytes:
        if not self.is_open:
            raise TransportError("closed")
        try:
            return self._inbox.get(timeout=timeout)
        except queue.Empty:
            return b""

    def write(self, data: bytes) -> None:
        if not self.is_open:
            raise TransportError("closed")
        self.written.append(data)
        reply = self.on_host_bytes(data)
        if reply:
            self._inbox.put(reply)

    def push(self, data: bytes) -> None:
        self._inbox.put(data)
