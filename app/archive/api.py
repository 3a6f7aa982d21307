"""The archive's interface: what the app (the Patients window, the session start, the sessions browser, replay,
the reports, the exports, the command line) asks of the clinic's archive. Qt-free and typed; the one
implementation is :class:`app.archive.store.SqlArchive` (SQLAlchemy 2: SQLite in ``<data>`` or PostgreSQL),
made by :func:`app.archive.store.open_archive`. docs/archive.md says what is stored where.

Identity and concurrency:

* A patient is its ``patient_id`` (the pseudonym). Every patient row has a **version** (1 at creation, +1 per
  save). A save names the version it was based on (``expected_version``); when a field it writes was changed
  by a later version, the save is refused with :class:`StaleRecord`, naming who changed it, on which station
  and when — nothing is written. A save of *some* fields (``fields=...``: a running session's electrode
  choice, the therapy-plan dialog) is refused only when one of *its* fields changed since its version; the
  other fields are left as they are now (never put back to the stale copy's values).
* A session is its **UUID**, made by the recorder at the session's start (``manifest.json``'s
  ``session_uuid``; sessions recorded before it have a stable one derived from the manifest:
  :func:`app.archive.folders.session_uuid`). Uploading is idempotent: the same session again is a no-op;
  a *different* session (other files) claiming the same UUID is refused with :class:`SessionConflict`.
* The session's files (manifest, events, streams) are kept byte for byte, each by its SHA-256; an archived
  session is read exactly like a folder: :meth:`SessionFiles.materialise` writes the folder back (checked
  against the hashes) so ``app.session.recording.load_session`` and every loader read it unchanged.

Field keys of a patient (:data:`PATIENT_FIELDS`): the profile's top-level fields, with ``fes`` split in three:
``fes.profile``, ``fes.caps`` and one key per muscular district's electrode choice,
``fes.electrodes.<district>`` (:func:`electrode_field`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal, Protocol, runtime_checkable

from app.therapy.patients import ElectrodeChoice, PatientProfile

# The patient's field keys a save may name (besides ``fes.electrodes.<district>``). ``patient_id``, ``version``,
# ``created`` and ``updated`` are the record's own: set by the archive, never by a save.
PATIENT_FIELDS: tuple[str, ...] = (
    "full_name", "birth_date", "record_number", "affected_side", "scores", "assistance", "fes.profile", "fes.caps",
    "robot", "notes", "therapy_plan",
)
ELECTRODES_PREFIX = "fes.electrodes."


def electrode_field(district: str) -> str:
    """The field key of one district's electrode choice, e.g. ``fes.electrodes.anterior deltoid``."""
    return f"{ELECTRODES_PREFIX}{district}"


# ---------------------------------------------------------------------------------------------- errors
class ArchiveError(Exception):
    """Anything the archive refuses or cannot do; ``str(exc)`` is a sentence a clinician can act on."""


class ArchiveUnavailable(ArchiveError):
    """The archive cannot be reached (the server is down, the network is out, the file cannot be opened). The
    station keeps working: sessions wait in the outbox."""


class ArchiveTooNew(ArchiveError):
    """The archive's schema is newer than this application knows: it is refused, never written to."""


class NeedsUpgrade(ArchiveError):
    """The archive's schema is older than this application's: ``linarmpp archive upgrade`` migrates it."""


class NotFound(ArchiveError):
    """No such patient or session in the archive."""


class PatientExists(ArchiveError):
    """A new patient (``expected_version=None``) whose identifier is already in the archive."""


class SessionConflict(ArchiveError):
    """A session whose UUID is already in the archive with other files: refused (never merged, never replaced)."""


class ConfigProblem(ArchiveError):
    """The archive's configuration is refused (a URL holding a password, an unreadable password file)."""


@dataclass(eq=False)
class StaleRecord(ArchiveError):
    """A save based on an older version of the patient than the archive holds: refused, nothing written."""

    patient_id: str
    expected_version: int
    current_version: int
    changed_by: str  # the operator of the save that made the conflicting version
    changed_station: str
    changed_at: str  # ISO time with zone
    fields: tuple[str, ...] = ()  # the fields of this save that were changed meanwhile

    def __str__(self) -> str:
        what = f" ({', '.join(self.fields)})" if self.fields else ""
        return (f"Patient {self.patient_id} was changed{what} by {self.changed_by or 'someone'} on station "
                f"{self.changed_station or '(unknown)'} at {self.changed_at} after this copy was opened "
                f"(version {self.expected_version}, now {self.current_version}): nothing was saved; reload the "
                "patient and make the change again.")


# ---------------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class PatientRecord:
    """A patient as the archive holds it: the profile, its row version, and the last change's author."""

    profile: PatientProfile
    version: int
    changed_at: str  # ISO time with zone of the save that made this version
    changed_by: str  # its operator
    changed_station: str


@dataclass(frozen=True)
class PatientUnreadable:
    """A patient's row whose values are not a valid profile (:meth:`Archive.patient_reads`): listed with why."""

    patient_id: str
    version: int
    error: str  # a sentence


@dataclass(frozen=True)
class PatientListItem:
    """One row of the Patients window's list (no profile parsed: the list of 2 000 patients stays fast)."""

    patient_id: str
    full_name: str
    record_number: str
    version: int
    changed_at: str
    sessions: int
    last_session: str  # ISO start of the newest session, '' if none
    changed_by: str = ""  # the operator of the save that made this version
    changed_station: str = ""  # the station it was saved on


@dataclass(frozen=True)
class PatientChange:
    """One entry of a patient's history (append-only, hash-chained): what one save changed."""

    patient_id: str
    version: int
    fields: tuple[str, ...]
    values: dict[str, Any]  # field key -> the new value (plain YAML-able data; None = cleared)
    changed_by: str
    changed_station: str
    changed_at: str
    reason: str  # "import", "save", "electrode choice", ...
    prev_hash: str
    hash: str


SessionStatus = Literal["complete", "failed", "recording"]  # "recording": interrupted (no end in the record)


@dataclass(frozen=True)
class SessionInfo:
    """One row of the sessions browser (and of ``SessionSummary``'s fields): no file read."""

    uuid: str
    patient_id: str
    station: str
    operator: str
    note: str
    start: str  # ISO with zone ('' when unknown)
    start_epoch_s: float
    end: str  # '' when the session has no end (interrupted)
    duration_s: float
    status: str  # SessionStatus, or what an odd manifest said
    app_version: str
    exercises: tuple[str, ...]  # the runs' titles in order
    alarms: int
    folder_name: str  # "<patient>/<YYYYmmdd-HHMMSS>" as recorded on its station
    archived_at: str

    @property
    def complete(self) -> bool:
        return self.status == "complete"


@dataclass(frozen=True)
class FileInfo:
    name: str  # relative to the session folder: manifest.json, events.jsonl, streams/<stream>.csv
    size: int
    sha256: str


@dataclass(frozen=True)
class SessionDetail:
    info: SessionInfo
    manifest: dict[str, Any]  # as recorded (configuration, devices, streams, counts)
    files: tuple[FileInfo, ...]
    summary: dict[str, Any]  # app.session.metrics.metrics_of_session's summary, computed at upload
    problems: tuple[str, ...]  # app.session.recording.load_session's problems at upload (an interrupted session's)


@dataclass(frozen=True)
class RunInfo:
    """An exercise run (app.core.runs.ExerciseRun's record) with its own summary
    (app.session.metrics.metrics_by_run)."""

    session_uuid: str
    run_id: str
    position: int  # order in the session, from 1
    program: dict[str, Any]  # kind, ident, title, version, path, text_sha256
    title: str
    parameters: tuple[dict[str, Any], ...]  # {name, label, value, unit}
    source: str
    operator: str
    restart_of: str | None
    started_s: float  # from the session's start
    ended_s: float | None
    end_reason: str | None
    end_detail: str
    summary: dict[str, Any]


@dataclass(frozen=True)
class RepetitionInfo:
    session_uuid: str
    run_id: str
    index: int  # within the run, from 1
    metrics: dict[str, Any]  # app.session.metrics.RepetitionMetrics.as_dict() (plus run_id)


@dataclass(frozen=True)
class JournalEntry:
    """One event of a session (events.jsonl's line) in the append-only, hash-chained journal."""

    session_uuid: str
    seq: int  # from 1, in the file's order
    t_wall: str
    t_mono: float | None
    kind: str
    who: str
    origin: str
    data: dict[str, Any]
    prev_hash: str
    hash: str


@dataclass(frozen=True)
class ProgressSession:
    """The progress report's input for one session, from the archive alone (no stream read)."""

    info: SessionInfo
    summary: dict[str, Any]
    scores: dict[str, Any]  # the clinical scores in the profile as recorded at that session
    runs: tuple[RunInfo, ...]
    repetitions: tuple[RepetitionInfo, ...]


@dataclass(frozen=True)
class UploadResult:
    uuid: str
    outcome: Literal["uploaded", "already_archived"]
    files: int
    bytes: int
    seconds: float


@dataclass(frozen=True)
class VerifyProblem:
    where: str  # "session <uuid> journal row 17", "file streams/linarm.vsa.csv of session <uuid>", ...
    what: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"


@dataclass
class VerifyReport:
    files: int = 0  # stream files re-hashed
    bytes: int = 0
    rows: int = 0  # chained rows re-hashed (journals, patient histories, ledger)
    problems: list[VerifyProblem] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def first_problem(self) -> VerifyProblem | None:
        return self.problems[0] if self.problems else None


@dataclass(frozen=True)
class OutboxStatus:
    """What the station's outbox says (the window's status bar, ``--headless``'s last line)."""

    waiting: int  # finished sessions not yet archived
    uploaded: int  # by the last pass
    error: str  # why the last try failed ('' when it did not); a sentence
    next_try_in_s: float | None  # None: nothing waits

    def text(self) -> str:
        """"2 sessions waiting for the archive" (with why when the archive cannot be reached); '' if none."""
        if not self.waiting:
            return ""
        noun = "session" if self.waiting == 1 else "sessions"
        why = f" ({self.error})" if self.error else ""
        return f"{self.waiting} {noun} waiting for the archive{why}"


# Progress of a long operation: fraction 0..1; returning False cancels (nothing is committed).
Progress = Callable[[float], bool | None]


# ---------------------------------------------------------------------------------------------- files
@runtime_checkable
class SessionFiles(Protocol):
    """An archived session's files, read like its folder."""

    uuid: str

    def files(self) -> list[FileInfo]: ...

    def open(self, name: str) -> IO[bytes]:
        """A file-like object streaming the file's bytes from the archive (chunk by chunk)."""
        ...

    def read_bytes(self, name: str) -> bytes: ...

    def materialise(self, folder: Path, progress: Progress | None = None) -> Path:
        """Write the session folder (the recorder's layout) into ``folder`` (made if needed; must be empty),
        each file checked against its SHA-256; returns the session folder. ``app.session.recording.load_session`` and
        every exporter read it exactly as the station's own folder. ``progress`` returning False cancels."""
        ...


# ---------------------------------------------------------------------------------------------- the archive
@runtime_checkable
class Archive(Protocol):
    """The clinic's archive. Every method is one transaction; none holds one between calls. Methods that write
    name the ``operator`` (the person); the station is the archive's own (``station``, from the configuration)."""

    station: str
    url: str  # for messages: the URL without any password

    def close(self) -> None: ...

    # ------------------------------------------------------------------ schema
    def schema_revision(self) -> str: ...

    # ------------------------------------------------------------------ patients
    def list_patients(self, search: str = "", limit: int = 1000, offset: int = 0) -> list[PatientListItem]:
        """Patients by id (case-insensitive order); ``search``: every word found in the id, name, record
        number or notes (as app.therapy.patients.matches)."""
        ...

    def get_patient(self, patient_id: str) -> PatientRecord:
        """Raises NotFound."""
        ...

    def patient_records(self, limit: int = 1000, offset: int = 0) -> list[PatientRecord]:
        """Every patient's record, ordered as :meth:`list_patients`, read in one transaction (the Patients window).
        Raises ArchiveError when one of them is not a valid profile (then read them one by one)."""
        ...

    def patient_reads(self, block: int = 25) -> Iterator[list[PatientRecord | PatientUnreadable]]:
        """Every patient, ordered as :meth:`list_patients`, read in one transaction and built block by block (the
        Patients window's loader thread: the first rows shown at once; stopping between blocks)."""
        ...

    def import_profiles(self, profiles: Iterable[PatientProfile], *, operator: str) -> int:
        """New patients in one transaction (PatientExists: nothing written). Returns how many."""
        ...

    def save_patient(self, profile: PatientProfile, *, expected_version: int | None, operator: str,
                     fields: Iterable[str] | None = None, reason: str = "save") -> PatientRecord:
        """Validate (PatientProfile.validate) and write. ``expected_version=None``: a new patient (PatientExists if
        the id is taken). ``fields=None``: every field of :data:`PATIENT_FIELDS` and every district's choice;
        else only those keys are written (the others stay as the archive holds them). Refused with StaleRecord
        when a written field changed after ``expected_version``. Returns the new record (its new version)."""
        ...

    def choose_electrodes(self, patient_id: str, district: str, choice: ElectrodeChoice | None, *,
                          expected_version: int, operator: str) -> PatientRecord:
        """A session's electrode choice: writes only ``fes.electrodes.<district>`` (None clears it)."""
        ...

    def patient_history(self, patient_id: str) -> list[PatientChange]: ...

    # ------------------------------------------------------------------ sessions
    def upload_session(self, folder: Path, progress: Progress | None = None) -> UploadResult:
        """Upload a session folder in one transaction, idempotently by its UUID: files (hashes checked by the
        database side after insert), session row, runs, repetitions with their metrics, the journal. Raises
        SessionConflict (same UUID, other files), ArchiveUnavailable (server down: nothing written)."""
        ...

    def has_session(self, uuid: str) -> bool: ...

    def held_sessions(self, uuids: Sequence[str]) -> set[str]:
        """Which of ``uuids`` the archive holds, in one read (a station's folders against the archive)."""
        ...

    def list_sessions(self, patient_id: str | None = None, *, limit: int = 200, offset: int = 0,
                      after: tuple[float, str] | None = None) -> list[SessionInfo]:
        """Newest first (start time, then UUID); one patient's or everyone's. ``after``: the (start_epoch_s, uuid)
        of the last session of the previous page — the sessions browser's blocks, each one indexed read, none
        repeated or skipped when a session is uploaded meanwhile."""
        ...

    def count_sessions(self, patient_id: str | None = None) -> int: ...

    def get_session(self, uuid: str) -> SessionDetail: ...

    def runs(self, uuid: str) -> list[RunInfo]: ...

    def repetitions(self, uuid: str, run_id: str | None = None) -> list[RepetitionInfo]: ...

    def journal(self, uuid: str, kinds: Sequence[str] | None = None) -> list[JournalEntry]: ...

    def journals(self, uuids: Sequence[str], kinds: Sequence[str]) -> dict[str, list[JournalEntry]]:
        """The journal rows of ``kinds`` of several sessions, in one read (a list's statuses)."""
        ...

    def progress_sessions(self, patient_id: str) -> list[ProgressSession]:
        """Everything the progress report needs of a patient's sessions, oldest first, every station's."""
        ...

    # ------------------------------------------------------------------ files
    def session_files(self, uuid: str) -> SessionFiles: ...

    def materialised(self, uuid: str) -> AbstractMaterialised:
        """``with archive.materialised(uuid) as folder:`` a private temporary session folder, removed after."""
        ...

    # ------------------------------------------------------------------ integrity
    def verify(self, progress: Progress | None = None) -> VerifyReport:
        """Re-hash every stored file and every chained row (journals, patient histories, the ledger); the
        report names the first row or file that does not match."""
        ...


class AbstractMaterialised(Protocol):
    def __enter__(self) -> Path: ...

    def __exit__(self, *exc: object) -> None: ...


def iter_chunks(stream: IO[bytes], size: int) -> Iterator[bytes]:
    """Read a binary stream in chunks of ``size`` bytes."""
    while chunk := stream.read(size):
        yield chunk


__all__ = [
    "ELECTRODES_PREFIX", "PATIENT_FIELDS", "AbstractMaterialised", "Archive", "ArchiveError", "ArchiveTooNew",
    "ArchiveUnavailable", "ConfigProblem", "FileInfo", "JournalEntry", "NeedsUpgrade", "NotFound", "OutboxStatus",
    "PatientChange",
    "PatientExists", "PatientListItem", "PatientRecord", "PatientUnreadable", "Progress", "ProgressSession",
    "RepetitionInfo", "RunInfo",
    "SessionConflict", "SessionDetail", "SessionFiles", "SessionInfo", "SessionStatus", "StaleRecord",
    "UploadResult", "VerifyProblem", "VerifyReport", "electrode_field",
]
