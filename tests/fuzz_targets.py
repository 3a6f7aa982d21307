"""Fuzz targets for every codec: random bytes and mutations of valid frames, fed in random chunks.

A target must never raise, and must decode a valid frame that follows the damage (resync within
one frame). The suite runs a few thousand inputs per codec (tests/test_fuzz_codecs.py); the full
count (10^5 per codec) runs with `python bench/fuzz_codecs.py`.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass

from app.wire import linarm_protocol as lp
from app.wire import sciencemode as sm
from app.wire import udp_frames as uf
from app.wire.cmdmessenger import ArduinoReceiver, CmdMessengerDecoder
from app.wire.physio_codec import PhysioRawFrame, PhysioStreamDecoder, encode_physio_frame


@dataclass
class FuzzTarget:
    name: str
    valid_frames: list[bytes]
    # Feed one damaged input (in chunks) then `probe`; return True when `probe` was decoded.
    run: Callable[[list[bytes], bytes], bool]


def _physio_frames() -> list[bytes]:
    return [encode_physio_frame(PhysioRawFrame(seq=i, tick=10 * i, ppg=2000 + i, skinConductance=500,
                                               temperature=2300, force=40 * i)) for i in range(8)]


def _run_physio(chunks: list[bytes], probe: bytes) -> bool:
    dec = PhysioStreamDecoder()
    for c in chunks:
        dec.feed(c)
    # Two valid frames: the first may be eaten by a damaged header just before it; the second must come out.
    got = dec.feed(probe + probe)
    return any(s.seq == 7 for s in got)


def _linarm_controller_frames() -> list[bytes]:
    return [
        lp.encode_vsa_state(lp.VsaState(123, 0.25, 0.02, 900.0, 0.251, -0.01, 1.5)),
        lp.encode_motor_state(lp.MotorState(456, 1, 0.3, 0.0, 0.5, 0.3)),
        lp.encode_ack(7, "moveCentreTo"),
        lp.encode_error(9, 9, lp.ReplyError.OUT_OF_RANGE, "targetPos"),
        lp.encode_identify(1, "fw-1.0"),
    ]


def _run_linarm_host(chunks: list[bytes], probe: bytes) -> bool:
    dec = CmdMessengerDecoder()
    for c in chunks:
        for frame in dec.feed(c):
            try:
                lp.decode_controller_frame(frame)
            except lp.ProtocolError:
                pass
    ok = False
    for frame in dec.feed(b";" + probe + b";" + probe):  # at most one frame lost to the damage
        try:
            ok |= isinstance(lp.decode_controller_frame(frame), lp.VsaState)
        except lp.ProtocolError:
            pass
    return ok


def _linarm_host_frames() -> list[bytes]:
    return [
        lp.encode_command("moveCentreTo", 5, 0.4, 0.15, 0.15, 0.0, False),
        lp.encode_command("setCtrlState", 6, 2),
        lp.encode_command("heartbeat", 7),
        lp.encode_command("setPidTunings", 8, 1, 100.0, 1.0, 2.0),
    ]


def _run_linarm_firmware(chunks: list[bytes], probe: bytes) -> bool:
    rx = ArduinoReceiver()
    for c in chunks:
        for msg in rx.feed(c):
            try:
                lp.read_host_message(msg)
            except lp.CommandRejected:
                pass
    ok = False
    for msg in rx.feed(b";" + probe + b";" + probe):
        try:
            ok |= lp.read_host_message(msg).name == "setPidTunings"
        except lp.CommandRejected:
            pass
    return ok


_CCL = sm.ChannelListConfig(channels=(1, 2), t1_ms=25.0, t2_ms=3.0)
_SETTINGS = {1: sm.PulseSetting(20, 200), 2: sm.PulseSetting(10, 150)}


def _sm1_frames() -> list[bytes]:
    return [sm.encode_sm1_init(_CCL), sm.encode_sm1_update(_CCL, _SETTINGS), sm.encode_sm1_stop()]


def _run_sm1_device(chunks: list[bytes], probe: bytes) -> bool:
    dec = sm.Sm1CommandDecoder()
    dec.update_channels = _CCL.channels
    for c in chunks:
        dec.feed(c)
    dec.update_channels = _CCL.channels
    return any(isinstance(m, sm.Sm1Stop) for m in dec.feed(probe + probe))


def _run_sm1_acks(chunks: list[bytes], probe: bytes) -> bool:
    dec = sm.Sm1AckDecoder()
    for c in chunks:
        dec.feed(c)
    return any(isinstance(m, sm.Sm1Ack) for m in dec.feed(probe))


def _sm2_frames() -> list[bytes]:
    return [sm.encode_sm2_init_channel_list(3, _CCL), sm.encode_sm2_start(4, _CCL, _SETTINGS),
            sm.encode_sm2(sm.Sm2StopChannelListMode(5))]


def _run_sm2(chunks: list[bytes], probe: bytes) -> bool:
    dec = sm.Sm2Decoder()
    for c in chunks:
        dec.feed(c)
    return any(isinstance(m, sm.Sm2StopChannelListMode) for m in dec.feed(probe + probe))


def _datagram_target(name: str, frames: list[bytes], decode: Callable[[bytes], object]) -> FuzzTarget:
    def run(chunks: list[bytes], probe: bytes) -> bool:
        for c in chunks:  # each chunk is one datagram
            try:
                decode(c)
            except uf.FrameError:
                pass
        return decode(probe) is not None  # datagrams are self-contained: the next one always decodes

    return FuzzTarget(name, frames, run)


def _udp_targets() -> list[FuzzTarget]:
    pm = uf.encode_patient_model_frame(uf.PatientModelFrame(12, 72.0, 3.1, 33.2, 15.0, 2.5, 0.1, 0.25, 0.4))
    reply = uf.encode_patient_model_reply(uf.PatientModelReply(3, 12, 0.3, 0.5, 0.6, 0.1, 0.0, 0.6))
    vr = uf.encode_vr_frame(uf.VrFrame(4, 15.0, 2.5, 0.1, 0.25, 0.4))
    ev = uf.encode_vr_event(uf.VrEventFrame(5, next(iter(uf.VrEvent))))
    return [
        _datagram_target("udp patient-model frame", [pm], uf.decode_patient_model_frame),
        _datagram_target("udp patient-model reply", [reply], uf.decode_patient_model_reply),
        _datagram_target("udp VR frame", [vr], uf.decode_vr_frame),
        _datagram_target("udp VR event", [ev], uf.decode_vr_event),
    ]


def all_targets() -> list[FuzzTarget]:
    return [
        FuzzTarget("physio 20-byte frames", _physio_frames(), _run_physio),
        FuzzTarget("LINarm controller→host (CmdMessenger)", _linarm_controller_frames(), _run_linarm_host),
        FuzzTarget("LINarm host→controller (Arduino receiver)", _linarm_host_frames(), _run_linarm_firmware),
        FuzzTarget("ScienceMode 1 commands (device side)", _sm1_frames(), _run_sm1_device),
        FuzzTarget("ScienceMode 1 acks", [sm.encode_sm1_ack(1, True)], _run_sm1_acks),
        FuzzTarget("ScienceMode 2 packets", _sm2_frames(), _run_sm2),
        *_udp_targets(),
    ]


def probe_for(target: FuzzTarget) -> bytes:
    return target.valid_frames[-1] if "LINarm controller" not in target.name else target.valid_frames[0]


def make_input(rng: random.Random, target: FuzzTarget) -> list[bytes]:
    """Random bytes, or a valid frame sequence with flips, drops, inserts and truncation; in chunks."""
    kind = rng.random()
    if kind < 0.3:
        data = bytearray(rng.randbytes(rng.randint(0, 120)))
    else:
        data = bytearray(b"".join(rng.choice(target.valid_frames) for _ in range(rng.randint(1, 4))))
        for _ in range(rng.randint(1, 4)):
            if not data:
                break
            op, i = rng.random(), rng.randrange(len(data))
            if op < 0.35:
                data[i] ^= 1 << rng.randrange(8)
            elif op < 0.6:
                del data[i]
            elif op < 0.85:
                data.insert(i, rng.randrange(256))
            else:
                del data[i:]
    if target.name.startswith("udp"):
        return [bytes(data)]
    chunks, i = [], 0
    while i < len(data):
        n = rng.randint(1, 25)
        chunks.append(bytes(data[i:i + n]))
        i += n
    return chunks


def fuzz(target: FuzzTarget, count: int, seed: int = 1) -> tuple[int, int]:
    """Run ``count`` inputs; return (inputs, resync failures). Exceptions propagate (they are bugs)."""
    rng = random.Random(seed)
    probe = probe_for(target)
    failures = 0
    for _ in range(count):
        if not target.run(make_input(rng, target), probe):
            failures += 1
    return count, failures
