"""What each recorded channel *is*, in the words of each format: the one place the exporters look it up.

The recorder knows a channel's name, unit and label (app.core.bus.Channel, in the manifest). A research format also
wants its kind: BIDS motion channel types (POS, VEL, MISC, LATENCY) with a component and a tracked point, an XDF
channel ``type`` (LabRecorder/LSL meta-data conventions: Position, Force, …), units in plain ASCII for EDF's header,
and where a stream goes in BIDS (the LINarm's kinematics and forces as motion, the sensors as physio, the
stimulator and the VR task as stimulus recordings).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from app.core import streams
from app.core.bus import Channel

# Where a stream goes in a BIDS dataset: "motion" (tracksys-LINarm), "physio", "stim".
BIDS_PLACE: dict[str, str] = {
    streams.LINARM_VSA: "motion", streams.LINARM_MOTOR0: "motion", streams.LINARM_MOTOR1: "motion",
    streams.LINARM_STATE: "motion", streams.PHYSIO_MAIN: "physio", streams.PATIENT_MODEL_MAIN: "physio",
    streams.FES_CHANNELS: "stim", streams.VR_MAIN: "stim",
}
TRACKSYS = "LINarm"


@dataclass(frozen=True)
class ChannelKind:
    xdf_type: str  # LSL/XDF channel type
    motion_type: str  # BIDS motion channel type (POS, VEL, MISC)
    component: str  # BIDS component ("x": the LINarm moves along one axis) or "n/a"
    tracked_point: str  # BIDS tracked point ("handle", "equilibrium", "motor0") or "n/a"


_BY_NAME: dict[tuple[str, str], ChannelKind] = {
    (streams.LINARM_VSA, "equilibriumPos"): ChannelKind("Position", "POS", "x", "equilibrium"),
    (streams.LINARM_VSA, "delta"): ChannelKind("Position", "MISC", "n/a", "spring"),
    (streams.LINARM_VSA, "stiffness"): ChannelKind("Stiffness", "MISC", "n/a", "spring"),
    (streams.LINARM_VSA, "handlePos"): ChannelKind("Position", "POS", "x", "handle"),
    (streams.LINARM_VSA, "handleVel"): ChannelKind("Velocity", "VEL", "x", "handle"),
    (streams.LINARM_VSA, "interactionForce"): ChannelKind("Force", "MISC", "x", "handle"),
}
for _i, _motor in enumerate(streams.LINARM_MOTORS):
    _BY_NAME[(_motor, "position")] = ChannelKind("Position", "POS", "x", f"motor{_i}")
    _BY_NAME[(_motor, "velocity")] = ChannelKind("Velocity", "VEL", "x", f"motor{_i}")
    _BY_NAME[(_motor, "current")] = ChannelKind("Current", "MISC", "n/a", f"motor{_i}")
    _BY_NAME[(_motor, "target")] = ChannelKind("Position", "MISC", "x", f"motor{_i}")

_BY_UNIT = {"m": "Position", "m/s": "Velocity", "N": "Force", "N/m": "Stiffness", "bpm": "HeartRate",
            "µS": "SkinConductance", "°C": "Temperature", "mA": "Current", "A": "Current", "µs": "PulseWidth"}


def kind(stream: str, channel: Channel) -> ChannelKind:
    known = _BY_NAME.get((stream, channel.name))
    if known is not None:
        return known
    xdf_type = _BY_UNIT.get(channel.unit, "State" if stream == streams.LINARM_STATE else "Misc")
    return ChannelKind(xdf_type, "MISC", "n/a", "n/a")


# Units as BIDS writes them (CMIXF-12: "u" for micro, "oC" for degrees Celsius) and as EDF's ASCII header does.
_BIDS_UNITS = {"µS": "uS", "µs": "us", "°C": "oC", "bpm": "bpm", "": "n/a"}
_EDF_UNITS = {"µS": "uS", "µs": "us", "°C": "degC"}


def bids_unit(unit: str) -> str:
    return _BIDS_UNITS.get(unit, unit)


def edf_unit(unit: str) -> str:
    text = _EDF_UNITS.get(unit, unit)
    return text.encode("ascii", errors="replace").decode("ascii")[:8]


def bids_label(text: str, fallback: str = "x") -> str:
    """A BIDS entity label (letters and digits only)."""
    label = re.sub(r"[^A-Za-z0-9]", "", text)
    return label or fallback


def acq_label(stream: str) -> str:
    """``linarm.vsa`` → ``vsa``, ``linarm.motor0`` → ``motor0``, ``patient_model.main`` → ``patientmodel``."""
    device, _, part = stream.partition(".")
    return bids_label(part if device == streams.LINARM else device)
