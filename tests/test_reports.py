"""Reports and views on synthetic session folders (known reaches, no devices): the session PDF and the
progress PDF render page by page with pdftoppm; the summary and the progress views show the repetitions and
trends; the sessions browser opens them."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.devices.linarm import VSA_STREAM
from app.devices.physio import PHYSIO_STREAM
from app.session.metrics import session_metrics
from app.session.reports import progress_rows, write_progress_report, write_session_report

FS = 200.0
T0 = 1000.0  # the monotonic clock at the session's start


def min_jerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5


def write_session(folder: Path, *, reps: int, distance: float, duration: float, fm: int | None = None,
                  alarm: bool = False, day: int = 1) -> Path:
    """A session folder as app.session.recording writes it: ``reps`` marked reaches out and back."""
    (folder / "streams").mkdir(parents=True)
    total = 1.0 + reps * (duration + 1.0) + 1.0
    t = np.arange(0.0, total, 1 / FS)
    x = np.full_like(t, 0.1)
    events: list[dict[str, Any]] = [{"kind": "session_start", "t_mono": T0, "data": {}},
                                    {"kind": "exercise_start", "t_mono": T0 + 0.5,
                                     "data": {"exercise": "trigger_reaching", "params": {"movements": reps}}},
                                    {"kind": "script_start", "t_mono": T0 + 0.5, "data": {"name": "reach.py"}}]
    for k in range(reps):
        start = 1.0 + k * (duration + 1.0)
        step = distance * min_jerk((t - start) / duration)
        x += step if k % 2 == 0 else -step
        events += [{"kind": "repetition_start", "t_mono": T0 + start - 0.2,
                    "data": {"index": k + 1, "total": reps}},
                   {"kind": "repetition_end", "t_mono": T0 + start + duration + 0.2,
                    "data": {"index": k + 1, "ok": True}}]
    if alarm:
        events.append({"kind": "alarm", "t_mono": T0 + 2.0, "data": {"level": "WARNING", "source": "physio",
                                                                    "text": "physio stopped sending data"}})
    events.append({"kind": "script_stop", "t_mono": T0 + total - 0.5, "data": {"status": "finished"}})
    force = 3.0 * np.sin(np.pi * (x - 0.1) / distance)
    vsa = np.column_stack([t + T0, x, np.zeros_like(t), np.full_like(t, 900.0), x, np.gradient(x, 1 / FS), force])
    physio = np.column_stack([t + T0, 70 + 0 * t, 2 + 0 * t, 33 + 0 * t, 5 + 0 * t])[::2]
    streams = {}
    for spec, data in ((VSA_STREAM, vsa), (PHYSIO_STREAM, physio)):
        name = spec.name
        lines = ["t_mono_s," + ",".join(c.name for c in spec.channels)]
        lines += [",".join(repr(float(v)) for v in row) for row in data]
        (folder / "streams" / f"{name}.csv").write_text("\n".join(lines) + "\n")
        streams[name] = {"file": f"streams/{name}.csv", "device": name.split(".")[0],
                         "nominal_rate_hz": spec.nominal_rate_hz,
                         "channels": [{"name": c.name, "unit": c.unit, "label": c.label} for c in spec.channels]}
    (folder / "events.jsonl").write_text("".join(json.dumps({"t_wall": "", "who": "", "origin": "app", **e}) + "\n"
                                                 for e in events))
    manifest = {"format_version": 1, "status": "complete", "patient_id": folder.parent.name, "operator": "dr_rossi",
                "note": "", "patient": {"affected_side": "left", "scores": {"fugl_meyer_ue": fm}},
                "start": {"t_wall": f"2026-03-{day:02d}T10:00:00+01:00", "t_mono_s": T0, "t_wall_epoch_s": 0.0},
                "end": {"t_mono_s": T0 + total}, "duration_s": total, "streams": streams}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def render(pdf: Path, out: Path) -> list[Path]:
    subprocess.run(["pdftoppm", "-r", "30", "-png", str(pdf), str(out / pdf.stem)], check=True, timeout=60)
    return sorted(out.glob(f"{pdf.stem}*.png"))


def test_metrics_of_a_written_session(tmp_path: Path) -> None:
    folder = write_session(tmp_path / "P1" / "20260301-100000", reps=4, distance=0.2, duration=1.0, alarm=True)
    m = session_metrics(folder)
    assert len(m["repetitions"]) == 4
    for r in m["repetitions"]:
        assert r["range_m"] == pytest.approx(0.2, rel=0.01)
        assert r["peak_speed_m_s"] == pytest.approx(1.875 * 0.2, rel=0.02)
        assert r["peak_force_n"] == pytest.approx(3.0, rel=0.01)
    assert m["summary"]["exercise_params"] == {"movements": 4} and m["summary"]["alarms"] == 1
    assert [a["kind"] for a in m["alarms"]] == ["alarm"] and m["alarms"][0]["t_s"] == 2.0


@pytest.mark.skipif(shutil.which("pdftoppm") is None, reason="poppler-utils (pdftoppm) is not installed")
def test_session_and_progress_pdfs_render(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    folders = [write_session(root / "P1" / f"2026030{k + 1}-100000", reps=12, distance=0.15 + 0.03 * k,
                             duration=1.4 - 0.2 * k, fm=30 + 2 * k, day=k + 1, alarm=k == 0) for k in range(3)]
    pages = write_session_report(folders[0], tmp_path / "session.pdf")
    assert pages >= 2  # 12 repetitions, plots and alarms do not fit on one A4 page
    assert len(render(tmp_path / "session.pdf", tmp_path)) == pages
    rows = progress_rows("P1", root)
    assert [r.date for r in rows] == ["2026-03-01 10:00", "2026-03-02 10:00", "2026-03-03 10:00"]
    assert [round(r.value("range_m"), 2) for r in rows] == [0.15, 0.18, 0.21]
    assert [r.scores["fugl_meyer_ue"] for r in rows] == [30, 32, 34]
    pages = write_progress_report("P1", tmp_path / "progress.pdf", rows)
    assert len(render(tmp_path / "progress.pdf", tmp_path)) == pages >= 1


def test_summary_and_progress_views_from_the_sessions_browser(qtbot, tmp_path: Path) -> None:
    from app.ui.sessions_browser import SessionsBrowser

    root = tmp_path / "sessions"
    for k in range(2):
        write_session(root / "P7" / f"2026030{k + 1}-100000", reps=3, distance=0.2 + 0.05 * k, duration=1.0,
                      fm=40 + k, day=k + 1)
    browser = SessionsBrowser(root=root)
    qtbot.addWidget(browser)
    browser.set_patient("P7")
    assert browser.summary_button.isEnabled() and browser.progress_button.isEnabled()
    with qtbot.waitSignal(browser.opened, timeout=30000) as opened:  # read in the worker process (#37)
        browser.open_summary()
    summary = opened.args[0]
    qtbot.addWidget(summary)
    assert summary.summary.table.rowCount() == 3
    assert summary.summary.table.item(0, 3).text() == "0.250"  # the newest session first: 0.25 m
    assert summary.summary.save_pdf(tmp_path / "s.pdf") and (tmp_path / "s.pdf").stat().st_size > 1000
    with qtbot.waitSignal(browser.opened, timeout=30000) as opened:
        browser.open_progress()
    progress = opened.args[0]
    qtbot.addWidget(progress)
    view = progress.view
    assert view.table.rowCount() == 2
    assert {"peak_speed_m_s", "sparc", "range_m", "fugl_meyer_ue"} <= set(view.plots)
    xs, ys = view.plots["range_m"].listDataItems()[0].getData()
    assert list(xs) == [1, 2] and list(np.round(ys, 3)) == [0.2, 0.25]
    assert view.save_pdf(tmp_path / "p.pdf")


def test_the_progress_tables_assistance_level_is_one_unbroken_number(tmp_path: Path) -> None:
    """α near 0 was printed to three significant digits ("-0.00501"), too wide for its column: the cell wrapped
    into "-0.005" over "01", which a reader takes for -0.005 (seen in the clinician's day's progress report)."""
    from tests.pdf_layout import pdf_words

    root = tmp_path / "sessions"
    write_session(root / "P1" / "20260301-100000", reps=3, distance=0.15, duration=1.2, fm=30, day=1)
    rows = progress_rows("P1", root)
    rows[0].summary["mean_alpha"] = {"mean": -0.00501}
    write_progress_report("P1", tmp_path / "progress.pdf", rows)
    words = [w.text for w in pdf_words(tmp_path / "progress.pdf")[0]]
    assert "-0.01" in words, words
    assert "01" not in words and "-0.005" not in words, words


def test_a_level_that_rounds_to_zero_reads_zero_not_minus_zero(tmp_path: Path) -> None:
    """The clinician's day's progress report printed α "-0.00" (a small negative mean rounded): a reader takes a
    sign for a meaning. Rounded to zero, it reads "0.00"."""
    from app.session.reports import fmt
    from tests.pdf_layout import pdf_words

    assert (fmt(-0.004, "{:.2f}"), fmt(-0.0, "{:.1f}"), fmt(-0.006, "{:.2f}"), fmt(-3, "{}")) == (
        "0.00", "0.0", "-0.01", "-3")
    root = tmp_path / "sessions"
    write_session(root / "P1" / "20260301-100000", reps=3, distance=0.15, duration=1.2, fm=30, day=1)
    rows = progress_rows("P1", root)
    rows[0].summary["mean_alpha"] = {"mean": -0.004}
    write_progress_report("P1", tmp_path / "progress.pdf", rows)
    words = [w.text for w in pdf_words(tmp_path / "progress.pdf")[0]]
    assert "0.00" in words and "-0.00" not in words, words
