"""The assistance panel: the patient's gains k_r, k_f, the clinical score given to the embedded
patient model, the therapist's four maps, and the live α, a_r, a_f with the values being applied.

Expects (all optional, so the panel also works before the lead wires them):

* ``manager.assistance`` — an ``app.safety.assistance.AssistanceController``; every edit calls its
  ``set_config`` (gains and maps together) so it takes effect at once; without it the panel only
  shows and edits and says the split is not active;
* ``manager.driver("patient_model")`` — a ``PatientModelDriver``; the clinical score is written to
  its ``clinical_score`` (None = not set: the model uses its default and flags the reply);
* the stream bus (the window's Qt bus adapter, else ``manager.bus``) — without a controller, the model's
  latest α is shown from it;
* ``manager.config.safety`` — the spin boxes stop at the robot's stiffness limit and the FES
  pulse-width limit (the drivers' command paths check them again).

``config_changed(AssistanceConfig)`` is emitted after each edit, e.g. to store it in the patient's
profile.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from PySide6.QtCore import QTimer, Signal
from PySide6.QtWidgets import (
    QDoubleSpinBox,
    QFormLayout,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QSpinBox,
    QVBoxLayout,
    QWidget,
)

from app.core import streams
from app.core.config import AssistanceConfig, AssistanceMap
from app.ui.qt_bus import QtBus
from app.ui.widgets import StepSlider, on_screen

# (config field, label, unit, decimals, step)
MAPS: tuple[tuple[str, str, str, int, float], ...] = (
    ("k_m_stiffness_n_m", "k_m  VSA stiffness", "N/m", 0, 50.0),
    ("k_a_admittance_m_s_n", "k_a  admittance gain", "m/(s·N)", 4, 0.0005),
    ("k_t_assistive_n_m", "k_t  assistive gain", "N/m", 0, 10.0),
    ("fes_pulse_width_us", "FES pulse width", "µs", 0, 10.0),
)
NOT_SET = -1
GAIN_MAX_STEP = 5  # slider units (0.01 each): the most one action moves a gain


class _GainEditor(QWidget):
    """A 0..1 gain as a slider and a spin box kept in step."""

    changed = Signal(float)

    def __init__(self, value: float) -> None:
        super().__init__()
        # The gains drive the robot's assistance and the stimulation live: the slider never jumps (at
        # most 0.05 per action); a far value is typed into the spin box and applies on Enter.
        self.slider = StepSlider(GAIN_MAX_STEP)
        self.slider.setRange(0, 100)
        self.spin = QDoubleSpinBox()
        self.spin.setRange(0.0, 1.0)
        self.spin.setSingleStep(0.05)
        self.spin.setDecimals(2)
        self.spin.setKeyboardTracking(False)
        lay = QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.slider, 1)
        lay.addWidget(self.spin)
        self.set_value(value)
        self.slider.valueChanged.connect(lambda v: self._from(v / 100.0))
        self.spin.valueChanged.connect(self._from)

    def set_value(self, value: float) -> None:
        for w in (self.slider, self.spin):
            w.blockSignals(True)
        self.slider.setValue(round(value * 100))
        self.spin.setValue(value)
        for w in (self.slider, self.spin):
            w.blockSignals(False)

    def value(self) -> float:
        return self.spin.value()

    def _from(self, value: float) -> None:
        self.set_value(value)
        self.changed.emit(value)


class AssistancePanel(QWidget):
    config_changed = Signal(object)  # AssistanceConfig

    def __init__(self, manager: Any, refresh_hz: float = 10.0, parent: QWidget | None = None, *,
                 qt_bus: QtBus | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Assistance")
        self.manager = manager
        self.qt_bus = qt_bus
        controller = self.controller
        self.config: AssistanceConfig = (controller.config if controller is not None
                                         else manager.config.assistance)
        safety = getattr(manager.config, "safety", None)
        limits = {
            "k_m_stiffness_n_m": safety.robot.max_stiffness_n_m if safety else 10000.0,
            "k_a_admittance_m_s_n": 1.0,
            "k_t_assistive_n_m": safety.robot.max_stiffness_n_m if safety else 10000.0,
            "fes_pulse_width_us": safety.fes.max_pulse_width_us if safety else 500.0,
        }

        gains = QGroupBox("Assistance split  (a_r = k_r·α,  a_f = k_f·α)")
        gf = QFormLayout(gains)
        self.k_r = _GainEditor(self.config.k_r)
        self.k_f = _GainEditor(self.config.k_f)
        gf.addRow("k_r  robot share:", self.k_r)
        gf.addRow("k_f  FES share:", self.k_f)
        self.k_r.changed.connect(lambda _v: self._apply())
        self.k_f.changed.connect(lambda _v: self._apply())

        model = QGroupBox("Patient model")
        mf = QFormLayout(model)
        self.clinical_score = QSpinBox()
        lo, hi, name = self._score_range()
        self.clinical_score.setRange(NOT_SET, hi)
        self.clinical_score.setSpecialValueText("not set")
        self.clinical_score.setToolTip(f"{name}, {lo}..{hi}; 'not set' lets the model use its default")
        pm = self._pm_driver()
        current = getattr(pm, "clinical_score", None) if pm is not None else None
        self.clinical_score.setValue(NOT_SET if current is None else int(current))
        self.clinical_score.valueChanged.connect(self._score_changed)
        mf.addRow(f"Clinical score ({name}):", self.clinical_score)

        maps = QGroupBox("Therapist maps  (level 0 → at 0,  level 1 → at 1)")
        grid = QGridLayout(maps)
        grid.addWidget(QLabel("at 0"), 0, 1)
        grid.addWidget(QLabel("at 1"), 0, 2)
        self.map_spins: dict[str, tuple[QDoubleSpinBox, QDoubleSpinBox]] = {}
        for row, (key, label, unit, decimals, step) in enumerate(MAPS, start=1):
            m: AssistanceMap = getattr(self.config, key)
            pair = []
            for col, value in ((1, m.at_zero), (2, m.at_one)):
                spin = QDoubleSpinBox()
                spin.setDecimals(decimals)
                spin.setSingleStep(step)
                spin.setRange(0.0, limits[key])
                spin.setSuffix(f" {unit}")
                spin.setValue(value)
                spin.setKeyboardTracking(False)  # typed values apply on Enter, not digit by digit
                spin.valueChanged.connect(lambda _v: self._apply())
                grid.addWidget(spin, row, col)
                pair.append(spin)
            grid.addWidget(QLabel(label), row, 0)
            self.map_spins[key] = (pair[0], pair[1])

        live = QGroupBox("Now")
        lf = QFormLayout(live)
        self.live: dict[str, QLabel] = {}
        for key, label in (("alpha", "α"), ("a_r", "a_r"), ("a_f", "a_f"), ("robot", "Robot (k_m, k_a, k_t)"),
                           ("fes", "FES pulse width"), ("status", "Status")):
            self.live[key] = QLabel("–")
            lf.addRow(f"{label}:", self.live[key])

        layout = QVBoxLayout(self)
        supervisor = getattr(manager, "supervisor", None)
        if supervisor is not None:  # the run holding the robot keeps its gains (one owner during a run, #36)
            from app.ui.held_by import HeldByLabel

            self.held_by = HeldByLabel(supervisor, "robot", what="it keeps its own gains: the split below does not "
                                                                  "reach the robot until the run ends")
            layout.addWidget(self.held_by)
        for box in (gains, model, maps, live):
            layout.addWidget(box)
        layout.addStretch(1)
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._tick)
        self.timer.start(int(1000 / refresh_hz))
        self.refresh()

    # ------------------------------------------------------------------ wiring
    @property
    def controller(self) -> Any:
        return getattr(self.manager, "assistance", None)

    def _pm_driver(self) -> Any:
        try:
            return self.manager.driver(streams.PATIENT_MODEL)
        except Exception:
            return None

    def _score_range(self) -> tuple[int, int, str]:
        try:
            from app.devices.sim.patient_model.decision_tree import load_tree_config

            c = load_tree_config()
            return int(c.scoreMin), int(c.scoreMax), c.scoreName.split(",")[0]
        except ValueError:
            return 0, 254, "clinical score"

    def edited_config(self) -> AssistanceConfig:
        maps = {key: AssistanceMap(a.value(), b.value()) for key, (a, b) in self.map_spins.items()}
        return replace(self.config, k_r=self.k_r.value(), k_f=self.k_f.value(), **maps)

    def _apply(self) -> None:
        self.config = self.edited_config()
        controller = self.controller
        if controller is not None:
            controller.set_config(self.config)
        self.config_changed.emit(self.config)
        self.refresh()

    def _score_changed(self, value: int) -> None:
        pm = self._pm_driver()
        if pm is not None:
            pm.clinical_score = None if value == NOT_SET else value

    # ------------------------------------------------------------------ display
    def _tick(self) -> None:
        """The timer's slot: the held-back change always goes out; the display only while seen."""
        if on_screen(self):
            self.refresh()
            return
        controller = self.controller
        if controller is not None:
            controller.flush()  # a change held back by the rate limit goes out even if α stops

    def showEvent(self, event: Any) -> None:
        super().showEvent(event)
        self.refresh()  # catch up at once on what was skipped while hidden

    def refresh(self) -> None:
        controller = self.controller
        if controller is not None:
            controller.flush()  # a change held back by the rate limit goes out even if α stops
            alpha = controller.alpha
            targets = controller.targets
            self.live["alpha"].setText(_fmt(alpha))
            self.live["a_r"].setText(_fmt(targets.a_r if targets else None))
            self.live["a_f"].setText(_fmt(targets.a_f if targets else None))
            robot = controller.applied_robot
            self.live["robot"].setText("not applied (k_r = 0 or no α yet)" if robot is None else
                                       f"{robot[0]:.0f} N/m, {robot[1]:.4f} m/(s·N), {robot[2]:.0f} N/m")
            pw = controller.applied_pulse_width_us
            self.live["fes"].setText("–" if pw is None else f"{pw:.0f} µs")
            err = controller.last_error
            self.live["status"].setText(f"active; last refusal: {err}" if err else "active")
            return
        self.live["status"].setText("assistance split not active (the manager has no controller)")
        s = self._model_sample() if self._pm_driver() is not None else None
        if s is not None:
            self.live["alpha"].setText(_fmt(s.alpha))
            self.live["a_r"].setText(_fmt(self.config.k_r * s.alpha))
            self.live["a_f"].setText(_fmt(self.config.k_f * s.alpha))

    def _model_sample(self) -> Any:
        """The patient model's latest sample on the bus (None before the first, or without a bus)."""
        bus = self.qt_bus.bus if self.qt_bus is not None else getattr(self.manager, "bus", None)
        return bus.latest(streams.PATIENT_MODEL_MAIN) if bus is not None else None


def _fmt(x: float | None) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:+.3f}"
