"""Codecs: frames per second of every decoder, and our CmdMessenger decoder against PyCmdMessenger 0.2.4 on the
same LINarm controller frames (the decoded values must be identical).

    .venv/bin/python bench/bench_codecs.py [--frames N] [--trials T]

Stream decoders are fed the bytes in 4 KiB reads (as a driver's serial read hands them over); UDP decoders
get one datagram per call. Each figure is over ``--trials`` repetitions: the median rate and the p99 of the
per-trial time, as a rate (the slowest trials).

PyCmdMessenger needs bench/.venv (bench/README.md). It reads from a fake serial object holding the bytes,
one byte per ``read()`` call as the library does, with the Arduino DUE's sizes (int_bytes=4, long_bytes=4,
float_bytes=4, double_bytes=8). The frames compared are the controller's real ones (vsaState, motorState,
linarmState, ack) with random values; text booleans decode as 1/0 there and True/False here (equal values).
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

from app.wire import linarm_protocol as lp
from app.wire import sciencemode as sm
from app.wire import udp_frames as uf
from app.wire.cmdmessenger import ArduinoReceiver, CmdMessengerDecoder, read_field
from app.wire.physio_codec import PhysioRawFrame, PhysioStreamDecoder, encode_physio_frame

READ_SIZE = 4096


def chunks(data: bytes) -> list[bytes]:
    return [data[i:i + READ_SIZE] for i in range(0, len(data), READ_SIZE)]


def controller_frames(n: int, seed: int = 3) -> list[bytes]:
    """The LINarm controller's stream: per period a VSA and two motor frames, a state frame every tenth, acks."""
    rng = random.Random(seed)

    def f() -> float:
        return rng.uniform(-2.0, 2.0)

    out: list[bytes] = []
    k = 0
    while len(out) < n:
        t_us = (k * 5000) & 0xFFFFFFFF
        out.append(lp.encode_vsa_state(lp.VsaState(t_us, f(), f(), rng.uniform(0, 3000), f(), f(), f())))
        out.append(lp.encode_motor_state(lp.MotorState(t_us, k % 2, f(), f(), f(), f())))
        if k % 10 == 0:
            out.append(lp.encode_linarm_state(lp.LinarmState(
                t_us, lp.ControlState(rng.randrange(3)), lp.ControlMode(rng.randrange(5)),
                lp.HomeState(rng.randrange(5)), lp.ErrorState(rng.randrange(9)), lp.TriggerMode(rng.randrange(3)),
                rng.random() < 0.5, lp.TrajectoryType(rng.randrange(2)), rng.random() < 0.5, rng.random() < 0.5,
                rng.random() < 0.5)))
        if k % 25 == 0:
            out.append(lp.encode_ack(k & 0xFFFF, "moveCentreTo"))
        k += 1
    return out[:n]


def physio_stream(n: int) -> bytes:
    return b"".join(encode_physio_frame(PhysioRawFrame(seq=i & 0xFFFF, tick=(10 * i) & 0xFFFF, ppg=2000 + i % 900,
                                                       skinConductance=500, temperature=2300, force=40 * (i % 50)))
                    for i in range(n))


def timed(fn: Callable[[], int], trials: int) -> tuple[list[float], int]:
    """Per-trial seconds and the items decoded (the same every trial)."""
    times, count = [], 0
    for _ in range(trials):
        t0 = time.perf_counter()
        count = fn()
        times.append(time.perf_counter() - t0)
    return times, count


def report_rate(name: str, times: list[float], count: int) -> None:
    rates = [count / t for t in times]
    slow = count / common.percentile(times, 99.0)
    print(f"  {name:58} {count:7d} frames  median {sorted(rates)[len(rates) // 2]:12,.0f} /s"
          f"  p99 {slow:12,.0f} /s", flush=True)


# ---------------------------------------------------------------------------------------------- PyCmdMessenger
class FakeSerial:
    """What PyCmdMessenger's ArduinoBoard reads from: the bytes, one ``read()`` at a time."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def read(self, size: int = 1) -> bytes:
        out = self.data[self.pos:self.pos + size]
        self.pos += len(out)
        return out

    def write(self, data: bytes) -> int:
        return len(data)


def pycmdmessenger(data: bytes) -> Any:
    from PyCmdMessenger import ArduinoBoard, CmdMessenger

    class FakeBoard(ArduinoBoard):
        def open(self) -> None:
            self.comm = FakeSerial(data)
            self._is_connected = True

    formats = {"ack": "gg", "linarmState": "L" + "g" * 10, "motorState": "Lgffff", "vsaState": "Lffffff"}
    commands = [[f"unused{i}", ""] for i in range(max(lp.MESSAGES_BY_ID) + 1)]
    for msg in lp.CONTROLLER_MESSAGES:
        if msg.name in formats:
            commands[msg.id] = [msg.name, formats[msg.name]]
    board = FakeBoard("fake", int_bytes=4, long_bytes=4, float_bytes=4, double_bytes=8)
    return CmdMessenger(board, commands, warnings=False)


def ours_values(data: bytes) -> list[tuple[int, list[Any]]]:
    decoder = CmdMessengerDecoder()
    out = []
    for chunk in chunks(data):
        for frame in decoder.feed(chunk):
            spec = lp.MESSAGES_BY_ID[frame.cmd_id]
            out.append((frame.cmd_id, [read_field(f, a.kind) for f, a in zip(frame.fields, spec.fields,
                                                                               strict=False)]))
    return out


def theirs_values(data: bytes) -> list[tuple[int, list[Any]]]:
    messenger = pycmdmessenger(data)
    ids = {name: i for i, (name, _fmt) in enumerate(messenger.commands)}
    out = []
    while True:
        got = messenger.receive()
        if got is None:
            return out
        name, values, _t = got
        out.append((ids[name], list(values)))


def compare_pycmdmessenger(frames: list[bytes], trials: int) -> None:
    if not common.use_extras():
        print("  PyCmdMessenger: not installed (create bench/.venv as bench/README.md says)")
        return
    try:
        import PyCmdMessenger  # noqa: F401
    except ImportError as exc:
        print(f"  PyCmdMessenger: cannot import ({exc})")
        return
    data = b"".join(frames)
    ours = ours_values(data)
    theirs = theirs_values(data)
    same = sum(1 for a, b in zip(ours, theirs, strict=False) if a == b)
    print(f"  identical results: {same} of {len(ours)} frames (PyCmdMessenger decoded {len(theirs)})"
          + ("" if same == len(ours) == len(theirs) else "  ← DIFFERENT"))
    times, count = timed(lambda: len(ours_values(data)), trials)
    report_rate("ours: CmdMessengerDecoder + read_field (same output)", times, count)
    times, count = timed(lambda: len(theirs_values(data)), trials)
    report_rate("PyCmdMessenger 0.2.4 receive() (byte reads)", times, count)


# ---------------------------------------------------------------------------------------------- main
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--trials", type=int, default=7)
    args = parser.parse_args()
    common.print_machine("codecs: decoder throughput")
    n, trials = args.frames, args.trials

    physio = physio_stream(n)

    def physio_feed() -> int:
        dec = PhysioStreamDecoder()
        return sum(len(dec.feed(c, 0.0)) for c in chunks(physio))

    def physio_batch() -> int:
        dec = PhysioStreamDecoder()
        return sum(len(dec.feed_batch(c)[0]) for c in chunks(physio))

    controller = b"".join(controller_frames(n))

    def linarm_split() -> int:
        dec = CmdMessengerDecoder()
        return sum(len(dec.feed(c)) for c in chunks(controller))

    def linarm_typed() -> int:
        dec = CmdMessengerDecoder()
        return sum(1 for c in chunks(controller) for f in dec.feed(c) if lp.decode_controller_frame(f))

    host_frames = [lp.encode_command("moveCentreTo", i & 0xFFFF, 0.1 + (i % 30) / 100, 0.15, 0.15, 0.0, False)
                   for i in range(n // 2)]
    host_frames += [lp.encode_command("heartbeat", i & 0xFFFF) for i in range(n - len(host_frames))]
    host = b"".join(host_frames)

    def linarm_firmware() -> int:
        rx = ArduinoReceiver()
        return sum(1 for c in chunks(host) for m in rx.feed(c) if lp.read_host_message(m))

    from tests.fuzz_targets import all_targets

    valid = {t.name: t.valid_frames for t in all_targets()}
    sm1_cmds = b"".join(valid["ScienceMode 1 commands (device side)"] * (n // 3))
    sm1_acks = b"".join(valid["ScienceMode 1 acks"] * n)
    sm2 = b"".join(valid["ScienceMode 2 packets"] * (n // 3))

    def sm1_device() -> int:
        dec = sm.Sm1CommandDecoder()
        from tests.fuzz_targets import _CCL

        dec.update_channels = _CCL.channels
        return sum(len(dec.feed(c)) for c in chunks(sm1_cmds))

    def sm1_ack() -> int:
        dec = sm.Sm1AckDecoder()
        return sum(len(dec.feed(c)) for c in chunks(sm1_acks))

    def sm2_packets() -> int:
        dec = sm.Sm2Decoder()
        return sum(len(dec.feed(c)) for c in chunks(sm2))

    def datagrams(decode: Callable[[bytes], Any], frame: bytes) -> Callable[[], int]:
        def run() -> int:
            for _ in range(n):
                decode(frame)
            return n
        return run

    cases: list[tuple[str, Callable[[], int]]] = [
        ("physio 20-byte frames: feed() → PhysioSample", physio_feed),
        ("physio 20-byte frames: feed_batch() (numpy)", physio_batch),
        ("LINarm controller→host: CmdMessenger frames only", linarm_split),
        ("LINarm controller→host: frames → typed messages", linarm_typed),
        ("LINarm host→controller: Arduino receiver model + decode", linarm_firmware),
        ("ScienceMode 1 commands (simulator side)", sm1_device),
        ("ScienceMode 1 acks", sm1_ack),
        ("ScienceMode 2 packets", sm2_packets),
        ("UDP patient-model frame", datagrams(uf.decode_patient_model_frame, valid["udp patient-model frame"][0])),
        ("UDP patient-model reply", datagrams(uf.decode_patient_model_reply, valid["udp patient-model reply"][0])),
        ("UDP VR frame", datagrams(uf.decode_vr_frame, valid["udp VR frame"][0])),
        ("UDP VR event", datagrams(uf.decode_vr_event, valid["udp VR event"][0])),
    ]
    for name, fn in cases:
        times, count = timed(fn, trials)
        report_rate(name, times, count)
    print()
    print("CmdMessenger decoder vs PyCmdMessenger on the same controller frames:")
    compare_pycmdmessenger(controller_frames(min(n, 5000)), trials)
    return 0


if __name__ == "__main__":
    sys.exit(main())
