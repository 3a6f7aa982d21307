"""The assistance split (D2.2 Fig. 2) and its live controller, with recording fakes."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.core.config import AssistanceConfig, AssistanceMap, SafetyConfig
from app.safety.assistance import AssistanceController, AssistanceSplit
from app.safety.supervisor import SafetySupervisor

CFG = AssistanceConfig(
    k_r=1.0, k_f=1.0,
    k_m_stiffness_n_m=AssistanceMap(200.0, 1200.0),
    k_a_admittance_m_s_n=AssistanceMap(0.002, 0.01),
    k_t_assistive_n_m=AssistanceMap(0.0, 150.0),
    fes_pulse_width_us=AssistanceMap(100.0, 300.0),
    max_update_rate_hz=10.0,
)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Recorder:
    def __init__(self) -> None:
        self.robot: list[tuple[float, float, float]] = []
        self.fes: list[float] = []

    def apply_robot(self, k_m: float, k_a: float, k_t: float) -> None:
        self.robot.append((k_m, k_a, k_t))

    def apply_fes(self, pw: float) -> None:
        self.fes.append(pw)


def controller(config: AssistanceConfig = CFG, supervisor: SafetySupervisor | None = None):
    rec, clock = Recorder(), Clock()
    ctl = AssistanceController(config, rec.apply_robot, rec.apply_fes, supervisor, clock=clock)
    return ctl, rec, clock


# ------------------------------------------------------------------ the pure split


def test_full_assistance_gives_the_top_of_every_map() -> None:
    t = AssistanceSplit(CFG).compute(1.0, 1.0, 1.0)
    assert (t.a_r, t.a_f) == (1.0, 1.0)
    assert (t.k_m, t.k_a, t.k_t) == (1200.0, 0.01, 150.0)
    assert t.pulse_width_us == 300.0


def test_neutral_gives_the_bottom_of_every_map() -> None:
    t = AssistanceSplit(CFG).compute(0.0, 1.0, 1.0)
    assert (t.k_m, t.k_a, t.k_t, t.pulse_width_us) == (200.0, 0.002, 0.0, 100.0)


def test_split_scales_alpha_by_the_gains() -> None:
    t = AssistanceSplit(CFG).compute(0.8, 0.5, 0.25)
    assert t.a_r == pytest.approx(0.4)
    assert t.a_f == pytest.approx(0.2)
    assert t.k_m == pytest.approx(200 + 0.4 * 1000)
    assert t.k_t == pytest.approx(0.4 * 150)
    assert t.pulse_width_us == pytest.approx(100 + 0.2 * 200)


def test_resistance_stiffens_the_vsa_with_admittance_and_assistive_gain_at_their_floor() -> None:
    t = AssistanceSplit(CFG).compute(-0.5, 1.0, 1.0)
    assert t.a_r == -0.5
    assert t.k_m == pytest.approx(700.0)
    assert t.k_a == 0.002
    assert t.k_t == 0.0
    assert t.pulse_width_us == 100.0  # FES only assists


def test_k_f_zero_keeps_the_pulse_width_at_its_floor_for_any_alpha() -> None:
    split = AssistanceSplit(CFG)
    assert {split.compute(a, 1.0, 0.0).pulse_width_us for a in (-1.0, -0.3, 0.0, 0.5, 1.0)} == {100.0}


def test_nan_is_refused() -> None:
    with pytest.raises(ValueError, match="NaN"):
        AssistanceSplit(CFG).compute(math.nan, 1.0, 1.0)


@settings(max_examples=200, deadline=None)
@given(alpha=st.floats(-1, 1), k_r=st.floats(0, 1), k_f=st.floats(0, 1))
def test_targets_stay_inside_the_therapist_maps(alpha: float, k_r: float, k_f: float) -> None:
    t = AssistanceSplit(CFG).compute(alpha, k_r, k_f)
    assert 200.0 <= t.k_m <= 1200.0
    assert 0.002 <= t.k_a <= 0.01
    assert 0.0 <= t.k_t <= 150.0
    assert 100.0 <= t.pulse_width_us <= 300.0
    assert abs(t.a_r) <= k_r + 1e-12 and abs(t.a_f) <= k_f + 1e-12


@settings(max_examples=200, deadline=None)
@given(a=st.floats(-1, 1), b=st.floats(-1, 1))
def test_more_assistance_never_lowers_the_assistive_parameters(a: float, b: float) -> None:
    lo, hi = sorted((a, b))
    split = AssistanceSplit(CFG)
    t_lo, t_hi = split.compute(lo, 1.0, 1.0), split.compute(hi, 1.0, 1.0)
    assert t_hi.k_a >= t_lo.k_a and t_hi.k_t >= t_lo.k_t and t_hi.pulse_width_us >= t_lo.pulse_width_us


# ------------------------------------------------------------------ the controller


def test_alpha_one_with_k_r_one_applies_the_top_of_the_maps() -> None:
    ctl, rec, _clock = controller()
    ctl.update_alpha(1.0)
    assert rec.robot == [(1200.0, 0.01, 150.0)]
    assert rec.fes == [300.0]


def test_k_r_zero_never_touches_the_robot() -> None:
    ctl, rec, clock = controller()
    ctl.set_gains(0.0, 1.0)
    for i in range(50):
        clock.t += 0.2
        ctl.update_alpha(math.sin(i / 3.0))
    assert rec.robot == []
    assert len(rec.fes) > 5  # the FES side still follows α


def test_k_f_zero_holds_the_pulse_width_at_its_floor() -> None:
    ctl, rec, clock = controller()
    ctl.set_gains(1.0, 0.0)
    for a in (0.2, 0.9, -0.7, 1.0):
        clock.t += 0.2
        ctl.update_alpha(a)
    assert rec.fes == [100.0]  # applied once, never moved
    assert len(rec.robot) == 4


def test_updates_are_rate_limited_and_the_last_one_is_not_lost() -> None:
    ctl, rec, clock = controller()
    for i in range(100):  # α at 100 Hz for 1 s
        clock.t += 0.01
        ctl.update_alpha(i / 100.0)
    assert 9 <= len(rec.robot) <= 11  # max_update_rate_hz = 10
    clock.t += 0.2
    assert ctl.flush()
    assert rec.robot[-1][2] == pytest.approx(0.99 * 150.0)


def test_an_unchanged_alpha_is_not_sent_again() -> None:
    ctl, rec, clock = controller()
    for _ in range(20):
        clock.t += 0.5
        ctl.update_alpha(0.5)
    assert len(rec.robot) == 1 and len(rec.fes) == 1


def test_alpha_passes_through_the_supervisor_clamp() -> None:
    events: list[tuple[str, dict]] = []
    sup = SafetySupervisor(SafetyConfig())
    sup.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    ctl, rec, _clock = controller(supervisor=sup)
    ctl.update_alpha(1.7)
    assert ctl.alpha == 1.0
    assert rec.robot == [(1200.0, 0.01, 150.0)]
    assert any(kind == "clamped" for kind, _ in events)


def test_nothing_is_applied_after_an_emergency_stop() -> None:
    sup = SafetySupervisor(SafetyConfig())
    ctl, rec, _clock = controller(supervisor=sup)
    sup.emergency_stop("test")
    ctl.update_alpha(0.8)
    assert rec.robot == [] and rec.fes == []


def test_a_refused_command_is_counted_and_the_loop_goes_on() -> None:
    clock = Clock()

    def refuse(*_args: float) -> None:
        raise RuntimeError("stiffness above the limit")

    fes: list[float] = []
    ctl = AssistanceController(CFG, refuse, fes.append, clock=clock)
    ctl.update_alpha(0.5)
    assert ctl.errors == 1 and "stiffness" in ctl.last_error
    assert fes == [200.0]


def test_new_maps_take_effect() -> None:
    ctl, rec, clock = controller()
    ctl.update_alpha(1.0)
    clock.t += 0.2  # past the rate limit (10 Hz), α still fresh
    ctl.set_config(AssistanceConfig(k_r=1.0, k_f=1.0, k_m_stiffness_n_m=AssistanceMap(100.0, 800.0),
                                    k_a_admittance_m_s_n=CFG.k_a_admittance_m_s_n,
                                    k_t_assistive_n_m=CFG.k_t_assistive_n_m,
                                    fes_pulse_width_us=AssistanceMap(100.0, 250.0)))
    assert rec.robot[-1] == (800.0, 0.01, 150.0)
    assert rec.fes[-1] == 250.0


def test_a_stale_alpha_is_never_applied() -> None:
    ctl, rec, clock = controller()
    ctl.update_alpha(0.2)
    sent = len(rec.robot)
    clock.t += 1.0  # the model went quiet
    ctl.set_gains(1.0, 1.0)  # the therapist moves a gain meanwhile
    assert not ctl.flush()
    assert len(rec.robot) == sent
    ctl.update_alpha(0.9)  # α flows again: applied at once
    assert len(rec.robot) == sent + 1


def test_gains_outside_zero_one_are_refused() -> None:
    ctl, _rec, _clock = controller()
    with pytest.raises(ValueError, match="k_r"):
        ctl.set_gains(1.5, 0.5)


# ------------------------------------------------------------------ the panel


class _PmDriver:
    clinical_score: int | None = None

    def latest(self, stream: str) -> None:
        return None


class _Manager:
    def __init__(self, controller: AssistanceController | None) -> None:
        from app.core.config import AppConfig

        self.config = AppConfig()
        self.assistance = controller
        self.pm = _PmDriver()

    def driver(self, name: str) -> _PmDriver | None:
        return self.pm if name == "patient_model" else None


def test_panel_edits_reach_the_controller_and_the_model(qtbot) -> None:
    from app.ui.assistance_panel import AssistancePanel

    ctl, rec, clock = controller()
    manager = _Manager(ctl)
    panel = AssistancePanel(manager)
    qtbot.addWidget(panel)
    ctl.update_alpha(1.0)
    assert rec.robot[-1] == (1200.0, 0.01, 150.0)

    clock.t += 0.15  # past the 10 Hz rate limit, with α still fresh
    panel.k_r.spin.setValue(0.5)
    assert ctl.k_r == 0.5
    assert rec.robot[-1][0] == pytest.approx(700.0)

    clock.t += 0.15  # past the 10 Hz rate limit, with α still fresh
    panel.map_spins["fes_pulse_width_us"][1].setValue(250.0)
    assert rec.fes[-1] == 250.0  # k_f = 1, α = 1: the top of the edited map
    panel.clinical_score.setValue(20)
    assert manager.pm.clinical_score == 20
    panel.clinical_score.setValue(-1)
    assert manager.pm.clinical_score is None
    panel.refresh()
    assert panel.live["alpha"].text() == "+1.000"


def test_panel_caps_the_maps_at_the_safety_limits(qtbot) -> None:
    from app.ui.assistance_panel import AssistancePanel

    manager = _Manager(None)
    panel = AssistancePanel(manager)
    qtbot.addWidget(panel)
    spin = panel.map_spins["k_m_stiffness_n_m"][1]
    spin.setValue(1e6)
    assert spin.value() == manager.config.safety.robot.max_stiffness_n_m
    assert "not active" in panel.live["status"].text()


def test_a_click_anywhere_on_a_gain_slider_changes_it_by_at_most_one_step(qtbot) -> None:
    """Issue #19: the gains drive the robot and the stimulation live; a click on a slider's groove
    page-jumped, a drag could go anywhere."""
    from PySide6.QtCore import QPoint, Qt

    from app.ui.assistance_panel import GAIN_MAX_STEP, AssistancePanel

    manager = _Manager(None)
    panel = AssistancePanel(manager)
    qtbot.addWidget(panel)
    panel.resize(600, 500)
    panel.show()
    qtbot.waitExposed(panel)
    slider = panel.k_f.slider
    for x in range(2, slider.width() - 2, max(1, slider.width() // 15)):
        before = panel.k_f.value()
        qtbot.mouseClick(slider, Qt.MouseButton.LeftButton, pos=QPoint(x, slider.height() // 2))
        assert abs(panel.k_f.value() - before) <= 0.01 + 1e-9, f"click at x={x}: {before} -> {panel.k_f.value()}"
    handle = slider._handle_rect().center()
    before = slider.value()
    qtbot.mousePress(slider, Qt.MouseButton.LeftButton, pos=handle)
    qtbot.mouseMove(slider, QPoint(slider.width() - 1 if before < 50 else 1, handle.y()))  # a flick to the end
    qtbot.mouseRelease(slider, Qt.MouseButton.LeftButton, pos=QPoint(slider.width() - 1, handle.y()))
    assert 0 < abs(slider.value() - before) <= GAIN_MAX_STEP


# ------------------------------------------------------------------ the therapy thread (app/manager.py)
def _therapy(bus=None):
    from app.core.bus import StreamBus
    from app.manager import TherapyThread

    calls: list[tuple[str, object]] = []
    therapy = TherapyThread(bus or StreamBus(), lambda a: calls.append(("alpha", a)),
                            lambda why: calls.append(("lost", why)), lambda t: calls.append(("target", t)))
    return therapy, calls


def _item(stream: str, **fields: float):
    from types import SimpleNamespace

    from app.core.bus import SampleItem

    return SampleItem(stream, 0.0, SimpleNamespace(**fields), 0.0)


def test_a_therapy_pass_applies_the_newest_alpha_and_target_and_never_one_from_before_a_loss() -> None:
    from app.core import streams
    from app.core.journal import device_event

    therapy, calls = _therapy()
    lost = device_event(streams.PATIENT_MODEL, "silent", "", 0.0)
    other = device_event(streams.PHYSIO, "disconnected", "", 0.0)
    therapy.handle([_item(streams.PATIENT_MODEL_MAIN, alpha=0.1), _item(streams.VR_MAIN, targetPos=0.1),
                    _item(streams.PATIENT_MODEL_MAIN, alpha=0.2), _item(streams.VR_MAIN, targetPos=0.4), other])
    assert calls == [("alpha", 0.2), ("target", 0.4)], "a backlog is not replayed: the newest of each"
    calls.clear()
    therapy.handle([_item(streams.PATIENT_MODEL_MAIN, alpha=0.3), lost, _item(streams.VR_MAIN, targetPos=math.nan)])
    assert calls == [("lost", "silent")], "an α from before the loss is stale; a NaN target is no target"
    calls.clear()
    therapy.handle([lost, _item(streams.PATIENT_MODEL_MAIN, alpha=0.5)])
    assert calls == [("lost", "silent"), ("alpha", 0.5)], "an α after the loss (the model is back) counts"


def test_the_therapy_thread_takes_alpha_from_the_bus_off_the_driver_thread_and_stops(qtbot) -> None:
    import threading

    from app.core import streams
    from app.core.bus import StreamBus
    from app.devices.patient_model import PATIENT_MODEL_STREAM

    bus = StreamBus()
    bus.declare([PATIENT_MODEL_STREAM])
    therapy, calls = _therapy(bus)
    seen_on: list[str] = []
    therapy.on_alpha = lambda a: (calls.append(("alpha", a)), seen_on.append(threading.current_thread().name))
    therapy.start()
    try:
        assert therapy.running and any(t.name == "therapy" for t in threading.enumerate())
        bus.publish(streams.PATIENT_MODEL_MAIN, 1.0, _item(streams.PATIENT_MODEL_MAIN, alpha=0.7).sample)
        qtbot.waitUntil(lambda: ("alpha", 0.7) in calls, timeout=2000)
    finally:
        assert therapy.stop(2.0)
    assert seen_on == ["therapy"]
    assert not therapy.running and not any(t.name == "therapy" for t in threading.enumerate())
    assert all(s.name != "therapy" for s in bus.subscriptions()), "its subscription is closed"


def test_the_stiffness_move_of_the_assistance_is_the_constants_tables() -> None:
    """setStiffness(k_m, maxVel, maxAcc, execTime) from the split: the motion profile is one fact, in the table
    (issue #29; it was the literal (0.05, 0.2, 0.0) in the manager). Fails when a copy comes back."""
    import ast
    from pathlib import Path

    from app.manager import STIFFNESS_MOVE
    from app.wire.linarm_constants import K

    velocity, acceleration, exec_time = STIFFNESS_MOVE
    assert (velocity, acceleration) == (K["PRETENSION_MOVE_VELOCITY"], K["PRETENSION_MOVE_ACCELERATION"])
    assert exec_time == 0.0  # planned from the velocity and acceleration
    # what the controller's setter accepts under its default limits (firmware: Linarm::plan)
    assert K["MOVE_LIMIT_MIN"] <= velocity <= K["MAX_VELOCITY"]
    assert K["MOVE_LIMIT_MIN"] <= acceleration <= K["MAX_ACCELERATION"]
    copies = []
    for path in sorted((Path(__file__).resolve().parents[1] / "app").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            items = node.elts if isinstance(node, ast.Tuple) else node.args if isinstance(node, ast.Call) else []
            names = [i for i, e in enumerate(items)
                     if isinstance(e, ast.Constant) and e.value in ("setStiffness", "moveDeltaTo")]
            for i in names:
                literals = [e for e in items[i + 2:] if isinstance(e, ast.Constant) and isinstance(e.value, float)]
                if literals:
                    copies.append(f"{path.name}:{node.lineno} {ast.unparse(node)}")
    assert not copies, f"the pretension move (setStiffness, moveDeltaTo) typed again, not read from the table: {copies}"
