#!/usr/bin/env python3
"""The two set-up commands of the README, self-sufficient on a machine with only Python 3.11+.

    python3 dev.py run  [main.py arguments...]   create .venv if needed, install, start the app
    python3 dev.py test [pytest arguments...]    create .venv if needed, install, run the whole suite
                                                 (3 pytest-xdist workers, 2 on busy cores; 1 when tests are named)

The project is installed into .venv in editable mode with its dependencies (and the `linarmpp`
command); that is redone when pyproject.toml's project or packaging tables change (a hash stamp in .venv).
`test` runs under Xvfb (xvfb-run) when no display is present and xvfb-run exists, so the
OpenGL tests run too; otherwise the suite falls back to Qt's offscreen platform by itself. It runs the suite
on TEST_WORKERS pytest-xdist workers (BUSY_TEST_WORKERS when other programs keep the cores busy), unless the
arguments name tests (a path, a node id, -k) or give -n themselves (``-n 0``: one process): a developer running
one file does not pay the workers' start-up.
Standard library only: this file runs before anything is installed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
STAMP = VENV / ".linarmpp-installed"
# pytest-xdist workers for the whole suite on the 2-core machine it is measured on (docs/decisions.md, "Tests:
# the suite in 7 minutes"): many tests wait on the wall clock, so a third worker uses the cores while two wait
# (2 workers: 513 s of pytest, the cores ~60 % busy; 3: 405 s). When other programs already keep the cores busy
# there are no waits to overlap: a third worker then only starves the real-time tests (with two CPU hogs beside
# it, 3 workers failed 3 tests and reran 6), so the suite takes BUSY_TEST_WORKERS.
TEST_WORKERS = 3
BUSY_TEST_WORKERS = 2
BUSY_IDLE_SHARE = 0.5  # below this share of the cores idle (measured over a second before the start): busy


def idle_share(seconds: float = 1.0) -> float | None:
    """The share of the machine's CPU time left idle over ``seconds`` (Linux /proc/stat), None elsewhere."""
    import time

    def sample() -> tuple[int, int]:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return fields[3] + (fields[4] if len(fields) > 4 else 0), sum(fields)  # idle + iowait, all

    try:
        idle0, total0 = sample()
        time.sleep(seconds)
        idle1, total1 = sample()
    except (OSError, ValueError, IndexError):
        return None
    return (idle1 - idle0) / (total1 - total0) if total1 > total0 else None


def test_workers() -> int:
    """TEST_WORKERS, or BUSY_TEST_WORKERS when the cores are already busy; LINARMPP_TEST_WORKERS overrides."""
    chosen = os.environ.get("LINARMPP_TEST_WORKERS", "")
    if chosen.isdigit():
        return int(chosen)
    share = idle_share()
    if share is not None and share < BUSY_IDLE_SHARE:
        print(f"[dev] the cores are busy ({share:.0%} idle): {BUSY_TEST_WORKERS} workers, not {TEST_WORKERS}",
              flush=True)
        return BUSY_TEST_WORKERS
    return TEST_WORKERS


def venv_python() -> Path:
    if os.name == "nt":
        return VENV / "Scripts" / "python.exe"
    return VENV / "bin" / "python"


def install_spec() -> str:
    """What goes into the venv, as one stamp: the project's metadata and packaging tables (a change to
    dependencies, entry points or packages reinstalls; a change to lint or test settings does not)."""
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    relevant = {k: pyproject.get(k) for k in ("build-system", "project")}
    relevant["setuptools"] = pyproject.get("tool", {}).get("setuptools")
    return json.dumps(relevant, sort_keys=True)


def ensure_venv(with_tests: bool) -> Path:
    target = ".[test]" if with_tests else "."
    digest = hashlib.sha256(f"{target}\n{install_spec()}".encode()).hexdigest()
    if not venv_python().exists():
        print(f"[dev] creating virtual environment in {VENV}", flush=True)
        subprocess.check_call([sys.executable, "-m", "venv", str(VENV)])
    installed = STAMP.read_text(encoding="utf-8").split() if STAMP.exists() else []
    if digest not in installed:
        # Editable: the venv runs this checkout's code, and has the `linarmpp` command and metadata.
        print(f"[dev] installing the project (editable) and its dependencies into {VENV}", flush=True)
        # For the suite, no byte-compiling of every installed file (~20 s of the ~55 s install: mypy, hypothesis,
        # SQLAlchemy…): the suite's processes compile what they import, once (run_tests lets them write it).
        no_compile = ["--no-compile"] if with_tests else []
        subprocess.check_call([str(venv_python()), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                               *no_compile, "-e", target], cwd=ROOT)
        STAMP.write_text("\n".join([*installed, digest]), encoding="utf-8")
    return venv_python()


def run_app(args: list[str]) -> int:
    py = ensure_venv(with_tests=False)
    return subprocess.call([str(py), str(ROOT / "main.py"), *args], cwd=ROOT)


# pytest options whose next argument is a value, never a test to run (e.g. ``--ignore tests/test_x.py``)
VALUE_OPTIONS = {"-c", "-p", "-o", "-m", "-W", "--basetemp", "--rootdir", "--confcutdir", "--junitxml", "--durations",
                 "--deselect", "--ignore", "--ignore-glob", "--timeout", "--maxfail", "--log-file", "--dist", "--tb"}


def names_tests(args: list[str]) -> bool:
    """Whether pytest ``args`` choose the tests to run (a file, folder or node id, or -k) or the workers (-n)."""
    value = False
    for arg in args:
        if value:
            value = False
            if arg in ("no:xdist", "no:xdist.plugin"):
                return True
            continue
        if arg in VALUE_OPTIONS:
            value = True
        elif arg in ("-k", "-n", "--numprocesses") or arg.startswith("--numprocesses=") \
                or (arg[:2] in ("-k", "-n") and len(arg) > 2):  # -k EXPR, -n 0, -kEXPR, -n0
            return True
        elif not arg.startswith("-") and (ROOT / arg.split("::", 1)[0]).exists():
            return True
    return False


def distribution(workers: int) -> list[str]:
    """How the whole suite is spread over ``workers`` pytest-xdist workers."""
    # loadgroup: the tests of a module's shared rig stay on one worker (tests/conftest.py); the order is the suite's
    # own (long modules first), not xdist's (largest group first). A worker that crashes ends the run, failed and
    # saying so: replaced, the crashed worker's group was never handed on and the run waited for it without end
    # (seen after a segmentation fault; tests/test_dev_workers.py).
    return ["-n", str(workers), "--dist", "loadgroup", "--no-loadscope-reorder", "--max-worker-restart", "0"]


def run_tests(args: list[str]) -> int:
    py = ensure_venv(with_tests=True)
    if not names_tests(args):
        args = [*distribution(test_workers()), *args]
    cmd = [str(py), "-m", "pytest", *args]
    env = dict(os.environ)
    # The suite starts hundreds of Python processes (workers, simulators, script kernels, the command line):
    # each reuses the bytecode the first one wrote instead of compiling every module it imports again.
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    if os.name != "nt" and not env.get("DISPLAY") and shutil.which("xvfb-run"):
        # A real X server (Xvfb + Mesa) lets the OpenGL 3D-view tests run; offscreen Qt cannot do GL.
        cmd = ["xvfb-run", "-a", "-s", "-screen 0 1920x1080x24", *cmd]
        env["QT_QPA_PLATFORM"] = "xcb"
    print("[dev] " + " ".join(cmd), flush=True)
    code = subprocess.call(cmd, cwd=ROOT, env=env)
    if code == 5:
        print("[dev] pytest collected no tests: that is a failure here", flush=True)
        return 1
    return code


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"run", "test"}:
        print(__doc__)
        return 2
    return run_app(argv[1:]) if argv[0] == "run" else run_tests(argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
