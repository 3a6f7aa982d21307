"""The device-driver base: one QThread per device owning its transport.

A driver reads bytes, decodes them with its (pure) codec into typed, timestamped samples and publishes them
one way: on the :class:`~app.core.bus.StreamBus` (issue #29). The bus keeps each stream's latest sample, wakes a
script's ``waitCondition`` once per read, runs the safety monitor inline and gives every other consumer a
bounded, counted queue (or display-rate columns for the Qt adapter). Connection changes, silence and errors
are bus events (``connected``, ``disconnected``, ``silent``, ``alive``, ``error``, ``controller_error``, …), each
published by one call, :meth:`DeviceDriver._fire_event`: a journal record on the bus (origin: the device), and,
where the driver keeps a Qt signal for it (``EVENT_SIGNALS``), that signal, emitted by the same call.

The loop reconnects with back-off when the transport drops, and stops within one read timeout.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from PySide6.QtCore import QThread

from app.core import journal
from app.core.bus import StreamBus, StreamSpec
from app.core.journal import Record
from app.devices.realtime import request_realtime
from app.devices.transport import Transport, TransportError

__all__ = ["DeviceDriver"]  # the stream types are the bus's (app.core.bus), the real-time request app.devices.realtime

log = logging.getLogger(__name__)

RATE_WINDOW_S = 1.0  # rates() is the count of the last window of this length


class DeviceDriver(QThread):
    """Base class. Subclasses set ``streams`` and implement ``on_bytes`` (and optionally
    ``on_connect``, ``on_tick``, ``on_disconnect``)."""

    streams: tuple[StreamSpec, ...] = ()
    # Round-robin real-time priority of the driver thread (None: normal scheduling). Off by default: a
    # real-time thread that wakes hundreds of times a second takes the interpreter lock from the GUI thread
    # each time, and under CPU load the GUI then waits for the CPU again (measured: the window took 15-20 s
    # instead of 3-5 s to build at load 15, #16). The LINarm heartbeat has its own real-time thread instead.
    realtime_priority: int | None = None
    # A device event's Qt face, where the driver keeps one: kind -> the signal's name, emitted with the detail by
    # the one publishing call (_fire_event). The window takes the event from the bus through its adapter.
    EVENT_SIGNALS: ClassVar[dict[str, str]] = {}

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        bus: StreamBus | None = None,
        read_timeout_s: float = 0.01,
        silence_timeout_s: float | None = None,
    ) -> None:
        super().__init__()
        self.setObjectName(f"driver:{name}")
        self.name = name
        self.transport = transport
        # The composition root's bus; a private one when none is given (a driver on its own, in a test or a bench).
        self.bus = bus if bus is not None else StreamBus()
        self.bus.declare(self.streams)
        self._bus_publish = self.bus.publish  # looked up once: publish runs hundreds of times a second
        self.read_timeout_s = read_timeout_s
        self.silence_timeout_s = silence_timeout_s
        self._stop = threading.Event()
        self._connected = False
        self._silent = False
        self._last_reason = ""
        self._last_sample_mono = 0.0
        self._silent_since = 0.0  # the last sample before a silence
        self._in_read = False  # on_bytes is running: publish leaves the wake-up to the loop
        self._wake_pending = False
        self._count_window = {s.name: 0 for s in self.streams}  # samples this rate window, per stream
        self._totals = {s.name: 0 for s in self.streams}
        self._rates: dict[str, float] = {s.name: 0.0 for s in self.streams}
        self._rate_window_start = time.monotonic()
        self.reconnect_backoff_s = (0.1, 2.0)
        self.connected_since: float | None = None
        self.realtime = False  # whether the OS granted realtime_priority to the loop
        self.native_thread_id: int | None = None

    # ------------------------------------------------------------------ public, any thread
    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def silent(self) -> bool:
        return self._silent

    def latest(self, stream: str) -> Any:
        """The newest sample of ``stream`` (the bus keeps it; None before the first)."""
        return self.bus.latest(stream)

    def rates(self) -> dict[str, float]:
        """Samples per second of each stream over the last second."""
        return dict(self._rates)

    def total_samples(self, stream: str) -> int:
        return self._totals[stream]

    def send(self, data: bytes) -> None:
        """Write bytes now, from any thread (the transport serialises writers)."""
        if not self._connected:
            raise TransportError(f"{self.name} is not connected")
        self.transport.write(data)

    def resume(self) -> None:
        """Start the loop again after :meth:`stop` (a QThread may be started again once it ended)."""
        if self.isRunning():
            return
        self._stop.clear()
        self.start()

    def stop(self, timeout_s: float = 1.0) -> bool:
        """Ask the loop to end and wait for it; True when the thread has finished."""
        self._stop.set()
        if self.isRunning():
            return self.wait(int(timeout_s * 1000))
        return True

    # ------------------------------------------------------------------ subclass hooks (driver thread)
    def on_connect(self) -> None:
        """Handshake after the transport opened; raise TransportError to retry later."""

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        raise NotImplementedError

    def on_tick(self, now_s: float) -> None:
        """Called every loop pass (at least every read timeout): heartbeats, timeouts."""

    def on_disconnect(self) -> None:
        """Transport is about to close: fail pending requests."""

    def publish(self, stream: str, t_s: float, sample: Any, arrival_s: float | None = None) -> None:
        """Hand one decoded sample to the bus. ``sample`` exposes the stream's channels as attributes;
        ``t_s`` is when it was taken on the host's monotonic clock (the device clock mapped by
        app.devices.clock, or a dejittered arrival), ``arrival_s`` when it came back from its read (default
        ``t_s``)."""
        self._count_window[stream] += 1
        self._totals[stream] += 1
        self._last_sample_mono = time.monotonic()
        if self._in_read:
            # Within one read the samples arrive together: waiters are woken once, after the last of them
            # (the loop wakes the bus), instead of once per sample.
            self._wake_pending = True
            self._bus_publish(stream, t_s, sample, arrival_s, wake=False)
        else:
            self._bus_publish(stream, t_s, sample, arrival_s)

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
        self.native_thread_id = threading.get_native_id()  # the OS's id of the loop's thread (its scheduling, tests)
        if self.realtime_priority is not None:
            self.realtime = request_realtime(self.realtime_priority)
        lo, hi = self.reconnect_backoff_s
        backoff = lo
        while not self._stop.is_set():
            try:
                self.transport.open()
            except TransportError as exc:
                self._set_connected(False, str(exc))
                self._stop.wait(backoff)
                backoff = min(backoff * 2, hi)
                continue
            reason = "disconnected"
            try:
                self.on_connect()
                self._set_connected(True, f"connected ({self.transport.description})")
                backoff = lo
                self._io_loop()
                reason = "stopped"
            except TransportError as exc:
                reason = str(exc)
            except Exception as exc:  # a decoder bug must never take the thread down silently
                log.exception("%s: driver failure", self.name)
                reason = f"driver failure: {exc!r}"
                self._fire_event(journal.DEVICE_ERROR_EVENT, f"{self.name}: {reason}")
            finally:
                try:
                    self.on_disconnect()
                except Exception:
                    log.exception("%s: on_disconnect failed", self.name)
                self.transport.close()
            self._set_connected(False, reason)
            self._update_rates(force=True)
            if not self._stop.is_set():
                self._stop.wait(backoff)
        self._update_rates(force=True)

    def _take_bytes(self, on_bytes: Callable[[bytes, int], None], data: bytes, t_ns: int) -> None:
        """Decode one read; waiters are woken once per read (not per sample), after it."""
        self._in_read = True
        try:
            on_bytes(data, t_ns)
        finally:
            self._in_read = False
            if self._wake_pending:
                self._wake_pending = False
                self.bus.wake()

    def _io_loop(self) -> None:
        # Runs once per read (hundreds of times a second): the lookups are done once, here.
        read, on_bytes, on_tick = self.transport.read, self.on_bytes, self.on_tick
        monotonic, monotonic_ns, stop = time.monotonic, time.monotonic_ns, self._stop
        silence_timeout = self.silence_timeout_s
        next_rates = monotonic() + RATE_WINDOW_S
        self._last_sample_mono = monotonic()
        take = self._take_bytes
        while not stop.is_set():
            data = read(self.read_timeout_s)  # read each pass: a driver may set it in on_tick (FES: its t1 grid)
            if data:
                take(on_bytes, data, monotonic_ns())
            now = monotonic()
            on_tick(now)
            if silence_timeout is not None:
                silent = now - self._last_sample_mono > silence_timeout
                if silent and not self._silent:
                    # Judge the device, not this thread: when the read above timed out and this thread then
                    # waited for the CPU or the interpreter lock (a busy start-up, a loaded machine), the
                    # device's bytes have been waiting meanwhile. Take them before calling the device silent
                    # (the false "stopped sending data" warnings of #27: the next read found data at once).
                    pending = read(0.0)
                    if pending:
                        take(on_bytes, pending, monotonic_ns())
                        now = monotonic()
                        silent = now - self._last_sample_mono > silence_timeout
                if silent != self._silent:
                    self._silent = silent
                    if silent:
                        self._silent_since = self._last_sample_mono
                    # "alive" carries how long the stream was silent (s), for "resumed after 0.3 s"
                    self._fire_event(journal.SILENT if silent else journal.ALIVE,
                                     "" if silent else f"{self._last_sample_mono - self._silent_since:.3f}")
            if now >= next_rates:
                self._update_rates()
                next_rates = now + RATE_WINDOW_S

    def _update_rates(self, force: bool = False) -> None:
        """Each stream's samples per second over the window that just ended (once a second, and at a disconnect)."""
        now = time.monotonic()
        window = now - self._rate_window_start
        if window < RATE_WINDOW_S and not force:
            return
        counts = self._count_window
        self._rates = {name: (n / window if window > 0 else 0.0) for name, n in counts.items()}
        for name in counts:
            counts[name] = 0
        self._rate_window_start = now

    def _set_connected(self, connected: bool, reason: str) -> None:
        changed = connected != self._connected or (not connected and reason != self._last_reason)
        self._connected = connected
        self._last_reason = reason
        if connected:
            self.connected_since = time.monotonic()
            self._silent = False
        if changed:
            level = logging.INFO if connected else logging.WARNING
            log.log(level, "%s: %s", self.name, reason)
            # the bus wakes the waiters
            self._fire_event(journal.CONNECTED if connected else journal.DISCONNECTED, reason)

    def _fire_event(self, event: str, detail: str = "") -> Record:
        """A device event: a record on the bus (``bus.event`` wakes the waiters and runs the safety monitor inline),
        then its Qt signal when the driver keeps one (``EVENT_SIGNALS``): one call, two faces."""
        record = self.bus.event(self.name, event, detail)
        signal = self.EVENT_SIGNALS.get(event)
        if signal is not None:
            getattr(self, signal).emit(detail)
        return record
