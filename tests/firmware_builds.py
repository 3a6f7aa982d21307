"""The firmware's builds for the tests, made once and shared (issue #38): by the test modules of one run, by the
pytest-xdist workers of one run, and by later runs.

Each build goes into ``firmware/build/cache/<name>-<digest>``, the digest being a hash of what the build
depends on: the firmware's sources (firmware/host, firmware/linarm_controller, firmware/tools), the Python
table the protocol header is generated and checked from (app/wire/linarm_protocol.py, linarm_constants.py,
cmdmessenger.py), the toolchain file, the tools' identity (path, size, date) and the Python that runs the
generator. A change to any of them is a new folder; an unchanged tree reuses the old one without even running
CMake. Workers (processes) and runs agree through a file lock per folder: the first to need a build makes it,
the others wait for it and find it done.

Only the targets a test asks for are built (``ensure(BUILD, "linarm_sil")`` builds the SIL and its libraries,
not the unit tests); each target built has its stamp. The stable paths the application and the developers know
(``firmware/build/pytest``, ``pytest-arm``, ``pytest-due``; app/devices/sim/host.py looks there for the SIL and
the MPS2 image) are symbolic links to the folder of the current sources.

CI starts from a clean clone: everything is built once, by the first worker that needs it.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIRMWARE = ROOT / "firmware"
CACHE = FIRMWARE / "build" / "cache"
HOST_DIR = FIRMWARE / "host"
BUILD_TIMEOUT_S = 600
KEEP_PER_BUILD = 3  # older folders of the same build are removed (least recently used first)

# What every build depends on besides its own CMake folder (the header check runs the Python generator).
SOURCE_TREES = (FIRMWARE / "host", FIRMWARE / "linarm_controller", FIRMWARE / "tools")
TABLE_FILES = tuple(ROOT / "app" / "wire" / f for f in ("linarm_protocol.py", "linarm_constants.py",
                                                       "cmdmessenger.py"))


@dataclass(frozen=True)
class Build:
    """One CMake build of the firmware."""

    name: str  # host | arm | due
    source: Path  # the CMake source folder
    toolchain: Path | None  # the cross toolchain file, None for the host's compiler
    tools: tuple[str, ...]  # the programs it needs (their identity is part of the digest)
    link: Path  # the stable path (a symbolic link to the current folder)
    cmake_args: tuple[str, ...] = ()


HOST = Build("host", HOST_DIR, None, ("cmake", "make", "g++"), FIRMWARE / "build" / "pytest",
             ("-DCMAKE_BUILD_TYPE=Release",))
ARM = Build("arm", HOST_DIR, HOST_DIR / "cmake" / "arm-linux-gnueabihf.cmake",
            ("cmake", "make", "arm-linux-gnueabihf-g++"), FIRMWARE / "build" / "pytest-arm")
DUE = Build("due", HOST_DIR / "due", HOST_DIR / "cmake" / "arm-none-eabi-cortex-m3.cmake",
            ("cmake", "make", "arm-none-eabi-gcc", "arm-none-eabi-g++"), FIRMWARE / "build" / "pytest-due")


class BuildFailed(RuntimeError):
    pass


def _files(tree: Path) -> Iterator[Path]:
    for path in sorted(tree.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            yield path


def digest(build: Build) -> str:
    """The hash of everything ``build`` depends on (16 hex digits)."""
    h = hashlib.sha256()
    h.update(f"{build.name}\n{build.source.relative_to(ROOT)}\n{build.cmake_args}\n{sys.executable}\n".encode())
    for path in [*(p for tree in SOURCE_TREES for p in _files(tree)), *TABLE_FILES,
                 *([build.toolchain] if build.toolchain else [])]:
        h.update(str(path.relative_to(ROOT)).encode() + b"\0" + path.read_bytes() + b"\0")
    for tool in build.tools:
        found = shutil.which(tool)
        if found:
            st = os.stat(found)
            h.update(f"{tool}={found}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes, also when this process dies
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _run(cmd: list[str], niceness: int = 0) -> None:
    if niceness:
        cmd = ["nice", "-n", str(niceness), *cmd]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    if result.returncode != 0:
        raise BuildFailed(f"{' '.join(cmd)} failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}")


def _point_link(link: Path, folder: Path) -> None:
    """``link`` → ``folder`` (atomically; a folder left at ``link`` by an older version of the suite goes)."""
    if link.is_symlink() and Path(os.readlink(link)) == folder:
        return
    if link.exists() and not link.is_symlink():
        shutil.rmtree(link)
    tmp = link.with_name(f".{link.name}.{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    tmp.symlink_to(folder)
    os.replace(tmp, link)


def _prune(build: Build, keep: Path) -> None:
    """Remove the least recently used folders of ``build`` beyond KEEP_PER_BUILD (never one being built)."""
    folders = sorted((p for p in CACHE.glob(f"{build.name}-*") if p.is_dir()),
                     key=lambda p: p.stat().st_mtime, reverse=True)
    for old in [p for p in folders if p != keep][KEEP_PER_BUILD - 1:]:
        lock = old.with_suffix(".lock")
        with open(lock, "a+b") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # another run is using it
            shutil.rmtree(old, ignore_errors=True)
        lock.unlink(missing_ok=True)


def ensure(build: Build, *targets: str, niceness: int = 0) -> Path:
    """The folder of ``build`` for the current sources with ``targets`` built in it (all targets when none is
    named); builds what is missing, under the folder's lock. Raises BuildFailed with CMake's output."""
    folder = CACHE / f"{build.name}-{digest(build)}"
    wanted = targets or ("all",)
    with _locked(folder.with_suffix(".lock")):
        done = (folder / ".built-all").exists()
        missing = [] if done else [t for t in wanted if not (folder / f".built-{t}").exists()]
        if missing:
            t0 = time.monotonic()
            if not (folder / "CMakeCache.txt").exists():
                cmd = ["cmake", "-S", str(build.source), "-B", str(folder), f"-DLINARM_PYTHON={sys.executable}",
                       *build.cmake_args]
                if build.toolchain is not None:
                    cmd.append(f"-DCMAKE_TOOLCHAIN_FILE={build.toolchain}")
                _run(cmd, niceness)
            _run(["cmake", "--build", str(folder), "-j", "2", "--target", *missing], niceness)
            for t in missing:
                (folder / f".built-{t}").write_text(f"{time.monotonic() - t0:.1f} s\n", encoding="utf-8")
        os.utime(folder)  # most recently used
        with _locked(CACHE / "links.lock"):
            _point_link(build.link, folder)
        _prune(build, folder)
    return folder


# What the test modules ask for (tests/test_firmware*.py, test_sim_host.py): built ahead by prebuild().
AHEAD: tuple[tuple[Build, tuple[str, ...]], ...] = (
    (HOST, ()),  # all: the unit tests, the SIL, the DUE sketch's check
    (DUE, ("linarm_due.elf", "linarm_mps2.elf")),
    (ARM, ("linarm_unit_tests", "linarm_sil")),
)


def prebuild() -> threading.Thread:
    """Make the builds the suite needs in a background thread, niced (the pytest-xdist controller starts it while
    its workers start and collect): a worker that needs one then finds it made, or waits on its lock, and no
    build competes at full priority with the real-time tests. A build whose tools are missing or that fails is
    left to the tests, which skip or fail with the reason."""

    def run() -> None:
        for build, targets in AHEAD:
            if all(shutil.which(tool) for tool in build.tools):
                with contextlib.suppress(BuildFailed, OSError, subprocess.SubprocessError):
                    ensure(build, *targets, niceness=10)

    thread = threading.Thread(target=run, name="firmware prebuild", daemon=True)
    thread.start()
    return thread
