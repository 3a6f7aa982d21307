"""``linarmpp archive verify``: re-hash every stored file and every chained row, and name what does not match.

Checked, in this order (the report's first problem is the first found):

1. every blob: each chunk against its own SHA-256, the whole against the blob's key and size;
2. every session: its files' digest against the session row, its journal chain row by row (each row's hash
   over its stored text, each ``prev_hash`` against the row before, the head and length against the session
   row), the ledger's seal;
3. every patient: the history chain, the versions 1..n without a gap, the patient row's version and its fields
   against the history replayed (a row changed without a save no longer matches);
4. the ledger's own chain, and that every session and every patient save has its ledger row.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from sqlalchemy import func, select

from app.archive import folders
from app.archive.api import Progress, VerifyProblem, VerifyReport
from app.archive.chain import chain_hash, genesis, history_parts, journal_parts, ledger_parts, session_seal
from app.archive.models import (
    Blob,
    JournalRow,
    LedgerRow,
    Patient,
    PatientHistory,
    SessionFile,
    SessionRow,
)


def verify_archive(archive: Any, progress: Progress | None = None) -> VerifyReport:
    report = VerifyReport()
    problems = report.problems
    with archive._read() as conn:
        blobs = conn.execute(select(Blob.sha256, Blob.size, Blob.chunks).order_by(Blob.sha256)).all()
        holders: dict[str, list[str]] = {}
        for uuid, name, sha in conn.execute(select(SessionFile.session_uuid, SessionFile.name, SessionFile.sha256)):
            holders.setdefault(sha, []).append(f"{name} of session {uuid}")
        total = sum(b.size for b in blobs) or 1
    done = 0
    for sha, size, n_chunks in blobs:
        where = "file " + (", ".join(sorted(holders.get(sha, []))) or f"(unreferenced blob {sha[:12]})")
        whole = hashlib.sha256()
        got = seq_expected = 0
        bad = False
        for seq, chunk_sha, data in archive._chunks(sha):
            if seq != seq_expected:
                break
            seq_expected += 1
            whole.update(data)
            got += len(data)
            if hashlib.sha256(data).hexdigest() != chunk_sha and not bad:
                problems.append(VerifyProblem(f"{where}, blob_chunks row (sha256={sha[:12]}…, seq={seq})",
                                              "its bytes do not match the chunk's SHA-256"))
                bad = True
        report.files += 1
        report.bytes += got
        done += size
        if not bad and (whole.hexdigest() != sha or got != size or seq_expected != n_chunks):
            problems.append(VerifyProblem(where, f"the stored bytes ({got} of {size}, {seq_expected} of {n_chunks} "
                                                 "chunks) do not match the file's SHA-256"))
        if progress is not None and progress(0.8 * done / total) is False:
            return report
    with archive._read() as conn:
        _verify_sessions(conn, report)
        _verify_patients(archive, conn, report)
        _verify_ledger(conn, report)
    if progress is not None:
        progress(1.0)
    return report


def _verify_sessions(conn: Any, report: VerifyReport) -> None:
    seals = {r.key: r.head for r in conn.execute(select(LedgerRow.key, LedgerRow.head)
                                                 .where(LedgerRow.kind == "session"))}
    for s in conn.execute(select(SessionRow.uuid, SessionRow.content_digest, SessionRow.journal_head,
                                 SessionRow.journal_rows).order_by(SessionRow.uuid)).all():
        files = conn.execute(select(SessionFile.name, SessionFile.sha256)
                             .where(SessionFile.session_uuid == s.uuid)).all()
        if folders.content_digest([(n, h) for n, h in files]) != s.content_digest:
            report.problems.append(VerifyProblem(f"session {s.uuid} session_files", "the list of its files or their "
                                                 "hashes does not match the digest it was archived with"))
        prev = genesis("journal", s.uuid)
        n = 0
        broken = False
        for r in conn.execute(select(JournalRow).where(JournalRow.session_uuid == s.uuid).order_by(JournalRow.seq)):
            n += 1
            where = f"session {s.uuid} journal row {r.seq} ({r.kind})"
            if r.seq != n:
                report.problems.append(VerifyProblem(where, f"row {n} is missing"))
                broken = True
                break
            if r.prev_hash != prev:
                report.problems.append(VerifyProblem(where, "its prev_hash is not the hash of the row before"))
                broken = True
                break
            if chain_hash(prev, journal_parts(s.uuid, r.seq, r.t_wall, r.t_mono, r.kind, r.who, r.origin,
                                              r.data)) != r.hash:
                report.problems.append(VerifyProblem(where, "its content does not match its hash"))
                broken = True
                break
            prev = r.hash
        report.rows += n
        if not broken and (n != s.journal_rows or prev != s.journal_head):
            report.problems.append(VerifyProblem(f"session {s.uuid} journal", f"{n} rows, the session was archived "
                                                 f"with {s.journal_rows}: rows were removed or added"))
        seal = seals.get(s.uuid)
        if seal is None:
            report.problems.append(VerifyProblem(f"session {s.uuid}", "it has no ledger row"))
        elif seal != session_seal(s.content_digest, s.journal_head, s.journal_rows):
            report.problems.append(VerifyProblem(f"session {s.uuid}", "its files' digest or journal head does not "
                                                 "match its ledger row"))


def _verify_patients(archive: Any, conn: Any, report: VerifyReport) -> None:
    seals = {(r.key, r.version): r.head for r in conn.execute(
        select(LedgerRow.key, LedgerRow.version, LedgerRow.head).where(LedgerRow.kind == "patient"))}
    for p in conn.execute(select(Patient).order_by(Patient.patient_id)).all():
        prev = genesis("patient", p.patient_id)
        replay: dict[str, Any] = {}
        n = 0
        broken = False
        for h in conn.execute(select(PatientHistory).where(PatientHistory.patient_id == p.patient_id)
                              .order_by(PatientHistory.version)):
            n += 1
            where = f"patient {p.patient_id} patient_history row version {h.version}"
            if h.version != n:
                report.problems.append(VerifyProblem(where, f"version {n} is missing"))
                broken = True
                break
            if h.prev_hash != prev or chain_hash(prev, history_parts(h)) != h.hash:
                report.problems.append(VerifyProblem(where, "its content does not match its hash" if h.prev_hash == prev
                                                     else "its prev_hash is not the hash of the row before"))
                broken = True
                break
            if seals.get((p.patient_id, h.version)) != h.hash:
                report.problems.append(VerifyProblem(where, "it does not match its ledger row"))
                broken = True
                break
            replay.update(json.loads(h.values))
            prev = h.hash
        report.rows += n
        if broken:
            continue
        if n != p.version:
            report.problems.append(VerifyProblem(f"patient {p.patient_id}", f"version {p.version} but {n} saves in "
                                                 "its history"))
            continue
        current = archive._values(conn, p)
        replay = {k: v for k, v in replay.items() if v is not None}
        if current != replay:
            keys = sorted(k for k in set(current) | set(replay) if current.get(k) != replay.get(k))
            report.problems.append(VerifyProblem(f"patient {p.patient_id} (patients row)", "its fields "
                                                 f"{', '.join(keys)} differ from its history: changed without a save"))


def _verify_ledger(conn: Any, report: VerifyReport) -> None:
    prev = genesis("ledger", "")
    n = 0
    for r in conn.execute(select(LedgerRow).order_by(LedgerRow.seq)):
        n += 1
        where = f"ledger row {r.seq} ({r.kind} {r.key})"
        if r.seq != n:
            report.problems.append(VerifyProblem(where, f"row {n} is missing"))
            return
        if r.prev_hash != prev or chain_hash(prev, ledger_parts(r)) != r.hash:
            report.problems.append(VerifyProblem(where, "its content does not match its hash"))
            return
        prev = r.hash
    report.rows += n
    sessions = conn.execute(select(func.count()).select_from(SessionRow)).scalar() or 0
    sealed = conn.execute(select(func.count()).select_from(LedgerRow)
                          .where(LedgerRow.kind == "session")).scalar() or 0
    if sealed != sessions:
        report.problems.append(VerifyProblem("ledger", f"{sealed} sessions sealed, {sessions} in the archive: a "
                                             "session was removed or added without the ledger"))

