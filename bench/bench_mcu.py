"""The firmware's 1 kHz budget on the emulated Cortex-M3 board (issue #31): the controller image for the MPS2 AN385
(firmware/host/mps2) under qemu-system-arm with instruction counting (-icount), the host streaming to it over
UART0 in real time. The image measures every control tick's work in counts of its 25 MHz system clock (a CMSDK
timer); with -icount shift=N one count is 40 / 2**N instructions. Per mode it prints the worst and p99 tick, the
plant's step (the simulated robot: hardware on the DUE, not part of its budget), the worst command poll, late
ticks, the painted stack's high-water mark and UART0's receive overruns / ring overflows, beside the DUE's
budget: 84 000 cycles per 1 ms tick at 84 MHz.

Caveat: qemu counts instructions, not cycles. A Cortex-M3 at 84 MHz with the SAM3X8E's flash wait states
needs more than one cycle for many of them (loads, branches, soft-float calls): read the percentages as
instructions against cycles, a lower bound of the real load.

    .venv/bin/python bench/bench_mcu.py [--seconds 4] [--shift 0] [--image firmware/build/due/linarm_mps2.elf]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.devices.sim.host import find_mcu_image  # noqa: E402
from app.wire.cmdmessenger import CmdMessengerDecoder  # noqa: E402
from app.wire.linarm_protocol import (  # noqa: E402
    ControlMode,
    ControlState,
    HomeState,
    LinarmState,
    decode_controller_frame,
    encode_command,
)
from firmware.tools.mcu_board import McuBoard  # noqa: E402

DUE_CYCLES_PER_TICK = 84_000  # 84 MHz x 1 ms
TARGET_SHARE = 0.50


class Host:
    """The host's side of UART0: commands, heartbeats, the controller's stream decoded."""

    def __init__(self, board: McuBoard) -> None:
        self.board = board
        self.decoder = CmdMessengerDecoder()
        self.seq = 0
        self.state: LinarmState | None = None
        self.frames = 0
        board.uart0.settimeout(0.001)

    def send(self, name: str, *args: object) -> None:
        self.seq = self.seq % 60000 + 1
        self.board.uart0.sendall(encode_command(name, self.seq, *args))

    def pump(self, seconds: float, every_s: float = 0.1, each: object = None) -> None:
        """Read the stream for `seconds`, sending a heartbeat (or calling `each`) every `every_s`."""
        end = time.monotonic() + seconds
        next_send = time.monotonic()
        while time.monotonic() < end:
            if time.monotonic() >= next_send:
                each() if callable(each) else self.send("heartbeat")
                next_send += every_s
            try:
                chunk = self.board.uart0.recv(65536)
            except TimeoutError:
                continue
            for frame in self.decoder.feed(chunk):
                try:
                    msg = decode_controller_frame(frame)
                except Exception:
                    continue
                self.frames += 1
                if isinstance(msg, LinarmState):
                    self.state = msg


def run(image: Path, seconds: float, shift: int) -> int:
    per_count = 40 / 2 ** shift  # instructions per count of the 25 MHz clock at 2**shift ns per instruction
    board = McuBoard(image, icount=shift)
    rows = []
    try:
        host = Host(board)
        host.send("startDataStream", 0.005)  # the app's 200 Hz stream, in every mode

        def measure(mode: str, pump_s: float, **pump: object) -> None:
            assert board.ask("RESET") == "OK"
            frames0 = host.frames
            host.pump(pump_s, **pump)
            s = board.status()
            st = host.state
            seen = (f"{ControlState(st.control_state).name.split('_')[0]}/{ControlMode(st.control_mode).name[8:]}"
                    f"/{st.error_state.name}" if st else "?")
            rows.append((mode, s, (host.frames - frames0) / pump_s, seen))

        measure("idle", seconds)
        host.send("setCtrlState", int(ControlState.HOME_CTRL_STATE))
        measure("homing", min(seconds, 2.0))
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and (host.state is None or host.state.home_state != HomeState.HOME_DONE
                                               or host.state.control_state != ControlState.ON_CTRL_STATE):
            if host.state is not None and host.state.home_state == HomeState.HOME_DONE:
                host.send("setCtrlState", int(ControlState.ON_CTRL_STATE))
            host.pump(0.3)
        if host.state is None or host.state.control_state != ControlState.ON_CTRL_STATE:
            print(f"homing did not finish: {host.state}", file=sys.stderr)
            return 1
        host.send("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS))
        targets = iter([0.40, 0.10] * 100)
        calls = [0]

        def back_and_forth() -> None:  # heartbeats at 10 Hz, a new trapezoid between 0.10 and 0.40 m every 2.2 s
            if calls[0] % 22 == 0:
                host.send("moveCentreTo", next(targets), 0.150, 0.150, 0.0, False)
            else:
                host.send("heartbeat")
            calls[0] += 1

        measure("trajectory", seconds, every_s=0.1, each=back_and_forth)
        host.send("setCtrlState", int(ControlState.IDLE_CTRL_STATE))
        host.send("setCtrlMode", int(ControlMode.POS_REF_BY_ADMITTANCE))
        host.send("setCtrlState", int(ControlState.ON_CTRL_STATE))
        pushes = iter([10.0, -10.0] * 1000)
        ticks = [0]

        def stream_200hz() -> None:  # the host at the stream's rate: a command every 5 ms, a push every 0.5 s
            host.send("heartbeat")
            ticks[0] += 1
            if ticks[0] % 100 == 1:
                board.ask(f"F {round(next(pushes) * 1000)}")

        measure("admittance 200 Hz", seconds, every_s=0.005, each=stream_200hz)
        host.send("setCtrlState", int(ControlState.IDLE_CTRL_STATE))
    finally:
        board.close()

    budget = DUE_CYCLES_PER_TICK
    print(f"emulated MPS2 AN385 (Cortex-M3) under qemu-system-arm -icount shift={shift}: 1 count of the 25 MHz clock = "
          f"{per_count:g} instructions; the DUE's budget: {budget} cycles per 1 ms tick (target: worst <= "
          f"{TARGET_SHARE:.0%})")
    print(f"{'mode':<19}{'ticks':>7}{'worst':>9}{'p99':>9}{'worst/DUE':>10}{'plant':>9}{'poll':>9}{'late':>6}"
          f"{'stack B':>9}{'rx B':>8}{'ovr':>5}{'drop':>5}{'ring':>6}{'frames/s':>9}  state/mode/error at the end")
    worst_share, overruns = 0.0, 0
    for mode, s, fps, seen in rows:
        worst, p99 = s["tick_max"] * per_count, s["tick_p99"] * per_count
        share = worst / budget
        worst_share = max(worst_share, share)
        overruns += s["rx_overruns"] + s["rx_dropped"]
        print(f"{mode:<19}{s['ticks']:>7}{worst:>9.0f}{p99:>9.0f}{share:>10.1%}{s['plant_max'] * per_count:>9.0f}"
              f"{s['poll_max'] * per_count:>9.0f}{s['late']:>6}{s['stack_hwm']:>9}{s['rx_bytes']:>8}"
              f"{s['rx_overruns']:>5}{s['rx_dropped']:>5}{s['rx_ring_hwm']:>6}{fps:>9.0f}  {seen}")
    print("instructions per tick (worst, p99: the controller's controlTick incl. interrupts); plant = the simulated "
          "robot's step; poll = the worst app.poll() with bytes; stack B = painted-stack high-water mark of "
          f"{rows[-1][1]['stack_size']} B; rx B / ovr / drop / ring = UART0 bytes, hardware overruns, ring "
          f"overflows, most bytes waiting in the {256} B ring")
    verdict = "met" if worst_share <= TARGET_SHARE and overruns == 0 else "MISSED"
    print(f"target (worst tick <= {TARGET_SHARE:.0%} of the DUE budget, zero overruns): {verdict}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=4.0, help="per mode (homing: at most 2 s)")
    parser.add_argument("--shift", type=int, default=0, help="-icount shift: 2**shift ns per instruction")
    parser.add_argument("--image", type=Path, default=None, help="the MPS2 image (default: the built one)")
    args = parser.parse_args()
    image = args.image or find_mcu_image()
    if image is None:
        print("the MPS2 image is not built: see firmware/README.md (cmake --build firmware/build/due)",
              file=sys.stderr)
        return 2
    return run(image, args.seconds, args.shift)


if __name__ == "__main__":
    sys.exit(main())
