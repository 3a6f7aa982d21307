"""The pure device simulator cores on the link thread's interface (``SimCore``: host bytes in, reply bytes out,
``poll`` at monotonic time ``t``), for both hostings: the simulator process (app.devices.sim.host) and the
in-process SerialSimulator.

They lived in the driver modules until #29; there they made the simulator process import the drivers, and
with them Qt. Here they import only the pure cores and codecs: nothing under ``app/devices/sim/`` reaches Qt
(tests/test_architecture.py), and a driver module imports this one, never the reverse.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from app.devices.sim.base import linarm_starts_homed
from app.devices.sim.linarm_model import LinarmSimCore
from app.devices.sim.physio_signals import PhysioSimSource
from app.devices.sim.rehastim_core import RehaStimSimCore
from app.wire.linarm_constants import K
from app.wire.physio_codec import Calibration

if TYPE_CHECKING:
    from app.devices.sim.patient import SimulatedPatient


# ---------------------------------------------------------------------------------------------- LINarm
class _PatientOnCoreClock:
    """The shared simulated patient lives on the monotonic clock; the LINarm core counts from 0."""

    def __init__(self, patient: Any, t0: float) -> None:
        self.patient = patient
        self.t0 = t0

    def handle_force(self, t: float, handle_pos: float, handle_vel: float) -> float:
        t_abs = t + self.t0
        self.patient.update_handle(t_abs, handle_pos, handle_vel)
        return float(self.patient.handle_force(t_abs, handle_pos, handle_vel))


# How often the LINarm's simulator thread wakes at most with nothing to read: its frames go out when due
# (``next_output``), the controller's 1 kHz loop is caught up at each wake (LinarmSimCore.advance_to), and host
# bytes wake it at once. Waking every millisecond cost the simulator process ~10 % of a core for nothing.
LINARM_POLL_S = 0.005
# The physiological board's frames go out at their sample instants (``next_output``), nothing else: its thread wakes
# for each frame (100 a second at 100 Hz), not on a 5 ms grid as well (200 wake-ups a second, half of them for
# nothing, and each frame up to 5 ms after its instant).
PHYSIO_POLL_S = 0.05
# The stimulator acts on its own only at its watchdog's expiry or a repeated Init (``next_output``); the rest is
# answers to host bytes, which wake its thread at once. Its thread woke every 2 ms before, for nothing.
FES_POLL_S = 0.05


class LinarmSimAdapter:
    """LinarmSimCore on the simulator thread's monotonic clock. Without an explicit ``start_homed`` it starts
    homed at the home position when ``LINARMPP_SIM_HOMED=1`` (app.devices.sim.base.linarm_starts_homed)."""

    def __init__(self, patient: Any | None, **core_kwargs: Any) -> None:
        if "start_homed" not in core_kwargs and linarm_starts_homed():
            core_kwargs = {"initial_centre": K["HOME_CENTRE"], "initial_delta": K["HOME_DELTA"], **core_kwargs,
                           "start_homed": True}
        self.t0 = time.monotonic()
        self.core = LinarmSimCore(patient=_PatientOnCoreClock(patient, self.t0) if patient is not None else None,
                                  **core_kwargs)

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        return self.core.handle_host_bytes(data, t - self.t0)

    def poll(self, t: float) -> bytes:
        return self.core.stream_bytes(t - self.t0)

    def next_output(self) -> float | None:
        """When (monotonic) the core next has a stream frame to send, or None."""
        due = self.core.next_output_time()
        return None if due is None else self.t0 + due


# ---------------------------------------------------------------------------------------------- physiological board
class PhysioSimCore:
    """The simulated acquisition board: streams frames at its rate; ignores what the host sends."""

    def __init__(self, patient: SimulatedPatient, rate_hz: float, calibration: Calibration, seed: int = 1) -> None:
        self.source = PhysioSimSource(patient, seed=seed, rate_hz=rate_hz, calibration=calibration,
                                      start_time=time.monotonic())

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        return b""

    def poll(self, t: float) -> bytes:
        return self.source.frames_until(t)

    def next_output(self) -> float | None:
        """When (monotonic) the next frame is due."""
        return self.source.next_frame_time()


# ---------------------------------------------------------------------------------------------- FES stimulator
class RehaStimSimAdapter(RehaStimSimCore):
    """RehaStimSimCore on the SerialSimulator's interface (``with_core`` hands out the core's API)."""

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        return self.handle_bytes(data, t)

    def poll(self, t: float) -> bytes:
        return self.tick(t)

    def next_output(self) -> float | None:
        return self.next_event_time()
