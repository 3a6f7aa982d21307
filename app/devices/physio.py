"""Physiological sensors: the driver (20-byte frames → PhysioSample) and its simulated board.

The frame layout, CRC, sequence counter and beat detector live in app.wire.physio_codec; this
module only connects them to a transport and to the manager.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from app.core import streams
from app.core.bus import Channel, StreamBus, StreamSpec
from app.core.config import PhysioCalibration, PhysioDevice
from app.core.links import simulator_link
from app.devices.clock import DeviceClock
from app.devices.driver import DeviceDriver
from app.devices.sim.base import SerialSimulator
from app.devices.transport import SerialSettings, SerialTransport, Transport
from app.wire.physio_codec import Calibration, ChannelCalibration, PhysioStreamDecoder

if TYPE_CHECKING:
    from app.devices.registry import DeviceContext, DeviceHandle

PHYSIO_STREAM = StreamSpec(streams.PHYSIO_MAIN, (
    Channel("heartRate", "bpm", "Heart rate"),
    Channel("skinConductance", "µS", "Skin conductance"),
    Channel("temperature", "°C", "Skin temperature"),
    Channel("force", "N", "Grip force"),
), 100.0)


def calibration_from_config(cal: PhysioCalibration) -> Calibration:
    return Calibration(
        skinConductance=ChannelCalibration(cal.skin_conductance_gain, cal.skin_conductance_offset),
        temperature=ChannelCalibration(cal.temperature_gain, cal.temperature_offset),
        force=ChannelCalibration(cal.force_gain, cal.force_offset),
    )


class PhysioDriver(DeviceDriver):
    streams = (PHYSIO_STREAM,)

    def __init__(self, transport: Transport, calibration: Calibration, *,
                 bus: StreamBus | None = None, silence_timeout_s: float | None = None) -> None:
        super().__init__(streams.PHYSIO, transport, bus=bus, silence_timeout_s=silence_timeout_s)
        self.calibration = calibration
        self.decoder = PhysioStreamDecoder(calibration)
        # The board's millisecond tick (unwrapped by the decoder into boardTime) mapped to the host's clock:
        # samples are stamped when the board took them, not when the read carrying them returned (#27).
        self.clock = DeviceClock()

    def on_connect(self) -> None:
        self.decoder.reset()  # a new connection starts a new sequence; old gaps are not losses
        self.clock.reset()

    def on_bytes(self, data: bytes, t_ns: int) -> None:
        t = t_ns / 1e9
        stamp, replace, publish = self.clock.map, dataclasses.replace, self.publish
        for sample in self.decoder.feed(data, t):
            taken = stamp(sample.boardTime, t)
            publish(streams.PHYSIO_MAIN, taken, replace(sample, timestamp=taken), t)

    @property
    def frames_lost(self) -> int:
        return self.decoder.framesLost

    @property
    def bad_frames(self) -> int:
        return self.decoder.badFrames


def create(ctx: DeviceContext) -> DeviceHandle | None:
    from app.devices.registry import DeviceHandle
    from app.devices.sim.adapters import PHYSIO_POLL_S, PhysioSimCore

    cfg: PhysioDevice = ctx.config
    if cfg.mode == "off":
        return None
    calibration = calibration_from_config(cfg.calibration)
    simulator = None
    url = cfg.port
    if cfg.mode == "simulated":
        link, rate = simulator_link(ctx.runtime_dir, streams.PHYSIO), cfg.rate_hz
        simulator = ctx.simulators.serial(
            streams.PHYSIO, streams.PHYSIO,
            lambda patient: SerialSimulator(streams.PHYSIO, lambda: PhysioSimCore(patient, rate, calibration), link,
                                            tick_s=PHYSIO_POLL_S),
            rate_hz=rate, calibration={k: [c.gain, c.offset] for k, c in (
                ("skinConductance", calibration.skinConductance), ("temperature", calibration.temperature),
                ("force", calibration.force))})
        url = simulator.url
    driver = PhysioDriver(SerialTransport(url, SerialSettings(baudrate=cfg.baudrate)), calibration,
                          bus=ctx.bus,
                          silence_timeout_s=ctx.silence_timeout(cfg.rate_hz))
    return DeviceHandle(streams.PHYSIO, driver, simulator)
