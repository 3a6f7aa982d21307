"""LINarm++ Manager."""

from __future__ import annotations

DISTRIBUTION = "linarmpp-manager"  # the project's name in pyproject.toml


def _version() -> str:
    """The installed distribution's version; from a checkout that is not installed, pyproject.toml's.
    A checkout is preferred when this package is the checkout's (an editable install's metadata can be
    older than the pyproject.toml it was installed from)."""
    from pathlib import Path

    pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
    if pyproject.is_file():
        import tomllib

        try:
            project = tomllib.loads(pyproject.read_text(encoding="utf-8")).get("project", {})
            if project.get("name") == DISTRIBUTION and project.get("version"):
                return str(project["version"])
        except (OSError, tomllib.TOMLDecodeError):
            pass
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


__version__: str = _version()
