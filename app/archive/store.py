"""The archive on SQLAlchemy 2: an SQLite file in ``<data>`` by default, a PostgreSQL server for a clinic.

:func:`open_archive` makes a :class:`SqlArchive` (the one implementation of :class:`app.archive.api.Archive`)
from the configuration (``archive.url``, ``archive.password_file``, ``station``) and checks the schema
(app/archive/schema.py). Each method is one transaction:

* writes on SQLite take the database's write lock at their start (``BEGIN IMMEDIATE``; WAL journal, so readers
  are never blocked and never see half of a write; ``synchronous=FULL``, so a commit the outbox has marked is on
  disk); on PostgreSQL a patient save locks its row (``SELECT … FOR UPDATE``) and the ledger's append takes a
  transaction-scoped advisory lock;
* the session files go into ``blobs``/``blob_chunks`` (content-addressed, 1 MiB chunks) inside the upload's
  transaction, and the database itself hashes what it stored (PostgreSQL's ``sha256()``; on SQLite a function
  registered on the connection) before the session row can commit: a chunk that does not match refuses the
  upload.

Hash chains (docs/archive.md, "Integrity"): ``hash = SHA-256(prev_hash ␞ field ␞ field …)`` over the stored
text of the row; the first row of a chain follows ``genesis(kind, key)``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import logging
import os
import platform
import shutil
import stat
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any, NamedTuple

import yaml
from sqlalchemy import (
    Connection,
    Engine,
    and_,
    create_engine,
    delete,
    event,
    func,
    insert,
    or_,
    select,
    text,
    update,
)
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import DBAPIError, IntegrityError, InterfaceError, OperationalError, ProgrammingError

from app.archive import folders, schema
from app.archive.api import (
    ELECTRODES_PREFIX,
    PATIENT_FIELDS,
    ArchiveError,
    ArchiveUnavailable,
    ConfigProblem,
    FileInfo,
    JournalEntry,
    NotFound,
    PatientChange,
    PatientExists,
    PatientListItem,
    PatientRecord,
    PatientUnreadable,
    Progress,
    ProgressSession,
    RepetitionInfo,
    RunInfo,
    SessionConflict,
    SessionDetail,
    SessionInfo,
    StaleRecord,
    UploadResult,
    VerifyReport,
    electrode_field,
)
from app.archive.chain import canonical, chain_hash, genesis, history_parts, ledger_parts, session_seal
from app.archive.models import (
    Blob,
    BlobChunk,
    ElectrodeChoiceRow,
    JournalRow,
    LedgerRow,
    Patient,
    PatientHistory,
    PlanStep,
    RepetitionRow,
    RunRow,
    SessionFile,
    SessionRow,
)
from app.core import paths
from app.core.yamlschema import ConfigError, to_plain
from app.therapy.patients import PROFILE_VERSION, ElectrodeChoice, PatientProfile, parse_profile

log = logging.getLogger(__name__)

ARCHIVE_FILE = "archive.sqlite3"  # the embedded archive in <data>
CHUNK_BYTES = 1 << 20
_INSERT_BATCH = 8  # chunks per INSERT round trip (8 MiB)
_LEDGER_LOCK = 0x4C494E41  # "LINA": PostgreSQL advisory lock of the ledger's append


def _now() -> str:
    return folders.wall_now()


# ---------------------------------------------------------------------------------------------- patients <-> rows
def profile_values(profile: PatientProfile) -> dict[str, Any]:
    """The profile as field key -> plain value (app.archive.api.PATIENT_FIELDS and one key per district)."""
    plain = to_plain(profile)
    values = {k: plain[k] for k in ("full_name", "birth_date", "record_number", "affected_side", "scores",
                                    "assistance", "robot", "notes", "therapy_plan")}
    values["fes.profile"] = plain["fes"]["profile"]
    values["fes.caps"] = {str(ch): cap for ch, cap in plain["fes"]["caps"].items()}
    for district, choice in plain["fes"]["electrodes"].items():
        values[electrode_field(district)] = choice
    return json.loads(canonical(values))  # the stored form: what is compared is what is kept


def profile_from_values(patient_id: str, values: dict[str, Any], created: str, updated: str) -> PatientProfile:
    """Build the profile from field values through app.therapy.patients' own validation (a value the profile schema
    refuses is refused here too)."""
    electrodes = {k[len(ELECTRODES_PREFIX):]: v for k, v in values.items()
                  if k.startswith(ELECTRODES_PREFIX) and v is not None}
    data = {
        "patient_id": patient_id, "version": PROFILE_VERSION,
        "full_name": values.get("full_name", ""), "birth_date": values.get("birth_date", ""),
        "record_number": values.get("record_number", ""), "affected_side": values.get("affected_side", "unknown"),
        "scores": values.get("scores") or {}, "assistance": values.get("assistance") or {},
        "fes": {"profile": values.get("fes.profile", ""),
                "caps": {int(ch): cap for ch, cap in (values.get("fes.caps") or {}).items()},
                "electrodes": electrodes},
        "robot": values.get("robot") or {}, "notes": values.get("notes", ""),
        "therapy_plan": values.get("therapy_plan") or [], "created": created, "updated": updated,
    }
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    try:
        return parse_profile(text, f"archive:{patient_id}")
    except ConfigError as exc:
        raise ArchiveError(f"Patient {patient_id}: the archive's record is not a valid profile: {exc}") from exc


def _check_keys(keys: Iterable[str]) -> set[str]:
    out = set(keys)
    bad = [k for k in out if k not in PATIENT_FIELDS and not (k.startswith(ELECTRODES_PREFIX) and
                                                              len(k) > len(ELECTRODES_PREFIX))]
    if bad:
        raise ValueError(f"unknown patient field(s) {', '.join(sorted(bad))}; known: {', '.join(PATIENT_FIELDS)}, "
                         f"{ELECTRODES_PREFIX}<district>")
    return out


# ---------------------------------------------------------------------------------------------- engines
def default_url() -> str:
    return f"sqlite:///{paths.data_dir() / ARCHIVE_FILE}"


def _password_from_file(path_text: str) -> str:
    path = Path(path_text).expanduser()
    try:
        st = path.stat()
        secret = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ConfigProblem(f"The archive's password file {path} cannot be read: {exc.strerror or exc}") from exc
    if os.name == "posix" and st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigProblem(f"The archive's password file {path} can be read by other users (mode "
                            f"{stat.S_IMODE(st.st_mode):o}): make it yours only (chmod 600 {path})")
    if not secret:
        raise ConfigProblem(f"The archive's password file {path} is empty")
    return secret


def make_engine(url: str, password_file: str = "", station: str = "") -> Engine:
    """An engine for the archive's URL. Refuses a URL that holds a password (ConfigProblem)."""
    try:
        u: URL = make_url(url)
    except Exception as exc:
        raise ConfigProblem(f"The archive's URL {url!r} is not a database URL: {exc}") from exc
    if u.password is not None:
        raise ConfigProblem("The archive's URL holds a password: anyone who can read the configuration could read "
                            "it. Remove it from the URL and put it in archive.password_file (a file only you can "
                            "read) or in ~/.pgpass.")
    if u.get_backend_name() == "sqlite":
        database = u.database or ""
        if database and database != ":memory:":
            path = Path(database).expanduser()
            paths.private_dir(path.parent)
            if not path.exists():
                os.close(os.open(path, os.O_WRONLY | os.O_CREAT, paths.PRIVATE_FILE_MODE))
        engine = create_engine(u, connect_args={"timeout": 60})
        _sqlite_events(engine)
        return engine
    if u.get_backend_name() != "postgresql":
        raise ConfigProblem(f"The archive's URL {url!r}: the archive is PostgreSQL or SQLite")
    if u.drivername == "postgresql":
        u = u.set(drivername="postgresql+psycopg")
    connect_args: dict[str, Any] = {"connect_timeout": 5,
                                    "application_name": f"linarmpp {station}".strip()[:60]}
    if password_file:
        connect_args["password"] = _password_from_file(password_file)
    return create_engine(u, pool_pre_ping=True, pool_size=2, max_overflow=2, connect_args=connect_args)


def _sqlite_events(engine: Engine) -> None:
    def sha256hex(data: bytes | None) -> str | None:
        return None if data is None else hashlib.sha256(data).hexdigest()

    @event.listens_for(engine, "connect")
    def _connect(dbapi_connection: Any, _record: Any) -> None:
        dbapi_connection.isolation_level = None  # SQLAlchemy's BEGIN below, not the driver's
        cur = dbapi_connection.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA synchronous=FULL")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.close()
        dbapi_connection.create_function("sha256hex", 1, sha256hex, deterministic=True)

    @event.listens_for(engine, "begin")
    def _begin(conn: Connection) -> None:
        conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("archive_write") else "BEGIN")


def _station_name(station: str | None) -> str:
    return station or platform.node() or "station"


def open_archive(config: Any = None, *, url: str | None = None, station: str | None = None,
                 password_file: str | None = None, create: bool = True) -> SqlArchive:
    """The configured archive (``config.archive``, ``config.station``), or ``url``; '' = the SQLite file in
    ``<data>``. Raises ConfigProblem, ArchiveUnavailable, ArchiveTooNew, NeedsUpgrade (sentences)."""
    cfg_archive = getattr(config, "archive", None)
    url = url if url is not None else (getattr(cfg_archive, "url", "") or "")
    password_file = password_file if password_file is not None else (getattr(cfg_archive, "password_file", "") or "")
    station = _station_name(station if station is not None else getattr(config, "station", ""))
    url = url or default_url()
    engine = make_engine(url, password_file, station)
    archive = SqlArchive(engine, station)
    archive.password_file = password_file
    try:
        with archive._errors("open"):
            schema.check(engine, archive.url, create=create)
    except BaseException:
        engine.dispose()
        raise
    return archive


class Upgraded(NamedTuple):
    """What ``linarmpp archive upgrade`` did: the schema revisions and the embedded archive's copy made first."""

    before: str | None
    after: str
    copy: Path | None  # the SQLite file as it was, when its schema was changed (None: nothing to change, or a server)


def upgrade_archive(config: Any = None, *, url: str | None = None, password_file: str | None = None) -> Upgraded:
    """``linarmpp archive upgrade``: migrate to this application's schema, in one transaction. The embedded
    (SQLite) archive is first copied beside itself (``backup_sqlite``): a clinic's server has its own backups, a
    single PC has only this file."""
    cfg_archive = getattr(config, "archive", None)
    url = (url if url is not None else getattr(cfg_archive, "url", "")) or default_url()
    pw = password_file if password_file is not None else (getattr(cfg_archive, "password_file", "") or "")
    engine = make_engine(url, pw)
    copies: list[Path] = []
    database = engine.url.database if engine.url.get_backend_name() == "sqlite" else None

    def copy_first(revision: str) -> None:
        if database and database != ":memory:":
            copies.append(backup_sqlite(Path(database).expanduser(), revision))

    try:
        try:
            before, after = schema.upgrade(engine, before_change=copy_first)
        except (OperationalError, InterfaceError) as exc:
            raise ArchiveUnavailable(_unreachable(engine, exc)) from exc
    finally:
        engine.dispose()
    return Upgraded(before, after, copies[0] if copies else None)


def backup_sqlite(path: Path, revision: str) -> Path:
    """A copy of the SQLite archive ``path`` (at schema ``revision``) beside it, made with SQLite's backup API (a
    consistent copy even while another connection reads), private (0600), and read back: its integrity check
    passes and it holds ``revision``. Raises ArchiveError (nothing is migrated then)."""
    import sqlite3

    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    copy = path.with_name(f"{path.stem}.before-upgrade-{revision}-{stamp}{path.suffix}")
    try:
        os.close(os.open(copy, os.O_WRONLY | os.O_CREAT | os.O_EXCL, paths.PRIVATE_FILE_MODE))
        with contextlib.closing(sqlite3.connect(path)) as src, contextlib.closing(sqlite3.connect(copy)) as dst:
            src.backup(dst)
        with contextlib.closing(sqlite3.connect(f"file:{copy}?mode=ro", uri=True)) as check:
            ok = check.execute("PRAGMA integrity_check").fetchone()
            held = check.execute("SELECT version_num FROM alembic_version").fetchone()
    except (OSError, sqlite3.Error) as exc:
        raise ArchiveError(f"The archive {path} was not upgraded: its copy {copy} could not be made ({exc}); "
                           "nothing was changed.") from exc
    if ok != ("ok",) or held != (revision,):
        raise ArchiveError(f"The archive {path} was not upgraded: its copy {copy} does not read back as the archive "
                           f"(integrity {ok}, schema {held}); nothing was changed.")
    return copy


def _unreachable(engine: Engine, exc: BaseException) -> str:
    orig = getattr(exc, "orig", exc)
    first = str(orig).strip().splitlines()[0] if str(orig).strip() else type(orig).__name__
    return f"the archive at {engine.url.render_as_string(hide_password=True)} cannot be reached ({first})"


class _Cancelled(ArchiveError):
    pass


# ---------------------------------------------------------------------------------------------- the archive
class SqlArchive:
    """app.archive.api.Archive on SQLAlchemy 2 (SQLite or PostgreSQL)."""

    def __init__(self, engine: Engine, station: str) -> None:
        self.engine = engine
        self.station = station
        self.url = engine.url.render_as_string(hide_password=True)
        self.dialect = engine.dialect.name
        self.password_file = ""  # the configuration's (open_archive): another process opens the same archive with it
        # Profiles built by patient_reads, by (patient, version, changed_at): a version's values never change, so the
        # Patients window opened again validates only the records saved since (validation is ~5-15 ms a record).
        self._built: dict[tuple[str, int, str], PatientProfile] = {}
        self._lz4: bool | None = None  # PostgreSQL: whether the server compresses with lz4 (_fast_toast)

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> SqlArchive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ transactions
    @contextlib.contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        try:
            yield
        except (OperationalError, InterfaceError) as exc:
            raise ArchiveUnavailable(_unreachable(self.engine, exc)) from exc
        except ProgrammingError as exc:
            orig = getattr(exc, "orig", exc)
            if "permission denied" in str(orig).lower():
                raise ArchiveError(f"The archive at {self.url} refused to {what}: {str(orig).strip().splitlines()[0]}"
                                   " (the station's database role lacks this right: docs/archive.md)") from exc
            raise
        except DBAPIError as exc:
            if exc.connection_invalidated:
                raise ArchiveUnavailable(_unreachable(self.engine, exc)) from exc
            raise

    @contextlib.contextmanager
    def _read(self) -> Iterator[Connection]:
        with self._errors("read"), self.engine.connect() as conn, conn.begin():
            yield conn

    @contextlib.contextmanager
    def _write(self, what: str) -> Iterator[Connection]:
        with self._errors(what), self.engine.connect() as conn:
            conn = conn.execution_options(archive_write=True)
            with conn.begin():
                yield conn

    def schema_revision(self) -> str:
        with self._read() as conn:
            return schema.current_revision(conn) or ""

    # ------------------------------------------------------------------ ledger
    def _append_ledger(self, conn: Connection, kind: str, key: str, version: int, head: str, at: str) -> None:
        if self.dialect == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _LEDGER_LOCK})
        last = conn.execute(select(LedgerRow.seq, LedgerRow.hash).order_by(LedgerRow.seq.desc()).limit(1)).first()
        seq, prev = (last[0] + 1, last[1]) if last else (1, genesis("ledger", ""))
        row = {"seq": seq, "kind": kind, "key": key, "version": version, "head": head, "at": at,
               "station": self.station}
        row["prev_hash"] = prev
        row["hash"] = chain_hash(prev, ledger_parts(_Obj(row)))
        conn.execute(insert(LedgerRow), [row])

    # ------------------------------------------------------------------ patients
    def list_patients(self, search: str = "", limit: int = 1000, offset: int = 0) -> list[PatientListItem]:
        counts = (select(SessionRow.patient_id, func.count().label("n"), func.max(SessionRow.start_iso).label("last"))
                  .group_by(SessionRow.patient_id).subquery())
        q = (select(Patient.patient_id, Patient.full_name, Patient.record_number, Patient.version, Patient.changed_at,
                    counts.c.n, counts.c.last, Patient.changed_by, Patient.changed_station)
             .outerjoin(counts, counts.c.patient_id == Patient.patient_id))
        for word in search.lower().split():
            escaped = word.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
            q = q.where(Patient.search_text.like(f"%{escaped}%", escape="\\"))
        q = q.order_by(func.lower(Patient.patient_id), Patient.patient_id).limit(limit).offset(offset)
        with self._read() as conn:
            return [PatientListItem(r[0], r[1], r[2], r[3], r[4], int(r[5] or 0), r[6] or "", r[7], r[8])
                    for r in conn.execute(q)]

    def _values(self, conn: Connection, row: Any) -> dict[str, Any]:
        return self._values_of(conn, [row])[row.patient_id]

    def _values_of(self, conn: Connection, rows: Sequence[Any]) -> dict[str, dict[str, Any]]:
        """Each row's field values, its plan steps and electrode choices read for all rows at once (three queries
        per 500 patients, not two per patient: the Patients window lists every record)."""
        out: dict[str, dict[str, Any]] = {}
        for row in rows:
            out[row.patient_id] = {
                "full_name": row.full_name, "birth_date": row.birth_date, "record_number": row.record_number,
                "affected_side": row.affected_side, "scores": json.loads(row.scores),
                "assistance": json.loads(row.assistance), "robot": json.loads(row.robot), "notes": row.notes,
                "fes.profile": row.fes_profile, "fes.caps": json.loads(row.fes_caps), "therapy_plan": [],
            }
        ids = list(out)
        for k in range(0, len(ids), 500):
            part = ids[k:k + 500]
            steps = conn.execute(select(PlanStep.patient_id, PlanStep.exercise, PlanStep.params, PlanStep.note)
                                 .where(PlanStep.patient_id.in_(part))
                                 .order_by(PlanStep.patient_id, PlanStep.position)).all()
            for pid, e, p, n in steps:
                out[pid]["therapy_plan"].append({"exercise": e, "params": json.loads(p), "note": n})
            choices = conn.execute(select(ElectrodeChoiceRow.patient_id, ElectrodeChoiceRow.district,
                                          ElectrodeChoiceRow.cleared, ElectrodeChoiceRow.choice)
                                   .where(ElectrodeChoiceRow.patient_id.in_(part))
                                   .order_by(ElectrodeChoiceRow.id)).all()
            current: dict[str, dict[str, Any]] = {pid: {} for pid in part}
            for pid, district, cleared, choice in choices:
                current[pid].pop(district, None)  # the newest choice last (its district's place: when it was chosen)
                if not cleared:
                    current[pid][district] = json.loads(choice)
            for pid, chosen in current.items():
                for district, choice in chosen.items():
                    out[pid][electrode_field(district)] = choice
        return out

    def _record(self, conn: Connection, row: Any) -> PatientRecord:
        profile = profile_from_values(row.patient_id, self._values(conn, row), row.created, row.updated)
        return PatientRecord(profile, row.version, row.changed_at, row.changed_by, row.changed_station)

    def patient_records(self, limit: int = 1000, offset: int = 0) -> list[PatientRecord]:
        """Every patient's record (by id, as list_patients), read in one transaction: the Patients window's list."""
        q = select(Patient).order_by(func.lower(Patient.patient_id), Patient.patient_id).limit(limit).offset(offset)
        with self._read() as conn:
            rows = conn.execute(q).all()
            values = self._values_of(conn, rows)
        out = []
        for row in rows:
            profile = profile_from_values(row.patient_id, values[row.patient_id], row.created, row.updated)
            out.append(PatientRecord(profile, row.version, row.changed_at, row.changed_by, row.changed_station))
        return out

    def patient_reads(self, block: int = 25) -> Iterator[list[PatientRecord | PatientUnreadable]]:
        """Every patient's record in blocks of ``block``, ordered as :meth:`list_patients`. The rows are read in
        one transaction (a snapshot: a save meanwhile neither duplicates nor hides a patient); each profile is
        then built and validated block by block, so the caller (the Patients window's loader thread) shows the
        first rows at once and can stop between blocks. A record that is not a valid profile comes as
        :class:`PatientUnreadable` in its place, never hiding the others."""
        q = select(Patient).order_by(func.lower(Patient.patient_id), Patient.patient_id)
        with self._read() as conn:
            rows = conn.execute(q).all()
            values = self._values_of(conn, rows)
        for k in range(0, len(rows), max(1, block)):
            out: list[PatientRecord | PatientUnreadable] = []
            for row in rows[k:k + block]:
                key = (row.patient_id, row.version, row.changed_at)
                profile = self._built.get(key)
                if profile is None:
                    try:
                        profile = profile_from_values(row.patient_id, values[row.patient_id], row.created,
                                                      row.updated)
                    except ArchiveError as exc:
                        out.append(PatientUnreadable(row.patient_id, row.version, str(exc)))
                        continue
                    self._built[key] = profile
                out.append(PatientRecord(profile, row.version, row.changed_at, row.changed_by, row.changed_station))
            yield out

    def import_profiles(self, profiles: Iterable[PatientProfile], *, operator: str) -> int:
        """New patients written in one transaction (a bulk import, a test's archive of many patients): each as
        :meth:`save_patient` with ``expected_version=None`` would write it, history and ledger included. Raises
        PatientExists (nothing written) when one is already archived. Returns how many were written."""
        if not operator:
            raise ValueError("a patient's save needs the operator (who makes the change)")
        n = 0
        with self._write("import patients") as conn:
            for profile in profiles:
                profile.validate()
                self._save_in(conn, profile.patient_id, profile_values(profile), None, None, operator, "import",
                              (profile.created, profile.updated), _now(), returning=False)
                n += 1
        return n

    def get_patient(self, patient_id: str) -> PatientRecord:
        with self._read() as conn:
            row = conn.execute(select(Patient).where(Patient.patient_id == patient_id)).first()
            if row is None:
                raise NotFound(f"There is no patient {patient_id} in the archive.")
            return self._record(conn, row)

    def save_patient(self, profile: PatientProfile, *, expected_version: int | None, operator: str,
                     fields: Iterable[str] | None = None, reason: str = "save") -> PatientRecord:
        profile.validate()
        values = profile_values(profile)
        keys = None if fields is None else _check_keys(fields)
        times = (profile.created, profile.updated if reason == "import" else "")
        return self._save(profile.patient_id, values, keys, expected_version, operator, reason, times)

    def choose_electrodes(self, patient_id: str, district: str, choice: ElectrodeChoice | None, *,
                          expected_version: int, operator: str) -> PatientRecord:
        key = electrode_field(district)
        value = None if choice is None else json.loads(canonical(to_plain(choice)))
        return self._save(patient_id, {key: value}, {key}, expected_version, operator, "electrode choice", None)

    def _save(self, patient_id: str, values: dict[str, Any], keys: set[str] | None, expected_version: int | None,
              operator: str, reason: str, times: tuple[str, str] | None) -> PatientRecord:
        if not operator:
            raise ValueError("a patient's save needs the operator (who makes the change)")
        at = _now()
        with self._write(f"save patient {patient_id}") as conn:
            return self._save_in(conn, patient_id, values, keys, expected_version, operator, reason, times, at)

    def _save_in(self, conn: Connection, patient_id: str, values: dict[str, Any], keys: set[str] | None,
                 expected_version: int | None, operator: str, reason: str, times: tuple[str, str] | None,
                 at: str, returning: bool = True) -> PatientRecord:
        """One save inside the caller's transaction; ``returning=False`` (a bulk import) skips building the saved
        record back (the caller does not use it; the values were validated before writing all the same)."""
        row = conn.execute(select(Patient).where(Patient.patient_id == patient_id).with_for_update()).first()
        if expected_version is None:
            if row is not None:
                raise PatientExists(f"Patient {patient_id} is already in the archive (changed by "
                                    f"{row.changed_by} on {row.changed_station} at {row.changed_at}); open it "
                                    "there instead of creating it again.")
            current: dict[str, Any] = {}
            written = set(values) if keys is None else keys
            version = 1
        else:
            if row is None:
                raise NotFound(f"There is no patient {patient_id} in the archive.")
            current = self._values(conn, row)
            written = (set(PATIENT_FIELDS) | {k for k in (*values, *current) if k.startswith(ELECTRODES_PREFIX)}
                       if keys is None else keys)
            if row.version != expected_version:
                self._refuse_if_stale(conn, row, expected_version, written)
            version = row.version + 1
        changed = {k: values.get(k) for k in sorted(written) if values.get(k) != current.get(k)}
        if row is not None and not changed:
            return self._record(conn, row)
        merged = {**current, **changed}
        created = (row.created if row is not None else "") or (times[0] if times else "") or at
        updated = (times[1] if times else "") or at
        profile = profile_from_values(patient_id, merged, created, updated)  # validates the result
        columns = self._columns(profile, merged)
        columns.update(version=version, created=created, updated=updated, changed_at=at, changed_by=operator,
                       changed_station=self.station)
        if row is None:
            conn.execute(insert(Patient).values(patient_id=patient_id, **columns))
        else:
            conn.execute(update(Patient).where(Patient.patient_id == patient_id).values(**columns))
        if "therapy_plan" in changed:
            conn.execute(delete(PlanStep).where(PlanStep.patient_id == patient_id))
            steps = [{"patient_id": patient_id, "position": k, "exercise": s["exercise"],
                      "params": canonical(s["params"]), "note": s["note"]}
                     for k, s in enumerate(merged["therapy_plan"], start=1)]
            if steps:
                conn.execute(insert(PlanStep), steps)
        choices = [self._choice_row(patient_id, k[len(ELECTRODES_PREFIX):], v, version)
                   for k, v in changed.items() if k.startswith(ELECTRODES_PREFIX)]
        if choices:
            conn.execute(insert(ElectrodeChoiceRow), choices)
        last = conn.execute(select(PatientHistory.hash).where(PatientHistory.patient_id == patient_id)
                            .order_by(PatientHistory.version.desc()).limit(1)).scalar()
        h = {"patient_id": patient_id, "version": version, "fields": canonical(sorted(changed)),
             "values": canonical(changed), "changed_by": operator, "changed_station": self.station,
             "changed_at": at, "reason": reason, "prev_hash": last or genesis("patient", patient_id)}
        h["hash"] = chain_hash(h["prev_hash"], history_parts(_Obj(h)))
        conn.execute(insert(PatientHistory), [h])
        self._append_ledger(conn, "patient", patient_id, version, h["hash"], at)
        if not returning:
            return None  # type: ignore[return-value]
        row = conn.execute(select(Patient).where(Patient.patient_id == patient_id)).first()
        return self._record(conn, row)

    def _refuse_if_stale(self, conn: Connection, row: Any, expected: int, written: set[str]) -> None:
        later = conn.execute(select(PatientHistory).where(PatientHistory.patient_id == row.patient_id,
                                                          PatientHistory.version > expected)
                             .order_by(PatientHistory.version)).all()
        if expected > row.version:
            raise StaleRecord(row.patient_id, expected, row.version, row.changed_by, row.changed_station,
                              row.changed_at)
        touched: set[str] = set()
        last = None
        for h in later:
            hit = set(json.loads(h.fields)) & written
            if hit:
                touched |= hit
                last = h
        if last is not None:
            raise StaleRecord(row.patient_id, expected, row.version, last.changed_by, last.changed_station,
                              last.changed_at, tuple(sorted(touched)))

    @staticmethod
    def _choice_row(patient_id: str, district: str, value: Any, version: int) -> dict[str, Any]:
        value = value or {}
        return {"patient_id": patient_id, "district": district, "patient_version": version, "cleared": not value,
                "choice": canonical(value), "channel": value.get("channel"), "electrodes": value.get("electrodes", ""),
                "chosen_at": value.get("chosen_at", ""), "chosen_by": value.get("chosen_by", ""),
                "session": value.get("session", "")}

    @staticmethod
    def _columns(profile: PatientProfile, merged: dict[str, Any]) -> dict[str, Any]:
        search = " ".join([profile.patient_id, profile.full_name, profile.record_number, profile.notes]).lower()
        return {"full_name": merged.get("full_name", ""), "birth_date": merged.get("birth_date", ""),
                "record_number": merged.get("record_number", ""),
                "affected_side": merged.get("affected_side", "unknown"), "notes": merged.get("notes", ""),
                "fes_profile": merged.get("fes.profile", ""), "scores": canonical(merged.get("scores") or {}),
                "assistance": canonical(merged.get("assistance") or {}), "robot": canonical(merged.get("robot") or {}),
                "fes_caps": canonical(merged.get("fes.caps") or {}), "search_text": search}

    def patient_history(self, patient_id: str) -> list[PatientChange]:
        with self._read() as conn:
            rows = conn.execute(select(PatientHistory).where(PatientHistory.patient_id == patient_id)
                                .order_by(PatientHistory.version)).all()
        return [PatientChange(r.patient_id, r.version, tuple(json.loads(r.fields)), json.loads(r.values),
                              r.changed_by, r.changed_station, r.changed_at, r.reason, r.prev_hash, r.hash)
                for r in rows]

    # ------------------------------------------------------------------ sessions
    def has_session(self, uuid: str) -> bool:
        with self._read() as conn:
            return conn.execute(select(SessionRow.uuid).where(SessionRow.uuid == uuid)).first() is not None

    def upload_session(self, folder: Path, progress: Progress | None = None) -> UploadResult:
        from app.archive.derive import derive_session

        t0 = time.perf_counter()
        folder = Path(folder)
        manifest = folders.read_manifest(folder)
        files = folders.session_files(folder)
        if not any(f.name == folders.MANIFEST_FILE for f in files):
            raise ArchiveError(f"{folder} is not a session folder (no readable {folders.MANIFEST_FILE})")
        uuid = folders.session_uuid(folder, manifest)
        digest = folders.content_digest([(f.name, f.sha256) for f in files])
        total = sum(f.size for f in files)
        with self._read() as conn:
            known = conn.execute(select(SessionRow.content_digest).where(SessionRow.uuid == uuid)).scalar()
        if known is not None:
            return self._already(uuid, known, digest, folder, files, total, t0)
        derived = derive_session(folder, manifest, uuid, digest, self.station)
        at = _now()
        done = 0
        try:
            with self._write(f"archive the session {folder.name}") as conn:
                self._fast_toast(conn)
                session_row = {**derived.session, "archived_at": at, "archived_station": self.station}
                inserted = conn.execute(self._insert_ignore(SessionRow, ["uuid"]).values(**session_row)
                                        .returning(SessionRow.uuid)).first()
                if inserted is None:  # another station committed it meanwhile
                    known = conn.execute(select(SessionRow.content_digest).where(SessionRow.uuid == uuid)).scalar()
                    return self._already(uuid, str(known), digest, folder, files, total, t0)
                for f in files:
                    done = self._store_blob(conn, f, done, total, progress)
                conn.execute(insert(SessionFile), [{"session_uuid": uuid, "name": f.name, "size": f.size,
                                                    "sha256": f.sha256} for f in files])
                if derived.runs:
                    conn.execute(insert(RunRow), derived.runs)
                if derived.repetitions:
                    conn.execute(insert(RepetitionRow), derived.repetitions)
                if derived.journal:
                    conn.execute(insert(JournalRow), derived.journal)
                self._append_ledger(conn, "session", uuid, 0, session_seal(digest, derived.session["journal_head"],
                                                                           derived.session["journal_rows"]), at)
        except IntegrityError as exc:  # the same UUID raced in from another station: the insert's conflict
            if self.has_session(uuid):
                with self._read() as conn:
                    known = conn.execute(select(SessionRow.content_digest).where(SessionRow.uuid == uuid)).scalar()
                return self._already(uuid, str(known), digest, folder, files, total, t0)
            raise ArchiveError(f"The archive refused the session {folder}: {exc.orig}") from exc
        if progress is not None:
            progress(1.0)
        return UploadResult(uuid, "uploaded", len(files), total, time.perf_counter() - t0)

    def _fast_toast(self, conn: Connection) -> None:
        """On PostgreSQL ≥ 14 built with lz4: this transaction's stored chunks compressed with lz4 rather than the
        default pglz. pglz made the server spend ~4 s of a 30-minute session's upload compressing its CSV text
        (lz4: ~0.4 s, the chunks ~25 % larger); a session setting the application's role may set, no schema
        change, and every chunk says how it was compressed (older ones read as before)."""
        if self.dialect != "postgresql":
            return
        if self._lz4 is None:
            found = conn.execute(text("SELECT 'lz4' = ANY(enumvals) FROM pg_settings "
                                      "WHERE name = 'default_toast_compression'")).scalar()
            self._lz4 = bool(found)
        if self._lz4:
            conn.execute(text("SET LOCAL default_toast_compression = 'lz4'"))

    def _already(self, uuid: str, known: str, digest: str, folder: Path, files: list[folders.FolderFile],
                 total: int, t0: float) -> UploadResult:
        if known != digest:
            raise SessionConflict(f"The archive already holds another session with the UUID {uuid} (its files "
                                  f"differ from {folder}): this session was not archived. Keep the folder and report "
                                  "it: two sessions must never share a UUID.")
        return UploadResult(uuid, "already_archived", len(files), total, time.perf_counter() - t0)

    def _insert_ignore(self, model: Any, keys: list[str]) -> Any:
        if self.dialect == "postgresql":
            from sqlalchemy.dialects.postgresql import insert as pg_insert

            return pg_insert(model).on_conflict_do_nothing(index_elements=keys)
        from sqlalchemy.dialects.sqlite import insert as sqlite_insert

        return sqlite_insert(model).on_conflict_do_nothing(index_elements=keys)

    def _store_blob(self, conn: Connection, f: folders.FolderFile, done: int, total: int,
                    progress: Progress | None) -> int:
        """Insert a file's chunks unless the archive already holds its content; the database then hashes what it
        stored and the upload is refused if any chunk differs from what was read."""
        n_chunks = max(1, -(-f.size // CHUNK_BYTES))
        new = conn.execute(self._insert_ignore(Blob, ["sha256"]).values(sha256=f.sha256, size=f.size, chunks=n_chunks)
                           .returning(Blob.sha256)).first()
        if new is None:
            return done + f.size
        whole = hashlib.sha256()
        sent: list[str] = []
        batch: list[dict[str, Any]] = []
        size = 0
        with open(f.path, "rb") as fh:
            seq = 0
            while True:
                data = fh.read(CHUNK_BYTES)
                if not data and seq > 0:
                    break
                whole.update(data)
                size += len(data)
                chunk_sha = hashlib.sha256(data).hexdigest()
                sent.append(chunk_sha)
                batch.append({"sha256": f.sha256, "seq": seq, "chunk_sha256": chunk_sha, "data": data})
                seq += 1
                if len(batch) >= _INSERT_BATCH:
                    conn.execute(insert(BlobChunk), batch)
                    batch = []
                done += len(data)
                if progress is not None and progress(done / max(1, total)) is False:
                    raise _Cancelled("The upload was cancelled; nothing was archived.")
                if not data:
                    break
        if batch:
            conn.execute(insert(BlobChunk), batch)
        if whole.hexdigest() != f.sha256 or size != f.size or len(sent) != n_chunks:
            raise ArchiveError(f"{f.path} changed while it was being archived: nothing was archived; it is tried "
                               "again later")
        stored = self._server_chunk_hashes(conn, f.sha256)
        if stored != sent:
            bad = next((k for k, (a, b) in enumerate(zip(stored, sent, strict=False)) if a != b), len(stored))
            raise ArchiveError(f"The archive stored chunk {bad} of {f.name} differently from what was sent: "
                               "nothing was archived")
        return done

    def _server_chunk_hashes(self, conn: Connection, sha: str) -> list[str]:
        """The chunks' SHA-256 as computed by the database itself from what it stored."""
        if self.dialect == "postgresql":
            q = text("SELECT encode(sha256(data), 'hex') FROM blob_chunks WHERE sha256 = :s ORDER BY seq")
        else:
            q = text("SELECT sha256hex(data) FROM blob_chunks WHERE sha256 = :s ORDER BY seq")
        return [r[0] for r in conn.execute(q, {"s": sha})]

    @staticmethod
    def _info(r: Any) -> SessionInfo:
        return SessionInfo(r.uuid, r.patient_id, r.station, r.operator, r.note, r.start_iso, r.start_epoch_s,
                           r.end_iso, r.duration_s, r.status, r.app_version, tuple(json.loads(r.exercises)),
                           r.alarms, r.folder_name, r.archived_at)

    _INFO_COLUMNS = (SessionRow.uuid, SessionRow.patient_id, SessionRow.station, SessionRow.operator,
                     SessionRow.note, SessionRow.start_iso, SessionRow.start_epoch_s, SessionRow.end_iso,
                     SessionRow.duration_s, SessionRow.status, SessionRow.app_version, SessionRow.exercises,
                     SessionRow.alarms, SessionRow.folder_name, SessionRow.archived_at)

    _INFO_NAMES = tuple(f.name for f in dataclasses.fields(SessionInfo))

    def held_sessions(self, uuids: Sequence[str]) -> set[str]:
        found: set[str] = set()
        uuid_list = list(uuids)
        with self._read() as conn:
            for k in range(0, len(uuid_list), 500):  # bounded IN lists
                q = select(SessionRow.uuid).where(SessionRow.uuid.in_(uuid_list[k:k + 500]))
                found.update(conn.execute(q).scalars())
        return found

    def list_sessions(self, patient_id: str | None = None, *, limit: int = 200, offset: int = 0,
                      after: tuple[float, str] | None = None) -> list[SessionInfo]:
        """One query of plain columns; the records are made without SessionInfo's frozen ``__init__`` (15 guarded
        attribute sets a row: most of listing 10 000 sessions) and each distinct list of run titles is parsed
        once (a patient's sessions repeat their exercises). ``after`` continues past a page's last session (keyset:
        the index on (patient, start) reads only the page, where an offset reads every row before it)."""
        q = select(*self._INFO_COLUMNS)
        if patient_id is not None:
            q = q.where(SessionRow.patient_id == patient_id)
        if after is not None:
            start, uuid = after
            q = q.where(or_(SessionRow.start_epoch_s < start,
                            and_(SessionRow.start_epoch_s == start, SessionRow.uuid > uuid)))
        q = q.order_by(SessionRow.start_epoch_s.desc(), SessionRow.uuid).limit(limit).offset(offset)
        with self._read() as conn:
            rows = conn.execute(q).all()
        names, titles, new = self._INFO_NAMES, {}, object.__new__
        out = []
        for r in rows:
            values = dict(zip(names, r, strict=True))
            text_ = values["exercises"]
            parsed = titles.get(text_)
            if parsed is None:
                parsed = titles[text_] = tuple(json.loads(text_))
            values["exercises"] = parsed
            info = new(SessionInfo)
            info.__dict__.update(values)  # the same record SessionInfo(**values) makes (a test compares them)
            out.append(info)
        return out

    def count_sessions(self, patient_id: str | None = None) -> int:
        q = select(func.count()).select_from(SessionRow)
        if patient_id is not None:
            q = q.where(SessionRow.patient_id == patient_id)
        with self._read() as conn:
            return int(conn.execute(q).scalar() or 0)

    def get_session(self, uuid: str) -> SessionDetail:
        with self._read() as conn:
            r = conn.execute(select(SessionRow).where(SessionRow.uuid == uuid)).first()
            if r is None:
                raise NotFound(f"There is no session {uuid} in the archive.")
            files = conn.execute(select(SessionFile.name, SessionFile.size, SessionFile.sha256)
                                 .where(SessionFile.session_uuid == uuid).order_by(SessionFile.name)).all()
        return SessionDetail(self._info(r), json.loads(r.manifest), tuple(FileInfo(*f) for f in files),
                             json.loads(r.summary), tuple(json.loads(r.problems)))

    @staticmethod
    def _run(r: Any) -> RunInfo:
        return RunInfo(r.session_uuid, r.run_id, r.position, json.loads(r.program), r.title,
                       tuple(json.loads(r.parameters)), r.source, r.operator, r.restart_of, r.started_s, r.ended_s,
                       r.end_reason, r.end_detail, json.loads(r.summary))

    def runs(self, uuid: str) -> list[RunInfo]:
        with self._read() as conn:
            rows = conn.execute(select(RunRow).where(RunRow.session_uuid == uuid).order_by(RunRow.position)).all()
        return [self._run(r) for r in rows]

    def repetitions(self, uuid: str, run_id: str | None = None) -> list[RepetitionInfo]:
        q = select(RepetitionRow).where(RepetitionRow.session_uuid == uuid)
        if run_id is not None:
            q = q.where(RepetitionRow.run_id == run_id)
        with self._read() as conn:
            rows = conn.execute(q.order_by(RepetitionRow.run_position, RepetitionRow.idx)).all()
        return [RepetitionInfo(r.session_uuid, r.run_id, r.idx, json.loads(r.metrics)) for r in rows]

    def journal(self, uuid: str, kinds: Sequence[str] | None = None) -> list[JournalEntry]:
        q = select(JournalRow).where(JournalRow.session_uuid == uuid)
        if kinds:
            q = q.where(JournalRow.kind.in_(list(kinds)))
        with self._read() as conn:
            rows = conn.execute(q.order_by(JournalRow.seq)).all()
        return [JournalEntry(r.session_uuid, r.seq, r.t_wall, r.t_mono, r.kind, r.who, r.origin, json.loads(r.data),
                             r.prev_hash, r.hash) for r in rows]

    def journals(self, uuids: Sequence[str], kinds: Sequence[str]) -> dict[str, list[JournalEntry]]:
        """The journal rows of ``kinds`` of several sessions in one read (the sessions browser's statuses)."""
        out: dict[str, list[JournalEntry]] = {u: [] for u in uuids}
        uuid_list = list(uuids)
        with self._read() as conn:
            for k in range(0, len(uuid_list), 500):  # bounded IN lists
                q = (select(JournalRow).where(JournalRow.session_uuid.in_(uuid_list[k:k + 500]),
                                              JournalRow.kind.in_(list(kinds)))
                     .order_by(JournalRow.session_uuid, JournalRow.seq))
                for r in conn.execute(q):
                    out[r.session_uuid].append(JournalEntry(r.session_uuid, r.seq, r.t_wall, r.t_mono, r.kind, r.who,
                                                            r.origin, json.loads(r.data), r.prev_hash, r.hash))
        return out

    def progress_sessions(self, patient_id: str) -> list[ProgressSession]:
        with self._read() as conn:
            rows = conn.execute(select(*self._INFO_COLUMNS, SessionRow.summary, SessionRow.manifest)
                                .where(SessionRow.patient_id == patient_id)
                                .order_by(SessionRow.start_epoch_s, SessionRow.uuid)).all()
            uuids = [r.uuid for r in rows]
            runs = conn.execute(select(RunRow).where(RunRow.session_uuid.in_(uuids))
                                .order_by(RunRow.session_uuid, RunRow.position)).all() if uuids else []
            reps = conn.execute(select(RepetitionRow).where(RepetitionRow.session_uuid.in_(uuids))
                                .order_by(RepetitionRow.session_uuid, RepetitionRow.run_position,
                                          RepetitionRow.idx)).all() if uuids else []
        by_runs: dict[str, list[RunInfo]] = {}
        for r in runs:
            by_runs.setdefault(r.session_uuid, []).append(self._run(r))
        by_reps: dict[str, list[RepetitionInfo]] = {}
        for r in reps:
            by_reps.setdefault(r.session_uuid, []).append(RepetitionInfo(r.session_uuid, r.run_id, r.idx,
                                                                         json.loads(r.metrics)))
        out = []
        for r in rows:
            manifest = json.loads(r.manifest)
            scores = dict(((manifest.get("patient") or {}).get("scores")) or {})
            out.append(ProgressSession(self._info(r), json.loads(r.summary), scores, tuple(by_runs.get(r.uuid, [])),
                                       tuple(by_reps.get(r.uuid, []))))
        return out

    # ------------------------------------------------------------------ files
    def session_files(self, uuid: str) -> ArchivedFiles:
        with self._read() as conn:
            r = conn.execute(select(SessionRow.folder_name).where(SessionRow.uuid == uuid)).first()
            if r is None:
                raise NotFound(f"There is no session {uuid} in the archive.")
            files = conn.execute(select(SessionFile.name, SessionFile.size, SessionFile.sha256)
                                 .where(SessionFile.session_uuid == uuid).order_by(SessionFile.name)).all()
        return ArchivedFiles(self, uuid, r.folder_name, [FileInfo(*f) for f in files])

    @contextlib.contextmanager
    def materialised(self, uuid: str) -> Iterator[Path]:
        files = self.session_files(uuid)
        tmp = Path(tempfile.mkdtemp(prefix="linarmpp-session-"))
        try:
            patient, _, stamp = files.folder_name.partition("/")
            folder = tmp / (folders_safe(patient) or "patient") / (folders_safe(stamp) or uuid)
            yield files.materialise(folder)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _chunks(self, sha: str) -> Iterator[tuple[int, str, bytes]]:
        """A blob's chunks in order, one short read each (no transaction held while the caller writes)."""
        seq = 0
        while True:
            with self._read() as conn:
                r = conn.execute(select(BlobChunk.seq, BlobChunk.chunk_sha256, BlobChunk.data)
                                 .where(BlobChunk.sha256 == sha, BlobChunk.seq == seq)).first()
            if r is None:
                return
            yield r[0], r[1], bytes(r[2])
            seq += 1

    # ------------------------------------------------------------------ integrity
    def verify(self, progress: Progress | None = None) -> VerifyReport:
        from app.archive.verify import verify_archive

        return verify_archive(self, progress)


def folders_safe(name: str) -> str:
    from app.session.recording import safe_name

    return safe_name(name) if name else ""


class _Obj:
    """Attribute access to a row dict (for the chain's parts)."""

    def __init__(self, d: dict[str, Any]) -> None:
        self.__dict__.update(d)


class _BlobReader(io.RawIOBase):
    def __init__(self, chunks: Iterator[tuple[int, str, bytes]]) -> None:
        self._chunks = chunks
        self._buf = b""

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        while not self._buf:
            nxt = next(self._chunks, None)
            if nxt is None:
                return 0
            self._buf = nxt[2]
        n = min(len(b), len(self._buf))
        b[:n] = self._buf[:n]
        self._buf = self._buf[n:]
        return n


class ArchivedFiles:
    """app.archive.api.SessionFiles of an archived session."""

    def __init__(self, archive: SqlArchive, uuid: str, folder_name: str, files: list[FileInfo]) -> None:
        self._archive = archive
        self.uuid = uuid
        self.folder_name = folder_name
        self._files = {f.name: f for f in files}

    def files(self) -> list[FileInfo]:
        return list(self._files.values())

    def _info(self, name: str) -> FileInfo:
        try:
            return self._files[name]
        except KeyError:
            raise NotFound(f"The archived session {self.uuid} has no file {name}.") from None

    def open(self, name: str) -> IO[bytes]:
        return io.BufferedReader(_BlobReader(self._archive._chunks(self._info(name).sha256)), CHUNK_BYTES)

    def read_bytes(self, name: str) -> bytes:
        with self.open(name) as fh:
            return fh.read()

    def materialise(self, folder: Path, progress: Progress | None = None) -> Path:
        folder = Path(folder)
        total = max(1, sum(f.size for f in self._files.values()))
        done = 0
        paths.private_dir(folder)
        if any(folder.iterdir()):
            raise ArchiveError(f"{folder} is not empty: an archived session is written into an empty folder")
        for info in self._files.values():
            target = folder / info.name
            if target.resolve().parent not in (folder.resolve(), (folder / "streams").resolve()):
                raise ArchiveError(f"the archived file name {info.name!r} is not a session file; not written")
            paths.private_dir(target.parent)
            digest = hashlib.sha256()
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, paths.PRIVATE_FILE_MODE)
            with open(fd, "wb") as out:
                for _seq, _sha, data in self._archive._chunks(info.sha256):
                    digest.update(data)
                    out.write(data)
                    done += len(data)
                    if progress is not None and progress(done / total) is False:
                        raise _Cancelled("The copy of the archived session was cancelled.")
            if digest.hexdigest() != info.sha256:
                raise ArchiveError(f"The archived file {info.name} of session {self.uuid} does not match its SHA-256: "
                                   "run `linarmpp archive verify`")
        return folder


__all__ = ["ARCHIVE_FILE", "ArchivedFiles", "SqlArchive", "Upgraded", "backup_sqlite", "canonical", "chain_hash",
           "default_url", "genesis", "make_engine", "open_archive", "profile_from_values", "profile_values",
           "upgrade_archive"]
