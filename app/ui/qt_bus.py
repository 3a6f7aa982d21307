"""The one Qt adapter of the stream bus (issue #29): bus traffic in, Qt signals out, on the GUI thread.

The bus (:mod:`app.bus`) knows nothing of Qt; the window's frames know nothing of drivers. A :class:`QtBus`
sits between them, napari style: it subscribes to the bus when built (and only while someone listens to its
signals), and lets go of everything when closed.

* ``samples`` — every stream's samples since the last tick as columns (``dict[str, SampleBatch]``), taken from
  a ``subscribe_batches("qt")`` on a GUI timer at the display rate (30 Hz): never one signal per sample.
* ``device_event(device, kind, detail)`` — every device event, from a queued ``subscribe("qt-events", [],
  events=True)`` drained on the same timer; and, folded from those, ``connection_changed(device, connected,
  reason)`` and ``silence_changed(device, silent)``.
* Current values are not signals: a frame that polls asks :meth:`latest` (the bus's own latest sample) and
  :meth:`connected` / :meth:`silent` on its own timer.

The timer runs only while a slot is connected to one of the signals; the batch subscription is open only while
a slot listens to ``samples``. Connection queries read the events already queued first, so a frame asking just
after a device dropped sees the drop even before the next tick emits it.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from PySide6.QtCore import QMetaMethod, QObject, QTimer, Signal

from app.bus import BatchSubscription, DeviceEvent, StreamBus, StreamSpec, Subscription

log = logging.getLogger(__name__)

DISPLAY_HZ = 30.0
BATCHES_NAME = "qt"
EVENTS_NAME = "qt-events"
# Kinds that say the link is up although they are not "connected": the device sent them while connected.
_UP_KINDS = frozenset({"connected", "silent", "alive", "controller_error"})
_SIGNAL_NAMES = frozenset({b"samples", b"device_event", b"connection_changed", b"silence_changed"})


@dataclass
class LinkState:
    """What the events told about one device's link so far."""

    connected: bool = False
    silent: bool = False
    reason: str = ""


class QtBus(QObject):
    """Qt signals for a :class:`~app.bus.StreamBus` (see the module docstring). Build it and close it on the GUI
    thread; the bus may be fed from any thread. Destroying it (with its Qt parent) closes it too."""

    samples = Signal(object)  # dict[str, SampleBatch]
    device_event = Signal(str, str, str)  # device, kind, detail
    connection_changed = Signal(str, bool, str)  # device, connected, reason
    silence_changed = Signal(str, bool)  # device, silent

    def __init__(self, bus: StreamBus, *, display_hz: float = DISPLAY_HZ, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.bus = bus
        # The subscriptions, in a holder the ``destroyed`` handler shares: it must not reference self.
        self._subs = _Subscriptions(events=bus.subscribe(EVENTS_NAME, [], events=True))
        self.destroyed.connect(lambda *_a, subs=self._subs: subs.close())
        self._links: dict[str, LinkState] = {}
        self._pending: list[DeviceEvent] = []  # folded by a query, emitted at the next tick
        for device in {spec.device for spec in bus.specs().values()}:
            self._seed_link(device)
        self.timer = QTimer(self)
        self.timer.setInterval(max(1, round(1000 / max(display_hz, 1.0))))
        self.timer.timeout.connect(self.tick)
        meta = self.metaObject()
        self._signal_methods = [meta.method(meta.indexOfSignal(sig)) for sig in (
            "samples(PyObject)", "device_event(QString,QString,QString)",
            "connection_changed(QString,bool,QString)", "silence_changed(QString,bool)")]

    @property
    def closed(self) -> bool:
        return self._subs.closed

    # ------------------------------------------------------------------ current values (GUI thread, any time)
    def latest(self, stream: str) -> Any:
        """The newest sample of ``stream`` (None before the first): the bus's own."""
        return self.bus.latest(stream)

    def specs(self, device: str | None = None) -> dict[str, StreamSpec]:
        return self.bus.specs(device)

    def connected(self, device: str) -> bool:
        return self._link(device).connected

    def silent(self, device: str) -> bool:
        """Connected, but no sample for the driver's silence timeout."""
        link = self._link(device)
        return link.connected and link.silent

    def reason(self, device: str) -> str:
        """The detail of the device's last connection event (e.g. why it disconnected)."""
        return self._link(device).reason

    def _link(self, device: str) -> LinkState:
        self._pull_events()
        link = self._links.get(device)
        return link if link is not None else self._seed_link(device)

    def _seed_link(self, device: str) -> LinkState:
        """A device first asked about: its state from the bus's record of its last event."""
        link = LinkState()
        last = self.bus.last_event(device)
        if last is not None:
            link = _fold(LinkState(connected=last.kind in _UP_KINDS), last)
        self._links[device] = link
        return link

    # ------------------------------------------------------------------ the timer
    def connectNotify(self, signal: QMetaMethod) -> None:
        """A slot connects: listen (to the batches only for ``samples``) and start the timer."""
        name = bytes(signal.name().data())
        if self.closed or name not in _SIGNAL_NAMES:  # e.g. ``destroyed``, connected while being built
            return
        if name == b"samples" and self._subs.batches is None:
            self._subs.batches = self.bus.subscribe_batches(BATCHES_NAME)
        if not self.timer.isActive():
            self.timer.start()

    def listened(self) -> bool:
        """Whether any slot is connected to one of the signals."""
        return any(self.isSignalConnected(m) for m in self._signal_methods)

    def tick(self) -> None:
        """Emit what arrived since the last tick; stop when nobody listens any more."""
        if self.closed:
            return
        self._pull_events()
        pending, self._pending = self._pending, []
        for event in pending:
            self._emit_event(event)
        batches_sub = self._subs.batches
        if batches_sub is not None:
            if self.isSignalConnected(self._signal_methods[0]):
                batches = batches_sub.take()
                if batches:
                    self.samples.emit(batches)
            else:  # nobody draws: no columns kept on the driver threads for nobody
                batches_sub.close()
                self._subs.batches = None
        if not self.listened():
            self.timer.stop()

    def _pull_events(self) -> None:
        """Fold the queued events into the link states now; their signals go out at the next tick."""
        events = self._subs.events
        if events is None:
            return
        emit = self.listened()  # with nobody listening, the state is all that is kept
        for item in events.drain():
            if isinstance(item, DeviceEvent):
                self._links[item.device] = _fold(self._links.get(item.device) or LinkState(), item)
                if emit:
                    self._pending.append(item)

    def _emit_event(self, event: DeviceEvent) -> None:
        self.device_event.emit(event.device, event.kind, event.detail)
        if event.kind in ("connected", "disconnected"):
            self.connection_changed.emit(event.device, event.kind == "connected", event.detail)
        elif event.kind in ("silent", "alive"):
            self.silence_changed.emit(event.device, event.kind == "silent")

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Let go of the bus: no subscription of this adapter remains, its timer stops, no signal follows."""
        self._subs.close()
        self._pending.clear()
        self.timer.stop()


@dataclass
class _Subscriptions:
    events: Subscription | None
    batches: BatchSubscription | None = None
    closed: bool = False

    def close(self) -> None:
        self.closed = True
        for sub in (self.batches, self.events):
            if sub is not None:
                sub.close()
        self.batches = self.events = None


def _fold(link: LinkState, event: DeviceEvent) -> LinkState:
    """The link after ``event``; a kind the adapter does not know (a driver's own) changes nothing."""
    kind = event.kind
    if kind in ("connected", "disconnected"):
        return LinkState(kind == "connected", False, event.detail)
    if kind in ("silent", "alive"):
        return LinkState(True, kind == "silent", link.reason)
    if kind == "controller_error":
        return LinkState(True, link.silent, link.reason)
    return link


def qt_bus_for(manager: Any, qt_bus: QtBus | None = None, owner: QObject | None = None) -> QtBus:
    """The adapter a frame reads: the one its window passed, else one of the frame's own on ``manager.bus``
    (``owner`` its parent: it closes with the frame)."""
    if qt_bus is not None:
        return qt_bus
    return QtBus(manager.bus, parent=owner)


def takes_qt_bus(factory: Callable[..., Any]) -> bool:
    """Whether a frame or panel reads the window's adapter (a ``qt_bus`` keyword); others get the manager only."""
    try:
        return "qt_bus" in inspect.signature(factory).parameters
    except (TypeError, ValueError):
        return False
