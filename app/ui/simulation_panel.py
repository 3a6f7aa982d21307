"""The simulation panel: what the simulated patient does, and the simulated devices' plugs.

Shown only when a device is simulated. The one simulated patient (``manager.patient``, shared by
the LINarm and physiological-board simulators) grips the handle -- idle, squeeze now, squeeze
periodically, squeeze when the handle reaches a target -- and pushes it -- passive, push to a
target, or fail the sub-task (too weak, or stops early). The physiological board can be given a
skin-conductance response and sensor-fault flags, and each simulated device can be "unplugged"
(kill) and plugged back (restart) to show what the application does when a cable is pulled.

Inputs are checked before anything is applied: a bad value is reported and nothing changes.
"""

from __future__ import annotations

import logging
from typing import Any

from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QHideEvent, QShowEvent
from PySide6.QtWidgets import (
    QCheckBox,
    QDoubleSpinBox,
    QFrame,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QVBoxLayout,
    QWidget,
)

from app.core import journal, streams
from app.core.bus import StreamBus
from app.devices.sim.host import SimulatorProcessError
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus
from app.ui.theme import colours
from app.wire.physio_codec import FAULT_FLAGS

log = logging.getLogger(__name__)



def fixed_lines(label: QLabel, lines: int = 2) -> QLabel:
    """A wrapping label of a fixed number of lines: it wraps, but gives its layout no height-for-width
    (which would make an enclosing scroll area size the whole panel by its preferred height)."""
    label.setWordWrap(True)
    label.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Fixed)
    label.setFixedHeight(lines * label.fontMetrics().lineSpacing() + 6)
    return label


def spin(value: float, lo: float, hi: float, decimals: int, step: float, suffix: str, name: str) -> QDoubleSpinBox:
    box = QDoubleSpinBox()
    box.setDecimals(decimals)
    box.setRange(lo, hi)
    box.setSingleStep(step)
    box.setValue(value)
    box.setSuffix(f" {suffix}" if suffix else "")
    box.setKeyboardTracking(False)
    box.setObjectName(name)
    box.setAccessibleName(name)
    box.setMinimumWidth(70)
    return box


def parse_positions(text: str) -> list[float]:
    """``"0.15, 0.35"`` -> [0.15, 0.35] (m); ValueError with a plain sentence otherwise."""
    parts = [p for p in text.replace(";", ",").replace(" ", ",").split(",") if p.strip()]
    if not parts:
        raise ValueError("type at least one target position, e.g. 0.15, 0.35")
    out = []
    for p in parts:
        try:
            x = float(p)
        except ValueError:
            raise ValueError(f"{p.strip()!r} is not a number (positions in metres, separated by commas)") from None
        if not 0.0 <= x <= 0.5:
            raise ValueError(f"{x} m is off the rail (0 .. 0.5 m)")
        out.append(x)
    return out


def _scroll(content: QWidget) -> QScrollArea:
    area = QScrollArea()
    area.setWidgetResizable(True)
    area.setFrameShape(QFrame.Shape.NoFrame)
    area.setWidget(content)
    return area


class SimulationPanel(QWidget):
    def __init__(self, manager: LinarmppManager, *, qt_bus: QtBus | None = None) -> None:
        """The simulators of ``manager``; the live grip force from the bus (``qt_bus``'s, else the manager's)."""
        super().__init__()
        self.manager = manager
        self.bus: StreamBus = qt_bus.bus if qt_bus is not None else manager.bus
        self.patient: Any = manager.patient
        self.sim_buttons: dict[str, tuple[QPushButton, QPushButton, QLabel]] = {}
        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        outer.setSpacing(3)
        self.summary = QLabel()
        self.summary.setObjectName("patientSummary")
        fixed_lines(self.summary)
        outer.addWidget(self.summary)
        content = QWidget()
        cols = QHBoxLayout(content)
        cols.setContentsMargins(2, 2, 2, 2)
        left, right = QVBoxLayout(), QVBoxLayout()
        cols.addLayout(left, 1)
        cols.addLayout(right, 1)
        outer.addWidget(_scroll(content), 1)
        self.message = QLabel("")
        self.message.setObjectName("simMessage")
        fixed_lines(self.message)
        outer.addWidget(self.message)

        left.addWidget(self._grip_box())
        left.addWidget(self._handle_box())
        left.addStretch(1)
        right.addWidget(self._physio_box())
        right.addWidget(self._simulators_box())
        right.addStretch(1)
        if self.patient is None:
            for box in (self.grip_box, self.handle_box):
                box.setEnabled(False)
                box.setToolTip("No simulated patient: no device is simulated")

        # Refreshed while shown only (a hidden tab, a closed window: nobody reads it, and a window a failed test
        # left alive must not keep asking a simulator process that has ended).
        self.timer = QTimer(self)
        self.timer.setInterval(250)
        self.timer.timeout.connect(self.refresh)
        self.refresh()

    def showEvent(self, event: QShowEvent) -> None:
        super().showEvent(event)
        self.refresh()
        self.timer.start()

    def hideEvent(self, event: QHideEvent) -> None:
        self.timer.stop()
        super().hideEvent(event)

    # ------------------------------------------------------------------ building
    def _grip_box(self) -> QGroupBox:
        box = self.grip_box = QGroupBox("Grip (simulated patient)")
        g = QGridLayout(box)
        g.setVerticalSpacing(3)
        self.grip_idle = QPushButton("&Idle")
        self.grip_idle.setToolTip("Hand resting on the handle")
        self.grip_idle.clicked.connect(lambda: self._apply("grip idle", lambda p: p.idle()))
        g.addWidget(self.grip_idle, 0, 0)
        self.peak = spin(38.0, 0.0, 200.0, 1, 1.0, "N", "peak force")
        self.peak_button = QPushButton("Set peak")
        self.peak_button.clicked.connect(
            lambda: self._apply(f"peak force {self.peak.value():.1f} N", lambda p: p.set_peak_force(self.peak.value())))
        g.addWidget(self.peak, 0, 1)
        g.addWidget(self.peak_button, 0, 2)

        self.squeeze_duration = spin(1.0, 0.05, 60.0, 2, 0.25, "s", "squeeze duration")
        self.squeeze_button = QPushButton("&Squeeze now")
        self.squeeze_button.clicked.connect(self.squeeze_now)
        g.addWidget(self.squeeze_button, 1, 0)
        g.addWidget(self.squeeze_duration, 1, 1)

        self.period = spin(2.0, 0.1, 60.0, 2, 0.5, "s", "period")
        self.duty = spin(50.0, 0.0, 100.0, 0, 5.0, "%", "duty")
        self.periodic_button = QPushButton("&Periodically")
        self.periodic_button.setToolTip("Squeeze for duty × period, every period")
        self.periodic_button.clicked.connect(self.squeeze_periodically)
        g.addWidget(self.periodic_button, 2, 0)
        g.addWidget(self.period, 2, 1)
        g.addWidget(self.duty, 2, 2)

        self.targets = QLineEdit("0.15, 0.35")
        self.targets.setObjectName("targets")
        self.targets.setAccessibleName("target positions in metres")
        self.targets.setToolTip("Handle positions (m), separated by commas")
        self.tolerance = spin(0.005, 0.0005, 0.05, 4, 0.001, "m", "tolerance")
        self.reaction = spin(0.2, 0.0, 5.0, 2, 0.05, "s", "reaction delay")
        self.target_button = QPushButton("At &targets")
        self.target_button.setToolTip("Squeeze (for the duration above) after the reaction delay, each time the "
                                      "handle arrives within the tolerance of a target")
        self.target_button.clicked.connect(self.squeeze_at_targets)
        g.addWidget(self.target_button, 3, 0)
        g.addWidget(self.targets, 3, 1, 1, 2)
        row = QHBoxLayout()
        tol, rea = QLabel("± tol."), QLabel("delay")
        tol.setBuddy(self.tolerance)
        rea.setBuddy(self.reaction)
        for w in (tol, self.tolerance, rea, self.reaction):
            row.addWidget(w)
        g.addLayout(row, 4, 0, 1, 3)
        return box

    def _handle_box(self) -> QGroupBox:
        box = self.handle_box = QGroupBox("Handle (simulated patient's arm)")
        g = QGridLayout(box)
        g.setVerticalSpacing(3)
        self.passive_button = QPushButton("P&assive")
        self.passive_button.setToolTip("The arm follows the handle (small damping)")
        self.passive_button.clicked.connect(lambda: self._apply("handle passive", lambda p: p.passive()))
        g.addWidget(self.passive_button, 0, 0)
        self.push_target = spin(0.35, 0.0, 0.5, 3, 0.01, "m", "push target")
        self.push_force = spin(15.0, 0.0, 100.0, 1, 1.0, "N", "push force")
        self.push_button = QPushButton("Push t&o")
        self.push_button.clicked.connect(self.push_to)
        g.addWidget(self.push_button, 1, 0)
        g.addWidget(self.push_target, 1, 1)
        g.addWidget(self.push_force, 1, 2)
        self.fraction = spin(0.2, 0.0, 1.0, 2, 0.05, "", "fraction")
        self.fraction.setToolTip("Weak: fraction of the force; stop early: fraction of the distance")
        self.weak_button = QPushButton("Fail: &weak")
        self.weak_button.clicked.connect(self.fail_weak)
        self.early_button = QPushButton("Fail: stop &early")
        self.early_button.clicked.connect(self.fail_stop_early)
        label = QLabel("fraction")
        label.setBuddy(self.fraction)
        g.addWidget(self.weak_button, 2, 0)
        g.addWidget(self.early_button, 2, 1)
        row = QHBoxLayout()
        row.addWidget(label)
        row.addWidget(self.fraction)
        g.addLayout(row, 2, 2)
        return box

    def _physio_box(self) -> QGroupBox:
        box = self.physio_box = QGroupBox("Physiological board")
        g = QGridLayout(box)
        g.setVerticalSpacing(2)
        self.phasic_amplitude = spin(0.0, 0.0, 10.0, 2, 0.1, "µS", "response amplitude")
        self.phasic_amplitude.setSpecialValueText("random")
        self.phasic_button = QPushButton("Skin-conductance &response")
        self.phasic_button.setToolTip("A stimulus now: a response follows after 1.5–2.5 s")
        self.phasic_button.clicked.connect(self.phasic_event)
        g.addWidget(self.phasic_button, 0, 0)
        g.addWidget(self.phasic_amplitude, 0, 1)
        self.fault_checks: dict[int, QCheckBox] = {}
        for r, (flag, text, _channel) in enumerate(FAULT_FLAGS, start=1):
            check = QCheckBox(text[0].upper() + text[1:])
            check.setObjectName(f"fault:{flag}")
            check.clicked.connect(lambda _on: self.apply_fault_flags())
            g.addWidget(check, r, 0, 1, 2)
            self.fault_checks[flag] = check
        if self._physio_core_handle() is None:
            box.setEnabled(False)
            box.setToolTip("The physiological board is not simulated")
        return box

    def _simulators_box(self) -> QGroupBox:
        box = QGroupBox("Simulated devices (pull / plug the cable)")
        g = QGridLayout(box)
        g.setVerticalSpacing(2)
        r = 0
        for name, handle in self.manager.devices.items():
            if handle.simulator is None:
                continue
            status = QLabel()
            kill = QPushButton("Kill")
            kill.setObjectName(f"kill:{name}")
            kill.setToolTip(f"The {name} vanishes mid-stream (cable pulled)")
            kill.clicked.connect(lambda _c=False, n=name: self.kill(n))
            restart = QPushButton("Restart")
            restart.setObjectName(f"restart:{name}")
            restart.setToolTip(f"The {name} comes back, freshly powered up")
            restart.clicked.connect(lambda _c=False, n=name: self.restart(n))
            g.addWidget(QLabel(f"<b>{name}</b>"), r, 0)
            g.addWidget(status, r, 1)
            g.addWidget(kill, r, 2)
            g.addWidget(restart, r, 3)
            self.sim_buttons[name] = (kill, restart, status)
            r += 1
        if r == 0:
            g.addWidget(QLabel("No device is simulated on a serial link."), 0, 0)
        return box

    # ------------------------------------------------------------------ actions
    def _say(self, text: str, ok: bool = True) -> None:
        c = colours()
        self.message.setText(text)
        self.message.setStyleSheet(f"color: {c.ok if ok else c.bad};" + ("" if ok else " font-weight: bold;"))

    def _apply(self, what: str, fn: Any) -> bool:
        if self.patient is None:
            self._say("No simulated patient: no device is simulated.", ok=False)
            return False
        try:
            fn(self.patient)
        except (ValueError, RuntimeError) as exc:  # RuntimeError: the simulator process did not answer
            self._say(f"Not applied: {exc}", ok=False)
            return False
        self._say(f"Simulated patient: {what}.")
        self.manager.supervisor.record(journal.SIMULATION, action=what)
        self.refresh()
        return True

    def squeeze_now(self) -> bool:
        d = self.squeeze_duration.value()
        return self._apply(f"squeeze for {d:.2f} s", lambda p: p.squeeze(d))

    def squeeze_periodically(self) -> bool:
        period, duty = self.period.value(), self.duty.value() / 100.0
        return self._apply(f"squeeze every {period:.2f} s ({duty:.0%})", lambda p: p.squeeze_periodically(period, duty))

    def squeeze_at_targets(self) -> bool:
        try:
            targets = parse_positions(self.targets.text())
        except ValueError as exc:
            self._say(f"Not applied: {exc}", ok=False)
            self.targets.setFocus()
            return False
        tol, dur, delay = self.tolerance.value(), self.squeeze_duration.value(), self.reaction.value()
        shown = ", ".join(f"{x:.3f}" for x in targets)
        return self._apply(f"squeeze at {shown} m (±{tol * 1000:.1f} mm)",
                           lambda p: p.squeeze_at_targets(targets, tol, dur, delay))

    def push_to(self) -> bool:
        x, f = self.push_target.value(), self.push_force.value()
        return self._apply(f"push to {x:.3f} m with {f:.1f} N", lambda p: p.push_to(x, f))

    def fail_weak(self) -> bool:
        x, f, k = self.push_target.value(), self.push_force.value(), self.fraction.value()
        return self._apply(f"push weakly ({k:.0%}) to {x:.3f} m", lambda p: p.fail_weak(x, f, k))

    def fail_stop_early(self) -> bool:
        x, f, k = self.push_target.value(), self.push_force.value(), self.fraction.value()
        return self._apply(f"push to {x:.3f} m, give up after {k:.0%}", lambda p: p.fail_stop_early(x, f, k))

    def _physio_core_handle(self) -> Any:
        handle = self.manager.devices.get(streams.PHYSIO)
        return handle.simulator if handle is not None and handle.simulator is not None else None

    def phasic_event(self) -> bool:
        sim = self._physio_core_handle()
        if sim is None:
            self._say("The physiological board is not simulated.", ok=False)
            return False
        amp = self.phasic_amplitude.value()
        amplitude = None if amp <= self.phasic_amplitude.minimum() else amp
        if not self._control(sim, "phasic_event", amplitude):
            return False
        self._say("Skin-conductance response triggered" + (f" ({amp:.2f} µS)." if amplitude else "."))
        self.manager.supervisor.record(journal.SIMULATION, action="phasic event", amplitude=amplitude)
        return True

    def fault_flags(self) -> int:
        flags = 0
        for flag, check in self.fault_checks.items():
            if check.isChecked():
                flags |= flag
        return flags

    def apply_fault_flags(self) -> bool:
        sim = self._physio_core_handle()
        if sim is None:
            return False
        flags = self.fault_flags()
        if not self._control(sim, "set_fault_flags", flags):
            return False
        self._say(f"Physiological board fault flags: 0x{flags:02X}.")
        self.manager.supervisor.record(journal.SIMULATION, action="fault flags", flags=flags)
        return True

    def _control(self, sim: Any, name: str, *args: Any) -> bool:
        """A control of a simulator, in this process or the simulator process; False (said) when it failed."""
        try:
            sim.control(name, *args)
        except Exception as exc:  # the simulator process may be gone or slow: say so, change nothing
            self._say(f"Not applied: {exc}", ok=False)
            return False
        return True

    def kill(self, name: str) -> None:
        handle = self.manager.devices.get(name)
        if handle is None or handle.simulator is None:
            return
        try:
            handle.simulator.kill()
        except Exception as exc:
            self._say(f"Not applied: {exc}", ok=False)
            return
        self._say(f"Simulated {name}: cable pulled.")
        self.manager.supervisor.record(journal.SIMULATION, action="kill", device=name)
        self.refresh()

    def restart(self, name: str) -> None:
        handle = self.manager.devices.get(name)
        if handle is None or handle.simulator is None:
            return
        try:
            handle.simulator.restart()
        except Exception as exc:
            self._say(f"Not applied: {exc}", ok=False)
            return
        if name == streams.PHYSIO:  # a freshly powered board has no fault flags
            for check in self.fault_checks.values():
                check.setChecked(False)
        self._say(f"Simulated {name}: plugged back in (fresh power-up).")
        self.manager.supervisor.record(journal.SIMULATION, action="restart", device=name)
        self.refresh()

    # ------------------------------------------------------------------ state
    def grip_force_now(self) -> float | None:
        """The grip force the physiological board last sent (N), if any."""
        sample = self.bus.latest(streams.PHYSIO_MAIN)
        force = getattr(sample, "force", None)
        return float(force) if force is not None else None

    def refresh(self) -> None:
        c = colours()
        parts = []
        settings = None
        if self.patient is not None:
            try:
                settings = self.patient.settings()
            except SimulatorProcessError:
                # The process that simulates the patient ended (a crash, a kill): said here on every tick,
                # never raised from the timer into the window's event loop.
                parts.append("The simulated patient's simulator process has stopped: restart the application "
                             "to simulate again.")
        if settings is not None:
            s = settings
            grip = {
                "idle": "idle",
                "squeeze": f"squeeze {s.squeezeDuration:.2f} s",
                "periodic": f"every {s.period:.2f} s ({s.duty:.0%})",
                "at_target": "at " + ", ".join(f"{x:.3f}" for x in s.targets) + " m",
            }.get(s.gripMode.value, s.gripMode.value)
            handle = {
                "passive": "passive",
                "push": f"push to {s.handleTarget:.3f} m ({s.pushForce:.0f} N)",
                "weak": f"weak push to {s.handleTarget:.3f} m ({s.weakFraction:.0%})",
                "stop_early": f"push to {s.handleTarget:.3f} m, stops at {s.stopFraction:.0%}",
            }.get(s.handleMode.value, s.handleMode.value)
            parts.append(f"<b>Grip</b>: {grip} (peak {s.peakForce:.0f} N) · <b>Handle</b>: {handle}")
        force = self.grip_force_now()
        if force is not None:
            parts.append(f"grip force now <b>{force:.1f} N</b>")
        self.summary.setText(" · ".join(parts) or "No simulated patient.")
        self.summary.setTextFormat(Qt.TextFormat.RichText)
        for name, (kill, _restart, status) in self.sim_buttons.items():
            handle = self.manager.devices[name]
            running = handle.simulator is not None and handle.simulator.running
            status.setText(f"<span style='color:{c.ok if running else c.bad}'>●</span> "
                           f"{'running' if running else 'unplugged'}")
            kill.setEnabled(running)
