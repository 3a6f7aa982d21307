"""GUI-side history of every live signal: ring buffers fed by the Qt bus adapter's ``samples`` batches.

One :class:`SignalStore` per manager (``shared_store(manager, qt_bus)``) keeps, for every stream declared on
the bus, a ring of timestamps and one ring per channel, so each (stream, channel) is a signal with
the unit and label of its :class:`~app.core.bus.StreamSpec`. Signals are named
``"<stream>.<channel>"``, e.g. ``"linarm.vsa.handlePos"``.

Drawing long histories fast: besides the raw samples each ring keeps a min/max per block of
``BLOCK`` samples, updated as samples arrive, so :meth:`SignalStore.envelope` reduces 60 s × 1 kHz
to a few thousand points by combining block extremes instead of scanning every sample each frame
(qt-stack.md §5: pyqtgraph's own downsampling reaches ~30 fps there, an app-side envelope > 70 fps).

Rings store every value twice (at ``i`` and ``i + capacity``) so any window of the history is one
contiguous numpy view without copying or wrap-around handling. A stream's channels are the rows of one 2-D
array (and so are their block envelopes), so :meth:`SignalStore.envelopes` reduces every channel of a stream with
one numpy call per step instead of one per channel (#37: 49 signals at ≥ 30 frames a second).

Everything here runs on the GUI thread: batches arrive from the Qt bus adapter, taken on its GUI timer.
"""

from __future__ import annotations

import math
import time
import warnings
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import shiboken6
from PySide6.QtCore import QObject, Signal

from app.core.bus import SampleBatch, StreamSpec

if TYPE_CHECKING:
    from app.manager import LinarmppManager
    from app.ui.qt_bus import QtBus

BLOCK = 32  # samples per envelope block: 60 s × 1 kHz → 1875 blocks per channel
MIN_CAPACITY = 1024
MAX_CAPACITY = 1 << 20  # per stream: ~16 MB per channel at worst (doubled float64)
CAPACITY_MARGIN = 1.5  # headroom over the nominal rate: real devices run a little fast


@dataclass(frozen=True)
class SignalInfo:
    key: str  # "<stream>.<channel>"
    device: str
    stream: str
    channel: str
    unit: str
    label: str
    nominal_rate_hz: float


def signal_key(stream: str, channel: str) -> str:
    return f"{stream}.{channel}"




class _Ring:
    """Timestamps plus one row per channel, with per-block min/max envelopes (one row per channel too).

    Sample number ``n`` (counted since the stream began) lives at ``n % cap`` and ``n % cap + cap``.
    """

    def __init__(self, spec: StreamSpec, capacity: int) -> None:
        self.spec = spec
        self.channels = [c.name for c in spec.channels]
        self.row = {c: i for i, c in enumerate(self.channels)}
        self.total = 0  # samples ever written
        self.first = 0  # first sample number that is valid (after grow)
        self._alloc(capacity)

    def _alloc(self, capacity: int) -> None:
        self.cap = max(BLOCK, math.ceil(capacity / BLOCK) * BLOCK)
        self.nblocks = self.cap // BLOCK
        rows = len(self.channels)
        self.t = np.zeros(2 * self.cap)
        self.y = np.zeros((rows, 2 * self.cap))
        self.bmin = np.zeros((rows, 2 * self.nblocks))
        self.bmax = np.zeros((rows, 2 * self.nblocks))

    def col(self, channel: str) -> np.ndarray:
        """One channel's storage row (a view)."""
        return self.y[self.row[channel]]

    # -------------------------------------------------------------- writing
    def append(self, t: np.ndarray, data: dict[str, np.ndarray]) -> None:
        n = len(t)
        if n == 0:
            return
        if n > self.cap:  # only the newest `cap` samples can be held
            skip = n - self.cap
            self.total += skip
            t = t[skip:]
            data = {k: v[skip:] for k, v in data.items()}
            n = self.cap
        start = self.total
        self._write(self.t, start, t)
        block = np.full((len(self.channels), n), np.nan)
        for i, c in enumerate(self.channels):
            col = data.get(c)
            if col is not None:
                block[i] = np.asarray(col, np.float64)[-n:]
        self._write(self.y, start, block)
        self.total += n
        self._update_blocks(start, self.total)

    def _write(self, buf: np.ndarray, start: int, values: np.ndarray) -> None:
        """Write ``values`` (1-D, or 2-D: one row per channel) at sample ``start``, twice (see the class)."""
        n = values.shape[-1]
        pos = start % self.cap
        first = min(n, self.cap - pos)
        buf[..., pos:pos + first] = values[..., :first]
        buf[..., pos + self.cap:pos + self.cap + first] = values[..., :first]
        if first < n:
            rest = n - first
            buf[..., :rest] = values[..., first:]
            buf[..., self.cap:self.cap + rest] = values[..., first:]

    def _update_blocks(self, start: int, end: int) -> None:
        """Recompute the envelope of every block completed by samples [start, end)."""
        lo = max(start // BLOCK, -(-self.oldest // BLOCK))
        hi = end // BLOCK  # exclusive: only complete blocks
        if hi <= lo:
            return
        i0, i1 = self.index_range(lo * BLOCK, hi * BLOCK)
        seg = self.y[:, i0:i1].reshape(len(self.channels), -1, BLOCK)
        if np.isnan(seg).any():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks stay NaN
                mins, maxs = np.nanmin(seg, axis=2), np.nanmax(seg, axis=2)
        else:
            mins, maxs = seg.min(axis=2), seg.max(axis=2)
        self._write_blocks(self.bmin, lo, mins)
        self._write_blocks(self.bmax, lo, maxs)

    def _write_blocks(self, buf: np.ndarray, start: int, values: np.ndarray) -> None:
        pos = start % self.nblocks
        n = values.shape[-1]
        first = min(n, self.nblocks - pos)
        buf[..., pos:pos + first] = values[..., :first]
        buf[..., pos + self.nblocks:pos + self.nblocks + first] = values[..., :first]
        if first < n:
            rest = n - first
            buf[..., :rest] = values[..., first:]
            buf[..., self.nblocks:self.nblocks + rest] = values[..., first:]

    def grow(self, capacity: int) -> None:
        """Reallocate with a larger capacity, keeping the held samples and their numbering."""
        lo, i0, i1 = self.held()
        t = self.t[i0:i1].copy()
        cols = {c: self.y[i, i0:i1].copy() for i, c in enumerate(self.channels)}
        self._alloc(capacity)
        self.first = self.total = lo  # the block holding `lo` is partial: envelope() reads it raw
        self.append(t, cols)

    # -------------------------------------------------------------- reading
    @property
    def oldest(self) -> int:
        return max(self.first, self.total - self.cap)

    @property
    def count(self) -> int:
        return self.total - self.oldest

    def index_range(self, n0: int, n1: int) -> tuple[int, int]:
        """Storage slice of the held absolute samples [n0, n1): always one contiguous slice, because
        every value is stored twice and the range is at most `cap` long."""
        if n1 <= n0:
            return 0, 0
        i0 = n0 % self.cap
        return i0, i0 + (n1 - n0)

    def held(self) -> tuple[int, int, int]:
        """(first absolute sample held, storage start, storage end)."""
        lo = self.oldest
        i0, i1 = self.index_range(lo, self.total)
        return lo, i0, i1

    def times(self) -> np.ndarray:
        _lo, i0, i1 = self.held()
        return self.t[i0:i1]

    def count_in(self, t_from: float | None, t_to: float | None) -> int:
        n0, n1 = self.sample_range(t_from, t_to)
        return n1 - n0

    def sample_range(self, t_from: float | None, t_to: float | None) -> tuple[int, int]:
        """Absolute sample numbers [n0, n1) with t_from <= t <= t_to."""
        lo, i0, i1 = self.held()
        t = self.t[i0:i1]
        a = 0 if t_from is None else int(np.searchsorted(t, t_from, "left"))
        b = len(t) if t_to is None else int(np.searchsorted(t, t_to, "right"))
        return lo + a, lo + max(a, b)


class SignalStore(QObject):
    """Ring buffers for every signal on the attached bus; fed on the GUI thread."""

    signals_changed = Signal()  # new streams were attached
    updated = Signal()  # a batch was stored

    def __init__(self, history_s: float = 30.0, max_capacity: int = MAX_CAPACITY,
                 parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.history_s = float(history_s)
        self.max_capacity = int(max_capacity)
        self._rings: dict[str, _Ring] = {}
        self._info: dict[str, SignalInfo] = {}
        self._stream_device: dict[str, str] = {}
        self._source: weakref.ref[QtBus] | None = None  # the adapter feeding the store

    # -------------------------------------------------------------- wiring
    def attach_bus(self, qt_bus: QtBus) -> None:
        """Be fed by ``qt_bus`` (its ``samples``), with every stream declared on its bus listed at once.
        One source at a time: attaching another adapter lets go of the previous one (no sample twice).
        Idempotent; call again to list streams declared since."""
        for spec in qt_bus.specs().values():
            self.add_stream(spec)
        current = self._source() if self._source is not None else None
        if current is qt_bus:
            return
        if current is not None and shiboken6.isValid(current):
            try:
                current.samples.disconnect(self.feed)
            except (RuntimeError, TypeError):  # already gone with its window
                pass
        self._source = weakref.ref(qt_bus)
        qt_bus.samples.connect(self.feed)

    def add_stream(self, spec: StreamSpec, device: str | None = None) -> None:
        if spec.name in self._rings:
            return
        device = device or spec.name.split(".", 1)[0]
        capacity = self.history_s * max(spec.nominal_rate_hz, 1.0) * CAPACITY_MARGIN
        capacity = int(min(self.max_capacity, max(MIN_CAPACITY, capacity)))
        self._rings[spec.name] = _Ring(spec, capacity)
        self._stream_device[spec.name] = device
        for ch in spec.channels:
            key = signal_key(spec.name, ch.name)
            self._info[key] = SignalInfo(key, device, spec.name, ch.name, ch.unit, ch.label, spec.nominal_rate_hz)
        self.signals_changed.emit()

    def feed(self, batches: dict[str, SampleBatch]) -> None:
        """Slot for ``QtBus.samples``: store each batch (unknown streams are added)."""
        for name, batch in batches.items():
            ring = self._rings.get(name)
            if ring is None:
                self.add_stream(batch.stream)
                ring = self._rings[name]
            ring.append(np.asarray(batch.t, np.float64), batch.data)
            self._maybe_grow(ring)
        self.updated.emit()

    def _maybe_grow(self, ring: _Ring) -> None:
        """A device faster than its nominal rate would shorten the history: grow the ring."""
        if ring.total < ring.cap or ring.cap >= self.max_capacity:
            return
        t = ring.times()
        span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
        if 0 < span < self.history_s * 0.95:
            needed = ring.cap * self.history_s / span * 1.2
            ring.grow(int(min(self.max_capacity, max(needed, ring.cap * 2))))

    def clear(self) -> None:
        for ring in self._rings.values():
            ring._alloc(ring.cap)
            ring.total = ring.first = 0

    def frozen_copy(self, keys: Iterable[str] | None = None) -> SignalStore:
        """An unattached copy of the rings holding ``keys`` (all when None): what a paused view draws
        and saves, so its data is not overwritten while the live store keeps filling."""
        copy = SignalStore(self.history_s, self.max_capacity)
        streams = set(self._rings) if keys is None else {self._info[k].stream for k in keys}
        for stream in streams:
            ring = self._rings[stream]
            clone = _Ring.__new__(_Ring)
            clone.__dict__.update(ring.__dict__)
            clone.t = ring.t.copy()
            clone.y = ring.y.copy()
            clone.bmin = ring.bmin.copy()
            clone.bmax = ring.bmax.copy()
            copy._rings[stream] = clone
            copy._stream_device[stream] = self._stream_device[stream]
        copy._info = {k: i for k, i in self._info.items() if i.stream in streams}
        return copy

    # -------------------------------------------------------------- queries
    def signals(self) -> list[SignalInfo]:
        return list(self._info.values())

    def info(self, key: str) -> SignalInfo:
        return self._info[key]

    def __contains__(self, key: str) -> bool:
        return key in self._info

    def streams(self) -> list[str]:
        return list(self._rings)

    def capacity(self, stream: str) -> int:
        return self._rings[stream].cap

    def count(self, key: str) -> int:
        return self._ring(key)[0].count

    def last_time(self) -> float | None:
        """Newest timestamp of any stream (the 'now' of live plots)."""
        newest = [r.times()[-1] for r in self._rings.values() if r.count]
        return max(newest) if newest else None

    def time_span(self, keys: Iterable[str] | None = None) -> tuple[float, float] | None:
        streams = self._rings.values() if keys is None else {self._ring(k)[0] for k in keys}
        spans = [(r.times()[0], r.times()[-1]) for r in streams if r.count]
        if not spans:
            return None
        return min(s[0] for s in spans), max(s[1] for s in spans)

    def _ring(self, key: str) -> tuple[_Ring, str]:
        info = self._info[key]
        return self._rings[info.stream], info.channel

    def snapshot(self, key: str, t_from: float | None = None,
                 t_to: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the samples of ``key`` with t_from <= t <= t_to (None = the whole buffer)."""
        ring, channel = self._ring(key)
        n0, n1 = ring.sample_range(t_from, t_to)
        i0, i1 = ring.index_range(n0, n1)
        return ring.t[i0:i1].copy(), ring.col(channel)[i0:i1].copy()

    def value_at(self, key: str, t: float) -> tuple[float, float] | None:
        """(time, value) of the sample nearest to ``t``, or None when empty."""
        ring, channel = self._ring(key)
        _lo, i0, i1 = ring.held()
        if i1 == i0:
            return None
        ts = ring.t[i0:i1]
        j = int(np.searchsorted(ts, t))
        if j >= len(ts) or (j > 0 and t - ts[j - 1] <= ts[j] - t):
            j -= 1
        return float(ts[j]), float(ring.col(channel)[i0 + j])

    def envelope(self, key: str, t_from: float | None, t_to: float | None,
                 max_points: int = 2000) -> tuple[np.ndarray, np.ndarray]:
        """Samples of ``key`` in [t_from, t_to] reduced to at most ~``max_points`` points: when there
        are more, each bucket contributes its minimum and maximum (at the bucket's first time), so
        spikes stay visible. Arrays are copies."""
        return self.envelopes([key], t_from, t_to, max_points)[key]

    def envelopes(self, keys: Iterable[str], t_from: float | None, t_to: float | None,
                  max_points: int = 2000) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """:meth:`envelope` of every key at once: the keys of one stream share their time array (one object, do
        not modify it) and are reduced together, one numpy call per step for all of them."""
        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for stream_keys, t, ys, _pairs in self.envelope_rows(keys, t_from, t_to, max_points):
            for k, y in zip(stream_keys, ys, strict=True):
                out[k] = (t, y)
        return out

    def envelope_rows(self, keys: Iterable[str], t_from: float | None, t_to: float | None,
                      max_points: int = 2000) -> list[tuple[list[str], np.ndarray, np.ndarray, bool]]:
        """The envelopes of ``keys`` grouped by stream: (the stream's keys, time, one row of values per key, whether
        they were reduced: then the points are (minimum, maximum) pairs, each pair at one time)."""
        by_stream: dict[str, list[str]] = {}
        for key in keys:
            by_stream.setdefault(self._info[key].stream, []).append(key)
        out = []
        for stream, stream_keys in by_stream.items():
            ring = self._rings[stream]
            rows = [ring.row[self._info[k].channel] for k in stream_keys]
            t, ys = _envelope_rows(ring, rows, t_from, t_to, max_points)
            out.append((stream_keys, t, ys, ring.count_in(t_from, t_to) > max_points))
        return out

    # -------------------------------------------------------------- export
    def export_csv(self, path: str | Path, signals: Sequence[str], t_from: float | None = None,
                   t_to: float | None = None, t_zero: float | None = None, t_zero_text: str = "") -> int:
        """Write ``signals`` over [t_from, t_to] (None = whole buffer) to a CSV file; returns the
        number of data rows.

        Layout: ``#`` comment lines (source, wall-clock anchor, alignment rule), then a row of names
        (``time`` then each signal key), a row of units (``s`` then each unit), then the data.

        Alignment of streams with different rates: no value is interpolated, repeated or dropped.
        There is one shared time column; each row is one instant, and a stream's cell is filled only
        in the rows of its own samples (empty otherwise). Streams sampled at the same instant (e.g.
        the robot's streams, decoded from one frame) share rows. Several samples of one stream with
        the same timestamp (decoded from one read) take consecutive rows with that time. Values are
        written with ``repr`` so they read back bit-exact; ``time`` is the monotonic clock in
        seconds, and the header gives the wall-clock time of t = 0 to anchor it.
        (pandas: ``read_csv(path, comment="#", header=[0, 1])``.)
        """
        from app.session.export import write_aligned_csv

        keys = list(signals)
        for k in keys:
            if k not in self._info:
                raise KeyError(f"unknown signal {k!r}")
        by_stream: dict[str, list[str]] = {}
        for k in keys:
            by_stream.setdefault(self._info[k].stream, []).append(k)
        streams = []
        for stream, stream_keys in by_stream.items():
            ring = self._rings[stream]
            i0, i1 = ring.index_range(*ring.sample_range(t_from, t_to))
            streams.append((ring.t[i0:i1], [(k, self._info[k].unit, ring.col(self._info[k].channel)[i0:i1])
                                           for k in stream_keys]))
        anchor = time.time() - time.monotonic()
        if t_zero is not None:  # time from a given instant (the session's start): ``t_zero_text`` says which
            streams = [(t - t_zero, cols) for t, cols in streams]
            anchor += t_zero
        what = f"seconds from {t_zero_text or 'the reference instant'}" if t_zero is not None else "monotonic seconds"
        return write_aligned_csv(path, streams, [
            "LINarm++ Manager signal export",
            f"time: {what}; wall clock of time 0 = {anchor:.6f} s since the Unix epoch",
            "each row is one sampling instant; empty cells: that stream has no sample at that instant",
        ])



def _envelope_rows(ring: _Ring, rows: list[int], t_from: float | None, t_to: float | None,
                   max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The envelope of rows ``rows`` of ``ring`` over [t_from, t_to]: (time, one row of values per channel)."""
    n0, n1 = ring.sample_range(t_from, t_to)
    n = n1 - n0
    sel = rows if len(rows) != ring.y.shape[0] else slice(None)  # all rows: views, not a gathered copy
    if n <= max_points:
        i0, i1 = ring.index_range(n0, n1)
        return ring.t[i0:i1].copy(), ring.y[sel, i0:i1].copy()
    buckets = max(1, max_points // 2)
    t_parts: list[np.ndarray] = []
    lo_parts: list[np.ndarray] = []
    hi_parts: list[np.ndarray] = []

    def raw_bucket(a: int, b: int) -> None:
        if b <= a:
            return
        i0, i1 = ring.index_range(a, b)
        seg = ring.y[sel, i0:i1]
        t_parts.append(ring.t[i0:i0 + 1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN bucket stays NaN
            lo_parts.append(np.nanmin(seg, axis=1, keepdims=True))
            hi_parts.append(np.nanmax(seg, axis=1, keepdims=True))

    # Whole blocks in [b0, b1); partial head [n0, b0*BLOCK) and tail [b1*BLOCK, n1) done directly.
    b0 = -(-n0 // BLOCK)
    b1 = n1 // BLOCK
    if n < BLOCK * buckets:
        # Blocks would be coarser than the buckets: reduce the raw samples directly (n is small).
        i0, i1 = ring.index_range(n0, n1)
        seg_t, seg = ring.t[i0:i1], ring.y[sel, i0:i1]
        starts = np.arange(0, n, -(-n // buckets))
        t_parts.append(seg_t[starts])
        lo_parts.append(np.fmin.reduceat(seg, starts, axis=1))
        hi_parts.append(np.fmax.reduceat(seg, starts, axis=1))
    elif b1 <= b0:
        raw_bucket(n0, n1)
    else:
        raw_bucket(n0, b0 * BLOCK)
        nb = b1 - b0
        group = max(1, -(-nb // buckets))
        j0 = b0 % ring.nblocks
        if j0 + nb > 2 * ring.nblocks:
            j0 -= ring.nblocks
        starts = np.arange(0, nb, group)
        lo_parts.append(np.fmin.reduceat(ring.bmin[sel, j0:j0 + nb], starts, axis=1))
        hi_parts.append(np.fmax.reduceat(ring.bmax[sel, j0:j0 + nb], starts, axis=1))
        t_parts.append(ring.t[((b0 + starts) * BLOCK) % ring.cap])
        raw_bucket(b1 * BLOCK, n1)
    tb = np.concatenate(t_parts)
    lo = np.concatenate(lo_parts, axis=1)
    hi = np.concatenate(hi_parts, axis=1)
    return np.repeat(tb, 2), np.stack((lo, hi), axis=2).reshape(lo.shape[0], -1)


_shared: weakref.WeakKeyDictionary[Any, SignalStore] = weakref.WeakKeyDictionary()


def shared_store(manager: LinarmppManager, qt_bus: QtBus) -> SignalStore:
    """The one store of ``manager`` (created on first use), fed by ``qt_bus`` (see :meth:`SignalStore.attach_bus`)."""
    store = _shared.get(manager)
    if store is None:
        history = max(float(manager.config.ui.history_s), 1.0)
        store = SignalStore(history)
        _shared[manager] = store
    store.attach_bus(qt_bus)
    return store
