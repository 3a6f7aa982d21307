"""The run log's changes travel as journal records on the bus (issue #40, "One journal"), and whoever follows runs
— the devices' leases (one owner, #36), the exercise's progress — hears them there, not through a listener list
of the run log's own.

Each session makes a run log of its own whose ids start again at run-1, so every run record names its log
(``log``); ``run_end`` carries the end on the run log's clock (``ended_mono``). A run still open in an earlier log
when the session ends is ended there (its lease released through its record). Recorded sessions written before
the ``log`` field still load.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from app.core import journal
from app.core.bus import StreamBus
from app.core.config import AppConfig
from app.core.journal import Record
from app.core.progress import ExerciseProgress
from app.core.runs import Program, RunLog, runs_from_events, text_hash

EXERCISE = Program("exercise", "trigger_reaching", "Trigger reaching", text_hash(""))
LOOK = Program("script_file", "look.py", "look.py", text_hash(""))


class Clock:
    def __init__(self, t: float = 10.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _manager() -> Any:
    from app.manager import LinarmppManager

    return LinarmppManager(AppConfig(), factories={})


def _events(folder: Path) -> list[dict[str, Any]]:
    text = (folder / "events.jsonl").read_text(encoding="utf-8")
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def test_leases_follow_runs_through_the_journal_across_two_sessions(qapp: Any, tmp_path: Path) -> None:
    """Two consecutive sessions, each with its run-1 holding the robot: each takes the robot when its run_start
    record is published and gives it back at its run_end, and the records tell the two run-1s apart."""
    manager = _manager()
    sup = manager.supervisor
    queue = manager.bus.subscribe("test", [], records=True, keep_records=True)  # in order, as the recorder reads
    folders = []
    for patient in ("P-ONE", "P-TWO"):
        folders.append(manager.start_session(patient, "Dr Rossi", root=tmp_path))
        run = manager.runs.start(EXERCISE, (), "exercises_tab", "Dr Rossi", holds=("robot",))
        assert run.run_id == "run-1"
        assert sup.holder("robot") == "Trigger reaching"
        manager.runs.end(run.run_id, "finished")
        assert sup.holder("robot") == ""
        manager.end_session()
    heard = [r for r in queue.drain() if isinstance(r, Record)]
    queue.close()
    starts = [r for r in heard if r.kind == journal.RUN_START]
    assert [r.origin for r in starts] == [journal.RUN, journal.RUN]
    assert [r.data["run_id"] for r in starts] == ["run-1", "run-1"]
    logs = [r.data.get("log") for r in starts]
    assert all(logs) and logs[0] != logs[1], f"the two sessions' run-1 records do not name their logs: {logs}"
    # The lease follows its run's record: taken right after run_start, released right after run_end.
    kinds = [r.kind for r in heard if r.kind in (journal.RUN_START, journal.RUN_END, journal.LEASE_TAKEN,
                                                  journal.LEASE_RELEASED)]
    assert kinds == [journal.RUN_START, journal.LEASE_TAKEN, journal.RUN_END, journal.LEASE_RELEASED] * 2
    for folder in folders:  # each session's record reads back one finished run, its lease beside it
        events = _events(folder)
        (run,) = runs_from_events(events)
        assert (run.run_id, run.end_reason) == ("run-1", "finished")
        assert [e["kind"] for e in events if e["kind"] in kinds] == kinds[:4]


def test_a_lease_follows_a_run_record_heard_on_the_bus(qapp: Any) -> None:
    """The manager holds devices for whatever run the journal announces, whichever run log published it."""
    manager = _manager()
    sup = manager.supervisor
    elsewhere = RunLog(lambda kind, **data: manager.bus.record(journal.RUN, kind, data))  # not the manager's log
    run = elsewhere.start(LOOK, (), "console", "t", holds=("stimulator",))
    assert sup.holder("stimulator") == "look.py", "the manager did not hold the devices of a run the journal announced"
    mine = manager.runs.start(EXERCISE, (), "exercises_tab", "t", holds=("robot",))
    assert mine.run_id == run.run_id  # both run-1, in two logs
    elsewhere.end(run.run_id, "finished")
    assert (sup.holder("stimulator"), sup.holder("robot")) == ("", "Trigger reaching")
    manager.runs.end(mine.run_id, "finished")
    assert sup.holder("robot") == ""


def test_a_lease_held_by_an_earlier_logs_open_run_is_released_at_the_sessions_end(qapp: Any, tmp_path: Path) -> None:
    """A run opened before the session (its log is the one the session replaced) still holds the stimulator when
    the session ends: the session's end ends it in its own log, and its record releases the lease — the session's
    own run-1 is not taken for it."""
    manager = _manager()
    sup = manager.supervisor
    earlier = manager.runs
    old = earlier.start(LOOK, (), "console", "t", holds=("stimulator",))
    folder = manager.start_session("P-EARLY", "Dr Rossi", root=tmp_path)
    assert manager.runs is not earlier and earlier.get(old.run_id).running
    assert sup.holder("stimulator") == "look.py"  # the session's start does not end a run of another log
    mine = manager.runs.start(EXERCISE, (), "exercises_tab", "Dr Rossi", holds=("robot",))
    assert mine.run_id == old.run_id
    manager.end_session()
    assert sup.holder("stimulator") == "", "a lease of an earlier log's run outlived the session"
    assert sup.holder("robot") == ""
    assert earlier.get(old.run_id).end_reason == "session_ended"
    (run,) = runs_from_events(_events(folder))  # the session's record: its own run-1 only
    assert (run.program.ident, run.end_reason) == ("trigger_reaching", "session_ended")


def test_the_progress_follows_its_run_through_the_journal_on_the_run_logs_clock(qapp: Any) -> None:
    """The run's state and end reach the exercise's progress as records; the end is the run log's time (a
    virtual clock here), carried in ``run_end`` — not the time the record was published."""
    clock = Clock()
    bus = StreamBus()
    heard: list[Record] = []
    bus.listen("test", heard.append)
    progress = ExerciseProgress(clock=clock)
    progress.follow_runs(bus)
    runs = RunLog(lambda kind, **data: bus.record(journal.RUN, kind, data), clock=clock)
    progress.attach_runs(runs)
    run = runs.start(EXERCISE, (), "exercises_tab", "A")
    progress.begin("Trigger reaching", run_id=run.run_id)
    runs.set_state(run.run_id, "waiting_for_grip", "hold still")
    assert progress.state.run_state == "waiting_for_grip"
    assert progress.state.state_text == "waiting for the grip (hold still)"
    # the same run id in another log is not this run
    other = RunLog(lambda kind, **data: bus.record(journal.RUN, kind, data), clock=clock)
    twin = other.start(EXERCISE, (), "exercises_tab", "A")
    assert twin.run_id == run.run_id
    other.set_state(twin.run_id, "moving")
    assert progress.state.run_state == "waiting_for_grip", "another log's run-1 was taken for this one"
    clock.t = 20.0
    runs.end(run.run_id, "emergency_stop", "F12")
    end = next(r for r in heard if r.kind == journal.RUN_END and r.data.get("log") == runs.log_id)
    assert end.data["ended_mono"] == 20.0
    assert progress.state.ended_monotonic == 20.0
    assert progress.state.state_text == "stopped: emergency stop" and progress.state.run_state == "stopped"
    clock.t = 900.0
    assert progress.state.elapsed_s(clock.t) == pytest.approx(10.0)
    progress.stop_following_runs()
    other.end(twin.run_id, "finished")


def test_an_old_record_without_the_log_field_still_loads() -> None:
    """Sessions recorded before run records named their log read back as before."""
    events = [
        {"kind": "run_start", "t_mono": 1.0, "data": {"run_id": "run-1", "program": EXERCISE.as_dict(),
                                                      "parameters": [], "source": "exercises_tab"}},
        {"kind": "run_state", "t_mono": 2.0, "data": {"run_id": "run-1", "state": "moving"}},
        {"kind": "repetition_start", "t_mono": 2.5, "data": {"run_id": "run-1", "index": 1}},
        {"kind": "repetition_end", "t_mono": 3.0, "data": {"run_id": "run-1", "index": 1, "ok": True}},
        {"kind": "run_end", "t_mono": 4.0, "data": {"run_id": "run-1", "reason": "finished", "completed": 1}},
    ]
    (run,) = runs_from_events(events)
    assert (run.end_reason, run.ended_mono, len(run.repetitions)) == ("finished", 4.0, 1)


def test_another_logs_records_do_not_touch_a_run_of_the_same_id() -> None:
    """In one session's record, the end (and the marks) of an earlier log's run-1 — still open when the session
    began — are not the session's run-1's."""
    events = [
        {"kind": "run_start", "t_mono": 1.0, "data": {"run_id": "run-1", "log": "log-2",
                                                      "program": EXERCISE.as_dict(), "parameters": []}},
        {"kind": "repetition_start", "t_mono": 1.5, "data": {"run_id": "run-1", "log": "log-1", "index": 1}},
        {"kind": "run_state", "t_mono": 1.6, "data": {"run_id": "run-1", "log": "log-1", "state": "moving"}},
        {"kind": "run_end", "t_mono": 2.0, "data": {"run_id": "run-1", "log": "log-1", "reason": "finished"}},
        {"kind": "run_state", "t_mono": 2.5, "data": {"run_id": "run-1", "log": "log-2", "state": "resting"}},
        {"kind": "run_end", "t_mono": 5.0, "data": {"run_id": "run-1", "log": "log-2",
                                                    "reason": "stopped_by_operator"}},
    ]
    (run,) = runs_from_events(events)
    assert (run.end_reason, run.ended_mono, run.repetitions) == ("stopped_by_operator", 5.0, ()), (
        f"the earlier log's run-1 records ended the session's run-1: {run.end_reason} at {run.ended_mono}")


def test_the_exports_spans_keep_two_logs_runs_apart() -> None:
    """The research export's run and repetition spans (BIDS, XDF, EDF+) pair a start with the end of the same run
    in the same log; records without ``log`` pair by id as before."""
    from app.research_export.marks import event_marks

    def run(log: str | None, kind: str, t: float, **data: Any) -> dict[str, Any]:
        return {"kind": kind, "t_mono": t, "data": {"run_id": "run-1", **({"log": log} if log else {}), **data}}

    events = [run("log-2", "run_start", 1.0, program=EXERCISE.as_dict()),
              run("log-2", "repetition_start", 1.5, index=1),
              run("log-1", "repetition_end", 1.8, index=1, ok=False),
              run("log-1", "run_end", 2.0, reason="session_ended"),
              run("log-2", "repetition_end", 3.0, index=1, ok=True),
              run("log-2", "run_end", 5.0, reason="finished")]
    spans = {(m.kind, m.duration) for m in event_marks(events, 6.0) if m.duration}
    assert spans == {("run", 4.0), ("repetition", 1.5)}, f"an earlier log's ends closed the session's spans: {spans}"
    old = [{**e, "data": {k: v for k, v in e["data"].items() if k != "log"}} for e in events if e["t_mono"] != 2.0
           and e["t_mono"] != 1.8]
    assert {(m.kind, m.duration) for m in event_marks(old, 6.0) if m.duration} == {("run", 4.0), ("repetition", 1.5)}
