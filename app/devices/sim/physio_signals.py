"""Simulated physiological signals and the simulated acquisition board that frames them.

* heart: rate ~60..100 bpm = mean + respiratory sinus arrhythmia (0.25 Hz) + a slow
  Ornstein-Uhlenbeck wander; the pulse (PPG) waveform is a systolic peak plus a smaller diastolic
  wave per beat, on a respiratory baseline, with ADC noise;
* skin conductance: a slowly wandering tonic level (~5 µS) plus phasic responses (bi-exponential,
  1.5..2.5 s latency) triggered by ``phasic_event(t)`` (e.g. on stimulation onset) and occasional
  spontaneous ones;
* skin temperature: slow wander around 33 °C, kept within 32..34 °C;
* grip force: from the shared ``SimulatedPatient``.

Values are turned into raw 12-bit counts with the codec's calibration (its inverse), so the
default decoder maps them back to bpm/µS/°C/N.  ``PhysioSimSource.frames_until(t)`` produces the
encoded frames due up to ``t`` (100 Hz by default, e.g. 1 kHz for stress tests).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from app.devices.sim.patient import SimulatedPatient
from app.wire.physio_codec import (
    ADC_MAX,
    FLAG_PPG_FAULT,
    PHYSIO_RATE_HZ,
    Calibration,
    PhysioRawFrame,
    encode_physio_frame,
)

RESP_HZ = 0.25  # breathing, modulates heart rate and the PPG baseline


def _ou_step(x: float, mean: float, tau: float, sigma: float, dt: float, rng: np.random.Generator) -> float:
    """Exact Ornstein-Uhlenbeck step: mean-reverting (tau s) wander with stationary std ``sigma``."""
    a = math.exp(-dt / tau)
    return mean + (x - mean) * a + sigma * math.sqrt(1.0 - a * a) * float(rng.standard_normal())


class HeartModel:
    """Heart rate (bpm) and the PPG waveform (counts)."""

    PPG_CENTRE = 2048.0
    PPG_AMPLITUDE = 700.0
    PPG_RESP_COUNTS = 60.0
    PPG_NOISE_COUNTS = 4.0

    def __init__(self, rng: np.random.Generator, mean_bpm: float = 72.0, rsa_bpm: float = 3.0,
                 wander_bpm: float = 4.0) -> None:
        self._rng = rng
        self.mean_bpm = mean_bpm
        self.rsa_bpm = rsa_bpm
        self.wander_bpm = wander_bpm
        self._wander = 0.0
        self._phase = float(rng.uniform(0.0, 1.0))  # beats, fractional part = position in the beat
        self.heartRate = mean_bpm

    @staticmethod
    def pulse_shape(phi: float) -> float:
        """One beat, phi in [0, 1): systolic peak at 0.15, diastolic wave at 0.45 (unit peak)."""
        systolic = math.exp(-0.5 * ((phi - 0.15) / 0.06) ** 2)
        return systolic + 0.35 * math.exp(-0.5 * ((phi - 0.45) / 0.10) ** 2)

    def step(self, t: float, dt: float) -> float:
        """Advance to ``t``; returns the PPG sample in counts."""
        self._wander = _ou_step(self._wander, 0.0, 30.0, self.wander_bpm, dt, self._rng)
        rate = self.mean_bpm + self.rsa_bpm * math.sin(2 * math.pi * RESP_HZ * t) + self._wander
        self.heartRate = min(100.0, max(60.0, rate))
        self._phase += self.heartRate / 60.0 * dt
        phi = self._phase % 1.0
        return (self.PPG_CENTRE + self.PPG_AMPLITUDE * (self.pulse_shape(phi) - 0.25)
                + self.PPG_RESP_COUNTS * math.sin(2 * math.pi * RESP_HZ * t)
                + self.PPG_NOISE_COUNTS * float(self._rng.standard_normal()))


@dataclass
class _Scr:
    onset: float      # response start (event time + latency)
    amplitude: float  # µS at the peak


class SkinConductanceModel:
    """Tonic level + phasic responses (µS)."""

    RISE_TAU = 0.75
    DECAY_TAU = 2.5
    SPONTANEOUS_PER_MIN = 2.0

    def __init__(self, rng: np.random.Generator, event_rng: np.random.Generator, tonic: float = 5.0) -> None:
        self._rng = rng
        self._event_rng = event_rng  # separate, so an event does not change the other noise
        self.tonic_mean = tonic
        self._tonic = tonic
        self._responses: list[_Scr] = []
        # peak of exp(-x/decay) - exp(-x/rise), to normalise responses to their amplitude
        rise, decay = self.RISE_TAU, self.DECAY_TAU
        tp = math.log(decay / rise) * decay * rise / (decay - rise)
        self._norm = 1.0 / (math.exp(-tp / decay) - math.exp(-tp / rise))

    def phasic_event(self, t: float, amplitude: float | None = None) -> None:
        """A stimulus at ``t``: a response follows after 1.5..2.5 s."""
        amp = float(self._event_rng.uniform(0.4, 1.0)) if amplitude is None else amplitude
        self._responses.append(_Scr(t + float(self._event_rng.uniform(1.5, 2.5)), amp))

    def step(self, t: float, dt: float) -> float:
        self._tonic = _ou_step(self._tonic, self.tonic_mean, 60.0, 0.5, dt, self._rng)
        if self._rng.random() < self.SPONTANEOUS_PER_MIN / 60.0 * dt:
            self._responses.append(_Scr(t, float(self._rng.uniform(0.05, 0.2))))
        self._responses = [r for r in self._responses if t - r.onset < 10 * self.DECAY_TAU]
        phasic = 0.0
        for r in self._responses:
            x = t - r.onset
            if x > 0.0:
                shape = math.exp(-x / self.DECAY_TAU) - math.exp(-x / self.RISE_TAU)
                phasic += r.amplitude * self._norm * shape
        return max(0.05, self._tonic + phasic)


class SkinTemperatureModel:
    """Slow wander around 33 °C within 32..34 °C, plus sensor noise (°C)."""

    def __init__(self, rng: np.random.Generator, mean: float = 33.0) -> None:
        self._rng = rng
        self.mean = mean
        self._value = mean

    def step(self, t: float, dt: float) -> float:
        self._value = min(34.0, max(32.0, _ou_step(self._value, self.mean, 120.0, 0.4, dt, self._rng)))
        return self._value + 0.02 * float(self._rng.standard_normal())


class PhysioSimSource:
    """The simulated acquisition board: samples the models at ``rate_hz`` and encodes frames."""

    def __init__(self, patient: SimulatedPatient, seed: int = 0, rate_hz: float = PHYSIO_RATE_HZ,
                 calibration: Calibration | None = None, start_time: float = 0.0) -> None:
        if rate_hz <= 0.0:
            raise ValueError("rate_hz must be > 0")
        self._lock = threading.Lock()
        self._patient = patient
        streams = np.random.SeedSequence(seed).spawn(4)
        heart, skin, events, temperature = (np.random.default_rng(s) for s in streams)
        self._cal = calibration or Calibration()
        self.rate_hz = rate_hz
        self._start = start_time
        self._k = 0  # next sample index
        self.heart = HeartModel(heart)
        self.skin = SkinConductanceModel(skin, events)
        self.temperature = SkinTemperatureModel(temperature)
        self._flags = 0
        self.last: dict[str, float] = {}  # true values of the last sample (tests, GUI)

    def phasic_event(self, t: float, amplitude: float | None = None) -> None:
        """Trigger a skin-conductance response (e.g. on FES onset); thread-safe."""
        with self._lock:
            self.skin.phasic_event(t, amplitude)

    def set_fault_flags(self, flags: int) -> None:
        """Simulate sensor faults; with FLAG_PPG_FAULT the pulse channel reads 0."""
        with self._lock:
            self._flags = flags & 0x1F

    @property
    def frames_sent(self) -> int:
        return self._k

    def next_frame_time(self) -> float:
        """When the next sample is taken (the clock of ``frames_until``): its frame goes out then."""
        with self._lock:
            return self._start + self._k / self.rate_hz

    def frames_until(self, t: float) -> bytes:
        """Encoded frames for every sample instant not yet produced and not later than ``t``."""
        out: list[bytes] = []
        dt = 1.0 / self.rate_hz
        with self._lock:
            while self._start + self._k * dt <= t + 1e-12:
                ts = self._start + self._k * dt
                ppg = self.heart.step(ts, dt)
                sc = self.skin.step(ts, dt)
                temp = self.temperature.step(ts, dt)
                force = self._patient.grip_force(ts)
                if self._flags & FLAG_PPG_FAULT:
                    ppg = 0.0
                self.last = {"time": ts, "heartRate": self.heart.heartRate, "skinConductance": sc,
                             "temperature": temp, "force": force, "ppg": ppg}
                out.append(encode_physio_frame(PhysioRawFrame(
                    seq=self._k & 0xFFFF, tick=round(ts * 1000.0) & 0xFFFF,
                    ppg=int(min(ADC_MAX, max(0, round(ppg)))),
                    skinConductance=self._cal.skinConductance.to_counts(sc),
                    temperature=self._cal.temperature.to_counts(temp),
                    force=self._cal.force.to_counts(force), flags=self._flags)))
                self._k += 1
        return b"".join(out)
