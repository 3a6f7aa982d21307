"""The station's side of the archive: what of a session folder is uploaded, its UUID, and the "archived" marker.

Pure file work (no database, no Qt). The recorder's folder layout is docs/sessions.md's; the files kept are
``manifest.json``, ``events.jsonl``, ``streams/*.csv`` and ``recording-failed.txt`` when there is one. The
space reserve, temporary manifests and this module's own marker are not part of the session.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid as _uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.session.recording import CLOCK_FILE, EVENTS_FILE, FAILED_FILE, FILE_MODE, MANIFEST_FILE, STREAMS_DIR

ARCHIVED_MARKER = ".archived"  # written in the session folder once the archive has committed it
REFUSED_MARKER = ".archive-refused"  # the archive refused it (another session holds its UUID): kept, said loudly
# Derived UUIDs of sessions recorded before the recorder wrote one: a fixed namespace, so the same folder
# always gets the same UUID (on every station, at every import).
LEGACY_NAMESPACE = _uuid.UUID("5b0c4f3e-7a4e-4d1c-9a51-2f0d6c1e3a39")
HASH_CHUNK = 1 << 20


@dataclass(frozen=True)
class FolderFile:
    name: str  # relative, with '/'
    path: Path
    size: int
    sha256: str


def read_manifest(folder: Path) -> dict[str, Any]:
    """The manifest as a dict ({} when missing or unreadable: the loaders say why)."""
    try:
        data = json.loads((folder / MANIFEST_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return {}
    return data if isinstance(data, dict) else {}


def session_files(folder: Path) -> list[FolderFile]:
    """The files that make the session, hashed (SHA-256), in a stable order. Only regular files of the folder
    itself and of its streams folder: never a link out of it."""
    names: list[Path] = []
    for name in (MANIFEST_FILE, EVENTS_FILE, FAILED_FILE, CLOCK_FILE):
        if (folder / name).is_file() and not (folder / name).is_symlink():
            names.append(folder / name)
    streams = folder / STREAMS_DIR
    if streams.is_dir() and not streams.is_symlink():
        names += sorted(p for p in streams.iterdir() if p.suffix == ".csv" and p.is_file() and not p.is_symlink())
    out = []
    for path in names:
        digest = hashlib.sha256()
        size = 0
        with open(path, "rb") as fh:
            while chunk := fh.read(HASH_CHUNK):
                digest.update(chunk)
                size += len(chunk)
        out.append(FolderFile(path.relative_to(folder).as_posix(), path, size, digest.hexdigest()))
    return out


def content_digest(files: list[tuple[str, str]]) -> str:
    """One hash of a session's files: SHA-256 over the sorted (name, sha256) pairs. Two uploads with the same
    UUID are the same session exactly when this matches."""
    text = "\n".join(f"{name}\t{sha}" for name, sha in sorted(files))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def session_uuid(folder: Path, manifest: dict[str, Any] | None = None) -> str:
    """The session's UUID: the manifest's ``session_uuid`` (written by the recorder at the session's start), or
    for a session recorded before that one derived from what identifies it for good — patient, start (wall and
    monotonic time) and the recording computer — so every import of the same folder gives the same UUID."""
    manifest = read_manifest(folder) if manifest is None else manifest
    given = manifest.get("session_uuid")
    if isinstance(given, str):
        try:
            return str(_uuid.UUID(given))
        except ValueError:
            pass
    start = manifest.get("start") if isinstance(manifest.get("start"), dict) else {}
    host = manifest.get("host") if isinstance(manifest.get("host"), dict) else {}
    if start:
        key = json.dumps(["session", manifest.get("patient_id", ""), start.get("t_wall", ""),
                          start.get("t_mono_s", ""), host.get("node", "")], default=str)
    else:  # no readable manifest: the folder's own name and its files' bytes
        key = json.dumps(["folder", folder.parent.name, folder.name,
                          content_digest([(f.name, f.sha256) for f in session_files(folder)])])
    return str(_uuid.uuid5(LEGACY_NAMESPACE, key))


def is_archived(folder: Path) -> bool:
    return (folder / ARCHIVED_MARKER).is_file()


def mark(folder: Path, marker: str, info: dict[str, Any]) -> None:
    """Write a marker file atomically (temp + fsync + rename) so a kill leaves it whole or absent."""
    path = folder / marker
    tmp = folder / f"{marker}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    try:
        with open(fd, "w", encoding="utf-8") as fh:
            json.dump(info, fh, indent=2, default=str)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def session_folders(root: Path) -> list[Path]:
    """Every session folder under a sessions root (``<root>/<patient>/<stamp>/manifest.json``), oldest first by
    folder name within each patient."""
    if not root.is_dir():
        return []
    out = []
    for patient in sorted(p for p in root.iterdir() if p.is_dir()):
        out += sorted(f for f in patient.iterdir() if f.is_dir() and (f / MANIFEST_FILE).is_file())
    return out


def wall_now() -> str:
    """Now, ISO 8601 with the UTC offset (seconds)."""
    import datetime as _dt

    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")
