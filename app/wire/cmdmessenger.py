"""CmdMessenger wire codec (pure: bytes in, frames out; no I/O, no Qt).

Three parts, all following /work/shared/reference/cmdmessenger.md:

* ``CmdMessengerDecoder``: the PC-side streaming receiver. A byte-level state machine that
  survives split reads, garbage, overlong frames and lost bytes, and never raises.
* ``encode_frame``: the PC-side sender. Typed fields, escaping of ``, ; /`` and NUL, no empty
  fields, floats as ``'.9g'`` text, and the Arduino's 62-byte receive limit enforced.
* An *Arduino-side model* of CmdMessenger 4.2.0 (``ArduinoReceiver`` / ``ArduinoMessage`` for the
  receiver, ``ArduinoSender`` and the ``print_*`` helpers for the sender). The simulator runs host
  bytes through it so that it shows the real firmware's quirks: the 62-byte buffer and its
  overflow, empty-field skipping, lenient ``atoi``/``strtod``, uint8 command-id truncation and
  garbage dispatched as command 0.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import StrEnum

FIELD_SEPARATOR = ord(",")
COMMAND_SEPARATOR = ord(";")
ESCAPE_CHARACTER = ord("/")
_SPECIAL = frozenset((FIELD_SEPARATOR, COMMAND_SEPARATOR, ESCAPE_CHARACTER, 0))
_LEADING_WHITESPACE = frozenset(b"\r\n ")

MESSENGER_BUFFER_SIZE = 64  # MESSENGERBUFFERSIZE of the Arduino library (4.2.0 default)
# Largest message the Arduino accepts, counted before the ';' and including every escape byte.
ARDUINO_MAX_MESSAGE = MESSENGER_BUFFER_SIZE - 2
MAX_CALLBACKS = 50  # MAXCALLBACKS: ids 0..49 reach attached callbacks, others the default one
DEFAULT_MAX_FRAME_LENGTH = 1024  # PC side: well above any legitimate controller frame


class CmdMessengerError(ValueError):
    """Base class of the codec's errors."""


class FrameTooLongError(CmdMessengerError):
    """An encoded frame would not fit the Arduino's receive buffer."""

    def __init__(self, length: int, limit: int) -> None:
        super().__init__(f"encoded frame is {length} bytes before ';', the Arduino accepts at most {limit}")
        self.length = length
        self.limit = limit


class FieldError(CmdMessengerError):
    """A received field does not parse as the expected type."""

    def __init__(self, message: str, flag: str | None = None) -> None:
        super().__init__(message)
        self.flag = flag  # 'nan', 'inf' or 'ovf' when the Arduino printed a special float value


class Kind(StrEnum):
    """Wire representation of one field. Text kinds are read with readXArg, binary with readBinArg<T>."""

    TEXT_INT = "int"  # signed decimal
    TEXT_FLOAT = "float"  # '.9g', no locale
    TEXT_BOOL = "bool"  # '1' / '0'
    TEXT_STR = "str"  # ASCII, escaped
    BIN_BOOL = "<?"  # one byte 0x01 / escaped 0x00
    BIN_UINT8 = "<B"
    BIN_INT16 = "<h"
    BIN_INT32 = "<i"  # also 'int' / 'long' on the DUE
    BIN_UINT32 = "<I"
    BIN_FLOAT = "<f"
    BIN_DOUBLE = "<d"  # 8 bytes on the DUE (4 on AVR)


BINARY_KINDS = frozenset(k for k in Kind if k.value.startswith("<"))
TEXT_KINDS = frozenset(k for k in Kind if not k.value.startswith("<"))


def binary_size(kind: Kind | str) -> int:
    """sizeof(T) on the Arduino DUE for a binary kind."""
    return struct.calcsize(Kind(kind).value)


def max_encoded_size(kind: Kind | str) -> int | None:
    """Worst-case escaped size of a binary field (every byte escaped); None for text kinds."""
    k = Kind(kind)
    return 2 * binary_size(k) if k in BINARY_KINDS else None


@dataclass(frozen=True, slots=True)
class Frame:
    """One received message: the command id and the unescaped fields after it."""

    cmd_id: int
    fields: tuple[bytes, ...]

    def __len__(self) -> int:
        return len(self.fields)


# ---------------------------------------------------------------------------------------------
# Escaping and encoding (PC -> Arduino, and the simulator's Arduino -> PC replies)
# ---------------------------------------------------------------------------------------------



def escape(data: bytes) -> bytes:
    """Put '/' before every ',' ';' '/' and NUL (printEsc). The escape itself first, so the ones put in are not
    escaped again; four C-level replaces instead of a regular expression's template (the simulated LINarm
    encodes some 3 000 fields a second)."""
    return (data.replace(b"/", b"//").replace(b",", b"/,").replace(b";", b"/;").replace(b"\x00", b"/\x00"))


def unescape(data: bytes) -> bytes:
    """Drop every '/' and keep the byte after it (the PC-side inverse of ``escape``)."""
    out = bytearray()
    it = iter(data)
    for b in it:
        if b == ESCAPE_CHARACTER:
            escaped = next(it, None)
            if escaped is None:
                break
            b = escaped
        out.append(b)
    return bytes(out)


def format_float(value: float) -> str:
    """Text float as the PC writes it: '.9g' (round-trips float32), no locale, finite only."""
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"refusing to send a non-finite float ({v!r})")
    return format(v, ".9g")


def encode_field(kind: Kind | str, value: object) -> bytes:
    """One field, escaped and never empty."""
    k = Kind(kind)
    if k is Kind.TEXT_INT:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"text int field needs an int, got {value!r}")
        raw = str(value).encode("ascii")
    elif k is Kind.TEXT_FLOAT:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"text float field needs a number, got {value!r}")
        raw = format_float(value).encode("ascii")
    elif k is Kind.TEXT_BOOL:
        if not isinstance(value, (bool, int)) or value not in (0, 1):
            raise TypeError(f"text bool field needs a bool, got {value!r}")
        raw = b"1" if value else b"0"
    elif k is Kind.TEXT_STR:
        if isinstance(value, str):
            raw = value.encode("ascii")
        elif isinstance(value, (bytes, bytearray)):
            raw = bytes(value)
        else:
            raise TypeError(f"string field needs str or bytes, got {value!r}")
        if not raw:
            raise ValueError("refusing to send an empty field (the Arduino skips it, shifting later ones)")
    else:
        if k is Kind.BIN_BOOL:
            if not isinstance(value, (bool, int)) or value not in (0, 1):
                raise TypeError(f"binary bool field needs a bool, got {value!r}")
            value = bool(value)
        elif k in (Kind.BIN_FLOAT, Kind.BIN_DOUBLE):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"binary float field needs a number, got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"binary integer field needs an int, got {value!r}")
        try:
            raw = struct.pack(k.value, value)
        except (struct.error, OverflowError) as exc:
            raise ValueError(f"{value!r} does not fit {k.value}: {exc}") from exc
    return escape(raw)


def encode_frame(
    cmd_id: int,
    fields: Iterable[tuple[Kind | str, object]] = (),
    *,
    max_len: int | None = ARDUINO_MAX_MESSAGE,
) -> bytes:
    """``<cmdId>{,<field>}*;`` with escaped typed fields.

    ``max_len`` is the limit on the escaped length before ';' (62 for anything the Arduino must
    receive). Pass ``None`` for controller -> PC frames, which have no limit. No ``\\r\\n`` is added.
    """
    if isinstance(cmd_id, bool) or not isinstance(cmd_id, int) or not 0 <= cmd_id <= 255:
        raise ValueError(f"command id must be an int in 0..255, got {cmd_id!r}")
    parts = [str(cmd_id).encode("ascii")]
    parts.extend(encode_field(kind, value) for kind, value in fields)
    body = b",".join(parts)
    if max_len is not None and len(body) > max_len:
        raise FrameTooLongError(len(body), max_len)
    return body + b";"


# ---------------------------------------------------------------------------------------------
# Strict field readers (PC side)
# ---------------------------------------------------------------------------------------------

_INT_RE = re.compile(rb"[+-]?[0-9]+")
_FLOAT_RE = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_SPECIAL_FLOATS = {b"nan": "nan", b"inf": "inf", b"-inf": "inf", b"ovf": "ovf", b"-ovf": "ovf",
                   b"INF": "inf", b"-INF": "inf", b"NaN": "nan"}


def text_int(field: bytes) -> int:
    if not _INT_RE.fullmatch(field):
        raise FieldError(f"not a decimal integer: {field!r}")
    return int(field)


def text_float(field: bytes) -> float:
    flag = _SPECIAL_FLOATS.get(field)
    if flag is not None:
        raise FieldError(f"controller sent a special float value {field!r}", flag=flag)
    if not _FLOAT_RE.fullmatch(field):
        raise FieldError(f"not a decimal float: {field!r}")
    return float(field)


def text_bool(field: bytes) -> bool:
    if field == b"1":
        return True
    if field == b"0":
        return False
    raise FieldError(f"not a boolean ('0' or '1'): {field!r}")


def text_str(field: bytes) -> str:
    return field.decode("latin-1")


def _binary_reader(kind: Kind) -> Callable[[bytes], int | float | bool]:
    """readBinArg<T> on the PC side, for one kind: its struct compiled once (the decoders' hot path)."""
    code = kind.value
    size = struct.calcsize(code)
    unpack = struct.Struct(code).unpack

    if kind is Kind.BIN_BOOL:
        def read_bool(field: bytes) -> bool:
            if len(field) != size:
                raise FieldError(f"binary {code} field has {len(field)} bytes, expected {size}")
            if field not in (b"\x00", b"\x01"):
                raise FieldError(f"binary bool is neither 0 nor 1: {field!r}")
            return field == b"\x01"
        return read_bool

    def read(field: bytes) -> int | float:
        if len(field) != size:
            raise FieldError(f"binary {code} field has {len(field)} bytes, expected {size}")
        return unpack(field)[0]  # type: ignore[no-any-return]
    return read


_BINARY_READERS: dict[Kind, Callable[[bytes], int | float | bool]] = {k: _binary_reader(k) for k in BINARY_KINDS}


def bin_value(field: bytes, kind: Kind | str) -> int | float | bool:
    """A binary field of exactly sizeof(T) bytes (already unescaped by the decoder)."""
    k = Kind(kind)
    if k not in BINARY_KINDS:
        raise ValueError(f"{k} is not a binary kind")
    return _BINARY_READERS[k](field)


def bin_int16(field: bytes) -> int:
    return int(bin_value(field, Kind.BIN_INT16))


def bin_int32(field: bytes) -> int:
    return int(bin_value(field, Kind.BIN_INT32))


def bin_uint32(field: bytes) -> int:
    return int(bin_value(field, Kind.BIN_UINT32))


def bin_float(field: bytes) -> float:
    return float(bin_value(field, Kind.BIN_FLOAT))


def bin_double(field: bytes) -> float:
    return float(bin_value(field, Kind.BIN_DOUBLE))


def bin_bool(field: bytes) -> bool:
    return bool(bin_value(field, Kind.BIN_BOOL))


FIELD_READERS: dict[Kind, Callable[[bytes], int | float | bool | str]] = {
    Kind.TEXT_INT: text_int, Kind.TEXT_FLOAT: text_float, Kind.TEXT_BOOL: text_bool, Kind.TEXT_STR: text_str,
    **_BINARY_READERS,
}


def read_field(field: bytes, kind: Kind | str) -> int | float | bool | str:
    """Strictly parse one field of the given kind (``FIELD_READERS[kind]`` for a kind known in advance)."""
    return FIELD_READERS[Kind(kind)](field)


# ---------------------------------------------------------------------------------------------
# PC-side streaming decoder
# ---------------------------------------------------------------------------------------------

# Every id field the decoder accepts (1 to 3 decimal digits, 0..255, leading zeros allowed) -> the id
_CMD_IDS: dict[bytes, int] = {f"{i:0{w}d}".encode(): i for w in (1, 2, 3) for i in range(min(256, 10**w))}
_STOP_RE = re.compile(rb"[/;]")  # the bytes the decoder must look at one by one
_LEADING_WHITESPACE_RE = re.compile(rb"[\r\n ]*")
# A complete frame from here: leading whitespace, then runs of ordinary bytes or escape pairs (the body),
# then an unescaped ';'.
_WHOLE_FRAME_RE = re.compile(rb"[\r\n ]*+([^/;]*+(?:/[\s\S][^/;]*+)*+);")
_ESCAPE_PAIR_RE = re.compile(rb"/([\s\S])")
FIELD_SEPARATOR_BYTE = b","
ESCAPE_BYTE = b"/"


class CmdMessengerDecoder:
    """Streaming frame decoder. ``feed`` accepts any chunking of the byte stream and never raises.

    Frames are cut on an unescaped ';', fields on an unescaped ','; each field is unescaped.
    Leading CR/LF/space before a frame is ignored (printLfCr). Empty and whitespace-only frames are
    dropped silently. A frame whose id is not a decimal 0..255 counts as bad. A frame longer than
    ``max_frame_length`` bytes is discarded up to the next unescaped ';'.
    """

    def __init__(self, max_frame_length: int = DEFAULT_MAX_FRAME_LENGTH) -> None:
        self.max_frame_length = max_frame_length
        self.frames_ok = 0
        self.frames_bad = 0
        self.bytes_discarded = 0
        self.last_error: str | None = None
        self._fields: list[bytes] = []
        self._current = bytearray()
        self._length = 0  # raw bytes of the frame so far (escapes included, leading whitespace not)
        self._escaped = False
        self._discarding = False

    def reset(self) -> None:
        """Forget any partial frame (e.g. after reopening the port). Counters are kept."""
        self._fields = []
        self._current = bytearray()
        self._length = 0
        self._escaped = False
        self._discarding = False

    @property
    def pending(self) -> int:
        """Bytes of an incomplete frame held between reads."""
        return self._length

    def feed(self, data: bytes) -> list[Frame]:
        # Runs of ordinary bytes and ',' are handled a slice at a time (a regex finds the next '/' or ';');
        # only escapes, ';' and the length limit are stepped through. Byte for byte the same frames,
        # counters and errors as the plain state machine (tests/test_cmdmessenger.py keeps one as reference).
        if not isinstance(data, bytes):
            data = bytes(data)
        frames: list[Frame] = []
        limit = self.max_frame_length
        search, whole = _STOP_RE.search, _WHOLE_FRAME_RE.finditer
        n = len(data)
        i = 0
        while i < n:
            if self._discarding:
                if self._escaped:  # the byte after a '/' never ends the discarding
                    self._escaped = False
                    self.bytes_discarded += 1
                    i += 1
                    continue
                m = search(data, i)
                j = n if m is None else m.start()
                if j == n:
                    self.bytes_discarded += n - i
                    break
                self.bytes_discarded += j + 1 - i
                i = j + 1
                if data[j] == ESCAPE_CHARACTER:
                    self._escaped = True
                else:
                    self._discarding = False
                continue
            if self._escaped:
                self._escaped = False
                self._current.append(data[i])
                i += 1
                self._length += 1
                if self._length > limit:
                    self._overflow(limit, escaped=False)
                continue
            if self._length == 0:
                # Whole frames ahead within the limit (the usual case): cut each in one go. A match
                # that does not start where the previous ended is no frame of ours (e.g. after a
                # dangling '/'): the byte-wise path below takes over from there.
                for m in whole(data, i):
                    if m.start() != i:
                        break
                    body = m.group(1)
                    if len(body) > limit:
                        break
                    i = m.end()
                    if body:  # ';' alone or after whitespace: an empty frame, dropped
                        frame = self._frame(_split_fields(body), len(body))
                        if frame is not None:
                            frames.append(frame)
                if i == n:
                    break
                if data[i] in _LEADING_WHITESPACE:
                    i = _LEADING_WHITESPACE_RE.match(data, i).end()  # type: ignore[union-attr]
                    if i == n:
                        break
            m = search(data, i)
            j = n if m is None else m.start()
            if j > i:
                room = limit - self._length
                if j - i > room:  # the limit is passed inside this run, at byte i + room
                    self._length = limit + 1
                    self._overflow(limit, escaped=False)
                    i += room + 1
                    continue
                run = data[i:j]
                self._length += j - i
                if FIELD_SEPARATOR_BYTE in run:
                    parts = run.split(FIELD_SEPARATOR_BYTE)
                    self._current += parts[0]
                    self._fields.append(bytes(self._current))
                    self._fields.extend(parts[1:-1])
                    self._current = bytearray(parts[-1])
                else:
                    self._current += run
                if j == n:
                    break
            i = j + 1
            if data[j] == COMMAND_SEPARATOR:
                frame = self._finish()
                if frame is not None:
                    frames.append(frame)
            else:  # the escape character counts towards the limit too
                self._length += 1
                if self._length > limit:
                    self._overflow(limit, escaped=True)
                else:
                    self._escaped = True
        return frames

    def _overflow(self, limit: int, *, escaped: bool) -> None:
        """The frame passed ``limit`` bytes: count it and discard up to the next unescaped ';'."""
        self.frames_bad += 1
        self.bytes_discarded += self._length
        self.last_error = f"frame longer than {limit} bytes without ';'"
        self.reset()
        self._escaped = escaped
        self._discarding = True

    def _finish(self) -> Frame | None:
        length = self._length
        fields = self._fields
        fields.append(bytes(self._current))
        self._fields = []
        self._current = bytearray()
        self._length = 0
        if length == 0:
            return None  # ';;' or whitespace only
        return self._frame(fields, length)

    def _frame(self, fields: list[bytes], length: int) -> Frame | None:
        """A complete frame of ``length`` raw bytes (before ';'), or None (counted) if its id is bad."""
        id_field = fields[0]
        cmd_id = _CMD_IDS.get(id_field)
        if cmd_id is None:
            self.frames_bad += 1
            self.bytes_discarded += length + 1
            self.last_error = f"bad command id {id_field[:16]!r}"
            return None
        self.frames_ok += 1
        return Frame(cmd_id, tuple(fields[1:]))


def _unescape_run(part: bytes) -> bytes:
    """Unescape bytes in which every '/' has its byte after it (no dangling escape at the end)."""
    if b"//" in part:
        return _ESCAPE_PAIR_RE.sub(rb"\1", part)
    return part.replace(ESCAPE_BYTE, b"")  # every '/' escapes a byte that is not '/'


def _split_fields(body: bytes) -> list[bytes]:
    """The unescaped fields of a complete frame body (no ';'; every '/' has its byte after it)."""
    if ESCAPE_BYTE not in body:
        return body.split(FIELD_SEPARATOR_BYTE)
    if b"/," not in body and b"//" not in body:
        # Every '/' escapes a byte that is neither ',' nor '/' (mostly NUL in binary fields): every ','
        # separates, and unescaping is dropping the '/'.
        return body.replace(ESCAPE_BYTE, b"").split(FIELD_SEPARATOR_BYTE)
    parts = body.split(FIELD_SEPARATOR_BYTE)
    fields: list[bytes] = []
    carry = b""  # a field continued past an escaped ','
    for part in parts:
        if ESCAPE_BYTE in part:
            # An odd run of '/' at the end leaves the last one escaping the ',' that split here: data.
            if (len(part) - len(part.rstrip(ESCAPE_BYTE))) & 1:
                carry += _unescape_run(part[:-1]) + FIELD_SEPARATOR_BYTE
                continue
            part = _unescape_run(part)
        fields.append(carry + part if carry else part)
        carry = b""
    return fields


# ---------------------------------------------------------------------------------------------
# Arduino-side model: the CmdMessenger 4.2.0 receiver
# ---------------------------------------------------------------------------------------------

LIBRARY_4_2_0 = "4.2.0"
LIBRARY_2026 = "2026"

_C_SPACE = b" \t\n\v\f\r"
_ATOL_RE = re.compile(rb"[ \t\n\v\f\r]*([+-]?[0-9]+)")
_STRTOD_RE = re.compile(
    rb"[ \t\n\v\f\r]*([+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf(?:inity)?|nan))",
    re.IGNORECASE,
)
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


def c_atol(text: bytes) -> int:
    """newlib atol/atoi on the DUE: leading space, sign, digits; clamps to long; garbage gives 0."""
    m = _ATOL_RE.match(text)
    if m is None:
        return 0
    return max(_INT32_MIN, min(_INT32_MAX, int(m.group(1))))


def c_strtod(text: bytes) -> float:
    """strtod: the longest decimal prefix (also inf/nan); garbage gives 0.0."""
    m = _STRTOD_RE.match(text)
    if m is None:
        return 0.0
    try:
        return float(m.group(1))
    except ValueError:  # pragma: no cover - the regex only matches float() syntax
        return 0.0


def to_float32(value: float) -> float:
    """Round a double to the nearest IEEE binary32, as a C cast does (overflow becomes inf)."""
    try:
        return float(struct.unpack("<f", struct.pack("<f", value))[0])
    except OverflowError:
        return math.copysign(math.inf, value)


def _wrap(value: int, bits: int, signed: bool) -> int:
    value &= (1 << bits) - 1
    if signed and value >= 1 << (bits - 1):
        value -= 1 << bits
    return value


class ArduinoMessage:
    """One message as a 4.2.0 callback sees it: a snapshot of the receive buffer plus the
    argument cursor. The reads mirror readXArg, including their leniency and in-place mutation.

    The library reads the command id as soon as the message ends, so ``command_id`` (uint8) and
    ``id_arg_ok`` are set on construction. Mutations stay in this snapshot (the real buffer would
    keep them; that only matters for reads past the end of a message).
    """

    def __init__(self, buffer: bytes, version: str = LIBRARY_4_2_0) -> None:
        self._buf = bytearray(buffer)
        self._version = version
        self._next_pos = 0
        self._current: int | None = None
        self.arg_ok = False
        self.command_id = _wrap(self.read_int16(), 8, signed=False)
        self.id_arg_ok = self.arg_ok

    @property
    def raw(self) -> bytes:
        """The buffer up to its first unescaped NUL (what the library stored, escapes included)."""
        return bytes(self._buf[: self._scan(0, stop_on_separator=False)])

    def is_attached(self, attached: Iterable[int]) -> bool:
        """Would handleMessage call an attached callback (else the default callback)?"""
        return self.id_arg_ok and self.command_id < MAX_CALLBACKS and self.command_id in set(attached)

    # -- the library's cursor ---------------------------------------------------------------
    def _byte(self, pos: int) -> int:
        return self._buf[pos] if pos < len(self._buf) else 0

    def _scan(self, pos: int, stop_on_separator: bool = True) -> int:
        """findNext: offset of the next unescaped separator or unescaped NUL."""
        n = 0
        last = 0
        while True:
            c = self._byte(pos + n)
            escaped = last == ESCAPE_CHARACTER
            last = c
            if c == ESCAPE_CHARACTER and escaped:
                last = 0
            if not escaped and (c == 0 or (stop_on_separator and c == FIELD_SEPARATOR)):
                return n
            if pos + n >= len(self._buf):
                return n
            n += 1

    def _next(self) -> bool:
        """split_r: strip leading separators, terminate the field with NUL, remember the rest."""
        pos = self._next_pos
        while self._scan(pos) == 0 and self._byte(pos) != 0:
            pos += 1
        if self._byte(pos) == 0:
            self._current = None
            return False
        start = pos
        pos += self._scan(pos)
        if self._byte(pos) != 0:
            self._buf[pos] = 0
            pos += 1
        self._next_pos = pos
        self._current = start
        return True

    def _cstr(self, pos: int) -> bytes:
        end = self._buf.find(0, pos)
        return bytes(self._buf[pos:] if end < 0 else self._buf[pos:end])

    def _unescape_in_place(self, pos: int) -> None:
        src = dst = pos
        buf = self._buf
        while src < len(buf) and buf[src] != 0:
            if buf[src] == ESCAPE_CHARACTER:
                src += 1
                if src >= len(buf):
                    break
            buf[dst] = buf[src]
            dst += 1
            src += 1
        for i in range(dst, min(src, len(buf))):
            buf[i] = 0

    def available(self) -> bool:
        """available(): an alias of next() that *advances* the cursor (issue #13)."""
        return self._next()

    # -- readXArg ---------------------------------------------------------------------------
    def read_int16(self) -> int:
        if self._next():
            self.arg_ok = True
            return _wrap(c_atol(self._cstr(self._current_pos())), 16, signed=True)
        self.arg_ok = False
        return 0

    def read_int32(self) -> int:
        if self._next():
            self.arg_ok = True
            return c_atol(self._cstr(self._current_pos()))
        self.arg_ok = False
        return 0

    def read_bool(self) -> bool:
        return self.read_int16() != 0

    def read_char(self) -> int:
        if self._next():
            self.arg_ok = True
            return self._byte(self._current_pos())
        self.arg_ok = False
        return 0

    def read_float(self) -> float:
        if self._next():
            self.arg_ok = True
            return to_float32(c_strtod(self._cstr(self._current_pos())))
        self.arg_ok = False
        return 0.0

    def read_double(self) -> float:
        if self._next():
            self.arg_ok = True
            return c_strtod(self._cstr(self._current_pos()))
        self.arg_ok = False
        return 0.0

    def read_string(self) -> bytes:
        """readStringArg: 4.2.0 returns the raw escaped text; 2026 unescapes it first."""
        if self._next():
            self.arg_ok = True
            pos = self._current_pos()
            if self._version == LIBRARY_2026:
                self._unescape_in_place(pos)
            return self._cstr(pos)
        self.arg_ok = False
        return b""

    def unescape_current(self) -> bytes:
        """The library's unescape() applied to the field last read (the old firmware idiom)."""
        if self._current is None:
            return b""
        self._unescape_in_place(self._current)
        return self._cstr(self._current)

    def read_bin(self, kind: Kind | str) -> int | float | bool:
        """readBinArg<T>: unescape in place, copy sizeof(T) bytes. 4.2.0 reads past a short field
        (into the buffer's leftovers); 2026 zero-fills. ArgOk is not touched (as in 4.2.0)."""
        k = Kind(kind)
        size = binary_size(k)
        if not self._next():
            return False if k is Kind.BIN_BOOL else (0.0 if k in (Kind.BIN_FLOAT, Kind.BIN_DOUBLE) else 0)
        pos = self._current_pos()
        if self._version == LIBRARY_2026:
            field = self._unescaped_field(pos)[:size]
            data = field + bytes(size - len(field))
            self._unescape_in_place(pos)
        else:
            self._unescape_in_place(pos)
            data = bytes(self._byte(pos + i) for i in range(size))
        if k is Kind.BIN_BOOL:
            return data[0] != 0
        value: int | float = struct.unpack(k.value, data)[0]
        return value

    def _unescaped_field(self, pos: int) -> bytes:
        """The field at pos, unescaped, with its true length (an escaped NUL is data)."""
        out = bytearray()
        while True:
            c = self._byte(pos)
            if c == 0 or pos >= len(self._buf):
                return bytes(out)
            if c == ESCAPE_CHARACTER:
                pos += 1
                if pos >= len(self._buf):
                    return bytes(out)
                c = self._buf[pos]
            out.append(c)
            pos += 1

    # -- the project's firmware helpers (stricter than the library; the C++ firmware mirrors them)
    def read_raw_field(self) -> bytes | None:
        """The next field, unescaped, with its true length (a NUL only ends it when unescaped).
        Firmware helper built on 4.2.0's readStringArg, which returns the escaped text."""
        if not self._next():
            self.arg_ok = False
            return None
        self.arg_ok = True
        return self._unescaped_field(self._current_pos())

    def _current_pos(self) -> int:
        assert self._current is not None
        return self._current


class ArduinoReceiver:
    """The 4.2.0 receive path (feedinSerialData / processLine) on a 64-byte buffer.

    ``feed`` returns the messages that would be dispatched, in order. With ``version='4.2.0'`` the
    buffer is emptied after every 63 stored bytes and reading continues, so the tail of an overlong
    message becomes a new message (usually command 0). With ``version='2026'`` bytes are discarded
    up to the next unescaped ';'.
    """

    def __init__(self, buffer_size: int = MESSENGER_BUFFER_SIZE, version: str = LIBRARY_4_2_0) -> None:
        if version not in (LIBRARY_4_2_0, LIBRARY_2026):
            raise ValueError(f"unknown library version {version!r}")
        if not 4 <= buffer_size <= 256:
            raise ValueError("bufferIndex is a uint8_t: buffer size must be 4..256")
        self.version = version
        self._buf = bytearray(buffer_size)
        self._last_index = buffer_size - 1
        self._index = 0
        self._last_char = 0
        self._discarding = False
        self.overflows = 0

    def feed(self, data: bytes) -> list[ArduinoMessage]:
        messages: list[ArduinoMessage] = []
        buf = self._buf
        for b in data:
            escaped = self._last_char == ESCAPE_CHARACTER
            self._last_char = b
            if b == ESCAPE_CHARACTER and escaped:
                self._last_char = 0
            if b == COMMAND_SEPARATOR and not escaped:
                if self._discarding:
                    self._discarding = False
                    self._index = 0
                    continue
                buf[self._index] = 0
                if self._index > 0:
                    messages.append(ArduinoMessage(bytes(buf), self.version))
                    self._last_char = 0
                self._index = 0
            elif not self._discarding:
                buf[self._index] = b
                self._index += 1
                if self._index >= self._last_index:
                    self.overflows += 1
                    self._index = 0
                    if self.version == LIBRARY_2026:
                        self._discarding = True
        return messages


# ---------------------------------------------------------------------------------------------
# Arduino-side model: the sender (Print on the DUE + CmdMessenger's send functions)
# ---------------------------------------------------------------------------------------------

_DIGITS = "0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ"


def print_int(value: int, base: int = 10) -> bytes:
    """Print::print(long, base): signed decimal; other bases print the unsigned 32-bit value."""
    if base == 10:
        return str(_wrap(value, 32, signed=True)).encode("ascii")
    n = _wrap(value, 32, signed=False)
    if n == 0:
        return b"0"
    out = []
    while n:
        n, r = divmod(n, base)
        out.append(_DIGITS[r])
    return "".join(reversed(out)).encode("ascii")


def print_float(value: float, digits: int = 2) -> bytes:
    """Print::printFloat of ArduinoCore-sam: fixed point, round half up, nan/inf/ovf."""
    number = float(value)
    if math.isnan(number):
        return b"nan"
    if math.isinf(number):
        return b"inf"
    if number > 4294967040.0 or number < -4294967040.0:
        return b"ovf"
    out = ""
    if number < 0.0:
        out = "-"
        number = -number
    rounding = 0.5
    for _ in range(digits):
        rounding /= 10.0
    number += rounding
    int_part = int(number) & 0xFFFFFFFF
    remainder = number - float(int_part)
    out += str(int_part)
    if digits > 0:
        out += "."
    for _ in range(digits):
        remainder *= 10.0
        to_print = int(remainder)
        out += str(to_print)
        remainder -= to_print
    return out.encode("ascii")


def print_sci(value: float, digits: int = 6) -> bytes:
    """CmdMessenger::printSci (4.2.0), bugs included: one-step normalisation, float maths."""
    f = float(value)
    out = ""
    if f < 0.0:
        out = "-"
        f = -f
    if math.isinf(f):
        return (out + "INF").encode("ascii")
    if math.isnan(f):
        return (out + "NaN").encode("ascii")
    digits = min(digits, 6)
    multiplier = int(10.0**digits)
    exponent = 0 if abs(f) < 10.0 else int(math.log10(f))
    g = to_float32(f / 10.0**exponent)
    if g < 1.0 and g != 0.0:
        g = to_float32(g * 10)
        exponent -= 1
    whole = int(g)
    part = int(to_float32((g - whole) * multiplier) + 0.5)
    if part == 100:
        whole += 1
        part = 0
    return (out + f"{whole}.{part:0{digits}d}E{exponent:+d}").encode("ascii")


class ArduinoSender:
    """Builds the bytes a 4.2.0 firmware writes with sendCmdStart / sendCmdArg / sendCmdEnd.

    Sending has no length limit. ``print_lf_cr`` appends ``\\r\\n`` after every ';'.
    """

    def __init__(self, print_lf_cr: bool = False) -> None:
        self.print_lf_cr = print_lf_cr
        self._out = bytearray()

    def cmd_start(self, cmd_id: int) -> ArduinoSender:
        self._out += print_int(_wrap(cmd_id, 8, signed=False))  # the id is a byte
        return self

    def _arg(self, data: bytes) -> ArduinoSender:
        self._out += b"," + data
        return self

    def arg_int(self, value: int, base: int = 10) -> ArduinoSender:
        return self._arg(print_int(value, base))

    def arg_bool(self, value: bool) -> ArduinoSender:
        return self._arg(b"1" if value else b"0")

    def arg_char(self, value: str) -> ArduinoSender:
        return self._arg(value.encode("latin-1")[:1])  # char is printed raw, not escaped

    def arg_float(self, value: float, digits: int = 2) -> ArduinoSender:
        return self._arg(print_float(value, digits))

    def arg_sci(self, value: float, digits: int = 6) -> ArduinoSender:
        return self._arg(print_sci(value, digits))

    def arg_str(self, value: bytes | str) -> ArduinoSender:
        """sendCmdArg(const char*): raw, NOT escaped."""
        data = value.encode("latin-1") if isinstance(value, str) else value
        return self._arg(data.split(b"\x00", 1)[0])

    def arg_esc_str(self, value: bytes | str) -> ArduinoSender:
        """sendCmdEscArg: escaped (a C string, so it ends at the first NUL)."""
        data = value.encode("latin-1") if isinstance(value, str) else value
        return self._arg(escape(data.split(b"\x00", 1)[0]))

    def arg_bin(self, kind: Kind | str, value: object) -> ArduinoSender:
        k = Kind(kind)
        if k not in BINARY_KINDS:
            raise ValueError(f"{k} is not a binary kind")
        return self._arg(escape(struct.pack(k.value, value)))

    def cmd_end(self) -> bytes:
        self._out += b";\r\n" if self.print_lf_cr else b";"
        out = bytes(self._out)
        self._out.clear()
        return out

