"""A trivial device used to test the foundation (transport, driver base, simulator thread,
reconnection) independently of any real device protocol: the device sends `C<uint32 count>\n`
every millisecond; the host may send `R` to reset the counter."""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from app.core import streams
from app.core.bus import Channel, StreamBus, StreamSpec, UpdateNotifier
from app.devices.driver import DeviceDriver
from app.devices.sim.base import SerialSimulator
from app.devices.transport import SerialTransport

if TYPE_CHECKING:
    from app.devices.registry import DeviceContext

FRAME = struct.Struct("<cIc")


@dataclass(frozen=True)
class CounterSample:
    count: float


class CounterCore:
    def __init__(self, period_s: float = 0.001) -> None:
        self.count = 0
        self.period_s = period_s
        self.next_t: float | None = None

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        if b"R" in data:
            self.count = 0
        return b""

    def poll(self, t: float) -> bytes:
        if self.next_t is None:
            self.next_t = t
        out = bytearray()
        while self.next_t <= t:
            out += FRAME.pack(b"C", self.count, b"\n")
            self.count += 1
            self.next_t += self.period_s
        return bytes(out)


class CounterDriver(DeviceDriver):
    streams = (StreamSpec("counter.main", (Channel("count", "", "Count"),), 1000.0),)

    def __init__(self, url: str, **kw) -> None:
        super().__init__("counter", SerialTransport(url), **kw)
        self._buf = bytearray()

    def on_connect(self) -> None:
        self._buf.clear()

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        self._buf += data
        while len(self._buf) >= FRAME.size:
            start = self._buf.find(b"C")
            if start < 0:
                self._buf.clear()
                return
            del self._buf[:start]
            if len(self._buf) < FRAME.size:
                return
            _c, count, nl = FRAME.unpack_from(self._buf)
            if nl != b"\n":
                del self._buf[:1]
                continue
            del self._buf[: FRAME.size]
            self.publish("counter.main", t_ns / 1e9, CounterSample(float(count)))


def make_counter_device(tmp_path, name: str = "counter"):
    sim = SerialSimulator(name, CounterCore, tmp_path / f"{name}.tty")
    return sim


def counter_factory(tmp_path, name: str = "counter"):
    from app.manager import DeviceHandle

    def factory(ctx: DeviceContext) -> DeviceHandle:
        sim = make_counter_device(tmp_path, name)
        driver = CounterDriver(sim.url, bus=ctx.bus, silence_timeout_s=0.05)
        driver.name = name
        return DeviceHandle(name, driver, sim)

    return factory


class ListenerDriver:
    """Only the listener surface of a DeviceDriver (what the session recorder attaches to), driven by
    the test: ``listeners`` get samples, ``event_listeners`` connection events."""

    def __init__(self, *streams: StreamSpec) -> None:
        self.streams = streams
        self.connected = True
        self.listeners: list = []
        self.event_listeners: list = []

    def add_listener(self, fn) -> None:
        self.listeners.append(fn)

    def remove_listener(self, fn) -> None:
        self.listeners.remove(fn)

    def add_event_listener(self, fn) -> None:
        self.event_listeners.append(fn)

    def remove_event_listener(self, fn) -> None:
        self.event_listeners.remove(fn)

    def fire(self, event: str, detail: str = "") -> None:
        for fn in self.event_listeners:
            fn(event, detail)


class BusSamples(dict):
    """A fake device's latest samples: setting one publishes it on the bus, as a driver does."""

    def __init__(self, bus: StreamBus) -> None:
        super().__init__()
        self.bus = bus

    def __setitem__(self, stream: str, sample: Any) -> None:
        super().__setitem__(stream, sample)
        self.bus.publish(stream, time.monotonic(), sample)


def fake_bus(notifier: UpdateNotifier | None = None) -> StreamBus:
    """A bus with every stream of the application declared (no channels: nothing here draws them)."""
    bus = StreamBus(notifier)
    bus.declare(StreamSpec(name, (), 100.0) for name in streams.STREAMS)
    return bus
