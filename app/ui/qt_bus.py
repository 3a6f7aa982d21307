"""The one Qt adapter of the stream bus (issue #29): bus traffic in, Qt signals out, on the GUI thread.

The bus (:mod:`app.core.bus`) knows nothing of Qt; the window's frames know nothing of drivers. A :class:`QtBus`
sits between them, napari style: it subscribes to the bus when built (and only while someone listens to its
signals), and lets go of everything when closed.

* ``samples`` — every stream's samples since the last tick as columns (``dict[str, SampleBatch]``), taken from
  a ``subscribe_batches("qt")`` on a GUI timer at the display rate (30 Hz): never one signal per sample.
* ``device_event(device, kind, detail)`` — every device event, from a queued ``subscribe("qt-events", [],
  events=True)`` drained on the same timer; and, folded from those, ``connection_changed(device, connected,
  reason)`` and ``silence_changed(device, silent)``.
* The journal (:mod:`app.core.journal`), from the same queue (``records=True``): ``record(Record)`` for every record
  (the devices' events too), and, folded from the supervisor's, ``alarm_raised(Alarm)``, ``alarms_changed()``,
  ``estop_changed(latched, reason)``, ``command_refused(source, reason)`` and ``lease_changed()``; and
  ``progress_changed(ProgressState)`` from the exercise's progress (:meth:`watch_progress`). The panels take these
  here, never from a driver or the supervisor: the supervisor is a plain class, the drivers' signals are theirs.
  The window calls :meth:`tick` right after it stops, so the e-stop shows at once, not one tick later.
* Current values are not signals: a frame that polls asks :meth:`latest` (the bus's own latest sample) and
  :meth:`connected` / :meth:`silent` on its own timer.

The timer runs only while a slot is connected to one of the signals; the batch subscription is open only while
a slot listens to ``samples``. Connection queries read the events already queued first, so a frame asking just
after a device dropped sees the drop even before the next tick emits it.
"""

from __future__ import annotations

import inspect
import logging
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from PySide6.QtCore import QMetaMethod, QObject, QTimer, Signal

from app.core import journal
from app.core.bus import BatchSubscription, StreamBus, StreamSpec, Subscription
from app.core.journal import Record
from app.safety.supervisor import Alarm, AlarmLevel

log = logging.getLogger(__name__)

DISPLAY_HZ = 30.0
BATCHES_NAME = "qt"
EVENTS_NAME = "qt-events"
# Kinds that say the link is up although they are not "connected": the device sent them while connected.
_UP_KINDS = frozenset({journal.CONNECTED, journal.SILENT, journal.ALIVE, journal.CONTROLLER_ERROR})
_SIGNALS = ("samples(PyObject)", "device_event(QString,QString,QString)",
            "connection_changed(QString,bool,QString)", "silence_changed(QString,bool)", "record(PyObject)",
            "alarm_raised(PyObject)", "alarms_changed()", "estop_changed(bool,QString)",
            "command_refused(QString,QString)", "lease_changed()", "progress_changed(PyObject)")
_SIGNAL_NAMES = frozenset(sig.partition("(")[0].encode() for sig in _SIGNALS)
AlarmLookup = Callable[[int], "Alarm | None"]


@dataclass
class LinkState:
    """What the events told about one device's link so far."""

    connected: bool = False
    silent: bool = False
    reason: str = ""


class QtBus(QObject):
    """Qt signals for a :class:`~app.core.bus.StreamBus` (see the module docstring). Build it and close it on the GUI
    thread; the bus may be fed from any thread. Destroying it (with its Qt parent) closes it too."""

    samples = Signal(object)  # dict[str, SampleBatch]
    device_event = Signal(str, str, str)  # device, kind, detail
    connection_changed = Signal(str, bool, str)  # device, connected, reason
    silence_changed = Signal(str, bool)  # device, silent
    record = Signal(object)  # app.core.journal.Record: every journal record and device event, in order
    alarm_raised = Signal(object)  # app.safety.supervisor.Alarm
    alarms_changed = Signal()  # an alarm raised or acknowledged
    estop_changed = Signal(bool, str)  # latched, reason
    command_refused = Signal(str, str)  # source, reason
    lease_changed = Signal()  # a device's holder changed (the panels' "Robot held by: …")
    progress_changed = Signal(object)  # app.core.progress.ProgressState

    def __init__(self, bus: StreamBus, *, display_hz: float = DISPLAY_HZ, parent: QObject | None = None,
                 alarms: AlarmLookup | None = None, share: bool = False) -> None:
        super().__init__(parent)
        self.bus = bus
        self._alarm_lookup = alarms  # the supervisor's alarm by ident (the window passes supervisor.alarm)
        # The subscriptions, in a holder the ``destroyed`` handler shares: it must not reference self.
        self._subs = _Subscriptions(events=bus.subscribe(EVENTS_NAME, [], events=True, records=True))
        self.destroyed.connect(lambda *_a, subs=self._subs: subs.close())
        self._links: dict[str, LinkState] = {}
        self._pending: list[Record] = []  # folded by a query, emitted at the next tick
        self._progress: list[Any] = []  # progress states from the script's thread, emitted at the next tick
        self._progress_lock = threading.Lock()
        self._watched: dict[int, Callable[[], None]] = {}  # progress objects followed, by id
        for device in {spec.device for spec in bus.specs().values()}:
            self._seed_link(device)
        self.timer = QTimer(self)
        self.timer.setInterval(max(1, round(1000 / max(display_hz, 1.0))))
        self.timer.timeout.connect(self.tick)
        meta = self.metaObject()
        self._signal_methods = [meta.method(meta.indexOfSignal(sig)) for sig in _SIGNALS]
        if share:
            _SHARED[bus] = self

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
        if self._progress:
            with self._progress_lock:
                states, self._progress = self._progress, []
            for state in states:
                self.progress_changed.emit(state)
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
            if isinstance(item, Record):
                if item.from_device:
                    self._links[item.device] = _fold(self._links.get(item.device) or LinkState(), item)
                if emit:
                    self._pending.append(item)

    def _emit_event(self, event: Record) -> None:
        if event.from_device:
            self.device_event.emit(event.device, event.kind, event.detail)
            if event.kind in (journal.CONNECTED, journal.DISCONNECTED):
                self.connection_changed.emit(event.device, event.kind == journal.CONNECTED, event.detail)
            elif event.kind in (journal.SILENT, journal.ALIVE):
                self.silence_changed.emit(event.device, event.kind == journal.SILENT)
        else:
            self._emit_journal(event)
        self.record.emit(event)

    def _emit_journal(self, rec: Record) -> None:
        """The supervisor's records as the window's signals (what its Qt signals were)."""
        kind, data = rec.kind, rec.data
        if rec.origin != journal.SAFETY:
            return
        if kind == journal.ALARM:
            self.alarm_raised.emit(self._alarm(rec))
            self.alarms_changed.emit()
        elif kind == journal.ALARM_ACKNOWLEDGED:
            self.alarms_changed.emit()
        elif kind == journal.EMERGENCY_STOP:
            self.estop_changed.emit(True, f"{data.get('reason', '')} ({data.get('source', '')})")
        elif kind == journal.EMERGENCY_STOP_RESET:
            self.estop_changed.emit(False, "")
        elif kind == journal.COMMAND_REFUSED or (kind == journal.LEASE_REFUSED and "run_id" in data):
            self.command_refused.emit(str(data.get("source", "")), str(data.get("reason", "")))
        if kind in (journal.LEASE_TAKEN, journal.LEASE_RELEASED):
            self.lease_changed.emit()

    def _alarm(self, rec: Record) -> Alarm:
        data = rec.data
        ident = int(data.get("ident", 0))
        alarm = self._alarm_lookup(ident) if self._alarm_lookup is not None else None
        if alarm is None:
            level = data.get("level", "INFO")
            alarm = Alarm(AlarmLevel[level] if level in AlarmLevel.__members__ else AlarmLevel.INFO,
                          str(data.get("source", "")), str(data.get("text", "")), t_wall=rec.t_wall, ident=ident)
        return alarm

    def watch_progress(self, progress: Any) -> Callable[[], None]:
        """``progress_changed`` for each state of ``progress`` (an app.core.progress.ExerciseProgress; its changes come
        on the script's thread), emitted at the next tick; returns the unsubscribe."""

        if id(progress) in self._watched:
            return self._watched[id(progress)]

        def changed(state: Any) -> None:
            with self._progress_lock:
                self._progress.append(state)

        unsubscribe: Callable[[], None] = progress.subscribe(changed)
        self._watched[id(progress)] = unsubscribe
        self.destroyed.connect(lambda *_a: unsubscribe())
        return unsubscribe

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


def _fold(link: LinkState, event: Record) -> LinkState:
    """The link after ``event``; a kind the adapter does not know (a driver's own) changes nothing."""
    kind = event.kind
    if kind in (journal.CONNECTED, journal.DISCONNECTED):
        return LinkState(kind == journal.CONNECTED, False, event.detail)
    if kind in (journal.SILENT, journal.ALIVE):
        return LinkState(True, kind == journal.SILENT, link.reason)
    if kind == journal.CONTROLLER_ERROR:
        return LinkState(True, link.silent, link.reason)
    return link


_SHARED: weakref.WeakKeyDictionary[StreamBus, QtBus] = weakref.WeakKeyDictionary()


def shared_qt_bus(bus: StreamBus, alarms: AlarmLookup | None = None) -> QtBus:
    """The window's adapter of ``bus`` (built with ``share=True``), for a panel built with the manager or the
    supervisor only; while no window has one (a panel alone, in a test), one of its own, shared the same way."""
    adapter = _SHARED.get(bus)
    if adapter is None or adapter.closed:
        adapter = QtBus(bus, alarms=alarms, share=True)
    elif adapter._alarm_lookup is None:
        adapter._alarm_lookup = alarms
    return adapter


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
