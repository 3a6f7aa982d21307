"""The house's picture, drawn from the code (issue #40): the floors of ``tests/test_architecture.py``, the rooms
(the folders of ``app/`` and its top-level modules) and the imports between them.

    python3 tools/house.py                 the floors and rooms in words, and every arrow that runs back up
    python3 tools/house.py --svg FILE      also the picture (docs/architecture.svg is made so)

Read from the source with ``ast`` like the structure test (the same import graph, TYPE_CHECKING included); nothing
of the application is run. An arrow points from the importer to what it imports; one that runs back up a floor
is drawn red (the structure test fails on it).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter, defaultdict
from pathlib import Path
from xml.sax.saxutils import escape

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.test_architecture import app_modules, floor_of, import_graph  # noqa: E402

# What each floor is, in a few words (the order of FLOORS).
FLOOR_WORDS = (
    "the package", "the wire: protocol tables, codecs, constants", "the core: bus, journal, ids, runs, config, files",
    "safety: supervisor, FES limiter, assistance, fault policy", "devices: drivers on QThreads, simulators",
    "therapy: patients, plans, exercises, electrodes", "the session's record: recording, metrics, reports, LSL",
    "the worker process (heavy work)", "the archive and the research export", "the composition root",
    "scripting: the console's kernel and API", "the window", "the application", "the command line",
)


def room_of(module: str) -> str:
    """``app.core.bus`` → ``app/core``; ``app.manager`` → ``app/manager.py``; ``app`` → ``app/__init__.py``."""
    parts = module.split(".")
    if len(parts) == 1:
        return "app/__init__.py"
    path = app_modules(ROOT)[module]
    if len(parts) == 2 and path.name != "__init__.py":
        return f"app/{parts[1]}.py"
    return f"app/{parts[1]}"


def house() -> tuple[dict[int, Counter[str]], Counter[tuple[str, str]], dict[str, int]]:
    """(floor → room → lines, (room, room) → imports, room → floor)."""
    modules = app_modules(ROOT)
    internal, _ = import_graph(ROOT)
    rooms: dict[int, Counter[str]] = defaultdict(Counter)
    floor: dict[str, int] = {}
    for name, path in modules.items():
        room = room_of(name)
        level = floor_of(name)
        rooms[level][room] += sum(1 for _ in path.open(encoding="utf-8"))
        floor[room] = min(floor.get(room, level), level)
    arrows: Counter[tuple[str, str]] = Counter()
    for a, targets in internal.items():
        for b in targets:
            ra, rb = room_of(a), room_of(b)
            if ra != rb:
                arrows[(ra, rb)] += 1
    return rooms, arrows, floor


def words() -> str:
    rooms, arrows, _ = house()
    internal, _ = import_graph(ROOT)
    lines = []
    for level in sorted(rooms, reverse=True):
        names = ", ".join(f"{r} ({n} lines)" for r, n in sorted(rooms[level].items()))
        lines.append(f"floor {level:2d}  {FLOOR_WORDS[level] if 0 <= level < len(FLOOR_WORDS) else '?'}: {names}")
    up = [f"{a} → {b}" for a in sorted(internal) for b in sorted(internal[a]) if floor_of(b) > floor_of(a)]
    lines.append(f"{sum(arrows.values())} imports between rooms; {len(up)} run back up")
    lines += [f"  back up: {u}" for u in up]
    return "\n".join(lines)


def svg() -> str:
    """Floors as bands (ground at the bottom), rooms as boxes, each import between rooms as an arc on the right
    (downward, grey, wider the more imports) or on the left (back up, red)."""
    rooms, arrows, floor = house()
    width, band, left, room_total = 1240, 56, 380, 520
    levels = sorted(rooms)
    height = band * len(levels) + 40
    box: dict[str, tuple[float, float, float, float]] = {}
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'font-family="DejaVu Sans, Arial, sans-serif" font-size="12">',
           f'<rect width="{width}" height="{height}" fill="white"/>']
    for row, level in enumerate(reversed(levels)):  # the top floor first, ground at the bottom
        y = 20 + row * band
        shade = "#f4f7fa" if row % 2 else "#ffffff"
        out.append(f'<rect x="0" y="{y}" width="{width}" height="{band}" fill="{shade}"/>')
        label = FLOOR_WORDS[level] if 0 <= level < len(FLOOR_WORDS) else ""
        out.append(f'<text x="10" y="{y + band / 2 + 4}" fill="#34495e">{level:2d}  {escape(label)}</text>')
        names = sorted(rooms[level])
        room_h = (band - 12 - 4 * (len(names) - 1)) / len(names)  # rooms of one floor stacked: arcs stay apart
        for i, name in enumerate(names):
            top = y + 6 + i * (room_h + 4)
            box[name] = (left, top, room_total, room_h)
            out.append(f'<rect x="{left}" y="{top:.0f}" width="{room_total}" height="{room_h:.0f}" rx="5" '
                       f'fill="#dbe9f6" stroke="#4a6d8c"/>')
            out.append(f'<text x="{left + room_total / 2:.0f}" y="{top + room_h / 2 + 4:.0f}" text-anchor="middle" '
                       f'fill="#1b2a38">{escape(name)} · {rooms[level][name]} lines</text>')
    for (a, b), n in sorted(arrows.items(), key=lambda kv: abs(floor[kv[0][0]] - floor[kv[0][1]])):
        ax, ay, aw, ah = box[a]
        bx, by, bw, bh = box[b]
        up = floor[b] > floor[a]
        span = abs(floor[a] - floor[b]) or 1
        if up:
            x1, x2, bulge, colour = ax, bx, -22 * span, "#d0342c"
        else:
            x1, x2, bulge, colour = ax + aw, bx + bw, 22 * span, "#7f93a6"
        y1, y2 = ay + ah * 0.6, by + bh * 0.4
        cx = max(x1, x2) + bulge if not up else min(x1, x2) + bulge
        out.append(f'<path d="M{x1:.0f},{y1:.0f} C{cx:.0f},{y1:.0f} {cx:.0f},{y2:.0f} {x2:.0f},{y2:.0f}" '
                   f'fill="none" stroke="{colour}" stroke-opacity="0.6" stroke-width="{1 + min(n, 30) / 10:.1f}"/>')
        out.append(f'<circle cx="{x2:.0f}" cy="{y2:.0f}" r="2.5" fill="{colour}"/>')
    out.append(f'<text x="{width - 10}" y="{height - 8}" text-anchor="end" fill="#34495e">arcs: imports, from the '
               f'importer to the dot on what it imports (grey down, red back up); width: how many</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--svg", type=Path, help="write the picture to this file")
    args = ap.parse_args(argv)
    print(words())
    if args.svg:
        args.svg.write_text(svg(), encoding="utf-8")
        print(f"picture: {args.svg}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
