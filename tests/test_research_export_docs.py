"""docs/export.md's code runs (issue #41, acceptance 4): every ``python`` block of the document, on a session
exported in the three formats, with ``xdf_file``, ``edf_file`` and ``bids_root`` set as the document says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from app.research_export.command import main as export_main
from tests.research_export_data import record_session

DOC = Path(__file__).resolve().parent.parent / "docs" / "export.md"
pytest.importorskip("pyxdf")
pytest.importorskip("bids")
pytest.importorskip("mne")


def blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.S)


def test_the_documents_python_blocks_run_on_an_exported_session(tmp_path, monkeypatch) -> None:
    rec = record_session(tmp_path / "sessions", seconds=4.0, estop_at=3.0, monkeypatch=monkeypatch)
    monkeypatch.undo()
    files = {}
    for fmt in ("xdf", "edf", "bids"):
        out = tmp_path / fmt
        assert export_main(["--format", fmt, str(rec.folder), "--out", str(out), "--quiet"]) == 0
        files[fmt] = str(next(out.glob(f"*.{fmt}"))) if fmt != "bids" else str(out)
    code = blocks()
    assert len(code) >= 5, "the document's examples"
    results = []
    for text in code:
        namespace = {"xdf_file": files["xdf"], "edf_file": files["edf"], "bids_root": files["bids"]}
        exec(compile(text, str(DOC), "exec"), namespace)  # the document's own code
        results.append(namespace)
    assert results[0]["estops"] == [pytest.approx(rec.estop_t, abs=1e-6)]
    assert len(results[0]["handle"]) == len(results[0]["t"]) > 0
    assert results[1]["estop_onsets"] and "handlePos" in results[1]["raw"].ch_names
    assert len(results[2]["heart_rate"]) > 0 and results[2]["rate"] == 100.0
    assert results[3]["raw"].info["sfreq"] == 100.0
    assert len(results[4]["reps"]) == 1 and "latency" in results[4]["vsa"].columns
