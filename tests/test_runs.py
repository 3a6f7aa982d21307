"""The run record (app/core/runs.py): what the live RunLog writes, runs_from_events reads back the same."""

from __future__ import annotations

from typing import Any

import pytest

from app.core.runs import Program, RunLog, RunParameter, runs_from_events, text_hash


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _log() -> tuple[RunLog, list[dict[str, Any]], Clock]:
    events: list[dict[str, Any]] = []
    clock = Clock()

    def record(kind: str, **data: Any) -> None:
        events.append({"kind": kind, "t_mono": clock.t, "data": data})
    return RunLog(record, clock=clock, wall_clock=lambda: 0.0), events, clock


def test_a_run_round_trips_through_the_record() -> None:
    log, events, clock = _log()
    prog = Program("exercise", "trigger_reaching", "Trigger reaching", text_hash("x"), version="v1")
    run = log.start(prog, [RunParameter("cycles", "Movements", 8, "")], "exercises_tab", "Dr A")
    assert log.current() == run
    clock.t = 101.0
    log.set_state(run.run_id, "waiting_for_grip")
    log.repetition_started(run.run_id, 1)
    events.append({"kind": "repetition_start", "t_mono": clock.t, "data": {"run_id": run.run_id, "index": 1}})
    clock.t = 103.0
    log.repetition_ended(run.run_id, 1, True)
    events.append({"kind": "repetition_end", "t_mono": clock.t, "data": {"run_id": run.run_id, "index": 1, "ok": True}})
    clock.t = 104.0
    log.end(run.run_id, "emergency_stop", "F12")
    log.end(run.run_id, "finished")  # a second end is ignored: the first cause stays
    live = log.get(run.run_id)
    assert live is not None and live.end_reason == "emergency_stop" and live.elapsed_s() == pytest.approx(4.0)
    restart = log.start(prog, live.parameters, "recover", "Dr A", restart_of=run.run_id)
    (a, b) = runs_from_events(events, t_end=110.0)
    assert (a.run_id, a.end_reason, a.end_detail, a.state) == (run.run_id, "emergency_stop", "F12", "stopped")
    assert [(m.index, m.start_mono, m.end_mono, m.ok) for m in a.repetitions] == [(1, 101.0, 103.0, True)]
    assert a.params_dict() == {"cycles": 8} and a.program.title == "Trigger reaching"
    assert b.restart_of == run.run_id and b.source == "recover"
    assert b.end_reason == "crashed" and b.ended_mono == 110.0  # no run_end in the record: a crash
    assert restart.run_id != run.run_id
    assert [e["data"]["not_started"] for e in events if e["kind"] == "run_end"] == [False]


def test_a_run_refused_before_its_first_movement_is_not_started() -> None:
    log, events, _ = _log()
    run = log.start(Program("console", "<console>", "Console code", text_hash("1"), text="1"), [], "console", "B")
    log.end(run.run_id, "refused", "FES current above the patient's cap")
    end = next(e for e in events if e["kind"] == "run_end")["data"]
    assert end["not_started"] is True and end["completed"] == 0


def test_a_restart_is_refused_when_the_program_cannot_be_run_again(tmp_path: Any) -> None:
    f = tmp_path / "ex.py"
    f.write_text("print(1)\n", encoding="utf-8")
    lib = Program("exercise", "ex", "Ex", text_hash("print(1)\n"), path=str(f))
    assert lib.changed_on_disk() == ""
    f.write_text("print(2)\n", encoding="utf-8")
    assert "changed on disk" in lib.changed_on_disk()
    assert "console" in Program("console", "<console>", "c", text_hash("x"), text="x").changed_on_disk()
    assert Program("script_file", str(f), "ex.py", text_hash("print(1)\n"), path=str(f),
                   text="print(1)\n").changed_on_disk() == ""


def test_unknown_states_and_reasons_are_refused() -> None:
    log, _, _ = _log()
    run = log.start(Program("console", "<console>", "c", text_hash("x")), [], "console", "B")
    with pytest.raises(ValueError):
        log.set_state(run.run_id, "dancing")
    with pytest.raises(ValueError):
        log.end(run.run_id, "bored")
