"""What the three exporters share: progress and cancel, the result they hand back, files written under a
temporary name and moved into place only once read back, and the session's clock for every format.

The exporters are plain functions (no Qt, no threads of their own): ``progress(fraction, text)`` is called now and
then, ``cancel()`` is asked as often; a cancelled export raises :class:`ExportCancelled` and leaves nothing.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from app.core.outputs import remove_quietly  # noqa: F401  (the export's modules import it from here)

Progress = Callable[[float, str], object]
Cancel = Callable[[], bool]

PART_SUFFIX = ".part"
FILE_MODE = 0o600  # exports hold health data, as the session files do (docs/sessions.md, "Privacy")
DIR_MODE = 0o700


class ExportCancelled(Exception):
    """The export was cancelled: nothing of it was left behind."""


class ExportError(Exception):
    """The export could not be written; the message is a sentence for the user."""


@dataclass
class ExportResult:
    """What an export wrote (only files read back and found right), what the sessions lacked
    (``missing``: exit 3 on the command line) and what the format could not hold (``notes``)."""

    written: list[Path] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)

    def merge(self, other: ExportResult) -> None:
        self.written += other.written
        self.missing += other.missing
        self.notes += other.notes
        self.figures.update(other.figures)


class Steps:
    """Maps the work of an export (bytes of stream files read, passes over them) to one fraction."""

    def __init__(self, progress: Progress | None, cancel: Cancel | None, total: float) -> None:
        self.progress = progress
        self.cancel = cancel
        self.total = max(1.0, float(total))
        self.done = 0.0
        self.text = ""
        self._untrimmed = 0.0

    def check(self) -> None:
        if self.cancel is not None and self.cancel():
            raise ExportCancelled("export cancelled")

    def advance(self, amount: float, text: str | None = None) -> None:
        self.done += amount
        self._untrimmed += amount
        if self._untrimmed >= TRIM_EVERY and _trim is not None:
            self._untrimmed = 0.0
            _trim(0)
        if text is not None:
            self.text = text
        self.check()
        if self.progress is not None:
            self.progress(min(1.0, self.done / self.total), self.text)


class HashingWriter:
    """A binary file written through a digest: what was handed to it can be compared with what is read back."""

    def __init__(self, fh: IO[bytes]) -> None:
        self.fh = fh
        self.digest = hashlib.blake2b(digest_size=20)
        self.size = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self.digest.update(data)
        self.size += len(data)
        return self.fh.write(data)

    def tell(self) -> int:
        return self.size

    def flush(self) -> None:
        self.fh.flush()


def file_digest(path: Path, block: int = 1 << 20) -> tuple[str, int]:
    digest = hashlib.blake2b(digest_size=20)
    size = 0
    with open(path, "rb") as fh:
        while data := fh.read(block):
            digest.update(data)
            size += len(data)
    return digest.hexdigest(), size


def part_path(path: Path) -> Path:
    return path.with_name(f".{path.name}{PART_SUFFIX}")


def open_private(path: Path) -> IO[bytes]:
    """A new file, 0600 whatever the umask (exports hold health data)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, FILE_MODE)
        return open(fd, "wb")
    except BaseException:
        os.close(fd)
        raise


def fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


TRIM_EVERY = 16 << 20  # work (bytes of the session read) between two returns of freed memory to the system
_trim: Callable[[int], int] | None = None  # glibc's malloc_trim, once release_memory_promptly() found it


def release_memory_promptly() -> None:
    """Freed memory back to the system as the export goes: glibc's ``malloc_trim`` every :data:`TRIM_EVERY` of
    work (:meth:`Steps.advance`).

    An export reads and frees a block of arrays per stream, over and over; glibc serves those blocks from a heap that
    fragments, and the process's resident memory crept up with the session's length (12 -> 48 minutes: 37 -> 51 MB
    for the same blocks). Stage 1 made every allocation above 256 KiB a mapping of its own (a fixed mmap threshold):
    that stopped the creep but made each block's pages fresh ones, faulted in and zeroed by the kernel — a BIDS
    export of two hours spent ~3 s more CPU on it (27.3 s against 24.5 s without), and the setting stayed with the
    worker process for every later task. Trimming now and then returns the same memory (two-hour BIDS: peak growth
    97 MB against 91 MB, 23.5 s of CPU). Called once by the command line and by the export's worker task; a no-op
    where there is no glibc."""
    import ctypes
    import sys

    global _trim
    if not sys.platform.startswith("linux"):
        return
    try:
        _trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        _trim = None
