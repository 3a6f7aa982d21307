"""The seed's script API (D2.2 Appendix): names, arguments, return values, enums, latest-sample reads,
errors as plain sentences, the safety supervisor on every command, callbacks queued off the driver thread."""

from __future__ import annotations

import inspect
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from app.core.bus import StreamBus, UpdateNotifier
from app.core.config import RESOURCES, SafetyConfig
from app.devices.linarm import LinarmCommandError, LinarmDriver, LinarmTimeout
from app.devices.transport import SerialTransport
from app.safety.supervisor import SafetySupervisor
from app.scripting import api
from app.scripting.api import (
    CommandError,
    CommandRefused,
    DeviceUnavailable,
    ScriptContext,
    ScriptStopped,
    build_api,
)
from app.wire import linarm_protocol as proto
from tests.fakes import BusSamples, fake_bus

# The Appendix's LinarmUser services (5.3.2.1) and members.
APPENDIX_LINARM = [
    "setDemo", "resetError", "setCtrlState", "setCtrlMode", "setCentreVelocity", "setDeltaVelocity",
    "getPidTunings", "moveCentreTo", "moveDeltaTo", "moveDeltato", "setStiffness", "goToHome", "setTrajectoryType",
    "setAssistanceTargetPos", "getAssistanceTargetPos", "enableVirtualVsa", "setVirtualVsaSpringDisplacement",
    "getIsInitialized", "disableEndstrokes", "setTriggerMode", "setTriggerParameter", "setAdmittanceParameter",
    "getAdmittanceParameter", "setAssistanceParameter", "getAssistanceParameter", "getConfigData",
    "setLinarmDataCallbackFun", "setLinarmMotor0DataCallbackFun", "setLinarmMotor1DataCallbackFun",
    "setLinarmVsaDataCallbackFun", "linarmDataCallbackList", "linarmMotor0DataCallbackList",
    "linarmMotor1DataCallbackList", "linarmVsaDataCallbackList", "classString",
    "CONTROL_STATES", "CONTROL_MODES", "HOME_STATES", "ERROR_STATES", "TRIGGER_MODES",
]




class Driver:
    def __init__(self, bus: StreamBus) -> None:
        self.notifier = bus.notifier
        self.connected = True
        self.command_timeout_s = 0.2
        self.samples: dict[str, Any] = BusSamples(bus)
        self.calls: list[tuple[str, tuple[Any, ...], str]] = []
        self.replies: dict[str, dict[str, Any]] = {}
        self.raise_on: dict[str, BaseException] = {}
        self.threads: set[str] = set()

    def latest(self, stream: str) -> Any:
        return self.samples.get(stream)

    def command(self, name: str, *args: Any, source: str = "", timeout_s: float | None = None) -> dict[str, Any]:
        self.threads.add(threading.current_thread().name)
        self.calls.append((name, args, source))
        if name in self.raise_on:
            raise self.raise_on[name]
        return dict(self.replies.get(name, {}))


class FesDriver:
    def __init__(self) -> None:
        self.profile: Any = None
        self.stimulating = False
        self.calls: list[tuple[str, tuple[Any, ...]]] = []

    def load_profile(self, profile: Any, source: str = "") -> None:
        self.calls.append(("load_profile", (profile,)))
        self.profile = profile

    def start_stimulation(self, source: str = "") -> None:
        self.calls.append(("start", (source,)))
        self.stimulating = True

    def stop_stimulation(self, reason: str = "", source: str = "") -> None:
        self.calls.append(("stop", (reason, source)))
        self.stimulating = False

    def set_current_scale(self, factor: float, source: str = "") -> float:
        self.calls.append(("current_scale", (factor, source)))
        return min(factor, 1.5)

    def set_pulse_width_scale(self, factor: float, source: str = "") -> float:
        self.calls.append(("pw_scale", (factor, source)))
        return factor


class Manager:
    def __init__(self) -> None:
        from app.core.config import AppConfig

        self.config = AppConfig()
        self.notifier = UpdateNotifier()
        self.bus = fake_bus(self.notifier)
        self.drivers: dict[str, Any] = {"linarm": Driver(self.bus), "physio": Driver(self.bus)}

    def driver(self, name: str) -> Any:
        return self.drivers.get(name)


@pytest.fixture
def manager() -> Manager:
    return Manager()


@pytest.fixture
def ctx(manager: Manager) -> ScriptContext:
    context = ScriptContext(manager)
    yield context
    context.close()


@pytest.fixture
def objects(ctx: ScriptContext) -> dict[str, Any]:
    return build_api(ctx)


# ---------------------------------------------------------------------------------------------- names
def test_every_appendix_name_is_there(objects: dict[str, Any]) -> None:
    linarm = objects["linarm"]
    missing = [n for n in APPENDIX_LINARM if not hasattr(type(linarm), n) and n not in vars(linarm)]
    assert missing == []
    for name in ("linarm", "physiologicalSensors", "fes", "patientModel", "VRUnity", "linarmppManager"):
        assert name in objects
    assert hasattr(objects["physiologicalSensors"], "setPhysiologicalSensorsDataCallbackFun")
    assert hasattr(objects["physiologicalSensors"], "physiologicalDataCallbackList")
    assert hasattr(objects["patientModel"], "setPatientModelDataCallbackFun")
    assert hasattr(objects["VRUnity"], "setVRUnityDataCallbackFun")
    for name in ("loadFile", "writeFile", "saveFile", "start", "stop", "setCurrentScaleFactor", "setPWScaleFactor"):
        assert callable(getattr(objects["fes"], name))
    mgr = objects["linarmppManager"]
    assert mgr.linarm is linarm and mgr.physiologicalSensors is objects["physiologicalSensors"]
    assert callable(mgr.setProgram) and callable(mgr.startProgram)


def test_every_script_command_of_the_protocol_is_a_method_with_named_arguments() -> None:
    for spec in api.SCRIPT_COMMANDS:
        method = getattr(api.LinarmUser, spec.name)
        params = list(inspect.signature(method).parameters)[1:]
        assert params == [a.name for a in spec.args], spec.name
        assert spec.name in method.__doc__
    assert not hasattr(api.LinarmUser, "heartbeat")  # the driver's, not the script's


def test_enums_carry_the_seed_values(objects: dict[str, Any]) -> None:
    linarm = objects["linarm"]
    assert linarm.CONTROL_STATES.IDLE_CTRL_STATE == 0 and linarm.CONTROL_STATES.ON_CTRL_STATE == 2
    assert linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS == 1 and linarm.CONTROL_MODES.POS_REF_BY_ASSISTANCE == 4
    assert linarm.HOME_STATES.HOME_DONE == proto.HomeState.HOME_DONE
    assert linarm.ERROR_STATES.NO_ERROR == 0
    assert linarm.TRIGGER_MODES.NO_TRIGGER == 0


# ---------------------------------------------------------------------------------------------- commands
def test_commands_coerce_like_the_seed_scripts_write_them(manager: Manager, objects: dict[str, Any]) -> None:
    linarm = objects["linarm"]
    assert linarm.moveCentreTo(0.4, 0.15, 0.15, 0, False) is None
    linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
    name, args, source = manager.drivers["linarm"].calls[0]
    assert name == "moveCentreTo" and args == (0.4, 0.15, 0.15, 0.0, False) and source == "script"
    assert [type(a) for a in args] == [float, float, float, float, bool]
    assert manager.drivers["linarm"].calls[1][1] == (2,) and type(manager.drivers["linarm"].calls[1][1][0]) is int
    assert manager.drivers["linarm"].threads == {"script-cmd_0"}  # not the caller's thread


def test_return_values(manager: Manager, objects: dict[str, Any]) -> None:
    driver = manager.drivers["linarm"]
    driver.replies = {"getIsInitialized": {"initialized": True},
                      "getPidTunings": {"index": 1, "kp": 100.0, "ki": 2.0, "kd": 3.0},
                      "getAdmittanceParameter": {"Ka": 0.005}}
    linarm = objects["linarm"]
    assert linarm.getIsInitialized() is True
    assert linarm.getPidTunings(1) == (100.0, 2.0, 3.0)
    assert linarm.getAdmittanceParameter() == 0.005


def test_bad_arguments_are_explained(objects: dict[str, Any]) -> None:
    linarm = objects["linarm"]
    with pytest.raises(TypeError, match=r"moveCentreTo takes 5 argument\(s\) \(targetPos, maxVel"):
        linarm.moveCentreTo(0.4)
    with pytest.raises(TypeError, match="trigger must be True or False"):
        linarm.moveCentreTo(0.4, 0.1, 0.1, 0, "no")
    with pytest.raises(TypeError, match="controlState must be a whole number"):
        linarm.setCtrlState(1.5)


def test_controller_errors_and_timeouts_become_sentences(manager: Manager, objects: dict[str, Any]) -> None:
    driver = manager.drivers["linarm"]
    driver.raise_on["setCtrlState"] = LinarmCommandError("setCtrlState", proto.ReplyError.NOT_HOMED, "home first")
    driver.raise_on["goToHome"] = LinarmTimeout("LINarm did not acknowledge goToHome within 0.20 s")
    linarm = objects["linarm"]
    with pytest.raises(CommandError, match=r"linarm.setCtrlState\(2\) failed: .*NOT_HOMED"):
        linarm.setCtrlState(2)
    t0 = time.monotonic()
    with pytest.raises(CommandError, match="did not acknowledge goToHome"):
        linarm.goToHome()
    assert time.monotonic() - t0 < 0.5


def test_the_safety_supervisor_checks_every_script_command() -> None:
    """The real driver path (not started): limits are checked before anything is sent."""
    supervisor = SafetySupervisor(SafetyConfig())
    driver = LinarmDriver(SerialTransport("socket://127.0.0.1:9"), supervisor)

    class M(Manager):
        def driver(self, name: str) -> Any:
            return driver if name == "linarm" else None

    context = ScriptContext(M())
    linarm = build_api(context)["linarm"]
    try:
        with pytest.raises(CommandRefused, match=r"moveCentreTo\(0.49.*: .*outside the allowed range"):
            linarm.moveCentreTo(0.49, 0.1, 0.1, 0, False)
        with pytest.raises(CommandRefused, match="velocity limit"):
            linarm.moveCentreTo(0.3, 0.9, 0.1, 0, False)
        with pytest.raises(DeviceUnavailable, match="not connected"):  # within limits: refused only by the link
            linarm.moveCentreTo(0.3, 0.1, 0.1, 0, False)
    finally:
        context.close()
        driver.commands.close("the test ended")


def test_calls_from_many_threads_all_complete(manager: Manager, objects: dict[str, Any]) -> None:
    linarm = objects["linarm"]
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda i: linarm.setAssistanceTargetPos(0.1 + i * 0.001), range(40)))
    assert len(manager.drivers["linarm"].calls) == 40


# ---------------------------------------------------------------------------------------------- samples
def test_attribute_reads_return_the_latest_sample(manager: Manager, objects: dict[str, Any]) -> None:
    from app.devices.linarm import VsaSample

    manager.drivers["linarm"].samples["linarm.vsa"] = VsaSample(0.25, 0.02, 900.0, 0.25, 0.0, 0.0, 1.0)
    assert objects["linarm"].linarmVsaState.equilibriumPos == 0.25
    manager.drivers["linarm"].samples["linarm.vsa"] = VsaSample(0.26, 0.02, 900.0, 0.26, 0.0, 0.0, 1.1)
    assert objects["linarm"].linarmVsaState.equilibriumPos == 0.26


def test_a_missing_sample_or_device_raises_a_clear_error(monkeypatch: pytest.MonkeyPatch,
                                                         objects: dict[str, Any]) -> None:
    monkeypatch.setattr(api, "FIRST_SAMPLE_TIMEOUT_S", 0.05)
    with pytest.raises(DeviceUnavailable, match="the physiological sensors: no data received yet"):
        _ = objects["physiologicalSensors"].physiologicalSensorsData
    with pytest.raises(DeviceUnavailable, match="the VR renderer is not available"):
        _ = objects["VRUnity"].VRUnityData
    with pytest.raises(DeviceUnavailable, match="the FES stimulator is not available"):
        objects["fes"].start()


def test_a_read_waits_for_the_first_sample(manager: Manager, objects: dict[str, Any]) -> None:
    from app.wire.physio_codec import PhysioSample

    sample = PhysioSample(1, 0.0, 0.0, 21.5, 33.0, 70.0, 5.0, 0, 0, 0)

    def later() -> None:
        time.sleep(0.05)
        manager.drivers["physio"].samples["physio.main"] = sample  # published: the bus wakes the waiter

    threading.Thread(target=later).start()
    assert objects["physiologicalSensors"].physiologicalSensorsData.force == 21.5


def test_a_stopped_context_stops_reads_and_commands(ctx: ScriptContext, objects: dict[str, Any]) -> None:
    ctx.stop_event.set()
    with pytest.raises(ScriptStopped):
        _ = objects["linarm"].linarmState
    with pytest.raises(ScriptStopped):
        objects["linarm"].resetError()


def test_callback_setters_queue_samples_never_run_them(manager: Manager, ctx: ScriptContext,
                                                       objects: dict[str, Any]) -> None:
    posted: list[tuple[str, list[Any], Any]] = []
    ctx.post_callback = lambda stream, funs, sample: posted.append((stream, funs, sample))
    ran: list[Any] = []
    physio = objects["physiologicalSensors"]
    physio.setPhysiologicalSensorsDataCallbackFun(ran.append)
    physio.setPhysiologicalSensorsDataCallbackFun(ran.append)
    assert len(physio.physiologicalDataCallbackList) == 2  # a function is added to the list
    assert len(manager.bus.subscriptions()) == 1  # one bus subscription for the callback streams
    manager.drivers["physio"].samples["physio.main"] = "sample"
    deadline = time.monotonic() + 2.0
    while not posted and time.monotonic() < deadline:
        time.sleep(0.005)
    assert ran == [] and posted[0][0] == "physio.main" and posted[0][2] == "sample"
    physio.setPhysiologicalSensorsDataCallbackFun([print])
    assert physio.physiologicalDataCallbackList == [print]  # a list replaces it
    physio.setPhysiologicalSensorsDataCallbackFun(None)
    assert physio.physiologicalDataCallbackList == []
    with pytest.raises(TypeError, match="expects a function"):
        physio.setPhysiologicalSensorsDataCallbackFun(3)
    ctx.close()
    assert manager.bus.subscriptions() == []


# ---------------------------------------------------------------------------------------------- FES
def test_fes_calls_reach_the_driver(manager: Manager, ctx: ScriptContext, objects: dict[str, Any],
                                    tmp_path: Path) -> None:
    fes_driver = FesDriver()
    manager.drivers["fes"] = fes_driver
    fes = objects["fes"]
    profile = fes.loadFile("frontal_reaching.yaml")  # found among the example profiles
    assert fes_driver.profile is profile and profile.axis == "phase"
    fes.start()
    assert fes.stimulating
    assert fes.setCurrentScaleFactor(1.8) == 1.5  # the applied (capped) factor comes back
    assert fes.setPWScaleFactor(0.5) == 0.5
    fes.stop()
    assert not fes.stimulating
    assert [c[0] for c in fes_driver.calls] == ["load_profile", "start", "current_scale", "pw_scale", "stop"]
    assert fes_driver.calls[1][1] == ("script",)
    fes.writeFile(profile, str(tmp_path / "copy.yaml"))
    from app.core.fes_profile import load_profile

    assert load_profile(tmp_path / "copy.yaml").channels.keys() == profile.channels.keys()
    assert (RESOURCES / "fes_profiles" / "frontal_reaching.yaml").is_file()
