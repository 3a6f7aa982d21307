"""The sessions browser's research export (issue #41, stage 2): select sessions, Export… → format and folder, run in
the worker process with a progress dialog and Cancel; what it writes is read back by each format's reader; a
cancelled or failed export leaves nothing in the folder and says so in one sentence."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QProgressDialog, QPushButton

from app.core import streams
from app.session.recording import load_session
from app.worker import TaskStatus
from tests.research_export_data import record_session, synth_session
from tests.waits import WORKER_TASK_MS

pyxdf = pytest.importorskip("pyxdf")
pyedflib = pytest.importorskip("pyedflib")
bids = pytest.importorskip("bids")

US = 1e-6


@pytest.fixture
def browser_on(tmp_path, monkeypatch, qtbot):
    """A browser over the sessions under ``root`` (its own worker process, ended by closing the browser)."""
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    made = []

    def make(root: Path):
        from app.ui.sessions_browser import SessionsBrowser

        browser = SessionsBrowser(root)
        qtbot.addWidget(browser)
        made.append(browser)
        return browser

    yield make
    for browser in made:
        browser.close()


def _select_all(browser) -> list[Path]:
    browser.table.selectAll()
    return browser.selected_folders()


def _run(qtbot, browser, folders, fmt, out) -> object:
    ended = []
    task = browser.research_export(folders, fmt, out, on_done=ended.append)
    qtbot.waitUntil(lambda: bool(ended), timeout=WORKER_TASK_MS)
    return task


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_export_from_the_browser_writes_what_the_readers_read(tmp_path, monkeypatch, qtbot, browser_on) -> None:
    """Two sessions of one patient, selected in the browser, exported in each format by the worker: pyxdf, pyedflib
    and pybids read every session back, with the samples the session folders hold."""
    root = tmp_path / "sessions"
    clock = pytest.MonkeyPatch()  # the recorder on a virtual clock while the sessions are made
    try:
        recs = [record_session(root, seed=seed, monkeypatch=clock) for seed in (7, 8)]
    finally:
        clock.undo()
    browser = browser_on(root)
    browser.set_patient("PZ-017")
    folders = _select_all(browser)
    assert sorted(folders) == sorted(r.folder for r in recs)
    assert browser.research_button.isEnabled()

    from app.ui.sessions_browser import ResearchExportDialog, documents_folder

    dialog = browser.ask_research_export()
    assert isinstance(dialog, ResearchExportDialog)
    assert dialog.folder == documents_folder()  # the user's documents folder by default
    assert [dialog.format_box.itemData(i) for i in range(dialog.format_box.count())] == ["bids", "xdf", "edf"]
    dialog.reject()

    out = tmp_path / "out"
    out.mkdir()
    task = _run(qtbot, browser, folders, "xdf", out)
    assert task.status is TaskStatus.DONE, task.error
    files = sorted(out.glob("*.xdf"))
    assert len(files) == 2 and browser.status.text().startswith("Exported 2 file(s) to")
    for path, rec in zip(files, sorted(recs, key=lambda r: r.folder.name), strict=True):
        session = load_session(rec.folder)
        data, _ = pyxdf.load_xdf(str(path), dejitter_timestamps=False)
        vsa = {s["info"]["name"][0]: s for s in data}[streams.LINARM_VSA]
        truth = session.streams[streams.LINARM_VSA]
        assert len(vsa["time_stamps"]) == len(truth.t) and np.max(np.abs(vsa["time_stamps"] - truth.t)) <= US
        assert np.array_equal(vsa["time_series"][:, 0], truth.data["equilibriumPos"], equal_nan=True)

    task = _run(qtbot, browser, folders, "edf", out)
    assert task.status is TaskStatus.DONE, task.error
    edfs = sorted(out.glob("*.edf"))
    assert len(edfs) == 2
    for path in edfs:
        with pyedflib.EdfReader(str(path)) as edf:
            assert "heartRate" in edf.getSignalLabels()
            assert any(text.startswith("emergency_stop") for text in edf.readAnnotations()[2])

    task = _run(qtbot, browser, folders, "bids", out)
    assert task.status is TaskStatus.DONE, task.error
    (dataset,) = out.glob("linarmpp-bids-*")
    layout = bids.BIDSLayout(str(dataset), validate=False)
    assert layout.get_subjects() == ["PZ017"] and layout.get_sessions() == ["1", "2"]
    assert len(layout.get(suffix="motion", extension=".tsv")) == 8
    assert _leftovers(out) == []  # no staging folder, no temporary left
    assert oct(os.stat(dataset).st_mode & 0o777) == "0o700"


def test_a_cancelled_or_failed_export_leaves_nothing_and_says_so(tmp_path, qtbot, browser_on) -> None:
    """Cancel from the progress dialog half-way through: the folder holds nothing (not the sessions already
    written, no staging folder) and the status line says so; an export that cannot be made says why in one
    sentence, in a message box too, and leaves nothing either."""
    root = tmp_path / "sessions"
    for k in range(2):  # two 20-minute LINarm streams: long enough to cancel half-way
        synth_session(root, "PZ-020", 1200.0, only=(streams.LINARM_VSA,), folder_name=f"20260301-10{k}000",
                      t0=20_000.0 + 3600 * k)
    browser = browser_on(root)
    browser.set_patient("PZ-020")
    folders = _select_all(browser)
    assert len(folders) == 2
    out = tmp_path / "out"
    out.mkdir()

    ended = []
    task = browser.research_export(folders, "xdf", out, on_done=ended.append)
    # the user presses Cancel in the progress dialog once the second session is being written
    qtbot.waitUntil(lambda: task.fraction > 0.6 or task.done, timeout=WORKER_TASK_MS)
    *_, dialog = browser.findChildren(QProgressDialog)
    qtbot.mouseClick(dialog.findChild(QPushButton), Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: bool(ended), timeout=WORKER_TASK_MS)
    assert task.status is TaskStatus.CANCELLED, (task.status, task.result)
    assert browser.status.text() == "Export cancelled: nothing was written."
    assert list(out.iterdir()) == []

    broken = tmp_path / "not-a-session"
    broken.mkdir()
    task = _run(qtbot, browser, [broken], "edf", out)
    assert task.status is TaskStatus.FAILED
    assert task.error.startswith("The export was not written: ") and task.error.count(".") >= 1
    assert browser.status.text() == task.error and browser.message_box.text() == task.error
    assert list(out.iterdir()) == []


def test_a_session_that_cannot_be_read_is_left_out_and_named(tmp_path) -> None:
    """The worker's task without the worker: of a readable session and a folder that is not one, the first is
    written and read back, the second named in the answer; nothing else is left in the folder."""
    from app.research_export.jobs import export_sessions

    clock = pytest.MonkeyPatch()
    try:
        rec = record_session(tmp_path / "sessions", monkeypatch=clock)
    finally:
        clock.undo()
    broken = tmp_path / "sessions" / "PZ-017" / "20260301-999999"
    broken.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    outcome = export_sessions("edf", [rec.folder, broken], out, "20260301-120000")
    assert [p.name for p in outcome.written] == [f.name for f in out.iterdir()] and len(outcome.written) == 1
    assert outcome.missing == ["PZ-017/20260301-999999: " + outcome.missing[0].split(": ", 1)[1]]
    assert "is not a session" in outcome.missing[0]
    sentence = outcome.sentence("edf", out)
    assert sentence.startswith(f"Exported 1 file(s) to {out} (EDF+ files, read back)") and "20260301-999999" in sentence
    with pyedflib.EdfReader(str(outcome.written[0])) as edf:
        assert len(edf.readSignal(edf.getSignalLabels().index("heartRate"))) > 0
