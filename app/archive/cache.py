"""The station's copy of the patients it read from the archive (issue #39): when the clinic's server cannot be
reached, the station still lists and opens the patients it saw last — read-only — and a session can be run for
one of them (it waits in the outbox, as sessions already do).

One JSON file per patient in ``<data>/archive-cache/patients/`` (the folder 0700, each file 0600: health data
on the station, as its session folders are): the record as the archive last gave it (the profile's field values,
its version, who changed it where and when), when this station read it, and from which archive. A copy is written
whenever the station reads a newer version than it holds (the Patients window's list, a form, a session's start, a
save) — atomically (a temporary file renamed over the old one) and read back. It is never written to the archive
and never saved from: with the archive back, the archive's record is read again and is the one used.

What a copy cannot know: a change made on another station since it was read (a cap lowered there). The session
started from it applies the site's limits as always (a copy looser than the configuration is refused like any
record), and the window says whose copy of when it is.

Qt-free.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.archive.api import PatientRecord
from app.core import paths

log = logging.getLogger(__name__)

CACHE_DIR = "archive-cache"


@dataclass(frozen=True)
class CachedRecord:
    """A patient's record as this station last read it from the archive."""

    record: PatientRecord
    seen_at: str  # ISO time (UTC) this station read it
    archive: str  # the archive's URL (no password)


def same_archive(a: str, b: str) -> bool:
    """Whether two archive URLs (passwords hidden) name one archive: ``postgresql://`` and ``postgresql+psycopg://``
    alike."""
    return bool(a) and re.sub(r"^(\w+)\+\w+://", r"\1://", a) == re.sub(r"^(\w+)\+\w+://", r"\1://", b)


class PatientCache:
    """The copies in ``folder`` (default ``<data>/archive-cache/patients``) of the records read from the archive at
    ``url`` (passwords hidden): a copy read from another archive is never offered for this one."""

    def __init__(self, url: str, folder: Path | None = None) -> None:
        self.url = url
        self.folder = folder or paths.data_dir() / CACHE_DIR / "patients"
        self._versions: dict[str, tuple[int, str]] | None = None  # id -> (version, changed_at) held
        self._lock = threading.Lock()

    def _path(self, patient_id: str) -> Path:
        from app.therapy.patients import patient_file

        return self.folder / patient_file(patient_id).with_suffix(".json").name  # the id's own safe name

    def _held(self) -> dict[str, tuple[int, str]]:
        if self._versions is None:  # the versions only (building a profile validates it: ~5-15 ms each)
            self._versions = {}
            for path in sorted(self.folder.glob("*.json")) if self.folder.is_dir() else []:
                try:
                    d = json.loads(path.read_text(encoding="utf-8"))
                    self._versions[str(d["patient_id"])] = (int(d["version"]), str(d["changed_at"]))
                except (OSError, ValueError, KeyError, TypeError):
                    continue  # written again at the next read
        return self._versions

    def put(self, record: PatientRecord) -> bool:
        """Keep ``record`` (unless this version is held already); True when a copy was written. A copy that cannot
        be written is logged, never raised: the station's work goes on without it."""
        from app.archive.store import profile_values

        pid = record.profile.patient_id
        with self._lock:
            if self._held().get(pid) == (record.version, record.changed_at):
                return False
            data = {"patient_id": pid, "values": profile_values(record.profile), "created": record.profile.created,
                    "updated": record.profile.updated, "version": record.version, "changed_at": record.changed_at,
                    "changed_by": record.changed_by, "changed_station": record.changed_station,
                    "seen_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "archive": self.url}
            text = json.dumps(data, sort_keys=True, ensure_ascii=False)
            try:
                path = self._path(pid)
                paths.private_dir(self.folder)
                tmp = path.with_name(f".{path.name}.part-{os.getpid()}")
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, paths.PRIVATE_FILE_MODE)
                with os.fdopen(fd, "w", encoding="utf-8") as fh:  # no fsync: a copy lost to a power cut is a
                    fh.write(text)  # copy not offered (read back fails), and 2 000 fsyncs held the listing seconds
                os.replace(tmp, path)
                if path.read_text(encoding="utf-8") != text:
                    raise OSError(f"{path} does not read back as written")
            except (OSError, ValueError) as exc:
                log.warning("the station's copy of patient %s was not kept: %s", pid, exc)
                return False
            self._held()[pid] = (record.version, record.changed_at)
            return True

    def get(self, patient_id: str) -> CachedRecord | None:
        try:
            path = self._path(patient_id)
        except ValueError:
            return None
        cached = self._read(path)
        return cached if cached is not None and same_archive(cached.archive, self.url) else None

    def records(self) -> list[CachedRecord]:
        """Every copy of this archive's records, by patient id; a copy that cannot be read is left out (logged)."""
        if not self.folder.is_dir():
            return []
        out = [c for p in sorted(self.folder.glob("*.json"))
               if (c := self._read(p)) is not None and same_archive(c.archive, self.url)]
        return sorted(out, key=lambda c: c.record.profile.patient_id.lower())

    @staticmethod
    def _read(path: Path) -> CachedRecord | None:
        from app.archive.store import profile_from_values

        if not path.is_file():
            return None
        try:
            d: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
            profile = profile_from_values(d["patient_id"], d["values"], d["created"], d["updated"])
            record = PatientRecord(profile, int(d["version"]), d["changed_at"], d["changed_by"], d["changed_station"])
            return CachedRecord(record, str(d["seen_at"]), str(d.get("archive", "")))
        except Exception as exc:  # a damaged copy is no copy: the patient is then not offered offline
            log.warning("the station's copy %s cannot be read: %s", path, exc)
            return None


__all__ = ["CACHE_DIR", "CachedRecord", "PatientCache"]
