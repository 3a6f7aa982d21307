"""Issue #17 point 2: one fault policy (app/safety/fault_policy.py) for the window and the headless runner.

The fault matrix (docs/fault-policy.md): for every device × fault, in the window (MainWindow + its script
console's runner) and headless (run_headless), the same outcome — the running script ends "stopped"
with the real cause, FES is stopped and the robot put in its safe state, at once (< 1 s), and headless
exits 3.  The devices are small counter simulators on real ptys named like the real ones; the faults
are the events their drivers report (connection lost, silence, the robot's error latch) and a recorder
whose files fail with ENOSPC."""

from __future__ import annotations

import errno
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pytest

from app.core.config import AppConfig
from app.devices.registry import DeviceContext
from app.manager import DeviceHandle, LinarmppManager
from tests.fakes import CounterDriver, make_counter_device
from tests.waits import KERNEL_START_MS

DEVICES = ("linarm", "fes", "physio", "patient_model", "vr")

# (device, fault, driver event, detail, words the script's stop message must contain)
MATRIX = [
    ("linarm", "error latch", "controller_error", "robot STOP: WATCHDOG (no host bytes for 0.25 s)", "WATCHDOG"),
    ("linarm", "connection lost", "disconnected", "cable pulled", "linarm connection lost"),
    ("linarm", "silence", "silent", "no sample for 0.25 s", "linarm stopped sending data"),
    ("fes", "connection lost", "disconnected", "cable pulled", "fes connection lost"),
    ("fes", "silence", "silent", "no sample for 0.25 s", "fes stopped sending data"),
    ("physio", "connection lost", "disconnected", "cable pulled", "physio connection lost"),
    ("patient_model", "link lost (α)", "disconnected", "no valid datagram for 0.5 s",
     "patient_model connection lost"),
    ("vr", "link lost", "disconnected", "no valid datagram for 2.5 s", "vr connection lost"),
    ("recording", "write error (ENOSPC)", "", "", "Recording failed"),
]
SCRIPT = "import time\nwhile True:\n    time.sleep(0.02)\n"


@dataclass
class Safe:
    """What the registered stop actions saw (the real FES and robot register the same names)."""

    calls: dict[str, list[tuple[float, str]]] = field(default_factory=lambda: {"FES stop": [], "robot IDLE": []})

    def action(self, name: str):
        def act(reason: str) -> None:
            self.calls[name].append((time.monotonic(), reason))
        return act


def fake_factories(tmp_path: Path, safe: Safe) -> dict[str, Any]:
    def factory_for(name: str):
        def factory(ctx: DeviceContext) -> DeviceHandle:
            sim = make_counter_device(tmp_path, name)
            driver = CounterDriver(sim.url, bus=ctx.bus)  # no natural silence: faults are injected
            driver.name = name
            if name == "fes":
                ctx.supervisor.register_estop_action("FES stop", safe.action("FES stop"))
            if name == "linarm":
                ctx.supervisor.register_estop_action("robot IDLE", safe.action("robot IDLE"))
            return DeviceHandle(name, driver, sim)
        return factory
    return {name: factory_for(name) for name in DEVICES}


class FailingFile:
    """A session file on a full disk."""

    def __init__(self, fh: Any) -> None:
        self._fh = fh
        self.name = getattr(fh, "name", "?")

    def write(self, _text: str) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    def flush(self) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    def fileno(self) -> int:
        return self._fh.fileno()

    def close(self) -> None:
        try:
            self._fh.close()
        except OSError:
            pass


def fill_the_disk(recorder: Any) -> None:
    for out in recorder._outs.values():
        out.fh = FailingFile(out.fh)
    recorder._events_fh = FailingFile(recorder._events_fh)


def inject(manager: LinarmppManager, device: str, event: str, detail: str) -> float:
    t0 = time.monotonic()
    if device == "recording":
        fill_the_disk(manager.recorder or manager._headless_recorder)
        return t0
    driver = manager.driver(device)
    if device in ("patient_model", "vr"):
        manager.driver("fes").stimulating = True  # α / the VR task drive something: the loss is a STOP
    if event == "silent":
        driver._silent = True  # still silent when the policy looks again (silence_stop_s later)
    driver._fire_event(event, detail)
    return t0


def check_outcome(safe: Safe, t0: float, result: Any, words: str) -> dict[str, Any]:
    assert result is not None and result.status == "stopped", result
    assert words in result.message, result.message
    fes = [t for t, _ in safe.calls["FES stop"] if t >= t0]
    robot = [t for t, _ in safe.calls["robot IDLE"] if t >= t0]
    assert fes and robot, safe.calls
    outcome = {"status": result.status, "fes_stop_s": fes[0] - t0, "robot_safe_s": robot[0] - t0}
    print(f"\nOUTCOME {words!r}: {result.status} / {result.message!r} / FES {outcome['fes_stop_s'] * 1e3:.1f} ms"
          f" / robot {outcome['robot_safe_s'] * 1e3:.1f} ms")
    return outcome


@pytest.fixture
def fast_config() -> AppConfig:
    cfg = AppConfig()
    return replace(cfg, ui=replace(cfg.ui, ask_session_on_start=False),
                   safety=replace(cfg.safety, silence_stop_s=0.2))


@pytest.mark.parametrize(("device", "fault", "event", "detail", "words"), MATRIX,
                         ids=[f"{d}-{f}" for d, f, *_ in MATRIX])
def test_window_fault(tmp_path, qtbot, monkeypatch, fast_config, device, fault, event, detail, words) -> None:
    from app.ui.main_window import MainWindow

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    safe = Safe()
    manager = LinarmppManager(fast_config, factories=fake_factories(tmp_path, safe))
    manager.start()
    window = None
    try:
        qtbot.waitUntil(manager.all_connected, timeout=10000)
        window = MainWindow(manager)
        qtbot.addWidget(window)
        from app.ui.script_console import ScriptConsole

        consoles = window.findChildren(ScriptConsole)
        assert consoles, "the window has a script console"
        runner = consoles[0].runner
        runner.home_first = False
        if device == "recording":
            manager.start_session("FAULT01", "tester", root=tmp_path / "sessions")
        runner.start(SCRIPT, "<fault matrix>")
        qtbot.waitUntil(lambda: runner.body_started_at is not None, timeout=KERNEL_START_MS)  # tests/waits.py
        t0 = inject(manager, device, event, detail)
        # The run's end: a hang bound (its timing is asserted below, from the wire's and the record's stamps)
        qtbot.waitUntil(lambda: runner.wait(0), timeout=KERNEL_START_MS)
        outcome = check_outcome(safe, t0, runner.result, words)
        assert outcome["fes_stop_s"] < 1.0 and outcome["robot_safe_s"] < 1.0
        assert manager.fault_policy.faults and words.split(":")[0].split(" ")[0] in manager.fault_policy.last_cause
    finally:
        if window is not None:
            # After a failure the script may still run: the window's quit question ("Stop it and quit?") is a
            # modal box nobody answers here — it held a loaded suite's worker until the timeout killed it.
            from PySide6.QtWidgets import QMessageBox

            monkeypatch.setattr(QMessageBox, "question", lambda *_a, **_k: QMessageBox.StandardButton.Yes)
            window.close()
        manager.shutdown()


@pytest.mark.parametrize(("device", "fault", "event", "detail", "words"), MATRIX,
                         ids=[f"{d}-{f}" for d, f, *_ in MATRIX])
def test_headless_fault(tmp_path, qtbot, monkeypatch, fast_config, device, fault, event, detail, words) -> None:
    from app.devices import registry
    from app.scripting import headless

    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    safe = Safe()
    monkeypatch.setattr(registry, "default_factories", lambda config: fake_factories(tmp_path, safe))
    script = tmp_path / "loop.py"
    script.write_text(SCRIPT, encoding="utf-8")
    seen: dict[str, Any] = {}
    out: list[str] = []

    from app.session.recording import SessionRecorder
    started = SessionRecorder.start

    def remember(self, manager, *a, **kw):  # the headless runner's recorder, for the disk-full fault
        manager._headless_recorder = self
        return started(self, manager, *a, **kw)

    monkeypatch.setattr(SessionRecorder, "start", remember)

    def prepare(manager) -> None:
        def fire() -> None:
            seen["t0"] = inject(manager, device, event, detail)
        timer = threading.Timer(0.5, fire)
        timer.daemon = True
        timer.start()
        seen["manager"] = manager

    import app.scripting.runner as runner_mod
    results: list[Any] = []
    original = runner_mod.ScriptRunner._report

    def report(self, result):
        results.append(result)
        return original(self, result)

    monkeypatch.setattr(runner_mod.ScriptRunner, "_report", report)
    monkeypatch.setattr(headless, "_let_the_record_show_the_safe_state", lambda manager, app: None)  # no LINarm state
    code = headless.run_headless(fast_config, str(script), duration_s=10.0, home_first=False, prepare=prepare,
                                 record_dir=str(tmp_path / "rec") if device == "recording" else None,
                                 output=lambda stream, text: out.append(text))
    assert code == headless.EXIT_SAFETY, "".join(out)
    outcome = check_outcome(safe, seen["t0"], results[-1], words)
    assert outcome["fes_stop_s"] < 1.0 and outcome["robot_safe_s"] < 1.0


def test_a_moment_of_silence_that_ends_is_no_stop(tmp_path, qtbot, fast_config) -> None:
    """A host starved for a moment (every device silent at once, then data again) must not stop a therapy."""
    safe = Safe()
    manager = LinarmppManager(fast_config, factories=fake_factories(tmp_path, safe))
    manager.start()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=10000)
        driver = manager.driver("linarm")
        driver._silent = False  # data came back before silence_stop_s
        driver._fire_event("silent", "no sample for 0.25 s")
        qtbot.wait(400)
        assert not manager.fault_policy.faults and not safe.calls["robot IDLE"]
    finally:
        manager.shutdown()


def test_losing_the_model_or_vr_while_they_drive_nothing_is_a_warning(tmp_path, qtbot, fast_config) -> None:
    safe = Safe()
    manager = LinarmppManager(fast_config, factories=fake_factories(tmp_path, safe))
    manager.start()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=10000)
        from app.safety.supervisor import AlarmLevel

        policy = manager.fault_policy
        assert policy.loss_level("patient_model") == AlarmLevel.WARNING  # e.g. while the robot homes
        assert policy.loss_level("vr") == AlarmLevel.WARNING
        assert policy.loss_level("physio") == AlarmLevel.STOP
        # The manager's watch counts a loss only after it has seen the "connected" event, which the driver
        # thread delivers just after `connected` turns true: inject until the watch has taken one.
        def lost() -> bool:
            manager.driver("patient_model")._fire_event("disconnected", "no valid datagram for 0.5 s")
            return any(a.level == AlarmLevel.WARNING and "patient_model" in a.text for a in manager.supervisor.alarms())

        qtbot.waitUntil(lost, timeout=3000)
        assert not policy.faults and not safe.calls["FES stop"]
        manager.driver("fes").stimulating = True
        assert policy.loss_level("patient_model") == AlarmLevel.STOP
    finally:
        manager.shutdown()
