"""Issue #36, the record of everything delivered (reports): the session PDF has the electrode set-up and the
stimulation started outside the exercises, no engineering string before its technical appendix, the sign-off on
the page with the summary; the progress PDF lists one exercise under one name whatever started it; one alarm
count everywhere (the session PDF, the progress PDF, the run summary and the sessions browser). Built on recorded
session folders (tests/delivered_session.py): no devices, no real time."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import unicodedata
from pathlib import Path

import pytest

from app.core.runs import Program, text_hash
from app.session.alarm_count import alarm_count
from app.session.clinical_words import ROBOT_ERROR_WORDS, plain
from app.session.recording import load_session, read_events
from app.session.reports import (
    exercise_identity,
    progress_rows,
    run_reports,
    write_progress_report,
    write_session_report,
)
from app.wire.linarm_protocol import ErrorState
from tests.conftest import screenshot_path
from tests.delivered_session import EXPECTED_ALARMS, SEED_SCRIPT, write_delivered_session
from tests.pdf_layout import overlaps, pdf_text
from tests.pdf_text import (
    ENGINEERING_PATTERNS,
    clinical_problems,
    delivered_problems,
    engineering_strings,
    sign_off_problems,
)
from tests.run_sessions import RunSpec, write_run_session

needs_poppler = pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
TRIGGER = "Trigger reaching (grip-triggered passive movements)"


def save_pages(pdf: Path, name: str) -> list[Path]:
    """The PDF's pages as a reader sees them (pdftoppm, 60 dpi), where the screenshots go (tests/conftest.py)."""
    first = screenshot_path(f"{name}-1.png")
    for old in first.parent.glob(f"{name}-*.png"):
        old.unlink()
    subprocess.run(["pdftoppm", "-png", "-r", "60", str(pdf), str(first.parent / name)], check=True, timeout=60)
    return sorted(first.parent.glob(f"{name}-*.png"))


def nf(text: str) -> str:
    """As pdf_text gives it (NFKC: the micro sign µ becomes the Greek μ)."""
    return unicodedata.normalize("NFKC", text)


@pytest.fixture(scope="module")
def day(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The clinic day's session folder and its session PDF (written once for the module's tests)."""
    root = tmp_path_factory.mktemp("day") / "sessions"
    folder = write_delivered_session(root / "P-DAY" / "20260301-100000")
    pdf = folder.parent.parent.parent / "session.pdf"
    write_session_report(folder, pdf)
    return folder, pdf


@needs_poppler
def test_the_session_pdf_records_the_electrode_setup_and_the_stimulation_outside_exercises(day) -> None:
    _folder, pdf = day
    assert delivered_problems(pdf, districts=("anterior deltoid", "triceps")) == []
    flat = re.sub(r"\s+", " ", pdf_text(pdf))
    summary = flat.split("Sign-off", 1)[0]
    # on the first page: what was delivered, in a sentence per district
    assert nf("anterior deltoid: 48 test bursts on 4 combinations, up to 30 mA at 250 µs; channel 2 (electrodes "
              "3-4) chosen by Dr Rossi (the proposal)") in summary
    assert nf("triceps: 2 test bursts on 2 combinations, up to 12 mA at 250 µs; ended early") in summary
    assert "Stimulation outside the exercises 2 times, 0 min 11 s in all (Wrist extension, 8 s cycle (example))" \
        in summary
    # the set-up's detail: each combination's currents up to the highest, its responses, the ratings, the choice
    setup = flat.split("Electrode set-up Test bursts given", 1)[1].split("Stimulation outside the exercises", 1)[0]
    assert nf("1 1-2 12 8, 10 … 30 mA at 250 µs") in setup
    assert "30: 5.00" in setup and "8: 0," in setup and "Motor threshold" in setup  # channel 2: 5 N at 30 mA
    assert "7/10" in setup and "3/10" in setup and "4/10" in setup and "not rated" in setup
    assert "Chosen channel 2 (electrodes 3-4) by Dr Rossi at 10:04:10, the proposal; saved in the patient's" in setup
    assert "Ended early the emergency stop was pressed" in setup
    # the stimulation outside the exercises: when, profile, what was sent, how long, how it ended
    stim = flat.split("Stimulation outside the exercises Start", 1)[1].split("The whole session", 1)[0]
    assert nf("10:02:07 Wrist extension, 8 s cycle (example) FES panel channel 3: up to 20 mA, 200 µs 0 min 08 s "
              "the profile ran to its end") in stim
    assert nf("channel 3: up to 16 mA, 200 µs 0 min 03 s emergency stop pressed (F12 key)") in stim
    # the Script tab's run of the seed's script is the trigger exercise, its file named
    assert f"Run 3 — {TRIGGER} — script trigger_exercise.py" in flat
    assert overlaps(pdf) == []
    save_pages(pdf, "report-session")


@needs_poppler
def test_no_engineering_string_before_the_technical_appendix(day) -> None:
    _folder, pdf = day
    assert clinical_problems(pdf) == []
    text = pdf_text(pdf)
    appendix = text.split("Technical appendix (for the engineer)", 1)[1]
    # the engineer still finds what the record says: the refusal's exception, the enum, the paths, the hashes
    for needle in ("CommandRefused", "ENVELOPE_BREACH", "/tmp/tmpq8x2k1ab", text_hash(SEED_SCRIPT.read_text())[:40]):
        assert needle in appendix.replace("\n", "").replace("\u200b", ""), needle
    clinical = re.sub(r"\s+", " ", text.split("Technical appendix", 1)[0])
    assert "Robot error: the handle left the range locked for the exercise (too fast or too far)" in clinical
    assert "stimulation refused: current 45 mA is above the patient's cap of 40 mA on channel 3" in clinical


def test_the_engineering_patterns_catch_what_the_reports_used_to_print() -> None:
    """The fixed list fails on each kind of string the reports printed before (so the check above can fail)."""
    samples = ["refused: CommandRefused: fes.loadFile(x)", "LINarm error: ENVELOPE_BREACH", "error: WATCHDOG (…)",
               "— level: STOP, source: keyboard", "Session folder /tmp/pytest-of-root/P1/2026",
               "script file /home/anna/scripts/reach.py", "version eeb75b0efcde930e", "sha 3273e9864418eca978c9",
               "name: trigger_reaching.py, status: stopped", "streams: ['patient_model.main']", "Apos=0.4",
               "library exercise “trigger_reaching”", "run-3", "Traceback (most recent call last)"]
    for sample in samples:
        assert engineering_strings(sample), sample
    for fine in ("Trigger reaching (grip-triggered passive movements)", "0.150 m/s", "3 N/mA", "trigger_exercise.py",
                 "Mean a_r 0.25", "emergency stop pressed (F12 key)", "Stop alarm", "2026-03-01 10:00:00",
                 "session 20260301-100000", "Robot error: the robot stopped itself"):
        assert not engineering_strings(fine), (fine, engineering_strings(fine))
    assert len(ENGINEERING_PATTERNS) >= 12


def test_plain_words_for_what_the_devices_write() -> None:
    assert set(ROBOT_ERROR_WORDS) == {s.name for s in ErrorState}  # every robot error state has its words
    assert plain("safety stop: linarm: LINarm error: WATCHDOG (no host bytes for 0.251 s)") == \
        "safety stop: robot error: the robot stopped itself: it lost contact with the computer"
    assert plain("patient_model connection lost: no valid datagram from patient_model for 0.5 s") == \
        "patient model connection lost: no data from the patient model for 0.5 s"
    assert plain("script error: ZeroDivisionError: division by zero (line 12)") == \
        "script error: division by zero (line 12)"
    assert plain("FES current 45 mA is above the patient's cap of 40 mA") == \
        "FES current 45 mA is above the patient's cap of 40 mA"  # a plain sentence stays as it is
    assert plain(plain("CommandRefused: linarm.moveCentreTo(0.5) was refused")) == \
        plain("CommandRefused: linarm.moveCentreTo(0.5) was refused")


@needs_poppler
def test_the_sign_off_sits_on_the_page_with_the_summary(day) -> None:
    _folder, pdf = day
    assert sign_off_problems(pdf) == []


@needs_poppler
def test_one_alarm_count_in_the_reports_the_run_summaries_and_the_sessions_browser(qtbot, day, tmp_path) -> None:
    """8 in the browser, 11 in the progress PDF (#36): the browser counted INFO messages, the reports counted each
    STOP twice. One definition (app/session/alarm_count.py) now: this session has 7."""
    from app.ui.sessions_browser import SessionsBrowser

    folder, pdf = day
    events, _ = read_events(folder / "events.jsonl")
    assert alarm_count(events) == EXPECTED_ALARMS
    browser = SessionsBrowser(root=folder.parent.parent)
    qtbot.addWidget(browser)
    browser.set_patient("P-DAY")
    assert browser.table.item(0, 3).text() == str(EXPECTED_ALARMS)  # the browser's Alarms column
    rows = progress_rows("P-DAY", folder.parent.parent)
    progress = tmp_path / "progress.pdf"
    write_progress_report("P-DAY", progress, rows)
    table = re.sub(r"\s+", " ", pdf_text(progress)).split("Alarms Session", 1)[1]
    assert re.search(r" 1 2026-03-01 10:00 .* (\d+) complete ", table).group(1) == str(EXPECTED_ALARMS), table[:300]
    flat = re.sub(r"\s+", " ", pdf_text(pdf))
    assert f"Alarms {EXPECTED_ALARMS} (4 stop alarms, 3 warnings)" in flat.split("Sign-off", 1)[0]
    assert f"Alarms counted: {EXPECTED_ALARMS} (4 stop alarms, 3 warnings)" in flat
    # the runs' own counts (the on-screen summary's) add up to the session's, with the alarms outside every run
    reports = run_reports(load_session(folder))
    per_run = [r.summary["alarms"] for r in reports]
    assert per_run == [1, 0, 1, 1]  # the F12 of run 1; the physio warning; the refusal's warning
    # outside the runs: the stops during the set-up and the FES panel's stimulation, the envelope breach, the patient
    # model's lost link
    assert sum(per_run) + 4 == EXPECTED_ALARMS


def test_the_alarm_count_definition() -> None:
    def ev(t: float, kind: str, **data) -> dict:
        return {"t_mono": t, "kind": kind, "data": data}

    events = [ev(1.0, "emergency_stop", source="keyboard"),
              ev(1.0, "alarm", level="STOP", text="Emergency stop: emergency stop pressed", ident=1),
              ev(1.2, "emergency_stop", source="button"),  # pressed again while latched
              ev(2.0, "alarm_acknowledged", ident=1), ev(2.0, "emergency_stop_reset"),
              ev(2.0, "alarm", level="INFO", text="Emergency stop reset", ident=2),
              ev(3.0, "alarm", level="WARNING", text="physio stopped sending data", ident=3),
              ev(3.5, "alarm_repeated", ident=3, repeats=5),
              ev(4.0, "gap_start", device="physio"), ev(5.0, "script_stop", status="stopped"),
              ev(6.0, "alarm", level="FATAL", text="x", ident=4),
              ev(7.0, "emergency_stop", source="keyboard"),  # an older record: no alarm came with it
              ev(8.0, "emergency_stop", source="keyboard")]  # still latched
    assert alarm_count(events) == 4  # STOP, WARNING, FATAL, the older record's stop
    assert alarm_count([ev(0.0, "alarm", text="no level: an older record")]) == 1


def _program(kind: str, ident: str, title: str, path: Path | str = "", text: str = "") -> dict:
    return {"kind": kind, "ident": ident, "title": title, "text_sha256": text_hash(text) if text else "0" * 64,
            "version": "", "path": str(path)}


@needs_poppler
def test_the_progress_pdf_lists_one_exercise_under_one_name(tmp_path: Path) -> None:
    """The library's trigger reaching from the Exercises tab, its seed script from the Script tab, and the library
    exercise's own script run headless are one exercise; a clinic's own script stays its own."""
    from app.therapy.exercises import find_exercise

    root = tmp_path / "sessions"
    library = find_exercise("trigger_reaching")
    seed = SEED_SCRIPT.read_text(encoding="utf-8")
    own = tmp_path / "my_reach.py"
    own.write_text("# the clinic's own script\n")
    sessions = [
        [RunSpec(TRIGGER, "trigger_reaching", reps=3)],
        [RunSpec("trigger_exercise.py", "trigger_exercise", kind="script_file", source="script_tab", reps=3)],
        [RunSpec("trigger_reaching.py", "trigger_reaching.py", kind="script_file", source="headless", reps=2),
         RunSpec("my_reach.py", "my_reach", kind="script_file", source="script_tab", reps=2)],
    ]
    programs = [[None], [_program("script_file", str(SEED_SCRIPT), "trigger_exercise.py", SEED_SCRIPT, seed)],
                [_program("script_file", "trigger_reaching.py", "trigger_reaching.py", "trigger_reaching.py",
                          library.script.read_text(encoding="utf-8")),
                 _program("script_file", str(own), "my_reach.py", own)]]
    for day, (runs, progs) in enumerate(zip(sessions, programs, strict=True), start=1):
        folder = write_run_session(root / "P4" / f"2026030{day}-100000", runs,
                                   start_iso=f"2026-03-0{day}T10:00:00+01:00")
        lines = (folder / "events.jsonl").read_text().splitlines()
        out, n = [], 0
        for line in lines:
            e = json.loads(line)
            if e["kind"] == "run_start":
                if progs[n] is not None:
                    e["data"]["program"] = progs[n]
                n += 1
            out.append(json.dumps(e))
        (folder / "events.jsonl").write_text("\n".join(out) + "\n")
    rows = progress_rows("P4", root)
    assert [r.exercises for r in rows] == [(TRIGGER,), (TRIGGER,), (TRIGGER, "my_reach.py")]
    pdf = tmp_path / "progress.pdf"
    write_progress_report("P4", pdf, rows)
    flat = re.sub(r"\s+", " ", pdf_text(pdf))
    assert flat.count("Trends: ") == 2 and f"Trends: {TRIGGER}" in flat and "Trends: my_reach.py" in flat
    assert "trigger_exercise.py" not in flat and "trigger_reaching.py" not in flat
    assert overlaps(pdf) == []
    save_pages(pdf, "report-progress")


def test_exercise_identity_rule() -> None:
    seed = SEED_SCRIPT.read_text(encoding="utf-8")
    as_seed = Program("script_file", str(SEED_SCRIPT), "trigger_exercise.py", text_hash(seed), path=str(SEED_SCRIPT))
    moved = Program("script_file", "/elsewhere/trigger_exercise.py", "trigger_exercise.py", text_hash(seed),
                    path="/elsewhere/trigger_exercise.py")  # another machine's copy: its text says what it is
    edited = Program("script_file", "/elsewhere/trigger_exercise.py", "trigger_exercise.py", text_hash(seed + "#"),
                     path="/elsewhere/trigger_exercise.py")  # an edited copy is another program
    library = Program("exercise", "trigger_reaching", TRIGGER, "x")
    assert exercise_identity(as_seed) == exercise_identity(moved) == exercise_identity(library) == \
        ("exercise:trigger_reaching", TRIGGER)
    assert exercise_identity(edited) == ("script:trigger_exercise.py", "trigger_exercise.py")
    console = Program("console", "<console>", "Console code", text_hash("print(1)"))
    assert exercise_identity(console) == ("console", "Console code")
