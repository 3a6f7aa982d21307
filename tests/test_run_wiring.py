"""Issue #26: every start opens a run and every end closes it with what really happened (finished, script
error, refused before its first movement, stopped by the operator, emergency stop, session ended), the
repetition marks carry the run's id, the record read back gives the same runs, the elapsed time stops with
the run, and each run starts from the robot's default settings (no stiffness carried over from the last)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from app.core import journal
from app.core.bus import StreamBus
from app.core.config import AppConfig, UdpEndpoint
from app.core.progress import ExerciseProgress
from app.core.runs import Program, RunLog, runs_from_events, text_hash
from app.manager import LinarmppManager
from app.scripting.runner import ScriptRunner

pytestmark = pytest.mark.sim_homed  # a homed LINarm from the start: the homing is tested on its own


@pytest.fixture
def manager(qtbot: Any) -> Iterator[LinarmppManager]:
    cfg = AppConfig()
    cfg = replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"),
                                       vr=UdpEndpoint(mode="off")))
    m = LinarmppManager(cfg)
    try:
        m.start()
        qtbot.waitUntil(m.all_connected, timeout=15000)
        yield m
    finally:
        m.shutdown()


@pytest.fixture
def runner(manager: LinarmppManager) -> Iterator[ScriptRunner]:
    r = ScriptRunner(manager, lambda _s, _t: None)
    try:
        yield r
    finally:
        r.stop("test over", wait_s=2.0)
        r.close()


def _run(runner: ScriptRunner, source: str, name: str = "x.py", timeout: float = 30.0) -> Any:
    run = runner.start(source, f"/tmp/{name}", run_source="script_tab")
    assert runner.wait(timeout), "the script did not end"
    return runner.manager.runs.get(run.run_id)


def test_each_end_is_recorded_with_its_real_cause(qtbot: Any, manager: LinarmppManager, runner: ScriptRunner,
                                                  tmp_path: Path) -> None:
    folder = manager.start_session("P-WIRING", "Dr Bianchi", root=tmp_path)
    runner.home_first = False  # the reasons, not the homing, are under test here
    done = _run(runner, "linarmppManager.startRepetition(1, 1)\nlinarmppManager.endRepetition(1, True)\n")
    assert (done.end_reason, done.source, done.operator) == ("finished", "script_tab", "Dr Bianchi")
    assert [(m.index, m.ok) for m in done.repetitions] == [(1, True)]
    err = _run(runner, "x = 1\nraise ValueError('bad value')\n")
    assert err.end_reason == "script_error" and "bad value" in err.end_detail and "line 2" in err.end_detail
    # refused by the safety supervisor before any movement: "refused", never a completed repetition
    refused = _run(runner, "linarm.moveCentreTo(0.9, 0.1, 0.1, 0, False)\n")
    assert refused.end_reason == "refused", refused.end_detail
    assert refused.repetitions == ()

    run = runner.start("wait(30)\n", "/tmp/wait.py")
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "running", timeout=5000)
    runner.stop("stopped by the operator (Script tab)")
    assert manager.runs.get(run.run_id).end_reason == "stopped_by_operator"

    run = runner.start("wait(30)\n", "/tmp/wait.py")
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "running", timeout=5000)
    manager.supervisor.emergency_stop("keyboard")
    assert runner.wait(5.0)
    assert manager.runs.get(run.run_id).end_reason == "emergency_stop"
    manager.supervisor.reset_emergency_stop("Dr Bianchi")

    run = runner.start("wait(30)\n", "/tmp/wait.py")
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "running", timeout=5000)
    live = manager.runs
    manager.end_session()
    assert runner.wait(5.0)
    assert live.get(run.run_id).end_reason == "session_ended"

    events = [json.loads(line) for line in (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()]
    reps = [e["data"] for e in events if e["kind"] in ("repetition_start", "repetition_end")]
    assert reps and all(d.get("run_id") == done.run_id for d in reps)
    again = runs_from_events(events)
    assert [r.end_reason for r in again] == ["finished", "script_error", "refused", "stopped_by_operator",
                                             "emergency_stop", "session_ended"]
    assert [r.program.kind for r in again] == ["script_file"] * 6
    assert again[1].program.text == "x = 1\nraise ValueError('bad value')\n"
    ends = {e["data"]["run_id"]: e["data"] for e in events if e["kind"] == "run_end"}
    assert ends[refused.run_id]["not_started"] is True and ends[refused.run_id]["completed"] == 0


def test_the_program_says_its_state_and_pause_shows_it(qtbot: Any, manager: LinarmppManager,
                                                       runner: ScriptRunner) -> None:
    runner.home_first = False
    run = runner.start("linarmppManager.setRunState('waiting_for_grip')\nwait(30)\n", "/tmp/s.py")
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "waiting_for_grip", timeout=5000)
    assert manager.progress.state.state_text == "waiting for the grip"
    runner.pause()
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "paused", timeout=2000)
    runner.resume()
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "waiting_for_grip", timeout=2000)
    runner.stop()
    state = manager.progress.state
    assert not state.running and state.state_text == "stopped: stopped by the operator"


def test_a_bad_state_from_the_program_is_an_error(manager: LinarmppManager, runner: ScriptRunner) -> None:
    runner.home_first = False
    run = _run(runner, "linarmppManager.setRunState('dancing')\n")
    assert run.end_reason == "script_error" and "dancing" in run.end_detail


def test_each_run_starts_from_the_default_stiffness(qtbot: Any, manager: LinarmppManager,
                                                    runner: ScriptRunner) -> None:
    """The first run stiffens the springs (free_admittance does); the next one, which sets nothing, must not
    inherit it: the runner brings the pretension back to the homed one before the program's own code."""
    stiff = ("linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)\n"
             "linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)\n"
             "linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)\n"
             "linarm.setStiffness(1800, 0.1, 0.5, 0)\n"
             "linarm.setAdmittanceParameter(0.004)\n"
             "ok = waitCondition(lambda: linarm.linarmVsaState.stiffness > 1700, 15)\n"
             "assert ok, linarm.linarmVsaState\n")
    assert runner.home_first  # the runner prepares the robot (homing when needed, then its defaults)
    first = _run(runner, stiff, "stiff.py", timeout=60)
    assert first.end_reason == "finished", first.end_detail
    robot = manager.driver("linarm")
    assert robot.latest("linarm.vsa").stiffness > 1700  # left stiff
    # Refused (the e-stop latched), the defaults are reported and the program still starts.
    said: list[str] = []
    runner.output = lambda _stream, text: said.append(text)
    manager.supervisor.emergency_stop("test")
    looked = _run(runner, "print('looking only')\n", "look.py")
    assert looked.end_reason == "finished", looked.end_detail
    assert any("default settings were not restored" in t for t in said) and "looking only\n" in said
    manager.supervisor.reset_emergency_stop("Dr Bianchi")
    # The robot moves again only once the STOP alarms are acknowledged (#25: ON and homing are refused while one
    # is open), as Recover does first.
    for alarm in manager.supervisor.alarms():
        if not alarm.acknowledged:
            manager.supervisor.acknowledge(alarm.ident, "Dr Bianchi")
    probe = ("print(linarm.getAdmittanceParameter())\n"
             "assert abs(linarm.linarmVsaState.stiffness - 900) < 60, linarm.linarmVsaState.stiffness\n"
             "assert abs(linarm.getAdmittanceParameter() - 0.005) < 1e-9, linarm.getAdmittanceParameter()\n")
    second = _run(runner, probe, "probe.py", timeout=60)
    assert second.end_reason == "finished", second.end_detail


def test_the_elapsed_time_stops_with_the_run(qapp: Any) -> None:
    class Clock:
        t = 10.0

        def __call__(self) -> float:
            return self.t

    clock = Clock()
    progress = ExerciseProgress(clock=clock)
    bus = StreamBus()  # the run's changes reach the progress as journal records, as in the app
    progress.follow_runs(bus)
    runs = RunLog(lambda kind, **data: bus.record(journal.RUN, kind, data), clock=clock)
    progress.attach_runs(runs)
    run = runs.start(Program("script_file", "/x.py", "x.py", text_hash("")), (), "script_tab", "A")
    progress.begin("x.py", run_id=run.run_id)
    clock.t = 15.0
    progress.start_repetition(1, 3)
    assert runs.get(run.run_id).repetitions[0].index == 1
    clock.t = 20.0
    runs.end(run.run_id, "emergency_stop", "F12")
    progress.finish("stopped")
    clock.t = 900.0
    state = progress.state
    assert state.elapsed_s() == pytest.approx(10.0)
    assert state.state_text == "stopped: emergency stop" and not state.running
    assert state.label() == "repetition 1 of 3"


def test_a_headless_run_is_in_its_record(qapp: Any, tmp_path: Path) -> None:
    from app.scripting.headless import EXIT_OK, run_headless

    script = tmp_path / "short.py"
    script.write_text("linarmppManager.startRepetition(1, 1)\nlinarmppManager.endRepetition(1, True)\n",
                      encoding="utf-8")
    cfg = AppConfig()
    cfg = replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"),
                                       vr=UdpEndpoint(mode="off")))
    code = run_headless(cfg, str(script), record_dir=str(tmp_path / "rec"), home_first=False,
                        output=lambda _s, _t: None)
    assert code == EXIT_OK
    (events_file,) = (tmp_path / "rec").rglob("events.jsonl")
    events = [json.loads(line) for line in events_file.read_text(encoding="utf-8").splitlines()]
    (run,) = runs_from_events(events)
    assert (run.source, run.end_reason, run.program.kind) == ("headless", "finished", "script_file")
    assert run.program.path == str(script.resolve()) and [m.ok for m in run.repetitions] == [True]


def test_closing_the_application_ends_the_run_as_app_exit(qtbot: Any, manager: LinarmppManager,
                                                          runner: ScriptRunner, tmp_path: Path) -> None:
    manager.start_session("P-EXIT", "Dr Bianchi", root=tmp_path)
    runner.home_first = False
    run = runner.start("wait(30)\n", "/tmp/wait.py")
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).state == "running", timeout=5000)
    live = manager.runs
    manager.shutdown()
    assert live.get(run.run_id).end_reason == "app_exit"
    assert runner.wait(5.0)
    assert live.get(run.run_id).end_reason == "app_exit"  # the runner's later end does not overwrite it


def test_a_repetition_open_at_the_stop_ends_before_its_run(qtbot: Any, manager: LinarmppManager,
                                                           runner: ScriptRunner) -> None:
    """The record reads in order: the interrupted repetition's end (not completed), then the run's end."""
    events: list[tuple[str, dict[str, Any]]] = []
    manager.bus.listen("test", lambda r: events.append((r.kind, dict(r.data))))
    runner.home_first = False
    run = runner.start("linarmppManager.startRepetition(1, 3)\nwait(30)\n", "/tmp/rep.py")
    qtbot.waitUntil(lambda: manager.runs.get(run.run_id).repetitions != (), timeout=10000)
    runner.stop()
    kinds = [(k, d.get("ok")) for k, d in events
             if k in ("repetition_end", "run_end") and d.get("run_id") == run.run_id]
    assert kinds == [("repetition_end", False), ("run_end", None)]
    end = next(d for k, d in events if k == "run_end" and d["run_id"] == run.run_id)
    assert end["completed"] == 0 and end["not_started"] is False

