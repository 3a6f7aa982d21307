"""The archive's tables as typed SQLAlchemy 2 models (docs/archive.md, "What is stored where").

JSON is kept as canonical text (``Text``), not as a JSON/JSONB type: the hash chains cover exactly the stored
text, identical on SQLite and PostgreSQL. The migrations in ``app/archive/migrations`` create these tables;
``tests/test_archive.py`` checks that the migrated schema and these models agree.
"""

from __future__ import annotations

from sqlalchemy import BigInteger, Boolean, Float, ForeignKey, Index, Integer, LargeBinary, String, Text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

HASH = 64  # hex SHA-256
ISO = 40  # an ISO time with zone
UUID_LEN = 36
PATIENT_ID = 64  # app.therapy.patients: letters, digits, '-', '_' (at most 64)


class Base(DeclarativeBase):
    pass


class Patient(Base):
    __tablename__ = "patients"

    patient_id: Mapped[str] = mapped_column(String(PATIENT_ID), primary_key=True)
    version: Mapped[int] = mapped_column(Integer)
    full_name: Mapped[str] = mapped_column(Text, default="")
    birth_date: Mapped[str] = mapped_column(String(10), default="")
    record_number: Mapped[str] = mapped_column(Text, default="")
    affected_side: Mapped[str] = mapped_column(String(16), default="unknown")
    notes: Mapped[str] = mapped_column(Text, default="")
    fes_profile: Mapped[str] = mapped_column(Text, default="")
    scores: Mapped[str] = mapped_column(Text, default="{}")  # JSON text
    assistance: Mapped[str] = mapped_column(Text, default="{}")
    robot: Mapped[str] = mapped_column(Text, default="{}")
    fes_caps: Mapped[str] = mapped_column(Text, default="{}")
    search_text: Mapped[str] = mapped_column(Text, default="")  # lower-case id, name, record number, notes
    created: Mapped[str] = mapped_column(String(ISO), default="")
    updated: Mapped[str] = mapped_column(String(ISO), default="")
    changed_at: Mapped[str] = mapped_column(String(ISO), default="")
    changed_by: Mapped[str] = mapped_column(Text, default="")
    changed_station: Mapped[str] = mapped_column(Text, default="")


class PlanStep(Base):
    __tablename__ = "plan_steps"

    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.patient_id"), primary_key=True)
    position: Mapped[int] = mapped_column(Integer, primary_key=True)
    exercise: Mapped[str] = mapped_column(Text)
    params: Mapped[str] = mapped_column(Text)  # JSON text
    note: Mapped[str] = mapped_column(Text, default="")


class ElectrodeChoiceRow(Base):
    """Every choice ever made (append-only); a district's current one is its newest row."""

    __tablename__ = "electrode_choices"
    __table_args__ = (Index("ix_electrode_choices_patient", "patient_id", "district"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.patient_id"))
    district: Mapped[str] = mapped_column(Text)
    patient_version: Mapped[int] = mapped_column(Integer)
    cleared: Mapped[bool] = mapped_column(Boolean, default=False)
    choice: Mapped[str] = mapped_column(Text, default="{}")  # app.therapy.patients.ElectrodeChoice as JSON text
    channel: Mapped[int | None] = mapped_column(Integer, nullable=True)
    electrodes: Mapped[str] = mapped_column(Text, default="")
    chosen_at: Mapped[str] = mapped_column(String(ISO), default="")
    chosen_by: Mapped[str] = mapped_column(Text, default="")
    session: Mapped[str] = mapped_column(Text, default="")


class PatientHistory(Base):
    """One row per save of a patient: append-only, hash-chained per patient."""

    __tablename__ = "patient_history"

    patient_id: Mapped[str] = mapped_column(String(PATIENT_ID), primary_key=True)
    version: Mapped[int] = mapped_column(Integer, primary_key=True)
    fields: Mapped[str] = mapped_column(Text)  # JSON list of field keys
    values: Mapped[str] = mapped_column(Text)  # canonical JSON {key: value}
    changed_by: Mapped[str] = mapped_column(Text)
    changed_station: Mapped[str] = mapped_column(Text)
    changed_at: Mapped[str] = mapped_column(String(ISO))
    reason: Mapped[str] = mapped_column(Text)
    prev_hash: Mapped[str] = mapped_column(String(HASH))
    hash: Mapped[str] = mapped_column(String(HASH))


class SessionRow(Base):
    __tablename__ = "sessions"
    __table_args__ = (Index("ix_sessions_patient_start", "patient_id", "start_epoch_s"),
                      Index("ix_sessions_start", "start_epoch_s"))

    uuid: Mapped[str] = mapped_column(String(UUID_LEN), primary_key=True)
    patient_id: Mapped[str] = mapped_column(String(PATIENT_ID))
    station: Mapped[str] = mapped_column(Text, default="")
    operator: Mapped[str] = mapped_column(Text, default="")
    note: Mapped[str] = mapped_column(Text, default="")
    start_iso: Mapped[str] = mapped_column(String(ISO), default="")
    start_epoch_s: Mapped[float] = mapped_column(Float, default=0.0)
    end_iso: Mapped[str] = mapped_column(String(ISO), default="")
    duration_s: Mapped[float] = mapped_column(Float, default=0.0)
    status: Mapped[str] = mapped_column(String(16), default="")
    app_version: Mapped[str] = mapped_column(Text, default="")
    format_version: Mapped[int] = mapped_column(Integer, default=0)
    folder_name: Mapped[str] = mapped_column(Text, default="")
    manifest: Mapped[str] = mapped_column(Text)  # JSON text, as recorded
    exercises: Mapped[str] = mapped_column(Text, default="[]")  # JSON list of the runs' titles
    alarms: Mapped[int] = mapped_column(Integer, default=0)
    summary: Mapped[str] = mapped_column(Text, default="{}")  # app.session.metrics summary, JSON text
    problems: Mapped[str] = mapped_column(Text, default="[]")  # load_session's problems at upload
    content_digest: Mapped[str] = mapped_column(String(HASH))  # folders.content_digest of its files
    journal_head: Mapped[str] = mapped_column(String(HASH))
    journal_rows: Mapped[int] = mapped_column(Integer)
    archived_at: Mapped[str] = mapped_column(String(ISO), default="")
    archived_station: Mapped[str] = mapped_column(Text, default="")


class RunRow(Base):
    __tablename__ = "runs"

    session_uuid: Mapped[str] = mapped_column(ForeignKey("sessions.uuid"), primary_key=True)
    position: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[str] = mapped_column(Text)
    program: Mapped[str] = mapped_column(Text)  # JSON text
    title: Mapped[str] = mapped_column(Text, default="")
    parameters: Mapped[str] = mapped_column(Text, default="[]")
    source: Mapped[str] = mapped_column(Text, default="")
    operator: Mapped[str] = mapped_column(Text, default="")
    restart_of: Mapped[str | None] = mapped_column(Text, nullable=True)
    started_s: Mapped[float] = mapped_column(Float, default=0.0)
    ended_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    end_reason: Mapped[str | None] = mapped_column(Text, nullable=True)
    end_detail: Mapped[str] = mapped_column(Text, default="")
    summary: Mapped[str] = mapped_column(Text, default="{}")


class RepetitionRow(Base):
    __tablename__ = "repetitions"

    session_uuid: Mapped[str] = mapped_column(ForeignKey("sessions.uuid"), primary_key=True)
    run_position: Mapped[int] = mapped_column(Integer, primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True)  # within the run, from 1
    run_id: Mapped[str] = mapped_column(Text)
    metrics: Mapped[str] = mapped_column(Text)  # JSON text


class JournalRow(Base):
    """A session's events (events.jsonl), append-only and hash-chained per session."""

    __tablename__ = "journal"
    __table_args__ = (Index("ix_journal_kind", "session_uuid", "kind"),)

    session_uuid: Mapped[str] = mapped_column(ForeignKey("sessions.uuid"), primary_key=True)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    t_wall: Mapped[str] = mapped_column(Text, default="")
    t_mono: Mapped[float | None] = mapped_column(Float, nullable=True)
    kind: Mapped[str] = mapped_column(Text, default="")
    who: Mapped[str] = mapped_column(Text, default="")
    origin: Mapped[str] = mapped_column(Text, default="")
    data: Mapped[str] = mapped_column(Text, default="{}")  # canonical JSON text
    prev_hash: Mapped[str] = mapped_column(String(HASH))
    hash: Mapped[str] = mapped_column(String(HASH))


class Blob(Base):
    """A file's bytes, content-addressed by SHA-256 (stored once however many sessions hold it)."""

    __tablename__ = "blobs"

    sha256: Mapped[str] = mapped_column(String(HASH), primary_key=True)
    size: Mapped[int] = mapped_column(BigInteger)
    chunks: Mapped[int] = mapped_column(Integer)


class BlobChunk(Base):
    __tablename__ = "blob_chunks"

    sha256: Mapped[str] = mapped_column(ForeignKey("blobs.sha256"), primary_key=True)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    chunk_sha256: Mapped[str] = mapped_column(String(HASH))
    data: Mapped[bytes] = mapped_column(LargeBinary)


class SessionFile(Base):
    __tablename__ = "session_files"

    session_uuid: Mapped[str] = mapped_column(ForeignKey("sessions.uuid"), primary_key=True)
    name: Mapped[str] = mapped_column(Text, primary_key=True)
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(ForeignKey("blobs.sha256"))


class LedgerRow(Base):
    """One row per upload and per patient save, hash-chained across the archive: a session or a patient history
    removed whole, or a chain cut short, no longer matches the ledger."""

    __tablename__ = "ledger"

    seq: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    kind: Mapped[str] = mapped_column(String(16))  # "session" | "patient"
    key: Mapped[str] = mapped_column(Text)  # the session's UUID or the patient's id
    version: Mapped[int] = mapped_column(Integer)  # the patient's version (0 for a session)
    head: Mapped[str] = mapped_column(String(HASH))  # what the entry seals (see store.session_seal)
    at: Mapped[str] = mapped_column(String(ISO))
    station: Mapped[str] = mapped_column(Text)
    prev_hash: Mapped[str] = mapped_column(String(HASH))
    hash: Mapped[str] = mapped_column(String(HASH))


# Tables the application role only appends to (no UPDATE, no DELETE granted: docs/archive.md).
APPEND_ONLY = ("journal", "patient_history", "ledger", "electrode_choices", "sessions", "runs", "repetitions",
               "session_files", "blobs", "blob_chunks")
