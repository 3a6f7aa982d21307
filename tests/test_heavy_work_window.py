"""Issue #37, acceptance 1 and 3, in the window during an FES exercise (the robot ON, stimulation running):

1. Replay and the summary of a 30-minute session opened from the sessions browser: no stall the GUI watch would
   warn of (the ≤ 50 ms figure is the bench's, see below), no host silence the LINarm's watchdog would trip on,
   no Stop from the guardian, the exercise goes on;
   F12 pressed while a session loads puts robot IDLE and FES Stop on the wire at once (≤ 20 ms: the bench's).
3. HDF5 and CSV exports and the session and progress reports to a full disk and to a read-only folder: the app
   keeps running, the therapy continues, one sentence, nothing claimed written that is not.

On the code before #37 the load ran on the GUI thread (4.6-5.8 s): the watchdog tripped, the guardian stopped FES,
F12 acted seconds late; the HDF5 export to a full disk killed the application."""

from __future__ import annotations

import time
from contextlib import ExitStack
from pathlib import Path

import pytest

from app.worker import TaskStatus
from tests.heavy_rig import WATCHDOG_S, open_from_browser, start_therapy, stop_therapy
from tests.long_session import shared_long_session
from tests.mounts import entries, full_disk, read_only
from tests.run_sessions import clinic_day_runs, write_run_session
from tests.waits import WORKER_TASK_MS

# What this test holds is functional: the therapy undisturbed (no alarm at all, so no GUI-watch warning at
# 0.35 s, no watchdog or guardian trip) and F12 not queued behind the load. Its bounds are regression guards an
# order of magnitude inside the failures (stalls of 4.6-5.8 s, F12 2.1-3.4 s late) and above this shared
# machine's scheduling noise; the figures (stall <= 50 ms, F12 <= 20 ms) are measured, quiet and with
# two CPU hogs, by bench/bench_heavy_work.py (bench/README.md), as speed goals are here.
STALL_BOUND_S = 0.250
ESTOP_BOUND_S = 0.200
BUILD_BOUND_S = 1.0

pytestmark = pytest.mark.realtime


def _undisturbed(seen: dict) -> None:  # type: ignore[type-arg]
    assert seen["stimulating"] and seen["robot_on"] and seen["robot_error"] == 0, seen
    assert not seen["fes_stop_on_wire"] and not seen["estop"] and seen["alarms"] == [], seen
    assert seen["host_silence_s"] < WATCHDOG_S * 0.8, seen


def test_opening_a_long_session_during_an_fes_exercise(qtbot, tmp_path_factory, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    folder = shared_long_session(tmp_path_factory)
    # The test's own set-up (mounting the full and read-only disks, writing and reading a small session) is done
    # before the exercise starts: it runs on this thread, the window's, which the GUI watch judges while the robot
    # is ON and stimulation runs (a mount is a process: ~1 s a stall no clinician's action makes).
    mounts = ExitStack()
    places = [mounts.enter_context(full_disk(tmp_path / "full", size_kib=1024, leave_bytes=16 * 1024)),
              mounts.enter_context(read_only(tmp_path / "ro"))]
    small = write_run_session(tmp_path / "sessions" / "P1" / "20260301-100000", clinic_day_runs())
    from app.session.reports import progress_rows
    from app.ui.progress_view import ProgressView
    from app.ui.session_summary import SessionSummaryDialog

    report_dialog = SessionSummaryDialog(small)  # built here, before the exercise: the browser opens it staged
    qtbot.addWidget(report_dialog)
    report_view = report_dialog.summary
    progress_view = ProgressView("P1", progress_rows("P1", tmp_path / "sessions"))
    qtbot.addWidget(progress_view)
    try:
        therapy = start_therapy(folder.parent.parent, lambda p, ms: qtbot.waitUntil(p, timeout=ms))
    except BaseException:
        mounts.close()
        raise
    browser = therapy.browser
    try:
        browser.set_patient(folder.parent.name)
        browser.select_folder(folder)
        qtbot.waitUntil(lambda: browser.tasks.service.last_start_s is not None, timeout=20000)  # warm
        therapy.meter.ticks.clear()

        # 1. the replay: read in the worker, built a piece per turn of the event loop
        wait = lambda p, ms: qtbot.waitUntil(p, timeout=ms)  # noqa: E731
        replay = open_from_browser(therapy, "replay", lambda w: w.is_ready and not w._events_left, wait)
        assert len(replay.widget.plots.curves) > 0 and replay.widget.source.duration == pytest.approx(1800, abs=1)
        _undisturbed(replay.therapy)
        assert replay.load_stall_s <= STALL_BOUND_S, f"replay: GUI thread held {replay.load_stall_s * 1e3:.1f} ms " \
                                                      f"while the session loaded"
        assert replay.build_stall_s <= BUILD_BOUND_S, f"replay: built in one stall of {replay.build_stall_s:.2f} s"

        # 2. the run summary: the metrics of both runs computed in the worker; the overview shown first
        summary = open_from_browser(therapy, "open_summary", lambda d: d.summary.is_ready, wait)
        runs = summary.widget.summary.runs
        assert len(runs) == 2 and sum(len(r.repetitions) for r in runs) > 200
        _undisturbed(summary.therapy)
        assert summary.load_stall_s <= STALL_BOUND_S, f"summary: GUI thread held {summary.load_stall_s * 1e3:.1f} " \
                                                       "ms while the metrics were computed"
        assert summary.build_stall_s <= STALL_BOUND_S, f"summary: overview built in {summary.build_stall_s:.2f} s"
        print(f"\nreplay: open {replay.seconds:.2f} s, stall while loading {replay.load_stall_s * 1e3:.0f} ms, "
              f"while building {replay.build_stall_s * 1e3:.0f} ms; summary: open {summary.seconds:.2f} s, stall "
              f"{summary.load_stall_s * 1e3:.0f} / {summary.build_stall_s * 1e3:.0f} ms; host silence max "
              f"{max(replay.therapy['host_silence_s'], summary.therapy['host_silence_s']) * 1e3:.0f} ms")

        # 3. outputs to a full disk and to a read-only folder during the exercise
        report_view.tasks = progress_view.tasks = browser.tasks  # their PDFs drawn in the window's worker
        t0 = time.monotonic()
        for place in places:
            results = []
            for kind, dest in (("hdf5", place / "s.h5"), ("csv", place / "csv")):
                job = browser.export(small, kind, dest)
                # shown on the GUI thread
                qtbot.waitUntil(lambda job=job: job not in browser.jobs, timeout=WORKER_TASK_MS)
                assert job.task.status is TaskStatus.FAILED and "\n" not in job.message
                assert browser.status.text() == job.message and browser.message_box.text() == job.message
                browser.message_box.close()
                results.append(job.message)
            for view, name in ((report_view, "r.pdf"), (progress_view, "p.pdf")):
                task = view.save_pdf_in_worker(place / name)
                qtbot.waitUntil(lambda task=task, view=view: task.done and "Writing" not in view.status.text(),
                                timeout=WORKER_TASK_MS)
                assert task.status is TaskStatus.FAILED and view.status.text() == task.error
                assert not view.status.text().startswith("Report written") and "\n" not in task.error
                results.append(task.error)
            assert entries(place) == [], entries(place)  # nothing claimed, nothing left
            word = "full" if place.name == "full" else "read-only"
            assert all(word in r for r in results), results
        seen = therapy.check_undisturbed(t0, time.monotonic())
        _undisturbed(seen)  # the HDF5 crash (or error) in the worker took nothing of the therapy with it

        # 4. F12 while a session loads: the stop on both wires at once
        task = browser.replay()
        qtbot.waitUntil(lambda: task.fraction > 0, timeout=20000)
        thread, pressed = therapy.press_f12_later(0.0)
        thread.join()
        qtbot.waitUntil(lambda: all(d is not None for d in therapy.stop_delays(pressed["t"])), timeout=3000)
        fes_delay, robot_delay = therapy.stop_delays(pressed["t"])
        assert fes_delay <= ESTOP_BOUND_S and robot_delay <= ESTOP_BOUND_S, (fes_delay, robot_delay)
        assert therapy.manager.supervisor.estop_latched
        qtbot.waitUntil(lambda: task.done, timeout=WORKER_TASK_MS)
        assert task.ok  # the load finishes anyway; its window opens
        print(f"F12 during the load: FES Stop {fes_delay * 1e3:.1f} ms, robot IDLE {robot_delay * 1e3:.1f} ms")
    finally:
        stop_therapy(therapy)
        for w in list(browser.windows):
            w.close()
        mounts.close()
