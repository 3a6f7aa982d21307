"""F12 and the emergency stop during an electrode test burst (issue #32), seen on the stimulator's wire: the
set-up dialog open over the main window, a burst running, F12 pressed in the dialog; and the delay from the
e-stop to Stop on the wire over repeated bursts (bench/README.md's target: p99 ≤ 20 ms)."""

from __future__ import annotations

import statistics
import threading
import time

import pytest
from PySide6.QtCore import Qt

from app.core.config import AppConfig
from app.devices import linarm, physio, rehastim
from app.manager import LinarmppManager
from app.therapy.electrodes import Burst, SetupPlan, app_ports
from app.ui.electrode_setup import ElectrodeSetupDialog
from app.ui.main_window import MainWindow
from app.wire.sciencemode import Sm1CommandDecoder, Sm1Stop, Sm1Update

pytestmark = [pytest.mark.realtime, pytest.mark.sim_in_thread, pytest.mark.sim_homed]


def wire(sim) -> list[tuple[float, object]]:
    decoder = Sm1CommandDecoder()
    return [(t, msg) for t, data in list(sim.host_bytes_log) for msg in decoder.feed(data)]


def stimulating_on_the_wire(sim, since: float) -> bool:
    return any(t >= since and isinstance(m, Sm1Update) and any(s.current_ma > 0 for s in m.settings)
               for t, m in wire(sim))


def first_stop_after(sim, t0: float) -> float | None:
    return next((t for t, m in wire(sim) if t >= t0 and isinstance(m, Sm1Stop)), None)


@pytest.fixture
def window(qtbot):
    manager = LinarmppManager(AppConfig(), factories={"linarm": linarm.create, "physio": physio.create,
                                                      "fes": rehastim.create})
    manager.start()
    win = MainWindow(manager)
    qtbot.addWidget(win)
    win.show()
    try:
        robot, fes = manager.driver("linarm"), manager.driver("fes")
        qtbot.waitUntil(lambda: manager.all_connected() and fes.device_ready, timeout=5000)
        manager.devices["fes"].simulator.keep_host_log = True
        robot.command("goToHome", source="test", timeout_s=2.0)
        qtbot.waitUntil(lambda: (s := robot.latest("linarm.state")) is not None and s.controlState == 1
                        and s.homeState == 4,
                        timeout=30000)
        yield manager, win
    finally:
        manager.supervisor.reset_emergency_stop("test")
        win.close()
        manager.shutdown()


def test_f12_in_the_setup_dialog_during_a_burst(window, qtbot) -> None:
    manager, win = window
    sim = manager.devices["fes"].simulator
    dialog = ElectrodeSetupDialog(manager, win)
    dialog.setModal(True)
    dialog.show()
    qtbot.waitExposed(dialog)
    t_start = time.monotonic()
    assert dialog.start(SetupPlan(ceiling_ma=20.0, start_ma=10.0, step_ma=5.0, ramp_s=0.0, hold_s=1.0,
                                  measure_s=0.3, baseline_s=0.1, rest_s=0.1))
    qtbot.waitUntil(lambda: stimulating_on_the_wire(sim, t_start), timeout=5000)
    t0 = time.monotonic()
    qtbot.keyClick(dialog, Qt.Key.Key_F12)
    qtbot.waitUntil(lambda: first_stop_after(sim, t0) is not None, timeout=2000)
    delay = first_stop_after(sim, t0) - t0
    print(f"F12 in the set-up dialog during a burst: Stop on the wire after {delay * 1000:.1f} ms")
    assert delay <= 0.1, f"Stop after {delay * 1000:.1f} ms"  # the bench's p99 target is 20 ms; CI gets slack
    assert manager.supervisor.estop_latched
    qtbot.waitUntil(lambda: not dialog.running and dialog.start_button.isEnabled(), timeout=3000)
    assert "emergency stop" in dialog.result.aborted and "ended early" in dialog.status.text()
    assert not stimulating_on_the_wire(sim, first_stop_after(sim, t0) + 1e-6)
    dialog.close()


def test_estop_delay_over_repeated_bursts(window, qtbot) -> None:
    """The e-stop from a non-GUI thread (the API path) during test bursts, 20 times: the figures."""
    manager, _win = window
    sim, fes, robot, sup = (manager.devices["fes"].simulator, manager.driver("fes"), manager.driver("linarm"),
                            manager.supervisor)
    ports = app_ports(fes, robot.command, robot.latest, sup.robot_hold_reason, lambda _k, _d: None)
    delays: list[float] = []
    for _ in range(20):
        t_start = time.monotonic()
        ports.start_burst(Burst(4, 12, 250, 40.0, 0.9, 1.0, 0.2))
        qtbot.waitUntil(lambda t_start=t_start: stimulating_on_the_wire(sim, t_start), timeout=3000)
        box: list[float] = []
        thread = threading.Thread(target=lambda box=box: (box.append(time.monotonic()),
                                                          sup.emergency_stop("test", "during a test burst")))
        thread.start()
        thread.join(2.0)
        qtbot.waitUntil(lambda box=box: first_stop_after(sim, box[0]) is not None, timeout=2000)
        delays.append(first_stop_after(sim, box[0]) - box[0])
        assert not fes.stimulating
        sup.reset_emergency_stop("test")
    delays.sort()
    p99 = delays[-1]  # n = 20: the largest
    print(f"e-stop during test bursts: median {statistics.median(delays) * 1000:.2f} ms, "
          f"max (p99 at n=20) {p99 * 1000:.2f} ms")
    assert p99 <= 0.1
