"""Reading a file someone else named (a script, an exercise, a profile picked by path) without letting the
name push work onto the application.

A script runs in its own process, but ``fes.loadFile(path)`` makes the *application* open ``path``:
``/dev/zero`` would be read without end (4.6 GB in 10 s was measured), a named pipe would block the reading
thread forever, a directory or a 2 GB log would be read whole. :func:`read_user_file` opens only regular
files, refuses any larger than the caller's limit, and gives up after a timeout; :func:`read_user_text` also
refuses text that is not UTF-8 (naming the line of the bad byte). Every refusal is a :class:`UserFileError`
whose message is one plain sentence naming the file. This is the application's one reader of a file a user or
a script names: configuration, patient profiles, exercises, FES profiles, the patient model's tree
(app.core.yamlschema turns a refusal into its ConfigError, naming the file and line).
"""

from __future__ import annotations

import os
import stat
import threading
import time
from pathlib import Path

DEFAULT_MAX_BYTES = 1024 * 1024  # profiles and exercise files are a few KB; also the YAML loader's cap
DEFAULT_TIMEOUT_S = 2.0
_CHUNK = 64 * 1024


class UserFileError(OSError):
    """A file the application was asked to open is refused or could not be read (one plain sentence)."""

    def __init__(self, path: str | Path, problem: str, line: int | None = None) -> None:
        self.path = str(path)
        self.problem = problem
        self.line = line  # the line of the problem (a byte that is not UTF-8), when it has one
        super().__init__(str(self))

    def __str__(self) -> str:  # OSError's own str() would show "None" fields
        where = f"line {self.line}: " if self.line is not None else ""
        return f"{self.path}: {where}{self.problem}"


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _read_fd(fd: int, path: str, max_bytes: int, deadline: float) -> bytes:
    out = bytearray()
    while True:
        if time.monotonic() > deadline:
            raise UserFileError(path, "reading it took too long (refused)")
        try:
            chunk = os.read(fd, _CHUNK)
        except BlockingIOError:  # procfs files such as /proc/kmsg: nothing yet, and nothing to wait for
            time.sleep(0.01)
            continue
        if not chunk:
            return bytes(out)
        out += chunk
        if len(out) > max_bytes:  # a file whose size stat() did not tell (procfs, a file still growing)
            raise UserFileError(path, f"the file is larger than {max_bytes} bytes (refused)")


def read_user_file(path: str | Path, max_bytes: int = DEFAULT_MAX_BYTES,
                   timeout_s: float = DEFAULT_TIMEOUT_S) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``max_bytes``, read within ``timeout_s``.

    Raises :class:`UserFileError` (an ``OSError``) for anything else: a device, a named pipe, a folder, a
    socket, a file too large, a read that does not finish in time, or the usual open errors (missing,
    permission). The open never blocks (``O_NONBLOCK``: a named pipe without a writer would wait forever),
    the type and size are checked on the open descriptor (no swap between check and read), and the read runs
    on a short-lived thread so that a read stuck in the kernel (a hung network share) costs the caller only
    ``timeout_s``."""
    name = str(path)
    flags = (os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
             | getattr(os, "O_BINARY", 0))  # O_BINARY: Windows would otherwise translate line ends
    try:
        fd = os.open(name, flags)
    except FileNotFoundError as exc:
        raise UserFileError(name, "no such file") from exc
    except IsADirectoryError as exc:
        raise UserFileError(name, "a folder, not a file (refused)") from exc
    except PermissionError as exc:
        raise UserFileError(name, "permission denied") from exc
    except OSError as exc:
        raise UserFileError(name, f"cannot open it: {exc.strerror or exc}") from exc
    handed_over = False
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise UserFileError(name, f"{_kind(info.st_mode)}, not a regular file (refused)")
        if info.st_size > max_bytes:
            raise UserFileError(name, f"the file is {info.st_size} bytes, more than the {max_bytes} allowed "
                                      "(refused)")
        deadline = time.monotonic() + timeout_s
        result: list[bytes] = []
        error: list[BaseException] = []

        def read() -> None:
            try:
                result.append(_read_fd(fd, name, max_bytes, deadline))
            except BaseException as exc:  # handed to the caller
                error.append(exc)
            finally:
                os.close(fd)

        reader = threading.Thread(target=read, name="read-user-file", daemon=True)
        reader.start()
        handed_over = True
        reader.join(timeout_s + 0.1)
        if reader.is_alive():  # stuck inside one read(): the thread ends when it returns; the caller goes on
            raise UserFileError(name, "reading it took too long (refused)")
        if error:
            failure = error[0]
            if isinstance(failure, UserFileError):
                raise failure
            raise UserFileError(name, f"cannot read it: {getattr(failure, 'strerror', None) or failure}") from failure
        return result[0]
    finally:
        if not handed_over:
            os.close(fd)


def read_user_text(path: str | Path, max_bytes: int = DEFAULT_MAX_BYTES, timeout_s: float = DEFAULT_TIMEOUT_S,
                   encoding: str = "utf-8") -> str:
    """:func:`read_user_file` decoded; a file that is not valid ``encoding`` is a :class:`UserFileError`."""
    return decode_user_text(read_user_file(path, max_bytes, timeout_s), str(path), encoding)


def decode_user_text(data: bytes, name: str, encoding: str = "utf-8") -> str:
    """``data`` (a file's bytes, or what a script handed over as one) as text; UserFileError naming the line of
    the first byte that is not ``encoding``."""
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise UserFileError(name, f"not {encoding.upper()} text (byte 0x{data[exc.start]:02x} at offset "
                                  f"{exc.start})", line) from exc


def check_writable_target(path: str | Path) -> None:
    """Refuse to replace anything but a regular file (or nothing): saving over ``/dev/zero``, a pipe or a
    folder would replace a device node, hang or fail half-way (the application may run as root)."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise UserFileError(str(path), f"cannot check it: {exc.strerror or exc}") from exc
    if stat.S_ISLNK(info.st_mode):
        try:
            info = os.stat(path)
        except FileNotFoundError:
            return
    if not stat.S_ISREG(info.st_mode):
        raise UserFileError(str(path), f"{_kind(info.st_mode)}, not a regular file (refused)")
