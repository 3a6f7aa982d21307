"""The reports a clinic files (issue #26, items 4 and 5), read back as a reader sees them with poppler's
``pdftotext``: every run of the session with its title, parameters in words, end reason and restart; the
repetitions numbered within each run; the reaction times the on-screen summary shows; alarms in full; no text
box overlapping another. The progress PDF: dates with times, interrupted sessions marked and kept off the
trend line."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from app.session.reports import (
    REPETITION_COLUMNS,
    charge_text,
    fmt,
    progress_rows,
    run_reports,
    trend_points,
    write_progress_report,
    write_session_report,
)
from app.therapy.patients import ClinicalScores, PatientProfile
from tests.pdf_layout import overlaps, pdf_text
from tests.run_sessions import LONG_ALARM, RunSpec, clinic_day_runs, write_run_session

pytestmark = pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
TRIGGER = "Trigger reaching (grip-triggered passive movements)"


def _section(text: str, start: str, end_pattern: str = r"\n\f?(Run \d+ — |The whole session)") -> str:
    i = text.index(start)
    m = re.search(end_pattern, text[i + len(start):])
    return text[i: i + len(start) + (m.start() if m else len(text))]


def _rep_numbers(section: str) -> list[int]:
    """The first column of the repetition table rows (# then the start time)."""
    part = section.split("numbered within the run", 1)[1]
    return [int(m.group(1)) for m in re.finditer(r"^\s*(\d+)\s+\d+\.\d\s", part, re.M)]


def test_the_session_pdf_lists_every_run_and_its_end(tmp_path: Path) -> None:
    folder = write_run_session(tmp_path / "sessions" / "PZ-017" / "20260301-100000", clinic_day_runs(),
                               profile={"patient_id": "PZ-017", "affected_side": "left", "full_name": "Anna Rossi",
                                        "birth_date": "1956-04-23", "record_number": "MRN-4471"})
    pdf = tmp_path / "session.pdf"
    pages = write_session_report(folder, pdf)
    text = pdf_text(pdf)
    assert pages >= 2
    # the overview: every run with its title, where it came from and how it ended
    overview = re.sub(r"\s+", " ", _section(text, "Session overview", r"\n\f?Run 1 — "))
    for needle in ("emergency stop: F12 pressed by the operator", "restarted as run 2", "restart of run 1",
                   "Recover, ", "Script tab", "trigger_exercise.py", "not started",
                   "refused before it started: FES current 45 mA is above the patient's cap of 40 mA"):
        assert needle in overview, needle
    # per run: title, parameters in words with units, repetitions numbered within the run
    for n, (title, reps) in enumerate([(TRIGGER, 2), (TRIGGER, 3), ("trigger_exercise.py", 2)], start=1):
        section = _section(text, f"Run {n} — {title}")
        assert _rep_numbers(section) == list(range(1, reps + 1)), n
    run1 = re.sub(r"\s+", " ", _section(text, f"Run 1 — {TRIGGER}"))
    assert "Trigger threshold 20.0 N" in run1 and "Start point 0.100 m" in run1
    assert "trigger_threshold_n" not in text  # raw keys are not for the record
    run4 = re.sub(r"\s+", " ", _section(text, "Run 4 — Assisted reaching with FES"))
    assert "FES current 45.0 mA" in run4 and "not started" in run4 and "1 completed" not in run4
    # the alarm in full, not cut at the right margin; identification, definitions, sign-off
    flat = re.sub(r"\s+", " ", text)
    assert "electrode-check-needed" in flat and LONG_ALARM[:60] in flat
    for needle in ("Patient ID PZ-017 Name Anna Rossi Date of birth 1956-04-23 Medical record no. MRN-4471",
                   "Definitions", "SPARC", "Reaction time", "Clinician (name)", "Signature"):
        assert needle in flat, needle
    assert "e+0" not in text
    assert overlaps(pdf) == []


def test_fes_charge_is_printed_in_mc(tmp_path: Path) -> None:
    folder = write_run_session(tmp_path / "P5" / "20260301-100000",
                               [RunSpec(TRIGGER, "trigger_reaching", reps=8)], fes_charge=True)
    pdf = tmp_path / "s.pdf"
    write_session_report(folder, pdf)
    flat = re.sub(r"\s+", " ", pdf_text(pdf))
    charge = re.search(r"FES charge, channel 1 ([0-9.]+) (mC|µC)", flat)
    # 40 mA × 300 µs × 40 Hz = 0.48 mC a second, over 8 repetitions of 1.8 s each (mark to mark): 6.9 mC
    assert charge is not None and charge.group(2) == "mC" and abs(float(charge.group(1)) - 6.91) < 0.3, flat[:3000]
    assert "e+0" not in flat


def test_the_session_pdf_shows_the_reaction_times_the_screen_shows(qtbot, tmp_path: Path) -> None:
    """The on-screen summary of each run and the PDF's table of that run show the same RT cells."""
    from app.session.recording import load_session
    from app.ui.session_summary import SessionSummaryDialog

    folder = write_run_session(tmp_path / "PZ-017" / "20260301-100000", clinic_day_runs())
    pdf = tmp_path / "session.pdf"
    write_session_report(folder, pdf)
    text = pdf_text(pdf)
    runs = run_reports(load_session(folder))
    rt_col = next(k for k, (key, _, _) in enumerate(REPETITION_COLUMNS) if key == "reaction_time_s")
    seen = 0
    for r in runs[:2]:  # the trigger runs: a grip before each movement
        dialog = SessionSummaryDialog(folder, r.run.started_mono, r.run.ended_mono, title=r.title)
        qtbot.addWidget(dialog)
        table = dialog.summary.tables[r.run.run_id]
        screen = [table.item(row, rt_col).text() for row in range(table.rowCount())]
        assert screen and all(v != "—" for v in screen)
        section = _section(text, f"Run {r.number} — {r.title}").split("numbered within the run", 1)[1]
        rows = [ln.split() for ln in section.splitlines() if re.match(r"^\s*\d+\s+\d+\.\d\s", ln)]
        assert [row[rt_col] for row in rows] == screen
        seen += len(screen)
    assert seen == 5


def test_values_in_sensible_units() -> None:
    assert charge_text(9240.0) == "9.24 mC" and charge_text(512.0) == "512 µC"
    assert fmt(9240.4) == "9240" and fmt(0.000123) == "0.000123" and fmt(2.8e-18) == "0"
    assert fmt(None) == "—" and fmt(0.13, "{:.2f}") == "0.13"


def test_the_progress_pdf_dates_and_interrupted_sessions(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    write_run_session(root / "P2" / "20260301-100000", [RunSpec(TRIGGER, "trigger_reaching", reps=4),
                                                        RunSpec("Free admittance", "free_admittance", reps=3)],
                      start_iso="2026-03-01T10:00:00+01:00")
    write_run_session(root / "P2" / "20260302-100000", [RunSpec(TRIGGER, "trigger_reaching", reps=4)],
                      start_iso="2026-03-02T10:00:00+01:00")
    # the same day, later: one movement, then F12 and the application was closed without ending it
    write_run_session(root / "P2" / "20260302-153000",
                      [RunSpec(TRIGGER, "trigger_reaching", reps=1, reason="emergency_stop", detail="F12")],
                      start_iso="2026-03-02T15:30:00+01:00", complete=False)
    rows = progress_rows("P2", root)
    assert [r.date for r in rows] == ["2026-03-01 10:00", "2026-03-02 10:00", "2026-03-02 15:30"]
    assert [r.interrupted for r in rows] == [False, False, True]
    xs, _, hollow = trend_points(rows, TRIGGER, "range_m")
    assert xs == [1.0, 2.0] and [x for x, _ in hollow] == [3.0]  # marked, not drawn as a decline
    xs, _, hollow = trend_points(rows, "Free admittance", "range_m")
    assert xs == [1.0] and not hollow  # trends are per exercise
    profile = PatientProfile(patient_id="P2", affected_side="right",
                             scores=ClinicalScores(fugl_meyer_ue=31, box_and_block=12, action_research_arm_test=20,
                                                   modified_ashworth=1.5, assessed_on="2026-02-27"))
    pdf = tmp_path / "progress.pdf"
    write_progress_report("P2", pdf, rows, profile)
    flat = re.sub(r"\s+", " ", pdf_text(pdf))
    assert "2026-03-02 10:00" in flat and "2026-03-02 15:30" in flat and "Box and Block (blocks/min) 12" in flat
    assert "interrupted: #3" in flat and f"Trends: {TRIGGER}" in flat and "Trends: Free admittance" in flat
    assert overlaps(pdf) == []


def test_the_progress_pdf_of_many_sessions_stays_readable(tmp_path: Path) -> None:
    """Twelve sessions, two a day: the session numbers under the plots and the table never overlap."""
    root = tmp_path / "sessions"
    for k in range(12):
        day, hour = 1 + k // 2, 9 if k % 2 == 0 else 16
        write_run_session(root / "P3" / f"202603{day:02d}-{hour:02d}0000",
                          [RunSpec(TRIGGER, "trigger_reaching", reps=2)],
                          start_iso=f"2026-03-{day:02d}T{hour:02d}:00:00+01:00")
    rows = progress_rows("P3", root)
    assert len({r.date for r in rows}) == 12
    pdf = tmp_path / "progress.pdf"
    write_progress_report("P3", pdf, rows)
    assert overlaps(pdf) == []


def test_the_sessions_browser_lists_run_titles(qtbot, tmp_path: Path) -> None:
    from app.ui.sessions_browser import SessionsBrowser

    root = tmp_path / "sessions"
    write_run_session(root / "PZ-017" / "20260301-100000", clinic_day_runs())
    browser = SessionsBrowser(root=root)
    qtbot.addWidget(browser)
    browser.set_patient("PZ-017")
    cell = browser.table.item(0, 2).toolTip()
    assert cell.startswith(f"{TRIGGER}, {TRIGGER}, trigger_exercise.py, Assisted reaching with FES")


def test_a_recording_without_any_program_still_reports_its_movements(tmp_path: Path) -> None:
    """Movements recorded with no exercise run (free use of the robot) are reported as one block."""
    folder = write_run_session(tmp_path / "P9" / "20260301-100000", [RunSpec("x", "x", reps=3)])
    events = [ln for ln in (folder / "events.jsonl").read_text().splitlines()
              if not any(k in ln for k in ('"run_start"', '"run_end"', '"script_start"', '"script_stop"',
                                           '"exercise_start"', '"repetition_'))]
    (folder / "events.jsonl").write_text("\n".join(events) + "\n")
    pdf = tmp_path / "s.pdf"
    write_session_report(folder, pdf)
    flat = re.sub(r"\s+", " ", pdf_text(pdf))
    assert "Run 1 — Movements without an exercise run" in flat and "3 (3 completed; segmented" in flat
    assert overlaps(pdf) == []
