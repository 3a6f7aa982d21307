"""The thread that runs a device simulator on the far side of a real serial link.

A simulator core is pure (bytes in → bytes out, plus time-driven output); this thread gives it a
link (pty or localhost socket) and a clock. ``kill()`` closes the link like pulling the cable;
``restart()`` brings the device back on a new link behind the same stable path.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from app.devices.realtime import request_realtime
from app.devices.transport import SimLink, make_sim_link

log = logging.getLogger(__name__)

# A simulated LINarm that powers up homed (encoders referenced, IDLE at the home position), as after a full
# homing: for tests that only need a homed robot (tests/conftest.py, marker ``sim_homed``). An environment
# variable, so that it reaches every hosting alike: this thread, the simulator process, an app subprocess's.
# A real controller always powers up unhomed; the application never sets it.
HOMED_ENV = "LINARMPP_SIM_HOMED"


def linarm_starts_homed() -> bool:
    """Whether simulated LINarms built now start homed (``LINARMPP_SIM_HOMED=1``)."""
    return os.environ.get(HOMED_ENV, "") == "1"

# What the Simulation panel and tests may ask of a device's simulator core, by name: one table for both
# hostings (this thread, and the simulator process of app.devices.sim.host), so the panel works the same
# in- and out-of-process.
DEVICE_CONTROLS: dict[str, Callable[..., Any]] = {
    "phasic_event": lambda core, amplitude=None: core.source.phasic_event(time.monotonic(), amplitude),
    "set_fault_flags": lambda core, flags: core.source.set_fault_flags(int(flags)),
    "frames_sent": lambda core: int(core.source.frames_sent),
    "fes_channel_state": lambda core: bool(core.channel_state()),
    "fes_running": lambda core: bool(core.running),
}


class SimCore(Protocol):
    """What a device simulator core offers to the link thread."""

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        """Bytes from the host arrived at monotonic time ``t``; return the reply bytes."""
        ...

    def poll(self, t: float) -> bytes:
        """Advance the device to time ``t``; return whatever it transmits by then."""
        ...


class SerialSimulator:
    """Runs ``core`` on a link in its own daemon thread, polling it every ``tick_s``."""

    def __init__(self, name: str, core_factory: Callable[[], SimCore], link_path: Path | None,
                 tick_s: float = 0.001, link_factory: Callable[[], SimLink] | None = None) -> None:
        self.name = name
        self.core_factory = core_factory
        self.link_path = link_path
        self.tick_s = tick_s
        # The far side of the link: a pty behind ``link_path`` by default, or e.g. a loopback socket.
        self.link_factory = link_factory or (lambda: make_sim_link(link_path))
        self.core: SimCore = core_factory()
        self.link: SimLink = self.link_factory()
        self.host_bytes_log: list[tuple[float, bytes]] = []  # what the driver sent, for tests
        self.keep_host_log = False
        self.device_bytes_log: list[tuple[float, bytes]] = []  # what the device wrote, for benchmarks
        self.keep_device_log = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()  # guards `core` against test/GUI threads poking it
        # The device stands in for a microcontroller: it is not the app's CPU load, and starving it would
        # measure the rig, not the app. Real-time (below the LINarm link's 20) when the OS allows.
        self.realtime_priority: int | None = None if os.environ.get("LINARMPP_SIM_REALTIME") == "0" else 10

    @property
    def url(self) -> str:
        return self.link.url

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"sim:{self.name}", daemon=True)
        self._thread.start()

    def halt(self) -> None:
        """The board stops making frames, every one it made written, its end of the link left open (closing it
        discards what the host has not read yet): a board that goes silent, not a pulled cable."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def stop(self) -> None:
        self.halt()
        self.link.close()

    def clear_host_log(self) -> None:
        """Forget the bytes logged so far (a shared test rig between tests)."""
        self.host_bytes_log.clear()

    def kill(self) -> None:
        """The device vanishes mid-stream (cable pulled, board reset)."""
        self.stop()

    def restart(self, fresh_state: bool = True) -> None:
        """The device comes back, on a new link behind the same path."""
        self.stop()
        if fresh_state:
            self.core = self.core_factory()
        self.link = self.link_factory()
        self.start()

    def with_core(self, fn: Callable[[SimCore], object]) -> object:
        """Run ``fn(core)`` under the simulator's lock (tests, the simulation panel)."""
        with self._lock:
            return fn(self.core)

    def control(self, name: str, *args: object) -> object:
        """A named control of the core (DEVICE_CONTROLS), as the simulator process offers it: the
        Simulation panel calls the same names however its simulators are hosted."""
        fn = DEVICE_CONTROLS[name]
        return self.with_core(lambda core: fn(core, *args))

    def _run(self) -> None:
        if self.realtime_priority is not None:
            request_realtime(self.realtime_priority)
        link = self.link
        next_tick = time.monotonic()
        try:
            while not self._stop.is_set():
                timeout = max(0.0, next_tick - time.monotonic())
                if link.wait_readable(timeout):
                    data = link.read()
                    if data:
                        now = time.monotonic()
                        if self.keep_host_log:
                            self.host_bytes_log.append((now, data))
                        with self._lock:
                            reply = self.core.handle_host_bytes(data, now)
                        if reply:
                            link.write(reply)
                now = time.monotonic()
                if now >= next_tick:
                    with self._lock:
                        out = self.core.poll(now)
                        next_output = getattr(self.core, "next_output", None)
                        due = next_output() if next_output is not None else None
                    if out:
                        if self.keep_device_log:
                            self.device_bytes_log.append((time.monotonic(), out))
                        link.write(out)
                    next_tick += self.tick_s
                    if next_tick < now - 0.1:  # fell far behind (debugger, suspended VM): do not burst
                        next_tick = now + self.tick_s
                    if due is not None and now < due < next_tick:  # a frame due before the next tick: wake for it
                        next_tick = due
        except OSError as exc:
            if not self._stop.is_set():
                log.warning("simulator %s: link failed: %s", self.name, exc)
        except Exception:
            log.exception("simulator %s crashed", self.name)
