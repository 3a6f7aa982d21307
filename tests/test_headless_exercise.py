"""A library exercise without the window (issue #39): ``--headless --exercise NAME --param NAME=VALUE …`` runs it as
the Exercises tab starts it (app.therapy.exercises.start_exercise: the run's program, parameters and source in its
record, the patient's limits applied); every wrong argument is refused in one sentence before anything starts; and
``--export`` takes an archived session's UUID as ``--report`` / ``--metrics`` do.

The refusals call the command line's ``main`` with the devices' manager and the archive's opening replaced by a
failure (anything started fails the test): no device is built. One real run on the simulators."""

from __future__ import annotations

import functools
import json
import threading
from pathlib import Path
from typing import Any

import pytest

from app.archive.store import open_archive
from app.therapy.patients import PatientProfile, PatientRobotLimits

PATIENT = "PZ-039"
TRIGGER = "Trigger reaching (grip-triggered passive movements)"


def station(tmp_path: Path, monkeypatch: Any, name: str = "room-A", devices: str = "") -> tuple[Path, str]:
    """A station of an SQLite archive in ``tmp_path``: its data folder (LINARMPP_HOME) set, (its configuration file,
    the archive's URL)."""
    url = f"sqlite:///{tmp_path / 'archive.sqlite3'}"
    config = tmp_path / f"{name}.yaml"
    config.write_text(f"archive: {{url: '{url}'}}\nstation: {name}\n{devices}", encoding="utf-8")
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / name))
    return config, url


def add_patient(url: str, profile: PatientProfile) -> None:
    with open_archive(url=url, station="room-A") as archive:
        archive.save_patient(profile, expected_version=None, operator="dr_rossi")


def started(*_args: Any, **_kwargs: Any) -> Any:
    raise AssertionError("something was started")


@pytest.fixture
def nothing_starts(monkeypatch: Any) -> None:
    """Building the devices' manager or opening the archive fails the test: a refusal starts nothing."""
    from app import cli
    from app.manager import LinarmppManager

    monkeypatch.setattr(LinarmppManager, "__init__", started)
    monkeypatch.setattr(cli, "_open_archive_headless", started)


# ---------------------------------------------------------------------------------------------- refusals
REFUSALS = [
    (["--exercise", "reaching_sideways"],
     "Nothing was started: there is no exercise 'reaching_sideways' in the library (its exercises: "
     "trigger_reaching, assisted_reaching_fes, free_admittance, temperature_follow)."),
    (["--exercise", "trigger_reaching", "--param", "movements=2", "--param", "repeats=3"],
     f"Nothing was started: {TRIGGER} has no parameter 'repeats' (its parameters: movements, start_m, end_m, "
     "speed_m_s, acceleration_m_s2, trigger_threshold_n, trigger_timeout_s, rest_s)."),
    (["--exercise", "trigger_reaching", "--param", "speed_m_s=0.5"],
     "Nothing was started: --param speed_m_s=0.5 is refused, Speed accepts 0.02 … 0.3 m/s (0.5 m/s is above the "
     "maximum 0.3 m/s)."),
    (["--exercise", "trigger_reaching", "--param", "movements=0"],
     "Nothing was started: --param movements=0 is refused, Movements accepts whole numbers 1 … 100 (0 is below the "
     "minimum 1)."),
    (["--exercise", "trigger_reaching", "--param", "movements=two"],
     "Nothing was started: --param movements=two is refused, Movements accepts whole numbers 1 … 100 ('two' is not "
     "a number)."),
    (["--exercise", "trigger_reaching", "--param", "movements=2.5"],
     "Nothing was started: --param movements=2.5 is refused, Movements accepts whole numbers 1 … 100 (must be a "
     "whole number)."),
    (["--exercise", "assisted_reaching_fes", "--param", "use_fes=maybe"],
     "Nothing was started: --param use_fes=maybe is refused, FES accepts yes or no."),
    (["--param", "movements=2"],
     "Nothing was started: --param sets a value of the exercise --exercise NAME runs; give --exercise."),
    (["--exercise", "trigger_reaching", "--script", "resources/scripts/trigger_exercise.py"],
     "Nothing was started: --exercise and --script each say what to run; give one of them."),
]


@pytest.mark.parametrize(("args", "sentence"), REFUSALS,
                         ids=["unknown exercise", "unknown parameter", "out of range", "below range", "wrong type",
                              "not whole", "not yes or no", "param without exercise", "with script"])
def test_a_wrong_exercise_argument_is_one_sentence_and_exit_2_and_nothing_starts(
        args: list[str], sentence: str, nothing_starts: None, tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    from app.cli import main

    config, _url = station(tmp_path, monkeypatch)
    assert main(["--config", str(config), "--headless", *args]) == 2
    out, err = capsys.readouterr()
    assert (err, out) == (sentence + "\n", "")
    assert not (tmp_path / "archive.sqlite3").exists()  # not even the archive was opened


def test_the_exercise_is_found_by_its_title_in_any_case() -> None:
    from app.scripting.headless import exercise_values, library_exercise

    exercise = library_exercise("  trigger REACHING (grip-triggered passive movements) ")
    assert exercise.ident == "trigger_reaching"
    values = exercise_values(exercise, ["movements=3", "speed_m_s=0,2"])  # the form's rule: a decimal comma too
    assert (values["movements"], values["speed_m_s"], values["rest_s"]) == (3, 0.2, 0.5)


def test_values_the_patients_limits_refuse_are_one_sentence_and_exit_2_before_anything_starts(
        tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """In range for the form, above this patient's speed limit: refused as the Exercises tab refuses it in their
    session (app.therapy.exercises.prescription_problems), before the devices start."""
    from app.cli import main
    from app.manager import LinarmppManager

    config, url = station(tmp_path, monkeypatch)
    add_patient(url, PatientProfile(patient_id=PATIENT, robot=PatientRobotLimits(max_velocity_m_s=0.1)))
    monkeypatch.setattr(LinarmppManager, "__init__", started)  # the devices: never built
    code = main(["--config", str(config), "--headless", "--exercise", "trigger_reaching", "--param", "speed_m_s=0.2",
                 "--patient", PATIENT, "--operator", "dr_verdi"])
    assert code == 2
    assert capsys.readouterr().err == (
        f"Nothing was started: the limits of patient {PATIENT} refuse {TRIGGER} with these values (Speed: 0.2 m/s is "
        "above this patient's limit of 0.1 m/s).\n")
    assert not (tmp_path / "room-A" / "sessions").exists()


# ---------------------------------------------------------------------------------------------- a real run
@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.sim_homed
def test_a_headless_exercise_is_the_patients_run_with_its_program_parameters_and_source(
        tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """``--headless --exercise trigger_reaching --param movements=2 … --patient --operator`` on the simulators,
    the simulated patient squeezing at each prompt: the session is the patient's, archived, and its one run is the
    exercise with the values given (the others their defaults), started from the command line, both movements
    done."""
    from app.cli import main
    from app.scripting import headless

    config, url = station(tmp_path, monkeypatch, devices="devices: {patient_model: {mode: 'off'}, vr: {mode: 'off'}}\n")
    add_patient(url, PatientProfile(patient_id=PATIENT, full_name="Maria Esposito"))
    timers: list[threading.Timer] = []

    def squeeze_at_each_prompt(manager: Any) -> None:
        patient = manager.sim_patient()
        patient.idle()

        def on_event(kind: str, _data: dict[str, Any]) -> None:
            if kind == "prompt":  # the patient reacts to the cue
                timers.append(threading.Timer(0.2, patient.squeeze, (0.3,)))  # released before the next prompt
                timers[-1].start()

        manager.bus.listen("test", lambda r: on_event(r.kind, r.data))

    monkeypatch.setattr(headless, "run_headless_exercise",
                        functools.partial(headless.run_headless_exercise, prepare=squeeze_at_each_prompt))
    given = {"movements": "2", "start_m": "0.12", "end_m": "0.17", "speed_m_s": "0.3", "acceleration_m_s2": "1"}
    params = [a for k, v in given.items() for a in ("--param", f"{k}={v}")]
    try:
        code = main(["--config", str(config), "--headless", "--exercise", "trigger_reaching", *params,
                     "--patient", PATIENT, "--operator", "dr_verdi", "--duration", "30"])
    finally:
        for timer in timers:
            timer.cancel()
            timer.join(5.0)
    out, err = capsys.readouterr()
    assert code == 0, err
    assert out.rstrip().splitlines()[-1] == "Session archived.", out
    with open_archive(url=url, station="room-A") as archive:
        (session,) = archive.list_sessions(PATIENT)
        (run,) = archive.runs(session.uuid)
    assert (session.station, session.operator) == ("room-A", "dr_verdi")
    assert (run.program["kind"], run.program["ident"], run.title) == ("exercise", "trigger_reaching", TRIGGER)
    assert (run.source, run.operator, run.end_reason) == ("headless", "dr_verdi", "finished")
    values = {p["name"]: p["value"] for p in run.parameters}
    assert values == {"movements": 2, "start_m": 0.12, "end_m": 0.17, "speed_m_s": 0.3, "acceleration_m_s2": 1.0,
                      "trigger_threshold_n": 20.0, "trigger_timeout_s": 10.0, "rest_s": 0.5}
    assert (run.summary["repetitions"], run.summary["completed"]) == (2, 2), run.summary
    (events,) = (tmp_path / "room-A" / "sessions" / PATIENT).rglob("events.jsonl")
    starts = [e["data"] for e in map(json.loads, events.read_text(encoding="utf-8").splitlines())
              if e["kind"] == "exercise_start"]
    assert starts == [{"exercise": "trigger_reaching", "title": TRIGGER, "script": "trigger_reaching.py",
                       "params": values}]


# ---------------------------------------------------------------------------------------------- --export UUID
def test_export_of_an_archived_sessions_uuid_writes_what_its_folder_gives(
        tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """A session recorded on room-A and uploaded to the archive; on room-B (no folder of it) ``--export UUID``
    writes the HDF5 that ``--export FOLDER`` writes on room-A."""
    import numpy as np

    from app.archive import folders
    from app.archive.outbox import Outbox
    from app.cli import main
    from app.session.export import load_hdf5
    from tests.run_sessions import RunSpec, write_run_session

    config_a, url = station(tmp_path, monkeypatch, "room-A")
    config_b, _ = station(tmp_path, monkeypatch, "room-B")
    folder = write_run_session(tmp_path / "room-A" / "sessions" / PATIENT / "20260302-100000",
                               [RunSpec(TRIGGER, "trigger_reaching", reps=3)], start_iso="2026-03-02T10:00:00+01:00")
    status = Outbox(tmp_path / "room-A" / "sessions", lambda: open_archive(url=url, station="room-A")).run_once(
        force=True)
    assert (status.uploaded, status.waiting) == (1, 0), status.text()
    uuid = folders.session_uuid(folder)

    def export(config: Path, home: str, session: str) -> Path:
        monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / home))
        out = tmp_path / f"{home}.h5"
        assert main(["--config", str(config), "--export", session, "--out", str(out)]) == 0, capsys.readouterr().err
        assert "HDF5, verified" in capsys.readouterr().err
        return out

    by_folder = load_hdf5(export(config_a, "room-A", str(folder)))
    by_uuid = load_hdf5(export(config_b, "room-B", uuid))
    assert by_uuid.manifest == by_folder.manifest and by_uuid.manifest["patient_id"] == PATIENT
    assert by_uuid.events == by_folder.events and len(by_uuid.events) > 10
    assert set(by_uuid.streams) == set(by_folder.streams) and by_folder.streams
    for name, stream in by_folder.streams.items():
        other = by_uuid.streams[name]
        assert np.array_equal(other.t, stream.t) and len(stream.t) > 0
        assert all(np.array_equal(other.data[c.name], stream.data[c.name], equal_nan=True) for c in stream.channels)
    unknown = "6a1c7f0e-0000-4000-8000-000000000000"
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "room-B"))
    assert main(["--config", str(config_b), "--export", unknown, "--out", str(tmp_path / "x.h5")]) == 2
    assert f"the archive has no session {unknown}" in capsys.readouterr().err
