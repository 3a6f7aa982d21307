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

No Qt here: the window calls ``tick`` from a timer and ``settle`` after building a large window.
"""

from __future__ import annotations

import gc
import logging
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

TICK_S = 2.0  # how often the window calls tick(): the age after which a survivor is settled while driving
# The window's policy collects only once nothing has driven for this long: the full walk (50-70 ms with every graph
# drawn) is one turn of the window's thread holding the interpreter lock, and a rest of a moment -- an e-stop,
# reset, start again -- is when the next start and the next e-stop press come (#37: the e-stop bench's presses
# waited behind it, 60 ms of CPU, when it ran at the first tick after a stop).
REST_S = 6.0


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
