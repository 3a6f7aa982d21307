"""Device time → host time (issue #27, acceptance 2), on a virtual clock: no wall time, no threads.

A simulated device samples every 5 ms on its own clock (±200 ppm off the host's, a counter that wraps), and
its link delivers the frames in random bursts of 1-10 with up to 50 ms of delay, as a USB-serial adapter and a
busy host do. After a 5 s warm-up the stamps must be within 0.5 ms (p99) of the true send times; a device reset
and a counter wrap must be survived. The driver-level tests feed real LINarm and physiological-board frames to
the drivers' decoding path with virtual arrival times: on the stamping before #27 (the arrival time) they fail.
"""

from __future__ import annotations

import itertools
import random
from dataclasses import dataclass

import numpy as np
import pytest

from app.core.bus import SampleItem
from app.devices.clock import CountedClock, DeviceClock
from app.wire import linarm_protocol as proto

PERIOD_S = 0.005
WRAP_US = 2**32


@dataclass
class Frame:
    send_s: float  # true host time at sampling
    device_raw: float  # device clock reading (wrapped), s


def device_frames(seconds: float, ppm: float, start_raw_s: float = 1.0, host_t0: float = 1000.0,
                  period_s: float = PERIOD_S, wrap_s: float = WRAP_US / 1e6, tick_s: float = 1e-6) -> list[Frame]:
    """Frames every ``period_s`` of device time; the device clock runs ``ppm`` fast against the host's."""
    out = []
    n = int(seconds / period_s)
    for k in range(n):
        dev = start_raw_s + k * period_s
        send = host_t0 + k * period_s / (1.0 + ppm * 1e-6)
        raw = (round(dev / tick_s) * tick_s) % wrap_s
        out.append(Frame(send, raw))
    return out


def bursty_link(frames: list[Frame], rng: random.Random, max_burst: int = 10,
                max_delay_s: float = 0.050) -> list[tuple[float, list[Frame]]]:
    """(arrival, frames) per read: bursts of 1..max_burst frames (a USB-serial adapter's packets, a reader that
    ran late), read after the burst's last frame by a delay that is usually short (exponential, mean 2 ms: the
    adapter's latency and the reader's wake-up) and, one read in five, anything up to max_delay_s (a busy host).
    No frame waits more than max_delay_s, and no read comes before the previous one."""
    reads: list[tuple[float, list[Frame]]] = []
    i, last = 0, 0.0
    while i < len(frames):
        size = rng.randint(1, max_burst)
        burst = frames[i:i + size]
        i += size
        late = rng.uniform(0.0, max_delay_s) if rng.random() < 0.2 else rng.expovariate(1 / 0.002)
        span = burst[-1].send_s - burst[0].send_s
        arrival = max(last, burst[-1].send_s + max(0.0, min(late, max_delay_s - span)))
        last = arrival
        reads.append((arrival, burst))
    return reads


def errors_after(stamps: list[tuple[float, float]], warmup_s: float, t0: float) -> np.ndarray:
    return np.array([abs(m - s) for s, m in stamps if s - t0 >= warmup_s])


@pytest.mark.parametrize("ppm", [-200.0, 0.0, 200.0])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_mapped_times_within_half_a_millisecond_of_the_send_times(ppm: float, seed: int) -> None:
    rng = random.Random(seed)
    frames = device_frames(20.0, ppm)
    clock = DeviceClock(wrap_s=WRAP_US / 1e6)
    stamps = []
    for arrival, burst in bursty_link(frames, rng):
        for f in burst:
            mapped = clock.map(f.device_raw, arrival)
            assert mapped <= arrival + 1e-4, "a sample stamped after it arrived"  # µs steps at the seed only
            stamps.append((f.send_s, mapped))
    err = errors_after(stamps, 5.0, frames[0].send_s)
    assert np.percentile(err, 99) < 0.0005, f"p99 error {1000 * np.percentile(err, 99):.3f} ms"
    mapped = np.array([m for _s, m in stamps])
    assert np.all(np.diff(mapped) > 0), "stamps must strictly increase"
    assert clock.resets == 0
    assert abs(clock.estimate.drift + ppm * 1e-6) < 50e-6, f"drift {clock.estimate.drift * 1e6:.0f} ppm"


def test_arrival_stamping_misses_by_far() -> None:
    """The yardstick: the arrival time itself (the stamping before #27) is off by tens of milliseconds."""
    rng = random.Random(1)
    frames = device_frames(10.0, 200.0)
    stamps = [(f.send_s, arrival) for arrival, burst in bursty_link(frames, rng) for f in burst]
    assert np.percentile(errors_after(stamps, 5.0, frames[0].send_s), 99) > 0.02


def test_a_counter_wrap_is_survived() -> None:
    rng = random.Random(4)
    wrap_s = WRAP_US / 1e6
    frames = device_frames(20.0, 150.0, start_raw_s=wrap_s - 8.0)  # wraps 8 s in
    assert any(b.device_raw < a.device_raw for a, b in itertools.pairwise(frames))
    clock = DeviceClock(wrap_s=wrap_s)
    stamps = [(f.send_s, clock.map(f.device_raw, arrival)) for arrival, burst in bursty_link(frames, rng)
              for f in burst]
    assert clock.resets == 0, "a wrap is not a reset"
    assert np.percentile(errors_after(stamps, 5.0, frames[0].send_s), 99) < 0.0005


def test_a_device_reset_reseeds_the_clock() -> None:
    """The device restarts 10 s in: its counter starts again near 0. Stamps stay increasing, the clock re-seeds
    once, and 5 s after the reset the stamps are within 0.5 ms again."""
    rng = random.Random(5)
    before = device_frames(10.0, -200.0, start_raw_s=500.0)
    t_reset = before[-1].send_s + 0.3  # 0.3 s of silence while it boots
    after = device_frames(12.0, -200.0, start_raw_s=0.002, host_t0=t_reset)
    clock = DeviceClock(wrap_s=WRAP_US / 1e6)
    stamps = [(f.send_s, clock.map(f.device_raw, arrival)) for arrival, burst in bursty_link(before + after, rng)
              for f in burst]
    assert clock.resets == 1
    mapped = np.array([m for _s, m in stamps])
    assert np.all(np.diff(mapped) > 0)
    later = [(s, m) for s, m in stamps if s >= t_reset]
    assert np.percentile(errors_after(later, 5.0, t_reset), 99) < 0.0005


def test_a_forward_jump_reseeds_and_a_single_corrupt_time_is_ignored() -> None:
    clock = DeviceClock(wrap_s=WRAP_US / 1e6)
    frames = device_frames(8.0, 0.0)
    stamps = []
    for k, f in enumerate(frames):
        raw = f.device_raw + (0.3 if k == 1000 else 0.0)  # one corrupt device time, 300 ms ahead
        stamps.append((f.send_s, clock.map(raw, f.send_s + 0.001)))
    assert clock.resets == 0 and clock.outliers == 1
    assert np.percentile(errors_after(stamps, 5.0, frames[0].send_s), 99) < 0.0015
    # the device clock jumps 5 s ahead for good (the firmware restarted its timer): a re-seed
    t = frames[-1].send_s
    for k in range(1, 400):
        clock.map(frames[-1].device_raw + 5.0 + k * PERIOD_S, t + k * PERIOD_S + 0.001)
    assert clock.resets == 1


def test_a_counted_clock_takes_the_jitter_out_of_arrivals() -> None:
    """A stream without a device clock (the VR's frames): the arrival times dejittered on its sequence number."""
    rng = random.Random(6)
    period = 0.02
    sends = [100.0 + k * period for k in range(1000)]
    clock = CountedClock(1.0 / period, wrap=65536)
    stamps = []
    for k, send in enumerate(sends):
        arrival = send + rng.uniform(0.0, 0.008)
        stamps.append((send, clock.map(arrival, seq=(k + 65000) % 65536)))  # wraps on the way
    err = errors_after(stamps, 3.0, sends[0])
    assert np.percentile(err, 99) < 0.001
    assert clock.clock.resets == 0


# ---------------------------------------------------------------------------------------------- the drivers
class _NoLink:
    description = "none"
    is_open = False

    def open(self) -> None: ...
    def close(self) -> None: ...
    def read(self, timeout: float) -> bytes:
        return b""

    def write(self, data: bytes) -> None: ...


def _vsa_frame(raw_us: int) -> bytes:
    return proto.encode_vsa_state(proto.VsaState(raw_us, 0.2, 0.03, 100.0, 0.2, 0.0, 0.0))


def _motor_frame(raw_us: int, index: int) -> bytes:
    return proto.encode_motor_state(proto.MotorState(raw_us, index, 0.2, 0.0, 0.0, 0.2))


@pytest.mark.parametrize("ppm", [-200.0, 200.0])
def test_linarm_samples_are_stamped_on_the_controller_clock(qtbot, ppm: float) -> None:
    from app.core.config import SafetyConfig
    from app.devices.linarm import LinarmDriver
    from app.safety.supervisor import SafetySupervisor

    driver = LinarmDriver(_NoLink(), SafetySupervisor(SafetyConfig()))  # type: ignore[arg-type]
    queue = driver.bus.subscribe("test", maxlen=1_000_000)
    frames = device_frames(12.0, ppm, start_raw_s=WRAP_US / 1e6 - 6.0)  # the controller's micros() wraps
    send_by_raw = {}
    for arrival, burst in bursty_link(frames, random.Random(7)):
        data = b""
        for f in burst:
            raw = round(f.device_raw * 1e6) % WRAP_US
            send_by_raw[raw] = f.send_s
            data += _vsa_frame(raw) + _motor_frame(raw, 0)
        driver.on_bytes(data, round(arrival * 1e9))
    got = [(item.stream, item.t, item.sample) for item in queue.drain() if isinstance(item, SampleItem)]
    assert queue.dropped == 0
    vsa = [(t, s) for stream, t, s in got if stream == "linarm.vsa"]
    assert len(vsa) == len(frames)
    stamps = [(send_by_raw[round(s.controllerTime * 1e6) % WRAP_US], t) for t, s in vsa]
    err = errors_after(stamps, 5.0, frames[0].send_s)
    assert np.percentile(err, 99) < 0.0005, f"p99 {1000 * np.percentile(err, 99):.2f} ms from the send times"
    t = np.array([t for t, _s in vsa])
    assert np.all(np.diff(t) > 0), "two LINarm samples share a timestamp"
    motor = [t for stream, t, _s in got if stream == "linarm.motor0"]
    assert motor == [t for t, _s in vsa], "samples of one controller cycle carry one time"
    arrivals = [driver.arrival_of(s) for _t, s in vsa[-3:]] if hasattr(driver, "arrival_of") else []
    assert all(a is None or a >= t_ for a, (t_, _s) in zip(arrivals, vsa[-3:], strict=False))


def test_physio_samples_are_stamped_on_the_board_clock(qtbot) -> None:
    from app.devices.physio import PhysioDriver
    from app.wire.physio_codec import Calibration, PhysioRawFrame, encode_physio_frame

    driver = PhysioDriver(_NoLink(), Calibration())  # type: ignore[arg-type]
    queue = driver.bus.subscribe("test", maxlen=1_000_000)
    period = 0.01
    frames = device_frames(15.0, 200.0, start_raw_s=50.0, period_s=period, wrap_s=65.536, tick_s=0.001)
    send_by_seq = {}
    for arrival, burst in bursty_link(frames, random.Random(8)):
        data = b""
        for f in burst:
            seq = len(send_by_seq) & 0xFFFF
            send_by_seq[seq] = f.send_s
            data += encode_physio_frame(PhysioRawFrame(seq=seq, tick=round(f.device_raw * 1000) & 0xFFFF,
                                                       ppg=2000, skinConductance=100, temperature=100, force=0))
        driver.on_bytes(data, round(arrival * 1e9))
    got = [(item.t, item.sample) for item in queue.drain() if isinstance(item, SampleItem)]
    assert queue.dropped == 0
    assert len(got) == len(frames)
    stamps = [(send_by_seq[s.seq], t) for t, s in got]  # type: ignore[attr-defined]
    err = errors_after(stamps, 5.0, frames[0].send_s)
    # the board's clock counts whole milliseconds: its quantisation adds up to 0.5 ms
    assert np.percentile(err, 99) < 0.001, f"p99 {1000 * np.percentile(err, 99):.2f} ms from the send times"
    assert np.all(np.diff([t for t, _s in got]) > 0)


def test_a_slightly_older_sample_is_stamped_on_the_line_without_a_reset() -> None:
    """Two streams of one device clock may interleave a little out of order: no re-seed, no disorder."""
    clock = DeviceClock(wrap_s=WRAP_US / 1e6)
    stamps = []
    for k in range(2000):
        stamps.append(clock.map(k * PERIOD_S, 1000.0 + k * PERIOD_S + 0.001))
        if k % 10 == 5:
            older = clock.map(k * PERIOD_S - 0.002, 1000.0 + k * PERIOD_S + 0.001)
            assert older < stamps[-1]
    assert clock.resets == 0
    assert np.all(np.diff(stamps) > 0)


def test_a_clock_that_fell_behind_reseeds() -> None:
    """A board that restarted quicker than its counter's wrap can show: its clock now runs 0.4 s behind the line.
    Every later sample then looks 0.4 s late; after 5 s of that the clock starts again and is right once more."""
    clock = DeviceClock()
    for k in range(2000):  # 10 s on time
        clock.map(k * PERIOD_S, 100.0 + k * PERIOD_S + 0.0005)
    t_restart = 100.0 + 2000 * PERIOD_S
    stamps = []
    for k in range(1600):  # the device time goes on from where it was, 0.4 s of host time later
        send = t_restart + 0.4 + k * PERIOD_S
        stamps.append((send, clock.map((2000 + k) * PERIOD_S, send + 0.0005)))
    assert clock.resets == 1
    assert all(abs(m - s) < 0.002 for s, m in stamps[-200:])
