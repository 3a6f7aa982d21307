"""Small disks for the tests of full and read-only folders (issue #37): a tmpfs of a few hundred KB, filled up, or
remounted read-only. They need root (``mount``), which the tests have here and in CI; without it a test skips on a
developer's machine and fails under ``CI=true`` (where skipping would hide the check)."""

from __future__ import annotations

import errno
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest


def require_mount() -> None:
    if os.geteuid() == 0:
        return
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail("this test mounts a small tmpfs and needs root: CI must run it, not skip it")
    pytest.skip("mounting a tmpfs needs root")


def _mount(path: Path, size_kib: int) -> None:
    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k,mode=0700", "tmpfs", str(path)], check=True)


def _umount(path: Path) -> None:
    if subprocess.run(["umount", str(path)], capture_output=True).returncode != 0:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)  # a file still open: detach it


def fill(path: Path, leave_bytes: int = 0) -> None:
    """Fill the disk holding ``path`` up, then free ``leave_bytes`` of it."""
    filler = path / ".filler"
    with open(filler, "wb") as fh:
        block = b"\0" * 65536
        while True:
            try:
                fh.write(block)
                fh.flush()
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                break
    with open(filler, "rb+") as fh:
        size = fh.seek(0, os.SEEK_END)
        fh.truncate(max(0, size - leave_bytes))


@contextmanager
def full_disk(path: Path, size_kib: int = 512, leave_bytes: int = 16 * 1024) -> Iterator[Path]:
    """A folder on a tmpfs of ``size_kib`` with only ``leave_bytes`` free."""
    require_mount()
    _mount(path, size_kib)
    try:
        fill(path, leave_bytes)
        yield path
    finally:
        _umount(path)


@contextmanager
def read_only(path: Path) -> Iterator[Path]:
    """An empty folder on a read-only mount (root ignores permission bits, not a read-only mount)."""
    require_mount()
    _mount(path, 64)
    try:
        subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True)
        yield path
    finally:
        _umount(path)


def entries(path: Path) -> list[str]:
    """What a test folder holds besides the filler."""
    return sorted(p.name for p in path.iterdir() if p.name != ".filler")
