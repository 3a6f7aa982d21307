"""Light and dark palettes (Fusion style) and the matching pyqtgraph colours.

``apply_palette(app, "light" | "dark")`` sets both; frames read the current colours through
:func:`colours` when they build plots, so a plot created after the switch matches the window.
Curve colours are the Okabe–Ito set (distinguishable with the common colour-vision deficiencies).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import pyqtgraph as pg
from PySide6.QtGui import QColor, QPalette
from PySide6.QtWidgets import QApplication

PaletteName = Literal["light", "dark"]


@dataclass(frozen=True)
class ThemeColours:
    name: PaletteName
    window: str
    base: str
    text: str
    plot_background: str
    plot_foreground: str
    grid_alpha: float
    curves: tuple[str, ...]
    ok: str  # connected, no error
    warn: str  # homing, silent
    bad: str  # error, disconnected
    idle: str  # inactive / absent


_OKABE_ITO_LIGHT = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#B8A000")
_OKABE_ITO_DARK = ("#56B4E9", "#E69F00", "#009E73", "#CC79A7", "#F0E442", "#D55E00", "#FFFFFF", "#0072B2")

THEMES: dict[str, ThemeColours] = {
    "light": ThemeColours("light", "#efefef", "#ffffff", "#111111", "#ffffff", "#222222", 0.25,
                          _OKABE_ITO_LIGHT, "#2e7d32", "#ef6c00", "#c62828", "#757575"),
    "dark": ThemeColours("dark", "#2b2b2b", "#1e1e1e", "#e6e6e6", "#141414", "#d0d0d0", 0.3,
                         _OKABE_ITO_DARK, "#66bb6a", "#ffa726", "#ef5350", "#9e9e9e"),
}

_current: ThemeColours = THEMES["light"]


def colours() -> ThemeColours:
    """The colours of the palette applied last (light until ``apply_palette`` is called)."""
    return _current


def curve_colour(index: int) -> str:
    curves = _current.curves
    return curves[index % len(curves)]


def _qpalette(c: ThemeColours) -> QPalette:
    pal = QPalette()
    R = QPalette.ColorRole
    G = QPalette.ColorGroup
    if c.name == "dark":
        pal.setColor(R.Window, QColor(c.window))
        pal.setColor(R.WindowText, QColor(c.text))
        pal.setColor(R.Base, QColor(c.base))
        pal.setColor(R.AlternateBase, QColor("#333333"))
        pal.setColor(R.ToolTipBase, QColor("#3c3c3c"))
        pal.setColor(R.ToolTipText, QColor(c.text))
        pal.setColor(R.Text, QColor(c.text))
        pal.setColor(R.Button, QColor("#3a3a3a"))
        pal.setColor(R.ButtonText, QColor(c.text))
        pal.setColor(R.BrightText, QColor("#ff5252"))
        pal.setColor(R.Link, QColor("#64b5f6"))
        pal.setColor(R.Highlight, QColor("#1e88e5"))
        pal.setColor(R.HighlightedText, QColor("#ffffff"))
        pal.setColor(R.PlaceholderText, QColor("#8a8a8a"))
        # Fusion draws frames and check-box outlines from these: keep them visible on dark.
        pal.setColor(R.Light, QColor("#5a5a5a"))
        pal.setColor(R.Midlight, QColor("#4a4a4a"))
        pal.setColor(R.Mid, QColor("#8a8a8a"))
        pal.setColor(R.Dark, QColor("#9a9a9a"))
        pal.setColor(R.Shadow, QColor("#101010"))
        for role in (R.WindowText, R.Text, R.ButtonText):
            pal.setColor(G.Disabled, role, QColor("#7a7a7a"))
    else:
        pal.setColor(R.Window, QColor(c.window))
        pal.setColor(R.WindowText, QColor(c.text))
        pal.setColor(R.Base, QColor(c.base))
        pal.setColor(R.AlternateBase, QColor("#f5f5f5"))
        pal.setColor(R.Text, QColor(c.text))
        pal.setColor(R.Button, QColor("#e4e4e4"))
        pal.setColor(R.ButtonText, QColor(c.text))
        pal.setColor(R.Highlight, QColor("#1565c0"))
        pal.setColor(R.HighlightedText, QColor("#ffffff"))
        for role in (R.WindowText, R.Text, R.ButtonText):
            pal.setColor(G.Disabled, role, QColor("#9e9e9e"))
    return pal


def apply_palette(app: QApplication, name: str = "light") -> ThemeColours:
    """Fusion style with the light or dark palette, and pyqtgraph's default colours to match
    (plots created afterwards use them; existing plots keep theirs)."""
    global _current
    if name not in THEMES:
        raise ValueError(f"unknown palette {name!r} (light or dark)")
    _current = THEMES[name]
    app.setStyle("Fusion")
    app.setPalette(_qpalette(_current))
    pg.setConfigOptions(background=_current.plot_background, foreground=_current.plot_foreground,
                        antialias=False)
    return _current
