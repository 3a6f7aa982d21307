"""Issue #25, the kernel's rows: a script cannot push work onto the application.

* files the application opens for a script (``fes.loadFile``) are regular files under a size limit, read
  with a timeout: ``/dev/zero``, a named pipe, a folder and an oversized file are refused with a plain error
  that reaches the script;
* a process a script starts — even one that left the kernel's session with ``setsid`` and holds the kernel's
  socket — ends with Stop, with the runner's close and when the application is killed;
* the bridge survives any line (deep nesting, a huge line, invalid UTF-8, a lone surrogate, a huge number):
  that script ends with an error saying why, the next script works;
* a flood of calls and a flood of refused requests are refused and counted, with a bounded number of log
  lines (a summary, not one line per request), and past REFUSAL_BURST refusals the flooding script is
  ended (each refusal still costs the application a parse and an answer);
* no helper process holds a link key in ``/proc/<pid>/environ``.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from app.core import fes_profile
from app.scripting import bridge as bridge_module
from app.scripting import kernel_process
from app.scripting.runner import ScriptRunner
from app.wire.udp_frames import LINK_KEY_ENV, PatientModelFrame
from tests.test_script_runner import FakeManager, Output, close_runners, started, wait_for

__all__ = ["close_runners"]  # the fixture, used by every test here (autouse)
ROOT = Path(__file__).resolve().parent.parent
# the limits, read softly so that this file also runs (and fails for the right reasons) on the code before #25
MAX_PROFILE_BYTES = getattr(fes_profile, "MAX_PROFILE_BYTES", 256 * 1024)
REFUSALS_LOGGED = getattr(bridge_module, "REFUSALS_LOGGED", 10)
REFUSAL_BURST = getattr(bridge_module, "REFUSAL_BURST", 1000)
CALL_RATE = getattr(bridge_module, "CALL_RATE", 2000.0)
CALL_BURST = getattr(bridge_module, "CALL_BURST", 200)
CALL_QUEUE_S = getattr(bridge_module, "CALL_QUEUE_S", 0.05)


@pytest.fixture
def manager() -> FakeManager:
    return FakeManager()


@pytest.fixture
def output() -> Output:
    return Output()


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def session_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[3])


def kill_quietly(pid: int | None) -> None:
    if pid is not None and alive(pid):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


# ---------------------------------------------------------------------------------------------- files
LOAD = '''
try:
    fes.loadFile({path!r})
except Exception as exc:
    print("refused:", type(exc).__name__, exc)
else:
    print("loaded")
'''


def _unblock_fifo(path: Path) -> None:
    """A reader blocked in open() on the pipe (the code before the fix) gets its writer and EOF."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
    except OSError:
        return
    os.close(fd)


@pytest.mark.realtime  # a bound on the wall clock
@pytest.mark.parametrize("case, words", [
    ("/dev/zero", "a character device, not a regular file (refused)"),
    ("a named pipe", "a named pipe, not a regular file (refused)"),
    ("a folder", "a folder, not a regular file (refused)"),
    ("an oversized file", f"more than the {MAX_PROFILE_BYTES} allowed (refused)"),
])
def test_a_file_the_app_opens_for_a_script_is_a_bounded_regular_file(manager: FakeManager, output: Output,
                                                                      tmp_path: Path, case: str,
                                                                      words: str) -> None:
    path = {"/dev/zero": Path("/dev/zero"), "a named pipe": tmp_path / "pipe", "a folder": tmp_path,
            "an oversized file": tmp_path / "big.yaml"}[case]
    if case == "a named pipe":
        os.mkfifo(path)
    if case == "an oversized file":
        path.write_text("# " + "x" * MAX_PROFILE_BYTES + "\nname: big\n")
    runner = ScriptRunner(manager, output, home_first=False)
    assert runner.ready(5.0)
    t0 = time.monotonic()
    try:
        runner.start(LOAD.format(path=str(path)), "<load>")
        # A read that blocks (a pipe with no writer) or never ends (/dev/zero) never answers: the deadline is
        # that hang's, not a speed goal (a loaded machine took 2.6 s to start the script and refuse).
        assert wait_for(lambda: "refused:" in output.text() or "loaded" in output.text(), 15.0), output.text()
        took = time.monotonic() - t0
        assert runner.wait(5.0)
    finally:
        if case == "a named pipe":
            _unblock_fifo(path)
    text = output.text("stdout")
    assert "refused: ValueError" in text and words in text and str(path) in text, text
    print(f"refused in {took:.2f} s")
    assert runner.result is not None and runner.result.status == "finished"


def test_read_user_file_reads_regular_files_and_refuses_the_rest(tmp_path: Path) -> None:
    from app.core import safe_files

    ok = tmp_path / "ok.yaml"
    ok.write_bytes(b"name: ok\n")
    assert safe_files.read_user_file(ok, 100, 1.0) == b"name: ok\n"
    # a procfs file says size 0 and then has more: the read itself is bounded
    with pytest.raises(safe_files.UserFileError, match="larger than 16 bytes"):
        safe_files.read_user_file("/proc/self/status", 16, 1.0)
    with pytest.raises(safe_files.UserFileError, match="no such file"):
        safe_files.read_user_file(tmp_path / "missing", 100, 1.0)
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes(b"name: caf\xe9\n")
    with pytest.raises(safe_files.UserFileError, match="line 1: not UTF-8"):
        safe_files.read_user_text(bad, 100, 1.0)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for target in (fifo, Path("/dev/null"), tmp_path):
        with pytest.raises(safe_files.UserFileError, match="not a regular file"):
            safe_files.check_writable_target(target)
    safe_files.check_writable_target(ok)
    safe_files.check_writable_target(tmp_path / "new.yaml")


# ---------------------------------------------------------------------------------------------- processes
ESCAPE = '''
import os, posix
r, w = os.pipe()
pid = os.fork()
if pid == 0:
    try:  # leave the kernel's session, then double-fork: the grandchild is nobody's child, and it holds
        os.setsid()  # every descriptor the kernel had, the kernel's socket included
        if os.fork() == 0:
            os.write(w, b"%d\\n" % os.getpid())
            os.execv({sleep!r}, ["sleep", "300"])
    finally:
        posix._exit(0)
os.waitpid(pid, 0)
print("escaped", os.read(r, 64).decode().strip())
time.sleep(1e6)
'''


def escape_script() -> str:
    sleep = shutil.which("sleep")
    assert sleep is not None
    return ESCAPE.format(sleep=sleep)


def escaped_pid(output: Output) -> int:
    assert wait_for(lambda: "escaped" in output.text(), 5.0), output.text()
    return int(output.text("stdout").split("escaped", 1)[1].split()[0])


@pytest.mark.realtime  # a bound on the wall clock
@pytest.mark.parametrize("how", ["Stop", "the runner's close"])
def test_a_setsid_grandchild_ends_with_stop_and_with_close(manager: FakeManager, output: Output, how: str) -> None:
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start(escape_script(), "<escape>")
    pid = escaped_pid(output)
    try:
        assert alive(pid)
        kernel_pid = runner.kernel_pid
        assert kernel_pid is not None and session_of(pid) != session_of(kernel_pid), "it left the kernel's session"
        t0 = time.monotonic()
        if how == "Stop":
            assert runner.stop("test stop", wait_s=2.0)
        else:
            runner.close()
        assert wait_for(lambda: not alive(pid), 3.0), f"the script's process {pid} outlived {how}"
        took = time.monotonic() - t0
        assert took < 1.0, f"it ended {took:.2f} s after {how}"
    finally:
        kill_quietly(pid)
    if how == "Stop":
        assert runner.result is not None and runner.result.status == "stopped"
        assert "ended with it" in output.text("info")
        runner.start("print('next one runs')\n", "<next>")
        assert runner.wait(3.0) and runner.result.status == "finished"


APP = '''
import sys, time
from tests.test_script_runner import FakeManager
from app.scripting.runner import ScriptRunner
runner = ScriptRunner(FakeManager(), lambda s, t: (sys.stdout.write(t), sys.stdout.flush()), home_first=False)
runner.start(sys.argv[1], "<escape>")
print("kernel", runner.kernel_pid, flush=True)
time.sleep(60)
'''


@pytest.mark.realtime  # a bound on the wall clock
def test_a_setsid_grandchild_ends_when_the_application_is_killed() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    app = subprocess.Popen([sys.executable, "-c", APP, escape_script()], cwd=str(ROOT), env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    pid = kernel_pid = None
    try:
        assert app.stdout is not None
        deadline = time.monotonic() + 20.0
        while (pid is None or kernel_pid is None) and time.monotonic() < deadline:
            line = app.stdout.readline()
            if not line:
                break
            if line.startswith("kernel "):
                kernel_pid = int(line.split()[1])
            if line.startswith("escaped "):
                pid = int(line.split()[1])
        assert pid is not None and kernel_pid is not None and alive(pid) and alive(kernel_pid)
        app.kill()  # no shutdown hook runs: only what the application's death itself closes
        app.wait(5.0)
        assert wait_for(lambda: not alive(pid) and not alive(kernel_pid), 3.0), \
            f"alive after the application's death: {[p for p in (pid, kernel_pid) if alive(p)]}"
    finally:
        if app.poll() is None:
            app.kill()
            app.wait(5.0)
        kill_quietly(pid)
        kill_quietly(kernel_pid)


# ---------------------------------------------------------------------------------------------- bad lines
BAD_LINE = '''
import gc, socket
link = next(o for o in gc.get_objects() if isinstance(o, socket.socket) and o.family == socket.AF_UNIX)
line = {line}
print("sending")
for _ in range({times}):
    link.sendall(line)
wait(5)
print("after the bad line")
'''
BAD_LINES = {
    "deep JSON": ('b"[" * 200000 + b"\\n"', 3, "nested too deeply"),
    "a huge line": ('b\'{"op": "out", "stream": "stdout", "text": "\' + b"x" * (5 << 20) + b\'"}\\n\'', 1,
                    "longer than 4 MB"),
    "invalid UTF-8": ('b\'{"op": "out", "stream": "stdout", "text": "\\xff\\xfe"}\\n\'', 1, "not UTF-8"),
    "a lone surrogate": ('b\'{"op": "out", "stream": "stdout", "text": "\\\\ud800"}\\n\'', 1, "not valid Unicode"),
    "a huge number": ('b\'{"op": "call", "id": \' + b"9" * 5000 + b"}\\n"', 1, "not JSON"),
    "not an object": ('b\'["a list"]\\n\'', 1, "not a JSON object"),
}


@pytest.mark.realtime  # a bound on the wall clock
@pytest.mark.parametrize("case", list(BAD_LINES))
def test_a_bad_line_ends_that_script_not_the_bridge(manager: FakeManager, output: Output, case: str) -> None:
    line, times, words = BAD_LINES[case]
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start(BAD_LINE.format(line=line, times=times), "<bad>")
    started(runner, output, "sending")
    t0 = time.monotonic()
    assert runner.wait(5.0), f"the run did not end: {output.text()[-500:]}"
    took = time.monotonic() - t0
    result = runner.result
    assert result is not None and result.status == "error", (result, output.text()[-500:])
    assert "the script was ended" in result.message and words in result.message, result.message
    assert "after the bad line" not in output.text()
    assert took < 2.0, f"the script ended {took:.2f} s after its bad line"
    assert manager.fes.fes_stops, "the devices went to the safe state"
    assert runner.ready(5.0), "a fresh kernel is ready"
    runner.start("print('next one runs', linarm.linarmState.controlState)\n", "<next>")
    assert runner.wait(3.0) and runner.result.status == "finished", (runner.result, output.text()[-500:])
    assert "next one runs" in output.text()


# ---------------------------------------------------------------------------------------------- floods
FLOOD = '''
import gc, socket, json
link = next(o for o in gc.get_objects() if isinstance(o, socket.socket) and o.family == socket.AF_UNIX)
lines = b"".join((json.dumps({{"op": "call", "id": 10**9 + i, "obj": {obj!r}, "name": {name!r}, "args": []}})
                  + "\\n").encode() for i in range({n}))
print("flooding")
link.sendall(lines)
wait(5)
print("after the flood")
'''
FLOOD_SIZE = 20000


def bridge_log_lines(caplog: pytest.LogCaptureFixture) -> int:
    return sum(1 for r in caplog.records if r.name.startswith("app.scripting"))


@pytest.mark.realtime  # a bound on the wall clock
def test_a_flood_of_refused_requests_is_counted_with_bounded_log_lines(manager: FakeManager, output: Output,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="app.scripting")
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start(FLOOD.format(obj="os", name="system", n=FLOOD_SIZE), "<flood>")
    started(runner, output, "flooding")
    t0 = time.monotonic()
    assert runner.wait(20.0), output.text()[-500:]
    took = time.monotonic() - t0
    lines = bridge_log_lines(caplog)
    assert lines <= REFUSALS_LOGGED + 5, f"{lines} log lines for a flood of {FLOOD_SIZE} refused requests"
    counted = re.search(r"(\d+) requests of the script were refused \((\d+) not an API call\)", output.text())
    assert counted is not None and counted.group(1) == counted.group(2), output.text()[-500:]
    refused = int(counted.group(1))
    assert REFUSAL_BURST <= refused <= FLOOD_SIZE
    assert runner.result is not None and runner.result.status == "error", (runner.result, output.text()[-500:])
    assert "a flood of requests (more than" in runner.result.message
    assert "after the flood" not in output.text()
    assert took < 3.0, f"the flood went on for {took:.1f} s"
    events = manager.supervisor.events
    assert len([d for k, d in events if k == "script_request_refused"]) == bridge_module.REFUSALS_RECORDED
    summaries = [d for k, d in events if k == "script_requests_refused"]
    assert summaries and summaries[-1]["total"] == refused


def test_a_flood_of_calls_is_refused_and_counted(manager: FakeManager, output: Output,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="app.scripting")
    served = [0]

    def config_data() -> dict[str, Any]:
        served[0] += 1
        return {"served": served[0]}

    manager.fes.config_data = config_data  # type: ignore[attr-defined]
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start(FLOOD.format(obj="fes", name="getConfigData", n=FLOOD_SIZE), "<flood>")
    started(runner, output, "flooding")
    t0 = time.monotonic()
    assert runner.wait(20.0), output.text()[-500:]
    took = time.monotonic() - t0
    assert runner.result is not None and runner.result.status == "error", (runner.result, output.text()[-500:])
    assert "a flood of requests (more than" in runner.result.message
    budget = CALL_BURST + CALL_RATE * (took + CALL_QUEUE_S)
    assert served[0] <= budget, f"{served[0]} of {FLOOD_SIZE} flooded calls served in {took:.2f} s"
    counted = re.search(r"(\d+) requests of the script were refused \((\d+) over rate\)", output.text())
    assert counted is not None and counted.group(1) == counted.group(2), output.text()[-500:]
    refused = int(counted.group(1))
    assert refused >= REFUSAL_BURST
    lines = bridge_log_lines(caplog)
    assert lines <= REFUSALS_LOGGED + 5, f"{lines} log lines for {refused} refusals"


def test_a_script_polling_a_value_is_paced_not_refused(manager: FakeManager, output: Output) -> None:
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start("t0 = time.monotonic()\nn = 0\nwhile time.monotonic() - t0 < 1.0:\n    fes.stimulating\n"
                 "    n += 1\nprint('calls', n, time.monotonic() - t0)\n", "<poll>")
    assert runner.wait(10.0)
    assert runner.result is not None and runner.result.status == "finished", (runner.result, output.text())
    n, took = output.text("stdout").split()[1:3]
    rate = int(n) / float(took)
    assert rate <= CALL_RATE * 1.1 + CALL_BURST, f"{rate:.0f} calls a second"
    assert "refused" not in output.text()


def test_a_print_flood_reaches_the_console_bounded(manager: FakeManager, output: Output) -> None:
    from app.scripting import runner as runner_module

    rate = getattr(runner_module, "OUTPUT_RATE", 512 * 1024)
    burst = getattr(runner_module, "OUTPUT_BURST", 4 * 1024 * 1024)
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start("chunk = 'x' * 99999 + '\\n'\nprint('printing')\nfor _ in range(400):\n    print(chunk, end='')\n",
                 "<print>")
    started(runner, output, "printing")
    t0 = time.monotonic()
    assert runner.wait(20.0)
    took = time.monotonic() - t0
    assert runner.result is not None and runner.result.status == "finished", runner.result
    passed = len(output.text("stdout"))
    assert passed <= burst + rate * took + 100_000, f"{passed} characters reached the console in {took:.1f} s"
    dropped = re.search(r"(\d+) characters of the script's output were dropped", output.text("info"))
    assert dropped is not None and int(dropped.group(1)) + passed >= 400 * 100_000


def test_a_script_writing_megabytes_is_slowed_to_the_read_budget(manager: FakeManager, output: Output) -> None:
    rate = getattr(kernel_process, "READ_RATE", 8 * 1024 * 1024)  # the kernel's link reads (bridge.py split, #40)
    burst = getattr(kernel_process, "READ_BURST", 16 * 1024 * 1024)
    runner = ScriptRunner(manager, output, home_first=False)
    runner.start("line = 'x' * 3_000_000\nn = 0\nt0 = time.monotonic()\nwhile time.monotonic() - t0 < 2.0:\n"
                 "    print(line)\n    n += 1\nprint('wrote', n, time.monotonic() - t0)\n", "<megabytes>")
    assert runner.wait(20.0)
    assert runner.result is not None and runner.result.status == "finished", runner.result
    found = re.search(r"wrote (\d+) ([\d.]+)", output.text("stdout"))
    assert found is not None, output.text()[-300:]
    written, took = int(found.group(1)) * 3_000_000, float(found.group(2))
    assert written <= burst + rate * took + 2 * (1 << 20) + 3_000_000, \
        f"the application read {written / 1e6:.0f} MB from the script in {took:.1f} s"


# ---------------------------------------------------------------------------------------------- link keys
def environ_of(pid: int) -> bytes:
    return Path(f"/proc/{pid}/environ").read_bytes()


def test_the_kernel_and_its_warden_hold_no_link_key(manager: FakeManager, output: Output,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LINK_KEY_ENV, "ab" * 32)  # as if the application itself had been handed one
    runner = ScriptRunner(manager, output, home_first=False)
    assert runner.ready(5.0)
    kernel = runner._kernel
    assert kernel is not None
    for pid in {kernel.pid, kernel.proc.pid}:
        env = environ_of(pid)
        assert LINK_KEY_ENV.encode() not in env and b"ab" * 32 not in env


@pytest.mark.parametrize("helper", ["patient model", "VR stand-in"])
def test_a_helper_gets_its_key_through_a_pipe_not_its_environment(qtbot: Any, helper: str) -> None:
    from app.devices import patient_model, vr
    from app.devices.patient_model import free_udp_port
    from app.devices.transport import UdpTransport

    host = "127.0.0.1"
    manager_port, helper_port = free_udp_port(host), free_udp_port(host)
    if helper == "patient model":
        proc = patient_model.embedded_process(host, helper_port, manager_port, extra=["--idle-exit", "5"])
        driver: Any = patient_model.PatientModelDriver(UdpTransport((host, manager_port), (host, helper_port)),
                                                       100.0, process=proc)
        driver.frame_source = lambda seq: PatientModelFrame(seq, 70, 5, 33, 2, 0, 0, 0.1, 0.4)
    else:
        proc = vr.standin_process(host, helper_port, manager_port, extra=["--idle-exit", "5"])
        driver = vr.VrDriver(UdpTransport((host, manager_port), (host, helper_port)), 50.0, process=proc)
    proc.authenticate = True
    proc.start()
    driver.start()
    try:
        qtbot.waitUntil(lambda: driver.datagrams_received >= 3, timeout=10000)
        assert sum(driver.invalid_datagrams.values()) == 0, driver.invalid_datagrams  # the key did arrive
        assert proc.key is not None and proc.pid is not None
        env = environ_of(proc.pid)
        assert proc.key.hex().encode() not in env, "the key is readable in /proc/<helper>/environ"
        assert LINK_KEY_ENV.encode() + b"=" not in env
        fds = os.listdir(f"/proc/{proc.pid}/fd")
        assert all("pipe" not in os.readlink(f"/proc/{proc.pid}/fd/{fd}") for fd in fds
                   if os.path.exists(f"/proc/{proc.pid}/fd/{fd}") and int(fd) > 2), "the key's pipe was closed"
    finally:
        driver.stop()
        proc.stop()
