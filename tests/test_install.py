"""The installable application (issue #21): the wheel holds the application and its resources and
nothing else, and installed into a fresh virtual environment it runs from any folder.

The wheel is built from a clean copy of the source tree (setuptools reuses a ``build/`` folder, which
could smuggle in files deleted since). Dependencies come from the package index as for any user;
pip's cache (filled when the suite's own venv was installed) keeps that quick.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

from app.devices.sim.base import HOMED_ENV

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
KEPT_OUT = ("tests/", "bench/", "firmware/", "tools/")
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
NOT_COPIED = {".venv", ".git", "build", "dist", "__pycache__", ".pytest_cache", ".hypothesis", ".ruff_cache"}


NOT_COPIED_SUFFIXES = (".egg-info", ".raw", ".h5", ".pyc")  # build metadata, bench captures, recordings


def _ignore(folder: str, names: list[str]) -> set[str]:
    return {n for n in names if n in NOT_COPIED or n.endswith(NOT_COPIED_SUFFIXES)}


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None, timeout: float = 600) -> str:
    result = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    output = f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    assert result.returncode == 0, f"{' '.join(cmd)} -> {result.returncode}\n{output}"
    return result.stdout


def _bin(venv: Path, name: str) -> Path:
    return venv / ("Scripts" if os.name == "nt" else "bin") / (f"{name}.exe" if os.name == "nt" else name)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("wheel")
    source = work / "source"
    shutil.copytree(ROOT, source, ignore=_ignore, symlinks=True)
    _run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "-w", str(work / "dist"), "-q"], cwd=work)
    wheels = list((work / "dist").glob("linarmpp_manager-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_the_wheel_holds_the_application_and_its_resources_and_nothing_else(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    resources = {f"app/_resources/{p.relative_to(ROOT / 'resources').as_posix()}"
                 for p in (ROOT / "resources").rglob("*") if p.is_file() and "__pycache__" not in p.parts}
    code = {p.relative_to(ROOT).as_posix() for p in (ROOT / "app").rglob("*.py") if "__pycache__" not in p.parts}
    assert {"app/_resources/config.default.yaml", "app/_resources/patient_model.yaml",
            "app/_resources/linarmpp.desktop", "app/_resources/linarmpp.svg"} <= resources
    assert any(n.startswith("app/_resources/scripts/") for n in resources)
    assert any(n.startswith("app/_resources/fes_profiles/") for n in resources)
    assert resources - names == set(), "resources missing from the wheel"
    assert code - names == set(), "application modules missing from the wheel"
    assert [n for n in names if n.startswith(KEPT_OUT)] == []
    top = {n.split("/")[0] for n in names} - {"app"}
    assert len(top) == 1 and top.pop().endswith(".dist-info"), "only the app package is installed"
    meta = zipfile.ZipFile(wheel)
    dist_info = next(n.split("/")[0] for n in names if n.endswith(".dist-info/entry_points.txt"))
    entry_points = meta.read(f"{dist_info}/entry_points.txt").decode()
    assert "linarmpp = app.cli:console_main" in entry_points
    assert "[gui_scripts]" in entry_points and "linarmpp-gui = app.cli:gui_main" in entry_points
    assert f"\nVersion: {VERSION}\n" in meta.read(f"{dist_info}/METADATA").decode()


@dataclass(frozen=True)
class Installed:
    venv: Path
    python: Path
    linarmpp: Path
    elsewhere: Path  # a folder outside the checkout: the commands run there
    env: dict[str, str]

    def run(self, *args: str, **env: str) -> str:
        return _run([str(self.linarmpp), *args], cwd=self.elsewhere, env={**self.env, **env}, timeout=120)


@pytest.fixture(scope="module")
def installed(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """The wheel in a fresh virtual environment (module scope: a rerun of a timing failure reuses it)."""
    work = tmp_path_factory.mktemp("installed")
    venv = work / "venv"
    # --without-pip: the venv's own copy of pip (ensurepip: ~4 s of CPU) is not what is tested; this process's pip
    # installs into it (--python), resolving the dependencies from the index the same way.
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=work)
    python = _bin(venv, "python")
    # Already-downloaded wheels are reused through pip's cache; the dependencies resolve as for any user.
    # --no-compile: byte-compiling PySide6 and numpy at install took most of the test's time (~30 s of
    # ~40 s); Python compiles what it imports when it runs.
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-compile",
          "--disable-pip-version-check", str(wheel)], cwd=work)
    elsewhere = work / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    # The simulated LINarm starts homed (the homing is tested on its own): the example's run does not wait ~4 s for it.
    env.update(LINARMPP_HOME=str(work / "home"), QT_QPA_PLATFORM="offscreen", **{HOMED_ENV: "1"})
    return Installed(venv, python, _bin(venv, "linarmpp"), elsewhere, env)


def test_the_installed_command_tells_its_version(installed: Installed) -> None:
    assert installed.run("--version").strip() == f"LINarm++ Manager {VERSION}"


def test_the_installed_command_runs_an_installed_example_headless_from_any_folder(installed: Installed) -> None:
    # The example is the installed copy, found the way the application finds it: not the checkout's.
    where = _run([str(installed.python), "-c", "import app, app.core.resources as r; "
                  "print(app.__file__); print(r.resource_path('scripts', 'trigger_exercise.py'))"],
                 cwd=installed.elsewhere, env=installed.env).split()
    package_file, example = Path(where[0]), Path(where[1])
    assert installed.venv in package_file.parents and installed.venv in example.parents, where
    assert example.is_file()

    record = installed.elsewhere / "rec"
    shutil.rmtree(record, ignore_errors=True)  # a rerun starts clean
    installed.run("--headless", "--script", str(example), "--duration", "1", "--record", str(record))
    manifests = list(record.rglob("manifest.json"))
    assert len(manifests) == 1, manifests
    assert json.loads(manifests[0].read_text(encoding="utf-8"))["app_version"] == VERSION


def test_the_installed_command_puts_itself_in_the_users_application_menu(installed: Installed) -> None:
    share = installed.elsewhere / "share"
    installed.run("--install-desktop-entry", XDG_DATA_HOME=str(share))
    entry = (share / "applications" / "linarmpp.desktop").read_text(encoding="utf-8")
    assert f"\nExec={installed.linarmpp}\n" in entry
    assert (share / "icons" / "hicolor" / "scalable" / "apps" / "linarmpp.svg").is_file()


def test_the_installed_window_opens_on_simulated_devices(installed: Installed) -> None:
    """The window loads its resources (icon, FES profiles, example scripts) from the installed copy."""
    shot = installed.elsewhere / "window.png"
    installed.run("--screenshot", str(shot))
    assert shot.is_file() and shot.stat().st_size > 10_000
