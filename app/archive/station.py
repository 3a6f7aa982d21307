"""The station's archive in the running application (issue #39, stage 2), and the patient's record through it.

The application (the window and ``--headless``) opens the archive once at start-up with :func:`open_station`
(off the GUI thread: a clinic's server may take seconds to answer) and installs it here (:func:`install`). From
then on every reader and writer of patients goes through this module or through ``app.therapy.patients.load_patient`` /
``list_patients`` called without a folder, which read the installed archive:

* :func:`read_record` — the profile and the record's version (the session start, the forms);
* :func:`save_profile` — a versioned save of the whole profile (the Patients form) or of some fields (the plan
  dialog: ``["therapy_plan"]``); refused with :class:`~app.archive.api.StaleRecord` when a written field changed
  since ``expected_version``;
* :func:`choose_electrodes` — a running session's electrode choice: that district's field only, so a session's
  copy can never bring back a cap lowered since.

When the archive could not be reached at start-up, :func:`unreachable` says why and reads and saves raise
:class:`~app.archive.api.ArchiveUnavailable` (the station runs; patients cannot be saved). With nothing installed
(a library use of the code, most tests) the patients folder's YAML files are the store, as before the archive:
its versions are 0 (unchecked) and a save of some fields re-reads the file and replaces only those fields.

Qt-free: the window's start-up and the dialogs call these functions; nothing here imports PySide6.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from app.archive.api import (
    Archive,
    ArchiveError,
    ArchiveUnavailable,
    NotFound,
    PatientExists,
    PatientRecord,
    PatientUnreadable,
)
from app.archive.cache import PatientCache
from app.therapy.electrodes import SetupResult, choice_for
from app.therapy.patients import (
    ElectrodeChoice,
    PatientEntry,
    PatientError,
    PatientProfile,
    limit_problems,
    load_patient,
    patient_file,
    use_store,
    yaml_entries,
)
from app.therapy.patients import save_patient as save_yaml_patient

log = logging.getLogger(__name__)

_lock = threading.Lock()
_archive: Archive | None = None
_problem = ""  # why the archive could not be reached ('' when it is open or none is in use)
_down = ""  # why the open archive stopped answering, since the last read it failed ('' when it answers)
_since = ""  # when the archive was found unreachable (local ISO time; '' when it answers)
_cache: PatientCache | None = None  # the station's copies of the patients it read (app.archive.cache)
_opened_url = ""  # the archive open_station last tried (passwords hidden): whose copies stand in when it fails


def _cache_for(url: str) -> PatientCache | None:
    """The station's copies of ``url``'s records; none for the embedded archive (it lives in the same data folder
    as the copies would: when it cannot be read, neither can they) or when no archive is known."""
    from app.archive.cache import same_archive
    from app.archive.store import default_url

    if not url or same_archive(url, default_url()):
        return None
    return PatientCache(url)


# ---------------------------------------------------------------------------------------------- the station's archive
def install(archive: Archive | None, problem: str = "") -> None:
    """The application's archive from now on; ``archive=None`` with ``problem``: it is in use but could not be
    reached (the station runs; reading and saving patients say why). ``app.therapy.patients.load_patient`` and
    ``list_patients`` without a folder read it too."""
    global _archive, _problem, _down, _since, _cache
    with _lock:
        _archive, _problem = archive, ("" if archive is not None else problem)
        _down, _since = "", (_now() if _problem else "")
        _cache = _cache_for(archive.url if archive is not None else _opened_url if _problem else "")
        use_store(_StationStore() if in_use() else None)


def uninstall() -> Archive | None:
    """Back to no archive (the YAML folder); returns the archive that was installed (the caller closes it)."""
    global _archive, _problem, _down, _since, _cache, _opened_url
    with _lock:
        archive, _archive, _problem, _down, _since, _cache, _opened_url = _archive, None, "", "", "", None, ""
        use_store(None)
    return archive


def _now() -> str:
    import datetime as _dt

    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def offline_since() -> str:
    """When the station's archive was found unreachable (ISO time), '' when it answers or none is in use."""
    return _since if (_problem or _down) else ""


def offline_sentence() -> str:
    """The window's sentence while the archive cannot be reached and the station's copies stand in ('' else)."""
    why = _problem or _down
    if not why:
        return ""
    since = _since[:16].replace("T", " ")
    return (f"{_sentence(why).rstrip('.')}, since {since}. The patients are shown as this station last read them, "
            "read-only: nothing can be saved until the archive is back; a session can be run, without stimulation, and "
            "waits for the archive.")


def _remember(record: PatientRecord) -> None:
    """Keep the station's copy of a record read from (or saved to) the station's archive; the archive answered."""
    global _down, _since
    cache, archive = _cache, _archive
    if _down:
        _down, _since = "", ""
    if cache is not None and archive is not None:
        cache.put(record)


def _went_down(exc: ArchiveUnavailable) -> None:
    global _down, _since
    if not _down:
        _down, _since = str(exc), _now()


def _copy(patient_id: str) -> PatientRecord | None:
    cached = _cache.get(patient_id) if _cache is not None else None
    return cached.record if cached is not None else None


def copy_in_use(patient_id: str) -> str:
    """When this station read the copy that stands in for the patient's record now (the station's archive
    unreachable), '' when the archive's own record is read (or no copy is held)."""
    if not (_problem or _down):
        return ""
    return copy_seen_at(patient_id)


def copy_seen_at(patient_id: str) -> str:
    """When this station read its copy of the patient ('' when it holds none)."""
    cached = _cache.get(patient_id) if _cache is not None else None
    return cached.seen_at if cached is not None else ""


class _StationStore:
    """app.therapy.patients.PatientStore on the station's archive: the readers that name no folder follow it."""

    def load(self, patient_id: str, safety: Any) -> PatientProfile:
        where = f"archive: patient {patient_id}"
        try:
            record = read_record(patient_id, safety)
        except ArchiveError as exc:
            raise PatientError(where, None, "", str(exc)) from exc
        if record is None:
            raise PatientError(where, None, "patient_id", f"there is no patient {patient_id} in the archive")
        return record.profile

    def entries(self, safety: Any) -> list[PatientEntry]:
        try:
            return list_entries(safety)
        except ArchiveUnavailable as exc:  # the station's copies stand in (the Start-session dialog lists them)
            log.warning("patients cannot be listed: %s", exc)
            return [e for part in _copy_blocks(safety, 1000) for e in part]


def current() -> Archive | None:
    return _archive


def unreachable() -> str:
    """Why the station's archive cannot be used ('' when it is open, or when none is in use)."""
    return _problem


def in_use() -> bool:
    """Whether patients live in an archive (open or unreachable) rather than in the YAML folder."""
    return _archive is not None or bool(_problem)


@dataclass
class Opened:
    """What :func:`open_station` found: the archive (None when it cannot be reached, ``problem`` saying why) and
    the patients imported from the data folder's YAML files when the embedded archive was made just now."""

    archive: Archive | None
    problem: str = ""
    imported: list[str] = field(default_factory=list)
    import_problems: list[str] = field(default_factory=list)

    def message(self) -> str:
        """The sentence for the window or stderr ('' when all is well)."""
        if self.archive is None:
            return (f"{_sentence(self.problem)}. The station works, but patients cannot be opened or saved, nor "
                    "their sessions started, until the archive is back.")
        if self.import_problems:
            return ("Some patient files of this station could not be brought into the archive: "
                    + "; ".join(self.import_problems))
        return ""


def open_station(config: Any) -> Opened:
    """Open the configured archive (``config.archive``; nothing configured: the SQLite file in the data folder).
    An embedded archive made just now takes the data folder's existing patient files once (so nothing is lost
    for a station that had YAML patients). Raises ArchiveTooNew, NeedsUpgrade and ConfigProblem (refuse to
    start); an archive that cannot be reached is returned as ``Opened(None, why)``. Slow on a server: call it off
    the GUI thread."""
    # Alembic names its plugins when imported and says "Context impl SQLiteImpl." at each schema check: noise on
    # the console of every start
    logging.getLogger("alembic").setLevel(logging.WARNING)
    from app.archive.store import ARCHIVE_FILE, open_archive
    from app.core import paths

    global _opened_url
    url = getattr(getattr(config, "archive", None), "url", "") or ""
    embedded = not url
    try:
        from sqlalchemy.engine import make_url

        _opened_url = make_url(url).render_as_string(hide_password=True) if url else ""
    except Exception:  # open_archive says what is wrong with it
        _opened_url = ""
    fresh = embedded and not (paths.data_dir() / ARCHIVE_FILE).exists()
    try:
        archive = open_archive(config)
    except ArchiveUnavailable as exc:
        log.warning("archive: %s", exc)
        return Opened(None, str(exc))
    opened = Opened(archive)
    if fresh:
        opened.imported, opened.import_problems = import_yaml_patients(archive, paths.patients_dir())
    return opened


def import_yaml_patients(archive: Archive, folder: Path) -> tuple[list[str], list[str]]:
    """The patient files of ``folder`` into ``archive`` (once, by ``linarmpp archive import``'s rule: a patient
    already archived is left as it is). Returns (imported ids, problems in words)."""
    from app.archive.transfer import ImportReport, import_patients

    report = ImportReport()
    if folder.is_dir():
        import_patients(archive, folder, report)
    if report.patients_added:
        log.info("archive: %d patient file(s) of %s imported: %s", len(report.patients_added), folder,
                 ", ".join(report.patients_added))
    problems = report.failed + [f"patient {p} is archived with other values: its file was not imported"
                                for p in report.patients_kept]
    for p in problems:
        log.warning("archive import: %s", p)
    return report.patients_added, problems


# ---------------------------------------------------------------------------------------------- the patient's record
def _target(archive: Archive | None, folder: Path | None) -> Archive | None:
    """The archive to use, or None for the YAML folder; raises ArchiveUnavailable when the station's archive is in
    use but cannot be reached."""
    if archive is not None:
        return archive
    if folder is not None:
        return None
    if _archive is not None:
        return _archive
    if _problem:
        raise ArchiveUnavailable(_sentence(_problem))
    return None


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:]


# The field keys (app.archive.api.PATIENT_FIELDS) in the form's words, for messages.
FIELD_WORDS = {"full_name": "name", "birth_date": "date of birth", "record_number": "medical record no.",
               "affected_side": "affected side", "scores": "clinical scores", "assistance": "assistance gains",
               "fes.profile": "FES profile", "fes.caps": "FES caps", "robot": "robot limits", "notes": "notes",
               "therapy_plan": "therapy plan"}


def field_words(key: str) -> str:
    """``fes.caps`` -> "FES caps"; ``fes.electrodes.triceps`` -> "electrodes of the triceps"."""
    if key.startswith("fes.electrodes."):
        return f"electrodes of the {key[len('fes.electrodes.'):]}"
    return FIELD_WORDS.get(key, key)


def _check_limits(profile: PatientProfile, safety: Any, where: str) -> None:
    """A profile looser than the site's limits is refused as a file would be (app.therapy.patients.parse_profile)."""
    if safety is None:
        return
    problems = limit_problems(profile, safety)
    if problems:
        key, problem = problems[0]
        raise PatientError(where, None, key, problem)


def _yaml_record(profile: PatientProfile) -> PatientRecord:
    return PatientRecord(profile, 0, profile.updated, "", "")


def record_or_none(patient_id: str, *, archive: Archive | None = None,
                   folder: Path | None = None) -> PatientRecord | None:
    """The patient's record as it is now, for a form opening on it; None when it cannot be read (the form's save
    then says why, in its words)."""
    try:
        return read_record(patient_id, archive=archive, folder=folder)
    except (ArchiveError, PatientError, OSError, ValueError):
        return None


def read_record(patient_id: str, safety: Any = None, *, archive: Archive | None = None,
                folder: Path | None = None) -> PatientRecord | None:
    """The patient's record (profile and version), or None when the patient has no profile. With ``safety`` a
    profile looser than the configuration is refused (PatientError). Raises ArchiveUnavailable."""
    own = archive is None and folder is None  # the station's archive: its copies stand in while it is unreachable
    try:
        target = _target(archive, folder)
        if target is None:
            if not patient_file(patient_id, folder).exists():
                return None
            return _yaml_record(load_patient(patient_id, safety, folder))
        record = target.get_patient(patient_id)
    except NotFound:
        return None
    except ArchiveUnavailable as exc:
        copy = _copy(patient_id) if own else None
        if copy is None:
            raise
        if _archive is not None:
            _went_down(exc)
        log.warning("patient %s: the station's copy of %s (%s)", patient_id, copy_seen_at(patient_id), exc)
        _check_limits(copy.profile, safety, f"this station's copy of patient {patient_id}")
        return copy
    _check_limits(record.profile, safety, f"archive: patient {patient_id}")
    if own:
        _remember(record)
    return record


def list_entries(safety: Any = None, *, archive: Archive | None = None, folder: Path | None = None
                 ) -> list[PatientEntry]:
    """Every patient as the Patients window lists them (with the version each was read at). A record that the
    configuration refuses is listed with its reason, never hidden. Raises ArchiveUnavailable. Slow for many
    patients (each profile is validated): a window calls :func:`entry_blocks` on a thread instead."""
    return [e for part in entry_blocks(safety, archive=archive, folder=folder, block=1000) for e in part]


ENTRY_BLOCK = 25  # patients per block of entry_blocks: ~0.1-0.3 s of validation, the window's rows in few turns


def entry_blocks(safety: Any = None, *, archive: Archive | None = None, folder: Path | None = None,
                 block: int = ENTRY_BLOCK) -> Iterator[list[PatientEntry]]:
    """Every patient as :func:`list_entries` lists them, in blocks of ``block`` as each is read and validated: the
    Patients window's loader thread hands each block to the window as it comes and stops between blocks when the
    window closes. The archive's rows are one snapshot (one transaction). Raises ArchiveUnavailable (at the first
    block: nothing was listed) and ArchiveError."""
    own = archive is None and folder is None
    try:
        target = _target(archive, folder)
        if target is None:
            yield from _yaml_blocks(folder, safety, block)
            return
        blocks = iter(target.patient_reads(block))
        first = next(blocks, None)  # the archive's snapshot is read here: unreachable raises before any block
    except ArchiveUnavailable as exc:
        if not own or _cache is None:
            raise
        if _archive is not None:
            _went_down(exc)
        yield from _copy_blocks(safety, block)
        raise ArchiveUnavailable(offline_sentence()) from exc
    for reads in _chain(first, blocks):
        out: list[PatientEntry] = []
        for read in reads:
            pid = read.patient_id if isinstance(read, PatientUnreadable) else read.profile.patient_id
            where = patient_file(pid) if _safe(pid) else Path(pid)
            if isinstance(read, PatientUnreadable):
                out.append(PatientEntry(pid, where, None, read.error, read.version))
                continue
            try:
                _check_limits(read.profile, safety, f"archive: patient {pid}")
            except PatientError as exc:
                out.append(PatientEntry(pid, where, None, str(exc), read.version))
                continue
            out.append(PatientEntry(pid, where, read.profile, "", read.version))
            if own:
                _remember(read)
        yield out


def _chain(first: Any, rest: Iterator[Any]) -> Iterator[Any]:
    if first is not None:
        yield first
        yield from rest


def _copy_blocks(safety: Any, block: int) -> Iterator[list[PatientEntry]]:
    """The station's copies as the Patients window's entries (checked against the site's limits as records are)."""
    copies = _cache.records() if _cache is not None else []
    for k in range(0, len(copies), max(1, block)):
        out: list[PatientEntry] = []
        for cached in copies[k:k + block]:
            r = cached.record
            pid = r.profile.patient_id
            try:
                _check_limits(r.profile, safety, f"this station's copy of patient {pid}")
            except PatientError as exc:
                out.append(PatientEntry(pid, patient_file(pid), None, str(exc), r.version))
                continue
            out.append(PatientEntry(pid, patient_file(pid), r.profile, "", r.version))
        yield out


def _yaml_blocks(folder: Path | None, safety: Any, block: int) -> Iterator[list[PatientEntry]]:
    """The patients folder's files in blocks (as app.therapy.patients.list_patients lists them, one file at a time)."""
    from app.core import paths

    where = folder or paths.patients_dir()
    files = sorted(where.glob("*.yaml"), key=lambda p: p.stem.lower()) if where.is_dir() else []
    for k in range(0, len(files), max(1, block)):
        out: list[PatientEntry] = []
        for path in files[k:k + block]:
            out += yaml_entries([path], where, safety)
        yield out


def _safe(patient_id: str) -> bool:
    try:
        patient_file(patient_id)
    except ValueError:
        return False
    return True


def save_profile(profile: PatientProfile, *, expected_version: int | None, operator: str,
                 fields: Iterable[str] | None = None, safety: Any = None, archive: Archive | None = None,
                 folder: Path | None = None, reason: str = "save") -> PatientRecord:
    """Save ``profile`` as of ``expected_version`` (None: a new patient; PatientExists when the id is taken).
    ``fields=None``: the whole profile (refused with StaleRecord when anything changed since); else only those
    field keys (app.archive.api.PATIENT_FIELDS), the others left as the archive holds them now. Checked against
    the configuration's limits first (PatientError), nothing written when refused."""
    keys = None if fields is None else list(fields)
    target = _target(archive, folder)
    if target is None:
        return _save_yaml(profile, expected_version, keys, safety, folder)
    if keys is None:
        _check_limits(profile, safety, f"patient {profile.patient_id}")
    record = target.save_patient(profile, expected_version=expected_version, operator=operator, fields=keys,
                                 reason=reason)
    if archive is None and folder is None:
        _remember(record)
    return record


def _save_yaml(profile: PatientProfile, expected_version: int | None, keys: list[str] | None, safety: Any,
               folder: Path | None) -> PatientRecord:
    """The YAML folder (no archive): no versions; a save of some fields re-reads the file and replaces only them."""
    exists = patient_file(profile.patient_id, folder).exists()
    if expected_version is None and exists:
        raise PatientExists(f"A patient {profile.patient_id!r} already exists.")
    if keys is not None and exists:
        current = load_patient(profile.patient_id, safety, folder)
        for key in keys:
            if key == "therapy_plan":
                current = replace(current, therapy_plan=profile.therapy_plan)
            elif key.startswith("fes.electrodes."):
                district = key[len("fes.electrodes."):]
                electrodes = dict(current.fes.electrodes)
                if district in profile.fes.electrodes:
                    electrodes[district] = profile.fes.electrodes[district]
                else:
                    electrodes.pop(district, None)
                current = replace(current, fes=replace(current.fes, electrodes=electrodes))
            else:
                raise ValueError(f"a save of the field {key!r} alone needs the archive")
        profile = current
    path = save_yaml_patient(profile, folder, safety)
    return _yaml_record(load_patient(profile.patient_id, None, path.parent))


def choose_electrodes(patient_id: str, district: str, choice: ElectrodeChoice | None, *, expected_version: int,
                      operator: str, archive: Archive | None = None, folder: Path | None = None,
                      safety: Any = None, fallback: PatientProfile | None = None) -> PatientRecord:
    """A running session's electrode choice for ``district``: only that field is written (onto the record as it is
    now: a cap lowered since the session's start stays lowered). ``fallback``: the session's profile, written
    whole when the YAML folder has no file for the patient yet."""
    target = _target(archive, folder)
    if target is not None:
        record = target.choose_electrodes(patient_id, district, choice, expected_version=expected_version,
                                          operator=operator)
        if archive is None and folder is None:
            _remember(record)
        return record
    if patient_file(patient_id, folder).exists():
        profile = load_patient(patient_id, safety, folder)
    elif fallback is not None:
        profile = fallback
    else:
        raise PatientError(str(patient_file(patient_id, folder)), None, "patient_id",
                           f"patient {patient_id} has no profile")
    electrodes = dict(profile.fes.electrodes)
    if choice is None:
        electrodes.pop(district, None)
    else:
        electrodes[district] = choice
    profile = replace(profile, fes=replace(profile.fes, electrodes=electrodes))
    path = save_yaml_patient(profile, folder, safety)
    return _yaml_record(load_patient(patient_id, None, path.parent))


def default_operator(operator: str = "") -> str:
    """Who a save is recorded as: the operator given, else the computer's login name (said as such)."""
    if operator.strip():
        return operator.strip()
    import getpass

    try:
        return f"{getpass.getuser()} (login)"
    except Exception:
        return "unknown (login)"





def save_choice(result: SetupResult, channel: int, profile: Any, operator: str, session: str = "",
                safety: Any = None, folder: Any = None, expected_version: int = 0) -> Any:
    """Choose ``channel`` for the result's district (an electrode set-up's result, app.therapy.electrodes) in the
    patient's profile (app.therapy.patients.PatientProfile) and return the new profile (:func:`save_choice_record`
    without the version)."""
    return save_choice_record(result, channel, profile, operator, session, safety, folder, expected_version).profile


def save_choice_record(result: SetupResult, channel: int, profile: Any, operator: str, session: str = "",
                       safety: Any = None, folder: Any = None, expected_version: int = 0) -> Any:
    """Save the choice of ``channel`` for the result's district — that district's field only, through the station's
    archive (app.archive.station.choose_electrodes) as of ``expected_version`` (the session's record), or into the
    YAML file without an archive — and return the patient's record as it is now (app.archive.api.PatientRecord).
    The rest of the record is the archive's, never ``profile``'s: a copy taken at the session's start must not
    bring back a cap lowered since (issues #36, #39). ``profile`` stands for the record only when there is no
    YAML file yet. A choice of the same district made meanwhile by someone else refuses it (StaleRecord)."""
    choice = choice_for(result, channel, operator, session)
    return choose_electrodes(profile.patient_id, result.district.name, choice,
                             expected_version=expected_version, operator=default_operator(operator),
                             folder=folder, safety=safety, fallback=profile)


__all__ = [
    "FIELD_WORDS",
    "Opened",
    "choose_electrodes",
    "copy_seen_at",
    "current",
    "default_operator",
    "entry_blocks",
    "field_words",
    "import_yaml_patients",
    "in_use",
    "install",
    "list_entries",
    "offline_sentence",
    "offline_since",
    "open_station",
    "read_record",
    "save_choice",
    "save_choice_record",
    "save_profile",
    "uninstall",
    "unreachable",
]
