"""One source for the controller's constants (app/wire/linarm_constants.py): the generated firmware header,
the firmware's own defaults as it reports them, the Python simulator, the LINarm panel and the host's safety
supervisor must all carry the table's values. Any constant that differs anywhere fails here. So does the
host's copy of the controller's watchdog timeout (the protocol table's WATCHDOG_TIMEOUT) in the config."""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import json
import os
import re
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from app.devices.sim import linarm_model
from app.devices.sim.linarm_model import LinarmParams, LinarmSimCore
from app.wire import linarm_constants
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_constants import CONSTANTS, K
from app.wire.linarm_protocol import WATCHDOG_TIMEOUT, Ack, decode_controller_frame, encode_command, protocol_table
from tests.test_firmware import FIRMWARE, GENERATOR, ROOT, FirmwareTarget, build_firmware

SRC = FIRMWARE / "linarm_controller" / "src"
GENERATED = SRC / "linarm_constants_generated.h"


def f32(value: float) -> float:
    return struct.unpack("<f", struct.pack("<f", value))[0]


def header_values(text: str) -> dict[str, float]:
    return {m[1]: float(m[2].rstrip("fUL")) for m in re.finditer(
        r"^const (?:float|unsigned long) (\w+) = ([-+0-9.e]+(?:f|UL)?);", text, re.M)}


def _generator() -> Any:
    spec = importlib.util.spec_from_file_location("gen_protocol_header", GENERATOR)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------------------------------------- table <-> header
def test_the_committed_header_carries_every_table_constant() -> None:
    text = GENERATED.read_text(encoding="utf-8")
    assert text == _generator().render_constants(protocol_table()), "run firmware/tools/gen_protocol_header.py --write"
    values = header_values(text)
    assert set(values) == set(K), set(values) ^ set(K)
    for c in CONSTANTS:
        want = int(c.value) if c.integer else f32(c.value)
        assert values[c.name] == pytest.approx(want, rel=1e-7, abs=0), c.name


def test_no_firmware_file_writes_a_table_constant_by_hand() -> None:
    for path in sorted([*SRC.glob("*.h"), *SRC.glob("*.cpp"), *(FIRMWARE / "host").rglob("*.h"),
                        *(FIRMWARE / "host").rglob("*.cpp")]):
        if path == GENERATED:
            continue
        text = path.read_text(encoding="utf-8")
        for name in K:
            assert not re.search(rf"\bconst\s+(?:float|double|unsigned long|int)\s+{name}\s*=", text), \
                f"{path.relative_to(ROOT)} defines {name}: it belongs in app/wire/linarm_constants.py"
    plant = (FIRMWARE / "host" / "sim" / "sim_plant.h").read_text(encoding="utf-8")
    body = plant[plant.index("struct PlantParams {"):plant.index("};", plant.index("struct PlantParams {"))]
    assert not re.search(r"=\s*[-0-9]", body), "the C++ plant's parameters come from cfg:: (the table)"


def test_a_drifted_constant_fails_the_build_check(tmp_path: Path) -> None:
    gen = _generator()
    table = protocol_table()
    next(r for r in table["constants"] if r["name"] == "ADMITTANCE_KA")["value"] = 0.002  # the Python side drifts
    assert gen.render_constants(table) != GENERATED.read_text(encoding="utf-8")
    tampered = tmp_path / "linarm_constants_generated.h"  # the C++ side drifts
    tampered.write_text(GENERATED.read_text(encoding="utf-8").replace("MAX_FORCE = 60.0f", "MAX_FORCE = 80.0f"))
    result = subprocess.run([sys.executable, str(GENERATOR), "--constants-check", str(tampered)],
                            capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert result.returncode == 1 and "drifted apart" in result.stderr


# ---------------------------------------------------------------------------------------------- simulator
PARAMS = {"rail_min": "RAIL_MIN", "rail_max": "RAIL_MAX", "switch_min": "SWITCH_MIN_POS",
          "switch_max": "SWITCH_MAX_POS", "carriage_mass": "CARRIAGE_MASS", "carriage_viscous": "CARRIAGE_VISCOUS",
          "carriage_coulomb": "CARRIAGE_COULOMB", "handle_mass": "HANDLE_MASS", "handle_damping": "HANDLE_DAMPING",
          "spring_a": "SPRING_A", "spring_b": "SPRING_B", "spring_free_length": "SPRING_FREE_LENGTH",
          "delta_min": "DELTA_MIN", "delta_max": "DELTA_MAX", "bumper": "BUMPER",
          "contact_stiffness": "CONTACT_STIFFNESS", "contact_damping": "CONTACT_DAMPING",
          "force_constant": "FORCE_CONSTANT", "current_hw_limit": "CURRENT_HW_LIMIT",
          "encoder_resolution": "ENCODER_RESOLUTION"}
CORE = {"pos_min": "POS_MIN", "pos_max": "POS_MAX", "max_tracking_error": "MAX_TRACKING_ERROR",
        "max_force": "MAX_FORCE", "max_current": "MAX_CURRENT", "max_acc": "MAX_ACCELERATION",
        "max_vel": "MAX_VELOCITY", "home_centre": "HOME_CENTRE", "home_delta": "HOME_DELTA",
        "homing_velocity": "HOMING_VELOCITY", "ka": "ADMITTANCE_KA", "kt": "ASSISTANCE_KT",
        "assist_target": "ASSISTANCE_TARGET"}


def test_the_simulator_uses_the_table() -> None:
    params = LinarmParams()
    assert {f.name for f in dataclasses.fields(params)} == set(PARAMS)
    for field, name in PARAMS.items():
        assert getattr(params, field) == K[name], field
    core = LinarmSimCore()
    for attr, name in CORE.items():
        assert getattr(core, attr) == K[name], attr
    for pid in core.pid:
        assert (pid.kp, pid.ki, pid.kd) == (K["PID_KP"], K["PID_KI"], K["PID_KD"])
    assert linarm_model.DT == K["DT"] and linarm_model.SEEK_LEAD == K["SEEK_LEAD"]
    assert linarm_model.HOME_SETTLE == pytest.approx(K["HOME_SETTLE_TICKS"] * K["DT"])
    assert linarm_model.OVER_CURRENT_TIME == pytest.approx(K["OVER_CURRENT_TICKS"] * K["DT"])
    # the stiffness law quoted in the docs follows from the table's springs
    assert params.stiffness(K["DELTA_MIN"]) == pytest.approx(450.0)
    assert params.stiffness(K["HOME_DELTA"]) == pytest.approx(900.0)


# ---------------------------------------------------------------------------------------------- panel
PANEL = {"Ka": "ADMITTANCE_KA", "Kt": "ASSISTANCE_KT", "Apos": "ASSISTANCE_TARGET", "minPos": "POS_MIN",
         "maxPos": "POS_MAX", "maxTrackingError": "MAX_TRACKING_ERROR", "maxForce": "MAX_FORCE",
         "maxCurrent": "MAX_CURRENT", "homeCentre": "HOME_CENTRE", "homeDelta": "HOME_DELTA",
         "homingVelocity": "HOMING_VELOCITY"}


def test_the_panel_shows_the_controller_defaults_of_the_table() -> None:
    from app.ui import linarm_panel

    assert set(linarm_panel.CONTROLLER_DEFAULTS) == set(PANEL)
    for key, name in PANEL.items():
        assert linarm_panel.DEFAULTS[key] == K[name], f"panel {key}={linarm_panel.DEFAULTS[key]} vs table {K[name]}"


# ---------------------------------------------------------------------------------------------- the host's supervisor
ENVELOPE = ("ENVELOPE_VELOCITY_FACTOR", "ENVELOPE_POSITION_MARGIN")


def literal_copies(path: Path, values: dict[str, float], scope: str | None = None) -> list[str]:
    """Numeric literals in ``path`` (within the class or function ``scope``, if given) equal to one of
    ``values``: each a hand-written copy of a fact that has its one place elsewhere."""
    tree: ast.AST = ast.parse(path.read_text(encoding="utf-8"), str(path))
    if scope is not None:
        tree = next(n for n in ast.walk(tree) if isinstance(n, (ast.ClassDef, ast.FunctionDef)) and n.name == scope)
    return [f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r} is {name}"
            for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and type(node.value) in (int, float)
            for name, value in values.items() if node.value == pytest.approx(value, rel=1e-9, abs=0)]


def test_the_supervisor_writes_no_envelope_margin_by_hand() -> None:
    """app/safety/supervisor.py's robot monitor is the controller's envelope check one layer up: its margins are the
    table's, read from it, never a literal (it once held ``1.2 *`` and ``± 0.01``)."""
    from app.safety import supervisor as safety

    copies = literal_copies(ROOT / "app" / "safety" / "supervisor.py", {name: K[name] for name in ENVELOPE})
    assert not copies, "read these from app/wire/linarm_constants.py:\n" + "\n".join(copies)
    assert (safety.ENVELOPE_VELOCITY_FACTOR, safety.ENVELOPE_POSITION_MARGIN) == tuple(K[n] for n in ENVELOPE)


# The supervisor's trip points, probed in a fresh interpreter whose table says ``sys.argv[1:3]``: a sample just
# inside and just outside each margin, after the grace samples that follow homing.
TRIP_PROBE = r"""
import json, sys
from app.wire import linarm_constants
factor, margin = float(sys.argv[1]), float(sys.argv[2])
linarm_constants.K.update(ENVELOPE_VELOCITY_FACTOR=factor, ENVELOPE_POSITION_MARGIN=margin)
from types import SimpleNamespace
from app.core.config import SafetyConfig
from app.safety.supervisor import RobotProbes, SafetySupervisor, StopAction
sup = SafetySupervisor(SafetyConfig())
lim = sup.robot
stops = []
sup.add_stop_action(StopAction("robot IDLE", stops.append, robot=True))
sup.set_robot_probes(RobotProbes(lambda: None, lambda: None, lambda: True))
centre = (lim.position_min_m + lim.position_max_m) / 2
ok = SimpleNamespace(handleVel=0.0, interactionForce=0.0, handlePos=centre)
for _ in range(20):
    sup.check_robot_sample(ok)
eps, v = 1e-4, factor * lim.max_velocity_m_s
probes = {"speed_inside": (v - eps, centre), "speed_outside": (v + eps, centre),
          "above_max_inside": (0.0, lim.position_max_m + margin - eps),
          "above_max_outside": (0.0, lim.position_max_m + margin + eps),
          "below_min_inside": (0.0, lim.position_min_m - margin + eps),
          "below_min_outside": (0.0, lim.position_min_m - margin - eps)}
tripped = {}
for name, (vel, pos) in probes.items():
    before = len(stops)
    sup.check_robot_sample(SimpleNamespace(handleVel=vel, interactionForce=0.0, handlePos=pos))
    tripped[name] = len(stops) > before
    sup.check_robot_sample(ok)
print(json.dumps(tripped))
"""


def supervisor_trips(factor: float, margin: float) -> dict[str, bool]:
    result = subprocess.run([sys.executable, "-c", TRIP_PROBE, repr(factor), repr(margin)], capture_output=True,
                            text=True, timeout=60, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    return dict(json.loads(result.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize(("factor", "margin"), [(K["ENVELOPE_VELOCITY_FACTOR"], K["ENVELOPE_POSITION_MARGIN"]),
                                                (1.7, 0.03), (1.05, 0.004)], ids=["table", "wider", "narrower"])
def test_the_supervisor_trips_where_the_table_says(factor: float, margin: float) -> None:
    """Change the table and the supervisor's trip points move with it: just inside each margin nothing happens,
    just outside the robot is stopped (speed above factor x max_velocity, position beyond either end + margin)."""
    trips = supervisor_trips(factor, margin)
    assert trips == {name: name.endswith("_outside") for name in trips} and len(trips) == 6, trips


# ---------------------------------------------------------------------------------------------- the watchdog's copy
def test_the_config_takes_the_silence_floor_from_the_controller_watchdog() -> None:
    """safety.silence_min_s defaults to the controller's host watchdog (one value: the protocol table's, which
    the firmware header is generated from), not a literal beside it."""
    from app.core.config import SafetyConfig

    config = ROOT / "app" / "core" / "config.py"
    copies = literal_copies(config, {"WATCHDOG_TIMEOUT": WATCHDOG_TIMEOUT}, scope="SafetyConfig")
    assert not copies, "read it from app/wire/linarm_protocol.py:\n" + "\n".join(copies)
    assert SafetyConfig().silence_min_s == WATCHDOG_TIMEOUT == protocol_table()["limits"]["watchdog_timeout_s"]
    probe = ("import sys\nfrom app.wire import linarm_protocol\nlinarm_protocol.WATCHDOG_TIMEOUT = 0.4\n"
             "from app.core.config import SafetyConfig\nprint(SafetyConfig().silence_min_s)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    assert float(result.stdout.strip().splitlines()[-1]) == 0.4, "the config's default did not follow the table"


# ---------------------------------------------------------------------------------------------- what they report
QUERIES = [("getPidTunings", (0,), {"kp": "PID_KP", "ki": "PID_KI", "kd": "PID_KD"}),
           ("getPidTunings", (1,), {"kp": "PID_KP", "ki": "PID_KI", "kd": "PID_KD"}),
           ("getAdmittanceParameter", (), {"Ka": "ADMITTANCE_KA"}),
           ("getAssistanceParameter", (), {"Kt": "ASSISTANCE_KT"}),
           ("getAssistanceTargetPos", (), {"Apos": "ASSISTANCE_TARGET"}),
           ("lockEnvelope", (), {"maxVel": "MAX_VELOCITY", "maxAcc": "MAX_ACCELERATION", "maxForce": "MAX_FORCE",
                                 "maxCurrent": "MAX_CURRENT", "maxTrackingError": "MAX_TRACKING_ERROR",
                                 "minPos": "POS_MIN", "maxPos": "POS_MAX"})]


def _ask(send: Any) -> None:
    decoder = CmdMessengerDecoder()
    for seq, (name, args, expected) in enumerate(QUERIES, start=1):
        replies = [decode_controller_frame(f) for f in decoder.feed(send(encode_command(name, seq, *args)))]
        ack = next(m for m in replies if isinstance(m, Ack) and m.seq == seq)
        for field, constant in expected.items():
            assert ack.values[field] == f32(K[constant]), f"{name}.{field} = {ack.values[field]} vs {constant}"


def test_the_firmware_reports_the_table_defaults() -> None:
    target = FirmwareTarget(build_firmware("linarm_sil") / "linarm_sil")
    try:
        _ask(target.send)
    finally:
        target.close()


def test_the_simulator_reports_the_table_defaults() -> None:
    _ask(LinarmSimCore().handle_host_bytes)


def test_every_constant_is_documented() -> None:
    for c in CONSTANTS:
        assert c.doc and c.group, c.name
    assert linarm_constants.constants_table() == protocol_table()["constants"]
