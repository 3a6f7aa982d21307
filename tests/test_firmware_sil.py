"""Acceptance: the app's LinarmDriver connects to the software-in-the-loop firmware over a pty and runs the
seed's trigger exercise motion (D2.2 Fig. 18: moveDeltaTo(0.010, ...), then 0.10 m <-> 0.40 m), with the
simulator's acceptance bounds: the target within 5 mm, peak speed <= maxVel x 1.05, a trapezoidal profile.

The SIL runs in real time here (its 1 kHz loop on the wall clock), so this test takes ~12 s.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import tty
from collections.abc import Iterator

import pytest

from app.core import streams
from app.core.bus import SampleItem, StreamBus
from app.core.config import SafetyConfig
from app.devices.linarm import LinarmCommandError, LinarmDriver
from app.devices.transport import SerialTransport
from app.safety.supervisor import SafetySupervisor
from app.wire.linarm_protocol import ControlMode, ControlState, HomeState, ReplyError
from tests.test_firmware import build_firmware

pytestmark = pytest.mark.slow

MAX_VEL = 0.150
MAX_ACC = 0.150


@pytest.fixture(scope="module")
def sil_link() -> Iterator[str]:
    """linarm_sil on the master side of a pty; yields the slave's path for the driver."""
    build = build_firmware("linarm_sil")
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo: the firmware must not read its own frames back
    proc = subprocess.Popen([str(build / "linarm_sil"), "--centre", "0.20"], stdin=master, stdout=master,
                            stderr=subprocess.PIPE)
    try:
        yield os.ttyname(slave)
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        if proc.stderr is not None:
            proc.stderr.close()
        os.close(master)
        os.close(slave)


class CentreRecorder:
    """(controller time, centre) of every VSA sample, from a queued bus subscription (none dropped: counted)."""

    def __init__(self, bus: StreamBus) -> None:
        self.queue = bus.subscribe("test centre", (streams.LINARM_VSA,), maxlen=1_000_000)
        self.samples: list[tuple[float, float]] = []

    def since(self, t0: float) -> list[tuple[float, float]]:
        self.samples.extend((i.sample.controllerTime, i.sample.equilibriumPos)
                            for i in self.queue.drain() if isinstance(i, SampleItem))
        assert self.queue.dropped == 0
        return [s for s in self.samples if s[0] >= t0]


def speeds(samples: list[tuple[float, float]], window: int = 4) -> list[tuple[float, float]]:
    """Centre speed by differences over `window` stream periods (20 ms at 200 Hz)."""
    out = []
    for (ta, xa), (tb, xb) in zip(samples, samples[window:], strict=False):
        if tb > ta:
            out.append(((ta + tb) / 2, (xb - xa) / (tb - ta)))
    return out


def test_driver_runs_the_trigger_exercise_on_the_firmware(qtbot, sil_link: str) -> None:  # type: ignore[no-untyped-def]
    driver = LinarmDriver(SerialTransport(sil_link), SafetySupervisor(SafetyConfig()))
    recorder = CentreRecorder(driver.bus)
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.connected and driver.latest("linarm.vsa") is not None, timeout=5000)
        assert driver.firmware_version == "sil-1.0"
        # what the app does at connect: its site limits, locked as the controller's envelope
        site = driver.supervisor.robot
        envelope = driver.apply_limits(site).result(5.0)
        assert envelope["maxVel"] == pytest.approx(site.max_velocity_m_s, rel=1e-6)
        assert envelope["minPos"] == pytest.approx(site.position_min_m, rel=1e-6)
        # a host bug widens the supervisor's limits: the controller still refuses
        driver.supervisor.robot = dataclasses.replace(site, max_velocity_m_s=1.0)
        with pytest.raises(LinarmCommandError) as refused:
            driver.command("setMaxVelocity", 1.0)
        assert refused.value.code == ReplyError.LOCKED
        driver.supervisor.robot = site
        # a session narrows to the patient's profile and goes back to the site's limits afterwards (app/manager.py)
        driver.apply_limits(dataclasses.replace(site, max_velocity_m_s=0.1, position_max_m=0.40)).result(5.0)
        driver.apply_limits(site).result(5.0)

        driver.command("goToHome")
        qtbot.waitUntil(lambda: driver.latest("linarm.state").homeState == HomeState.HOME_DONE, timeout=8000)

        # the seed's script, unmodified calls
        driver.command("setCtrlState", int(ControlState.IDLE_CTRL_STATE))
        driver.command("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS))
        driver.command("setCtrlState", int(ControlState.ON_CTRL_STATE))
        driver.command("moveDeltaTo", 0.010, MAX_VEL, MAX_ACC, 0, False)
        driver.command("moveCentreTo", 0.10, MAX_VEL, MAX_ACC, 0, False)  # to the start point
        qtbot.waitUntil(lambda: abs(driver.latest("linarm.vsa").equilibriumPos - 0.10) < 1e-3, timeout=5000)
        assert driver.latest("linarm.vsa").delta == pytest.approx(0.010, abs=1e-3)

        for start, end in ((0.10, 0.40), (0.40, 0.10)):
            t0 = driver.latest("linarm.vsa").controllerTime
            driver.command("moveCentreTo", end, MAX_VEL, MAX_ACC, 0, False)
            qtbot.waitUntil(lambda end=end: abs(end - driver.latest("linarm.vsa").equilibriumPos) < 5e-3,
                            timeout=6000)
            qtbot.waitUntil(lambda t0=t0: driver.latest("linarm.vsa").controllerTime > t0 + 3.4, timeout=3000)
            vsa = driver.latest("linarm.vsa")
            assert vsa.equilibriumPos == pytest.approx(end, abs=0.005)
            assert vsa.handlePos == pytest.approx(end, abs=0.005)
            profile = [(t - t0, abs(v)) for t, v in speeds(recorder.since(t0))]
            peak = max(v for _, v in profile)
            assert peak <= MAX_VEL * 1.05, f"peak speed {peak:.4f} m/s"

            def speed_at(tau: float, profile: list[tuple[float, float]] = profile) -> float:
                return min(profile, key=lambda s: abs(s[0] - tau))[1]

            # trapezoid: D = 0.3 m, 1 s ramp, 1 s cruise, 1 s ramp (t0 is within a few ms of the command)
            assert speed_at(0.5) == pytest.approx(0.075, abs=0.012)
            for tau in (1.3, 1.5, 1.7):
                assert speed_at(tau) == pytest.approx(MAX_VEL, abs=0.008)
            assert speed_at(2.5) == pytest.approx(0.075, abs=0.012)
            assert speed_at(3.3) < 0.005
            print(f"{start:.2f} -> {end:.2f} m: reached {vsa.equilibriumPos:.4f} m, peak {peak:.4f} m/s")

        state = driver.latest("linarm.state")
        assert state.errorState == 0 and state.controlState == ControlState.ON_CTRL_STATE
        driver.command("setCtrlState", int(ControlState.IDLE_CTRL_STATE))
        assert driver.protocol_errors == 0
    finally:
        driver.stop()
        driver.wait(3000)
