"""The device-driver base: one QThread per device owning its transport.

A driver reads bytes, decodes them with its (pure) codec into typed, timestamped samples and
publishes them three ways, each suited to its consumer:

* ``samples`` Qt signal — column batches at display rate (~30 Hz) for the GUI, never one signal
  per sample;
* listeners — plain callables run on the driver thread for each sample (recorder queue, safety
  watchdogs, script callbacks' queue); they must be quick and must not block;
* ``latest(stream)`` plus the shared :class:`UpdateNotifier` — so a script's ``waitCondition``
  wakes within a millisecond of the frame that satisfies it instead of polling.

The loop reconnects with back-off when the transport drops, and stops within one read timeout.
"""

from __future__ import annotations

import logging
import operator
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from PySide6.QtCore import QThread, Signal

from app.bus import Channel, SampleBatch, StreamSpec, UpdateNotifier
from app.devices.realtime import REALTIME_ENV, request_realtime
from app.devices.transport import Transport, TransportError

__all__ = ["REALTIME_ENV", "Channel", "DeviceDriver", "SampleBatch", "StreamSpec", "UpdateNotifier",
           "request_realtime"]

log = logging.getLogger(__name__)


@dataclass
class _Accumulator:
    """One stream's samples since the last batch. The samples themselves are kept (one append per sample);
    their channels are read into columns at batch time, one C call per sample (``attrgetter``)."""

    spec: StreamSpec
    t: list[float] = field(default_factory=list)
    arrival: list[float] = field(default_factory=list)
    samples: list[Any] = field(default_factory=list)
    count_window: int = 0
    total: int = 0
    last_t: float = 0.0

    def __post_init__(self) -> None:
        names = [c.name for c in self.spec.channels]
        self.names = names
        self._row = operator.attrgetter(*names) if names else None

    def take_batch(self) -> SampleBatch:
        """The accumulated samples as columns (float64, one array per channel); starts a new batch."""
        n = len(self.samples)
        if self._row is None:
            data: dict[str, np.ndarray] = {}
        else:
            rows = np.array([self._row(s) for s in self.samples], dtype=np.float64).reshape(n, len(self.names))
            columns = rows.T.copy()  # each channel contiguous
            data = {name: columns[k] for k, name in enumerate(self.names)}
        batch = SampleBatch(self.spec, np.asarray(self.t, dtype=np.float64), data,
                            np.asarray(self.arrival, dtype=np.float64))
        self.t = []
        self.arrival = []
        self.samples = []
        return batch


SampleListener = Callable[[str, float, Any], None]
EventListener = Callable[[str, str], None]


class DeviceDriver(QThread):
    """Base class. Subclasses set ``streams`` and implement ``on_bytes`` (and optionally
    ``on_connect``, ``on_tick``, ``on_disconnect``)."""

    connection_changed = Signal(bool, str)
    samples = Signal(object)  # dict[str, SampleBatch]
    error = Signal(str)
    silence_changed = Signal(bool)  # True: connected but no sample for `silence_timeout_s`

    streams: tuple[StreamSpec, ...] = ()
    # Round-robin real-time priority of the driver thread (None: normal scheduling). Off by default: a
    # real-time thread that wakes hundreds of times a second takes the interpreter lock from the GUI thread
    # each time, and under CPU load the GUI then waits for the CPU again (measured: the window took 15-20 s
    # instead of 3-5 s to build at load 15, #16). The LINarm heartbeat has its own real-time thread instead.
    realtime_priority: int | None = None

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        notifier: UpdateNotifier | None = None,
        batch_hz: float = 30.0,
        read_timeout_s: float = 0.01,
        silence_timeout_s: float | None = None,
    ) -> None:
        super().__init__()
        self.setObjectName(f"driver:{name}")
        self.name = name
        self.transport = transport
        self.notifier = notifier or UpdateNotifier()
        self.read_timeout_s = read_timeout_s
        self.batch_period_s = 1.0 / batch_hz
        self.silence_timeout_s = silence_timeout_s
        self._stop = threading.Event()
        self._connected = False
        self._silent = False
        self._last_reason = ""
        self._latest: dict[str, Any] = {}
        self._acc = {s.name: _Accumulator(s) for s in self.streams}
        self._acc_lock = threading.Lock()
        self._listeners: list[SampleListener] = []
        self._event_listeners: list[EventListener] = []
        self._last_sample_mono = 0.0
        # When the sample being published came back from its read (monotonic s): listeners that keep it as a
        # diagnostic (the recorder's arrival column) read it during their call.
        self.arrival_s = 0.0
        self._silent_since = 0.0  # the last sample before a silence
        self._in_read = False  # on_bytes is running: publish leaves the notification to the loop
        self._notify_pending = False
        self._rates: dict[str, float] = {s.name: 0.0 for s in self.streams}
        self._rate_window_start = time.monotonic()
        self.reconnect_backoff_s = (0.1, 2.0)
        self.connected_since: float | None = None
        self.realtime = False  # whether the OS granted realtime_priority to the loop

    # ------------------------------------------------------------------ public, any thread
    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def silent(self) -> bool:
        return self._silent

    def latest(self, stream: str) -> Any:
        return self._latest.get(stream)

    def rates(self) -> dict[str, float]:
        return dict(self._rates)

    def add_listener(self, fn: SampleListener) -> None:
        """``fn(stream_name, t_monotonic_s, sample)`` on the driver thread, for every sample."""
        self._listeners = [*self._listeners, fn]

    def remove_listener(self, fn: SampleListener) -> None:
        self._listeners = [f for f in self._listeners if f is not fn]

    def add_event_listener(self, fn: EventListener) -> None:
        """``fn(event, detail)`` on the driver thread: 'connected', 'disconnected', 'silent', 'alive'."""
        self._event_listeners = [*self._event_listeners, fn]

    def remove_event_listener(self, fn: EventListener) -> None:
        self._event_listeners = [f for f in self._event_listeners if f is not fn]

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
        """Hand one decoded sample to every consumer. ``sample`` exposes the stream's channels as attributes;
        ``t_s`` is when it was taken on the host's monotonic clock (the device clock mapped by
        app.devices.clock, or a dejittered arrival), ``arrival_s`` when it came back from its read (default
        ``t_s``)."""
        self._latest[stream] = sample
        arrival = t_s if arrival_s is None else arrival_s
        self.arrival_s = arrival
        acc = self._acc[stream]
        with self._acc_lock:
            acc.t.append(t_s)
            acc.arrival.append(arrival)
            acc.samples.append(sample)
            acc.count_window += 1
            acc.total += 1
            acc.last_t = t_s
        self._last_sample_mono = time.monotonic()
        for fn in self._listeners:
            try:
                fn(stream, t_s, sample)
            except Exception:  # a consumer's bug must not stop the device
                log.exception("%s: sample listener failed", self.name)
        if self._in_read:
            # Within one read the samples arrive together: waiters are woken once, after the last of them
            # (the loop notifies), instead of once per sample.
            self._notify_pending = True
        else:
            self.notifier.notify()

    def total_samples(self, stream: str) -> int:
        return self._acc[stream].total

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
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
                self.error.emit(f"{self.name}: {reason}")
            finally:
                try:
                    self.on_disconnect()
                except Exception:
                    log.exception("%s: on_disconnect failed", self.name)
                self.transport.close()
            self._set_connected(False, reason)
            self._emit_batches(force=True)
            if not self._stop.is_set():
                self._stop.wait(backoff)
        self._emit_batches(force=True)

    def _take_bytes(self, on_bytes: Any, data: bytes, t_ns: int) -> None:
        """Decode one read; waiters are woken once per read (not per sample), after it."""
        self._in_read = True
        try:
            on_bytes(data, t_ns)
        finally:
            self._in_read = False
            if self._notify_pending:
                self._notify_pending = False
                self.notifier.notify()

    def _io_loop(self) -> None:
        # Runs once per read (hundreds of times a second): the lookups are done once, here.
        read, on_bytes, on_tick = self.transport.read, self.on_bytes, self.on_tick
        monotonic, monotonic_ns, stop = time.monotonic, time.monotonic_ns, self._stop
        batch_period, silence_timeout = self.batch_period_s, self.silence_timeout_s
        next_batch = monotonic() + batch_period
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
                    self.silence_changed.emit(silent)
                    # "alive" carries how long the stream was silent (s), for "resumed after 0.3 s"
                    self._fire_event("silent" if silent else "alive",
                                     "" if silent else f"{self._last_sample_mono - self._silent_since:.3f}")
            if now >= next_batch:
                self._emit_batches()
                next_batch = now + batch_period

    def _emit_batches(self, force: bool = False) -> None:
        out: dict[str, SampleBatch] = {}
        now = time.monotonic()
        window = now - self._rate_window_start
        with self._acc_lock:
            for name, acc in self._acc.items():
                if acc.t:
                    out[name] = acc.take_batch()
            if window >= 1.0 or force:
                for name, acc in self._acc.items():
                    self._rates[name] = acc.count_window / window if window > 0 else 0.0
                    acc.count_window = 0
                self._rate_window_start = now
        if out:
            self.samples.emit(out)

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
            self.connection_changed.emit(connected, reason)
            self._fire_event("connected" if connected else "disconnected", reason)
            self.notifier.notify()

    def _fire_event(self, event: str, detail: str) -> None:
        for fn in self._event_listeners:
            try:
                fn(event, detail)
            except Exception:
                log.exception("%s: event listener failed", self.name)
