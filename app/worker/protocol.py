"""The link between the application and its worker process: length-prefixed pickled tuples over a socket pair.

Both ends are this application's own processes on a private socket pair (nothing else can connect), so pickle is
the simplest faithful encoding of the tasks' arguments and results (paths, dataclasses, numpy scalars). Large
arrays never travel here: a loaded session's samples are handed over as column files the window maps
(app/worker/session_data.py).

Messages, application → worker: ``("init", {...})``, ``("run", id, kind, args, kwargs)``, ``("cancel", id)``,
``("quit",)``; worker → application: ``("ready", pid)``, ``("progress", id, fraction, text)``,
``("done", id, result)``, ``("failed", id, sentence, detail)``, ``("cancelled", id)``.
"""

from __future__ import annotations

import pickle
import socket
import struct
import threading
from typing import Any

_HEADER = struct.Struct("!Q")
MAX_FRAME = 1 << 32  # a frame larger than this is a broken link, not a message


class LinkClosed(EOFError):
    """The other end has gone (it exited, crashed or closed the link)."""


def _recv_exact(sock: socket.socket, n: int) -> bytearray:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:])
        if k == 0:
            raise LinkClosed("the link closed")
        got += k
    return buf


def recv(sock: socket.socket) -> tuple[Any, ...]:
    """The next message (blocks); LinkClosed when the other end has gone."""
    try:
        (size,) = _HEADER.unpack(_recv_exact(sock, _HEADER.size))
        if size > MAX_FRAME:
            raise LinkClosed(f"a frame of {size} bytes: the link is broken")
        return pickle.loads(_recv_exact(sock, size))  # our own process on a private socket pair
    except OSError as exc:
        raise LinkClosed(str(exc)) from exc


class Sender:
    """Sends whole messages from any thread (one at a time)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._lock = threading.Lock()

    def send(self, *message: Any) -> None:
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:
            try:
                self.sock.sendall(_HEADER.pack(len(data)))
                self.sock.sendall(data)
            except OSError as exc:
                raise LinkClosed(str(exc)) from exc
