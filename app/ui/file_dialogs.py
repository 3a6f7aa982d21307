"""File dialogs that start where the user keeps their files (issue #30: Save profile opened at
``<checkout>/profile.yaml``, Load profile in the install folder).

Each dialog starts in a folder of the user's data folder; folders bundled with the application are offered
as extra places in the dialog's side bar, to open (read-only: saving a bundled file goes to the user's
folder). The two functions are the only way the window asks for a file path, so tests replace them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from PySide6.QtCore import QUrl
from PySide6.QtWidgets import QFileDialog, QWidget

from app.core.resources import RESOURCES


def is_bundled(path: str | Path) -> bool:
    """True for a file installed with the application (never written by the window)."""
    try:
        Path(path).resolve().relative_to(RESOURCES.resolve())
    except ValueError:
        return False
    return True


def _dialog(parent: QWidget | None, title: str, start: Path, filters: str, places: Sequence[Path]) -> QFileDialog:
    dialog = QFileDialog(parent, title, str(start), filters)
    dialog.setOption(QFileDialog.Option.DontUseNativeDialog, True)  # the side bar below is Qt's own
    urls = [QUrl.fromLocalFile(str(start)), *(QUrl.fromLocalFile(str(p)) for p in places if p.is_dir())]
    dialog.setSidebarUrls(urls)
    return dialog


def ask_open_file(parent: QWidget | None, title: str, start: Path, filters: str,
                  places: Sequence[Path] = ()) -> str:
    dialog = _dialog(parent, title, start, filters, places)
    dialog.setFileMode(QFileDialog.FileMode.ExistingFile)
    dialog.setAcceptMode(QFileDialog.AcceptMode.AcceptOpen)
    if dialog.exec() and dialog.selectedFiles():
        return dialog.selectedFiles()[0]
    return ""


def ask_save_file(parent: QWidget | None, title: str, start: Path, filters: str, default_suffix: str = "") -> str:
    """``start`` is the proposed file (in the user's folder); an answer inside the bundled folder is refused by
    the caller (see :func:`is_bundled`)."""
    dialog = _dialog(parent, title, start.parent, filters, ())
    dialog.selectFile(start.name)
    dialog.setAcceptMode(QFileDialog.AcceptMode.AcceptSave)
    if default_suffix:
        dialog.setDefaultSuffix(default_suffix)
    if dialog.exec() and dialog.selectedFiles():
        return dialog.selectedFiles()[0]
    return ""
