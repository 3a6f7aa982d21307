"""``linarmpp --install-desktop-entry``: put LINarm++ Manager in this user's Linux application menu.

pip and pipx install the desktop entry and the icon inside the package (app/_resources) but not where
a desktop looks for them; this copies both into the user's XDG data folder (no administrator rights):

    $XDG_DATA_HOME/applications/linarmpp.desktop                 (Exec = the absolute path of linarmpp)
    $XDG_DATA_HOME/icons/hicolor/scalable/apps/linarmpp.svg

The command's absolute path is written because a desktop session's PATH often lacks pipx's ~/.local/bin.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from app.core.resources import DESKTOP_FILE, ICON_FILE

COMMAND = "linarmpp"


def xdg_data_home() -> Path:
    return Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")


def installed_command() -> Path:
    """The ``linarmpp`` command of this installation (next to this interpreter), else the one on PATH."""
    scripts = Path(sys.executable).parent
    for candidate in (scripts / COMMAND, scripts / f"{COMMAND}.exe"):
        if candidate.is_file():
            return candidate
    found = shutil.which(COMMAND)
    if found:
        return Path(found)
    raise FileNotFoundError(f"the {COMMAND} command is not installed (pip install . or pipx install . first)")


def _exec_quoted(path: Path) -> str:
    """A path as the desktop entry specification wants it in Exec (quoted when it has reserved characters)."""
    text = str(path)
    if any(c in text for c in ' \t\n"\'\\><~|&;$*?#()`'):
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("`", "\\`").replace("$", "\\$") + '"'
    return text


def desktop_entry_text(command: Path) -> str:
    lines = []
    for line in DESKTOP_FILE.read_text(encoding="utf-8").splitlines():
        if line == f"Exec={COMMAND}":
            line = f"Exec={_exec_quoted(command)}"
        elif line == f"TryExec={COMMAND}":
            line = f"TryExec={command}"  # TryExec is a plain path, not a command line
        lines.append(line)
    return "\n".join(lines) + "\n"


def install_desktop_entry(data_home: Path | None = None, command: Path | None = None) -> list[Path]:
    """Write the desktop entry and the icon; returns the two files written."""
    data_home = data_home or xdg_data_home()
    command = command or installed_command()
    entry = data_home / "applications" / DESKTOP_FILE.name
    icon = data_home / "icons" / "hicolor" / "scalable" / "apps" / ICON_FILE.name
    entry.parent.mkdir(parents=True, exist_ok=True)
    icon.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(ICON_FILE, icon)
    entry.write_text(desktop_entry_text(command), encoding="utf-8")
    return [entry, icon]
