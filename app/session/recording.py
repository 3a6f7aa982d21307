"""Session recording: one folder per session, every device stream, every event, a manifest.

A session starts with :meth:`SessionRecorder.start` (not armed separately) and writes to
``<sessions>/<patient>/<YYYYmmdd-HHMMSS[-n]>/``, a folder created with an exclusive ``mkdir`` so an
earlier session is never overwritten::

    manifest.json          patient, operator, app and device versions, config snapshot, stream specs,
                           start (and, once stopped, end) with time zone, per-stream counts
    events.jsonl           one JSON object per line: t_wall, t_mono, kind, who, origin, data
    streams/<stream>.csv   header ``t_mono_s,<channel>,...,t_arrival_s`` then one line per sample: t_mono_s
                           when the sample was taken (the device's clock mapped to the host's, #27),
                           t_arrival_s when its bytes came back from a read (a diagnostic)
    clocks.csv             header ``t_mono_s,device,device_s,drift``: the map from each device clock to the host's
                           clock, one line each time its estimate changed (:class:`DeviceClockLog`)

Crash safety (docs/sessions.md): every file is append-only text written in whole lines, flushed to the
OS and fsync'ed at least every ``recording.flush_interval_s`` (≤ 1 s), so after a SIGKILL or a power
cut the files hold every line up to the last flush; at worst the last line is cut short, and
:func:`load_session` drops it. The manifest is replaced atomically (temp file + rename), so it is the
start version or the final one, never half of either.

Threads: the recorder subscribes to the stream bus (app/core/bus.py): one bounded, counted queue per device for
its samples and one for the journal (app/core/journal.py: the devices' events and the supervisor's records — alarms,
e-stops, refusals, leases, faults — in the order they were published), filled by the publishing threads (no I/O,
no formatting there);
one writer thread drains them, formats and writes. If a device's queue is full (the disk stalled for
minutes) its oldest samples are dropped, counted per device, and the drop is recorded as an event and in
the manifest (``dropped_samples``; lost device events: ``dropped_device_events``; the journal's own records are
never dropped).

Write failures (docs/sessions.md, "When recording fails"): any error writing the session files (a full
disk, a removed drive, a read-only folder) makes the writer call ``on_failure(folder, error)`` once —
the manager's fault policy raises a STOP alarm naming the folder and the error, which brings the devices
to their safe state — and from then on samples are dropped (counted) while events are kept in memory and
appended to ``events.jsonl`` again as soon as a write succeeds (tried every second and at stop).  ``stop``
never raises; the manifest says ``"status": "failed"`` with when and why (``recording_failure``). A
256 KiB space reserve (``.space-reserve``) allocated at start and released at the failure leaves room for
that manifest and the kept events on a disk that stays full; when even so the manifest cannot be written,
``recording-failed.txt`` says it and :func:`load_session` reads it. No temp file is left behind.
``check_free_space`` refuses to start a session below ``recording.min_free_mib`` and warns below
``recording.warn_free_mib``.
"""

from __future__ import annotations

import collections
import datetime as _dt
import errno
import heapq
import io
import json
import logging
import math
import os
import re
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from app.core import journal, paths, streams
from app.core.bus import Channel, StreamSpec, Subscription
from app.core.journal import Record
from app.core.outputs import fsync_dir
from app.session.alarm_count import alarm_count
from app.wire.linarm_protocol import T_US_WRAP_S

if TYPE_CHECKING:
    from app.core.config import AppConfig
    from app.therapy.services import SessionHost

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
MANIFEST_FILE = "manifest.json"
EVENTS_FILE = "events.jsonl"
STREAMS_DIR = "streams"
TIME_COLUMN = "t_mono_s"
ARRIVAL_COLUMN = "t_arrival_s"  # last column: when the sample's read returned (diagnostic; older files lack it)
_WRITER_PERIOD_S = 0.02  # how often the writer drains the queues (latency, not the flush interval)
_RETRY_PERIOD_S = 1.0  # after a write error: how often the kept events are tried again
FILE_MODE = 0o600  # session files hold health data: the user only (folders 0o700)
DIR_MODE = 0o700
RESERVE_FILE = ".space-reserve"  # room held back for the failure path (docs/sessions.md); gone once stopped
RESERVE_BYTES = 256 * 1024  # the final manifest (~10 KB) twice over (temp + old) and ~1000 kept events
FAILED_FILE = "recording-failed.txt"  # the sidecar the loader reads when even the manifest could not be written
CLOCK_FILE = "clocks.csv"  # the device clocks' maps to the host clock as they were estimated (DeviceClockLog)
CLOCK_COLUMNS = ("t_mono_s", "device", "device_s", "drift")


class RecordingError(OSError):
    """A session cannot be recorded (folder unwritable, disk full); the message names the folder."""


def _private_dir(path: Path) -> None:
    try:
        os.chmod(path, DIR_MODE)
    except OSError:
        pass


def _open_private(path: Path, **kw: Any) -> TextIO:
    """Open for appending, created 0600 whatever the umask."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, FILE_MODE)
    try:
        os.fchmod(fd, FILE_MODE) if hasattr(os, "fchmod") else None
        return open(fd, "a", encoding="utf-8", newline="\n", **kw)
    except BaseException:
        os.close(fd)
        raise


def free_space_mib(folder: Path) -> float:
    import shutil

    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    return shutil.disk_usage(probe).free / (1 << 20)


def check_free_space(folder: Path, warn_mib: float, min_mib: float) -> str:
    """'' when there is room; a warning text below ``warn_mib``; raises RecordingError below ``min_mib``."""
    try:
        free = free_space_mib(folder)
    except OSError as exc:
        raise RecordingError(errno.EIO, f"cannot record in {folder}: {exc.strerror or exc}") from exc
    if free < min_mib:
        raise RecordingError(errno.ENOSPC, f"cannot record in {folder}: only {free:.0f} MiB free "
                                           f"(at least {min_mib:g} MiB needed)")
    if free < warn_mib:
        return f"only {free:.0f} MiB free in {folder} (below {warn_mib:g} MiB): the session may not fit"
    return ""


# ---------------------------------------------------------------------------------------------- helpers
def app_version() -> str:
    """The application's version (package metadata, or pyproject.toml in a checkout: app.__version__)."""
    from app import __version__

    return __version__


def wall_iso(t_wall: float | None = None) -> str:
    """ISO 8601 local time with the UTC offset, e.g. 2025-03-04T10:15:02.123456+01:00."""
    moment = _dt.datetime.now() if t_wall is None else _dt.datetime.fromtimestamp(t_wall)
    return moment.astimezone().isoformat(timespec="microseconds")


def sessions_root(config: AppConfig | None = None) -> Path:
    """``recording.folder`` when configured, else the user's data folder."""
    folder = config.recording.folder if config is not None else ""
    if folder:
        path = Path(folder).expanduser()
        path.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
        return path
    return paths.sessions_dir()


def is_session_uuid(text: str) -> bool:
    """Whether ``text`` is a UUID, as a session's identity is (made at its start, ``session_uuid``)."""
    try:
        uuid.UUID(text)
    except ValueError:
        return False
    return True


def safe_name(text: str) -> str:
    """A portable file/folder name for a stream or patient identifier (no separators, no surprises)."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]", "_", text).strip(".")
    return cleaned or "_"


def stream_file_name(stream: str) -> str:
    return f"{safe_name(stream)}.csv"


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON so that ``path`` is always either the old or the new document (temp + fsync + rename).

    When the write fails (a full disk) the temp file is removed: nothing half-written is left behind."""
    text = json.dumps(data, indent=2, ensure_ascii=False, default=str)  # before the file: no empty temp on a bad value
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
        with open(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    fsync_dir(path.parent)


def _reserve_space(path: Path, nbytes: int) -> None:
    """Allocate ``nbytes`` on the session's disk (released when the recording fails or stops, so the final
    manifest and the kept events still fit on a disk that filled up meanwhile). Raises OSError (ENOSPC)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    try:
        if hasattr(os, "posix_fallocate"):
            try:
                os.posix_fallocate(fd, 0, nbytes)  # real blocks, not a sparse hole
                return
            except OSError as exc:
                if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                    raise
        chunk = os.urandom(65536)  # not a pattern: a compressing file system would store it in almost no space
        left = nbytes
        while left > 0:
            left -= os.write(fd, chunk[: min(left, len(chunk))])
        os.fsync(fd)
    finally:
        os.close(fd)


def _cut_to_last_line(path: Path) -> None:
    """Truncate a text file after its last complete line (a write that failed half-way leaves a partial one)."""
    with open(path, "rb+") as fh:
        end = fh.seek(0, os.SEEK_END)
        pos = end
        while pos > 0:
            start = max(0, pos - 4096)
            fh.seek(start)
            block = fh.read(pos - start)
            nl = block.rfind(b"\n")
            if nl >= 0:
                pos = start + nl + 1
                break
            pos = start
        if pos != end:
            fh.truncate(pos)


def _count_lines(path: Path) -> int:
    """Complete lines of a file (its newlines), read in chunks."""
    n = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            n += chunk.count(b"\n")
    return n


def _discard_buffer(fh: Any) -> None:
    """Point a file object's descriptor at the null device: what its buffer still holds (lines a full disk
    refused) is dropped when it is closed instead of being written over the room the failure path needs."""
    try:
        fd = fh.fileno()
    except (OSError, ValueError, AttributeError):
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        return
    try:
        os.dup2(null, fd)
    except OSError:
        pass
    finally:
        os.close(null)


def _make_session_folder(root: Path, patient_id: str, now: _dt.datetime) -> Path:
    base = root / safe_name(patient_id)
    base.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
    _private_dir(base)
    stamp = now.strftime("%Y%m%d-%H%M%S")
    for n in range(1, 10_000):
        folder = base / (stamp if n == 1 else f"{stamp}-{n}")
        try:
            folder.mkdir(mode=DIR_MODE)  # exclusive: an existing session is never reused or overwritten
        except FileExistsError:
            continue
        _private_dir(folder)
        return folder
    raise RuntimeError(f"cannot create a session folder under {base}")


def _jsonable(value: Any) -> Any:
    try:
        json.dumps(value)
        return value
    except (TypeError, ValueError):
        return str(value)


def _device_versions(driver: Any) -> dict[str, Any]:
    """Whatever version information a driver exposes (firmware after identify, protocol)."""
    out: dict[str, Any] = {}
    for attr in ("firmware_version", "protocol_version", "device_info", "hardware_version", "serial_number"):
        value = getattr(driver, attr, None)
        if value is not None and not callable(value):
            out[attr] = _jsonable(value)
    return out


# The streams whose rate the configuration sets (the spec's figure is the default's): stream -> the setting.
_CONFIGURED_RATES = {streams.LINARM_VSA: "state_rate_hz", streams.PHYSIO_MAIN: "rate_hz",
                     streams.PATIENT_MODEL_MAIN: "rate_hz", streams.VR_MAIN: "rate_hz"}


def configured_rate_hz(config: AppConfig, device: str, spec: StreamSpec) -> float:
    """The rate a stream runs at with this configuration (the spec's figure is the default's)."""
    setting = _CONFIGURED_RATES.get(spec.name)
    cfg = getattr(config.devices, device, None)  # a device the configuration has no section for: the default
    if setting is None or cfg is None:
        return spec.nominal_rate_hz
    return float(getattr(cfg, setting, spec.nominal_rate_hz))


def _spec_dict(spec: StreamSpec, device: str, rate_hz: float | None = None) -> dict[str, Any]:
    return {
        "device": device,
        "file": f"{STREAMS_DIR}/{stream_file_name(spec.name)}",
        "nominal_rate_hz": spec.nominal_rate_hz if rate_hz is None else rate_hz,
        "channels": [{"name": c.name, "unit": c.unit, "label": c.label} for c in spec.channels],
    }


# ---------------------------------------------------------------------------------------------- recorder
@dataclass
class _StreamOut:
    spec: StreamSpec
    fh: TextIO
    path: Path | None = None
    count: int = 0
    on_disk: int | None = None  # after a write failure: the samples the file holds (it is not written again)
    first_t: float | None = None
    last_t: float | None = None


# The devices whose samples carry their own clock's reading (s), the attribute holding it and where it wraps: the
# recorder keeps how each was mapped to the host's clock (app.devices.clock), read off the samples.
DEVICE_CLOCK_FIELDS: dict[str, tuple[str, float | None]] = {
    streams.LINARM: ("controllerTime", T_US_WRAP_S),  # the controller's micros(), wrapping every 71.6 min
    streams.PHYSIO: ("boardTime", None),  # the board's ms tick, unwrapped by the decoder
}
CLOCK_TOLERANCE_S = 1e-6  # a sample further than this from the line it follows starts a new line (a new estimate)
CLOCK_RESTART_S = 1.0  # a device step this far from the host's elapsed time: the device restarted (DeviceClock.jump_s)
CLOCK_REORDER_S = 0.02  # a step back this short is an older sample of another stream (DeviceClock.reorder_s)


class DeviceClockLog:
    """How one device's clock was mapped to the host's while recording, read off the samples (writer thread).

    A sample of a device with a clock carries its device time (the LINarm's ``controllerTime``, the board's
    ``boardTime``) and its host time, mapped by the driver's :class:`app.devices.clock.DeviceClock` on a line
    ``host = device·(1 + drift) + offset`` that it re-estimates now and then (a refit every 0.5 s, a less delayed
    sample). Between two estimates every sample lies on one line; :meth:`feed` returns a line for ``clocks.csv``
    when a sample leaves it — the estimate changed: about twice a second, more while it settles — holding the new
    line: from ``t_mono_s`` (host) and ``device_s`` on, ``host = t_mono_s + (device − device_s)·(1 + drift)``.
    So every recorded time maps back to its device time within :data:`CLOCK_TOLERANCE_S`, and the offsets the
    application measured are kept (the XDF export's ClockOffset chunks). The drivers' threads do nothing more.

    ``device_s`` is the device's clock in seconds, unwrapped (the LINarm's µs counter wraps every 71.6 min) and,
    across a restart of the device (its clock jumped), continued by the host's elapsed time: one monotonic clock
    per device for the whole session."""

    def __init__(self, device: str, wrap_s: float | None) -> None:
        self.device = device
        self.wrap_s = wrap_s
        self._raw: float | None = None  # the last reading, as the sample had it
        self._device_s = 0.0  # ... unwrapped and continued
        self._host = 0.0
        self._line: tuple[float, float, float] | None = None  # (t_mono_s, device_s, 1 + drift) being followed
        self._start: tuple[float, float] | None = None  # a new line's first point, written with its second
        self.lines = 0

    def feed(self, host: float, reading: Any) -> str | None:
        """The sample taken at ``host`` (its recorded time) with device clock ``reading``: a ``clocks.csv`` line
        when the map changed, else None."""
        try:
            raw = float(reading)
        except (TypeError, ValueError):
            return None
        if not (math.isfinite(raw) and math.isfinite(host)):
            return None
        if self._raw is None:
            device_s = raw
        else:
            step = raw - self._raw
            wrap = self.wrap_s
            if wrap:
                step %= wrap
                if step > wrap / 2:
                    step -= wrap  # a step back, not most of a wrap ahead
            if step == 0.0:
                return None  # another stream's sample of the same instant (the LINarm's VSA and motors)
            if -CLOCK_REORDER_S <= step < 0.0:
                return None  # an older sample of another stream: the driver stamped it on the line it follows
            elapsed = host - self._host
            if step < 0.0 or abs(step - elapsed) > CLOCK_RESTART_S:
                step = max(elapsed, 1e-6)  # the device restarted (its clock jumped): continued by the host's time
            device_s = self._device_s + step
        self._raw, self._device_s, self._host = raw, device_s, host
        if self._start is not None:
            h0, d0 = self._start
            self._start = None
            slope = (host - h0) / (device_s - d0)
            self._line = (h0, d0, slope)
            return self._row(h0, d0, slope - 1.0)
        line = self._line
        if line is not None and abs(host - (line[0] + (device_s - line[1]) * line[2])) <= CLOCK_TOLERANCE_S:
            return None
        self._start = (host, device_s)  # a new estimate: its line is known at the next sample
        return None

    def finish(self) -> str | None:
        """At the end: a line started by the last sample (with the drift of the one before)."""
        if self._start is None:
            return None
        h0, d0 = self._start
        self._start = None
        return self._row(h0, d0, self._line[2] - 1.0 if self._line is not None else 0.0)

    def _row(self, host: float, device_s: float, drift: float) -> str:
        self.lines += 1
        return f"{host!r},{self.device},{device_s!r},{drift!r}\n"


# Device events the recorder's queue holds: they are rare (a few a minute), so this is a stall of hours.
DEVICE_EVENT_QUEUE = 10_000


# ---------------------------------------------------------------------------------------------- journal → events
def journal_event(rec: Record, operator: str, in_gap: dict[str, bool],
                  device_streams: Mapping[str, Sequence[str]]) -> dict[str, Any]:
    """How a journal record reads in the session record (and on the LSL marker outlet, :mod:`app.session.lsl`):
    a device's event (``in_gap``, the devices now without data, is updated: a disconnect or silence starts a data
    gap, the device's return ends it), what the application records (who did it), a run change (the session's
    ``operator``'s), or the supervisor's (origin safety). Call it on one thread per ``in_gap``."""
    if rec.from_device:
        return _device_event(rec, in_gap, device_streams)
    data = dict(rec.data)
    if rec.origin == journal.APP:  # what the application records for the session, by whom it says
        return {"t_wall_epoch_s": rec.t_wall, "t_mono": rec.t_mono, "kind": rec.kind, "who": rec.who,
                "origin": "app", "data": data}
    if rec.origin == journal.RUN:  # the session's runs, as the application records them: the operator's
        return {"t_wall_epoch_s": rec.t_wall, "t_mono": rec.t_mono, "kind": rec.kind, "who": operator,
                "origin": "app", "data": data}
    who = str(data.get("operator") or data.get("source") or "safety")
    return {"t_wall_epoch_s": rec.t_wall, "t_mono": rec.t_mono, "kind": rec.kind, "who": who, "origin": "safety",
            "data": data}


def _device_event(ev: Record, in_gap: dict[str, bool], device_streams: Mapping[str, Sequence[str]]) -> dict[str, Any]:
    device, event = ev.origin, ev.kind
    gap = in_gap.get(device, False)
    if event in ("disconnected", "silent"):
        kind = "device_disconnected" if gap else "gap_start"
        in_gap[device] = True
    elif event in ("connected", "alive"):
        kind = "gap_end" if gap else f"device_{event}"
        in_gap[device] = False
    else:
        kind = f"device_{event}"
    t_wall = time.time() - (time.monotonic() - ev.t_mono)  # when it happened, not when the writer saw it
    return {"t_wall_epoch_s": t_wall, "t_mono": ev.t_mono, "kind": kind, "who": device, "origin": "device",
            "data": {"device": device, "cause": event, "detail": ev.detail,
                     "streams": list(device_streams.get(device, []))}}


def written_event(ev: dict[str, Any]) -> dict[str, Any]:
    """A session event as one line of ``events.jsonl`` holds it (and the LSL marker outlet sends it)."""
    return {"t_wall": wall_iso(ev["t_wall_epoch_s"]), "t_mono": ev["t_mono"], "kind": ev["kind"],
            "who": ev["who"], "origin": ev["origin"], "data": ev["data"]}


class SessionRecorder:
    """Records one session at a time. ``start`` → samples and events flow to disk → ``stop``.

    ``event`` may be called from any thread and never blocks; samples and device events come from the bus.
    ``queue_limit`` bounds each device's queue of samples waiting for the writer.
    """

    def __init__(self, queue_limit: int = 500_000, fsync: bool = True) -> None:
        self.queue_limit = queue_limit
        self.fsync = fsync
        self.folder: Path | None = None
        self._events: collections.deque[dict[str, Any]] = collections.deque()
        self._sample_subs: dict[str, Subscription] = {}  # device -> its streams' samples
        self._operator = ""
        self._event_sub: Subscription | None = None  # the journal: the devices' events and the supervisor's records
        self._record_sub: Subscription | None = None  # the supervisor's records when it publishes on another bus
        self._in_gap: dict[str, bool] = {}  # device -> no data now (writer thread only)
        self._device_streams: dict[str, list[str]] = {}
        self._reported_drops: dict[str, int] = {}
        self._reported_event_drops = 0
        self._outs: dict[str, _StreamOut] = {}
        self._events_fh: TextIO | None = None
        self._clock_fh: TextIO | None = None  # clocks.csv (writer thread)
        self._clock_logs: dict[str, DeviceClockLog] = {}  # device -> how its clock was mapped (writer thread)
        self._writer: threading.Thread | None = None
        self._stop = threading.Event()
        self._manifest: dict[str, Any] = {}
        self._flush_interval_s = 0.5
        self._lock = threading.Lock()  # start/stop only
        self._hooked: set[int] = set()
        self.event_count = 0
        self.on_failure: Callable[[str, str], None] | None = None  # (folder, error), once per failure
        self.failure = ""  # the write error, '' while recording works
        self.failure_t_wall: float | None = None
        self.failed_samples = 0  # dropped because the files could not be written
        self._kept_events: list[str] = []  # lines not yet known to be on disk after a failure
        self._unflushed: list[str] = []  # event lines written since the last successful flush
        self._events_synced = 0  # size of events.jsonl at the last successful flush (all of it on disk)
        self._next_retry = 0.0

    # ------------------------------------------------------------------ public
    @property
    def active(self) -> bool:
        return self._writer is not None

    def counts(self) -> dict[str, int]:
        return {name: out.count for name, out in self._outs.items()}

    @property
    def dropped(self) -> int:
        """Samples lost because the writer did not drain in time (every device)."""
        return sum(self._drops().values())

    def _drops(self) -> dict[str, int]:
        return {device: sub.dropped for device, sub in self._sample_subs.items()}

    def start(self, host: SessionHost, patient_id: str, operator: str, note: str = "",
              root: Path | None = None, profile: Any = None) -> Path:
        """Create the session folder, write the manifest, subscribe to the bus's streams and device events and
        to the supervisor's events; returns the folder. ``host`` is what the recorder uses of the
        application (app.therapy.services.SessionHost; the LinarmppManager is one)."""
        with self._lock:
            if self._writer is not None:
                raise RuntimeError(f"a session is already being recorded in {self.folder}")
            if not patient_id:
                raise ValueError("a session needs a patient")
            if not operator:
                raise ValueError("a session needs an operator")
            config = host.config
            self._flush_interval_s = min(float(config.recording.flush_interval_s), 1.0)
            t_wall, t_mono = time.time(), time.monotonic()
            now = _dt.datetime.fromtimestamp(t_wall).astimezone()
            rec = config.recording
            root = root or sessions_root(config)
            warning = check_free_space(root, float(getattr(rec, "warn_free_mib", 0)),
                                       float(getattr(rec, "min_free_mib", 0)))
            try:
                folder = _make_session_folder(root, patient_id, now)
            except OSError as exc:
                raise RecordingError(exc.errno or errno.EIO,
                                     f"cannot record in {root}: {exc.strerror or exc}") from exc
            try:
                self._begin(host, folder, patient_id, operator, note, profile, t_wall, t_mono, now)
            except BaseException as exc:
                self._abandon(folder)
                if isinstance(exc, OSError):
                    raise RecordingError(exc.errno or errno.EIO,
                                         f"cannot record in {root}: {exc.strerror or exc}") from exc
                raise
            self._stop.clear()
            self._operator = operator  # who the session's runs are recorded for (journal records of origin run)
            self._writer = threading.Thread(target=self._run, name="session-recorder", daemon=True)
            self._writer.start()
            self.event("session_start", operator, patient_id=patient_id, note=note, folder=str(folder))
            if warning:
                log.warning("%s", warning)
                self.event("low_disk_space", "recorder", warning=warning)
                from app.safety.supervisor import AlarmLevel

                host.supervisor.raise_alarm(AlarmLevel.WARNING, "recording", warning[:1].upper() + warning[1:])
            self._subscribe(host)
            if id(host) not in self._hooked:
                self._hooked.add(id(host))
                # Runs after the manager's safe-state actions, so those are recorded too; stop is idempotent.
                host.add_shutdown_hook(lambda: self.stop("application closing"))
            log.info("session recording in %s", folder)
            return folder

    def _abandon(self, folder: Path) -> None:
        """A start that failed: nothing was recorded yet, so no half-made session folder (and no open file)
        is left behind."""
        for out in self._outs.values():
            _discard_buffer(out.fh)
            _close_quietly(out.fh)
        self._outs.clear()
        if self._events_fh is not None:
            _close_quietly(self._events_fh)
            self._events_fh = None
        if self._clock_fh is not None:
            _close_quietly(self._clock_fh)
            self._clock_fh = None
        self.folder = None
        import shutil

        shutil.rmtree(folder, ignore_errors=True)

    def _begin(self, host: SessionHost, folder: Path, patient_id: str, operator: str, note: str,
               profile: Any, t_wall: float, t_mono: float, now: _dt.datetime) -> None:
        """The session's files: the reserve, one file per stream (every stream declared on the bus), the
        events, the first manifest."""
        config = host.config
        self._outs.clear()  # the last session's (closed) files: _abandon must see only this one's
        self._events_fh = None
        self._clock_fh = None
        (folder / STREAMS_DIR).mkdir(mode=DIR_MODE)
        _private_dir(folder / STREAMS_DIR)
        _reserve_space(folder / RESERVE_FILE, RESERVE_BYTES)
        self.folder = folder
        self._events.clear()
        self._sample_subs, self._event_sub, self._record_sub = {}, None, None  # the last session's queues, counts
        self._reported_drops.clear()
        self._reported_event_drops = 0
        self.event_count = 0
        self.failure, self.failure_t_wall, self.failed_samples = "", None, 0
        self._kept_events.clear()
        self._unflushed = []
        self._events_synced = 0
        if self.on_failure is None:
            self.on_failure = host.fault_policy.recording_failed
        specs = host.bus.specs()
        self._device_streams = {}
        for spec in specs.values():
            self._device_streams.setdefault(spec.device, []).append(spec.name)
        streams: dict[str, Any] = {}
        devices: dict[str, Any] = {}
        for name, handle in host.devices.items():
            driver = handle.driver
            devices[name] = {"simulated": handle.simulated, "connected": bool(driver.connected),
                             "streams": list(self._device_streams.get(name, [])), **_device_versions(driver)}
        for spec in specs.values():
            streams[spec.name] = _spec_dict(spec, spec.device, configured_rate_hz(config, spec.device, spec))
            path = folder / STREAMS_DIR / stream_file_name(spec.name)
            fh = _open_private(path, buffering=1 << 16)
            self._outs[spec.name] = _StreamOut(spec, fh, path)
            fh.write(",".join([TIME_COLUMN, *(c.name for c in spec.channels), ARRIVAL_COLUMN]) + "\n")
            fh.flush()  # the header on disk now: a stream file is never without its columns
        self._events_fh = _open_private(folder / EVENTS_FILE)
        self._clock_logs = {device: DeviceClockLog(device, wrap) for device, (_, wrap) in DEVICE_CLOCK_FIELDS.items()
                            if device in self._device_streams}
        self._clock_fh = _open_private(folder / CLOCK_FILE, buffering=1 << 14)
        self._clock_fh.write(",".join(CLOCK_COLUMNS) + "\n")
        self._clock_fh.flush()
        if profile is None:
            profile = _try_load_profile(patient_id, config)
        from app.core.config import config_as_dict
        from app.core.yamlschema import to_plain

        self._manifest = {
            "format_version": FORMAT_VERSION,
            # The session's identity in the clinic's archive (docs/archive.md): made here, at its start, so an
            # upload is idempotent and a session interrupted before its end is still one session.
            "session_uuid": str(uuid.uuid4()),
            "status": "recording",
            "patient_id": patient_id,
            "patient": to_plain(profile) if profile is not None and not isinstance(profile, str) else None,
            "patient_error": profile if isinstance(profile, str) else "",
            "operator": operator,
            "note": note,
            "app_version": app_version(),
            "host": _host(),
            "start": {"t_wall": wall_iso(t_wall), "t_wall_epoch_s": t_wall, "t_mono_s": t_mono,
                      "time_zone": now.tzname() or "", "utc_offset": now.strftime("%z")},
            "end": None,
            "devices": devices,
            "streams": streams,
            "config": config_as_dict(config),
            "config_source": getattr(config, "source", ""),
            "flush_interval_s": self._flush_interval_s,
            "counts": {},
        }
        write_json_atomic(folder / MANIFEST_FILE, self._manifest)

    def event(self, kind: str, who: str = "", **data: Any) -> None:
        """Record an event from the GUI, a script or a driver (any thread; never blocks).

        Conventions: ``script_start`` (name, text), ``script_stop`` (name, reason), ``parameter_change``
        (name, old, new), ``command`` (device, name, args, source) and ``ack`` (device, name, ok, detail).
        """
        self._enqueue_event(kind, who, "app", data)

    def stop(self, reason: str = "stopped") -> Path | None:
        """Detach, write everything still queued, close the files and finalise the manifest."""
        with self._lock:
            writer = self._writer
            if writer is None:
                return None
            self._unsubscribe()  # what is queued stays in the queues: the writer drains it below
            self.event("session_stop", "", reason=reason)
            self._stop.set()
            writer.join()
            self._writer = None
            t_wall, t_mono = time.time(), time.monotonic()
            now = _dt.datetime.fromtimestamp(t_wall).astimezone()
            folder = self.folder
            assert folder is not None
            self._release_reserve()  # room for the final manifest, however full the disk is now
            counts = self.counts()
            failure = None
            if self.failure:
                # What is in the files, not what was handed to them: a full disk refused the buffered lines.
                lost_in_buffers = 0
                for name, out in self._outs.items():
                    on_disk = out.on_disk if out.on_disk is not None else _lines_on_disk(out)
                    lost_in_buffers += max(0, out.count - on_disk)
                    counts[name] = on_disk
                failure = {"t_wall": wall_iso(self.failure_t_wall), "error": self.failure,
                           "samples_lost": self.failed_samples + lost_in_buffers,
                           "events_not_written": len(self._kept_events)}
            self._manifest.update({
                "status": "failed" if self.failure else "complete",
                "recording_failure": failure,
                "end": {"t_wall": wall_iso(t_wall), "t_wall_epoch_s": t_wall, "t_mono_s": t_mono,
                        "time_zone": now.tzname() or "", "utc_offset": now.strftime("%z"), "reason": reason},
                "duration_s": t_mono - self._manifest["start"]["t_mono_s"],
                "counts": counts,
                "first_t_mono_s": {n: o.first_t for n, o in self._outs.items()},
                "last_t_mono_s": {n: o.last_t for n, o in self._outs.items()},
                "dropped_samples": self._drops(),
                "dropped_device_events": self._event_sub.dropped if self._event_sub is not None else 0,
                "event_count": self.event_count - len(self._kept_events),
            })
            try:
                write_json_atomic(folder / MANIFEST_FILE, self._manifest)
            except OSError as exc:
                log.error("the manifest of %s could not be finalised: %s", folder, exc.strerror or exc)
                if self.failure:
                    self._write_failure_sidecar(failure)
            else:
                try:
                    (folder / FAILED_FILE).unlink(missing_ok=True)  # the manifest says it all now
                except OSError:
                    pass
            if self._kept_events:
                log.error("%d session events could not be written to %s", len(self._kept_events), folder)
            log.info("session recording stopped (%s): %s", reason, folder)
            return folder

    def _release_reserve(self) -> None:
        if self.folder is None:
            return
        try:
            (self.folder / RESERVE_FILE).unlink(missing_ok=True)
        except OSError as exc:
            log.warning("the space reserve of %s could not be removed: %s", self.folder, exc.strerror or exc)

    def _write_failure_sidecar(self, failure: dict[str, Any] | None) -> None:
        """The manifest could not say ``failed``: a small file next to it does (load_session reads it). Even
        on a disk without one free block an empty file can usually be made; the reason follows if it fits."""
        if self.folder is None:
            return
        try:
            fd = os.open(self.folder / FAILED_FILE, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
        except OSError as exc:
            log.error("not even %s could be written in %s: %s", FAILED_FILE, self.folder, exc.strerror or exc)
            return
        try:
            os.write(fd, json.dumps(failure or {"error": self.failure}, default=str).encode("utf-8") + b"\n")
        except OSError:
            pass  # the name alone says it
        finally:
            os.close(fd)

    # ------------------------------------------------------------------ producers (any thread)
    def _subscribe(self, host: SessionHost) -> None:
        """One queue per device for its samples and one for the journal: the devices' events and the supervisor's
        records (alarms, e-stop, refusals), in the order they were published on their threads."""
        bus = host.bus
        self._sample_subs = {device: bus.subscribe(f"recorder:{device}", names, maxlen=self.queue_limit)
                             for device, names in self._device_streams.items()}
        journal_bus = getattr(host.supervisor, "bus", bus)
        self._event_sub = bus.subscribe("recorder:journal", (), events=True, records=journal_bus is bus,
                                        keep_records=True, maxlen=DEVICE_EVENT_QUEUE)
        if journal_bus is not bus:  # a supervisor publishing on a bus of its own (a test's host)
            self._record_sub = journal_bus.subscribe("recorder:journal", (), records=True, keep_records=True,
                                                     maxlen=DEVICE_EVENT_QUEUE)
        self._in_gap = {}
        for name, handle in host.devices.items():
            self._in_gap[name] = not handle.driver.connected
            if self._in_gap[name]:
                self._enqueue_event("gap_start", name, "device", {
                    "device": name, "cause": "not connected", "detail": "",
                    "streams": list(self._device_streams.get(name, []))})

    def _unsubscribe(self) -> None:
        for sub in (*self._sample_subs.values(), self._event_sub, self._record_sub):
            if sub is not None:
                sub.close()

    def _journal_record(self, rec: Record) -> dict[str, Any]:
        """A journal record as a session event (writer thread)."""
        return journal_event(rec, self._operator, self._in_gap, self._device_streams)

    def _enqueue_event(self, kind: str, who: str, origin: str, data: dict[str, Any]) -> None:
        # Events are rare and must never be dropped: their queue is unbounded.
        self._events.append({"t_wall_epoch_s": time.time(), "t_mono": time.monotonic(), "kind": kind,
                             "who": who, "origin": origin, "data": data})

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        next_flush = time.monotonic() + self._flush_interval_s
        try:
            while True:
                stopping = self._stop.wait(_WRITER_PERIOD_S)
                now = time.monotonic()
                try:
                    if self.failure:
                        self._drain_failed(now, force=stopping)
                    else:
                        self._drain()
                        if stopping:
                            self._finish_clocks()
                        if stopping or now >= next_flush:
                            self._flush(sync=self.fsync)
                            next_flush = now + self._flush_interval_s
                except Exception as exc:  # a write error: never silent, never fatal
                    self._fail(exc)
                if stopping:
                    break
        finally:
            for out in self._outs.values():
                _close_quietly(out.fh)
            if self._events_fh is not None:
                _close_quietly(self._events_fh)
                self._events_fh = None
            if self._clock_fh is not None:
                _close_quietly(self._clock_fh)
                self._clock_fh = None

    def _fail(self, exc: BaseException) -> None:
        error = (f"{exc.strerror} (errno {exc.errno})" if isinstance(exc, OSError) and exc.strerror
                 else f"{type(exc).__name__}: {exc}")
        first = not self.failure
        self.failure = self.failure or error
        self.failure_t_wall = self.failure_t_wall or time.time()
        self._next_retry = time.monotonic() + _RETRY_PERIOD_S
        # What was written since the last successful flush may not be on disk: keep it to write again.
        self._kept_events[:0] = self._unflushed
        self._unflushed = []
        if not first:
            return
        log.error("recording failed in %s: %s", self.folder, error)
        # The files' buffers hold lines the disk refused: drop them (they would be written over the room
        # freed below at close) and cut each file after its last whole line. Samples are not written again
        # (counted at stop); the event lines since the last flush are in _kept_events.
        for out in self._outs.values():
            _discard_buffer(out.fh)
            if out.path is not None:
                try:
                    _cut_to_last_line(out.path)
                except OSError:
                    pass
            out.on_disk = _lines_on_disk(out)  # counted here, on the writer thread, not at stop on the GUI's
        if self._events_fh is not None:
            _discard_buffer(self._events_fh)
        if self._clock_fh is not None:  # the clock lines stop with the samples (a line cut short is cut off)
            _discard_buffer(self._clock_fh)
            _close_quietly(self._clock_fh)
            self._clock_fh = None
            if self.folder is not None:
                try:
                    _cut_to_last_line(self.folder / CLOCK_FILE)
                except OSError:
                    pass
        self._release_reserve()
        self._enqueue_event("recording_failed", "recorder", "recorder", {"folder": str(self.folder), "error": error})
        self._manifest.update({"status": "failed", "recording_failure": {
            "t_wall": wall_iso(self.failure_t_wall), "error": error}})
        if self.folder is not None:
            try:
                write_json_atomic(self.folder / MANIFEST_FILE, self._manifest)
            except Exception:
                self._write_failure_sidecar(self._manifest["recording_failure"])  # the stop tries again
        self._next_retry = 0.0  # the kept events into the freed room at once
        if self.on_failure is not None:
            try:
                self.on_failure(str(self.folder), error)
            except Exception:
                log.exception("recording failure handler failed")

    def _drain_failed(self, now: float, force: bool) -> None:
        """After a write error: samples are dropped (counted); events are kept and tried again each second."""
        self.failed_samples += sum(len(sub.drain()) for sub in self._sample_subs.values())
        for ev in self._take_events():
            record = written_event(ev)
            self._kept_events.append(json.dumps(record, ensure_ascii=False, default=str) + "\n")
            self.event_count += 1
        if not (force or now >= self._next_retry) or self.folder is None:
            return
        self._next_retry = now + _RETRY_PERIOD_S
        if not self._kept_events:
            return
        # A fresh descriptor, cut back to what the last good flush left on disk: the kept lines include
        # every line since then, so none is written twice and no half line stays in the file.
        data = "".join(self._kept_events).encode("utf-8")
        try:
            fd = os.open(self.folder / EVENTS_FILE, os.O_WRONLY | os.O_CREAT, FILE_MODE)
        except OSError:
            return
        synced = self._events_synced
        try:
            os.ftruncate(fd, synced)
            os.lseek(fd, synced, os.SEEK_SET)
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            if self.fsync:
                os.fsync(fd)
        except OSError:
            try:
                os.ftruncate(fd, synced)
            except OSError:
                pass
            return
        finally:
            os.close(fd)
        self._events_synced = synced + len(data)
        log.info("recording: %d kept events written to %s", len(self._kept_events), self.folder)
        self._kept_events.clear()

    def _take_events(self) -> list[dict[str, Any]]:
        """The events to write now, in time order: the application's and the recorder's own (queued by
        ``_enqueue_event``) merged with the journal from the bus (the devices' events, the supervisor's records)."""
        events = self._events
        pending = [events.popleft() for _ in range(len(events))]
        sub = self._event_sub
        for journal_sub in (sub, self._record_sub):
            if journal_sub is None:
                continue
            published = [self._journal_record(ev) for ev in journal_sub.drain() if isinstance(ev, Record)]
            if published:
                pending = list(heapq.merge(pending, published, key=lambda e: e["t_mono"]))
        if sub is not None:
            if sub.dropped != self._reported_event_drops:
                self._reported_event_drops = sub.dropped
                pending.append(self._recorder_event("device_events_dropped", {
                    "dropped_total": sub.dropped, "reason": "recorder queue full (disk too slow)"}))
        return pending

    @staticmethod
    def _recorder_event(kind: str, data: dict[str, Any]) -> dict[str, Any]:
        return {"t_wall_epoch_s": time.time(), "t_mono": time.monotonic(), "kind": kind, "who": "recorder",
                "origin": "recorder", "data": data}

    def _drain(self) -> None:
        outs = self._outs
        clock_fh = self._clock_fh
        for device, sub in self._sample_subs.items():
            items = sub.drain()
            clock = self._clock_logs.get(device) if clock_fh is not None else None
            reading = DEVICE_CLOCK_FIELDS[device][0] if clock is not None else ""
            for k, item in enumerate(items):
                out = outs.get(item.stream)  # type: ignore[union-attr]  # a sample subscription: SampleItems
                if out is None:
                    continue
                t = item.t  # type: ignore[union-attr]
                sample = item.sample  # type: ignore[union-attr]
                values = [repr(float(t))]
                for ch in out.spec.channels:
                    try:
                        values.append(repr(float(getattr(sample, ch.name))))
                    except (TypeError, ValueError, AttributeError):
                        values.append("nan")
                values.append(repr(float(item.arrival)))  # type: ignore[union-attr]
                try:
                    out.fh.write(",".join(values) + "\n")
                except BaseException:
                    self.failed_samples += len(items) - k  # this one and the rest of the batch: not written
                    raise
                out.count += 1
                if out.first_t is None:
                    out.first_t = t
                out.last_t = t
                if clock is not None and (line := clock.feed(t, getattr(sample, reading, None))):
                    clock_fh.write(line)  # type: ignore[union-attr]
        for device, dropped in self._drops().items():
            if dropped != self._reported_drops.get(device, 0):
                self._enqueue_event("samples_dropped", "recorder", "recorder",
                                    {"device": device, "dropped_total": dropped,
                                     "reason": "recorder queue full (disk too slow)"})
                self._reported_drops[device] = dropped
        pending = self._take_events()
        fh = self._events_fh
        wrote = False
        for k, ev in enumerate(pending):
            record = written_event(ev)
            line = json.dumps(record, ensure_ascii=False, default=str) + "\n"
            self._unflushed.append(line)  # before the write: a failing write keeps the event
            if fh is not None:
                try:
                    fh.write(line)
                except BaseException:
                    self._events.extendleft(reversed(pending[k + 1:]))  # the rest: kept for the failure path
                    self.event_count += 1
                    raise
                wrote = True
            self.event_count += 1
        if wrote and fh is not None:
            fh.flush()  # events (e-stop, alarms) reach the OS at once; fsync follows at the flush interval

    def _finish_clocks(self) -> None:
        if self._clock_fh is None:
            return
        for clock in self._clock_logs.values():
            if line := clock.finish():
                self._clock_fh.write(line)

    def _flush(self, sync: bool) -> None:
        files = [o.fh for o in self._outs.values()]
        if self._events_fh is not None:
            files.append(self._events_fh)
        if self._clock_fh is not None:
            files.append(self._clock_fh)
        for fh in files:
            fh.flush()
            if sync:
                try:
                    os.fsync(fh.fileno())
                except OSError as exc:
                    if exc.errno in (errno.EINVAL, errno.ENOTSUP, errno.EROFS) and not isinstance(exc, RecordingError):
                        log.warning("fsync failed for %s", getattr(fh, "name", fh))  # the device cannot sync
                    else:
                        raise
        if self._events_fh is not None:
            self._events_synced = os.fstat(self._events_fh.fileno()).st_size
        self._unflushed = []


def _lines_on_disk(out: _StreamOut) -> int:
    """Samples a stream file holds (its complete lines but the header)."""
    if out.path is None:
        return out.count
    try:
        return max(0, _count_lines(out.path) - 1)
    except OSError:
        return 0


def _close_quietly(fh: TextIO) -> None:
    try:
        fh.flush()
        fh.close()
    except OSError:
        log.exception("closing %s failed", getattr(fh, "name", fh))


def _host() -> dict[str, str]:
    import platform

    return {"node": platform.node(), "system": platform.system(), "release": platform.release(),
            "python": platform.python_version()}


def _try_load_profile(patient_id: str, config: AppConfig) -> Any:
    """The patient's profile for the manifest; the error text when it cannot be loaded; None if absent."""
    from app.therapy.patients import load_patient, patient_file

    try:
        if not patient_file(patient_id).exists():
            return None
        return load_patient(patient_id, config.safety)
    except Exception as exc:
        return str(exc)


# ---------------------------------------------------------------------------------------------- reading
@dataclass
class RecordedStream:
    name: str
    channels: tuple[Channel, ...]
    nominal_rate_hz: float
    t: np.ndarray
    data: dict[str, np.ndarray]
    device: str = ""
    dropped_lines: int = 0  # a cut-short last line (crash) or unreadable lines
    arrival: np.ndarray | None = None  # when each sample's read returned (files before #27: None)

    @property
    def spec(self) -> StreamSpec:
        return StreamSpec(self.name, self.channels, self.nominal_rate_hz)

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class RecordedSession:
    folder: Path
    manifest: dict[str, Any]
    streams: dict[str, RecordedStream]
    events: list[dict[str, Any]]
    problems: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        """False when the session was not stopped normally (crash, kill, power cut) or its recording failed."""
        return self.manifest.get("status") == "complete"

    @property
    def status(self) -> str:
        """``complete``, ``failed`` (a write error: docs/sessions.md), ``recording`` (never stopped: a crash)."""
        return str(self.manifest.get("status") or "unknown")

    @property
    def start_mono(self) -> float:
        start = (self.manifest.get("start") or {}).get("t_mono_s")
        if start is not None:
            return float(start)
        firsts = [s.t[0] for s in self.streams.values() if len(s.t)]
        return float(min(firsts)) if firsts else 0.0

    @property
    def end_mono(self) -> float:
        ends = [float(s.t[-1]) for s in self.streams.values() if len(s.t)]
        ends += [float(e["t_mono"]) for e in self.events if isinstance(e.get("t_mono"), int | float)]
        end = (self.manifest.get("end") or {}).get("t_mono_s")
        if end is not None:
            ends.append(float(end))
        return max(ends) if ends else self.start_mono

    @property
    def duration_s(self) -> float:
        return max(0.0, self.end_mono - self.start_mono)

    def wall_time(self, t_mono: float) -> float:
        """Epoch seconds of a monotonic time stamp, via the start anchor."""
        start = self.manifest.get("start") or {}
        return float(start.get("t_wall_epoch_s", 0.0)) + (t_mono - self.start_mono)


def _read_text_lines(path: Path) -> tuple[list[str], int]:
    """Complete lines of a file; a last line without its newline (cut by a crash) is dropped and counted."""
    text = path.read_bytes().decode("utf-8", errors="replace")
    lines = text.split("\n")
    tail = lines.pop()  # "" when the file ends with a newline, else a partial line
    return lines, (1 if tail else 0)


# The bytes of plain numbers as the recorder writes them (repr of floats: digits, sign, point, exponent, nan, inf);
# a file holding any other (a quote pandas would unquote, a space or a carriage return float() would strip) is
# parsed by float() field by field, as before.
_PLAIN = b"0123456789.,-+eEnaNiIfFty\n"
_PANDAS_MIN_BYTES = 1 << 20  # below, Python's parse takes less than importing pandas the first time (~0.3 s)


def csv_values(body: bytes, ncols: int, usecols: list[int] | None = None) -> np.ndarray | None:
    """Whole lines of plain comma-separated numbers (no header) as float64 [lines, ncols] (or the ``usecols``
    columns), parsed by pandas' C parser: ~10x faster than Python's float() of each field, and bit for bit the
    same values (the shortest repr the recorder writes reads back exactly; nan, inf and -inf as float() reads
    them). None when the text is not plain numbers (an empty or quoted field, a blank line, a value that is not a
    number): the caller's slower parse then decides line by line."""
    if len(body) < _PANDAS_MIN_BYTES or body.translate(None, _PLAIN):  # (an empty field: pandas refuses it too)
        return None
    try:
        values = read_csv_numbers(body, ncols, usecols)
    except ImportError:  # a dependency; the slower parse stays exact without it
        return None
    except ValueError:  # pandas' ParserError is one
        return None
    lines = body.count(b"\n") + (0 if body.endswith(b"\n") else 1)
    return values if len(values) == lines else None  # (pandas skips a blank line: then line by line)


def read_csv_numbers(body: bytes, ncols: int, usecols: list[int] | None = None) -> np.ndarray:
    """Comma-separated numbers (no header) as float64 [rows, ncols] (or the ``usecols`` columns) by pandas' C
    parser, with the settings that give float()'s values bit for bit: the one place they are set (the research
    export parses its blocks with it too). Raises ValueError on a field that is not a number; skips blank lines."""
    import pandas as pd

    kwargs: dict[str, Any] = {}
    if int(pd.__version__.split(".", 1)[0]) < 3:
        kwargs["float_precision"] = "round_trip"  # pandas 3 reads the shortest repr back exactly by default
    frame = pd.read_csv(io.BytesIO(body), header=None, names=range(ncols), usecols=usecols, dtype=np.float64,
                        engine="c", na_filter=True, keep_default_na=False, na_values=["nan", "NaN", "-nan"], **kwargs)
    return frame.to_numpy(dtype=np.float64)


def read_stream_csv(path: Path) -> tuple[list[str], np.ndarray, int]:
    """(column names, values [n, columns] float64, dropped line count) of a stream file.

    The complete lines are parsed as bytes in one call when every line has the header's number of fields; a file
    with a damaged line is read line by line and keeps the good ones. Values are Python's own float parse of the
    ``repr`` the recorder wrote: exact. (Parsing is what makes a long session slow to read -- some 150 ns a value;
    :func:`load_session` reads the columnar side-file instead when there is one.)"""
    raw = path.read_bytes()
    first = raw.find(b"\n")
    if first < 0:  # not even a whole header
        return [], np.zeros((0, 0)), (1 if raw else 0)
    header = raw[:first].decode("utf-8", errors="replace").split(",")
    ncols = len(header)
    body = raw[first + 1:]
    last = body.rfind(b"\n")
    dropped = 1 if len(body) - (last + 1) > 0 else 0  # a last line cut short by a crash
    body = body[:last + 1]
    nlines = body.count(b"\n")
    if nlines == 0:
        return header, np.zeros((0, ncols)), dropped
    if body.count(b",") == nlines * (ncols - 1) and b"\n\n" not in body and not body.startswith(b"\n"):
        fast = csv_values(body, ncols)
        if fast is not None and fast.shape == (nlines, ncols):
            return header, fast, dropped
        try:
            flat = np.array(body[:-1].replace(b"\n", b",").split(b","), dtype=np.float64)
        except ValueError:  # a field that is not a number: the slow path finds which line
            pass
        else:
            if flat.size == nlines * ncols:
                return header, flat.reshape(nlines, ncols), dropped
    lines = body.decode("utf-8", errors="replace").split("\n")[:-1]
    good = [ln for ln in lines if ln and ln.count(",") == ncols - 1]
    dropped += len(lines) - len(good)
    rows = []
    for ln in good:
        try:
            rows.append([float(x) for x in ln.split(",")])
        except ValueError:
            dropped += 1
    return header, np.array(rows, dtype=np.float64).reshape(len(rows), ncols), dropped


def _event_lines(path: Path) -> tuple[list[tuple[int, dict[str, Any]]], int]:
    """(line number, record) of every readable event, and the count of unreadable lines."""
    if not path.exists():
        return [], 0
    lines, dropped = _read_text_lines(path)
    out = []
    for number, ln in enumerate(lines, start=1):
        if not ln.strip():
            continue
        try:
            record = json.loads(ln)
        except (json.JSONDecodeError, RecursionError):
            dropped += 1
            continue
        if isinstance(record, dict):
            out.append((number, record))
        else:  # not an event (a hand-edited or damaged file): counted like a cut line
            dropped += 1
    return out, dropped


def read_events(path: Path) -> tuple[list[dict[str, Any]], int]:
    records, dropped = _event_lines(path)
    return [r for _n, r in records], dropped


@dataclass(frozen=True)
class ClockLines:
    """One device's lines of ``clocks.csv`` (DeviceClockLog): from ``host[i]`` and ``device[i]`` on,
    ``host = host[i] + (device − device[i])·(1 + drift[i])``."""

    host: np.ndarray
    device: np.ndarray
    drift: np.ndarray

    def __len__(self) -> int:
        return len(self.host)

    def to_device(self, host: np.ndarray) -> np.ndarray:
        """Device times of samples recorded at ``host`` (each on the line in force when it was taken)."""
        i = np.clip(np.searchsorted(self.host, host, side="right") - 1, 0, None)
        return self.device[i] + (host - self.host[i]) / (1.0 + self.drift[i])


def parse_clock_lines(data: bytes) -> tuple[dict[str, ClockLines], int]:
    """The lines of a ``clocks.csv`` by device, and how many were dropped (cut short by a crash, damaged)."""
    lines = data.decode("utf-8", errors="replace").split("\n")
    dropped = 1 if lines.pop() else 0  # a last line without its newline
    rows: dict[str, list[tuple[float, float, float]]] = {}
    for ln in lines[1:] if lines and lines[0] == ",".join(CLOCK_COLUMNS) else lines:
        parts = ln.split(",")
        try:
            host, device, drift = float(parts[0]), float(parts[2]), float(parts[3])
        except (ValueError, IndexError):
            dropped += 1
            continue
        if len(parts) != len(CLOCK_COLUMNS) or not all(map(math.isfinite, (host, device, drift))):
            dropped += 1
            continue
        rows.setdefault(parts[1], []).append((host, device, drift))
    out = {}
    for name, got in rows.items():
        got.sort()
        table = np.array(got, dtype=np.float64)
        out[name] = ClockLines(table[:, 0].copy(), table[:, 1].copy(), table[:, 2].copy())
    return out, dropped


def read_failure_sidecar(folder: Path) -> dict[str, Any] | None:
    """What ``recording-failed.txt`` says (the recorder wrote it when the manifest could not say
    ``failed``); None when there is none."""
    path = folder / FAILED_FILE
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        return {"error": f"(unreadable: {exc.strerror or exc})"}
    return failure_of_sidecar(raw)


def failure_of_sidecar(raw: bytes) -> dict[str, Any]:
    """What the bytes of ``recording-failed.txt`` say (a session folder's, or the archive's copy of it)."""
    text = raw[:65536].decode("utf-8", errors="replace")
    try:
        data = json.loads(text) if text.strip() else {}
    except (json.JSONDecodeError, RecursionError):
        data = {"error": text.strip()[:500]}
    if not isinstance(data, dict):
        data = {}
    data.setdefault("error", "the reason could not be written")
    return data


def _manifest_with_sidecar(folder: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    return manifest_with_failure(manifest, read_failure_sidecar(folder))


def manifest_with_failure(manifest: dict[str, Any], failure: dict[str, Any] | None) -> dict[str, Any]:
    """The manifest as the loader reads it: ``failed``, with the sidecar's reason, when there is a sidecar."""
    if failure is None or manifest.get("status") == "failed":
        return manifest
    return {**manifest, "status": "failed", "recording_failure": {**(manifest.get("recording_failure") or {}),
                                                                 **failure}}


def _status_problem(manifest: dict[str, Any]) -> str:
    status = manifest.get("status")
    if status == "complete":
        return ""
    if status == "failed":
        f = manifest.get("recording_failure") or {}
        at = f" at {f['t_wall']}" if f.get("t_wall") else ""
        lost = []
        if f.get("samples_lost"):
            lost.append(f"{f['samples_lost']} samples")
        if f.get("events_not_written"):
            lost.append(f"{f['events_not_written']} events")
        tail = f"; {' and '.join(lost)} could not be written" if lost else ""
        ended = "" if manifest.get("end") else "; the session has no end time"
        return f"the recording failed{at}: {f.get('error') or 'reason unknown'}{tail}{ended}; data end at the failure"
    if status == "recording":
        return ("the session was not stopped normally (crash, kill or power cut): no end time; "
                "data end at the last flush")
    return f"the manifest's status is {status!r}, not 'complete'"


# ---------------------------------------------------------------------------------------------- columns side-file
# A derived, columnar copy of the stream files (issue #37): ``<session>/.columns/<stream file>.npy`` holds the parsed
# table as float64 [columns, samples] (every column contiguous) and ``index.json`` what each copy was made from
# (the CSV's size, its modification time, its dropped lines). It is a cache: the CSV files stay the record, a copy
# that no longer matches its CSV is ignored, and the folder may be deleted at any time. Written in the worker
# process (app/worker) at a session's end or at its first load; read by load_session and mapped by the replay.
COLUMNS_DIR = ".columns"
COLUMNS_INDEX = "index.json"
COLUMNS_FORMAT = 1
COLUMNS_QUIET_S = 60.0  # a session still being written (or crashed a moment ago) is not indexed: its files change
MAX_SESSION_S = 24 * 3600.0  # a time further than this from the session's start and its data is not one of it
_TAIL_BYTES = 4096


@dataclass
class StreamTable:
    """A stream file's parsed table: the header's names and the values as [columns, samples]."""

    header: list[str]
    columns: np.ndarray  # float64 [len(header), n]
    dropped: int

    @property
    def rows(self) -> int:
        return int(self.columns.shape[1]) if self.columns.ndim == 2 else 0


def _columns_name(rel: str) -> str:
    return safe_name(Path(rel).name) + ".npy"


def _read_columns_index(folder: Path) -> dict[str, Any]:
    try:
        index = json.loads((folder / COLUMNS_DIR / COLUMNS_INDEX).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return {}
    if not isinstance(index, dict) or index.get("format") != COLUMNS_FORMAT or not isinstance(index.get("files"), dict):
        return {}
    return index["files"]


def _last_line_values(path: Path, ncols: int) -> np.ndarray | None:
    """The values of the last complete line of a CSV (its last 4 KB read)."""
    try:
        with open(path, "rb") as fh:
            size = fh.seek(0, os.SEEK_END)
            fh.seek(max(0, size - _TAIL_BYTES))
            tail = fh.read()
    except OSError:
        return None
    lines = tail.split(b"\n")[:-1]
    if not lines:
        return None
    try:
        values = np.array(lines[-1].split(b","), dtype=np.float64)
    except ValueError:
        return None
    return values if values.size == ncols else None


def columns_path(folder: Path, rel: str, *, check: bool = True) -> Path | None:
    """The side-file of the stream file ``rel`` when it is there and still matches that file, else None.
    A match: the CSV's size is the one recorded, and its modification time too -- or, for a copied folder (new
    times), its last line holds exactly the copy's last row."""
    entry = _read_columns_index(folder).get(rel)
    if not isinstance(entry, dict):
        return None
    npy = folder / COLUMNS_DIR / _columns_name(rel)
    try:
        st = (folder / rel).stat()
        if not npy.is_file() or st.st_size != entry.get("size"):
            return None
    except OSError:
        return None
    if not check or st.st_mtime_ns == entry.get("mtime_ns"):
        return npy
    rows, ncols = entry.get("rows"), len(entry.get("header") or [])
    if not rows:
        return npy if rows == 0 else None
    last = _last_line_values(folder / rel, ncols)
    if last is None:
        return None
    try:
        table = np.load(npy, mmap_mode="r")
        same = table.shape == (ncols, rows) and np.array_equal(np.asarray(table[:, -1]), last, equal_nan=True)
    except (OSError, ValueError):
        return None
    return npy if same else None


def _load_columns(folder: Path, rel: str, mmap: bool = False) -> StreamTable | None:
    npy = columns_path(folder, rel)
    if npy is None:
        return None
    entry = _read_columns_index(folder)[rel]
    try:
        columns = np.load(npy, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError):
        return None
    header = [str(h) for h in entry.get("header") or []]
    if columns.ndim != 2 or columns.shape != (len(header), entry.get("rows")) or columns.dtype != np.float64:
        return None
    return StreamTable(header, columns, int(entry.get("dropped") or 0))


def read_stream_table(folder: Path, rel: str, columns: bool = True, mmap: bool = False) -> StreamTable:
    """A stream file's table: from its columnar side-file when that matches the file, else parsed from the CSV."""
    if columns:
        table = _load_columns(folder, rel, mmap)
        if table is not None:
            return table
    header, values, dropped = read_stream_csv(folder / rel)
    return StreamTable(header, np.ascontiguousarray(values.T), dropped)


def _stream_files(folder: Path) -> list[str]:
    """The session's stream files (relative paths), whether or not the manifest names them."""
    return sorted(f"{STREAMS_DIR}/{p.name}" for p in (folder / STREAMS_DIR).glob("*.csv") if p.is_file())


def index_session(folder: str | Path, *, force: bool = False,
                  progress: Callable[[float], object] | None = None) -> str:
    """Write the columnar side-file of every stream file that has none (or a stale one). Returns '' when done
    (or nothing was needed), else why not in words: a session still being written, a folder that cannot be
    written. Meant for the worker process: it parses every CSV it has to index."""
    folder = Path(folder)
    files = _stream_files(folder)
    if not files:
        return ""
    if not force:
        try:
            manifest = json.loads((folder / MANIFEST_FILE).read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError):
            manifest = {}
        newest = max(((folder / rel).stat().st_mtime for rel in files), default=0.0)
        if (not isinstance(manifest, dict) or manifest.get("status") == "recording") \
                and time.time() - newest < COLUMNS_QUIET_S:
            return "the session is still being recorded"
    todo = [rel for rel in files if columns_path(folder, rel) is None]
    if not todo:
        return ""
    try:
        sizes = [(folder / rel).stat().st_size for rel in todo]
        for k, rel in enumerate(todo):
            if progress is not None:
                progress(sum(sizes[:k]) / max(1, sum(sizes)))
            st = (folder / rel).stat()
            header, values, dropped = read_stream_csv(folder / rel)
            if (folder / rel).stat().st_size != st.st_size:
                return f"{rel} changed while it was read"
            columns = np.ascontiguousarray(values.T) if values.size else np.zeros((len(header), 0))
            save_columns(folder, rel, header, columns, dropped, st)
    except OSError as exc:
        return f"the columnar copy of {folder} could not be written: {exc.strerror or exc}"
    return ""


def save_columns(folder: Path, rel: str, header: list[str], columns: np.ndarray, dropped: int = 0,
                 st: os.stat_result | None = None) -> None:
    """Write the side-file of the stream file ``rel`` from its parsed table ``columns`` [len(header), n] (exactly
    what parsing the file gives), and record in the index what it was made from (``st``: the file's stat when it
    was read; now by default). Raises OSError."""
    st = st or (folder / rel).stat()
    out = folder / COLUMNS_DIR
    out.mkdir(mode=DIR_MODE, exist_ok=True)
    _save_npy_atomic(out / _columns_name(rel), np.ascontiguousarray(columns, dtype=np.float64))
    index = _read_columns_index(folder)
    index[rel] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "rows": int(columns.shape[1]),
                  "header": list(header), "dropped": int(dropped)}
    write_json_atomic(out / COLUMNS_INDEX, {"format": COLUMNS_FORMAT, "files": index})


INDEX_MIN_BYTES = 8 << 20  # below this (a minute or two of recording) the CSV files parse in well under 0.1 s


def index_worthwhile(folder: Path) -> bool:
    """Whether a session's files are large enough for a columnar copy to matter (a few stat calls)."""
    try:
        return sum((folder / rel).stat().st_size for rel in _stream_files(folder)) >= INDEX_MIN_BYTES
    except OSError:
        return False


def _save_npy_atomic(path: Path, array: np.ndarray) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
        with open(fd, "wb") as fh:
            np.save(fh, array, allow_pickle=False)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


# ---------------------------------------------------------------------------------------------- loading
def _finite_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)


def _checked_manifest_times(manifest: dict[str, Any], problems: list[str]) -> dict[str, Any]:
    """A start or end time that is not a number is reported and left out (the data's own times are used)."""
    out = manifest
    for part in ("start", "end"):
        section = manifest.get(part)
        if isinstance(section, dict) and "t_mono_s" in section and section["t_mono_s"] is not None \
                and not _finite_number(section["t_mono_s"]):
            problems.append(f"the manifest's {part} time {section['t_mono_s']!r} is not a time; not used")
            out = {**out, part: {k: v for k, v in section.items() if k != "t_mono_s"}}
    return out


def _checked_events(records: list[tuple[int, dict[str, Any]]], anchors: list[float],
                    problems: list[str]) -> list[dict[str, Any]]:
    """Events every reader can use: a time that is a number within the session, a kind that is a text, data
    that is an object. An event without a usable time is left out (it has no place on the time line); a wrong
    kind or data is replaced. Each is one line of ``problems``, naming the event's line in events.jsonl."""
    out = []
    for number, e in records:
        t, kind = e.get("t_mono"), e.get("kind")
        what = f"{EVENTS_FILE} line {number} ({kind if isinstance(kind, str) else 'no kind'})"
        if not _finite_number(t):
            problems.append(f"{what}: its time {t!r} is not a number; the event was left out")
            continue
        if not _plausible(np.array([float(t)]), anchors)[0]:
            problems.append(f"{what}: its time {t!r} is outside the session; the event was left out")
            continue
        if not isinstance(kind, str):
            problems.append(f"{what}: its kind {kind!r} is not a text; read as 'unknown'")
            e = {**e, "kind": "unknown"}
        if "data" in e and not isinstance(e["data"], dict):
            problems.append(f"{what}: its data {str(e['data'])[:40]!r} is not an object; left empty")
            e = {**e, "data": {}}
        out.append(e)
    return out


def _time_anchors(manifest: dict[str, Any], tables: dict[str, StreamTable]) -> list[float]:
    """Times the session certainly covers: its start in the manifest and the median time of each stream. A sample
    or event further than MAX_SESSION_S from all of them is a forged or corrupted time (one such value must not
    stretch the session's time line to the year 3000: issue #37, replay's OverflowError)."""
    anchors = []
    start = (manifest.get("start") or {}).get("t_mono_s")
    if _finite_number(start):
        anchors.append(float(start))
    for table in tables.values():
        if table.rows:
            t = np.asarray(table.columns[0])
            finite = t[np.isfinite(t)]
            if finite.size:
                anchors.append(float(np.median(finite)))
    return anchors


def _plausible(t: np.ndarray, anchors: list[float]) -> np.ndarray:
    ok = np.isfinite(t)
    if not anchors:
        return ok
    near = np.zeros(t.shape, dtype=bool)
    for a in anchors:
        near |= np.abs(t - a) <= MAX_SESSION_S
    return ok & near


def load_session(folder: str | Path, *, columns: bool = True, mmap: bool = False) -> RecordedSession:
    """Read a session folder, tolerant of a crash (a missing end, a cut-short last line) and of damage (a line
    or an event time that cannot be read is left out and listed in ``problems``).

    ``columns``: read each stream from its columnar side-file when it matches its CSV (fast; see
    :func:`index_session`); ``mmap``: map those side-files instead of reading them (the arrays are then
    read-only)."""
    folder = Path(folder)
    problems: list[str] = []
    try:
        manifest = json.loads((folder / MANIFEST_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: not UTF-8 or not JSON
        manifest = {}
        problems.append(f"manifest unreadable: {exc}")
    if not isinstance(manifest, dict):
        manifest = {}
        problems.append("manifest unreadable: not a JSON object")
    manifest = _manifest_with_sidecar(folder, manifest)
    if manifest and (problem := _status_problem(manifest)):
        problems.append(problem)
    manifest = _checked_manifest_times(manifest, problems)
    specs: dict[str, Any] = dict(manifest.get("streams") or {})
    known_files = {v.get("file") for v in specs.values() if isinstance(v, dict)}
    for path in sorted((folder / STREAMS_DIR).glob("*.csv")):
        rel = f"{STREAMS_DIR}/{path.name}"
        if rel not in known_files and path.stem not in specs:  # no manifest entry: names from the header, no units
            specs[path.stem] = {"file": rel, "device": "", "nominal_rate_hz": 0.0, "channels": None}
    tables: dict[str, tuple[dict[str, Any], StreamTable]] = {}
    streams_dir = (folder / STREAMS_DIR).resolve()
    for name, spec in specs.items():
        rel = spec.get("file") if isinstance(spec, dict) else None
        if not isinstance(rel, str):
            problems.append(f"{name}: the manifest names no file")
            continue
        path = folder / rel
        # A session folder may come from elsewhere: read only regular files of its own streams folder
        # (a manifest naming ../../dev/zero or a FIFO would read forever).
        if path.resolve().parent != streams_dir or path.suffix != ".csv":
            problems.append(f"{name}: file {rel!r} is not in the session's {STREAMS_DIR} folder; not read")
            continue
        if not path.exists():
            problems.append(f"{name}: file {rel} is missing")
            continue
        if not path.is_file():
            problems.append(f"{name}: file {rel} is not a regular file; not read")
            continue
        tables[name] = (spec, read_stream_table(folder, f"{STREAMS_DIR}/{path.name}", columns, mmap))
    anchors = _time_anchors(manifest, {n: t for n, (_s, t) in tables.items()})
    streams: dict[str, RecordedStream] = {}
    for name, (spec, table) in tables.items():
        header, values, dropped = list(table.header), table.columns, table.dropped
        arrival = None
        if header and header[-1] == ARRIVAL_COLUMN:
            if values.ndim == 2 and values.shape[0] == len(header):
                arrival, values = values[-1], values[:-1]
            header = header[:-1]
        if spec.get("channels") is None:
            channels = tuple(Channel(h, "", h) for h in header[1:])
        else:
            channels = tuple(Channel(c["name"], c.get("unit", ""), c.get("label", c["name"]))
                             for c in spec["channels"])
        columns_ = header[1:] if header else [c.name for c in channels]
        if header and [c.name for c in channels] != columns_:
            problems.append(f"{name}: file columns {columns_} differ from the manifest; using the file's")
            channels = tuple(Channel(h, "", h) for h in columns_)
        if values.size == 0:
            values, arrival = np.zeros((len(channels) + 1, 0)), (None if arrival is None else np.zeros(0))
        t = values[0]
        bad = ~_plausible(np.asarray(t), anchors)
        if bad.any():  # a forged or corrupted time: the sample has no place on the time line
            problems.append(f"{name}: {int(bad.sum())} sample(s) with a time outside the session left out")
            keep = ~bad
            values = values[:, keep]
            arrival = None if arrival is None else arrival[keep]
            t = values[0]
        data = {c.name: values[i + 1] for i, c in enumerate(channels)}
        streams[name] = RecordedStream(name, channels, float(spec.get("nominal_rate_hz") or 0.0), t, data,
                                       device=spec.get("device", ""), dropped_lines=dropped, arrival=arrival)
        if dropped:
            problems.append(f"{name}: {dropped} incomplete line(s) dropped")
    records, dropped = _event_lines(folder / EVENTS_FILE)
    if not (folder / EVENTS_FILE).exists():
        problems.append(f"{EVENTS_FILE} is missing")
    if dropped:
        problems.append(f"events: {dropped} incomplete line(s) dropped")
    events = _checked_events(records, anchors, problems)
    problems += _count_problems(manifest, streams, events, len(records))
    return RecordedSession(folder, manifest, streams, events, problems)


def _count_problems(manifest: dict[str, Any], streams: dict[str, RecordedStream],
                    events: list[dict[str, Any]], readable_events: int | None = None) -> list[str]:
    """What the stopped session's manifest counted and the files no longer hold (a truncated copy, a
    file cut by hand), and the samples the recorder had to drop."""
    out = []
    counts = manifest.get("counts") or {}
    specs = manifest.get("streams") or {}
    for name, expected in counts.items():
        if not isinstance(expected, int) or name not in streams:
            continue
        have = len(streams[name])
        if have < expected:
            file = (specs.get(name) or {}).get("file", name)
            out.append(f"{name}: {expected - have} of {expected} samples missing from {file}")
    expected_events = manifest.get("event_count")
    have = len(events) if readable_events is None else readable_events  # left-out events are listed already
    if isinstance(expected_events, int) and have < expected_events:
        out.append(f"events: {expected_events - have} of {expected_events} missing from {EVENTS_FILE}")
    for device, n in (manifest.get("dropped_samples") or {}).items():
        if isinstance(n, int) and n > 0:
            out.append(f"{device}: {n} samples dropped while recording (the disk was too slow)")
    lost_events = manifest.get("dropped_device_events")
    if isinstance(lost_events, int) and lost_events > 0:
        out.append(f"{lost_events} device events dropped while recording (the disk was too slow)")
    return out


def session_problems(folder: str | Path) -> list[str]:
    """What is missing or wrong in a recorded session ([] for a complete one): the completeness check of
    ``--metrics`` / ``--report``. Raises nothing; a folder without a manifest is one problem."""
    folder = Path(folder)
    if not (folder / MANIFEST_FILE).is_file():
        return [f"{folder} is not a session folder (no {MANIFEST_FILE})"]
    try:
        return load_session(folder).problems
    except Exception as exc:  # a file no reader expects: still an answer, not a traceback
        return [f"the session cannot be read: {type(exc).__name__}: {exc}"]


# ---------------------------------------------------------------------------------------------- browsing
@dataclass(frozen=True)
class SessionSummary:
    folder: Path
    patient_id: str
    operator: str
    start: str  # ISO with time zone ('' when unknown)
    duration_s: float
    exercises: tuple[str, ...]  # scripts run, in order
    alarms: int
    complete: bool
    note: str = ""
    status: str = ""  # complete, failed (a write error), recording (never stopped)


def summarize_session(folder: Path) -> SessionSummary:
    """Summary from the manifest and the events (streams are not read: listing stays fast)."""
    try:
        manifest = json.loads((folder / MANIFEST_FILE).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        manifest = {}
    if not isinstance(manifest, dict):
        manifest = {}
    manifest = _manifest_with_sidecar(folder, manifest)
    events, _ = read_events(folder / EVENTS_FILE)
    exercises = tuple(str((e.get("data") if isinstance(e.get("data"), dict) else {}).get("name") or "script")
                      for e in events if e.get("kind") == "script_start")
    alarms = alarm_count(events)  # the one definition (app.session.alarm_count): the reports count the same
    start = manifest.get("start") if isinstance(manifest.get("start"), dict) else {}
    start_mono = start.get("t_mono_s") if _finite_number(start.get("t_mono_s")) else None
    if _finite_number(manifest.get("duration_s")):
        duration = float(manifest["duration_s"])
    else:  # crashed: the last thing written
        monos = [float(e["t_mono"]) for e in events if _finite_number(e.get("t_mono"))
                 and (start_mono is None or 0.0 <= e["t_mono"] - start_mono <= MAX_SESSION_S)]
        last = max(monos, default=start_mono if start_mono is not None else 0.0)
        specs = manifest.get("streams") if isinstance(manifest.get("streams"), dict) else {}
        for info in specs.values():
            path = folder / str(info.get("file", "") if isinstance(info, dict) else "")
            if isinstance(info, dict) and isinstance(info.get("file"), str) and path.is_file():
                t = _last_time(path)
                if start_mono is None or 0.0 <= t - start_mono <= MAX_SESSION_S:
                    last = max(last, t)
        duration = max(0.0, float(last) - float(start_mono if start_mono is not None else last))
    return SessionSummary(folder, str(manifest.get("patient_id", folder.parent.name)),
                          str(manifest.get("operator", "")), str(start.get("t_wall", "")), duration, exercises,
                          alarms, manifest.get("status") == "complete", str(manifest.get("note", "")),
                          str(manifest.get("status") or ""))


def _last_time(path: Path) -> float:
    """The time stamp of the last complete line (reads only the file's tail)."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        fh.seek(max(0, size - 4096))
        lines = fh.read().split(b"\n")[:-1]
    for ln in reversed(lines):
        try:
            return float(ln.split(b",", 1)[0])
        except ValueError:
            continue
    return 0.0


def list_sessions(patient_id: str, root: Path | None = None) -> list[SessionSummary]:
    """A patient's sessions, newest first."""
    base = (root or paths.sessions_dir()) / safe_name(patient_id)
    if not base.is_dir():
        return []
    out = [summarize_session(f) for f in base.iterdir() if f.is_dir() and (f / MANIFEST_FILE).exists()]
    return sorted(out, key=lambda s: s.folder.name, reverse=True)


def list_patients_with_sessions(root: Path | None = None) -> list[str]:
    base = root or paths.sessions_dir()
    return sorted(p.name for p in base.iterdir() if p.is_dir()) if base.is_dir() else []
