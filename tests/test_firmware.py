"""The LINarm controller firmware, built for the host (CMake + g++): its C++ unit tests, the protocol header
generated from the Python table, the DUE sketch compiled against stub headers, and the shared protocol
scenarios (tests/protocol_scenarios) run against the software-in-the-loop executable.

The build is made once and shared by the test modules, the workers and later runs (tests/firmware_builds.py:
firmware/build/cache, keyed on the sources; firmware/build/pytest points at it; ignored by git). Without
cmake/g++ the tests skip locally and fail in CI (``CI`` set), where the toolchain is installed.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from app.wire.linarm_protocol import ReplyError, protocol_table
from tests import firmware_builds
from tests.test_protocol_scenarios import SCENARIOS, Scenario, run_scenario

ROOT = Path(__file__).resolve().parent.parent
FIRMWARE = ROOT / "firmware"
BUILD_DIR = firmware_builds.HOST.link
COMMITTED_HEADER = FIRMWARE / "linarm_controller" / "src" / "protocol_generated.h"
GENERATOR = FIRMWARE / "tools" / "gen_protocol_header.py"
BUILD_TIMEOUT_S = 300

_build_lock = threading.Lock()
_build_result: dict[tuple[str, ...], object] = {}


def toolchain_problem() -> str | None:
    missing = [tool for tool in ("cmake", "make") if shutil.which(tool) is None]
    if shutil.which("g++") is None and shutil.which("c++") is None:
        missing.append("g++")
    return f"the C++ toolchain is missing ({', '.join(missing)})" if missing else None


def build_firmware(*targets: str) -> Path:
    """The host build for the current sources, with ``targets`` (all when none is named) built in it: once
    for every module, worker and run (tests/firmware_builds.py); returns its folder."""
    with _build_lock:  # one thread of this process at a time; the file lock orders the processes
        key = targets or ("all",)
        if key in _build_result:
            result = _build_result[key]
            if isinstance(result, str):  # the build failed: its message
                raise RuntimeError(result)
            return Path(result)  # type: ignore[arg-type]
        problem = toolchain_problem()
        if problem:
            if os.environ.get("CI"):
                pytest.fail(f"{problem}: CI must install cmake and g++ (see .ci/run)")
            pytest.skip(f"{problem}; install cmake and g++ to build the firmware's host tests")
        try:
            folder = firmware_builds.ensure(firmware_builds.HOST, *targets)
        except firmware_builds.BuildFailed as exc:
            _build_result[key] = str(exc)
            raise RuntimeError(str(exc)) from None
        _build_result[key] = folder
        return folder


@pytest.fixture(scope="session")
def firmware_build() -> Path:
    return build_firmware()


class FirmwareTarget:
    """The SIL executable in lockstep mode: host bytes and simulated time over a line protocol."""

    def __init__(self, sil: Path | list[str], centre: float = 0.20, start_homed: bool = False,
                 service: bool = False) -> None:
        args = [*([str(sil)] if isinstance(sil, Path) else sil), "--lockstep", "--centre", repr(centre)]
        if start_homed:
            args.append("--start-homed")
        if service:
            args.append("--service")
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)

    def _ask(self, line: str) -> bytes:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        reply = self.proc.stdout.readline()
        if not reply.startswith("R"):
            raise RuntimeError(f"linarm_sil stopped (exit {self.proc.poll()}) after {line[:40]!r}")
        return bytes.fromhex(reply[2:].strip())

    def send(self, data: bytes) -> bytes:
        return self._ask("S " + data.hex())

    def advance(self, seconds: float) -> bytes:
        return self._ask(f"A {round(seconds * 1000)}")

    def push(self, newtons: float) -> bytes:
        return self._ask(f"F {float(newtons)!r}")

    def restart(self) -> bytes:
        return self._ask("N")

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.write("Q\n")
                self.proc.stdin.close()
                self.proc.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


# ---------------------------------------------------------------------------------------------
# Build products and C++ unit tests
# ---------------------------------------------------------------------------------------------


def test_cpp_unit_tests_pass(firmware_build: Path) -> None:
    result = subprocess.run([str(firmware_build / "linarm_unit_tests")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    summary = result.stdout.strip().splitlines()[-1]
    ran = int(summary.split()[0])
    assert summary.endswith(" 0 failed") and ran >= 20, summary
    for name in ("error_watchdog", "homing_on_the_endstrokes", "error_homing_failed", "error_over_force",
                 "error_tracking", "error_endstroke_hit_and_disable", "error_over_current",
                 "error_over_velocity", "error_position_limit"):
        assert f"[  OK  ] {name}" in result.stdout


def test_due_sketch_compiles_against_stub_headers(firmware_build: Path) -> None:
    assert (firmware_build / "due_compile_check").is_file()  # the .ino and DueHal, compiled and linked


# ---------------------------------------------------------------------------------------------
# One source for the protocol: the header is generated from protocol_table()
# ---------------------------------------------------------------------------------------------


def _generator():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("gen_protocol_header", GENERATOR)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_header_matches_the_python_table() -> None:
    gen = _generator()
    text = gen.render(protocol_table())
    assert COMMITTED_HEADER.read_text(encoding="utf-8") == text, "run firmware/tools/gen_protocol_header.py --write"
    assert "CMD_MOVE_DELTA_TO = 10," in text and "OUT_OF_RANGE = 3," in text


def test_a_drifted_id_fails_the_check(tmp_path: Path) -> None:
    """A command id changed on either side makes the generator's --check (run by every CMake build) fail."""
    gen = _generator()
    table = protocol_table()
    table["enums"]["REPLY_ERRORS"]["OUT_OF_RANGE"] = 33  # the Python side drifts
    assert gen.render(table) != COMMITTED_HEADER.read_text(encoding="utf-8")
    tampered = tmp_path / "protocol_generated.h"  # the C++ side drifts
    tampered.write_text(COMMITTED_HEADER.read_text(encoding="utf-8").replace("CMD_MOVE_CENTRE_TO = 9,",
                                                                            "CMD_MOVE_CENTRE_TO = 19,"))
    result = subprocess.run([sys.executable, str(GENERATOR), "--check", str(tampered)], capture_output=True,
                            text=True, timeout=60, cwd=ROOT)
    assert result.returncode == 1 and "drifted apart" in result.stderr
    ok = subprocess.run([sys.executable, str(GENERATOR), "--check", str(COMMITTED_HEADER)], capture_output=True,
                        text=True, timeout=60, cwd=ROOT)
    assert ok.returncode == 0, ok.stderr
    assert int(ReplyError.OUT_OF_RANGE) == 3


# ---------------------------------------------------------------------------------------------
# The shared scenarios against the firmware
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.id for s in SCENARIOS])
def test_scenario_against_the_firmware(firmware_build: Path, scenario: Scenario) -> None:
    setup = scenario.setup
    target = FirmwareTarget(firmware_build / "linarm_sil", setup.get("centre", 0.20), setup.get("start_homed", False),
                            setup.get("service", False))
    run_scenario(target, scenario)


def test_firmware_target_reports_a_wrong_expectation(firmware_build: Path) -> None:
    bad = Scenario("bad", {}, [{"send": ["setCtrlState", 2]}], "inline")
    with pytest.raises(AssertionError, match="expected ACK"):
        run_scenario(FirmwareTarget(firmware_build / "linarm_sil"), bad)


def test_service_mode_is_only_chosen_at_boot(firmware_build: Path) -> None:
    """The service jumper is read once at boot: the IDENTIFY says so, and no command turns it on or off."""
    from app.wire.cmdmessenger import CmdMessengerDecoder
    from app.wire.linarm_protocol import Identify, decode_controller_frame, encode_command

    for service, suffix in ((False, ""), (True, "+service")):
        target = FirmwareTarget(firmware_build / "linarm_sil", service=service)
        try:
            decoder = CmdMessengerDecoder()
            boot = [decode_controller_frame(f) for f in decoder.feed(target.advance(0.0))]
            again = [decode_controller_frame(f) for f in decoder.feed(target.send(encode_command("identify", 3)))]
            assert [m.firmware_version for m in boot + again if isinstance(m, Identify)] == [f"sil-1.0{suffix}"] * 2
        finally:
            target.close()
