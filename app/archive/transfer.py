"""Existing data into the archive and profiles back out (``linarmpp archive import`` / ``export``).

Import takes a ``<data>`` folder as today's version leaves it — ``patients/*.yaml`` and
``sessions/<patient>/<stamp>/`` (complete, failed and interrupted sessions alike) — without loss: every profile
field (``created`` and ``updated`` kept), every file of every session byte for byte. It can be run again: a
patient already archived with the same profile and a session already archived are skipped; a patient archived
with a different profile is not overwritten (said in the report). Export writes each profile as the YAML
``app.therapy.patients.load_patient`` reads, so a round trip gives back the same profile.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from app.archive.api import Archive, ArchiveError, NotFound
from app.archive.folders import session_folders
from app.therapy.patients import list_patients, patient_file, profile_to_yaml


@dataclass
class ImportReport:
    patients_added: list[str] = field(default_factory=list)
    patients_same: list[str] = field(default_factory=list)
    patients_kept: list[str] = field(default_factory=list)  # archived with other values: not overwritten
    sessions_added: list[str] = field(default_factory=list)
    sessions_same: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)  # "<file or folder>: why"

    def lines(self) -> list[str]:
        out = [f"patients: {len(self.patients_added)} added, {len(self.patients_same)} already archived",
               f"sessions: {len(self.sessions_added)} added, {len(self.sessions_same)} already archived"]
        out += [f"patient {p} is archived with other values: not overwritten (export it to compare)"
                for p in self.patients_kept]
        out += [f"not imported: {f}" for f in self.failed]
        return out


def import_data_folder(archive: Archive, data: Path, operator: str = "import",
                       log: Callable[[str], None] | None = None) -> ImportReport:
    data = Path(data)
    if not (data / "patients").is_dir() and not (data / "sessions").is_dir():
        raise ArchiveError(f"{data} is not a LINarm++ data folder (it has neither patients/ nor sessions/)")
    report = ImportReport()
    if (data / "patients").is_dir():
        import_patients(archive, data / "patients", report, operator)
    for folder in session_folders(data / "sessions"):
        try:
            result = archive.upload_session(folder)
        except ArchiveError as exc:
            report.failed.append(f"{folder}: {exc}")
            continue
        (report.sessions_added if result.outcome == "uploaded" else report.sessions_same).append(str(folder))
        if log is not None:
            log(f"{folder}: {result.outcome}")
    return report


def import_patients(archive: Archive, folder: Path, report: ImportReport, operator: str = "import") -> None:
    """The patient files of ``folder`` (``<data>/patients``) into the archive: a patient not archived yet is added
    (its ``created`` and ``updated`` kept), one archived with the same profile is skipped, one archived with other
    values is left as the archive holds it (named in ``report``)."""
    for entry in list_patients(folder):
        if entry.profile is None:
            report.failed.append(entry.error)
            continue
        try:
            current = archive.get_patient(entry.patient_id)
        except NotFound:
            archive.save_patient(entry.profile, expected_version=None, operator=operator, reason="import")
            report.patients_added.append(entry.patient_id)
            continue
        (report.patients_same if current.profile == entry.profile else report.patients_kept).append(entry.patient_id)


def export_profiles(archive: Archive, out: Path, patient_ids: Iterable[str] | None = None) -> list[Path]:
    """Write each patient's profile as ``<out>/<id>.yaml`` (atomically; an existing file is replaced)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True, mode=0o700)
    ids = list(patient_ids) if patient_ids is not None else [p.patient_id for p in _all_patients(archive)]
    written = []
    for pid in ids:
        profile = archive.get_patient(pid).profile
        path = patient_file(pid, out)
        fd, tmp = tempfile.mkstemp(prefix=f".{pid}-", suffix=".tmp", dir=out)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(profile_to_yaml(profile))
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        written.append(path)
    return written


def _all_patients(archive: Archive) -> list:
    out, offset = [], 0
    while page := archive.list_patients(limit=1000, offset=offset):
        out += page
        offset += len(page)
    return out
