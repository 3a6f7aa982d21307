"""Printable reports for the medical record: a PDF per session and a progress PDF per patient.

Drawn with Qt's own PDF writer (QPdfWriter + QPainter: no new dependency): patient, operator, date, the
exercise and its parameters, the per-repetition metrics (app/metrics.py) as tables and plots, the alarms and
interruptions. Also the command line's ``--metrics`` / ``--report`` / ``--progress``.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.metrics import SUMMARY_METRICS, metrics_of_session

# Session metrics shown as trends across sessions (key in the summary → label, unit)
TREND_METRICS: tuple[tuple[str, str, str], ...] = (
    ("peak_speed_m_s", "Peak speed", "m/s"),
    ("sparc", "Smoothness (SPARC)", ""),
    ("range_m", "Range of motion", "m"),
    ("movement_time_s", "Movement time", "s"),
    ("speed_peaks", "Speed peaks", ""),
    ("mean_force_n", "Mean interaction force", "N"),
    ("mean_alpha", "Assistance α", ""),
    ("mean_a_r", "Robot assistance a_r", ""),
)
SCORES: tuple[tuple[str, str], ...] = (
    ("fugl_meyer_ue", "Fugl-Meyer UE (0–66)"),
    ("action_research_arm_test", "ARAT (0–57)"),
    ("box_and_block", "Box and Block (blocks/min)"),
    ("modified_ashworth", "Modified Ashworth (0–4)"),
)
# Repetition table of the session report: (key, header, format)
REPETITION_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("index", "#", "{:d}"),
    ("start_s", "Start s", "{:.1f}"),
    ("movement_time_s", "Move s", "{:.2f}"),
    ("range_m", "Range m", "{:.3f}"),
    ("peak_speed_m_s", "Peak m/s", "{:.3f}"),
    ("mean_speed_m_s", "Mean m/s", "{:.3f}"),
    ("sparc", "SPARC", "{:.2f}"),
    ("speed_peaks", "Peaks", "{:d}"),
    ("peak_force_n", "Force N", "{:.1f}"),
    ("grip_at_start_n", "Grip N", "{:.1f}"),
    ("reaction_time_s", "RT s", "{:.2f}"),
    ("completed", "Done", "{}"),
)


def fmt(value: Any, spec: str = "{:.3g}") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    try:
        return spec.format(value)
    except (ValueError, TypeError):
        return str(value)


# ------------------------------------------------------------------------------------------- data
@dataclass
class SessionReportData:
    folder: Path
    manifest: dict[str, Any]
    metrics: dict[str, Any]
    exercises: list[str]
    position: tuple[list[float], list[float]]  # (t s from the start, handle position m), decimated
    problems: list[str]

    @property
    def patient_id(self) -> str:
        return str(self.manifest.get("patient_id") or self.folder.parent.name)

    @property
    def started(self) -> str:
        return str((self.manifest.get("start") or {}).get("t_wall", ""))


def session_report_data(folder: str | Path) -> SessionReportData:
    from app.recording import load_session

    session = load_session(folder)
    metrics = metrics_of_session(session)
    exercises = [str((e.get("data") or {}).get("name") or "script") for e in session.events
                 if e.get("kind") == "script_start"]
    t: list[float] = []
    x: list[float] = []
    vsa = session.streams.get("linarm.vsa")
    if vsa is not None and len(vsa.t) and "handlePos" in vsa.data:
        step = max(1, len(vsa.t) // 2000)
        t = [float(v) - session.start_mono for v in vsa.t[::step]]
        x = [float(v) for v in vsa.data["handlePos"][::step]]
    return SessionReportData(Path(folder), session.manifest, metrics, exercises, (t, x), list(session.problems))


@dataclass
class ProgressRow:
    """One session of a patient, as a point of the trends."""

    folder: Path
    started: str  # ISO
    exercises: tuple[str, ...]
    summary: dict[str, Any]
    scores: dict[str, Any]  # the clinical scores in the profile at that session
    complete: bool

    def value(self, key: str) -> float | None:
        entry = self.summary.get(key)
        if isinstance(entry, dict):
            return entry.get("mean")
        return entry if isinstance(entry, int | float) else None

    @property
    def date(self) -> str:
        return self.started[:10] or self.folder.name[:8]


def progress_rows(patient_id: str, root: Path | None = None,
                  progress: Callable[[float], None] | None = None) -> list[ProgressRow]:
    """Every session of the patient, oldest first, with its metrics summary (reads every stream)."""
    from app.recording import list_sessions, load_session

    sessions = list(reversed(list_sessions(patient_id, root)))
    rows = []
    for k, s in enumerate(sessions):
        if progress is not None:
            progress(k / max(1, len(sessions)))
        session = load_session(s.folder)
        m = metrics_of_session(session)
        scores = dict(((session.manifest.get("patient") or {}).get("scores")) or {})
        rows.append(ProgressRow(s.folder, s.start, s.exercises, m["summary"], scores, s.complete))
    if progress is not None:
        progress(1.0)
    return rows


# ------------------------------------------------------------------------------------------- drawing
def _ensure_gui_app() -> Any:
    from PySide6.QtCore import QCoreApplication
    from PySide6.QtGui import QGuiApplication

    app = QCoreApplication.instance()
    if app is None:
        import os

        if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # a PDF needs fonts, not a screen
        app = QGuiApplication([sys.argv[0] if sys.argv else "linarmpp"])
    return app


PLOT_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")


class _Pdf:
    """A4 pages drawn top to bottom with a cursor; a new page when the next block does not fit."""

    DPI = 96
    MARGIN = 48

    def __init__(self, path: Path, title: str, footer: str) -> None:
        from PySide6.QtCore import QMarginsF
        from PySide6.QtGui import QPageLayout, QPageSize, QPainter, QPdfWriter

        self.writer = QPdfWriter(str(path))
        self.writer.setResolution(self.DPI)
        self.writer.setTitle(title)
        self.writer.setCreator("LINarm++ Manager")
        self.writer.setPageLayout(QPageLayout(QPageSize(QPageSize.PageSizeId.A4), QPageLayout.Orientation.Portrait,
                                              QMarginsF(0, 0, 0, 0)))
        self.painter = QPainter()
        if not self.painter.begin(self.writer):
            raise OSError(f"cannot write {path}")
        self.width = self.writer.width()
        self.height = self.writer.height()
        self.footer = footer
        self.page = 1
        self.y = float(self.MARGIN)

    @property
    def inner_width(self) -> float:
        return self.width - 2 * self.MARGIN

    def font(self, size: float, bold: bool = False) -> None:
        from PySide6.QtGui import QFont

        f = QFont("DejaVu Sans")
        f.setPointSizeF(size)
        f.setBold(bold)
        self.painter.setFont(f)

    def ensure(self, h: float) -> None:
        if self.y + h > self.height - self.MARGIN - 20:
            self._draw_footer()
            self.writer.newPage()
            self.page += 1
            self.y = float(self.MARGIN)

    def _draw_footer(self) -> None:
        from PySide6.QtCore import QRectF, Qt

        self.font(7)
        self.painter.setPen(self._colour("#555555"))
        self.painter.drawText(QRectF(self.MARGIN, self.height - self.MARGIN, self.inner_width, 16),
                              int(Qt.AlignmentFlag.AlignLeft), self.footer)
        self.painter.drawText(QRectF(self.MARGIN, self.height - self.MARGIN, self.inner_width, 16),
                              int(Qt.AlignmentFlag.AlignRight), f"page {self.page}")

    @staticmethod
    def _colour(name: str) -> Any:
        from PySide6.QtGui import QColor

        return QColor(name)

    def text(self, text: str, size: float = 9, bold: bool = False, colour: str = "#000000", gap: float = 4) -> None:
        from PySide6.QtCore import QRectF, Qt

        self.font(size, bold)
        metrics = self.painter.fontMetrics()
        rect = metrics.boundingRect(0, 0, int(self.inner_width), 10000, int(Qt.TextFlag.TextWordWrap), text)
        self.ensure(rect.height() + gap)
        self.painter.setPen(self._colour(colour))
        self.painter.drawText(QRectF(self.MARGIN, self.y, self.inner_width, rect.height() + 2),
                              int(Qt.TextFlag.TextWordWrap), text)
        self.y += rect.height() + gap

    def heading(self, text: str) -> None:
        self.ensure(60)
        self.y += 6
        self.text(text, 12, True, "#1a3d6d", gap=6)

    def fields(self, pairs: Sequence[tuple[str, str]], label_width: float = 150) -> None:
        from PySide6.QtCore import QRectF, Qt

        for label, value in pairs:
            self.font(9)
            h = self.painter.fontMetrics().boundingRect(0, 0, int(self.inner_width - label_width), 10000,
                                                        int(Qt.TextFlag.TextWordWrap), value).height()
            self.ensure(h + 3)
            self.font(9, True)
            self.painter.setPen(self._colour("#333333"))
            self.painter.drawText(QRectF(self.MARGIN, self.y, label_width, h + 2), 0, label)
            self.font(9)
            self.painter.setPen(self._colour("#000000"))
            self.painter.drawText(QRectF(self.MARGIN + label_width, self.y, self.inner_width - label_width, h + 2),
                                  int(Qt.TextFlag.TextWordWrap), value)
            self.y += h + 3

    def table(self, headers: Sequence[str], rows: Sequence[Sequence[str]], widths: Sequence[float] | None = None,
              size: float = 7.5) -> None:
        from PySide6.QtCore import QRectF, Qt

        widths = list(widths or [1.0] * len(headers))
        scale = self.inner_width / sum(widths)
        widths = [w * scale for w in widths]
        self.font(size)
        row_h = self.painter.fontMetrics().height() + 5

        def draw_row(cells: Sequence[str], bold: bool, shade: bool) -> None:
            self.ensure(row_h)
            if shade:
                self.painter.fillRect(QRectF(self.MARGIN, self.y, self.inner_width, row_h), self._colour("#eef2f7"))
            self.font(size, bold)
            self.painter.setPen(self._colour("#000000"))
            x = float(self.MARGIN)
            for cell, w in zip(cells, widths, strict=False):
                self.painter.drawText(QRectF(x + 3, self.y, w - 6, row_h),
                                      int(Qt.AlignmentFlag.AlignVCenter | Qt.AlignmentFlag.AlignLeft), cell)
                x += w
            self.y += row_h

        self.ensure(row_h * 2)
        draw_row(headers, True, True)
        self.painter.setPen(self._colour("#1a3d6d"))
        self.painter.drawLine(int(self.MARGIN), int(self.y), int(self.MARGIN + self.inner_width), int(self.y))
        for k, row in enumerate(rows):
            if self.y + row_h > self.height - self.MARGIN - 20:
                self.ensure(row_h * 2)
                draw_row(headers, True, True)
            draw_row(row, False, k % 2 == 1)
        self.y += 6

    def plot(self, title: str, series: Sequence[tuple[str, Sequence[float], Sequence[float | None]]],
             unit: str = "", x_label: str = "", width: float | None = None, height: float = 150,
             x_ticks: Sequence[tuple[float, str]] | None = None, shade: Sequence[tuple[float, float]] = (),
             markers: bool = True, left: float | None = None, advance: bool = True) -> None:
        """A line plot: ``series`` = [(name, x, y)] (None values skipped)."""
        from PySide6.QtCore import QPointF, QRectF, Qt
        from PySide6.QtGui import QPen, QPolygonF

        width = width or self.inner_width
        if advance:
            self.ensure(height + 10)
        p = self.painter
        x0 = self.MARGIN if left is None else left
        self.font(8.5, True)
        p.setPen(self._colour("#1a3d6d"))
        p.drawText(QRectF(x0, self.y, width, 14), 0, title + (f" [{unit}]" if unit else ""))
        box = QRectF(x0 + 46, self.y + 18, width - 56, height - 38)
        p.setPen(self._colour("#888888"))
        p.drawRect(box)
        pts = [(float(x), float(y)) for _, xs, ys in series for x, y in zip(xs, ys, strict=False)
               if y is not None and math.isfinite(float(y))]
        if not pts:
            self.font(8)
            p.drawText(box, int(Qt.AlignmentFlag.AlignCenter), "no data")
        else:
            xmin = min(x for x, _ in pts)
            xmax = max(x for x, _ in pts)
            if xmax == xmin:
                xmin, xmax = xmin - 1, xmax + 1
            ymin, ymax = y_range([y for _, y in pts])

            def to_px(x: float, y: float) -> QPointF:
                return QPointF(box.left() + (x - xmin) / (xmax - xmin) * box.width(),
                               box.bottom() - (y - ymin) / (ymax - ymin) * box.height())

            for k, (a, b) in enumerate(shade):
                left_px = to_px(max(a, xmin), ymin).x()
                right_px = to_px(min(b, xmax), ymin).x()
                p.fillRect(QRectF(left_px, box.top(), max(0.5, right_px - left_px), box.height()),
                           self._colour("#dde9cf" if k % 2 == 0 else "#eef4e6"))
            self.font(7)
            yticks, ydec = _nice_ticks(ymin, ymax)
            for y in yticks:
                py = to_px(xmin, y).y()
                p.setPen(self._colour("#e0e0e0"))
                p.drawLine(QPointF(box.left(), py), QPointF(box.right(), py))
                p.setPen(self._colour("#444444"))
                p.drawText(QRectF(x0, py - 6, 42, 12), int(Qt.AlignmentFlag.AlignRight), f"{y:.{ydec}f}")
            if x_ticks is None:
                xt, xdec = _nice_ticks(xmin, xmax)
                x_ticks = [(x, f"{x:.{xdec}f}") for x in xt]
            for x, label in x_ticks:
                px = to_px(x, ymin).x()
                p.drawText(QRectF(px - 30, box.bottom() + 2, 60, 12), int(Qt.AlignmentFlag.AlignHCenter), label)
            if x_label:
                p.drawText(QRectF(box.left(), box.bottom() + 12, box.width(), 12),
                           int(Qt.AlignmentFlag.AlignHCenter), x_label)
            for k, (name, xs, ys) in enumerate(series):
                colour = self._colour(PLOT_COLOURS[k % len(PLOT_COLOURS)])
                pen = QPen(colour)
                pen.setWidthF(1.4)
                p.setPen(pen)
                line = [to_px(float(x), float(y)) for x, y in zip(xs, ys, strict=False)
                        if y is not None and math.isfinite(float(y))]
                if len(line) > 1:
                    p.drawPolyline(QPolygonF(line))
                if markers and len(line) < 200:
                    p.setBrush(colour)
                    for q in line:
                        p.drawEllipse(q, 2.2, 2.2)
                    p.setBrush(Qt.BrushStyle.NoBrush)
                if len(series) > 1:  # the legend, in the title row
                    self.font(7.5, True)
                    p.drawText(QRectF(box.right() - 60 * (len(series) - k), box.top() - 17, 58, 12),
                               int(Qt.AlignmentFlag.AlignRight), name)
        if advance:
            self.y += height + 6

    def plot_grid(self, plots: Sequence[dict[str, Any]], columns: int = 2, height: float = 150) -> None:
        w = self.inner_width / columns
        for k in range(0, len(plots), columns):
            self.ensure(height + 10)
            for j, spec in enumerate(plots[k:k + columns]):
                self.plot(**spec, width=w - 6, height=height, left=self.MARGIN + j * w, advance=False)
            self.y += height + 6

    def finish(self) -> int:
        self._draw_footer()
        self.painter.end()
        return self.page


def y_range(values: Sequence[float]) -> tuple[float, float]:
    """The y axis: the data with a margin, and at least 10 % of the largest magnitude tall, so that
    differences at the level of noise do not fill the plot."""
    lo, hi = min(values), max(values)
    span = max(hi - lo, 0.1 * max(abs(lo), abs(hi)), 1e-6)
    mid = (lo + hi) / 2
    lo, hi = min(lo, mid - span / 2), max(hi, mid + span / 2)
    pad = (hi - lo) * 0.08
    return lo - pad, hi + pad


def _nice_ticks(lo: float, hi: float, target: int = 5) -> tuple[list[float], int]:
    """Ticks at 1, 2 or 5 × 10^k inside [lo, hi], and the decimals that show them."""
    raw = (hi - lo) / target
    if raw <= 0 or not math.isfinite(raw):
        return [lo], 2
    exp = math.floor(math.log10(raw))
    step = next(m * 10 ** exp for m in (1, 2, 5, 10) if m * 10 ** exp >= raw)
    first = math.ceil(lo / step) * step
    ticks = [first + k * step for k in range(int((hi - first) / step + 1e-9) + 1)]
    return ticks, max(0, -math.floor(math.log10(step)))


def _footer(what: str) -> str:
    from app.recording import app_version

    now = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return f"LINarm++ Manager {app_version()} — {what} — printed {now}"


def _when(iso: str) -> str:
    try:
        return _dt.datetime.fromisoformat(iso).strftime("%Y-%m-%d %H:%M:%S (UTC%z)")
    except ValueError:
        return iso or "unknown"


def _duration(seconds: Any) -> str:
    if not isinstance(seconds, int | float):
        return "—"
    m, s = divmod(round(seconds), 60)
    return f"{m} min {s:02d} s"


# ------------------------------------------------------------------------------------------- session PDF
def write_session_report(folder: str | Path, out: str | Path, data: SessionReportData | None = None) -> int:
    """Write the session's report; returns the number of pages."""
    _ensure_gui_app()
    data = data or session_report_data(folder)
    m, summary = data.metrics, data.metrics["summary"]
    reps = m["repetitions"]
    manifest = data.manifest
    patient = manifest.get("patient") or {}
    pdf = _Pdf(Path(out), f"Session {data.patient_id} {data.started}", _footer(f"session {data.folder.name}"))
    pdf.text("Therapy session report", 17, True, "#1a3d6d", gap=8)
    status = "complete" if manifest.get("status") == "complete" else "INTERRUPTED (not stopped normally)"
    pdf.fields([
        ("Patient", f"{data.patient_id}   (affected side: {patient.get('affected_side', 'unknown')})"),
        ("Operator", str(manifest.get("operator") or "—")),
        ("Date", _when(data.started)),
        ("Duration", f"{_duration(manifest.get('duration_s', summary.get('session_duration_s')))}   ({status})"),
        ("Exercises", ", ".join(data.exercises) or "—"),
        ("Note", str(manifest.get("note") or "—")),
        ("Session folder", str(data.folder)),
    ])
    pdf.heading("Exercise parameters")
    params = summary.get("exercise_params") or {}
    if params:
        pdf.fields([(str(k), fmt(v, "{}")) for k, v in params.items()], label_width=190)
    else:
        pdf.text("— (not started from an exercise form: see the script in the session's events)", colour="#555555")

    pdf.heading("Summary")
    how = "marked by the exercise" if summary.get("source") == "marks" else "segmented from the handle speed"
    pdf.fields([("Repetitions", f"{summary.get('repetitions', 0)} ({summary.get('completed', 0)} completed; {how})"),
                ("Alarms / stops", str(summary.get("alarms", 0)))])
    rows = []
    for key, (unit, label) in SUMMARY_METRICS.items():
        entry = summary.get(key)
        if isinstance(entry, dict):
            rows.append([label + (f" [{unit}]" if unit else ""), fmt(entry["mean"]), fmt(entry["sd"]),
                         fmt(entry["first"]), fmt(entry["last"]), str(entry["n"])])
    if summary.get("fes_charge_uc"):
        for ch, q in summary["fes_charge_uc"].items():
            rows.append([f"FES charge ch {ch} [µC]", fmt(q), "", "", "", "total"])
    if rows:
        pdf.table(["Metric", "Mean", "SD", "First", "Last", "n"], rows, [3.2, 1, 1, 1, 1, 0.6])

    pdf.heading("Repetitions")
    if reps:
        pdf.table([h for _, h, _ in REPETITION_COLUMNS],
                  [[fmt(r.get(k), f) for k, _, f in REPETITION_COLUMNS] for r in reps],
                  [0.5, 0.8, 0.8, 0.9, 0.9, 0.9, 0.8, 0.6, 0.8, 0.8, 0.7, 0.6])
    else:
        pdf.text("No repetition: the exercise marked none and no movement was found in the handle's speed.")

    pdf.heading("Plots")
    t, x = data.position
    pdf.plot("Handle position over the session (repetitions shaded)", [("position", t, x)], "m", "s from start",
             shade=[(r["start_s"], r["end_s"]) for r in reps], markers=False, height=170)
    idx = [r["index"] for r in reps]
    ticks = [(float(i), str(i)) for i in idx] if len(idx) <= 20 else None
    pdf.plot_grid([
        {"title": "Peak speed", "series": [("peak", idx, [r["peak_speed_m_s"] for r in reps]),
                                           ("mean", idx, [r["mean_speed_m_s"] for r in reps])],
         "unit": "m/s", "x_label": "repetition", "x_ticks": ticks},
        {"title": "Smoothness (SPARC, closer to 0 is smoother)", "series": [("SPARC", idx, [r["sparc"] for r in reps])],
         "x_label": "repetition", "x_ticks": ticks},
        {"title": "Range of motion", "series": [("range", idx, [r["range_m"] for r in reps])], "unit": "m",
         "x_label": "repetition", "x_ticks": ticks},
        {"title": "Interaction force", "series": [("peak", idx, [r["peak_force_n"] for r in reps]),
                                                  ("mean", idx, [r["mean_force_n"] for r in reps])],
         "unit": "N", "x_label": "repetition", "x_ticks": ticks},
    ])

    pdf.heading("Alarms and interruptions")
    if m["alarms"]:
        pdf.table(["Time s", "Event", "Details"],
                  [[f"{a['t_s']:.1f}", a["kind"], _details(a["data"])] for a in m["alarms"]], [0.8, 1.4, 6])
    else:
        pdf.text("None.")
    if data.problems:
        pdf.heading("Recording problems")
        for p in data.problems:
            pdf.text("• " + p)
    return pdf.finish()


def _details(data: dict[str, Any]) -> str:
    """An alarm's own sentence first (its text or reason), then the rest."""
    said = str(data.get("text") or data.get("reason") or "")
    rest = ", ".join(f"{k}: {v}" for k, v in data.items() if k not in ("text", "reason", "ident"))
    text = " — ".join(p for p in (said, rest) if p)
    return text if len(text) < 110 else text[:107] + "…"


# ------------------------------------------------------------------------------------------- progress PDF
def write_progress_report(patient_id: str, out: str | Path, rows: Sequence[ProgressRow],
                          profile: Any = None) -> int:
    """Write the patient's progress report from :func:`progress_rows`; returns the number of pages."""
    _ensure_gui_app()
    pdf = _Pdf(Path(out), f"Progress {patient_id}", _footer(f"progress of {patient_id}"))
    pdf.text("Patient progress report", 17, True, "#1a3d6d", gap=8)
    first = rows[0].date if rows else "—"
    last = rows[-1].date if rows else "—"
    pdf.fields([
        ("Patient", patient_id + (f"   (affected side: {profile.affected_side})" if profile is not None else "")),
        ("Sessions", f"{len(rows)}   ({first} … {last})"),
        ("Repetitions", str(sum(int(r.summary.get("repetitions") or 0) for r in rows))),
    ])
    if profile is not None:
        scores = profile.scores
        pdf.fields([(label, fmt(getattr(scores, key, None))) for key, label in SCORES]
                   + [("Assessed on", scores.assessed_on or "—")])

    pdf.heading("Sessions")
    pdf.table(["Date", "Exercises", "Reps", "Peak m/s", "SPARC", "Range m", "Move s", "α", "Alarms"],
              [[r.date, ", ".join(r.exercises)[:40] or "—", fmt(r.summary.get("repetitions"), "{}"),
                fmt(r.value("peak_speed_m_s")), fmt(r.value("sparc")), fmt(r.value("range_m")),
                fmt(r.value("movement_time_s")), fmt(r.value("mean_alpha")), fmt(r.summary.get("alarms"), "{}")]
               for r in rows], [1.2, 2.6, 0.6, 0.9, 0.8, 0.9, 0.8, 0.6, 0.7])

    pdf.heading("Trends across sessions (session means)")
    n = list(range(1, len(rows) + 1))
    ticks = [(float(i), rows[i - 1].date[5:]) for i in n] if len(n) <= 12 else None
    plots = [{"title": label, "series": [(label, n, [r.value(key) for r in rows])], "unit": unit,
              "x_label": "session", "x_ticks": ticks} for key, label, unit in TREND_METRICS
             if any(r.value(key) is not None for r in rows)]
    pdf.plot_grid(plots)
    scored = [(key, label) for key, label in SCORES if any(r.scores.get(key) is not None for r in rows)]
    if scored:
        pdf.heading("Clinical scores (as in the profile at each session)")
        pdf.plot_grid([{"title": label, "series": [(label, n, [r.scores.get(key) for r in rows])],
                        "x_label": "session", "x_ticks": ticks} for key, label in scored])
    return pdf.finish()


# ------------------------------------------------------------------------------------------- command line
def run_report_command(config: Any, *, metrics: str | None = None, report: str | None = None,
                       progress: str | None = None, out: str | None = None) -> int:
    """``--metrics`` prints JSON to stdout; ``--report`` / ``--progress`` write ``--out``. Exit 0, or 2 with a
    message on stderr when the input is wrong."""
    from app.recording import MANIFEST_FILE, sessions_root

    if (report or progress) and not out:
        print("--report and --progress need --out FILE.pdf", file=sys.stderr)
        return 2
    for folder in (metrics, report):
        if folder and not (Path(folder) / MANIFEST_FILE).is_file():
            print(f"{folder} is not a session folder (no {MANIFEST_FILE})", file=sys.stderr)
            return 2
    if metrics:
        print(json.dumps(_metrics_json(metrics), indent=1, ensure_ascii=False))
    if report:
        pages = write_session_report(report, out)  # type: ignore[arg-type]
        print(f"Session report written: {out} ({pages} page{'s' if pages > 1 else ''})", file=sys.stderr)
    if progress:
        from app.patients import PatientError, load_patient

        rows = progress_rows(progress, sessions_root(config))
        if not rows:
            print(f"no session of patient {progress} under {sessions_root(config)}", file=sys.stderr)
            return 2
        try:
            profile = load_patient(progress, config.safety)
        except (PatientError, OSError):
            profile = None
        pages = write_progress_report(progress, out, rows, profile)  # type: ignore[arg-type]
        print(f"Progress report written: {out} ({pages} page{'s' if pages > 1 else ''})", file=sys.stderr)
    return 0


def _metrics_json(folder: str) -> dict[str, Any]:
    from app.metrics import session_metrics

    return session_metrics(folder)
