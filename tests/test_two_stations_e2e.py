"""Two stations of one clinic, end to end (issue #39, acceptance 1): every step is a separate application process
(``main.py`` or the station's own patient functions in a process of their own), each station with its own
configuration file (``station: room-A`` / ``room-B``) and its own data folder (``LINARMPP_HOME``), both on the one
real PostgreSQL server the tests start (tests/postgres.py; under CI=true a server that cannot start fails this
test).

* room-A creates the patient with ``main.py archive patient add`` (the Patients form's fields and checks), then the
  therapy plan as the plan dialog saves it (``app.archive.station.save_profile``, that field alone; no command
  edits a plan), and runs the plan's exercise with ``main.py --headless --exercise … --param … --patient …
  --operator …``;
* room-B lists the patients with ``main.py archive patients --json`` (the patient, the station that made them) and
  as the Start-session dialog reads them (``app.therapy.patients.list_patients`` through the station's installed
  archive: the plan made on A), and runs the plan's exercise the same way for the same patient;
* ``main.py --progress`` on A's and on B's configuration: each PDF lists both sessions, each with its station.

Every process is waited for, and killed if the test fails before it ends."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.archive.store import open_archive
from app.devices.sim.base import HOMED_ENV
from tests.pdf_layout import pdf_text
from tests.postgres import APP, Database, PostgresServer, server_or_skip

ROOT = Path(__file__).resolve().parent.parent
PATIENT = "PZ-239"
EXERCISE = "temperature_follow"
TITLE = "Temperature follow"
PLAN_PARAMS = {"duration_s": 1.0, "base_m": 0.2, "update_period_s": 0.2}  # short: the test pays for every second
# (base_m: where the simulated LINarm powers up homed, so the run does not first travel to its base)

# The station's own patient functions in a process of their own, as the application calls them after its start-up
# (app.cli._open_archive_headless: open_station, install): "plan" saves the patient's therapy plan as the plan
# dialog does (that field alone, as of the version it read); "list" reads the patients as the Start-session dialog
# does. Prints JSON.
_STATION = r"""
import json, sys
from dataclasses import replace
from app.archive import station
from app.core.config import load_config
from app.therapy.patients import PlannedExercise, list_patients

config_file, what = sys.argv[1:3]
config = load_config(config_file)
opened = station.open_station(config)
assert opened.archive is not None, opened.message()
station.install(opened.archive)
try:
    if what == "plan":
        pid, exercise, params = sys.argv[3], sys.argv[4], json.loads(sys.argv[5])
        record = station.read_record(pid, config.safety)
        plan = [PlannedExercise(exercise, params, "every session")]
        record = station.save_profile(replace(record.profile, therapy_plan=plan), expected_version=record.version,
                                      operator=station.default_operator("dr_rossi"), fields=["therapy_plan"],
                                      safety=config.safety, reason="therapy plan")
        print(json.dumps({"version": record.version}))
    else:
        entries = list_patients(safety=config.safety)
        print(json.dumps([{"id": e.patient_id, "error": e.error, "version": e.version,
                           "name": e.profile.full_name if e.profile else "",
                           "plan": [[s.exercise, s.params] for s in e.profile.therapy_plan] if e.profile else []}
                          for e in entries]))
finally:
    archive = station.uninstall()
    if archive is not None:
        archive.close()
"""


@pytest.fixture(scope="module")
def pg_server() -> Iterator[PostgresServer]:
    with server_or_skip() as server:
        yield server


class Clinic:
    """Two stations of one PostgreSQL archive: each its configuration file and its data folder; every command a
    subprocess of its own, waited for (killed when it overstays or the test fails)."""

    def __init__(self, base: Path, db: Database) -> None:
        self.base, self.db = base, db
        for name in ("room-A", "room-B"):
            self.home(name).mkdir(parents=True)
            self.config(name).write_text(
                f"archive: {{url: '{db.url(APP)}', password_file: '{db.password_file(APP)}'}}\n"
                f"station: {name}\n"
                "devices: {patient_model: {mode: 'off'}, vr: {mode: 'off'}}\n", encoding="utf-8")

    def home(self, name: str) -> Path:
        return self.base / name

    def config(self, name: str) -> Path:
        return self.base / f"{name}.yaml"

    def run(self, *commands: tuple[str, list[str]], timeout: float = 90.0) -> list[subprocess.CompletedProcess[str]]:
        """Each ``(station, arguments)`` a Python process of that station (its data folder), all started at once and
        all waited for; any still running when this returns or raises (overstayed, a failure) is killed."""
        procs: list[subprocess.Popen[str]] = []
        try:
            for name, args in commands:
                env = {**os.environ, "LINARMPP_HOME": str(self.home(name)), "QT_QPA_PLATFORM": "offscreen",
                       HOMED_ENV: "1", "PYTHONPATH": str(ROOT)}
                procs.append(subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                              text=True, cwd=ROOT, env=env, start_new_session=True))
            deadline = time.monotonic() + timeout
            done = []
            for proc in procs:
                out, err = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
                done.append(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
            return done
        finally:
            for proc in procs:
                if proc.poll() is None:  # never left running: the process and what it started (its simulators)
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(proc.pid, signal.SIGKILL)
                    proc.communicate()

    def station(self, name: str, *args: str) -> object:
        (done,) = self.run((name, ["-c", _STATION, str(self.config(name)), *args]))
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    def main(self, name: str, *args: str) -> subprocess.CompletedProcess[str]:
        (done,) = self.run(self.main_args(name, *args))
        return done

    def archive(self, name: str, *args: str) -> subprocess.CompletedProcess[str]:
        """``main.py archive --config <the station's> …``."""
        (done,) = self.run((name, [str(ROOT / "main.py"), "archive", "--config", str(self.config(name)), *args]))
        return done

    def main_args(self, name: str, *args: str) -> tuple[str, list[str]]:
        return name, [str(ROOT / "main.py"), "--config", str(self.config(name)), *args]


def plan_args(plan: list[list[object]]) -> list[str]:
    """The plan's first step as the command line runs it: ``--exercise NAME --param k=v …``."""
    exercise, params = plan[0]
    assert isinstance(params, dict)
    return ["--exercise", str(exercise), *[a for k, v in params.items() for a in ("--param", f"{k}={v}")]]


@pytest.mark.slow
@pytest.mark.realtime
def test_a_patient_created_on_one_station_is_treated_on_both_and_either_progress_report_has_both_sessions(
        pg_server: PostgresServer, tmp_path: Path) -> None:
    clinic = Clinic(tmp_path / "clinic", pg_server.new_database())

    # room-A: the patient (the command) and their plan, then the plan's exercise
    added = clinic.archive("room-A", "patient", "add", PATIENT, "--name", "Maria Esposito", "--operator",
                        "dr_rossi")
    assert added.returncode == 0, added.stderr[-2000:]
    assert added.stdout.startswith(f"Patient {PATIENT} added to the archive at "), added.stdout
    created = clinic.station("room-A", "plan", PATIENT, EXERCISE, json.dumps(PLAN_PARAMS))
    assert created == {"version": 2}  # created (1), the plan saved (2)
    with open_archive(url=clinic.db.url(APP), password_file=clinic.db.password_file(APP), station="check") as a:
        record = a.get_patient(PATIENT)
        assert (record.changed_by, record.changed_station) == ("dr_rossi", "room-A")
        plan = [[s.exercise, s.params] for s in record.profile.therapy_plan]
    assert plan == [[EXERCISE, PLAN_PARAMS]]
    run_a = clinic.main("room-A", "--headless", *plan_args(plan), "--patient", PATIENT, "--operator", "dr_rossi",
                        "--duration", "30")
    assert run_a.returncode == 0, run_a.stderr[-2000:]
    assert run_a.stdout.rstrip().splitlines()[-1] == "Session archived.", run_a.stdout[-2000:]

    # room-B: the patient is listed (made on A, one session) and with A's plan; B runs the plan's exercise for them
    table = clinic.archive("room-B", "patients", "--json")
    assert table.returncode == 0, table.stderr[-2000:]
    assert [(p["id"], p["name"], p["station"], p["sessions"]) for p in json.loads(table.stdout)] == [
        (PATIENT, "Maria Esposito", "room-A", 1)]
    listed = clinic.station("room-B", "list")
    assert isinstance(listed, list)
    (entry,) = [e for e in listed if e["id"] == PATIENT]
    assert (entry["error"], entry["name"], entry["version"]) == ("", "Maria Esposito", 2)
    assert entry["plan"] == [[EXERCISE, PLAN_PARAMS]]
    run_b = clinic.main("room-B", "--headless", *plan_args(entry["plan"]), "--patient", PATIENT, "--operator",
                        "dr_verdi", "--duration", "30")
    assert run_b.returncode == 0, run_b.stderr[-2000:]
    assert run_b.stdout.rstrip().splitlines()[-1] == "Session archived.", run_b.stdout[-2000:]

    # the archive holds both sessions, each the plan's exercise with the plan's values, from its own station
    with open_archive(url=clinic.db.url(APP), password_file=clinic.db.password_file(APP), station="check") as a:
        sessions = sorted(a.list_sessions(PATIENT), key=lambda s: s.start)
        assert [(s.station, s.operator) for s in sessions] == [("room-A", "dr_rossi"), ("room-B", "dr_verdi")]
        for s in sessions:
            (run,) = a.runs(s.uuid)
            values = {p["name"]: p["value"] for p in run.parameters}
            assert (run.program["ident"], run.source, run.end_reason) == (EXERCISE, "headless", "finished")
            assert {k: values[k] for k in PLAN_PARAMS} == PLAN_PARAMS
    for name in ("room-A", "room-B"):  # each station's own folder holds its own session only, archived
        (folder,) = (clinic.home(name) / "sessions" / PATIENT).iterdir()
        assert (folder / ".archived").is_file()

    # --progress on either station (the two at once): both sessions, each naming its station
    stations = ("room-A", "room-B")
    reports = clinic.run(*[clinic.main_args(n, "--progress", PATIENT, "--out", str(tmp_path / f"progress-{n}.pdf"))
                           for n in stations])
    for name, done in zip(stations, reports, strict=True):
        assert done.returncode == 0, (name, done.stderr[-2000:])
        text = pdf_text(tmp_path / f"progress-{name}.pdf")
        assert "Sessions 2 (" in text and "Maria Esposito" in text, (name, text[:1200])
        assert "Station" in text, (name, text[:1200])
        # the Sessions table's rows: "1 <date> room-A Temperature follow … complete", then B's, each once
        rows = [line.split() for line in text.splitlines() if TITLE in line and line.endswith("complete")]
        assert [(r[0], r[3]) for r in rows] == [("1", "room-A"), ("2", "room-B")], (name, text[:2000])
