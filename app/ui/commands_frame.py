"""Frame 4 — commands. On top the main commands: one connect/disconnect toggle per device. Below,
tabs with the panels of the other parts of the application (robot states and modes, FES,
assistance, scripts, simulation, alarms), each loaded only when its module is present.

The manager has no per-device start/stop yet, so :func:`set_device_running` does it here with the
driver's own ``start()``/``stop()``.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable

from PySide6.QtCore import Qt, QTimer
from PySide6.QtWidgets import (
    QFrame,
    QGridLayout,
    QGroupBox,
    QLabel,
    QMessageBox,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from app.core import journal
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus, qt_bus_for, takes_qt_bus
from app.ui.theme import colours

log = logging.getLogger(__name__)

# (tab title, module, class, only when a device is simulated)
# Panels that lay out (and scroll) their own content: no scroll area around them -- a scroll area
# inside a scroll area hid the primary controls below two folds (issue #19).
SELF_SCROLLING = {"LinarmPanel", "ScriptConsole", "AlarmsPanel", "FesPanel", "LinarmViewer"}
# The viewers only show what the devices send: each is built when its tab is first shown (their graphs are a
# second's CPU of the window's start, spent for tabs a session may never open). The panels that act (robot, FES,
# assistance, exercises, script, alarms) are built with the window.
BUILT_WHEN_SHOWN = {"LinarmViewer", "PhysioViewer", "PatientModelViewer", "VrViewer"}

PANELS: list[tuple[str, str, str, bool]] = [
    ("Robot", "app.ui.linarm_panel", "LinarmPanel", False),
    ("Motors", "app.ui.linarm_viewer", "LinarmViewer", False),
    ("FES", "app.ui.fes_panel", "FesPanel", False),
    ("Sensors", "app.ui.physio_viewer", "PhysioViewer", False),
    ("Assistance", "app.ui.assistance_panel", "AssistancePanel", False),
    ("Model", "app.ui.patient_model_viewer", "PatientModelViewer", False),
    ("VR", "app.ui.vr_viewer", "VrViewer", False),
    ("Exercises", "app.ui.exercises_panel", "ExercisesPanel", False),
    ("Script", "app.ui.script_console", "ScriptConsole", False),
    ("Simulation", "app.ui.simulation_panel", "SimulationPanel", True),
    ("Alarms", "app.ui.alarms_panel", "AlarmsPanel", False),
]


def set_device_running(manager: LinarmppManager, name: str, running: bool, timeout_s: float = 1.0) -> bool:
    """Start or stop one device's driver (the simulator, if any, keeps running so a later connect
    finds it). Returns True when the driver is in the requested state.

    Stopping goes through the driver's ``on_disconnect`` (which fails pending requests); a device
    that needs a safe state first (robot idle, stimulation off) must get it from its driver or the
    safety supervisor — the caller asks the operator before disconnecting a device in use.
    """
    return manager.set_device_running(name, running, timeout_s)


class DeviceToggle(QPushButton):
    """A checkable button: checked = the device's driver is running (connected or reconnecting)."""

    def __init__(self, name: str, simulated: bool) -> None:
        super().__init__()
        self.name = name
        self.simulated = simulated
        self.setCheckable(True)
        self.setMinimumHeight(26)
        # One row of toggles; each shows the device's name, its state is its colour and tooltip (the
        # status bar is the one place with the words and rates).
        self.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Fixed)
        self._shown: tuple[bool, bool, str] | None = None

    def show_state(self, running: bool, connected: bool) -> None:
        c = colours()
        # Twice a second for every device: a style sheet re-polishes the button, so only on a change.
        if self._shown == (running, connected, c.name) and self.isChecked() == running:
            return
        self._shown = (running, connected, c.name)
        if connected:
            colour, state = c.ok, "connected"
        elif running:
            colour, state = c.warn, "connecting…"
        else:
            colour, state = c.bad, "disconnected"
        sim = " (sim)" if self.simulated else ""
        action = "Disconnect" if running else "Connect"
        self.blockSignals(True)
        self.setChecked(running)
        self.blockSignals(False)
        self.setText(f"● {self.name}{sim}")
        self.setStyleSheet(f"QPushButton {{ text-align: left; padding: 2px 8px; }} QPushButton {{ color: {colour}; }}")
        self.setToolTip(f"{self.name}{sim}: {state}. Press to {action.lower()}.")
        self.setAccessibleName(f"{self.name} {state}; press to {action.lower()}")


class CommandsFrame(QWidget):
    def __init__(self, manager: LinarmppManager, *, qt_bus: QtBus | None = None) -> None:
        """The device toggles and panels of ``manager``; link states (and the panels' data) through ``qt_bus``
        (the window's; else the frame's own)."""
        super().__init__()
        self.manager = manager
        self.qt_bus = qt_bus_for(manager, qt_bus, self)
        self.toggles: dict[str, DeviceToggle] = {}
        self.panels: dict[str, QWidget] = {}
        self._unbuilt: dict[int, tuple[str, Callable[..., QWidget]]] = {}  # tab index -> a viewer not built yet
        # Confirmation before disconnecting a device; tests replace it.
        self.confirm: Callable[[str], bool] = self._ask_confirmation

        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.setSpacing(4)
        self.devices_box = QGroupBox("Devices (press to connect or disconnect)")
        self.devices_grid = QGridLayout(self.devices_box)
        self.devices_grid.setContentsMargins(4, 4, 4, 4)
        self.devices_grid.setSpacing(4)
        self.no_devices = QLabel("no device configured")
        self.devices_grid.addWidget(self.no_devices, 0, 0)
        lay.addWidget(self.devices_box)

        self.tabs = QTabWidget()
        self.tabs.setDocumentMode(True)
        self.tabs.setUsesScrollButtons(True)
        # Eleven tabs must fit the dock's ~690 px at 1366×768 without scroll arrows: tighter padding
        # than the style's default (the text itself is never elided).
        self.tabs.tabBar().setStyleSheet("QTabBar::tab { padding: 5px 8px; }")
        lay.addWidget(self.tabs, 1)
        self._load_panels()
        if self.tabs.count() == 0:
            empty = QLabel("No command panel is available in this build.")
            empty.setAlignment(Qt.AlignmentFlag.AlignCenter)
            self.tabs.addTab(empty, "Panels")

        self._sync_devices()
        # A method, not a lambda: the connection ends with this frame (the window's adapter outlives it).
        self.qt_bus.connection_changed.connect(self._connection_changed)
        self.timer = QTimer(self)
        self.timer.setInterval(500)
        self.timer.timeout.connect(self.refresh)
        self.timer.start()
        self.refresh()

    def _load_panels(self) -> None:
        any_simulated = any(h.simulated for h in self.manager.devices.values())
        for title, module_name, class_name, needs_sim in PANELS:
            if needs_sim and not any_simulated:
                continue
            try:
                module = importlib.import_module(module_name)
            except ModuleNotFoundError as exc:
                if exc.name != module_name:
                    raise  # the panel exists but one of its imports is missing: a real bug
                continue
            factory = getattr(module, class_name)
            if class_name in BUILT_WHEN_SHOWN:
                holder = QWidget()
                holder.setLayout(QVBoxLayout())
                holder.layout().setContentsMargins(0, 0, 0, 0)
                self._unbuilt[self.tabs.addTab(holder, title)] = (class_name, factory)
                continue
            self.tabs.addTab(self._build_panel(class_name, factory), title)
        self.tabs.currentChanged.connect(self._build_shown)
        self._build_shown(self.tabs.currentIndex())

    def _build_panel(self, class_name: str, factory: Callable[..., QWidget]) -> QWidget:
        """The panel, and what its tab holds (the panel, or a scroll area around it)."""
        panel = factory(self.manager, qt_bus=self.qt_bus) if takes_qt_bus(factory) else factory(self.manager)
        self.panels[class_name] = panel
        if class_name in SELF_SCROLLING:
            return panel
        # A tall panel scrolls inside its tab instead of forcing the window taller than the screen.
        scroll = QScrollArea()
        scroll.setProperty("scrolls", True)
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QFrame.Shape.NoFrame)
        scroll.setWidget(panel)
        return scroll

    def _build_shown(self, index: int) -> None:
        """Build a viewer the first time its tab is shown (BUILT_WHEN_SHOWN)."""
        pending = self._unbuilt.pop(index, None)
        if pending is None:
            return
        holder = self.tabs.widget(index)
        holder.layout().addWidget(self._build_panel(*pending))

    def build_all_panels(self) -> None:
        """Every panel, shown or not (a check of every panel's text, a test that reads them all)."""
        for index in list(self._unbuilt):
            self._build_shown(index)

    def _sync_devices(self) -> None:
        for name, handle in self.manager.devices.items():
            if name in self.toggles:
                continue
            toggle = DeviceToggle(name, handle.simulated)
            toggle.toggled.connect(lambda on, n=name: self.set_running(n, on))
            n = len(self.toggles)
            self.devices_grid.addWidget(toggle, 0, n)
            self.toggles[name] = toggle
        self.no_devices.setVisible(not self.toggles)

    def _connection_changed(self, _device: str, _connected: bool, _reason: str) -> None:
        self.refresh()

    def refresh(self) -> None:
        self._sync_devices()
        for name, toggle in self.toggles.items():
            handle = self.manager.devices.get(name)
            if handle is None:
                toggle.setEnabled(False)
                continue
            toggle.show_state(handle.driver.isRunning(), self.qt_bus.connected(name))

    def set_running(self, name: str, running: bool) -> bool:
        """Connect (start) or disconnect (stop) one device, asking first before disconnecting one
        that is connected."""
        handle = self.manager.devices.get(name)
        if handle is None:
            return False
        if not running and self.qt_bus.connected(name) and not self.confirm(name):
            self.refresh()
            return False
        ok = set_device_running(self.manager, name, running)
        if not ok:
            log.error("%s: could not %s", name, "start" if running else "stop")
        self.manager.supervisor.record(journal.DEVICE_TOGGLED, device=name, running=running, ok=ok)
        self.refresh()
        return ok

    def _ask_confirmation(self, name: str) -> bool:
        answer = QMessageBox.question(
            self, f"Disconnect {name}",
            f"Disconnect {name}? Its data stops until you connect it again.",
        )
        return answer == QMessageBox.StandardButton.Yes
