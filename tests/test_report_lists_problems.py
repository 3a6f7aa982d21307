"""A damaged record still gives the session report, and the report says what was damaged (#37): the problems
the loading found are printed for the clinician (in plain words) and, as recorded, in the technical appendix.

Found by the #38 audit of what the suite catches: tests/test_session_loading.py checks that the report of a session
with a malformed event is written (its pages counted), not what it says; a report builder that dropped the
problems passed every test."""

from __future__ import annotations

import json
from pathlib import Path

from app.session.recording import load_session
from app.session.reports import save_session_report
from tests.pdf_layout import pdf_text
from tests.run_sessions import clinic_day_runs, write_run_session


def test_a_malformed_event_is_listed_in_the_report(tmp_path: Path) -> None:
    folder = write_run_session(tmp_path / "P1" / "20260301-100000", clinic_day_runs())
    lines = (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()
    lines[2] = json.dumps({**json.loads(lines[2]), "t_mono": "x"})  # line 3: a time that is not a number
    (folder / "events.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    problems = load_session(folder).problems
    assert any(p.startswith("events.jsonl line 3 (") and "its time 'x' is not a number" in p for p in problems), \
        problems

    save_session_report(folder, tmp_path / "r.pdf")
    text = pdf_text(tmp_path / "r.pdf")
    clinician, _, appendix = text.partition("Technical appendix")
    assert "Recording problems" in clinician, "the report does not list the session's recording problems"
    listed = clinician.split("Recording problems", 1)[1]
    assert "events.jsonl line 3" in listed and "its time 'x' is not a number; the event was left out" in listed
    assert "Recording problems as recorded" in appendix
    assert "events.jsonl line 3 (exercise_start): its time 'x' is not a number" in appendix
