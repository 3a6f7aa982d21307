"""One source for the controller's constants (app/devices/linarm_constants.py): the generated firmware header,
the firmware's own defaults as it reports them, the Python simulator and the LINarm panel must all carry the
table's values. Any constant that differs anywhere fails here."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from app.devices import linarm_constants
from app.devices.cmdmessenger import CmdMessengerDecoder
from app.devices.linarm_constants import CONSTANTS, K
from app.devices.linarm_protocol import Ack, decode_controller_frame, encode_command, protocol_table
from app.devices.sim import linarm_model
from app.devices.sim.linarm_model import LinarmParams, LinarmSimCore
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
                f"{path.relative_to(ROOT)} defines {name}: it belongs in app/devices/linarm_constants.py"
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
    target = FirmwareTarget(build_firmware() / "linarm_sil")
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
