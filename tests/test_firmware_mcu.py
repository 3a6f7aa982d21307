"""Issue #31: the firmware's ARM image as a machine — the controller logic, the CMSDK UART driver (receive by
interrupt into a ring), SysTick at 1 kHz and the SIL's plant, on qemu-system-arm's MPS2 AN385 board
(firmware/host/mps2) — talking to the host through the board's UART.

- the host goes silent: the image's own watchdog idles the motors within 0.25 s, seen on the UART0 stream;
- the shared protocol scenarios (tests/protocol_scenarios) through UART0, time stepped from the board
  console (UART1, "lockstep": one qemu for all of them, a fresh controller per scenario);
- the board console's STATUS: tick work, stack high-water mark, receive overruns;
- the seed's Fig. 18 script headless with ``simulation: {linarm: mcu}`` (the app's LINarm driver on UART0).

The image is built in the DUE build (tests/firmware_builds.py: once for every module, worker and run). Without
qemu-system-arm or the cross compiler the tests skip with the apt line as the reason; with CI set they fail.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import (
    ControlState,
    ErrorEvent,
    ErrorState,
    LinarmState,
    MotorState,
    decode_controller_frame,
    encode_command,
)
from firmware.tools.mcu_board import McuBoard
from tests import firmware_builds
from tests.test_firmware_arm import _need, build_cross
from tests.test_protocol_scenarios import SCENARIOS, Scenario, run_scenario

pytestmark = pytest.mark.realtime

APT_PACKAGES = "qemu-system-arm gcc-arm-none-eabi libnewlib-arm-none-eabi"
WATCHDOG_S = 0.25


@pytest.fixture(scope="session")
def mcu_image() -> Path:
    _need(("cmake", "arm-none-eabi-gcc", "arm-none-eabi-g++", "qemu-system-arm"), APT_PACKAGES)
    image = build_cross(firmware_builds.DUE, "linarm_mps2.elf") / "linarm_mps2.elf"
    assert image.is_file()
    return image


class McuLockstepTarget:
    """A scenario target (tests/test_protocol_scenarios.ScenarioTarget) on the emulated board: the host's bytes
    through UART0 into the ring and CmdMessenger, simulated time stepped from the console."""

    def __init__(self, board: McuBoard, centre: float = 0.20, start_homed: bool = False,
                 service: bool = False) -> None:
        self.board = board
        assert self._step("Z") == b""  # the board's real-time output before the harness took over is not ours:
        board.uart0.settimeout(0.05)  # its boot IDENTIFY, if qemu had the socket connected then
        with contextlib.suppress(TimeoutError):
            while board.uart0.recv(65536):
                pass
        self.sent = 0  # host bytes since "L", the board's reference for "S"
        self.pending = self._step(f"L {round(centre * 1e6)} 20000 {int(start_homed)} {int(service)}")

    def _step(self, line: str) -> bytes:
        answer = self.board.ask(line)
        assert answer.startswith("R "), f"{line!r} -> {answer!r}"
        return self.board.read_uart0(int(answer[2:]))

    def _with_pending(self, data: bytes) -> bytes:
        out, self.pending = self.pending + data, b""
        return out

    def send(self, data: bytes) -> bytes:
        self.board.uart0.sendall(data)
        self.sent += len(data)
        return self._with_pending(self._step(f"S {self.sent}"))

    def advance(self, seconds: float) -> bytes:
        return self._with_pending(self._step(f"A {round(seconds * 1000)}"))

    def push(self, newtons: float) -> bytes:
        return self._with_pending(self._step(f"F {round(newtons * 1000)}"))

    def restart(self) -> bytes:
        return self._with_pending(self._step("N"))

    def close(self) -> None:
        """The board stays up for the next scenario (each begins with a fresh controller)."""


@pytest.fixture(scope="module")
def lockstep_board(mcu_image: Path) -> Iterator[McuBoard]:
    board = McuBoard(mcu_image)
    yield board
    board.close()


@pytest.fixture
def realtime_board(mcu_image: Path) -> Iterator[McuBoard]:
    board = McuBoard(mcu_image)
    yield board
    board.close()


# ------------------------------------------------------------------------------------------------ the scenarios
@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.id for s in SCENARIOS])
def test_scenario_against_the_emulated_board(lockstep_board: McuBoard, scenario: Scenario) -> None:
    setup = scenario.setup
    target = McuLockstepTarget(lockstep_board, setup.get("centre", 0.20), setup.get("start_homed", False),
                               setup.get("service", False))
    run_scenario(target, scenario)


def test_a_wrong_expectation_fails_on_the_board_too(lockstep_board: McuBoard) -> None:
    bad = Scenario("bad", {}, [{"send": ["setCtrlState", 2]}], "inline")
    with pytest.raises(AssertionError, match="expected ACK"):
        run_scenario(McuLockstepTarget(lockstep_board), bad)


def test_the_board_receives_every_byte_through_its_ring(lockstep_board: McuBoard) -> None:
    """After the scenarios: the UART's receive path lost nothing (no overrun, no ring overflow), and the painted
    stack shows how deep the deepest command path went, well inside the stack."""
    status = lockstep_board.status()
    assert status["rx_bytes"] > 0
    assert status["rx_overruns"] == 0 and status["rx_dropped"] == 0, status
    assert 0 < status["stack_hwm"] < status["stack_size"] // 4, status


# ------------------------------------------------------------------------------------------ the image's watchdog
def test_host_silence_idles_the_motors_within_the_watchdog_time(realtime_board: McuBoard) -> None:
    """Real time: homing (motors on) with a heartbeat every 50 ms, then silence. The image's watchdog stops the
    motors and latches WATCHDOG after 0.25 s, seen on UART0: the ERROR_EVENT, IDLE and 0 A in the stream."""
    board, decoder = realtime_board, CmdMessengerDecoder()
    board.uart0.settimeout(0.02)
    received: list[tuple[float, Any]] = []

    def pump(until: float) -> None:
        while time.monotonic() < until:
            try:
                chunk = board.uart0.recv(65536)
            except TimeoutError:
                continue
            now = time.monotonic()
            for frame in decoder.feed(chunk):
                received.append((now, decode_controller_frame(frame)))

    board.uart0.sendall(encode_command("startDataStream", 1, 0.005) + encode_command("setCtrlState", 2,
                                                                                     int(ControlState.HOME_CTRL_STATE)))
    end = time.monotonic() + 0.5
    seq = 3
    while time.monotonic() < end:
        board.uart0.sendall(encode_command("heartbeat", seq))
        seq += 1
        pump(time.monotonic() + 0.05)
    homing = [m for _, m in received if isinstance(m, LinarmState)]
    assert homing and homing[-1].control_state == ControlState.HOME_CTRL_STATE, homing[-3:]
    assert any(isinstance(m, MotorState) and abs(m.current) > 0.01 for _, m in received), "the motors never ran"
    before_silence = len(received)
    t_last_host = time.monotonic()
    board.uart0.sendall(encode_command("heartbeat", seq))
    pump(t_last_host + WATCHDOG_S + 0.5)
    after = received[before_silence:]
    # the newest stream sample before the last host byte (motor/VSA frames every 5 ms): silence began after it
    t_controller_silent = max(m.t_us for _, m in received[:before_silence] if hasattr(m, "t_us"))
    events = [(t, m) for t, m in after if isinstance(m, ErrorEvent)]
    assert [m.error_state for _, m in events] == [ErrorState.WATCHDOG], events
    t_wall, event = events[0]
    silence = (event.t_us - t_controller_silent) * 1e-6  # the controller's own clock (SysTick-paced ticks)
    print(f"watchdog: {silence:.3f} s of silence on the controller's clock, the event on the host "
          f"{t_wall - t_last_host:.3f} s after its last byte")
    assert WATCHDOG_S - 0.01 <= silence <= WATCHDOG_S + 0.05, f"watchdog after {silence:.3f} s of silence"
    assert t_wall - t_last_host <= WATCHDOG_S + 0.15, f"the event reached the host {t_wall - t_last_host:.3f} s late"
    later = [m for _, m in after if getattr(m, "t_us", -1) > event.t_us]
    states = [m for m in later if isinstance(m, LinarmState)]
    currents = [m.current for m in later if isinstance(m, MotorState)]
    assert states and all(s.control_state == ControlState.IDLE_CTRL_STATE and s.error_state == ErrorState.WATCHDOG
                          for s in states)
    assert currents and all(c == 0.0 for c in currents), currents[:6]


# ------------------------------------------------------------------------------ the app, with linarm: mcu
@pytest.mark.slow
def test_trigger_exercise_fig18_against_the_emulated_board(mcu_image: Path, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The seed's Fig. 18 script, unmodified, headless, the LINarm being the image on the emulated board
    (simulation.linarm = mcu): 8 movements each after the grip, the record complete (test_seed_scripts'
    checks, with this configuration)."""
    from tests import test_seed_scripts

    base = test_seed_scripts.config

    def mcu_config() -> Any:
        cfg = base()
        return replace(cfg, simulation=replace(cfg.simulation, linarm="mcu", host="process"))

    import app.devices.sim.host as sim_host

    asked: list[Path] = []

    def image_found() -> Path:
        asked.append(mcu_image)
        return mcu_image

    monkeypatch.setattr(test_seed_scripts, "config", mcu_config)
    monkeypatch.setattr(sim_host, "find_mcu_image", image_found)
    monkeypatch.delenv("LINARMPP_SIM_HOST", raising=False)
    test_seed_scripts.test_trigger_exercise_fig18_moves_only_after_the_grip(tmp_path)
    assert asked, "the LINarm was not simulated by the emulated board"
    manifests = [p.read_text(encoding="utf-8") for p in tmp_path.rglob("*.json")]
    assert any("mps2-1.0" in text for text in manifests), "the record does not name the board's firmware"
