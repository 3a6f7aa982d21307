"""A therapy running in the window while someone opens a long past session (issue #37): the simulated LINarm homed
and ON (its controller's 250 ms host watchdog armed), the stimulator stimulating, the main window and its sessions
browser on a folder holding a 30-minute session. What is measured: the GUI thread's gaps (a 1 ms timer), the host's
bytes to the LINarm (the heartbeat), the stimulator's wire (a Stop), and the e-stop's delay to both wires.

Used by tests/test_heavy_work_window.py and bench/bench_heavy_work.py."""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PySide6.QtCore import QCoreApplication, QEvent, Qt, QTimer
from PySide6.QtGui import QKeyEvent

from app.core.config import AppConfig
from app.core.fes_profile import ChannelProfile, FesProfile, Trapezoid
from app.devices import linarm, physio, rehastim
from app.manager import LinarmppManager
from app.wire.linarm_protocol import ControlMode, ControlState, HomeState
from tests.test_estop_wire import robot_idle_after
from tests.test_fes_exit_paths import first_stop_after

# Stimulates from the first second and for an hour (the exit-path tests' profile ends at 100 s: a slow machine
# may take longer than that to read a summary).
PROFILE = FesProfile("exercise profile", "time",
                     {1: ChannelProfile(Trapezoid(10.0, (0.0, 0.25), (3600.0, 3601.0)),
                                        Trapezoid(150.0, (0.0, 0.25), (3600.0, 3601.0)))})

WATCHDOG_S = 0.25  # the controller's host watchdog (firmware): a longer silence of the host trips it


class GapMeter:
    """A 1 ms timer on the GUI thread: every tick's time and the gap since the one before, and the GUI thread's own
    CPU time within that gap (what the turn cost, however long a loaded machine kept the thread waiting)."""

    def __init__(self) -> None:
        from PySide6.QtCore import QTimer

        self.ticks: list[tuple[float, float]] = []
        self.cpu_gaps: list[float] = []  # one per tick: the GUI thread's CPU time since the tick before
        self._last = time.monotonic()
        self._last_cpu = time.thread_time()
        self.timer = QTimer()
        self.timer.setTimerType(Qt.TimerType.PreciseTimer)
        self.timer.setInterval(1)
        self.timer.timeout.connect(self._tick)
        self.timer.start()

    def _tick(self) -> None:
        now, cpu = time.monotonic(), time.thread_time()
        self.ticks.append((now, now - self._last))
        self.cpu_gaps.append(cpu - self._last_cpu)
        self._last, self._last_cpu = now, cpu

    def longest(self, t0: float, t1: float) -> float:
        """The longest gap ending in [t0, t1] (a stall running at t1 ends at the first tick after it)."""
        end = next((t for t, _g in self.ticks if t > t1), t1)
        return max((g for t, g in self.ticks if t0 < t <= end), default=0.0)

    def longest_cpu(self, t0: float, t1: float) -> float:
        """The GUI thread's largest CPU time in one gap ending in [t0, t1]."""
        end = next((t for t, _g in self.ticks if t > t1), t1)
        return max((c for (t, _g), c in zip(self.ticks, self.cpu_gaps, strict=True) if t0 < t <= end), default=0.0)

    def stop(self) -> None:
        self.timer.stop()


def host_silences(sim: Any, t0: float, t1: float) -> float:
    """The longest silence of the host towards the LINarm between t0 and t1 (what its watchdog sees)."""
    times = [t0, *(t for t, _data in list(sim.host_bytes_log) if t0 <= t <= t1), t1]
    return max((b - a for a, b in itertools.pairwise(times)), default=0.0)


@dataclasses.dataclass
class Therapy:
    manager: LinarmppManager
    window: Any
    browser: Any
    meter: GapMeter

    @property
    def fes(self) -> Any:
        return self.manager.driver("fes")

    @property
    def robot(self) -> Any:
        return self.manager.driver("linarm")

    def sim(self, name: str) -> Any:
        return self.manager.devices[name].simulator

    def running(self) -> dict[str, Any]:
        """The therapy's state now: stimulating, robot ON without error, no alarm raised."""
        state = self.robot.latest("linarm.state")
        return {"stimulating": bool(self.fes.stimulating),
                "robot_on": state is not None and int(state.controlState) == int(ControlState.ON_CTRL_STATE),
                "robot_error": int(state.errorState) if state is not None else None,
                "alarms": [a.text for a in self.manager.supervisor.alarms()],
                "estop": self.manager.supervisor.estop_latched}

    def check_undisturbed(self, t0: float, t1: float) -> dict[str, Any]:
        """What the therapy saw between t0 and t1."""
        return {**self.running(), "fes_stop_on_wire": first_stop_after(self.sim("fes"), "sm1", t0) is not None,
                "host_silence_s": host_silences(self.sim("linarm"), t0, t1), "gui_stall_s": self.meter.longest(t0, t1)}

    def press_f12_later(self, delay_s: float) -> tuple[threading.Thread, dict[str, float]]:
        """F12 posted to the window from another thread after ``delay_s`` (as a key press reaches a busy GUI
        thread: queued behind whatever it is doing). Returns the thread (join it) and {"t": when it was posted}."""
        stamp: dict[str, float] = {}

        def press() -> None:
            time.sleep(delay_s)
            stamp["t"] = time.monotonic()
            QCoreApplication.postEvent(self.window, QKeyEvent(QEvent.Type.KeyPress, Qt.Key.Key_F12,
                                                              Qt.KeyboardModifier.NoModifier))

        thread = threading.Thread(target=press, name="f12-press")
        thread.start()
        return thread, stamp

    def stop_delays(self, t0: float) -> tuple[float | None, float | None]:
        fes = first_stop_after(self.sim("fes"), "sm1", t0)
        robot = robot_idle_after(self.sim("linarm"), t0)
        return (None if fes is None else fes - t0), (None if robot is None else robot - t0)


def start_therapy(sessions_root: Path, wait: Callable[[Callable[[], bool], int], None]) -> Therapy:
    """The simulated devices, the window, the robot homed and ON, FES stimulating, the sessions browser open on
    ``sessions_root``. ``wait(predicate, timeout_ms)`` runs the Qt loop until it holds (qtbot.waitUntil)."""
    from app.ui.main_window import MainWindow

    config = AppConfig()
    config = dataclasses.replace(config, recording=dataclasses.replace(config.recording, folder=str(sessions_root)))
    manager = LinarmppManager(config, factories={"linarm": linarm.create, "physio": physio.create,
                                                 "fes": rehastim.create})
    manager.start()
    window = MainWindow(manager)
    try:
        window.show()
        wait(manager.all_connected, 10000)
        fes = manager.driver("fes")
        wait(lambda: fes.device_ready, 5000)
        robot = manager.driver("linarm")
        robot.command("goToHome")
        wait(lambda: robot.latest("linarm.state") is not None
             and int(robot.latest("linarm.state").homeState) == int(HomeState.HOME_DONE), 30000)
        robot.command("setCtrlState", int(ControlState.IDLE_CTRL_STATE))
        robot.command("setCtrlMode", int(ControlMode.POS_REF_BY_TARGET_POS))
        robot.command("setCtrlState", int(ControlState.ON_CTRL_STATE))
        for name in ("linarm", "fes"):
            manager.devices[name].simulator.keep_host_log = True
        fes.load_profile(PROFILE)
        fes.start_stimulation("exercise")
        wait(lambda: fes.stimulating, 3000)
        window.show_sessions_browser()
        browser = window._browser
        meter = GapMeter()
    except BaseException:  # nothing left running for the next test (a slow homing on a loaded machine)
        window.close()
        manager.shutdown()
        raise
    return Therapy(manager, window, browser, meter)


def stop_therapy(therapy: Therapy) -> None:
    therapy.meter.stop()
    therapy.browser.close()
    therapy.window.close()
    therapy.manager.shutdown()


def settle(seconds: float) -> None:
    """Run the Qt loop for ``seconds`` (the bench's pauses; the tests wait on conditions)."""
    from PySide6.QtCore import QEventLoop

    loop = QEventLoop()
    QTimer.singleShot(int(seconds * 1000), loop.quit)
    loop.exec()


@dataclasses.dataclass
class Opening:
    """How opening a window from the browser went: the GUI thread's longest stall while the worker read the
    session (``load_stall_s``), while the window was built and first drawn (``build_stall_s``), the times, and
    what the therapy saw meanwhile."""

    widget: Any
    seconds: float  # click → the window ready
    load_s: float  # click → the worker's result on the GUI thread
    load_stall_s: float
    build_stall_s: float
    therapy: dict[str, Any]


def open_from_browser(therapy: Therapy, action: str, ready: Callable[[Any], bool],
                      wait: Callable[[Callable[[], bool], int], None]) -> Opening:
    """Click ``action`` ("replay", "open_summary", …) from inside the event loop, as a click does, and measure."""
    browser = therapy.browser
    opened: list[Any] = []
    state: dict[str, Any] = {}
    browser.opened.connect(opened.append)

    def click() -> None:
        state["t"] = time.monotonic()
        state["task"] = getattr(browser, action)()

    QTimer.singleShot(0, click)
    try:
        wait(lambda: bool(opened) and ready(opened[0]), 180000)
    finally:
        browser.opened.disconnect(opened.append)
    t_ready = time.monotonic()
    wait(lambda: therapy.meter.ticks[-1][0] > t_ready + 0.05, 5000)  # the tick that ends a stall running at t_ready
    t0, task = state["t"], state["task"]
    t_result = task.finished if task.finished is not None else t_ready
    return Opening(opened[0], t_ready - t0, t_result - t0, therapy.meter.longest(t0, t_result),
                   therapy.meter.longest(t_result, t_ready), therapy.check_undisturbed(t0, t_ready))
