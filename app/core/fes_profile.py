"""FES profiles: per channel a current trapezoid and a pulse-width trapezoid, over time or movement phase.

A trapezoid rises linearly from ``baseline`` to ``level`` between the two ``ramp_up`` points, holds the
plateau, and falls back between the two ``ramp_down`` points. Points are seconds on a ``time`` axis
(from the start of stimulation) or fractions 0..1 of the current LINarm movement on a ``phase`` axis.
``FesProfile.value_at(x)`` interpolates every channel, scaled by the live current and pulse-width scale
factors (the seed's FESUser.setCurrentScaleFactor / setPWScaleFactor).

Files are YAML with a ``version`` field (see docs/fes.md). ``load_profile`` validates the whole file
and raises ``FesProfileError`` naming the file, the line and the key; nothing half-built is returned.

A profile may address muscular districts instead of (or beside) channels (``districts:``, issue #32): each
district's trapezoids go to the channel of the electrode combination chosen for the patient
(``resolve_districts``); channel-numbered profiles are unchanged.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import yaml
from yaml.nodes import MappingNode, Node

from app.core import yamlschema
from app.core.safe_files import UserFileError, read_user_file
from app.core.yamlschema import ConfigError, check_yaml, decode_text, load_dataclass, rng
from app.wire.sciencemode import CHANNELS, CHANNELS_TEXT, MAX_CURRENT_MA, MAX_PULSE_WIDTH_US, PulseMode, PulseSetting

PROFILE_VERSION = 1
MAX_SCALE = 2.0  # scale knobs run 0..2 × the designed profile (the limiter still caps the result)
Axis = Literal["time", "phase"]


class FesProfileError(ConfigError):
    """A profile file (or profile object) is invalid; the message names the file, the line and the key."""


@dataclass(frozen=True)
class Trapezoid:
    """baseline → level over ramp_up, plateau, level → baseline over ramp_down (points on the axis)."""

    level: float
    ramp_up: tuple[float, float]
    ramp_down: tuple[float, float]
    baseline: float = 0.0

    def value_at(self, x: float) -> float:
        (u0, u1), (d0, d1) = self.ramp_up, self.ramp_down
        if x < u0 or x >= d1:
            return self.baseline
        low, high = min(self.baseline, self.level), max(self.baseline, self.level)
        # Clamped: rounding in the interpolation must never step outside baseline..level (a level of
        # 5e-324 gave -5e-324 on the ramp down, i.e. below zero).
        if x < u1:
            return min(high, max(low, self.baseline + (self.level - self.baseline) * (x - u0) / (u1 - u0)))
        if x <= d0:
            return self.level
        return min(high, max(low, self.level + (self.baseline - self.level) * (x - d0) / (d1 - d0)))

    def problems(self, axis: Axis, maximum: float, unit: str) -> list[tuple[str, str]]:
        """(key, problem) pairs; empty when valid."""
        out: list[tuple[str, str]] = []
        for key in ("level", "baseline"):
            v = getattr(self, key)
            if not (math.isfinite(v) and 0 <= v <= maximum):
                out.append((key, f"{v:g} {unit} is outside the allowed range 0 .. {maximum:g} {unit}"))
        points = [*self.ramp_up, *self.ramp_down]
        if len(self.ramp_up) != 2 or len(self.ramp_down) != 2:
            out.append(
                ("ramp_up" if len(self.ramp_up) != 2 else "ramp_down", "expected two points [start, end]")
            )
            return out
        if not all(math.isfinite(p) for p in points):
            out.append(("ramp_up", "points must be finite numbers"))
        elif points != sorted(points):
            out.append(
                (
                    "ramp_down",
                    "points must not decrease: ramp_up start <= ramp_up end <= ramp_down start "
                    f"<= ramp_down end, got {points}",
                )
            )
        lo, hi = (0.0, 1.0) if axis == "phase" else (0.0, math.inf)
        for key, pair in (("ramp_up", self.ramp_up), ("ramp_down", self.ramp_down)):
            if any(not lo <= p <= hi for p in pair):
                allowed = "0 .. 1 (fraction of the movement)" if axis == "phase" else ">= 0 s"
                out.append((key, f"points {list(pair)} outside {allowed}"))
        return out


@dataclass(frozen=True)
class ChannelProfile:
    current_ma: Trapezoid
    pulse_width_us: Trapezoid
    muscle: str = ""
    mode: PulseMode = PulseMode.SINGLE


@dataclass(frozen=True)
class FesProfile:
    name: str
    axis: Axis
    channels: Mapping[int, ChannelProfile]
    frequency_hz: float = 40.0
    description: str = ""
    current_scale: float = 1.0
    pulse_width_scale: float = 1.0
    # district name -> its trapezoids; stimulated on the district's chosen channel (resolve_districts)
    districts: Mapping[str, ChannelProfile] = field(default_factory=dict)

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            key, problem = problems[0]
            raise FesProfileError(f"profile {self.name!r}", None, key, problem)

    def problems(self) -> list[tuple[str, str]]:
        out: list[tuple[str, str]] = []
        if self.axis not in ("time", "phase"):
            out.append(("axis", f"expected 'time' or 'phase', got {self.axis!r}"))
            return out
        if not self.channels and not self.districts:
            out.append(("channels", "at least one channel (or district) is needed"))
        for key, v in (("current_scale", self.current_scale), ("pulse_width_scale", self.pulse_width_scale)):
            if not (math.isfinite(v) and 0 <= v <= MAX_SCALE):
                out.append((key, f"{v:g} is outside the allowed range 0 .. {MAX_SCALE:g}"))
        if not (math.isfinite(self.frequency_hz) and 1 <= self.frequency_hz <= 100):
            out.append(("frequency_hz", f"{self.frequency_hz:g} Hz is outside the allowed range 1 .. 100 Hz"))
        for ch, cp in self.channels.items():
            if ch not in CHANNELS:
                out.append((f"channels.{ch}", f"channel must be one of {CHANNELS_TEXT}"))
                continue
            for key, trap, maximum, unit in (
                ("current_ma", cp.current_ma, MAX_CURRENT_MA, "mA"),
                ("pulse_width_us", cp.pulse_width_us, MAX_PULSE_WIDTH_US, "µs"),
            ):
                out += [(f"channels.{ch}.{key}.{k}", p) for k, p in trap.problems(self.axis, maximum, unit)]
        for name, cp in self.districts.items():
            if not str(name).strip():
                out.append(("districts", "a district needs a name (e.g. anterior deltoid)"))
                continue
            for key, trap, maximum, unit in (
                ("current_ma", cp.current_ma, MAX_CURRENT_MA, "mA"),
                ("pulse_width_us", cp.pulse_width_us, MAX_PULSE_WIDTH_US, "µs"),
            ):
                out += [(f"districts.{name}.{key}.{k}", p) for k, p in trap.problems(self.axis, maximum, unit)]
        return out

    def resolve_districts(self, channel_of: Mapping[str, int]) -> FesProfile:
        """This profile with every district on its chosen channel (``channel_of``: district -> channel, the
        patient's chosen combinations); the channel's ``muscle`` is the district's name. Unchanged when the
        profile names no district. Raises FesProfileError when a district has no chosen combination or its
        channel is already used by the profile."""
        if not self.districts:
            return self
        known = {str(k).strip().lower(): v for k, v in channel_of.items()}
        channels = dict(self.channels)
        for name, cp in self.districts.items():
            channel = known.get(str(name).strip().lower())
            if channel is None:
                raise FesProfileError(f"profile {self.name!r}", None, f"districts.{name}",
                                      f"no electrode combination is chosen for {name!r} yet: run the electrode "
                                      "set-up (FES tab) for this patient first")
            if channel in channels:
                raise FesProfileError(f"profile {self.name!r}", None, f"districts.{name}",
                                      f"the chosen combination of {name!r} is channel {channel}, which the "
                                      "profile already uses")
            channels[channel] = replace(cp, muscle=str(name))
        return replace(self, channels=channels, districts={})

    @property
    def end(self) -> float:
        """Where every channel is back to baseline: seconds (time axis) or 1.0 (phase axis)."""
        if self.axis == "phase":
            return 1.0
        return max(
            (
                max(cp.current_ma.ramp_down[1], cp.pulse_width_us.ramp_down[1])
                for cp in self.channels.values()
            ),
            default=0.0,
        )

    def value_at(self, x: float) -> dict[int, tuple[float, float]]:
        """{channel: (current mA, pulse width µs)} at time ``x`` s or phase ``x`` (clamped 0..1), scaled."""
        if not math.isfinite(x):
            raise ValueError(f"profile position must be a finite number, got {x!r}")
        if self.axis == "phase":
            x = min(1.0, max(0.0, x))
        return {
            ch: (
                cp.current_ma.value_at(x) * self.current_scale,
                cp.pulse_width_us.value_at(x) * self.pulse_width_scale,
            )
            for ch, cp in sorted(self.channels.items())
        }

    def settings_at(self, x: float) -> dict[int, PulseSetting]:
        """``value_at`` rounded to the device's whole mA / µs, with each channel's pulse group."""
        return {
            ch: PulseSetting(round(c), round(w), self.channels[ch].mode)
            for ch, (c, w) in self.value_at(x).items()
        }

    def peaks(self, scaled: bool = False) -> dict[int, tuple[float, float]]:
        """Per channel the largest (current, pulse width) of the profile (for the scale-knob clamp)."""
        cs, ws = (self.current_scale, self.pulse_width_scale) if scaled else (1.0, 1.0)
        return {
            ch: (
                max(cp.current_ma.level, cp.current_ma.baseline) * cs,
                max(cp.pulse_width_us.level, cp.pulse_width_us.baseline) * ws,
            )
            for ch, cp in sorted(self.channels.items())
        }

    def with_scales(
        self, current_scale: float | None = None, pulse_width_scale: float | None = None
    ) -> FesProfile:
        return replace(
            self,
            current_scale=self.current_scale if current_scale is None else current_scale,
            pulse_width_scale=self.pulse_width_scale if pulse_width_scale is None else pulse_width_scale,
        )


# ── YAML file format ─────────────────────────────────────────────────────────────────────────────
# Private schema classes read by app.core.yamlschema (types, ranges, unknown keys, lines); the checks that
# depend on the axis or the quantity are done afterwards with the node marks of the same file.


@dataclass(frozen=True)
class _TrapezoidFile:
    level: float
    ramp_up: list[float]
    ramp_down: list[float]
    baseline: float = 0.0

    def validate(self) -> None:
        for key in ("ramp_up", "ramp_down"):
            if len(getattr(self, key)) != 2:
                raise ValueError(f"{key}: expected two points [start, end], got {getattr(self, key)}")


@dataclass(frozen=True)
class _ChannelFile:
    current_ma: _TrapezoidFile
    pulse_width_us: _TrapezoidFile
    muscle: str = ""
    mode: Literal["single", "doublet", "triplet"] = "single"


@dataclass(frozen=True)
class _ProfileFile:
    version: int
    name: str
    axis: Literal["time", "phase"]
    channels: dict[int, _ChannelFile] = field(default_factory=dict)
    districts: dict[str, _ChannelFile] = field(default_factory=dict)
    description: str = ""
    frequency_hz: float = field(default=40.0, metadata=rng(1, 100, "Hz"))
    current_scale: float = field(default=1.0, metadata=rng(0, MAX_SCALE))
    pulse_width_scale: float = field(default=1.0, metadata=rng(0, MAX_SCALE))


def _node_at(root: Node, path: list[str]) -> Node:
    """The key node of the deepest entry found along ``path`` (keys as text): where a problem is."""
    node, found = root, root
    for key in path:
        if not isinstance(node, MappingNode):
            break
        for knode, vnode in node.value:
            if str(knode.value) == key:
                node, found = vnode, knode
                break
        else:
            break
    return found


def _fail(filename: str, node: Node | None, key: str, problem: str) -> FesProfileError:
    return FesProfileError(filename, node.start_mark.line + 1 if node is not None else None, key, problem)


def _trapezoid(t: _TrapezoidFile) -> Trapezoid:
    return Trapezoid(t.level, (t.ramp_up[0], t.ramp_up[1]), (t.ramp_down[0], t.ramp_down[1]), t.baseline)


def parse_profile(text: str | bytes, filename: str = "<profile>") -> FesProfile:
    """Parse and validate a profile (its text, or the file's bytes). Raises FesProfileError (file, line, key).

    First through the config loader's checks (app/core/yamlschema.py): UTF-8 (the line of a bad byte), size,
    nesting depth (PyYAML's composer recurses: 10 000 ``[`` were a RecursionError), anchors, tags."""
    try:
        text = decode_text(text, filename)
        check_yaml(text, filename)
    except ConfigError as exc:
        raise FesProfileError(exc.filename, exc.line, exc.key, exc.problem) from None
    try:
        root = yamlschema.compose(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        raise FesProfileError(
            filename, mark.line + 1 if mark else None, "", f"not valid YAML: {exc.problem}"
        ) from exc
    except yaml.YAMLError as exc:
        raise FesProfileError(filename, None, "", f"not valid YAML: {exc}") from exc
    if not isinstance(root, MappingNode):
        raise _fail(filename, root, "", "expected a mapping with version, name, axis and channels")
    version_key = _node_at(root, ["version"])
    version_node = next((v for k, v in root.value if k is version_key), None)
    if version_node is None:
        raise _fail(filename, root, "version", f"missing; this program reads version {PROFILE_VERSION}")
    if getattr(version_node, "value", None) != str(PROFILE_VERSION):
        raise _fail(
            filename,
            version_node,
            "version",
            f"unsupported version {getattr(version_node, 'value', '?')!r}; this program reads "
            f"version {PROFILE_VERSION}",
        )
    try:
        raw = load_dataclass(_ProfileFile, text, filename)
    except ConfigError as exc:
        raise FesProfileError(exc.filename, exc.line, exc.key, exc.problem) from exc
    try:
        channels = {
            ch: ChannelProfile(
                _trapezoid(c.current_ma), _trapezoid(c.pulse_width_us), c.muscle, PulseMode[c.mode.upper()]
            )
            for ch, c in raw.channels.items()
        }
        districts = {
            name: ChannelProfile(
                _trapezoid(c.current_ma), _trapezoid(c.pulse_width_us), c.muscle or name, PulseMode[c.mode.upper()]
            )
            for name, c in raw.districts.items()
        }
        profile = FesProfile(
            raw.name,
            raw.axis,
            channels,
            raw.frequency_hz,
            raw.description,
            raw.current_scale,
            raw.pulse_width_scale,
            districts,
        )
    except FesProfileError as exc:
        raise _fail(filename, _node_at(root, exc.key.split(".")), exc.key, exc.problem) from exc
    return profile


MAX_PROFILE_BYTES = 256 * 1024  # a profile is a few hundred bytes; a script may name any path
PROFILE_READ_TIMEOUT_S = 2.0


def load_profile(path: str | Path) -> FesProfile:
    """Read and check a profile file: only a regular file of at most MAX_PROFILE_BYTES, read within
    PROFILE_READ_TIMEOUT_S (app/core/safe_files.py: a script's ``fes.loadFile("/dev/zero")`` is read by the app)."""
    path = Path(path)
    try:
        data = read_user_file(path, MAX_PROFILE_BYTES, PROFILE_READ_TIMEOUT_S)
    except UserFileError as exc:  # every OSError of the read comes as one
        raise FesProfileError.refused(exc) from exc
    return parse_profile(data, str(path))  # bytes: a non-UTF-8 file is refused with its line


def _trapezoid_plain(t: Trapezoid) -> dict[str, object]:
    return {
        "level": float(t.level),
        "ramp_up": [float(p) for p in t.ramp_up],
        "ramp_down": [float(p) for p in t.ramp_down],
        "baseline": float(t.baseline),
    }


def profile_to_yaml(profile: FesProfile) -> str:
    plain = {
        "version": PROFILE_VERSION,
        "name": profile.name,
        "description": profile.description,
        "axis": profile.axis,
        "frequency_hz": float(profile.frequency_hz),
        "current_scale": float(profile.current_scale),
        "pulse_width_scale": float(profile.pulse_width_scale),
        "channels": {
            int(ch): {
                "muscle": cp.muscle,
                "mode": PulseMode(cp.mode).name.lower(),
                "current_ma": _trapezoid_plain(cp.current_ma),
                "pulse_width_us": _trapezoid_plain(cp.pulse_width_us),
            }
            for ch, cp in sorted(profile.channels.items())
        },
    }
    if profile.districts:
        plain["districts"] = {
            str(name): {
                "muscle": cp.muscle,
                "mode": PulseMode(cp.mode).name.lower(),
                "current_ma": _trapezoid_plain(cp.current_ma),
                "pulse_width_us": _trapezoid_plain(cp.pulse_width_us),
            }
            for name, cp in profile.districts.items()
        }
    header = (
        "# LINarm++ FES profile (docs/fes.md). Points are seconds (axis: time) or movement phase 0..1\n"
        "# (axis: phase); current in mA, pulse width in µs.\n"
    )
    return header + str(yaml.safe_dump(plain, sort_keys=False, allow_unicode=True))


def save_profile(profile: FesProfile, path: str | Path) -> None:
    """Write ``profile`` as YAML; the file is replaced atomically so a failed save leaves the old one."""
    text = profile_to_yaml(profile)
    parse_profile(text, str(path))  # what we write must read back
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
