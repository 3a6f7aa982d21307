"""The application's read-only resources: default configuration, patient-model tree, FES profiles,
example scripts, desktop entry and icon.

In the repository they live in the top-level ``resources/`` folder; the wheel ships that folder as
the data directory ``app/_resources`` (setuptools ``package-dir`` mapping, see docs/decisions.md).
``importlib.resources`` finds the installed copy; from a checkout (or an editable install, whose
``app`` package is the checkout's) the folder next to ``app/`` is used. Every lookup goes through
here, so nothing else needs to know where the application is installed.
"""

from __future__ import annotations

from importlib import resources as _importlib_resources
from pathlib import Path

INSTALLED_NAME = "_resources"  # app/_resources inside the wheel (pyproject.toml [tool.setuptools.package-dir])
_CHECKOUT_DIR = Path(__file__).resolve().parents[2] / "resources"


def _find_root() -> Path:
    installed = _importlib_resources.files("app").joinpath(INSTALLED_NAME)
    if isinstance(installed, Path) and installed.is_dir():
        # Callers need real files (YAML loader, a subprocess's arguments, file dialogs): a wheel
        # installs into a folder; a zipped import of this Qt application is not supported.
        return installed
    if _CHECKOUT_DIR.is_dir():
        return _CHECKOUT_DIR
    raise FileNotFoundError(
        f"the application's resources are missing: neither the installed app/{INSTALLED_NAME} nor "
        f"{_CHECKOUT_DIR} exists (a broken installation: reinstall the package)")


RESOURCES: Path = _find_root()
"""The resources folder (a real directory)."""


def resource_path(*parts: str) -> Path:
    """A file or folder inside the resources, e.g. ``resource_path("fes_profiles", "frontal_reaching.yaml")``.
    The path is returned whether or not it exists (callers say what is missing)."""
    return RESOURCES.joinpath(*parts)


DEFAULT_CONFIG_FILE = resource_path("config.default.yaml")
PATIENT_MODEL_FILE = resource_path("patient_model.yaml")
FES_PROFILES_DIR = resource_path("fes_profiles")
SCRIPTS_DIR = resource_path("scripts")
ICON_FILE = resource_path("linarmpp.svg")
DESKTOP_FILE = resource_path("linarmpp.desktop")
