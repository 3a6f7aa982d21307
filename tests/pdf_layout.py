"""What a printed PDF looks like to a reader, from poppler's ``pdftotext``: its text in reading order, and the
boxes of its words (``-bbox-layout``), to check that no text box overlaps another or leaves the page."""

from __future__ import annotations

import subprocess
import unicodedata
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

_NS = "{http://www.w3.org/1999/xhtml}"


@dataclass(frozen=True)
class Word:
    page: int
    text: str
    x0: float
    y0: float
    x1: float
    y1: float


def pdf_text(pdf: Path, layout: bool = False) -> str:
    """The text as drawn (``-raw``: a table cell's wrapped lines stay together), ligatures spelled out (ﬁ → fi);
    ``layout``: as it stands on the page."""
    out = subprocess.run(["pdftotext", "-layout" if layout else "-raw", str(pdf), "-"], check=True,
                         capture_output=True, text=True, timeout=60).stdout
    return unicodedata.normalize("NFKC", out)


def pdf_words(pdf: Path) -> tuple[list[Word], list[tuple[float, float]]]:
    """Every word with its box, and each page's (width, height), in points."""
    xml = subprocess.run(["pdftotext", "-bbox-layout", str(pdf), "-"], check=True, capture_output=True, text=True,
                         timeout=60).stdout
    root = ET.fromstring(xml)
    words: list[Word] = []
    sizes: list[tuple[float, float]] = []
    for k, page in enumerate(root.iter(f"{_NS}page")):
        sizes.append((float(page.get("width", 0)), float(page.get("height", 0))))
        for w in page.iter(f"{_NS}word"):
            words.append(Word(k + 1, w.text or "", float(w.get("xMin", 0)), float(w.get("yMin", 0)),
                              float(w.get("xMax", 0)), float(w.get("yMax", 0))))
    return words, sizes


def overlaps(pdf: Path, tolerance: float = 0.5) -> list[str]:
    """Pairs of words whose boxes overlap by more than ``tolerance`` points both ways, and words off the page,
    as readable lines (empty when the layout is clean)."""
    words, sizes = pdf_words(pdf)
    problems: list[str] = []
    by_page: dict[int, list[Word]] = {}
    for w in words:
        by_page.setdefault(w.page, []).append(w)
        width, height = sizes[w.page - 1]
        if w.x0 < -tolerance or w.y0 < -tolerance or w.x1 > width + tolerance or w.y1 > height + tolerance:
            problems.append(f"page {w.page}: {w.text!r} leaves the page ({w.x0:.1f}..{w.x1:.1f})")
    for page, ws in by_page.items():
        ws = sorted(ws, key=lambda w: w.y0)
        for i, a in enumerate(ws):
            for b in ws[i + 1:]:
                if b.y0 >= a.y1 - tolerance:
                    break
                dx = min(a.x1, b.x1) - max(a.x0, b.x0)
                dy = min(a.y1, b.y1) - max(a.y0, b.y0)
                if dx > tolerance and dy > tolerance:
                    problems.append(f"page {page}: {a.text!r} overlaps {b.text!r} "
                                    f"({a.x0:.1f},{a.y0:.1f})-({b.x0:.1f},{b.y0:.1f})")
    return problems
