"""Packaging facts that need no wheel build (issue #21): the resources are found through one module,
the package list in pyproject.toml is complete, the version is the project's everywhere, the command
line has one parser, and the desktop entry and icon are usable."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

import app
from app import cli
from app.core import resources

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_resources_are_found_from_the_checkout() -> None:
    assert resources.RESOURCES == ROOT / "resources"
    for path in (resources.DEFAULT_CONFIG_FILE, resources.PATIENT_MODEL_FILE, resources.ICON_FILE,
                 resources.DESKTOP_FILE, resources.resource_path("scripts", "trigger_exercise.py"),
                 resources.resource_path("fes_profiles", "frontal_reaching.yaml")):
        assert path.is_file(), path


def test_the_lookups_of_other_modules_go_through_app_resources() -> None:
    from app.core.config import DEFAULT_CONFIG_FILE, RESOURCES
    from app.devices.sim.patient_model.decision_tree import DEFAULT_CONFIG_PATH

    assert RESOURCES == resources.RESOURCES and DEFAULT_CONFIG_FILE == resources.DEFAULT_CONFIG_FILE
    assert DEFAULT_CONFIG_PATH == resources.PATIENT_MODEL_FILE


def test_every_package_of_the_application_is_in_the_wheel_list() -> None:
    """pyproject.toml lists the packages explicitly (resources/ is mapped in): a new subpackage of app
    that is not listed would be missing from the installed application."""
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "app").rglob("*.py")
               if "__pycache__" not in p.parts}
    assert on_disk - listed == set(), "add these to [tool.setuptools] packages in pyproject.toml"
    mapped = PYPROJECT["tool"]["setuptools"]["package-dir"]
    assert mapped == {f"app.{resources.INSTALLED_NAME}": "resources"}


def test_the_version_is_the_projects_in_about_manifest_and_command_line(capsys, monkeypatch) -> None:
    from app.session.recording import app_version

    version = PYPROJECT["project"]["version"]
    assert app.__version__ == version and app_version() == version
    with pytest.raises(SystemExit) as stop:
        cli.main(["--version"], prog="linarmpp")
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"LINarm++ Manager {version}"

    from app.ui import main_window

    shown: list[str] = []
    monkeypatch.setattr(main_window.QMessageBox, "about", lambda _parent, _title, text: shown.append(text))
    fake_window = SimpleNamespace(manager=SimpleNamespace(config=SimpleNamespace(source="defaults")))
    main_window.MainWindow.show_about(fake_window)  # type: ignore[arg-type]
    assert f"LINarm++ Manager</b> {version}" in shown[0] and f"Resources: {resources.RESOURCES}" in shown[0]


def test_main_py_and_the_installed_commands_share_one_parser() -> None:
    import main

    assert main.main is cli.main and main.build_parser is cli.build_parser
    scripts = PYPROJECT["project"]["scripts"]
    gui_scripts = PYPROJECT["project"]["gui-scripts"]
    assert scripts == {"linarmpp": "app.cli:console_main"} and gui_scripts == {"linarmpp-gui": "app.cli:gui_main"}
    options = {a.dest for a in cli.build_parser()._actions}
    assert {"config", "headless", "script", "duration", "record", "version"} <= options


def test_the_windows_gui_command_without_a_console_shows_a_refused_configuration(
        tmp_path: Path, monkeypatch, qapp) -> None:
    from PySide6.QtWidgets import QMessageBox

    bad = tmp_path / "site.yaml"
    bad.write_text("ui:\n  palette: neon\n", encoding="utf-8")
    shown: list[str] = []
    monkeypatch.setattr(QMessageBox, "critical", lambda _parent, _title, text: shown.append(text))
    monkeypatch.setattr(cli, "_no_console", False)
    # Logging is not under test; its console handler would keep the stand-in stream closed below.
    monkeypatch.setattr("app.core.logging_setup.setup_logging", lambda *_a, **_k: tmp_path / "log")
    monkeypatch.setattr(sys, "argv", ["linarmpp-gui", "--config", str(bad)])
    monkeypatch.setattr(sys, "stdout", None)  # pythonw: no console streams at all
    monkeypatch.setattr(sys, "stderr", None)
    try:
        assert cli.gui_main() == 2
        assert sys.stderr is not None and sys.stdout is not None  # printing no longer fails
    finally:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.close()
    assert len(shown) == 1 and "nothing was started" in shown[0] and "ui.palette" in shown[0]


def test_the_desktop_entry_starts_the_command_with_the_installed_icon(qapp) -> None:
    from PySide6.QtGui import QIcon

    from app.application import apply_desktop_identity

    entry = configparser.ConfigParser(interpolation=None)
    entry.optionxform = str  # type: ignore[assignment,method-assign]  # keys are case-sensitive
    entry.read(resources.DESKTOP_FILE, encoding="utf-8")
    desktop = entry["Desktop Entry"]
    assert desktop["Type"] == "Application" and desktop["Name"] == "LINarm++ Manager"
    assert desktop["Exec"] == "linarmpp" and desktop["Exec"] in PYPROJECT["project"]["scripts"]
    assert desktop["Icon"] == resources.ICON_FILE.stem and desktop["Terminal"] == "false"
    assert desktop["Categories"].endswith(";")

    icon = QIcon(str(resources.ICON_FILE))
    assert not icon.pixmap(64, 64).isNull(), "the SVG icon does not render (Qt's svg image plugin?)"
    apply_desktop_identity(qapp)
    assert not qapp.windowIcon().pixmap(32, 32).isNull()
    assert qapp.desktopFileName() == resources.DESKTOP_FILE.stem


def test_the_desktop_entry_is_installed_into_the_users_menu_with_the_commands_full_path(
        tmp_path: Path, monkeypatch, capsys) -> None:
    from app import desktop_entry

    command = tmp_path / "pipx venvs" / "bin" / "linarmpp"
    entry, icon = desktop_entry.install_desktop_entry(tmp_path / "share", command)
    assert entry == tmp_path / "share" / "applications" / "linarmpp.desktop"
    assert icon.read_bytes() == resources.ICON_FILE.read_bytes() and icon.parent.name == "apps"
    text = entry.read_text(encoding="utf-8")
    assert f'\nExec="{command}"\n' in text and f"\nTryExec={command}\n" in text and "\nIcon=linarmpp\n" in text

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(desktop_entry, "installed_command", lambda: Path("/usr/local/bin/linarmpp"))
    assert cli.main(["--install-desktop-entry"]) == 0
    assert "Exec=/usr/local/bin/linarmpp\n" in (tmp_path / "xdg" / "applications" / "linarmpp.desktop").read_text()
    assert "remove these files to undo" in capsys.readouterr().out


@pytest.mark.skipif(shutil.which("desktop-file-validate") is None, reason="desktop-file-utils is not installed")
def test_the_desktop_entries_pass_the_freedesktop_validator(tmp_path: Path) -> None:
    from app.desktop_entry import install_desktop_entry

    entry, _icon = install_desktop_entry(tmp_path, tmp_path / "with space" / "linarmpp")
    for path in (resources.DESKTOP_FILE, entry):
        result = subprocess.run(["desktop-file-validate", str(path)], capture_output=True, text=True, timeout=30)
        assert result.returncode == 0 and not result.stdout.strip(), result.stdout + result.stderr


def test_installed_example_scripts_are_the_users_code_in_tracebacks() -> None:
    """Installed, the examples lie inside app/ (app/_resources/scripts): their frames must still show."""
    from app.scripting import runner

    assert not runner._is_app_file(str(resources.resource_path("scripts", "trigger_exercise.py")))
    assert runner._is_app_file(runner.__file__)
