"""Lab Streaming Layer outlets: every device stream (and the session events) on the lab network.

Switched on by ``recording.lsl``. Lab tools (LabRecorder → XDF) then record our streams alongside
EEG, EMG or motion capture on one clock. One outlet per stream, named as the stream
(``physio.main``), source id ``linarmpp.<stream>`` (so LabRecorder re-finds it after a restart),
float64 channels with label and unit in the stream's description; plus an irregular-rate string
outlet ``linarmpp.events`` (type ``Markers``) carrying each journal record (app/core/journal.py: the devices'
events, alarms, e-stops, refusals, runs, what the application records) as JSON, as the session record writes it
(:func:`app.session.recording.journal_event`), whether or not a session records. The recorder's own events (the
session's start and stop, its drops and failures) are the session file's, not the journal's: they are not sent.

Time stamps are LSL's clock: the offset between ``time.monotonic()`` (our samples' clock) and
``pylsl.local_clock()`` is measured once at start, so each sample keeps the time it was taken — the
device's clock mapped to the host's by app.devices.clock (#27), the same stamp the recorder writes —
rather than the time it was pushed. (On Linux both are CLOCK_MONOTONIC and the offset is ~0.)

Like the recorder, the bridge subscribes once to the stream bus (app/core/bus.py): a bounded, counted queue of
the streams' samples and the journal's records that the publishing threads fill (a record is never dropped); a
worker thread drains it and pushes chunks and markers every 10 ms (the samples a stalled worker loses are counted
in ``dropped``); ``stop`` closes the subscription. If pylsl or its liblsl cannot be loaded the application runs
without LSL and says so once in the log (:func:`lsl_status`).
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

from app.core import journal, streams
from app.core.bus import StreamSpec, Subscription
from app.core.journal import Record
from app.session.recording import journal_event, written_event

if TYPE_CHECKING:
    from app.core.config import AppConfig
    from app.therapy.services import LslHost

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
    """Outlets for every stream declared on ``host``'s bus; ``stop`` removes them."""

    def __init__(self, host: LslHost, queue_limit: int = 200_000) -> None:
        import pylsl

        self._pylsl = pylsl
        self.host = host
        self.config = host.config
        self.queue_limit = queue_limit
        self.offset_s = measure_clock_offset()
        self.outlets: dict[str, Any] = {}
        self._channels: dict[str, tuple[str, ...]] = {}
        self._markers: collections.deque[tuple[float, str]] = collections.deque()
        self._in_gap: dict[str, bool] = {}  # the devices without data now, as the markers say it (worker thread)
        self._device_streams: dict[str, list[str]] = {}
        self._sub: Subscription | None = None
        self._dropped_before = 0  # what earlier subscriptions (an earlier start) lost
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        for spec in host.bus.specs().values():
            self.outlets[spec.name] = self._make_outlet(spec, spec.device)
            self._channels[spec.name] = tuple(c.name for c in spec.channels)
            self._device_streams.setdefault(spec.device, []).append(spec.name)
        info = pylsl.StreamInfo(EVENTS_STREAM, "Markers", 1, pylsl.IRREGULAR_RATE, "string",
                                f"{SOURCE_PREFIX}.events")
        self.events_outlet = pylsl.StreamOutlet(info)

    @property
    def dropped(self) -> int:
        """Samples lost because the worker did not drain in time."""
        return self._dropped_before + (self._sub.dropped if self._sub is not None else 0)

    def _make_outlet(self, spec: StreamSpec, device: str) -> Any:
        pylsl = self._pylsl
        info = pylsl.StreamInfo(spec.name, device, len(spec.channels), lsl_rate_hz(self.config, device, spec),
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
        if self._sub is None:
            bus = self.host.bus
            # A device not connected now is in a data gap, as the recorder starts a session's record.
            self._in_gap = {device: (last := bus.last_event(device)) is None or last.kind == journal.DISCONNECTED
                            for device in self._device_streams}
            self._sub = bus.subscribe("lsl", tuple(self._channels), events=True, records=True, keep_records=True,
                                      maxlen=self.queue_limit)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="lsl-outlets", daemon=True)
        self._thread.start()
        log.info("LSL outlets: %s (clock offset %.6f s)", ", ".join(self.outlets), self.offset_s)

    def stop(self) -> None:
        sub, self._sub = self._sub, None
        if sub is not None:
            sub.close()  # no new samples; the worker pushes what is queued, then ends
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if sub is not None:
            self._push(sub)
            self._dropped_before += sub.dropped
        self.outlets.clear()  # outlets vanish from the network when released
        self.events_outlet = None

    def lsl_time(self, t_mono: float) -> float:
        return t_mono + self.offset_s

    # ------------------------------------------------------------------ internals
    def _run(self) -> None:
        sub = self._sub
        while not self._stop.wait(_PUSH_PERIOD_S):
            try:
                self._push(sub)
            except Exception:
                log.exception("LSL push failed")

    def _marker_text(self, record: Record) -> str:
        event = journal_event(record, self.host.operator, self._in_gap, self._device_streams)
        return json.dumps(written_event(event), ensure_ascii=False, default=str)

    def _push(self, sub: Subscription | None) -> None:
        chunks: dict[str, tuple[list[list[float]], list[float]]] = {}
        for item in sub.drain() if sub is not None else ():
            if isinstance(item, Record):
                self._markers.append((item.t_mono, self._marker_text(item)))
                continue
            names = self._channels.get(item.stream)
            if names is None:
                continue
            rows, stamps = chunks.setdefault(item.stream, ([], []))
            rows.append([_num(getattr(item.sample, n, float("nan"))) for n in names])
            stamps.append(item.t + self.offset_s)
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
IRREGULAR_STREAMS: frozenset[str] = frozenset({streams.FES_CHANNELS})


def lsl_rate_hz(config: AppConfig, device: str, spec: StreamSpec) -> float:
    """The nominal rate declared to LSL: the configured rate, or 0 (irregular)."""
    if spec.name in IRREGULAR_STREAMS:
        return 0.0
    from app.session.recording import configured_rate_hz

    return float(configured_rate_hz(config, device, spec))


def start_lsl(host: LslHost, force: bool = False) -> LslBridge | None:
    """Outlets for every stream when ``recording.lsl`` is on (or ``force``); None when off or when
    pylsl/liblsl is missing on this platform (logged as a warning: the application runs without LSL)."""
    if not (force or host.config.recording.lsl):
        return None
    ok, text = lsl_status()
    if not ok:
        log.warning("recording.lsl is on but %s; running without LSL outlets", text)
        return None
    try:
        bridge = LslBridge(host)
    except Exception as exc:
        log.warning("LSL outlets could not be created (%s); running without LSL outlets", exc)
        return None
    bridge.start()
    log.info("%s", text)
    return bridge
