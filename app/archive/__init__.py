"""The clinic's archive (issue #39): patients, sessions, runs, repetitions, the journal and the session files
behind one interface (:mod:`app.archive.api`), in an SQLite file in ``<data>`` by default or on a clinic's
PostgreSQL server. Qt-free. docs/archive.md says what is stored where."""

from app.archive.api import (
    Archive,
    ArchiveError,
    ArchiveTooNew,
    ArchiveUnavailable,
    NeedsUpgrade,
    NotFound,
    SessionConflict,
    StaleRecord,
)

__all__ = ["Archive", "ArchiveError", "ArchiveTooNew", "ArchiveUnavailable", "NeedsUpgrade", "NotFound",
           "SessionConflict", "StaleRecord"]
