"""The type checker is part of the suite (issue #40): strict on the core floors (the wire, the core, safety) and on
the Protocols of app/therapy/services.py, which tests/typecheck_hosts.py holds against the manager and the script
runner that fulfil them — a Protocol that drifts from its implementation fails here. Settings: pyproject.toml's
[tool.mypy]."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import ROOT


def test_the_type_checker_passes_on_the_core_and_the_hosts() -> None:
    result = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary"], cwd=ROOT, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
