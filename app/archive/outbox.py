"""The station's outbox: finished sessions wait here until the archive has committed them (Qt-free).

The recorder's crash-safe folder stays the write path. A session folder is *waiting* until its ``.archived``
marker exists; :meth:`Outbox.run_once` uploads the waiting ones (oldest first, one transaction each,
idempotent by UUID) and writes the marker only after the archive's commit. A kill at any moment leaves either
no marker (the next pass uploads again: a committed session is then a no-op, so it is archived exactly once)
or the marker. When the archive cannot be reached the station keeps working: the status says "N sessions
waiting for the archive" and the next try is scheduled with a growing back-off. A session refused by the
archive (another session holds its UUID) is marked ``.archive-refused`` and said loudly (log and status); it
never blocks the others.

The window calls :func:`station_pass` in its worker process (app/worker: an upload reads the session's files
and computes its metrics, heavy work kept out of the real-time process, #37) at each session's end, at start-up
and every 30 s, and shows :meth:`OutboxStatus.text` in its status bar; ``--headless`` calls
:func:`headless_pass` at the end of its run and says the outcome on its last line.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from app.archive.api import Archive, ArchiveError, ArchiveUnavailable, OutboxStatus, SessionConflict
from app.archive.folders import ARCHIVED_MARKER, REFUSED_MARKER, mark, session_folders, wall_now

if TYPE_CHECKING:
    from app.worker.context import JobContext

log = logging.getLogger(__name__)

BACKOFF_S: tuple[float, ...] = (5.0, 15.0, 60.0, 300.0)  # after 1, 2, 3, 4+ failed tries in a row


class Outbox:
    """``root``: the station's sessions folder. ``connect``: opens the archive (raises ArchiveUnavailable when
    it cannot). ``active``: the folders being recorded now (never uploaded while recording)."""

    def __init__(self, root: Path, connect: Callable[[], Archive], *, clock: Callable[[], float] = time.monotonic,
                 backoff_s: tuple[float, ...] = BACKOFF_S) -> None:
        self.root = Path(root)
        self._connect = connect
        self._clock = clock
        self._backoff = backoff_s
        self._failures = 0
        self._next_try: float | None = None
        self._error = ""
        self._uploaded = 0
        self._active: set[Path] = set()

    def set_active(self, folders: Iterable[Path]) -> None:
        self._active = {Path(f).resolve() for f in folders}

    def waiting(self) -> list[Path]:
        """Session folders not yet archived (nor refused), oldest first; the active recording left out."""
        return [f for f in session_folders(self.root)
                if not (f / ARCHIVED_MARKER).is_file() and not (f / REFUSED_MARKER).is_file()
                and f.resolve() not in self._active]

    def refused(self) -> list[Path]:
        return [f for f in session_folders(self.root) if (f / REFUSED_MARKER).is_file()]

    def status(self) -> OutboxStatus:
        waiting = len(self.waiting())
        next_in = None
        if waiting:
            next_in = 0.0 if self._next_try is None else max(0.0, self._next_try - self._clock())
        return OutboxStatus(waiting, self._uploaded, self._error, next_in)

    def due(self) -> bool:
        return self._next_try is None or self._clock() >= self._next_try

    def run_once(self, force: bool = False) -> OutboxStatus:
        """Upload what waits, if a try is due (``force``: now). Never raises for an unreachable archive."""
        self._uploaded = 0
        if not force and not self.due():
            return self.status()
        folders = self.waiting()
        if not folders:
            self._failures, self._next_try, self._error = 0, None, ""
            return self.status()
        archive: Archive | None = None
        try:
            try:
                archive = self._connect()
            except OSError as exc:  # the archive's folder (a share, a disk) is not there
                raise ArchiveUnavailable(f"the archive cannot be reached ({exc})") from exc
            for folder in folders:
                try:
                    result = archive.upload_session(folder)
                except SessionConflict as exc:
                    log.error("the archive refused the session %s: %s", folder, exc)
                    mark(folder, REFUSED_MARKER, {"refused_at": wall_now(), "reason": str(exc)})
                    self._error = f"a session was refused by the archive: {exc}"
                    continue
                mark(folder, ARCHIVED_MARKER, {"uuid": result.uuid, "archive": archive.url,
                                               "station": archive.station, "archived_at": wall_now(),
                                               "outcome": result.outcome})
                self._uploaded += 1
                log.info("session %s archived (%s, %s)", folder, result.uuid, result.outcome)
        except ArchiveUnavailable as exc:
            self._failures += 1
            delay = self._backoff[min(self._failures, len(self._backoff)) - 1]
            self._next_try = self._clock() + delay
            self._error = f"{exc}; next try in {delay:g} s"  # "the archive at … cannot be reached (…)"
            log.warning("outbox: %s", self._error)
            return self.status()
        except ArchiveError as exc:  # refused for another reason (schema too new, configuration): said, retried
            self._failures += 1
            self._next_try = self._clock() + self._backoff[-1]
            self._error = str(exc)
            log.error("outbox: %s", exc)
            return self.status()
        finally:
            if archive is not None:
                archive.close()
        self._failures, self._next_try = 0, None
        if not self.refused():
            self._error = ""
        return self.status()


# ---------------------------------------------------------------------------------------------- the station's passes
_STATION_OUTBOXES: dict[tuple[str, str, str], Outbox] = {}


def _connector(url: str, password_file: str, station: str) -> Callable[[], Archive]:
    def connect() -> Archive:
        from app.archive.store import open_archive

        return open_archive(url=url, station=station, password_file=password_file)
    return connect


def station_pass(ctx: JobContext, root: str, url: str, password_file: str, station: str, active: list[str],
                 force: bool = False) -> OutboxStatus:
    """One pass of the station's outbox, as a job of the window's worker process (kind
    ``"app.archive.outbox:station_pass"``): the Outbox of ``root`` kept between passes in this process (its
    back-off), ``active`` (the folder being recorded) never uploaded. ``url=''``: the SQLite file in ``<data>``."""
    key = (str(root), url, station)
    box = _STATION_OUTBOXES.get(key)
    if box is None:
        box = _STATION_OUTBOXES[key] = Outbox(Path(root), _connector(url, password_file, station))
    box.set_active(Path(a) for a in active)
    return box.run_once(force)


def archive_settings(config: object) -> tuple[str, str, str]:
    """(url, password_file, station) of the configuration's archive (url '' = the SQLite file in ``<data>``)."""
    cfg = getattr(config, "archive", None)
    from app.archive.store import _station_name

    return (getattr(cfg, "url", "") or "", getattr(cfg, "password_file", "") or "",
            _station_name(getattr(config, "station", "") or ""))


def headless_pass(config: object, root: Path) -> str:
    """The sessions of ``root`` (a headless run's, and any left over) uploaded now; the run's last line:
    "Session archived." or "1 session waiting for the archive (…)."."""
    url, password_file, station = archive_settings(config)
    box = Outbox(Path(root), _connector(url, password_file, station))
    status = box.run_once(force=True)
    if status.waiting:
        return f"{status.text()}."
    if box.refused():
        return f"Not archived: {status.error}."
    return "Session archived."
