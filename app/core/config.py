"""Application configuration: devices (simulated or real), safety limits, assistance gains.

The defaults here are the single source; ``resources/config.default.yaml`` is a commented copy
that a test keeps identical to them. A user file (``--config FILE``) overrides any subset and is
validated whole before anything starts: unknown keys and bad values are refused with the file,
key and line named (see app.core.yamlschema).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from app.core.links import BAUDRATE_RANGE, DEFAULT_BAUDRATE, LOOPBACK
from app.core.resources import DEFAULT_CONFIG_FILE, RESOURCES  # noqa: F401 - RESOURCES re-exported for callers
from app.core.yamlschema import ConfigError, load_file, rng, to_plain
from app.wire import sciencemode
from app.wire.linarm_constants import K
from app.wire.linarm_protocol import WATCHDOG_TIMEOUT

DeviceMode = Literal["simulated", "serial", "off"]

# The ranges a robot limit may take, in the site's configuration and in a patient's profile (app.therapy.patients): the
# controller's own, from its constants table (app/wire/linarm_constants.py), never typed here.
ROBOT_LIMIT_RANGES: dict[str, dict[str, Any]] = {
    "position_min_m": rng(K["RAIL_MIN"], K["RAIL_MAX"], "m"),
    "position_max_m": rng(K["RAIL_MIN"], K["RAIL_MAX"], "m"),
    "max_velocity_m_s": rng(0.0, K["MAX_VEL_MAX"], "m/s"),
    "max_acceleration_m_s2": rng(0.0, K["MAX_ACC_MAX"], "m/s²"),
    "max_interaction_force_n": rng(0.0, K["MAX_FORCE_MAX"], "N"),
    "max_stiffness_n_m": rng(0.0, K["STIFFNESS_LIMIT_MAX"], "N/m"),
    "max_delta_m": rng(0.0, K["DELTA_MAX"], "m"),
}
# An FES current or pulse-width cap: at most what the stimulator can deliver (app/wire/sciencemode.py).
FES_CURRENT_RANGE = rng(0, sciencemode.MAX_CURRENT_MA, "mA")
FES_PULSE_WIDTH_RANGE = rng(0, sciencemode.MAX_PULSE_WIDTH_US, "µs")
FES_CHANNEL_RANGE = rng(sciencemode.CHANNELS[0], sciencemode.CHANNELS[-1])


def unknown_channel(key: str, channels: Iterable[int]) -> str | None:
    """The problem with the first of ``channels`` (a caps table's keys) the stimulator does not have; None."""
    bad = [ch for ch in channels if ch not in sciencemode.CHANNELS]
    if not bad:
        return None
    return f"{key}: channel {bad[0]} does not exist; the stimulator has channels {sciencemode.CHANNELS_TEXT}"


@dataclass(frozen=True)
class SerialDevice:
    """A serial device: `simulated` starts a simulator on a pty (or localhost socket) and connects
    the real driver to it; `serial` opens ``port`` (a name such as /dev/ttyACM0 or COM3, or any
    pyserial URL such as socket://host:port)."""

    mode: DeviceMode = "simulated"
    port: str = ""
    baudrate: int = field(default=DEFAULT_BAUDRATE, metadata=rng(*BAUDRATE_RANGE, "Bd"))

    def validate(self) -> None:
        if self.mode == "serial" and not self.port:
            raise ValueError("mode is 'serial' but no port is given (e.g. port: /dev/ttyACM0 or COM3)")


@dataclass(frozen=True)
class LinarmDevice(SerialDevice):
    baudrate: int = field(default=460800, metadata=rng(*BAUDRATE_RANGE, "Bd"))
    state_rate_hz: float = field(default=200.0, metadata=rng(1, 1000, "Hz"))
    command_timeout_s: float = field(default=1.0, metadata=rng(0.05, 30, "s"))
    heartbeat_period_s: float = field(default=0.1, metadata=rng(0.02, 0.2, "s"))


@dataclass(frozen=True)
class PhysioCalibration:
    """Raw 12-bit counts → physical units: value = gain · counts + offset. Heart rate has none:
    the board sends the raw pulse waveform and the app detects beats (docs/physio-and-udp-frames.md)."""

    skin_conductance_gain: float = field(default=0.01, metadata=rng(1e-6, 10, "µS/count"))
    skin_conductance_offset: float = field(default=0.0, metadata=rng(-100, 100, "µS"))
    temperature_gain: float = field(default=0.01, metadata=rng(1e-6, 10, "°C/count"))
    temperature_offset: float = field(default=10.0, metadata=rng(-50, 100, "°C"))
    force_gain: float = field(default=0.025, metadata=rng(1e-6, 10, "N/count"))
    force_offset: float = field(default=0.0, metadata=rng(-500, 500, "N"))


@dataclass(frozen=True)
class PhysioDevice(SerialDevice):
    rate_hz: float = field(default=100.0, metadata=rng(1, 5000, "Hz"))
    calibration: PhysioCalibration = field(default_factory=PhysioCalibration)


@dataclass(frozen=True)
class ElectrodeCombinationConfig:
    """One candidate combination of an electrode array: the stimulator channel its electrode pair is wired to,
    and which electrodes of the array form the pair (as labelled on the garment, e.g. "1-2")."""

    channel: int = field(default=1, metadata=FES_CHANNEL_RANGE)
    electrodes: str = ""


@dataclass(frozen=True)
class ElectrodeDistrictConfig:
    """A muscular district's electrode array (issue #32, docs/fes.md "Electrode set-up"): its candidate
    combinations, and the way its muscle moves the handle (the sign of the LINarm's interaction force that
    counts as its response; ``either``: the size of the change)."""

    combinations: list[ElectrodeCombinationConfig] = field(default_factory=list)
    direction: Literal["positive", "negative", "either"] = "either"

    def validate(self) -> None:
        if not self.combinations:
            raise ValueError("combinations: a district needs at least one electrode combination (a channel)")
        channels = [c.channel for c in self.combinations]
        if len(set(channels)) != len(channels):
            raise ValueError(f"combinations: channel {next(c for c in channels if channels.count(c) > 1)} "
                             "is listed twice")


def _default_electrodes() -> dict[str, ElectrodeDistrictConfig]:
    """The simulated set-up's wiring: two arrays of four electrodes, four candidate pairs each, one array on each
    of the stimulator's current modules."""
    pairs = ("1-2", "3-4", "1-3", "2-4")
    return {
        "anterior deltoid": ElectrodeDistrictConfig(
            [ElectrodeCombinationConfig(ch, e) for ch, e in zip(sciencemode.MODULE_A, pairs, strict=True)],
            "positive"),
        "triceps": ElectrodeDistrictConfig(
            [ElectrodeCombinationConfig(ch, e) for ch, e in zip(sciencemode.MODULE_B, pairs, strict=True)],
            "positive"),
    }


@dataclass(frozen=True)
class FesDevice(SerialDevice):
    protocol: Literal["sm1", "sm2"] = "sm1"
    ack_timeout_s: float = field(default=0.5, metadata=rng(0.01, 10, "s"))
    # The electrode arrays: per muscular district, the channels wired to its candidate combinations.
    electrodes: dict[str, ElectrodeDistrictConfig] = field(default_factory=_default_electrodes)

    def validate(self) -> None:
        super().validate()
        seen: dict[int, str] = {}
        for name, district in self.electrodes.items():
            if not name.strip():
                raise ValueError("electrodes: a district needs a name (e.g. anterior deltoid)")
            for combination in district.combinations:
                if combination.channel in seen:
                    raise ValueError(f"electrodes: channel {combination.channel} is wired to both "
                                     f"{seen[combination.channel]!r} and {name!r}")
                seen[combination.channel] = name


@dataclass(frozen=True)
class UdpEndpoint:
    """A UDP peer. `embedded`/`standin` run our own implementation as a separate process on the
    same UDP link; `external` talks to a model or renderer started elsewhere (Matlab, Unity)."""

    mode: Literal["embedded", "standin", "external", "off"] = "embedded"
    bind_host: str = LOOPBACK
    listen_port: int = field(default=0, metadata=rng(0, 65535))
    peer_host: str = LOOPBACK
    peer_port: int = field(default=0, metadata=rng(0, 65535))
    rate_hz: float = field(default=100.0, metadata=rng(1, 2000, "Hz"))
    # Listening on anything but loopback exposes the link to the network: only when the site says so.
    allow_remote: bool = False
    # A per-session key and a MAC on every datagram (app.wire.udp_frames). null = on for our own
    # embedded model / VR stand-in, off for an `external` peer (the seed's plain layout, Matlab/Unity).
    authenticate: bool | None = None
    key_file: str = ""  # `external` with authenticate: true: a file holding the shared key in hex

    @property
    def authenticated(self) -> bool:
        return self.mode != "external" if self.authenticate is None else self.authenticate

    def validate(self) -> None:
        if self.mode == "external" and not self.peer_port:
            raise ValueError("mode is 'external' but peer_port is not set")
        bind = _ip("bind_host", self.bind_host)
        if not bind.is_loopback and not self.allow_remote:
            raise ValueError(f"bind_host {self.bind_host} is not a loopback address: the link would be open to "
                             "the network; set allow_remote: true to allow it")
        if self.peer_host.replace(".", "").isdigit() or ":" in self.peer_host:
            peer = _ip("peer_host", self.peer_host)
            if self.mode == "external" and not peer.is_loopback and not self.allow_remote:
                raise ValueError(f"peer_host {self.peer_host} is not a loopback address; set allow_remote: true "
                                 "to talk to a peer on another machine")
        elif not self.peer_host or len(self.peer_host) > 253:
            raise ValueError(f"peer_host {self.peer_host!r} is not a host name or address")
        if self.mode == "external" and self.authenticate and not self.key_file:
            raise ValueError("authenticate is true for an external peer but key_file is not set")


def _ip(key: str, text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    if text == "localhost":
        return ipaddress.ip_address(LOOPBACK)
    try:
        return ipaddress.ip_address(text)
    except ValueError:
        raise ValueError(f"{key} {text!r} is not an IP address") from None


@dataclass(frozen=True)
class Devices:
    linarm: LinarmDevice = field(default_factory=LinarmDevice)
    physio: PhysioDevice = field(default_factory=PhysioDevice)
    fes: FesDevice = field(default_factory=FesDevice)
    patient_model: UdpEndpoint = field(default_factory=UdpEndpoint)
    vr: UdpEndpoint = field(default_factory=lambda: UdpEndpoint(mode="standin", rate_hz=50.0))


@dataclass(frozen=True)
class RobotLimits:
    position_min_m: float = field(default=0.02, metadata=ROBOT_LIMIT_RANGES["position_min_m"])
    position_max_m: float = field(default=0.48, metadata=ROBOT_LIMIT_RANGES["position_max_m"])
    max_velocity_m_s: float = field(default=0.30, metadata=ROBOT_LIMIT_RANGES["max_velocity_m_s"])
    max_acceleration_m_s2: float = field(default=1.0, metadata=ROBOT_LIMIT_RANGES["max_acceleration_m_s2"])
    max_interaction_force_n: float = field(default=60.0, metadata=ROBOT_LIMIT_RANGES["max_interaction_force_n"])
    max_stiffness_n_m: float = field(default=2000.0, metadata=ROBOT_LIMIT_RANGES["max_stiffness_n_m"])
    max_delta_m: float = field(default=0.06, metadata=ROBOT_LIMIT_RANGES["max_delta_m"])
    # Endstroke switches stop the carriage at the rail's ends; only a bench setup without a patient
    # may turn them off.
    allow_disable_endstrokes: bool = False
    # Encoder offsets and ratios move the position reference every limit is measured against: service only.
    allow_calibration: bool = False

    def validate(self) -> None:
        if self.position_min_m >= self.position_max_m:
            raise ValueError(
                f"position_min_m ({self.position_min_m}) must be below position_max_m ({self.position_max_m})")


@dataclass(frozen=True)
class FesChannelCaps:
    max_current_ma: float = field(default=40.0, metadata=FES_CURRENT_RANGE)
    max_pulse_width_us: float = field(default=300.0, metadata=FES_PULSE_WIDTH_RANGE)


@dataclass(frozen=True)
class FesSafety:
    max_current_ma: float = field(default=40.0, metadata=FES_CURRENT_RANGE)
    max_pulse_width_us: float = field(default=300.0, metadata=FES_PULSE_WIDTH_RANGE)
    max_current_rise_ma_s: float = field(default=40.0, metadata=rng(0.1, 1000, "mA/s"))
    max_pulse_width_rise_us_s: float = field(default=500.0, metadata=rng(1, 10000, "µs/s"))
    max_rms_current_ma: float = field(default=10.0, metadata=rng(0, 50, "mA"))
    start_ramp_s: float = field(default=1.0, metadata=rng(0, 10, "s"))
    frequency_hz: float = field(default=40.0, metadata=rng(1, 100, "Hz"))
    channels: dict[int, FesChannelCaps] = field(default_factory=dict)

    def validate(self) -> None:
        problem = unknown_channel("channels", self.channels)
        if problem:
            raise ValueError(problem)


@dataclass(frozen=True)
class SafetyConfig:
    robot: RobotLimits = field(default_factory=RobotLimits)
    fes: FesSafety = field(default_factory=FesSafety)
    # A streaming device that is silent for this many of its sample periods raises an alarm.
    silence_periods: int = field(default=3, metadata=rng(2, 100))
    # ...but never less than this: a Python driver thread can be starved of the GIL for tens of ms while
    # the GUI draws (qt-stack.md §4); the controller's host watchdog (the protocol table's WATCHDOG_TIMEOUT)
    # avoids false alarms, and calls a link silent no sooner than the controller itself would.
    silence_min_s: float = field(default=WATCHDOG_TIMEOUT, metadata=rng(0.01, 5, "s"))
    # A device that moves the patient or drives current (LINarm, FES) still silent this long after its
    # silence alarm is a STOP (app/safety/fault_policy.py): long enough that a host starved for a moment (the
    # whole process silent at once, as on a loaded CI machine) does not stop a therapy.
    silence_stop_s: float = field(default=1.0, metadata=rng(0, 10, "s"))
    # What the robot does when a script stops or the app leaves a session: IDLE (motors off) or hold.
    robot_safe_state: Literal["idle", "hold"] = "idle"


@dataclass(frozen=True)
class AssistanceMap:
    """Maps a_r (or a_f) in [0, 1] linearly onto [at_zero, at_one]."""

    at_zero: float = 0.0
    at_one: float = 1.0


@dataclass(frozen=True)
class AssistanceConfig:
    k_r: float = field(default=0.5, metadata=rng(0, 1))
    k_f: float = field(default=0.5, metadata=rng(0, 1))
    k_m_stiffness_n_m: AssistanceMap = field(default_factory=lambda: AssistanceMap(500.0, 1500.0))
    k_a_admittance_m_s_n: AssistanceMap = field(default_factory=lambda: AssistanceMap(0.001, 0.004))
    k_t_assistive_n_m: AssistanceMap = field(default_factory=lambda: AssistanceMap(0.0, 150.0))
    fes_pulse_width_us: AssistanceMap = field(default_factory=lambda: AssistanceMap(100.0, 300.0))
    max_update_rate_hz: float = field(default=10.0, metadata=rng(0.1, 100, "Hz"))


@dataclass(frozen=True)
class RecordingConfig:
    folder: str = ""  # empty: the user's data folder (shown in Help → About)
    lsl: bool = False
    flush_interval_s: float = field(default=0.5, metadata=rng(0.05, 1.0, "s"))
    # Free space in the sessions folder at session start: a warning below the first, refused below the second.
    warn_free_mib: float = field(default=1024.0, metadata=rng(0, 1_000_000, "MiB"))
    min_free_mib: float = field(default=100.0, metadata=rng(0, 1_000_000, "MiB"))


@dataclass(frozen=True)
class UiConfig:
    refresh_hz: float = field(default=30.0, metadata=rng(1, 120, "Hz"))
    history_s: float = field(default=30.0, metadata=rng(1, 600, "s"))
    palette: Literal["light", "dark"] = "light"
    emergency_stop_shortcut: str = "F12"
    ask_session_on_start: bool = True  # open "Start session" (patient + operator) when the window opens


@dataclass(frozen=True)
class SimulationConfig:
    """How simulated serial devices are hosted (app.devices.sim.host): ``process`` runs them in a process
    of their own, so the app's process is what it is with real hardware; ``thread`` runs them in the
    app's process (tests that reach into a simulator). ``linarm: firmware`` simulates the LINarm with the
    firmware's software-in-the-loop executable (built from firmware/host with CMake) instead of the
    Python model; ``linarm: mcu`` with the firmware's ARM image on an emulated Cortex-M3 board
    (qemu-system-arm -M mps2-an385, image built from firmware/host/due)."""

    host: Literal["process", "thread"] = "process"
    linarm: Literal["python", "firmware", "mcu"] = "python"
    link: Literal["pty", "socket"] = "socket"


@dataclass(frozen=True)
class ArchiveConfig:
    """The clinic's archive (docs/archive.md). ``url`` empty: an SQLite file in the data folder (one PC). A clinic:
    ``postgresql+psycopg://ROLE@HOST[:PORT]/DATABASE`` (or ``postgresql+psycopg:///DB?service=NAME``). The password
    is never in this file: ``password_file`` (readable by this user only) or libpq's own (~/.pgpass, PGPASSFILE,
    a service file)."""

    url: str = ""
    password_file: str = ""

    def validate(self) -> None:
        from urllib.parse import urlsplit

        if not self.url:
            return
        try:
            parts = urlsplit(self.url)
            password = parts.password
        except ValueError as exc:
            raise ValueError(f"url {self.url!r} is not a database URL: {exc}") from None
        if password is not None:
            raise ValueError("url holds a password; a password in the configuration would be readable by anyone "
                             "who can read the file: remove it from the URL and put it in password_file (a file "
                             "only you can read) or in ~/.pgpass")
        if not parts.scheme.startswith(("postgresql", "sqlite")):
            raise ValueError(f"url {self.url!r}: the archive is PostgreSQL (postgresql+psycopg://…) or SQLite "
                             "(sqlite:///FILE)")


@dataclass(frozen=True)
class AppConfig:
    version: int = field(default=1, metadata=rng(1, 1))
    devices: Devices = field(default_factory=Devices)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    assistance: AssistanceConfig = field(default_factory=AssistanceConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    ui: UiConfig = field(default_factory=UiConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    archive: ArchiveConfig = field(default_factory=ArchiveConfig)
    station: str = ""  # this PC's name in the archive ('' = the computer's network name)
    source: str = field(default="(defaults)", compare=False)


def load_config(path: str | Path | None = None) -> AppConfig:
    """The defaults, overridden by ``path`` when given. Raises ConfigError naming file, key, line."""
    if path is None:
        return AppConfig()
    cfg = load_file(AppConfig, path, base=AppConfig())
    return _with_source(cfg, str(path))


def _with_source(cfg: AppConfig, source: str) -> AppConfig:
    from dataclasses import replace

    return replace(cfg, source=source)


def config_as_dict(cfg: AppConfig) -> dict[str, Any]:
    data: dict[str, Any] = to_plain(cfg)
    data.pop("source", None)
    return data


__all__ = ["AppConfig", "ConfigError", "config_as_dict", "load_config"]
