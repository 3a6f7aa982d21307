"""Acceptance 1 (robot side): whatever the GUI, a script or the patient model asks, nothing outside
``config.safety.robot`` reaches the LINarm's wire.

One manager for the module: the real simulated LINarm (controller core behind a pty) homed once, ON; the
patient-model link in ``external`` mode with this test's own UDP socket as the model, so α — valid, out of
range, NaN, inf, garbage — arrives through the real port. Hypothesis drives each path with values inside
and outside the limits. After every example an independent checker decodes every frame the simulator
received (as the firmware's CmdMessenger 4.2.0 receive path does) and re-applies the limits written out
below — it never asks the supervisor. A call whose values break a rule must have been refused by the
supervisor with a reason (GUI: the panel's outcome; script: CommandRefused).

Timed moves (maxVel/maxAcc and the acceleration a move time implies) and setHomeParameter are drawn by
their own tests with a wider argument range (they were gaps in the supervisor, now closed).
"""

from __future__ import annotations

import logging
import math
import re
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import event as hypothesis_event
from hypothesis import strategies as st
from hypothesis.control import currently_in_test_context
from PySide6.QtWidgets import QApplication

from app.core import streams
from app.core.bus import SampleItem, Subscription
from app.core.config import AppConfig, AssistanceMap, RobotLimits, UdpEndpoint
from app.devices import linarm, patient_model
from app.manager import LinarmppManager
from app.scripting.runner import ScriptRunner
from app.ui.linarm_panel import LinarmPanel
from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import ArduinoReceiver
from app.wire.linarm_protocol import ControlMode, ControlState, HomeState
from app.wire.physio_codec import crc16_ccitt
from app.wire.udp_frames import PATIENT_MODEL_REPLY_LAYOUT, PatientModelReply, encode_patient_model_reply
from tests.waits import KERNEL_START_S

pytestmark = pytest.mark.sim_homed  # a homed LINarm from the start: the homing is tested on its own

PROFILE = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                   phases=(Phase.explicit, Phase.generate),  # no shrinking: each example drives a real link
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
GAP_PROFILE = settings(PROFILE, max_examples=25)
REL_TOL = 1e-6  # the wire carries float32: a value at a limit may arrive a few ulps above it
HOMING_TIMEOUT_S = 25.0

# ── the independent checker: the robot limits, written out again ─────────────────────────────────────

MOVES = {"moveCentreTo": "targetPos", "moveDeltaTo": "targetDeltaPos", "setStiffness": "stiffness"}
IGNORED_ON_WIRE = {"identify", "heartbeat", "startDataStream", "stopDataStream", "getState"}


def _le(value: float, limit: float) -> bool:
    return value <= limit + REL_TOL * max(1.0, abs(limit))


def _ge(value: float, limit: float) -> bool:
    return value >= limit - REL_TOL * max(1.0, abs(limit))


def _in(value: float, lo: float, hi: float) -> bool:
    return _ge(value, lo) and _le(value, hi)


def rule_breaks(name: str, a: dict[str, Any], lim: RobotLimits) -> list[str]:
    """Why ``name(a)`` is outside the robot limits ([] when it is within all of them). Only the values."""
    out = [f"{k}={v!r} is not finite" for k, v in a.items() if isinstance(v, float) and not math.isfinite(v)]
    if out:
        return out
    pos = (lim.position_min_m, lim.position_max_m)
    vmax, amax, fmax = lim.max_velocity_m_s, lim.max_acceleration_m_s2, lim.max_interaction_force_n
    if name in MOVES:
        key = MOVES[name]
        lo, hi = {"targetPos": pos, "targetDeltaPos": (0.0, lim.max_delta_m),
                  "stiffness": (0.0, lim.max_stiffness_n_m)}[key]
        if not _in(a[key], lo, hi):
            out.append(f"{key} {a[key]:.6g} outside {lo:g}..{hi:g}")
        if not _le(a["maxVel"], vmax):
            out.append(f"maxVel {a['maxVel']:.6g} > {vmax:g} m/s")
        if not _le(a["maxAcc"], amax):
            out.append(f"maxAcc {a['maxAcc']:.6g} > {amax:g} m/s²")
        if a["execTime"] < 0:
            out.append(f"execTime {a['execTime']:.6g} < 0")
        elif a["execTime"] == 0 and (a["maxVel"] <= 0 or a["maxAcc"] <= 0):
            out.append("an untimed move needs a positive maxVel and maxAcc")
    elif name in ("setCentreVelocity", "setDeltaVelocity"):
        v = next(iter(a.values()))
        if not _le(abs(v), vmax):
            out.append(f"{name} |{v:.6g}| > {vmax:g} m/s")
    elif name == "setAssistanceTargetPos":
        if not _in(a["Apos"], *pos):
            out.append(f"Apos {a['Apos']:.6g} outside {pos}")
    elif name == "setAdmittanceParameter":
        if a["Ka"] < 0 or not _le(a["Ka"] * fmax, vmax):
            out.append(f"Ka {a['Ka']:.6g}: Ka·Fmax = {a['Ka'] * fmax:.4g} m/s, limit {vmax:g}")
    elif name == "setAssistanceParameter":
        if not _in(a["Kt"], 0.0, lim.max_stiffness_n_m):
            out.append(f"Kt {a['Kt']:.6g} outside 0..{lim.max_stiffness_n_m:g}")
    elif name == "setPosLimit":
        if not (a["minPos"] < a["maxPos"] and _in(a["minPos"], *pos) and _in(a["maxPos"], *pos)):
            out.append(f"position limits {a['minPos']:.6g}..{a['maxPos']:.6g} not inside {pos}")
    elif name == "setMaxVelocity":
        if not (a["maxVel"] > 0 and _le(a["maxVel"], vmax)):
            out.append(f"maxVel {a['maxVel']:.6g} not in (0, {vmax:g}]")
    elif name == "setMaxAcceleration":
        if not (a["maxAcc"] > 0 and _le(a["maxAcc"], amax)):
            out.append(f"maxAcc {a['maxAcc']:.6g} not in (0, {amax:g}]")
    elif name == "setMaxForce":
        if not (a["maxForce"] > 0 and _le(a["maxForce"], fmax)):
            out.append(f"maxForce {a['maxForce']:.6g} not in (0, {fmax:g}]")
    elif name == "setVirtualVsaSpringDisplacement":
        if not _le(abs(a["disp"]), lim.max_delta_m):
            out.append(f"disp {a['disp']:.6g} beyond ±{lim.max_delta_m:g}")
    elif name == "disableEndstrokes":
        if a["disable"] and not lim.allow_disable_endstrokes:
            out.append("endstrokes disabled")
    elif name == "setHomeParameter":
        if not _in(a["homeCentre"], *pos):
            out.append(f"homeCentre {a['homeCentre']:.6g} outside {pos}")
        if not _in(a["homeDelta"], 0.0, lim.max_delta_m):
            out.append(f"homeDelta {a['homeDelta']:.6g} outside 0..{lim.max_delta_m:g}")
        if not (a["homingVelocity"] > 0 and _le(a["homingVelocity"], vmax)):
            out.append(f"homingVelocity {a['homingVelocity']:.6g} not in (0, {vmax:g}]")
    return out


def timed_move_breaks(name: str, a: dict[str, Any], lim: RobotLimits, starts: list[float]) -> list[str]:
    """A timed move (execTime > 0) of the centre or delta: its peak speed and acceleration (cycloid, the
    steeper profile: v = 2D/T, a = 2πD/T²) from the *nearest* of ``starts`` (the positions measured just
    before the frame) — a lower bound, so a break here is a break whatever the supervisor saw."""
    t_exec = a.get("execTime", 0.0)
    if name not in ("moveCentreTo", "moveDeltaTo") or not t_exec > 0 or not starts:
        return []
    target = a[MOVES[name]]
    dist = min(abs(target - s) for s in starts)
    v_pk, a_pk = 2 * dist / t_exec, 2 * math.pi * dist / t_exec**2
    out = []
    if not _le(v_pk, lim.max_velocity_m_s):
        out.append(f"timed {name}: {dist:.4f} m in {t_exec:.3g} s peaks at {v_pk:.3f} m/s")
    if not _le(a_pk, lim.max_acceleration_m_s2):
        out.append(f"timed {name}: {dist:.4f} m in {t_exec:.3g} s accelerates at {a_pk:.3f} m/s²")
    return out


# ── the rig ───────────────────────────────────────────────────────────────────────────────────────────


@dataclass(repr=False)
class Rig:
    manager: LinarmppManager
    driver: linarm.LinarmDriver
    sim: Any
    panel: LinarmPanel
    model_socket: socket.socket
    model_port: int  # where the manager listens for the model's replies
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    vsa: deque = field(default_factory=lambda: deque(maxlen=4000))  # (t, centre, delta)
    vsa_queue: Subscription | None = None  # the LINarm's VSA samples on the bus, pulled into ``vsa``
    receiver: ArduinoReceiver = field(default_factory=ArduinoReceiver)
    cursor: int = 0
    wire_frames: dict[str, int] = field(default_factory=dict)
    reply_seq: int = 0
    runner: ScriptRunner | None = None  # the test's script runner (see ``script_runner``), closed after the test

    def script_runner(self) -> ScriptRunner:
        """One runner for all of a test's examples, as the Script tab has one: each script still runs in a fresh
        kernel (the spare the runner keeps started ahead), so an example no longer waits for a cold kernel."""
        if self.runner is None:
            self.runner = ScriptRunner(self.manager, output=lambda _s, _t: None, home_first=False)
        return self.runner

    def close_runner(self) -> None:
        runner, self.runner = self.runner, None
        if runner is not None:
            runner.close()

    def __repr__(self) -> str:  # hypothesis prints the arguments of a failing example
        return f"<Rig: {len(self.sim.host_bytes_log)} host writes, {len(self.events)} events>"

    def _repr_pretty_(self, printer: Any, cycle: bool) -> None:
        printer.text(repr(self))

    @property
    def limits(self) -> RobotLimits:
        return self.manager.config.safety.robot

    def wire_breaks(self, timed: bool = True) -> list[str]:
        """Decode everything the simulator received since the last call and check every command."""
        log = list(self.sim.host_bytes_log)
        new, self.cursor = log[self.cursor:], len(log)
        found: list[str] = []
        for t, data in new:
            for msg in self.receiver.feed(data):
                if not msg.id_arg_ok:
                    continue  # the lone ';' the driver sends to flush the controller's parser
                try:
                    cmd = proto.read_host_message(msg)
                except proto.CommandRejected as exc:
                    found.append(f"{t:.3f}: a frame the controller cannot read reached the wire: {exc}")
                    continue
                if cmd.name in IGNORED_ON_WIRE:
                    continue
                self.wire_frames[cmd.name] = self.wire_frames.get(cmd.name, 0) + 1
                problems = rule_breaks(cmd.name, cmd.args, self.limits)
                if timed:
                    self.pull_vsa()
                    window = [s for s in list(self.vsa) if t - 0.3 <= s[0] <= t]
                    starts = [s[1] if cmd.name == "moveCentreTo" else s[2] for s in window]
                    problems += timed_move_breaks(cmd.name, cmd.args, self.limits, starts)
                found += [f"{t:.3f}: {cmd.name}{cmd.args} on the wire: {p}" for p in problems]
        return found

    def pull_vsa(self) -> None:
        if self.vsa_queue is not None:
            self.vsa.extend((i.t, i.sample.equilibriumPos, i.sample.delta)
                            for i in self.vsa_queue.drain() if isinstance(i, SampleItem))

    def events_since(self, n: int, kind: str, source: str) -> list[dict[str, Any]]:
        return [d for k, d in self.events[n:] if k == kind and d.get("source") == source]

    def send_model_reply(self, alpha: float, *, raw: bytes | None = None) -> None:
        """A reply from 'the model' (this socket is the peer the driver expects). ``alpha`` is packed as
        the float32 it is, with a valid CRC, even when no encoder would produce it."""
        if raw is None:
            self.reply_seq = (self.reply_seq + 1) & 0xFFFF
            good = encode_patient_model_reply(PatientModelReply(self.reply_seq, 0, 0.0, 0.5, 0.5, 0.5, -1.0, 1.0))
            fmt = PATIENT_MODEL_REPLY_LAYOUT.struct_format
            values = list(struct.unpack(fmt, good))
            values[3] = alpha  # header, seq, ackSeq, alpha, ...
            body = struct.pack(fmt, *values)[:-2]
            raw = body + struct.pack("<H", crc16_ccitt(body))
        self.model_socket.sendto(raw, ("127.0.0.1", self.model_port))


def wait_for(predicate: Callable[[], Any], timeout: float = 3.0, what: str = "a condition") -> None:
    """Poll ``predicate`` while Qt events are processed (the panel collects its Futures on a timer)."""
    app = QApplication.instance()
    gate = threading.Event()
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        if app is not None:
            app.processEvents()
        gate.wait(0.003)


def ensure_on(rig: Rig, mode: ControlMode) -> None:
    """Back to a homed robot, ON, in ``mode``, whatever the last example left (error, IDLE, limits)."""
    d = rig.driver
    # An open STOP alarm (e.g. the controller's watchdog on a loaded machine) holds the robot IDLE until it is
    # acknowledged (#25): what Recover does first.
    sup = rig.manager.supervisor
    for alarm in sup.alarms():
        if not alarm.acknowledged:
            sup.acknowledge(alarm.ident, "test")
    state = d.latest("linarm.state")
    if state.errorState:
        d.command("resetError", source="test")
    if not state.initialized:
        d.command("setCtrlState", int(ControlState.HOME_CTRL_STATE), source="test")
        wait_for(lambda: d.latest("linarm.state").homeState == HomeState.HOME_DONE
                 and d.latest("linarm.state").initialized, HOMING_TIMEOUT_S, "homing")
    # The controller's own limits back to the configured ones (a drawn in-limit value may have narrowed them).
    lim = rig.limits
    d.command("setPosLimit", lim.position_min_m + 0.06, lim.position_max_m - 0.06, source="test")
    d.command("setMaxVelocity", lim.max_velocity_m_s, source="test")
    d.command("setMaxAcceleration", lim.max_acceleration_m_s2, source="test")
    d.command("setMaxForce", lim.max_interaction_force_n, source="test")
    d.command("setCtrlMode", int(mode), source="test")  # also clears any motion (a jog left running)
    d.command("setCtrlState", int(ControlState.ON_CTRL_STATE), source="test")
    wait_for(lambda: d.latest("linarm.state").controlState == ControlState.ON_CTRL_STATE
             and d.latest("linarm.state").controlMode == int(mode), 2.0, "ON in the mode")


@pytest.fixture(scope="module")
def rig(qapp) -> Iterator[Rig]:
    model = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    model.bind(("127.0.0.1", 0))
    listen = patient_model.free_udp_port()
    config = AppConfig()
    endpoint = UdpEndpoint(mode="external", listen_port=listen, peer_port=model.getsockname()[1])
    config = replace(config, devices=replace(config.devices, patient_model=endpoint))
    manager = LinarmppManager(config, factories={"linarm": linarm.create, "patient_model": patient_model.create})
    manager.start()
    driver = manager.driver("linarm")
    sim = manager.devices["linarm"].simulator
    sim.keep_host_log = True
    panel = LinarmPanel(manager)
    r = Rig(manager, driver, sim, panel, model, listen)
    manager.bus.listen("test", lambda record: r.events.append((record.kind, record.data)))

    class Warnings(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            r.warnings.append(record.getMessage())

    handler = Warnings(logging.WARNING)
    logging.getLogger("app.manager").addHandler(handler)
    r.vsa_queue = manager.bus.subscribe("test vsa", (streams.LINARM_VSA,), maxlen=4000)
    # α changes are applied at most max_update_rate_hz: the fastest allowed keeps the examples short.
    manager.assistance.set_config(replace(manager.assistance.config, max_update_rate_hz=100.0))
    try:
        wait_for(lambda: driver.connected and driver.latest("linarm.state") is not None, 5.0, "the LINarm")
        ensure_on(r, ControlMode.POS_REF_BY_ASSISTANCE)
        yield r
    finally:
        logging.getLogger("app.manager").removeHandler(handler)
        panel.close()
        panel.deleteLater()
        manager.shutdown()
        model.close()


@pytest.fixture(autouse=True)
def _runner_closed_after_the_test(rig: Rig) -> Iterator[None]:
    """No kernel process outlives its test (the spare included)."""
    yield
    rig.close_runner()


# ── strategies: values inside and outside the limits ─────────────────────────────────────────────────

SPECIAL = st.sampled_from([math.nan, math.inf, -math.inf, 1e39, -1e39])
LIM = RobotLimits()


def around(lo: float, hi: float, *exact: float) -> st.SearchStrategy[float]:
    """Mostly plausible values (in range, just out, far out), the limits themselves, now and then specials."""
    span = hi - lo
    return st.one_of(
        st.floats(lo, hi), st.floats(lo - span, hi + span), st.sampled_from([lo, hi, 0.0, *exact]),
        st.floats(-10 * abs(hi) - 1, 10 * abs(hi) + 1), SPECIAL,
    )


POS = around(LIM.position_min_m, LIM.position_max_m, 0.5)
DELTA = around(0.0, LIM.max_delta_m, -0.01)
STIFF = around(0.0, LIM.max_stiffness_n_m, 2000.5)
SPEED = around(0.0, LIM.max_velocity_m_s, 0.3000001, -0.3)
ACCEL = around(0.0, LIM.max_acceleration_m_s2, 1.0000001)
KA = around(0.0, LIM.max_velocity_m_s / LIM.max_interaction_force_n, 0.0051, -0.001)
FORCE = around(0.0, LIM.max_interaction_force_n, 60.5)
UNTIMED = st.just(0.0)
TIMED = st.one_of(st.floats(0.01, 20.0), st.sampled_from([0.05, 0.2, 0.7, 5.0, 1e6]))


def arg_strategies(timed: bool) -> dict[str, st.SearchStrategy[tuple]]:
    t = TIMED if timed else UNTIMED
    return {
        "moveCentreTo": st.tuples(POS, SPEED, ACCEL, t, st.just(False)),
        "moveDeltaTo": st.tuples(DELTA, SPEED, ACCEL, t, st.just(False)),
        "setStiffness": st.tuples(STIFF, SPEED, ACCEL, t),
        "setCentreVelocity": st.tuples(SPEED),
        "setDeltaVelocity": st.tuples(SPEED),
        "setAdmittanceParameter": st.tuples(KA),
        "setAssistanceParameter": st.tuples(STIFF),
        "setAssistanceTargetPos": st.tuples(POS),
        "setVirtualVsaSpringDisplacement": st.tuples(DELTA),
        "setPosLimit": st.tuples(POS, POS),
        "setMaxVelocity": st.tuples(SPEED),
        "setMaxAcceleration": st.tuples(ACCEL),
        "setMaxForce": st.tuples(FORCE),
        "disableEndstrokes": st.tuples(st.booleans()),
        "setHomeParameter": st.tuples(POS, DELTA, SPEED),
    }


# setHomeParameter and timed moves: the known gaps, drawn by test_known_gap_* only.
MAIN_COMMANDS = [n for n in arg_strategies(False) if n != "setHomeParameter"]
MAIN_ARGS = arg_strategies(False)
GAP_ARGS = arg_strategies(True)


@st.composite
def calls(draw: st.DrawFn, names: list[str], args: dict[str, st.SearchStrategy[tuple]],
          max_size: int = 4) -> list[tuple[str, tuple]]:
    chosen = draw(st.lists(st.sampled_from(names), min_size=1, max_size=max_size))
    return [(n, draw(args[n])) for n in chosen]


MODES = st.sampled_from([ControlMode.POS_REF_BY_TARGET_POS, ControlMode.POS_REF_BY_VEL,
                         ControlMode.POS_REF_BY_ASSISTANCE])


def event(text: str) -> None:
    """Hypothesis statistics (``--hypothesis-show-statistics``); the helpers also run outside @given."""
    if currently_in_test_context():
        hypothesis_event(text)


def named(name: str, values: tuple) -> dict[str, Any]:
    return {a.name: v for a, v in zip(proto.COMMANDS_BY_NAME[name].args, values, strict=True)}


# ── path (a): the GUI panel ───────────────────────────────────────────────────────────────────────────

REFUSED_GUI = re.compile(r"refused by the safety supervisor: .*refused: \S")


def gui_action(rig: Rig, name: str, values: tuple) -> tuple[str, tuple] | None:
    """Type ``values`` into the panel's inputs for ``name`` and press its button (hold/release for a jog).
    Returns what the panel actually sent (the inputs clamp and round what is typed), None if nothing."""
    panel = rig.panel
    if name in ("setCentreVelocity", "setDeltaVelocity"):
        speed = panel.jog_speed[name]
        speed.set_value(abs(values[0]))
        minus, plus = panel.jog_buttons[name]
        button = minus if values[0] < 0 else plus
        sign = -1.0 if values[0] < 0 else 1.0
        sent = (sign * speed.value(),)
        pending = len(_outcomes(panel))
        button.pressed.emit()
        wait_for(lambda: len(_outcomes(panel)) > pending, 3.0, f"the panel's outcome of {name}")
        button.released.emit()  # sends 0 (within limits): collected with the next action
        wait_for(lambda: len(_outcomes(panel)) > pending + 1, 3.0, "the jog's release")
        return name, sent
    if name == "disableEndstrokes":
        check = panel.endstrokes_check
        if check.isChecked() != values[0]:
            check.click()
        else:
            panel.send(name, bool(values[0]))
        return name, (bool(values[0]),)
    form = panel.forms[name]
    for arg, value in zip(form.command.args, values, strict=True):
        if arg.name in form.inputs:
            form.inputs[arg.name].set_value(value)
    sent = form.values()
    form.send()
    return name, sent


def _outcomes(panel: LinarmPanel) -> list[Any]:
    return [o for o in panel.outcomes if o.kind != "event"]


def run_gui(rig: Rig, actions: list[tuple[str, tuple]]) -> list[str]:
    """Every action through the panel; returns the problems with how refusals were shown."""
    wrong = []
    for name, values in actions:
        before = len(_outcomes(rig.panel))
        done = gui_action(rig, name, values)
        assert done is not None
        wait_for(lambda before=before: len(_outcomes(rig.panel)) > before, 3.0, f"the panel's outcome of {name}")
        outcome = _outcomes(rig.panel)[before]
        assert outcome.command == name, (outcome, name)
        breaks = rule_breaks(name, named(*done), rig.limits)
        event(f"gui {name}: {outcome.kind}")
        if breaks and (outcome.kind != "refused" or not REFUSED_GUI.search(outcome.text)):
            wrong.append(f"GUI {done}: {breaks} but the panel showed {outcome.kind}: {outcome.text}")
    return wrong


# ── path (b): the script API ──────────────────────────────────────────────────────────────────────────

SCRIPT = """\
results = []
for name, args in CALLS:
    try:
        getattr(linarm, name)(*args)
        results.append(("ok", ""))
    except CommandRefused as exc:
        results.append(("refused", str(exc)))
    except Exception as exc:
        results.append((type(exc).__name__, str(exc)))
"""
REFUSED_SCRIPT = re.compile(r"refused: \S")


def literal(value: Any) -> str:
    return f"float({repr(value)!r})" if isinstance(value, float) else repr(value)


def run_script(rig: Rig, actions: list[tuple[str, tuple]]) -> list[str]:
    listed = ", ".join(f"({n!r}, ({''.join(literal(v) + ', ' for v in vals)}))" for n, vals in actions)
    runner = rig.script_runner()
    try:
        runner.start(f"CALLS = [{listed}]\n" + SCRIPT, "<property>")
        run_kernel = runner._kernel  # the kernel that runs it: its fate is in the message if the read fails
        assert run_kernel is not None
        wait_for(lambda: runner.wait(0), 10.0, "the script to end")
        assert runner.result is not None and runner.result.status == "finished", runner.result
        # The script runs in the kernel process; its answer comes from there (5 s was once not enough in CI).
        t_read = time.monotonic()
        results = runner.namespace_value("results", timeout=KERNEL_START_S)
        t_read = time.monotonic() - t_read
    except BaseException:  # a failing example leaves no kernel running, and the next one starts afresh
        rig.close_runner()
        raise
    assert results is not None, (
        f"the kernel did not answer the read of the script's results ({t_read:.2f} s; the run's kernel "
        f"{run_kernel.pid}: {'alive' if run_kernel.alive else run_kernel.cause()}; the prompt's kernel now "
        f"{runner.kernel_pid})")
    assert len(results) == len(actions)
    wrong = []
    for (name, values), (kind, text) in zip(actions, results, strict=True):
        event(f"script {name}: {kind}")
        breaks = rule_breaks(name, named(name, values), rig.limits)
        if breaks and (kind != "refused" or not REFUSED_SCRIPT.search(text)):
            wrong.append(f"script linarm.{name}{values}: {breaks} but the script saw {kind}: {text}")
    return wrong


# ── the properties ────────────────────────────────────────────────────────────────────────────────────


@PROFILE
@given(mode=MODES, actions=calls(MAIN_COMMANDS, MAIN_ARGS))
def test_gui_actions_put_nothing_outside_the_limits_on_the_wire(rig: Rig, mode: ControlMode,
                                                               actions: list[tuple[str, tuple]]) -> None:
    ensure_on(rig, mode)
    wrong = run_gui(rig, actions)
    assert rig.wire_breaks() == []
    assert wrong == []


@PROFILE
@given(mode=MODES, actions=calls(MAIN_COMMANDS, MAIN_ARGS, max_size=6))
def test_script_calls_put_nothing_outside_the_limits_on_the_wire(rig: Rig, mode: ControlMode,
                                                                actions: list[tuple[str, tuple]]) -> None:
    ensure_on(rig, mode)
    wrong = run_script(rig, actions)
    assert rig.wire_breaks() == []
    assert wrong == []


ALPHA = st.one_of(st.floats(-1.0, 1.0), st.floats(-5.0, 5.0), st.sampled_from([-1.0, 0.0, 0.75, 1.0]),
                  st.sampled_from([math.nan, math.inf, -math.inf, 1e30, -1e30]))
MAP_END = st.one_of(st.floats(0.0, 3000.0), st.sampled_from([0.0, 0.005, 0.01, 2000.0, 2500.0]))
MODEL_INPUT = st.one_of(
    st.tuples(st.just("update_alpha"), ALPHA),  # what the driver's listener does with a decoded α
    st.tuples(st.just("udp"), ALPHA),  # a reply on the wire, α packed as is with a valid CRC
    st.tuples(st.just("garbage"), st.binary(min_size=1, max_size=40)),
)


@PROFILE
@given(k_r=st.one_of(st.floats(0.0, 1.0), st.just(1.0)), maps=st.lists(MAP_END, min_size=6, max_size=6),
       custom_maps=st.booleans(), inputs=st.lists(MODEL_INPUT, min_size=1, max_size=6),
       mode=st.sampled_from([ControlMode.POS_REF_BY_ASSISTANCE, ControlMode.POS_REF_BY_ADMITTANCE]))
def test_patient_model_outputs_put_nothing_outside_the_limits_on_the_wire(
        rig: Rig, k_r: float, maps: list[float], custom_maps: bool, inputs: list[tuple[str, Any]],
        mode: ControlMode) -> None:
    ensure_on(rig, mode)
    assistance = rig.manager.assistance
    config = replace(assistance.config, k_r=k_r)
    if custom_maps:  # what the therapist may type into the assistance panel
        config = replace(config, k_m_stiffness_n_m=AssistanceMap(maps[0], maps[1]),
                         k_a_admittance_m_s_n=AssistanceMap(maps[2] / 1e5, maps[3] / 1e5),
                         k_t_assistive_n_m=AssistanceMap(maps[4], maps[5]))
    model = rig.manager.driver("patient_model")
    for kind, value in inputs:
        applied = assistance.apply_count
        events_at, warnings_at = len(rig.events), len(rig.warnings)
        if kind == "update_alpha":
            assistance.set_config(config)  # gains and maps as the panel sets them, then α
            assistance.update_alpha(value)
        else:
            seen = model.datagrams_received + sum(model.invalid_datagrams.values())
            assistance.set_config(config)
            if kind == "udp":
                rig.send_model_reply(value)
            else:
                rig.send_model_reply(0.0, raw=value)
            wait_for(lambda seen=seen: model.datagrams_received + sum(model.invalid_datagrams.values()) > seen, 2.0,
                     "the driver to take the datagram")
            if kind == "udp" and not -1.0 <= value <= 1.0:
                assert model.latest("patient_model.main") is None or \
                    -1.0 <= model.latest("patient_model.main").alpha <= 1.0
        # Each robot update is three commands on the assistance thread; it ends with setStiffness's ack
        # or with the first refusal / error (logged as "assistance not applied").
        sends = assistance.apply_count - applied
        event(f"model {kind}: {'sent' if sends else 'nothing sent'}")

        def finished(events_at: int = events_at, warnings_at: int = warnings_at, sends: int = sends) -> bool:
            ok = [d for d in rig.events_since(events_at, "robot_command", "assistance")
                  if d.get("command") == "setStiffness"]
            failed = [w for w in rig.warnings[warnings_at:] if w.startswith("assistance not applied")]
            return len(ok) + len(failed) >= sends

        wait_for(finished, 5.0, "the assistance commands")
        refused = rig.events_since(events_at, "command_refused", "assistance")
        assert all(re.search(r"refused: \S", d["reason"]) for d in refused), refused
    assert rig.wire_breaks() == []


def test_the_properties_are_not_vacuous(rig: Rig) -> None:
    """Each path does reach the wire with in-limit values, and the checker does catch a bad frame."""
    ensure_on(rig, ControlMode.POS_REF_BY_TARGET_POS)
    assert rig.wire_breaks() == []
    counts = dict(rig.wire_frames)
    assert run_gui(rig, [("moveCentreTo", (0.3, 0.1, 0.5, 0.0, False)), ("setMaxVelocity", (5.0,))]) == []
    assert run_script(rig, [("setAssistanceTargetPos", (0.2,)), ("setStiffness", (9e9, 0.1, 0.5, 0.0))]) == []
    assert rig.wire_breaks() == []
    assert rig.wire_frames.get("moveCentreTo", 0) == counts.get("moveCentreTo", 0) + 1
    assert rig.wire_frames.get("setAssistanceTargetPos", 0) == counts.get("setAssistanceTargetPos", 0) + 1
    assert rig.wire_frames.get("setMaxVelocity", 0) == counts.get("setMaxVelocity", 0)  # refused: not sent
    assert rig.wire_frames.get("setStiffness", 0) == counts.get("setStiffness", 0)
    ensure_on(rig, ControlMode.POS_REF_BY_ASSISTANCE)
    counts = dict(rig.wire_frames)
    assistance = rig.manager.assistance
    assistance.set_config(replace(assistance.config, k_r=1.0))
    assistance.update_alpha(0.1 if assistance.alpha != 0.1 else 0.2)
    found: list[str] = []
    wait_for(lambda: found.extend(rig.wire_breaks()) or found
             or rig.wire_frames.get("setStiffness", 0) > counts.get("setStiffness", 0), 3.0, "the assistance")
    assert found == []
    for name in ("setAdmittanceParameter", "setAssistanceParameter", "setStiffness"):
        assert rig.wire_frames.get(name, 0) > counts.get(name, 0), name
    # The checker: a frame written past the supervisor, straight to the transport, is caught.
    rig.driver.transport.write(proto.encode_command("setMaxVelocity", 60000, 0.9))
    wait_for(lambda: found.extend(rig.wire_breaks()) or found, 2.0, "the checker to flag the frame")
    assert "setMaxVelocity" in found[0] and "not in (0, 0.3]" in found[0]
    ensure_on(rig, ControlMode.POS_REF_BY_TARGET_POS)  # the controller's limit back to the configured one


# ── timed moves and homing parameters (once gaps, closed in app/safety/supervisor.py) ─────────────────────────────

TIMED_MOVES = ["moveCentreTo", "moveDeltaTo", "setStiffness"]


@GAP_PROFILE
@example(path="script", actions=[("moveCentreTo", (0.25, 5.0, 50.0, 10.0, False))])
@example(path="gui", actions=[("moveDeltaTo", (0.03, 1.5, 8.0, 2.0, False))])
@given(path=st.sampled_from(["gui", "script"]), actions=calls(TIMED_MOVES, GAP_ARGS, max_size=3))
def test_timed_moves_are_bounded_in_speed_and_acceleration(rig: Rig, path: str,
                                                            actions: list[tuple[str, tuple]]) -> None:
    ensure_on(rig, ControlMode.POS_REF_BY_TARGET_POS)
    wrong = run_gui(rig, actions) if path == "gui" else run_script(rig, actions)
    assert rig.wire_breaks() == []
    assert wrong == []


@GAP_PROFILE
@example(path="script", actions=[("setHomeParameter", (0.25, 0.02, 0.9))])
@example(path="gui", actions=[("setHomeParameter", (0.25, 0.02, 0.45))])
@given(path=st.sampled_from(["gui", "script"]), actions=calls(["setHomeParameter"], GAP_ARGS, max_size=2))
def test_home_parameters_are_checked(rig: Rig, path: str, actions: list[tuple[str, tuple]]) -> None:
    ensure_on(rig, ControlMode.POS_REF_BY_TARGET_POS)
    wrong = run_gui(rig, actions) if path == "gui" else run_script(rig, actions)
    assert rig.wire_breaks() == []
    assert wrong == []
