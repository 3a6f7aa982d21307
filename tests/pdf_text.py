"""What a clinician reads in a printed session report, checked from its text (poppler's ``pdftotext``): no
engineering string before the technical appendix, the electrode set-up and the stimulation outside the exercises
recorded, the sign-off on the page with the summary. Reusable checks: each returns a list of problems (empty when
the report is right), so a test can assert ``== []`` and show every problem at once.

The engineering strings are a fixed list of patterns (:data:`ENGINEERING_PATTERNS`), written here independently of
the application's own translator (app/session/clinical_words.py), so that the check is not the code it checks."""

from __future__ import annotations

import re
import subprocess
import unicodedata
from pathlib import Path

from tests.pdf_layout import pdf_text

TECHNICAL_APPENDIX = "Technical appendix"
# (what it is, pattern): text no clinician's page may hold. Case-sensitive.
ENGINEERING_PATTERNS: tuple[tuple[str, str], ...] = (
    ("exception class name", r"\b(?:[A-Z][a-z0-9]+){1,5}(?:Error|Refused|Exception|Stopped|Unavailable|Latched|"
                             r"Aborted|Timeout|Cancelled|Rejected)\b"),
    ("Python traceback", r"Traceback \(most recent call last\)|File \"[^\"]+\", line \d+"),
    ("enum name (CAPS_WITH_UNDERSCORES)", r"\b[A-Z][A-Z0-9]*_[A-Z0-9_]*[A-Z0-9]\b"),
    ("robot error state", r"\b(?:WATCHDOG|ENDSTROKE|HOMING_FAILED|NO_ERROR|IN_ERROR)\b"),
    ("alarm level as a key", r"\blevel[:=] ?(?:INFO|WARNING|STOP|FATAL)\b"),
    ("temporary path", r"/tmp/|/var/tmp/|/var/folders/|\\Temp\\|\btmp[a-z0-9_]{6,}\b|pytest-of-"),
    ("absolute path", r"(?<![\w.])/(?:[\w.\-+]+/){2,}"),
    ("hex hash (12 characters or more)", r"\b[0-9a-f]{12,}\b"),
    ("version hash", r"\bversion [0-9a-f]{6,}\b"),
    ("key=value", r"\b[A-Za-z_][A-Za-z0-9_]*="),
    ("record key", r"\b(?:source|level|status|ident|device|cause|streams|detail|kind|run_id): "),
    # (one-letter parts are the deliverable's notation with a subscript, a_r and a_f, defined in the report)
    ("snake_case identifier", r"\b[a-z][a-z0-9]+(?:_[a-z0-9]+)+\b(?!\.\w)|\b[a-z]_[a-z0-9]{2,}\b(?!\.\w)"),
    ("Python literal", r"\[\'|\{\'|\{\"|\bNone\b|\bTrue\b|\bFalse\b"),
    ("script API call", r"\b(?:linarm|fes|physiologicalSensors|patientModel|VRUnity|linarmppManager)\.\w+"),
    ("program id", r"<console>|\brun-\d+\b|\bsha256\b"),
    # a command's or an argument's name from the script API / protocol table (setAssistanceTargetPos, maxVel)
    ("camelCase identifier", r"\b[a-z]{2,}(?:[A-Z][a-z0-9]+)+\b"),
)
_COMPILED = tuple((name, re.compile(p)) for name, p in ENGINEERING_PATTERNS)


def engineering_strings(text: str) -> list[str]:
    """Every engineering string in ``text``: "<what>: '<match>' in '…context…'"."""
    text = text.replace("\u200b", "")  # the report's break opportunities inside long words
    found = []
    for name, pattern in _COMPILED:
        for m in pattern.finditer(text):
            context = text[max(0, m.start() - 40): m.end() + 40].replace("\n", " ")
            found.append(f"{name}: {m.group(0)!r} in '…{context}…'")
    return found


def pages_text(pdf: Path) -> list[str]:
    """The text of each page (pdftotext separates pages with a form feed)."""
    out = subprocess.run(["pdftotext", "-raw", str(pdf), "-"], check=True, capture_output=True, text=True,
                         timeout=60).stdout
    return [unicodedata.normalize("NFKC", p) for p in out.split("\f")][: _page_count(out)]


def _page_count(raw: str) -> int:
    parts = raw.split("\f")
    return len(parts) - 1 if parts and not parts[-1].strip() else len(parts)


def clinical_text(pdf: Path) -> str:
    """The clinician's pages: everything before the technical appendix's heading (all of it when there is none)."""
    text = pdf_text(pdf)
    i = text.find(TECHNICAL_APPENDIX)
    return text if i < 0 else text[:i]


def clinical_problems(pdf: Path) -> list[str]:
    """Engineering strings on the clinician's pages, and a technical appendix that is not the report's end."""
    problems = engineering_strings(clinical_text(pdf))
    pages = pages_text(pdf)
    first = next((k for k, p in enumerate(pages) if TECHNICAL_APPENDIX in p), None)
    if first is not None:
        if not pages[first].lstrip().startswith(TECHNICAL_APPENDIX):
            problems.append(f"the technical appendix does not start its own page (page {first + 1})")
        for k in range(first, len(pages)):
            for heading in ("Sign-off", "Definitions", "Session overview"):
                if heading in pages[k]:
                    problems.append(f"{heading!r} after the technical appendix (page {k + 1})")
    return problems


def delivered_problems(pdf: Path, districts: tuple[str, ...] = (), manual_stimulation: bool = True) -> list[str]:
    """The session PDF records the electrode set-up of each of ``districts`` (bursts, currents, responses, the
    discomfort ratings, the choice and by whom) and, with ``manual_stimulation``, the stimulation started outside
    the exercises (when, profile, currents, duration, how it ended) — on the clinician's pages."""
    flat = re.sub(r"\s+", " ", clinical_text(pdf))
    problems = []
    if districts:
        if "Electrode set-up" not in flat:
            problems.append("no electrode set-up section")
        for district in districts:
            if district.lower() not in flat.lower():
                problems.append(f"the set-up of the {district} is not reported")
        for needle in ("test bursts", "Response, N", "Discomfort", "Chosen"):
            if needle not in flat:
                problems.append(f"the electrode set-up does not say {needle!r}")
    if manual_stimulation:
        section = flat.split("Stimulation outside the exercises", 2)
        if len(section) < 3:  # the summary's line and the section's heading
            problems.append("no section on the stimulation outside the exercises")
        else:
            body = section[2][:1500]
            for needle, what in ((r"\d\d:\d\d:\d\d", "its start"), (r"\d+ mA", "the currents"),
                                 (r"\d+ min \d+ s", "its duration"), (r"How it ended", "how it ended")):
                if not re.search(needle, body):
                    problems.append(f"the stimulation outside the exercises does not give {what}")
            if "None: every stimulation" in body[:200]:
                problems.append("the stimulation outside the exercises is reported as none")
    return problems


def sign_off_problems(pdf: Path) -> list[str]:
    """The sign-off block is on the page of the session's summary (its overview), not alone on a later page."""
    pages = pages_text(pdf)
    signed = [k for k, p in enumerate(pages) if "Sign-off" in p]
    summary = [k for k, p in enumerate(pages) if "Session overview" in p]
    if not signed:
        return ["no sign-off block"]
    if not summary:
        return ["no session overview"]
    problems = []
    if signed[0] != summary[-1] and signed[0] != summary[0]:
        problems.append(f"the sign-off is on page {signed[0] + 1}, the summary on page {summary[0] + 1}")
    before = pages[signed[0]].split("Sign-off", 1)[0]
    if len(before.strip().splitlines()) < 5:
        problems.append(f"the sign-off stands (almost) alone on page {signed[0] + 1}")
    return problems
