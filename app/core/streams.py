"""Stream and device names: the one place they are spelled (issue #29).

A stream is ``"<device>.<stream>"``; drivers declare their :class:`app.core.bus.StreamSpec` under these names and
every consumer (recorder, LSL, script bridge, assistance, graphs) subscribes with them.
"""

from __future__ import annotations

from typing import Final

# devices (the config's sections under ``devices:``)
LINARM: Final = "linarm"
PHYSIO: Final = "physio"
FES: Final = "fes"
PATIENT_MODEL: Final = "patient_model"
VR: Final = "vr"
DEVICES: Final = (LINARM, PHYSIO, FES, PATIENT_MODEL, VR)

# streams
LINARM_STATE: Final = "linarm.state"
LINARM_VSA: Final = "linarm.vsa"
LINARM_MOTOR0: Final = "linarm.motor0"
LINARM_MOTOR1: Final = "linarm.motor1"
LINARM_MOTORS: Final = (LINARM_MOTOR0, LINARM_MOTOR1)
PHYSIO_MAIN: Final = "physio.main"
FES_CHANNELS: Final = "fes.channels"
PATIENT_MODEL_MAIN: Final = "patient_model.main"
VR_MAIN: Final = "vr.main"
STREAMS: Final = (LINARM_STATE, LINARM_VSA, *LINARM_MOTORS, PHYSIO_MAIN, FES_CHANNELS, PATIENT_MODEL_MAIN, VR_MAIN)


def device_of(stream: str) -> str:
    """``"linarm.vsa"`` → ``"linarm"``."""
    return stream.partition(".")[0]
