"""The firmware on the DUE's CPU and ABI (Debian packages, see firmware/README.md "ARM builds"):

* the sketch cross-compiled for the Cortex-M3 (gcc-arm-none-eabi, newlib-nano) against the stub core, with
  its size against the DUE's 512 KB flash / 96 KB RAM;
* the C++ unit tests and the shared protocol scenarios built for 32-bit ARM Linux (g++-arm-linux-gnueabihf:
  ILP32, unsigned char, as on the DUE) and run under qemu-arm;
* the same fuzzed receive streams (overlong frames, huge ids, garbage) fed to the ARM build, the host build
  and the Python simulator: identical replies.

Builds go to firmware/build/cache (pytest-arm and pytest-due point there; ignored by git), made once for every
module, worker and run (tests/firmware_builds.py), only the targets asked for. Without the
toolchains the tests skip locally with the reason; with CI set they fail (.ci/run installs them).
"""

from __future__ import annotations

import os
import random
import re
import shutil
import subprocess
import threading
from pathlib import Path
from typing import Any

import pytest

from app.devices.sim.linarm_model import LinarmSimCore
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import (
    COMMANDS_BY_NAME,
    HOST_COMMANDS,
    Ack,
    ErrorReply,
    Identify,
    LinarmState,
    MotorState,
    VsaState,
    decode_controller_frame,
    encode_command,
)
from tests import firmware_builds
from tests.test_firmware import FIRMWARE, FirmwareTarget, build_firmware
from tests.test_protocol_scenarios import SCENARIOS, run_scenario

HOST_DIR = FIRMWARE / "host"
ARM_BUILD = firmware_builds.ARM.link
DUE_BUILD = firmware_builds.DUE.link
DUE_FLASH, DUE_RAM = 512 * 1024, 96 * 1024
FUZZ_STREAMS = 1500

_lock = threading.Lock()
_builds: dict[tuple[str, ...], Any] = {}


def _need(tools: tuple[str, ...], packages: str) -> None:
    missing = [t for t in tools if shutil.which(t) is None]
    if not missing:
        return
    reason = f"{', '.join(missing)} not installed (Debian: apt-get install {packages})"
    if os.environ.get("CI"):
        pytest.fail(f"{reason}: CI must install it (.ci/run)")
    pytest.skip(reason)


def build_cross(build: firmware_builds.Build, *targets: str) -> Path:
    """``build`` with ``targets``, once for every module, worker and run (tests/firmware_builds.py)."""
    with _lock:
        key = (build.name, *targets)
        if key not in _builds:
            try:
                _builds[key] = firmware_builds.ensure(build, *targets)
            except firmware_builds.BuildFailed as exc:
                _builds[key] = str(exc)
        if isinstance(_builds[key], str):
            raise RuntimeError(_builds[key])
        return Path(_builds[key])


@pytest.fixture(scope="session")
def arm_build() -> Path:
    _need(("cmake", "arm-linux-gnueabihf-g++", "qemu-arm"), "g++-arm-linux-gnueabihf qemu-user")
    return build_cross(firmware_builds.ARM, "linarm_unit_tests", "linarm_sil")  # not the DUE sketch's check


@pytest.fixture(scope="session")
def due_build() -> Path:
    _need(("cmake", "arm-none-eabi-gcc", "arm-none-eabi-g++", "arm-none-eabi-size"),
          "gcc-arm-none-eabi libnewlib-arm-none-eabi")
    return build_cross(firmware_builds.DUE, "linarm_due.elf")


def qemu(build: Path, program: str) -> list[str]:
    return ["qemu-arm", str(build / program)]


# ---------------------------------------------------------------------------------------------
# Cortex-M3: it compiles for the DUE's CPU and fits
# ---------------------------------------------------------------------------------------------


def test_cortex_m3_image_fits_the_due(due_build: Path, capsys: pytest.CaptureFixture[str]) -> None:
    report = (due_build / "size.txt").read_text(encoding="utf-8")
    headline = report.splitlines()[0]
    with capsys.disabled():  # the figures belong in the CI log
        print(f"\n{headline}")
    flash, ram = (int(x) for x in re.findall(r"(?:flash|RAM) (\d+) of", headline))
    assert 10_000 < flash < DUE_FLASH // 4, headline  # the logic, not an empty image; room for the real core
    assert ram < DUE_RAM // 2, headline
    header = subprocess.run(["arm-none-eabi-readelf", "-h", "-A", str(due_build / "linarm_due.elf")],
                            capture_output=True, text=True, timeout=60).stdout
    assert "ARM" in header and "v7" in header and "Thumb-2" in header, header  # Cortex-M3: ARMv7-M, Thumb-2


# ---------------------------------------------------------------------------------------------
# 32-bit ARM Linux under qemu: ILP32 and unsigned char
# ---------------------------------------------------------------------------------------------


def test_arm_build_has_the_dues_abi(arm_build: Path) -> None:
    header = subprocess.run(["file", str(arm_build / "linarm_unit_tests")], capture_output=True, text=True,
                            timeout=60).stdout if shutil.which("file") else "ELF 32-bit LSB executable, ARM"
    assert "32-bit" in header and "ARM" in header, header


def test_cpp_unit_tests_pass_under_qemu_arm(arm_build: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = subprocess.run(qemu(arm_build, "linarm_unit_tests"), capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    summary = result.stdout.strip().splitlines()[-1]
    with capsys.disabled():
        print(f"\nC++ unit tests under qemu-arm (ILP32, unsigned char): {summary}")
    assert summary.endswith(" 0 failed") and int(summary.split()[0]) >= 20, summary
    assert "[  OK  ] abi_is_the_dues" in result.stdout  # the binary really is ILP32 with unsigned char


def test_shared_scenarios_pass_under_qemu_arm(arm_build: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every shared scenario against the ARM build; one summary line for the CI log."""
    failures: list[str] = []
    for scenario in SCENARIOS:
        setup = scenario.setup
        target = FirmwareTarget(qemu(arm_build, "linarm_sil"), setup.get("centre", 0.20),
                                setup.get("start_homed", False), setup.get("service", False))
        try:
            run_scenario(target, scenario)
        except (AssertionError, RuntimeError) as exc:
            failures.append(f"{scenario.id}: {exc}")
    with capsys.disabled():
        print(f"\nshared protocol scenarios under qemu-arm (ILP32, unsigned char): "
              f"{len(SCENARIOS) - len(failures)} of {len(SCENARIOS)} passed")
    assert not failures, "\n".join(failures)
    assert len(SCENARIOS) >= 25


# ---------------------------------------------------------------------------------------------
# Differential fuzzing of the receive path: ARM build, host build and Python simulator agree
# ---------------------------------------------------------------------------------------------

ISSUE_STREAM = b";27,1," + b"9" * 58 + b"4294967299,5;"  # ACKed resetError on the LP64 host build
HUGE = [b"4294967299", b"2147483647", b"2147483648", b"4294967295", b"4294967296", b"-2147483648",
        b"-2147483649", b"99999999999999999999", b"65535", b"65536", b"65539", b"255", b"256", b"305", b"-1",
        b"-255", b"0049", b"+3", b" 12", b"\t7", b"1e3", b"0x10"]
ALPHABET = b"0123456789,,,;;//--+ \t\r\n\x00\xff\x80ab"


def _valid_frame(rng: random.Random) -> bytes:
    cmd = rng.choice(HOST_COMMANDS)
    args: list[Any] = []
    for arg in cmd.args:
        if arg.kind.value == "bool":
            args.append(rng.random() < 0.5)
        elif arg.kind.value == "int":
            args.append(rng.randint(int(arg.min or 0), int(arg.max or 0)))
        else:
            args.append(rng.choice([0.0, 0.01, 0.1, 0.25, 0.5, 1.0, 5.0, 60.0, 1e6, -0.3, rng.uniform(-2, 2)]))
    try:
        return encode_command(cmd.name, rng.randint(0, 65535), *args)
    except ValueError:
        return encode_command("identify", rng.randint(0, 65535))


def _overlong(rng: random.Random) -> bytes:
    head = b"%d,%d," % (rng.randint(0, 60), rng.randint(0, 70000))
    fill = 63 - len(head) + rng.randint(-3, 3)  # the 4.2.0 buffer wraps after 63 stored bytes
    tail = rng.choice(HUGE) + rng.choice([b",5", b",%d" % rng.randint(0, 99999), b"", b",1,2", b",/,"])
    return b";" + head + bytes(rng.choice(b"0123456789") for _ in range(max(0, fill))) + tail + b";"


def _garbage(rng: random.Random) -> bytes:
    return bytes(rng.choice(ALPHABET) if rng.random() < 0.8 else rng.randrange(256)
                 for _ in range(rng.randint(1, 90)))


def _huge_id(rng: random.Random) -> bytes:
    return rng.choice(HUGE) + b",%d" % rng.randint(0, 65535) + rng.choice([b"", b",1", b",0,0"]) + b";"


def fuzz_streams(n: int, seed: int = 18) -> list[bytes]:
    rng = random.Random(seed)
    makers = (_valid_frame, _overlong, _garbage, _huge_id)
    streams = [ISSUE_STREAM]
    while len(streams) < n:
        pieces = [rng.choice(makers)(rng) for _ in range(rng.randint(1, 4))]
        streams.append(b"".join(pieces) + b";")
    return streams


def normalise(data: bytes) -> list[tuple[Any, ...]]:
    """The replies that must agree: kind, seq, command id, code / ACK values (messages are free text)."""
    decoder = CmdMessengerDecoder()
    out: list[tuple[Any, ...]] = []
    for frame in decoder.feed(data):
        msg = decode_controller_frame(frame)
        if isinstance(msg, Identify):
            out.append(("identify", msg.seq, msg.firmware_version))
        elif isinstance(msg, Ack):
            out.append(("ack", msg.seq, msg.cmd_id, tuple(sorted(msg.values.items()))))
        elif isinstance(msg, ErrorReply):
            out.append(("error", msg.seq, msg.cmd_id, msg.code.name))
        elif isinstance(msg, LinarmState):
            out.append(("linarmState", *(getattr(msg, f) for f in msg.__slots__[1:])))  # type: ignore[attr-defined]
        elif isinstance(msg, (MotorState, VsaState)):
            out.append((type(msg).__name__, getattr(msg, "index", None)))
        else:
            out.append((type(msg).__name__,))
    assert decoder.frames_bad == 0, decoder.last_error
    return out


class Lockstep:
    """A SIL in lockstep mode, restarted ("N") before each stream."""

    def __init__(self, argv: list[str]) -> None:
        self.target = FirmwareTarget(argv)
        self.target.advance(0.0)  # the boot IDENTIFY

    def replies(self, stream: bytes) -> bytes:
        self.target.restart()
        return self.target.send(stream)

    def close(self) -> None:
        self.target.close()


def simulator_replies(stream: bytes) -> bytes:
    core = LinarmSimCore(firmware_version="sil-1.0")
    core.stream_bytes()  # the boot IDENTIFY
    return core.handle_host_bytes(stream) + core.stream_bytes()


def test_fuzzed_streams_get_the_same_replies_everywhere(arm_build: Path, capsys: pytest.CaptureFixture[str]) -> None:
    host = Lockstep([str(build_firmware("linarm_sil") / "linarm_sil")])
    arm = Lockstep(qemu(arm_build, "linarm_sil"))
    differences: list[str] = []
    replied = 0
    try:
        for stream in fuzz_streams(FUZZ_STREAMS):
            want = normalise(simulator_replies(stream))
            got_arm = normalise(arm.replies(stream))
            got_host = normalise(host.replies(stream))
            replied += bool(want)
            if not want == got_arm == got_host and len(differences) < 5:
                differences.append(f"{stream!r}\n  simulator {want}\n  ARM       {got_arm}\n  host      {got_host}")
    finally:
        host.close()
        arm.close()
    with capsys.disabled():
        print(f"\n{FUZZ_STREAMS} fuzzed receive streams: ARM build, host build and simulator "
              f"{'agree' if not differences else 'DIFFER'} ({replied} streams with replies)")
    assert not differences, "\n".join(differences)
    assert replied > FUZZ_STREAMS // 2  # the streams reach the command handlers, not only the void


def test_the_issue_stream_is_unknown_command_255() -> None:
    """LP64 atol read the tail's 4294967299 as 3 (resetError); the DUE saturates it: id 255, UNKNOWN_COMMAND."""
    assert normalise(simulator_replies(ISSUE_STREAM)) == [("error", 5, 255, "UNKNOWN_COMMAND")]
    assert COMMANDS_BY_NAME["resetError"].id == 3
