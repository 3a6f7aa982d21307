"""Lab Streaming Layer outlets: every device stream (and the session events) on the lab network.

Switched on by ``recording.lsl``. Lab tools (LabRecorder → XDF) then record our streams alongside
EEG, EMG or motion capture on one clock. One outlet per stream, named as the stream
(``physio.main``), source id ``linarmpp.<stream>`` (so LabRecorder re-finds it after a restart),
float64 channels with label and unit in the stream's description; plus an irregular-rate string
outlet ``linarmpp.events`` carrying each recorded event as JSON (type ``Markers``).

Time stamps are LSL's clock: the offset between ``time.monotonic()`` (our samples' clock) and
``pylsl.local_clock()`` is measured once at start, so each sample keeps the time it was taken — the
device's clock mapped to the host's by app.devices.clock (#27), the same stamp the recorder writes —
rather than the time it was pushed. (On Linux both are CLOCK_MONOTONIC and the offset is ~0.)

Like the recorder, the drivers' listeners only append to a bounded deque; a worker thread pushes
chunks every 10 ms. If pylsl or its liblsl cannot be loaded the application runs without LSL and
says so once in the log (:func:`lsl_status`).
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.manager import LinarmppManager

log = logging.getLogger(__name__)

SOURCE_PREFIX = "linarmpp"
EVENTS_STREAM = "linarmpp.events"
_PUSH_PERIOD_S = 0.01


def lsl_status() -> tuple[bool, str]:
    """(available, text): whether pylsl and its liblsl load here, and a sentence saying so."""
    try:
        import pylsl

        return True, f"LSL available (liblsl {pylsl.library_version()}, pylsl {pylsl.__version__})"
    except Exception as exc:  # ImportError, or RuntimeError/OSError when liblsl itself cannot be loaded
        return False, f"LSL unavailable: {exc}"


def measure_clock_offset(tries: int = 7) -> float:
    """local_clock() − time.monotonic(), from the tightest of a few bracketed readings."""
    import pylsl

    best: tuple[float, float] | None = None
    for _ in range(tries):
        a = time.monotonic()
        lsl = pylsl.local_clock()
        b = time.monotonic()
        if best is None or b - a < best[0]:
            best = (b - a, lsl - (a + b) / 2)
    assert best is not None
    return best[1]


class LslBridge:
    """Outlets for every stream of ``manager``'s devices; ``stop`` removes them."""

    def __init__(self, manager: LinarmppManager, queue_limit: int = 200_000) -> None:
        import pylsl

        self._pylsl = pylsl
        self.manager = manager
        self.queue_limit = queue_limit
        self.offset_s = measure_clock_offset()
        self.outlets: dict[str, Any] = {}
        self._channels: dict[str, tuple[str, ...]] = {}
        self._queue: collections.deque[tuple[str, float, Any]] = collections.deque()
        self._markers: collections.deque[tuple[float, str]] = collections.deque()
        self.dropped = 0
        self._attached: list[tuple[Any, Any]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        for name, handle in manager.devices.items():
            for spec in handle.driver.streams:
                self.outlets[spec.name] = self._make_outlet(spec, name)
                self._channels[spec.name] = tuple(c.name for c in spec.channels)
        info = pylsl.StreamInfo(EVENTS_STREAM, "Markers", 1, pylsl.IRREGULAR_RATE, "string",
                                f"{SOURCE_PREFIX}.events")
        self.events_outlet = pylsl.StreamOutlet(info)

    def _make_outlet(self, spec: Any, device: str) -> Any:
        pylsl = self._pylsl
        info = pylsl.StreamInfo(spec.name, device, len(spec.channels), lsl_rate_hz(self.manager.config, device, spec),
                                "double64",
                                f"{SOURCE_PREFIX}.{spec.name}")
        desc = info.desc()
        desc.append_child_value("manufacturer", "LINarm++ Manager")
        chans = desc.append_child("channels")
        for ch in spec.channels:
            c = chans.append_child("channel")
            c.append_child_value("label", ch.name)
            c.append_child_value("unit", ch.unit)
            c.append_child_value("description", ch.label)
        return pylsl.StreamOutlet(info, chunk_size=0, max_buffered=60)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        for handle in self.manager.devices.values():
            fn = self._listener()
            handle.driver.add_listener(fn)
            self._attached.append((handle.driver, fn))
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="lsl-outlets", daemon=True)
        self._thread.start()
        log.info("LSL outlets: %s (clock offset %.6f s)", ", ".join(self.outlets), self.offset_s)

    def stop(self) -> None:
        for driver, fn in self._attached:
            driver.remove_listener(fn)
        self._attached.clear()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self.outlets.clear()  # outlets vanish from the network when released
        self.events_outlet = None

    def lsl_time(self, t_mono: float) -> float:
        return t_mono + self.offset_s

    def marker(self, record: dict[str, Any]) -> None:
        """Push an event (a recorder event record) as a JSON marker; use as ``recorder.add_event_tap``."""
        t = record.get("t_mono")
        t = float(t) if isinstance(t, int | float) else time.monotonic()
        self._markers.append((t, json.dumps(record, ensure_ascii=False, default=str)))

    # ------------------------------------------------------------------ internals
    def _listener(self) -> Any:
        queue, limit = self._queue, self.queue_limit

        def on_sample(stream: str, t: float, sample: Any) -> None:
            if len(queue) >= limit:
                self.dropped += 1
                return
            queue.append((stream, t, sample))

        return on_sample

    def _run(self) -> None:
        while not self._stop.wait(_PUSH_PERIOD_S):
            try:
                self._push()
            except Exception:
                log.exception("LSL push failed")
        self._push()

    def _push(self) -> None:
        chunks: dict[str, tuple[list[list[float]], list[float]]] = {}
        queue = self._queue
        for _ in range(len(queue)):
            stream, t, sample = queue.popleft()
            names = self._channels.get(stream)
            if names is None:
                continue
            rows, stamps = chunks.setdefault(stream, ([], []))
            rows.append([_num(getattr(sample, n, float("nan"))) for n in names])
            stamps.append(t + self.offset_s)
        for stream, (rows, stamps) in chunks.items():
            outlet = self.outlets.get(stream)
            if outlet is not None:
                outlet.push_chunk(rows, stamps)
        outlet = self.events_outlet
        for _ in range(len(self._markers)):
            t, text = self._markers.popleft()
            if outlet is not None:
                outlet.push_sample([text], t + self.offset_s)


def _num(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


# Streams published when something changes (FES: on each update the driver sends, ~10 Hz), not at a fixed
# rate: declared irregular (0) so an LSL consumer does not expect the stimulation frequency.
IRREGULAR_STREAMS: frozenset[str] = frozenset({"fes.channels"})


def lsl_rate_hz(config: Any, device: str, spec: Any) -> float:
    """The nominal rate declared to LSL: the configured rate, or 0 (irregular)."""
    if spec.name in IRREGULAR_STREAMS:
        return 0.0
    from app.recording import configured_rate_hz

    return float(configured_rate_hz(config, device, spec))


def start_lsl(manager: LinarmppManager, force: bool = False) -> LslBridge | None:
    """Outlets for every stream when ``recording.lsl`` is on (or ``force``); None when off or when
    pylsl/liblsl is missing on this platform (logged as a warning: the application runs without LSL)."""
    if not (force or manager.config.recording.lsl):
        return None
    ok, text = lsl_status()
    if not ok:
        log.warning("recording.lsl is on but %s; running without LSL outlets", text)
        return None
    try:
        bridge = LslBridge(manager)
    except Exception as exc:
        log.warning("LSL outlets could not be created (%s); running without LSL outlets", exc)
        return None
    bridge.start()
    log.info("%s", text)
    return bridge
