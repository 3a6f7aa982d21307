"""Replay a recorded session as if it were live.

:class:`ReplaySource` hands out the recorded samples as the same ``dict[stream → SampleBatch]`` the
drivers emit (original monotonic time stamps), so any consumer of live batches — the signal store and
the graphs — shows a recording without knowing it. It holds a position on the session's time line:
``seek`` jumps (a time slider), ``advance`` plays forward, ``window`` fetches any stretch.

No Qt here: the replay window drives it from a timer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.bus import SampleBatch, StreamSpec
from app.session.recording import RecordedSession, load_session


class ReplaySource:
    def __init__(self, session: RecordedSession | str | Path) -> None:
        self.session = session if isinstance(session, RecordedSession) else load_session(session)
        self.streams = {name: s for name, s in self.session.streams.items()}
        firsts = [float(s.t[0]) for s in self.streams.values() if len(s)]
        lasts = [float(s.t[-1]) for s in self.streams.values() if len(s)]
        self.start = min([self.session.start_mono, *firsts]) if firsts else self.session.start_mono
        self.end = max([self.session.end_mono, *lasts]) if lasts else self.session.end_mono
        self.position = self.start  # absolute monotonic seconds; samples up to here have been delivered

    # ------------------------------------------------------------------ time line
    @property
    def duration(self) -> float:
        return max(0.0, self.end - self.start)

    @property
    def elapsed(self) -> float:
        """Position relative to the session start (what a time slider shows)."""
        return self.position - self.start

    @property
    def at_end(self) -> bool:
        return self.position >= self.end

    def specs(self) -> dict[str, tuple[StreamSpec, str]]:
        """(spec, device) of every recorded stream."""
        return {name: (s.spec, s.device) for name, s in self.streams.items()}

    def seek(self, elapsed_s: float) -> None:
        """Jump to ``elapsed_s`` after the session start (clamped to the session)."""
        self.position = min(self.end, max(self.start, self.start + float(elapsed_s)))

    # ------------------------------------------------------------------ samples
    def window(self, t_from: float, t_to: float) -> dict[str, SampleBatch]:
        """Samples with t_from < t <= t_to (absolute monotonic seconds), per stream; empty streams left out."""
        out: dict[str, SampleBatch] = {}
        for name, s in self.streams.items():
            a = int(np.searchsorted(s.t, t_from, "right"))
            b = int(np.searchsorted(s.t, t_to, "right"))
            if b > a:
                out[name] = SampleBatch(s.spec, s.t[a:b].copy(), {c.name: s.data[c.name][a:b].copy()
                                                                  for c in s.channels})
        return out

    def history(self, seconds: float) -> dict[str, SampleBatch]:
        """The ``seconds`` before the position (what a live view would hold after a seek)."""
        return self.window(self.position - seconds, self.position)

    def advance(self, dt_s: float) -> dict[str, SampleBatch]:
        """Move forward by ``dt_s`` and return the samples passed."""
        new = min(self.end, self.position + max(0.0, dt_s))
        # The very first sample sits exactly at `start`: include it on the first step.
        t_from = self.position if self.position > self.start else np.nextafter(self.start, -np.inf)
        batches = self.window(float(t_from), new)
        self.position = new
        return batches

    def events_between(self, t_from: float, t_to: float) -> list[dict]:
        return [e for e in self.session.events
                if isinstance(e.get("t_mono"), int | float) and t_from < e["t_mono"] <= t_to]
