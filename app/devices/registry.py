"""The composition root: which devices exist, and the one place that assembles them.

Each device module offers ``create(ctx: DeviceContext) -> DeviceHandle | None`` (None when its config says
``off``). A device gets everything it needs from its context — its config section, the stream bus (where
its driver publishes and where it reads the other devices' latest samples and events), the supervisor's
registration API (typed stop actions, robot probes, FES limits), the link to its simulator when simulated,
the drivers built before it and the assistance split (the UDP peers' frames) — and never imports the manager.

Simulated serial devices are hosted by :class:`SimulatorHosting`: in a process of their own by default
(app.devices.sim.host), or in the app's process (``simulation.host: thread``).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.core import streams
from app.core.bus import StreamBus
from app.core.config import AppConfig, SafetyConfig
from app.core.links import simulator_link
from app.devices.driver import DeviceDriver
from app.safety.assistance import AssistanceLevels
from app.safety.supervisor import RobotProbes, SafetySupervisor, StopAction

log = logging.getLogger(__name__)

# name → module; the order is the build order (the patient model needs the others' streams).
DEVICE_MODULES: dict[str, str] = {
    streams.LINARM: "app.devices.linarm",
    streams.PHYSIO: "app.devices.physio",
    streams.FES: "app.devices.rehastim",
    streams.PATIENT_MODEL: "app.devices.patient_model",
    streams.VR: "app.devices.vr",
}


@dataclass
class DeviceHandle:
    """One device as the manager holds it: its driver, and its simulator when simulated."""

    name: str
    driver: DeviceDriver
    simulator: Any = None  # SerialSimulator (in-process) or RemoteSimulator (simulator process)
    extras: dict[str, Any] = field(default_factory=dict)  # e.g. helper processes, "safe_stop"

    @property
    def simulated(self) -> bool:
        return self.simulator is not None or bool(self.extras.get("simulated"))


class SimulatorHosting:
    """Gives simulated serial devices their far-side link, in- or out-of-process, and the simulated patient
    they share. Out of process, devices are collected while the root builds them and the simulator
    process starts once, before any driver (the links' paths are known in advance)."""

    def __init__(self, config: AppConfig, runtime_dir: Path) -> None:
        self.mode = os.environ.get("LINARMPP_SIM_HOST") or config.simulation.host
        if self.mode not in ("process", "thread"):
            raise ValueError(f"simulation host must be 'process' or 'thread', got {self.mode!r}")
        self.linarm_kind = config.simulation.linarm
        self.link = os.environ.get("LINARMPP_SIM_LINK") or config.simulation.link
        self.runtime_dir = runtime_dir
        self.process: Any = None  # app.devices.sim.host.SimulatorProcess
        self._spec: dict[str, dict[str, Any]] = {}
        self._patient: Any = None

    @property
    def out_of_process(self) -> bool:
        return self.mode == "process"

    def patient(self) -> Any:
        """The one simulated patient (grip and handle forces) shared by the simulators."""
        if self._patient is None:
            if self.out_of_process:
                from app.devices.sim.host import RemotePatient, SimulatorProcess

                self.process = self.process or SimulatorProcess(self._process_spec())
                self._patient = RemotePatient(self.process)
            else:
                from app.devices.sim.patient import SimulatedPatient

                self._patient = SimulatedPatient(seed=7)
        return self._patient

    def _process_spec(self) -> dict[str, Any]:
        return {"runtime_dir": str(self.runtime_dir), "devices": self._spec, "patient_seed": 7, "linger_s": 1.0,
                "events_file": os.environ.get("LINARMPP_SIM_EVENTS", "")}

    def serial(self, name: str, kind: str, in_process: Callable[[Any], Any], **params: Any) -> Any:
        """The simulator of device ``name`` (its ``url`` is what the driver opens). ``in_process(patient)``
        builds the in-process SerialSimulator; ``kind`` and ``params`` describe it to the simulator process."""
        if not self.out_of_process:
            return in_process(self.patient())
        from app.devices.sim.host import RemoteSimulator, SimulatorProcess, find_firmware_sil, free_tcp_port

        if kind == streams.LINARM and self.linarm_kind == "firmware":
            sil = find_firmware_sil()
            if sil is None:
                raise RuntimeError("simulation.linarm is 'firmware' but the firmware's SIL executable is not "
                                   "built (cmake -S firmware/host -B firmware/build && cmake --build firmware/build)")
            kind, params = "linarm_firmware", {**params, "executable": str(sil)}
        elif kind == streams.LINARM and self.linarm_kind == "mcu":
            from app.devices.sim.host import find_mcu_image

            image = find_mcu_image()
            if image is None:
                raise RuntimeError("simulation.linarm is 'mcu' but the firmware's MPS2 image is not built (cmake "
                                   "--build firmware/build/due --target linarm_mps2.elf, see firmware/README.md)")
            kind, params = "linarm_mcu", {**params, "image": str(image)}
        tcp_port = free_tcp_port() if self.link == "socket" else None
        self._spec[name] = {"kind": kind, **params, **({"tcp_port": tcp_port} if tcp_port else {})}
        self.patient()
        self.process = self.process or SimulatorProcess(self._process_spec())
        return RemoteSimulator(name, self.process, simulator_link(self.runtime_dir, name), tcp_port)

    def start(self) -> None:
        """Start the simulator process (when any device asked for one); raises when it does not come up."""
        if self.process is not None and self._spec and not self.process.alive:
            self.process.spec = self._process_spec()
            self.process.start()

    def stop(self) -> None:
        if self.process is not None:
            self.process.stop()


@dataclass
class DeviceContext:
    """What a device's ``create`` may use: nothing else of the application."""

    name: str
    config: Any  # the device's own config section (e.g. app.core.config.LinarmDevice)
    safety: SafetyConfig
    bus: StreamBus  # the driver publishes here; the other devices' latest samples and events are read here
    supervisor: SafetySupervisor  # the drivers' checked command paths call it
    runtime_dir: Path
    simulators: SimulatorHosting
    peers: Mapping[str, DeviceDriver]  # drivers built before this one, by name
    # α and its split with the gains in force (the manager's AssistanceController), for the UDP peers' frames;
    # None: the config's gains, and α as the patient model last published it
    assistance: AssistanceLevels | None = None

    # ---------------------------------------------------------------- the supervisor's registration API
    def add_stop_action(self, name: str, run: Callable[[str], None], *, robot: bool = False) -> None:
        self.supervisor.add_stop_action(StopAction(name, run, robot=robot))

    def set_robot_probes(self, probes: RobotProbes) -> None:
        self.supervisor.set_robot_probes(probes)

    def silence_timeout(self, rate_hz: float) -> float:
        """How long a stream at ``rate_hz`` may be quiet before it is called silent (one rule for all)."""
        return max(self.safety.silence_periods / rate_hz, self.safety.silence_min_s)

    def sim_patient(self) -> Any:
        return self.simulators.patient()


DeviceFactory = Callable[[DeviceContext], DeviceHandle | None]


def default_factories(config: AppConfig) -> dict[str, DeviceFactory]:
    factories: dict[str, DeviceFactory] = {}
    for name, module_name in DEVICE_MODULES.items():
        if getattr(config.devices, name).mode == "off":
            continue
        if importlib.util.find_spec(module_name) is None:
            log.warning("device %s is not available in this build (%s missing)", name, module_name)
            continue
        module = importlib.import_module(module_name)
        factories[name] = module.create
    return factories


def build_devices(factories: Mapping[str, DeviceFactory], config: AppConfig, *, bus: StreamBus,
                  supervisor: SafetySupervisor, runtime_dir: Path, simulators: SimulatorHosting,
                  assistance: AssistanceLevels | None = None,
                  on_error: Callable[[str, Exception], None] | None = None) -> dict[str, DeviceHandle]:
    """Every device of ``factories``, in order, each from its typed context; a device that fails to build
    is reported through ``on_error`` and left out."""
    handles: dict[str, DeviceHandle] = {}
    for name, factory in factories.items():
        section = getattr(config.devices, name, None)
        ctx = DeviceContext(name, section, config.safety, bus, supervisor, runtime_dir, simulators,
                            {n: h.driver for n, h in handles.items()}, assistance)
        try:
            handle = factory(ctx)
        except Exception as exc:
            log.exception("device %s could not be created", name)
            if on_error is not None:
                on_error(name, exc)
            continue
        if handle is not None:
            handles[name] = handle
    return handles
