"""The interpreter's garbage collector and the therapy (issue #37: nothing a clinician does may starve the devices).

A full (generation 2) collection walks every object the process holds while holding the interpreter lock: with
the window, a replay of a 30-minute session and its summary open (~120 000 objects) one took 45-75 ms, on whatever
thread allocated last: the window's (a stall the GUI watch judges), the worker link's (the summary's result
arrived 70 ms late and held the window meanwhile) or a driver's. Almost all of those objects live as long as
the window that made them; walking them again and again finds nothing (0 collected in every one measured).

So, while something drives (the robot ON or stimulation running): the objects that have lived a few seconds are
moved out of the collector's sight (``gc.freeze``), and the automatic collections walk only what is new; a window
that has just been built is settled at once. At rest (nothing drives) everything is given back to the collector
and collected once, so cycles made during a therapy are freed after it. Objects freed by their reference count
(nearly all) are freed at once either way; only cyclic garbage waits for the rest.

**Collections on the main thread only** (:class:`MainThreadCollections`, #38): an automatic collection runs on
whichever thread happens to allocate, and what it frees is destroyed there. A Qt object freed by the collector
(a widget or a timer caught in a reference cycle, cyclic garbage of a closed dialog) must be destroyed on its own
thread: destroyed on a loader's or a driver's thread, a shown window's destructor waited for the window's thread
(a hang, seen with a plot widget) or the process crashed (a segmentation fault "Garbage-collecting" on the Patients
window's loading thread, seen in the suite with two workers on busy cores). So a process with Qt objects turns
the automatic collections off and its main thread collects on a timer what the thresholds say is due — the same
generations, by the same counts, on the one thread where destroying a Qt object is safe.

No Qt here: the window calls ``tick`` from a timer and ``settle`` after building a large window;
app/main_thread_gc.py runs :class:`MainThreadCollections` from a timer on the main thread.
"""

from __future__ import annotations

import gc
import logging
import time
import weakref
from collections.abc import Callable

log = logging.getLogger(__name__)

TICK_S = 2.0  # how often the window calls tick(): the age after which a survivor is settled while driving
# The window's policy collects only once nothing has driven for this long: the full walk (50-70 ms with every graph
# drawn) is one turn of the window's thread holding the interpreter lock, and a rest of a moment -- an e-stop,
# reset, start again -- is when the next start and the next e-stop press come (#37: the e-stop bench's presses
# waited behind it, 60 ms of CPU, when it ran at the first tick after a stop).
REST_S = 6.0
# How often the main thread looks at the collector's counts (MainThreadCollections.collect_due). A young collection
# walks the container objects made since the last one and still alive (freed ones are gone by their reference
# count), so often enough that each stays small -- a loader on another thread building 10 000 rows makes them
# faster than a slow period walks them in a turn: its longest turn 8.7 ms of CPU at 10 ms, 11 ms at 50 ms
# (tests/test_archive_browser_blocks.py); the window in therapy (every graph, FES, the arm moving) 1.2 ms at 50 ms.
COLLECT_EVERY_S = 0.01
# A full walk outside a frozen heap (every object of the window: 45-75 ms) at most this often, and only when the
# window's policy says it may (at rest): the automatic collector's own rule (a quarter of the heap new) is not
# visible from Python, so its effect -- full walks are rare -- is kept by a gap.
FULL_GAP_S = 60.0


class HeapPolicy:
    """``drives()`` says what a stall would leave unattended ('' at rest; app.gui_watch.what_drives)."""

    def __init__(self, drives: Callable[[], str], clock: Callable[[], float] = time.monotonic,
                 rest_s: float = 0.0) -> None:
        self._drives = drives
        self._clock = clock
        self.rest_s = rest_s  # the rest a full collection waits for (0: the first tick at rest)
        self._last_drive_s: float | None = None  # when a tick last saw something drive
        self.frozen = False  # objects are out of the collector's sight
        self._drove = False  # settled while driving: given back at the next rest
        self.full_collections = 0  # the collections made at rest (tests)
        self.last_full_s: float | None = None

    def settle(self) -> None:
        """The objects alive now live on (a window just built): out of the automatic collections' walk."""
        gc.freeze()
        self.frozen = True

    def full_walk_allowed(self) -> bool:
        """Whether a full collection now keeps off the therapy: the heap frozen (the walk sees only what is new)
        or a rest of ``rest_s`` with nothing driving (MainThreadCollections.full_allowed)."""
        if self.frozen:
            return True
        if self._drives():
            return False
        return self._last_drive_s is None or self._clock() - self._last_drive_s >= self.rest_s

    def tick(self) -> None:
        """While driving, settle the survivors; at rest (for ``rest_s``), once after driving, give them back and
        collect."""
        if self._drives():
            self.settle()
            self._drove = True
            self._last_drive_s = self._clock()
            return
        rested = self._last_drive_s is None or self._clock() - self._last_drive_s >= self.rest_s
        if self._drove and rested:
            self._drove = False
            gc.unfreeze()
            self.frozen = False
            t0 = self._clock()
            found = gc.collect()
            self.last_full_s = self._clock() - t0
            self.full_collections += 1
            log.debug("garbage collected at rest: %d objects in %.0f ms", found, self.last_full_s * 1e3)


class MainThreadCollections:
    """The automatic collections, made by one thread (the main one: Qt's GUI thread) when it calls ``collect_due``.

    ``take_over`` turns the interpreter's automatic collections off (process-wide); ``give_back`` turns them on
    again. ``collect_due`` collects the oldest generation whose count passed its threshold, as the interpreter
    would; a full collection (generation 2) only when ``full_allowed()`` (the window's policy: while the heap is
    frozen a full walk is short; at rest, once nothing has driven for a while) and ``FULL_GAP_S`` after the last.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, full_gap_s: float = FULL_GAP_S) -> None:
        self._clock = clock
        self.full_gap_s = full_gap_s
        self.full_allowed: Callable[[], bool] = lambda: True
        self.active = False
        self.collections = [0, 0, 0]  # made here, per generation (tests, logs)
        self.longest_s = 0.0  # the longest collection made here
        self._last_full_s: float | None = None
        self._was_enabled = True

    def also_ask(self, policy: HeapPolicy) -> None:
        """A full walk also needs ``policy``'s consent (``full_walk_allowed``) while ``policy`` lives; the rule held
        before stays (the suite's: between tests only) -- a window gone leaves it as it was, not "always"."""
        window = weakref.ref(policy)  # not keeping a closed window's policy (and its window) alive
        before = self.full_allowed

        def full_allowed() -> bool:
            live = window()
            return before() and (live is None or live.full_walk_allowed())
        self.full_allowed = full_allowed

    def take_over(self) -> None:
        if not self.active:
            self._was_enabled = gc.isenabled()
            gc.disable()
            self.active = True
            self._last_full_s = self._clock()

    def give_back(self) -> None:
        if self.active:
            self.active = False
            if self._was_enabled:
                gc.enable()

    def due(self) -> int | None:
        """The generation the interpreter would collect now (None: nothing due)."""
        counts, thresholds = gc.get_count(), gc.get_threshold()
        if thresholds[0] == 0:  # collections switched off by gc.set_threshold(0)
            return None
        if counts[2] > thresholds[2] and self._full_may_run():
            return 2
        if counts[1] > thresholds[1]:
            return 1
        return 0 if counts[0] > thresholds[0] else None

    def _full_may_run(self) -> bool:
        last = self._last_full_s
        return (last is None or self._clock() - last >= self.full_gap_s) and self.full_allowed()

    def collect_due(self) -> int | None:
        """Collect what is due on the calling thread; the generation collected (None: nothing was due)."""
        generation = self.due()
        if generation is None:
            return None
        t0 = self._clock()
        gc.collect(generation)
        spent = self._clock() - t0
        self.longest_s = max(self.longest_s, spent)
        self.collections[generation] += 1
        if generation == 2:
            self._last_full_s = self._clock()
        return generation
