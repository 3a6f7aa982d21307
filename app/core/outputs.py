"""A file is written only when it is right (issue #37): reports and exports are written under a temporary name in
their destination's folder, read back and checked, and only then renamed into place. A failure -- a full disk, a
read-only folder, a writer that reports success for a truncated file -- leaves nothing at the destination (and no
temporary behind), and reaches the user as one sentence (:class:`OutputError`), never as a traceback or a false
"written".

    pages = write_verified(dest, lambda tmp: draw_pdf(tmp), verify=verify_pdf)

The checks are the reader's: a PDF must parse (header, cross-reference, trailer, its pages counted), an HDF5 file
must reopen with every stream and event (app/session/export.py), a CSV folder must hold every file with every row.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")
PART_TAG = ".part-"  # the temporary's name: .<name>.part-<token> beside the destination


class OutputError(OSError):
    """An output could not be written (or not verified): ``str()`` is one plain sentence saying what and where;
    nothing was left at the destination."""

    def __init__(self, sentence: str, err: int = errno.EIO) -> None:
        super().__init__(err, sentence)
        self.sentence = sentence

    def __str__(self) -> str:
        return self.sentence


def temporary_for(dest: Path, token: str | None = None) -> Path:
    """The temporary name beside ``dest`` that a write goes to before it is verified."""
    return dest.with_name(f".{dest.name}{PART_TAG}{token or uuid.uuid4().hex[:12]}")


def temporaries_of(dest: Path) -> list[Path]:
    """Temporaries of ``dest`` left behind (a writer process that crashed before it could clean up)."""
    try:
        return [p for p in dest.parent.iterdir() if p.name.startswith(f".{dest.name}{PART_TAG}")]
    except OSError:
        return []


def remove_quietly(path: Path) -> None:
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass


class NotRight(ValueError):
    """A written output read back is not what was meant (``str()``: why, in words)."""


FULL_BELOW_BYTES = 1 << 20  # an output that fails its check with less than this free: the disk is full


def _space_left(folder: Path) -> float:
    try:
        return float(shutil.disk_usage(folder).free)
    except OSError:
        return float("inf")


def _cap(text: str) -> str:
    return text[:1].upper() + text[1:]


def why_not(exc: BaseException, dest: Path, what: str = "the file") -> str:
    """One sentence for a failed write of ``dest``: the disk is full, the folder is read-only, or the error."""
    if isinstance(exc, OutputError):
        return exc.sentence
    err = exc.errno if isinstance(exc, OSError) else None
    text = str(exc)
    head = f"{_cap(what)} {dest} was not written"
    if err == errno.ENOSPC or "No space left" in text or "errno = 28" in text:
        return f"{head}: the disk is full (no space left in {dest.parent})."
    if err == errno.EDQUOT:
        return f"{head}: the disk quota is used up."
    if err in (errno.EROFS, errno.EACCES, errno.EPERM) or "Read-only file system" in text or "errno = 30" in text \
            or "Permission denied" in text or "errno = 13" in text:
        return f"{head}: the folder {dest.parent} is read-only."
    if err == errno.ENOENT and not Path(dest.parent).is_dir():
        return f"{head}: the folder {dest.parent} does not exist."
    if isinstance(exc, NotRight):
        if _space_left(dest.parent) < FULL_BELOW_BYTES:  # a writer that did not say why: the disk filled up
            return f"{head}: the disk is full (no space left in {dest.parent})."
        return f"{head}: {text}; nothing was left there."
    detail = exc.strerror if isinstance(exc, OSError) and exc.strerror else (text or type(exc).__name__)
    return f"{head}: {detail}."


def check_destination(dest: Path, what: str = "the file") -> None:
    """Refuse at once (OutputError) a destination whose folder is missing or cannot be written, tried with a real
    file (permission bits say nothing of a read-only mount, or of root)."""
    folder = dest.parent
    if not folder.is_dir():
        raise OutputError(f"{_cap(what)} {dest} was not written: the folder {folder} does not exist.", errno.ENOENT)
    probe = temporary_for(dest, "probe")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
    except OSError as exc:
        raise OutputError(why_not(exc, dest, what), exc.errno or errno.EIO) from exc
    finally:
        try:
            os.unlink(probe)
        except OSError:
            pass


def _fsync_path(path: Path) -> None:
    """Flush a written file (or every file of a written folder, and the folder) to the disk: a full disk on a
    delayed allocation shows here, not after "written"."""
    if path.is_dir():
        for child in path.iterdir():
            _fsync_path(child)
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):  # a folder on some systems: not syncable
            raise
    finally:
        os.close(fd)


def write_verified(dest: str | Path, write: Callable[[Path], T], verify: Callable[[Path, T], Any] | None = None,
                   *, what: str = "the file", replace_folder: bool = False) -> T:
    """``write(tmp)`` to a temporary beside ``dest``, then ``verify(tmp, result)`` (raises when the output is not
    right), fsync, and rename into place; returns ``write``'s result. Any failure removes the temporary and raises
    :class:`OutputError` with one sentence. ``replace_folder``: ``dest`` is a folder and an existing one is
    replaced (moved aside, then removed once the new one is in place)."""
    dest = Path(dest)
    check_destination(dest, what)
    tmp = temporary_for(dest)
    try:
        result = write(tmp)
        if not tmp.exists():
            raise NotRight("the writer made no file")
        if verify is not None:
            verify(tmp, result)
        _fsync_path(tmp)
        if replace_folder and dest.exists():
            old = temporary_for(dest, "old")
            os.replace(dest, old)
            os.replace(tmp, dest)
            remove_quietly(old)
        else:
            os.replace(tmp, dest)
        fsync_dir(dest.parent)
    except OutputError:
        remove_quietly(tmp)
        raise
    except BaseException as exc:
        remove_quietly(tmp)
        if isinstance(exc, OSError | ValueError | RuntimeError):  # NotRight is a ValueError
            raise OutputError(why_not(exc, dest, what), getattr(exc, "errno", None) or errno.EIO) from exc
        raise
    return result


def fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX; Windows cannot open a directory and NTFS journals the rename)."""
    if os.name != "posix":
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------------------------- PDF
_PAGE = re.compile(rb"/Type\s*/Page(?![a-zA-Z])")


def pdf_page_count(path: Path) -> int:
    """The pages of a PDF, read back from the file (its page objects); raises ValueError when the file is not a
    whole PDF (no header, no end-of-file marker, no cross-reference, a cut-short file)."""
    data = Path(path).read_bytes()
    if not data.startswith(b"%PDF-"):
        raise ValueError("it is not a PDF (no %PDF header)")
    tail = data[-2048:]
    if b"%%EOF" not in tail:
        raise ValueError("the PDF is cut short (no end-of-file marker)")
    if b"startxref" not in tail or (b"trailer" not in data[-65536:] and b"/XRef" not in data):
        raise ValueError("the PDF has no cross-reference table")
    return len(_PAGE.findall(data))


def verify_pdf(path: Path, pages: int) -> None:
    """The PDF at ``path`` is whole and has the ``pages`` its writer drew (raises :class:`NotRight`)."""
    try:
        found = pdf_page_count(path)
    except ValueError as exc:
        raise NotRight(f"the PDF read back is not whole ({exc})") from exc
    if found != pages:
        raise NotRight(f"the PDF read back has {found} page(s) where {pages} were drawn (a truncated file)")
