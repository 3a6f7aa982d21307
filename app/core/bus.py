"""The stream bus: the one way samples and device events leave a driver (issue #29).

Qt-free. The composition root builds one :class:`StreamBus` and hands it to every device (in its typed
``DeviceContext``) and to every consumer; nobody reaches into a driver for its data.

* A driver **declares** its streams (:class:`StreamSpec`) and **publishes** typed, timestamped samples and
  device events (``connected``, ``disconnected``, ``silent``, ``alive``, ``controller_error``, …).
* The **journal** travels here too (:mod:`app.core.journal`): one :class:`~app.core.journal.Record` type for the
  devices'
  events (:meth:`StreamBus.event`, origin the device) and the application's records — alarms, e-stops, refusals,
  leases, faults, run changes (:meth:`StreamBus.record`, origin ``safety``/``run``/``progress``). A subscriber
  asks for the first with ``events=True``, the second with ``records=True``; both arrive in one queue, in the
  order they were published. A subscriber that writes the medical record asks ``keep_records=True``: its queue
  then never drops a journal record (the oldest sample or device event goes instead); a display's queue drops
  the oldest of anything. :meth:`StreamBus.listen` calls a quick callback on the publishing thread instead.
* The bus keeps each stream's **latest** sample and the :class:`UpdateNotifier` a script's ``waitCondition``
  waits on (woken once per driver read, not once per sample).
* A consumer **subscribes** by name to the streams (and events) it wants and gets a **bounded, counted queue**
  (:class:`Subscription`): it drains it on its own thread or timer, so a slow consumer can only lose its own
  oldest items (counted in ``dropped``), never slow a driver or another consumer.
* **Inline** delivery (the callback runs on the publishing driver's thread, before ``publish`` returns) is
  kept for the safety monitor only, by name (:data:`INLINE_SUBSCRIBERS`): its check must see every sample
  before anything else does.
* The graphs and values want columns at display rate: a :class:`BatchSubscription` accumulates samples as they
  are decoded and hands them over as numpy columns (:class:`SampleBatch`) when taken. The Qt adapter
  (``app/ui/qt_bus.py``) takes them on a GUI timer and emits Qt signals; nothing here knows about Qt.

Stream names are constants in :mod:`app.core.streams`.
"""

from __future__ import annotations

import logging
import operator
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.core.journal import JOURNAL_ORIGINS, Record, RecordSink

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- stream types
@dataclass(frozen=True)
class Channel:
    """One scalar signal of a stream: attribute name on the sample, unit, human label."""

    name: str
    unit: str
    label: str


@dataclass(frozen=True)
class StreamSpec:
    name: str  # "<device>.<stream>", e.g. app.core.streams.LINARM_VSA
    channels: tuple[Channel, ...]
    nominal_rate_hz: float

    @property
    def device(self) -> str:
        return self.name.partition(".")[0]


@dataclass
class SampleBatch:
    """Samples of one stream since the last batch: ``t`` in monotonic seconds (when each sample was taken, on
    the device's clock mapped to the host's: app.devices.clock), one array per channel, and ``arrival`` (when
    each came back from a read; a diagnostic, None when not kept)."""

    stream: StreamSpec
    t: np.ndarray
    data: dict[str, np.ndarray]
    arrival: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True, slots=True)
class SampleItem:
    """One published sample: ``t`` when it was taken (device clock mapped to host monotonic s), ``arrival``
    when the read that carried it returned."""

    stream: str
    t: float
    sample: Any
    arrival: float


# A device's event is a journal Record whose origin is the device: one record type for everything that happens,
# the devices' events and the application's alike.
BusItem = SampleItem | Record

# Who may run on the publishing driver's thread. Anything else gets a queue.
INLINE_SUBSCRIBERS = frozenset({"safety"})
DEFAULT_MAXLEN = 4096  # items per subscription: ~4 s of the LINarm's four streams at their nominal rates


class UpdateNotifier:
    """A generation counter + condition: 'some device published something'.

    ``notify`` runs once per read on every driver thread: with nobody waiting (no script in a wait) it is one
    C-level lock and an increment, not Condition.notify_all's Python code."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._waiting = 0  # threads in wait_after, counted under the lock
        self.generation = 0

    def notify(self) -> None:
        with self._lock:
            self.generation += 1
            if self._waiting:
                self._cond.notify_all()

    def wait_after(self, generation: int, timeout: float) -> int:
        """Block until the generation moves past ``generation`` (or timeout); return the new one."""
        with self._lock:
            if self.generation == generation:
                self._waiting += 1
                try:
                    self._cond.wait(timeout)
                finally:
                    self._waiting -= 1
            return self.generation


# ---------------------------------------------------------------------------------------------- subscriptions
class Subscription:
    """A consumer's bounded queue of bus items. ``received`` counts every item offered, ``dropped`` the oldest
    ones pushed out because the consumer did not drain in time. Thread-safe: drivers put, the consumer drains."""

    def __init__(self, bus: StreamBus, name: str, streams: frozenset[str] | None, events: bool,
                 maxlen: int, records: bool = False, keep_records: bool = False) -> None:
        if maxlen < 1:
            raise ValueError("a subscription holds at least one item")
        self.bus = bus
        self.name = name
        self.streams = streams  # None: every stream
        self.events = events
        self.records = records  # the journal's records (alarms, e-stops, refusals, runs)
        self.keep_records = keep_records  # never drop one of them (the session record's queue)
        self.maxlen = maxlen
        self.received = 0
        self.dropped = 0
        self._items: deque[BusItem] = deque()
        self._lock = threading.Lock()
        self._ready = threading.Event()  # set by StreamBus.wake when items wait
        self.closed = False

    def wants(self, stream: str) -> bool:
        return self.streams is None or stream in self.streams

    def put(self, item: BusItem) -> None:
        with self._lock:
            self.received += 1
            if len(self._items) >= self.maxlen:
                self._drop_oldest()
            self._items.append(item)

    def _drop_oldest(self) -> None:
        """Make room (under the lock): the oldest item goes; with ``keep_records`` the oldest sample or device event,
        never a journal record (the queue then holds more than ``maxlen``: what the medical record says is kept)."""
        items = self._items
        if not self.keep_records or not (isinstance(items[0], Record) and not items[0].from_device):
            items.popleft()
            self.dropped += 1
            return
        for k, old in enumerate(items):
            if not (isinstance(old, Record) and not old.from_device):
                del items[k]
                self.dropped += 1
                return

    def pending(self) -> int:
        return len(self._items)

    def drain(self, max_items: int | None = None) -> list[BusItem]:
        """The queued items, oldest first (at most ``max_items``); they leave the queue."""
        with self._lock:
            if max_items is None or max_items >= len(self._items):
                out = list(self._items)
                self._items.clear()
            else:
                out = [self._items.popleft() for _ in range(max_items)]
            if not self._items:
                self._ready.clear()
        return out

    def wait(self, timeout: float | None) -> bool:
        """Block until items are queued (or ``timeout``); True when some are. Woken once per driver read."""
        if self._items:
            return True
        if self.closed:
            return False
        self._ready.wait(timeout)
        return bool(self._items)

    def _signal(self) -> None:
        if self._items and not self._ready.is_set():
            self._ready.set()

    def close(self) -> None:
        """Leave the bus; a consumer waiting in :meth:`wait` returns at once (False when nothing is left)."""
        self.bus.unsubscribe(self)
        self._ready.set()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class InlineSubscription:
    """A callback run on the publishing thread (safety monitor only: :data:`INLINE_SUBSCRIBERS`)."""

    bus: StreamBus
    name: str
    callback: Callable[[BusItem], None]
    streams: frozenset[str] | None
    events: bool
    records: bool = False
    failures: int = 0
    closed: bool = False

    def wants(self, stream: str) -> bool:
        return self.streams is None or stream in self.streams

    def close(self) -> None:
        self.bus.unsubscribe(self)


@dataclass
class _Columns:
    """One stream's samples since the last take: the samples themselves (one append per sample); their
    channels are read into columns when taken, one C call per sample (``attrgetter``)."""

    spec: StreamSpec
    maxlen: int
    t: deque[float] = field(default_factory=deque)
    arrival: deque[float] = field(default_factory=deque)
    samples: deque[Any] = field(default_factory=deque)
    dropped: int = 0

    def __post_init__(self) -> None:
        self.names = [c.name for c in self.spec.channels]
        self._row = operator.attrgetter(*self.names) if self.names else None

    def add(self, t: float, sample: Any, arrival: float) -> None:
        if len(self.t) >= self.maxlen:
            self.t.popleft()
            self.arrival.popleft()
            self.samples.popleft()
            self.dropped += 1
        self.t.append(t)
        self.arrival.append(arrival)
        self.samples.append(sample)

    def take(self) -> SampleBatch:
        n = len(self.samples)
        if self._row is None or n == 0:
            data: dict[str, np.ndarray] = {name: np.empty(0) for name in self.names}
        else:
            row = self._row
            rows = np.array([row(s) for s in self.samples], dtype=np.float64).reshape(n, len(self.names))
            columns = rows.T.copy()  # each channel contiguous
            data = {name: columns[k] for k, name in enumerate(self.names)}
        batch = SampleBatch(self.spec, np.asarray(self.t, dtype=np.float64), data,
                            np.asarray(self.arrival, dtype=np.float64))
        self.t, self.arrival, self.samples = deque(), deque(), deque()
        return batch


class BatchSubscription:
    """Samples accumulated as they are decoded, taken as columns (display rate, e.g. the Qt adapter's timer).
    Bounded to ``max_age_s`` of each stream at its nominal rate; what fell out is counted in ``dropped``."""

    def __init__(self, bus: StreamBus, name: str, streams: frozenset[str] | None, max_age_s: float) -> None:
        self.bus = bus
        self.name = name
        self.streams = streams
        self.max_age_s = max_age_s
        self._lock = threading.Lock()
        self._columns: dict[str, _Columns] = {}
        self.closed = False

    def wants(self, stream: str) -> bool:
        return self.streams is None or stream in self.streams

    def add(self, spec: StreamSpec, t: float, sample: Any, arrival: float) -> None:
        with self._lock:
            cols = self._columns.get(spec.name)
            if cols is None:
                cols = self._columns[spec.name] = _Columns(spec, max(16, int(spec.nominal_rate_hz * self.max_age_s)))
            cols.add(t, sample, arrival)

    @property
    def dropped(self) -> int:
        return sum(c.dropped for c in self._columns.values())

    def take(self, device: str | None = None) -> dict[str, SampleBatch]:
        """Every stream's samples since the last take (only ``device``'s when given), as columns."""
        with self._lock:
            return {name: cols.take() for name, cols in self._columns.items()
                    if cols.t and (device is None or cols.spec.device == device)}

    def close(self) -> None:
        self.bus.unsubscribe(self)


@dataclass
class RecordListener:
    """A quick callback for every journal record, on the publishing thread (:meth:`StreamBus.listen`)."""

    bus: StreamBus
    name: str
    callback: RecordSink
    failures: int = 0
    closed: bool = False

    def close(self) -> None:
        self.bus.unsubscribe(self)


AnySubscription = Subscription | InlineSubscription | BatchSubscription | RecordListener


# ---------------------------------------------------------------------------------------------- the bus
class StreamBus:
    """Streams by name, their latest samples, and the consumers' subscriptions (see the module docstring)."""

    def __init__(self, notifier: UpdateNotifier | None = None) -> None:
        self.notifier = notifier or UpdateNotifier()
        self._specs: dict[str, StreamSpec] = {}
        self._latest: dict[str, Any] = {}
        self._latest_t: dict[str, float] = {}
        self._totals: dict[str, int] = {}
        self._events: dict[str, Record] = {}  # each device's last event
        self._lock = threading.Lock()  # guards the subscription lists (copy-on-write: publish reads without it)
        self._queued: tuple[Subscription, ...] = ()
        self._inline: tuple[InlineSubscription, ...] = ()
        self._batches: tuple[BatchSubscription, ...] = ()
        # stream -> (inline, queued, batch) subscribers wanting it; rebuilt when subscriptions change
        self._routes: dict[str, tuple[tuple[InlineSubscription, ...], tuple[Subscription, ...],
                                      tuple[BatchSubscription, ...]]] = {}
        self._event_routes: tuple[tuple[InlineSubscription, ...], tuple[Subscription, ...]] = ((), ())
        self._listeners: tuple[RecordListener, ...] = ()
        self._record_routes: tuple[tuple[InlineSubscription, ...], tuple[Subscription, ...]] = ((), ())

    # ------------------------------------------------------------------ streams
    def declare(self, specs: Iterable[StreamSpec]) -> None:
        """A driver's streams (at construction). A name declared twice must mean the same stream."""
        with self._lock:
            for spec in specs:
                known = self._specs.get(spec.name)
                if known is not None and known != spec:
                    raise ValueError(f"stream {spec.name} is declared twice, differently")
                self._specs[spec.name] = spec
                self._totals.setdefault(spec.name, 0)
            self._reroute()

    def spec(self, stream: str) -> StreamSpec:
        return self._specs[stream]

    def specs(self, device: str | None = None) -> dict[str, StreamSpec]:
        return {n: s for n, s in self._specs.items() if device is None or s.device == device}

    def latest(self, stream: str) -> Any:
        """The newest sample of ``stream`` (None before the first)."""
        return self._latest.get(stream)

    def latest_time(self, stream: str) -> float | None:
        return self._latest_t.get(stream)

    def total(self, stream: str) -> int:
        return self._totals.get(stream, 0)

    def last_event(self, device: str) -> Record | None:
        return self._events.get(device)

    # ------------------------------------------------------------------ publishing (driver threads)
    def publish(self, stream: str, t: float, sample: Any, arrival: float | None = None, *,
                wake: bool = True) -> None:
        """One decoded sample to every subscriber of ``stream``. ``wake=False`` inside a read: the driver calls
        :meth:`wake` once after the read's last sample, so waiters wake once per read."""
        arrival = t if arrival is None else arrival
        self._latest[stream] = sample
        self._latest_t[stream] = t
        self._totals[stream] = self._totals.get(stream, 0) + 1
        route = self._routes.get(stream)
        if route is None:
            raise KeyError(f"stream {stream!r} was never declared")
        inline, queued, batches = route
        if inline or queued:
            item = SampleItem(stream, t, sample, arrival)
            for sub in inline:
                self._call_inline(sub, item)
            for q in queued:
                q.put(item)
        if batches:
            spec = self._specs[stream]
            for b in batches:
                b.add(spec, t, sample, arrival)
        if wake:
            self.wake()

    def event(self, device: str, kind: str, detail: str = "", **data: Any) -> Record:
        """A device event (connected, disconnected, silent, alive, controller_error, …) to the subscribers that
        asked for events, and to waiters."""
        if device in JOURNAL_ORIGINS:
            raise ValueError(f"{device!r} is not a device: its records go through record()")
        item = Record(device, kind, {"detail": detail, **data}, time.monotonic(), time.time())  # the bus's clock
        self._events[device] = item
        inline, queued = self._event_routes
        for sub in inline:
            self._call_inline(sub, item)
        for q in queued:
            q.put(item)
        self.wake()
        return item

    def record(self, origin: str, kind: str, data: dict[str, Any] | None = None, who: str = "") -> Record:
        """A journal record (an alarm, an e-stop, a refusal, a run change: :mod:`app.core.journal`) to the subscribers
        that asked for records, on the calling thread. The queues and listeners get it first, the safety monitor
        (inline) last: what it does about the record (a fault, a safe state) follows the record in the journal."""
        if origin not in JOURNAL_ORIGINS:
            raise ValueError(f"{origin!r} publishes device events through event(), not journal records")
        item = Record(origin, kind, data if data is not None else {}, time.monotonic(), time.time(), who)
        inline, queued = self._record_routes
        for q in queued:
            q.put(item)
        for listener in self._listeners:
            try:
                listener.callback(item)
            except Exception:  # a listener's bug must not stop the one who published
                listener.failures += 1
                log.exception("journal listener %s failed", listener.name)
        for sub in inline:
            self._call_inline(sub, item)
        if queued:
            for q in queued:
                q._signal()
        return item

    def wake(self) -> None:
        """Wake the consumers waiting on their queues, and the notifier's waiters (once per read)."""
        for q in self._queued:
            q._signal()
        self.notifier.notify()

    def _call_inline(self, sub: InlineSubscription, item: BusItem) -> None:
        try:
            sub.callback(item)
        except Exception:  # a consumer's bug must not stop the device
            sub.failures += 1
            log.exception("bus subscriber %s failed", sub.name)

    # ------------------------------------------------------------------ subscribing (any thread)
    def subscribe(self, name: str, streams: Iterable[str] | None = None, *, events: bool = False,
                  records: bool = False, keep_records: bool = False, maxlen: int = DEFAULT_MAXLEN) -> Subscription:
        """A bounded, counted queue of ``streams``' samples (every stream when None), with ``events`` the device
        events, with ``records`` the journal's records (with ``keep_records`` never dropped). Close it (or use it as
        a context manager) when done."""
        sub = Subscription(self, name, self._names(streams), events, maxlen, records, keep_records)
        with self._lock:
            self._queued = (*self._queued, sub)
            self._reroute()
        return sub

    def subscribe_inline(self, name: str, callback: Callable[[BusItem], None], streams: Iterable[str] | None = None,
                         *, events: bool = False, records: bool = False) -> InlineSubscription:
        """``callback(item)`` on the publishing thread, before ``publish`` returns: only for the safety monitor
        (:data:`INLINE_SUBSCRIBERS`); it must be quick and must not block."""
        if name not in INLINE_SUBSCRIBERS:
            raise ValueError(f"{name!r} may not run on a driver's thread; subscribe() gives it a queue")
        sub = InlineSubscription(self, name, callback, self._names(streams), events, records)
        with self._lock:
            self._inline = (*self._inline, sub)
            self._reroute()
        return sub

    def subscribe_batches(self, name: str, streams: Iterable[str] | None = None, *,
                          max_age_s: float = 10.0) -> BatchSubscription:
        """Samples as columns, taken at the consumer's rate (the Qt adapter's display timer)."""
        sub = BatchSubscription(self, name, self._names(streams), max_age_s)
        with self._lock:
            self._batches = (*self._batches, sub)
            self._reroute()
        return sub

    def listen(self, name: str, callback: RecordSink) -> RecordListener:
        """``callback(record)`` for every journal record, on the publishing thread, before :meth:`record` returns
        (the session record's sink, a test's log): records are rare, but the callback must still be quick."""
        listener = RecordListener(self, name, callback)
        with self._lock:
            self._listeners = (*self._listeners, listener)
        return listener

    def resubscribe(self, sub: Subscription, streams: Iterable[str] | None) -> None:
        """Change which streams a queued subscription receives (e.g. a script subscribing to one more): its
        queue and counts stay, so the order of what it already holds is kept."""
        with self._lock:
            sub.streams = self._names(streams)
            self._reroute()

    def unsubscribe(self, sub: AnySubscription) -> None:
        with self._lock:
            sub.closed = True
            self._queued = tuple(s for s in self._queued if s is not sub)
            self._inline = tuple(s for s in self._inline if s is not sub)
            self._batches = tuple(s for s in self._batches if s is not sub)
            self._listeners = tuple(s for s in self._listeners if s is not sub)
            self._reroute()

    def subscriptions(self) -> list[AnySubscription]:
        """Every open subscription (diagnostics: names, received and dropped counts)."""
        return [*self._inline, *self._queued, *self._batches, *self._listeners]

    def _names(self, streams: Iterable[str] | None) -> frozenset[str] | None:
        if streams is None:
            return None
        names = frozenset([streams] if isinstance(streams, str) else streams)
        return names

    def _reroute(self) -> None:
        """Rebuild the per-stream routes (under ``_lock``); publish reads them without locking."""
        routes = {}
        for stream in self._specs:
            routes[stream] = (tuple(s for s in self._inline if s.wants(stream)),
                              tuple(s for s in self._queued if s.wants(stream)),
                              tuple(s for s in self._batches if s.wants(stream)))
        self._routes = routes
        self._event_routes = (tuple(s for s in self._inline if s.events),
                              tuple(s for s in self._queued if s.events))
        self._record_routes = (tuple(s for s in self._inline if s.records),
                               tuple(s for s in self._queued if s.records))
