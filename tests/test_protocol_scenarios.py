"""Shared protocol scenarios (tests/protocol_scenarios/*.yaml) against the Python simulator.

The same files run against the host-built C++ firmware in tests/test_firmware.py, through the same
``ScenarioRunner``: frames sent -> frames / state expected, with tolerances on physical values. Physics may
differ between the two implementations; protocol, FSM and limits may not.

Scenario file format (a list under ``scenarios:``; each has ``name``, optional ``setup`` and ``steps``):

* ``setup: {centre: 0.20, start_homed: true, service: false}`` - where the robot starts, encoders referenced or
  not, booted in service mode (the jumper) or not.
* ``send: [command, *args]`` with ``expect: ack`` (default), ``{ack: {value: x | [x, tol]}}``,
  ``{error: CODE}``, ``identify`` or ``none``. Arguments are the table's, in order.
* ``raw: "bytes"`` with ``replies: [{error: CODE, seq: n, cmd: n} | {identify: {seq: n}}]`` (exactly these).
* ``run: seconds`` or ``run: {seconds: s, heartbeat: false}`` - heartbeats every 100 ms by default.
* ``state: {linarm: {field: value}, vsa: {...}, motor0: {...}, motor1: {...}}`` - via ``getState``.
* ``events: [ERROR_STATE, ...]`` - the ERROR_EVENTs since the last ``events`` / ``clear`` step, in order.
* ``stream: {vsaState: [lo, hi], motorState: [lo, hi], linarmState: [lo, hi], period_us: n}`` - frames of
  the last ``run`` step.
* ``sequence: {homeState: [..]}`` - successive distinct values of a LINARM_STATE field (stream and
  getState frames) since the last ``clear``.
* ``clear: true`` - forget the frames and events received so far.
* ``push: newtons`` - from now on a constant external force on the handle (a patient; + towards +x).
* ``restart: true`` - the controller restarts (power cycle): a fresh controller and robot, the same setup.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any, Protocol

import pytest
import yaml

from app.devices.sim.linarm_model import LinarmSimCore
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import (
    Ack,
    ErrorEvent,
    ErrorReply,
    Identify,
    LinarmState,
    MotorState,
    ReplyError,
    VsaState,
    decode_controller_frame,
    encode_command,
    next_seq,
)

SCENARIO_DIR = Path(__file__).resolve().parent / "protocol_scenarios"
HEARTBEAT_PERIOD = 0.1


class ScenarioTarget(Protocol):
    """A controller implementation driven in simulated time."""

    def send(self, data: bytes) -> bytes: ...  # host bytes arriving now -> everything written meanwhile
    def advance(self, seconds: float) -> bytes: ...  # run the 1 kHz loop -> everything written meanwhile
    def push(self, newtons: float) -> bytes: ...  # a constant external force on the handle from now on
    def restart(self) -> bytes: ...  # power cycle: a fresh controller (its boot IDENTIFY comes back)
    def close(self) -> None: ...


class ConstantPush:
    """A patient pushing the handle with a constant force."""

    def __init__(self) -> None:
        self.force = 0.0

    def handle_force(self, t: float, handle_pos: float, handle_vel: float) -> float:
        return self.force


class PythonTarget:
    def __init__(self, centre: float = 0.20, start_homed: bool = False, service: bool = False) -> None:
        self.setup = {"initial_centre": centre, "start_homed": start_homed, "service_mode": service}
        self.patient = ConstantPush()
        self.core = LinarmSimCore(patient=self.patient, **self.setup)  # type: ignore[arg-type]

    def push(self, newtons: float) -> bytes:
        self.patient.force = float(newtons)
        return self.core.stream_bytes()

    def restart(self) -> bytes:
        self.patient = ConstantPush()
        self.core = LinarmSimCore(patient=self.patient, **self.setup)  # type: ignore[arg-type]
        return self.core.stream_bytes()

    def send(self, data: bytes) -> bytes:
        return self.core.handle_host_bytes(data) + self.core.stream_bytes()

    def advance(self, seconds: float) -> bytes:
        self.core.step(seconds)
        return self.core.stream_bytes()

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class Scenario:
    name: str
    setup: dict[str, Any]
    steps: list[dict[str, Any]]
    source: str

    @property
    def id(self) -> str:
        return f"{self.source}:{self.name}"


def load_scenarios() -> list[Scenario]:
    out: list[Scenario] = []
    for path in sorted(SCENARIO_DIR.glob("*.yaml")):
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        for sc in data["scenarios"]:
            out.append(Scenario(sc["name"], dict(sc.get("setup") or {}), list(sc["steps"]), path.stem))
    return out


SCENARIOS = load_scenarios()


def _matches(actual: Any, expected: Any) -> bool:
    if isinstance(expected, list):  # [value, tolerance]
        value, tol = expected
        return isinstance(actual, (int, float)) and math.isfinite(actual) and abs(actual - value) <= tol
    if isinstance(actual, IntEnum) and isinstance(expected, str):
        return actual.name == expected
    if isinstance(expected, float):
        return isinstance(actual, (int, float)) and abs(actual - expected) <= 1e-6 * max(1.0, abs(expected))
    return actual == expected


@dataclass
class ScenarioRunner:
    target: ScenarioTarget
    seq: int = 0
    decoder: CmdMessengerDecoder = field(default_factory=CmdMessengerDecoder)
    frames: list[Any] = field(default_factory=list)  # everything since the last `clear`
    events: list[ErrorEvent] = field(default_factory=list)  # since the last `events` check
    last_run: list[Any] = field(default_factory=list)

    def _decode(self, data: bytes) -> list[Any]:
        msgs = [decode_controller_frame(f) for f in self.decoder.feed(data)]
        assert self.decoder.frames_bad == 0, f"undecodable frame: {self.decoder.last_error}"
        self.frames += msgs
        self.events += [m for m in msgs if isinstance(m, ErrorEvent)]
        return msgs

    def send(self, name: str, *args: Any) -> tuple[Any | None, list[Any]]:
        self.seq = next_seq(self.seq)
        msgs = self._decode(self.target.send(encode_command(name, self.seq, *args)))
        direct = [m for m in msgs if isinstance(m, (Ack, ErrorReply, Identify)) and m.seq == self.seq]
        assert len(direct) <= 1, f"{name}: more than one reply {direct}"
        return (direct[0] if direct else None), msgs

    def run(self, seconds: float, heartbeat: bool = True) -> None:
        start = len(self.frames)
        remaining = round(seconds * 1000)
        while remaining > 0:
            if heartbeat:
                self.seq = next_seq(self.seq)
                self._decode(self.target.send(encode_command("heartbeat", self.seq)))
            chunk = min(remaining, round(HEARTBEAT_PERIOD * 1000))
            self._decode(self.target.advance(chunk / 1000))
            remaining -= chunk
        self.last_run = self.frames[start:]

    # -- steps ------------------------------------------------------------------------------
    def execute(self, scenario: Scenario) -> None:
        self._decode(self.target.advance(0.0))  # the boot IDENTIFY
        for index, step in enumerate(scenario.steps):
            where = f"{scenario.id} step {index + 1} {step}"
            kind = next(k for k in ("send", "raw", "run", "state", "events", "stream", "sequence", "clear", "push",
                                    "restart") if k in step)
            getattr(self, f"_step_{kind}")(step, where)

    def _step_send(self, step: dict[str, Any], where: str) -> None:
        name, *args = step["send"]
        reply, _ = self.send(name, *args)
        expect = step.get("expect", "ack")
        if expect == "none":
            assert reply is None, f"{where}: expected no reply, got {reply}"
        elif expect == "identify":
            assert isinstance(reply, Identify), f"{where}: got {reply}"
        elif expect == "ack" or (isinstance(expect, dict) and "ack" in expect):
            assert isinstance(reply, Ack), f"{where}: expected ACK, got {reply}"
            for key, value in ((expect.get("ack") or {}) if isinstance(expect, dict) else {}).items():
                assert _matches(reply.values[key], value), f"{where}: {key}={reply.values[key]!r}, want {value}"
        else:
            code = ReplyError[expect["error"]]
            assert isinstance(reply, ErrorReply) and reply.code is code, f"{where}: expected {code.name}, got {reply}"

    def _step_raw(self, step: dict[str, Any], where: str) -> None:
        data = step["raw"].encode("latin-1")
        replies = [m for m in self._decode(self.target.send(data)) if isinstance(m, (Ack, ErrorReply, Identify))]
        expected = step.get("replies", [])
        assert len(replies) == len(expected), f"{where}: replies {replies}"
        for got, want in zip(replies, expected, strict=True):
            if "identify" in want:
                assert isinstance(got, Identify) and got.seq == want["identify"]["seq"], f"{where}: {got}"
            else:
                assert isinstance(got, ErrorReply), f"{where}: {got}"
                assert got.code is ReplyError[want["error"]], f"{where}: {got}"
                assert got.seq == want.get("seq", got.seq) and got.cmd_id == want.get("cmd", got.cmd_id), \
                    f"{where}: {got}"

    def _step_run(self, step: dict[str, Any], where: str) -> None:
        spec = step["run"]
        if isinstance(spec, dict):
            self.run(float(spec["seconds"]), heartbeat=spec.get("heartbeat", True))
        else:
            self.run(float(spec))

    def _step_state(self, step: dict[str, Any], where: str) -> None:
        reply, msgs = self.send("getState")
        assert isinstance(reply, Ack), f"{where}: getState -> {reply}"
        kinds = [type(m) for m in msgs if not isinstance(m, ErrorEvent)]
        assert kinds == [Ack, LinarmState, MotorState, MotorState, VsaState], f"{where}: getState gave {kinds}"
        linarm, m0, m1, vsa = (m for m in msgs if isinstance(m, (LinarmState, MotorState, VsaState)))
        snap = {"linarm": linarm, "motor0": m0, "motor1": m1, "vsa": vsa}
        for group, fields in step["state"].items():
            msg = snap[group]
            for key, want in fields.items():
                got = getattr(msg, _snake(key))
                assert _matches(got, want), f"{where}: {group}.{key} = {got!r}, expected {want}"

    def _step_events(self, step: dict[str, Any], where: str) -> None:
        got = [e.error_state.name for e in self.events]
        assert got == step["events"], f"{where}: error events {got}"
        for e in self.events:
            assert e.control_state.name == "IDLE_CTRL_STATE", f"{where}: {e}"
        self.events = []

    def _step_stream(self, step: dict[str, Any], where: str) -> None:
        counts = {"vsaState": VsaState, "motorState": MotorState, "linarmState": LinarmState}
        for key, want in step["stream"].items():
            if key == "period_us":
                stamps = [m.t_us for m in self.last_run if isinstance(m, VsaState)]
                steps = {b - a for a, b in itertools.pairwise(stamps)}
                assert steps == {want}, f"{where}: VSA_STATE periods {sorted(steps)[:5]} us"
                continue
            n = sum(1 for m in self.last_run if isinstance(m, counts[key]))
            assert want[0] <= n <= want[1], f"{where}: {n} {key} frames"

    def _step_sequence(self, step: dict[str, Any], where: str) -> None:
        for key, want in step["sequence"].items():
            values = [getattr(m, _snake(key)).name for m in self.frames if isinstance(m, LinarmState)]
            distinct = [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]
            assert distinct == want, f"{where}: {key} went {distinct}"

    def _step_clear(self, step: dict[str, Any], where: str) -> None:
        self.frames = []
        self.events = []

    def _step_push(self, step: dict[str, Any], where: str) -> None:
        self._decode(self.target.push(float(step["push"])))

    def _step_restart(self, step: dict[str, Any], where: str) -> None:
        msgs = self._decode(self.target.restart())
        assert any(isinstance(m, Identify) and m.seq == 0 for m in msgs), f"{where}: no boot IDENTIFY after restart"
        self.events = []


def _snake(name: str) -> str:
    return "".join("_" + c.lower() if c.isupper() else c for c in name)


def run_scenario(target: ScenarioTarget, scenario: Scenario) -> None:
    try:
        ScenarioRunner(target).execute(scenario)
    finally:
        target.close()


# ---------------------------------------------------------------------------------------------
# The scenarios against the Python simulator
# ---------------------------------------------------------------------------------------------


def test_scenario_files_are_present() -> None:
    names = {s.id for s in SCENARIOS}
    assert len(SCENARIOS) >= 15 and len(names) == len(SCENARIOS)
    covered = {str(e) for s in SCENARIOS for step in s.steps if "events" in step for e in step["events"]}
    assert covered >= {"WATCHDOG", "TRACKING_ERROR", "ENDSTROKE_HIT", "OVER_CURRENT", "OVER_VELOCITY",
                       "POSITION_LIMIT", "OVER_FORCE", "ENVELOPE_BREACH"}


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.id for s in SCENARIOS])
def test_scenario_against_the_simulator(scenario: Scenario) -> None:
    setup = scenario.setup
    run_scenario(PythonTarget(setup.get("centre", 0.20), setup.get("start_homed", False),
                              setup.get("service", False)), scenario)


def test_a_wrong_expectation_fails() -> None:
    """The runner really compares: an ACK expected where the controller refuses is a failure."""
    bad = Scenario("bad", {}, [{"send": ["setCtrlState", 2]}], "inline")
    with pytest.raises(AssertionError, match="expected ACK"):
        run_scenario(PythonTarget(), bad)
