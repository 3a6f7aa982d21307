"""Everything reads the archive (issue #39): ``--progress`` of a patient treated on two stations that share one
archive lists both stations' sessions (the archive's, plus the station's own not yet archived, never one twice);
``--metrics`` and ``--report`` take an archived session's UUID as well as a folder, with identical results.

Two stations are two data folders (``LINARMPP_HOME``) with their own ``station:`` names and one archive: an SQLite
file, and the real PostgreSQL server of tests/postgres.py (never a mock)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from app.archive.outbox import Outbox
from app.archive.store import open_archive
from app.therapy.patients import PatientProfile
from tests.pdf_layout import pdf_text
from tests.postgres import APP, PostgresServer, server_or_skip
from tests.run_sessions import RunSpec, write_run_session

PATIENT = "PZ-039"
TRIGGER = "Trigger reaching (grip-triggered passive movements)"


@dataclass
class Clinic:
    """Two stations (room-A, room-B) of one archive: each its own data folder and configuration file."""

    base: Path
    url: str
    password_file: str = ""

    def home(self, name: str) -> Path:
        return self.base / name

    def config(self, name: str) -> Path:
        path = self.base / f"{name}.yaml"
        if not path.exists():
            self.base.mkdir(parents=True, exist_ok=True)
            pw = f", password_file: {self.password_file}" if self.password_file else ""
            path.write_text(f"archive: {{url: '{self.url}'{pw}}}\nstation: {name}\n")
        return path

    def archive(self, name: str) -> Any:
        return open_archive(url=self.url, station=name, password_file=self.password_file)

    def session(self, name: str, stamp: str, reps: int) -> Path:
        day = f"{stamp[:4]}-{stamp[4:6]}-{stamp[6:8]}T{stamp[9:11]}:{stamp[11:13]}:00+01:00"
        return write_run_session(self.home(name) / "sessions" / PATIENT / stamp, [RunSpec(TRIGGER, "trigger_reaching",
                                                                                           reps=reps)],
                                 start_iso=day)

    def outbox_pass(self, name: str) -> int:
        """The station's outbox, as at a session's end: what waits is archived (and marked)."""
        status = Outbox(self.home(name) / "sessions", lambda: self.archive(name)).run_once(force=True)
        assert status.waiting == 0, status.text()
        return status.uploaded


def make_two_stations(clinic: Clinic) -> None:
    """Monday on room-A (3 repetitions), Wednesday on room-B (4), both archived; Friday on room-B (2) still in B's
    outbox. The patient was created on room-A."""
    with clinic.archive("room-A") as a:
        a.save_patient(PatientProfile(patient_id=PATIENT, full_name="Maria Esposito"), expected_version=None,
                       operator="dr_rossi")
    clinic.session("room-A", "20260302-100000", 3)
    assert clinic.outbox_pass("room-A") == 1
    clinic.session("room-B", "20260304-100000", 4)
    assert clinic.outbox_pass("room-B") == 1
    clinic.session("room-B", "20260306-100000", 2)  # made after B's last pass: waiting for the archive


def progress_of(clinic: Clinic, name: str, monkeypatch: Any, tmp_path: Path) -> tuple[int, list[Any], str]:
    """``--progress`` as run on station ``name``: (exit code, the rows the report was built from, its text)."""
    import app.session.reports
    from app.cli import main

    built: list[Any] = []
    real = app.session.reports.save_progress_report

    def spy(patient_id: str, out: Any, rows: Any, profile: Any = None) -> int:
        built[:] = list(rows)
        return real(patient_id, out, rows, profile)

    monkeypatch.setattr(app.session.reports, "save_progress_report", spy)
    monkeypatch.setenv("LINARMPP_HOME", str(clinic.home(name)))
    out = tmp_path / f"progress-{name}.pdf"
    code = main(["--config", str(clinic.config(name)), "--progress", PATIENT, "--out", str(out)])
    text = pdf_text(out) if out.exists() else ""
    return code, built, text


def check_both_stations(clinic: Clinic, monkeypatch: Any, tmp_path: Path) -> None:
    make_two_stations(clinic)
    expected = {"room-A": (["2026-03-02", "2026-03-04"], 7),  # the archive's two
                "room-B": (["2026-03-02", "2026-03-04", "2026-03-06"], 9)}  # + B's own waiting one, once
    for name, (days, reps) in expected.items():
        code, rows, text = progress_of(clinic, name, monkeypatch, tmp_path)
        assert code == 0, name
        assert [r.started[:10] for r in rows] == days, name
        assert sum(int(r.summary.get("repetitions") or 0) for r in rows) == reps, name
        assert [r.exercises for r in rows] == [("Trigger reaching (grip-triggered passive movements)",)] * len(days)
        assert f"Sessions {len(days)} (2026-03-02 10:00" in text, text[:600]
        assert f"Repetitions {reps}" in text and "Maria Esposito" in text, text[:600]
        # each session names the station that recorded it; B's own unarchived one says it waits
        assert [r.station for r in rows] == ["room-A", "room-B"] + (["room-B (not archived yet)"] if name == "room-B"
                                                                    else []), name
        assert "Station" in text and "room-A" in text and "room-B" in text, text[:1200]


# ---------------------------------------------------------------------------------------------- --progress
def test_progress_on_either_station_of_one_sqlite_archive_lists_both_stations_sessions(
        tmp_path: Path, monkeypatch: Any) -> None:
    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    check_both_stations(clinic, monkeypatch, tmp_path)


@pytest.fixture(scope="module")
def pg_server() -> Iterator[PostgresServer]:
    with server_or_skip() as server:
        yield server


def test_progress_on_either_station_of_one_postgres_archive_lists_both_stations_sessions(
        pg_server: PostgresServer, tmp_path: Path, monkeypatch: Any) -> None:
    db = pg_server.new_database()
    clinic = Clinic(tmp_path / "clinic", db.url(APP), db.password_file(APP))
    check_both_stations(clinic, monkeypatch, tmp_path)


def test_the_progress_rows_built_from_the_archive_are_those_computed_from_the_folders(tmp_path: Path) -> None:
    """A day with an emergency stop, its restart, a Script-tab run and a refused run; a plain session; an interrupted
    one: the rows the archive gives (no stream read) are the folders' rows, field by field."""
    from dataclasses import asdict

    from app.archive.reads import progress_rows as archive_rows
    from app.session.reports import progress_rows
    from tests.archive_data import make_data_folder

    make_data_folder(tmp_path / "data")
    root = tmp_path / "data" / "sessions"
    from_folders = progress_rows("PZ-017", root)
    with open_archive(url=f"sqlite:///{tmp_path / 'archive.sqlite3'}", station="room-A") as archive:
        Outbox(root, lambda: open_archive(url=archive.url, station="room-A")).run_once(force=True)
        from_archive = archive_rows("PZ-017", tmp_path / "elsewhere", archive)  # no local folder: the archive alone
    assert len(from_folders) == len(from_archive) == 3
    assert [r.station for r in from_archive] == ["room-A"] * 3 and all(r.uuid for r in from_archive)
    for a, f in zip(from_archive, from_folders, strict=True):
        assert a.folder.name == f.folder.name and a.interrupted == f.interrupted
        a_fields, f_fields = asdict(a), asdict(f)
        for key in ("folder", "uuid", "station"):
            a_fields.pop(key), f_fields.pop(key)
        assert json.loads(json.dumps(a_fields)) == json.loads(json.dumps(f_fields))


# ---------------------------------------------------------------------------------------------- --metrics, --report
def test_metrics_and_report_of_an_archived_session_by_its_uuid_are_those_of_its_folder(
        tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """Station room-B holds no folder of room-A's session: ``--metrics UUID`` and ``--report UUID`` read the
    archive's copy, and give what the folder gives on room-A (the JSON equal, the PDF's text equal but for the
    time it was printed)."""
    import re

    from app.archive import folders
    from app.archive.station import import_yaml_patients
    from app.archive.store import ArchivedFiles
    from app.cli import main
    from tests.archive_data import make_data_folder

    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    folder = make_data_folder(clinic.home("room-A"))["monday"]  # runs stopped, restarted, refused
    assert clinic.outbox_pass("room-A") == 4
    with clinic.archive("room-A") as a:
        assert import_yaml_patients(a, clinic.home("room-A") / "patients")[0] == ["PZ-017", "PZ-018"]
    uuid = folders.session_uuid(folder)
    written: list[Path] = []
    real = ArchivedFiles.materialise
    monkeypatch.setattr(ArchivedFiles, "materialise", lambda self, f: written.append(real(self, f)) or written[-1])

    def run(station: str, *args: str) -> tuple[int, str, str]:
        monkeypatch.setenv("LINARMPP_HOME", str(clinic.home(station)))
        code = main(["--config", str(clinic.config(station)), *args])
        out, err = capsys.readouterr()
        return code, out, err

    code, by_folder, _ = run("room-A", "--metrics", str(folder))
    assert code == 0
    code, by_uuid, _ = run("room-B", "--metrics", uuid)
    assert code == 0 and json.loads(by_uuid) == json.loads(by_folder)
    assert len(json.loads(by_uuid)["repetitions"]) == 7
    texts = []
    for station, given in (("room-A", str(folder)), ("room-B", uuid)):
        out = tmp_path / f"report-{station}.pdf"
        code, _, err = run(station, "--report", given, "--out", str(out))
        assert code == 0 and "Session report written" in err, err
        texts.append(re.sub(r"printed \d{4}-\d\d-\d\d \d\d:\d\d \S*", "printed", pdf_text(out)))
    # the technical appendix says where the session was read from: its folder, or the archive (never a temporary
    # folder that no longer exists)
    where = [re.search(r"Session (folder )?(/|archived).*?(?=Printed by)", t, re.S) for t in texts]
    assert where[0] and where[1] and f"archived session {uuid} (recorded on station room-A as PZ-017/" \
        "20260302-100000" in where[1].group(0).replace("\n", " ")
    texts = [t.replace(w.group(0), "") for t, w in zip(texts, where, strict=True)]
    assert texts[0] == texts[1] and "Maria Rossi" in texts[1]
    assert len(written) == 2 and not any(p.exists() for p in written)  # the archive's copies, removed after
    code, _, err = run("room-B", "--metrics", "6a1c7f0e-0000-4000-8000-000000000000")
    assert code == 2 and "the archive has no session 6a1c7f0e-0000-4000-8000-000000000000" in err


# ---------------------------------------------------------------------------------------------- headless
def test_a_headless_run_for_a_patient_and_an_operator_is_their_session_and_is_archived(
        tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """``--headless --script FILE --patient ID --operator NAME``: the session is the patient's (recorded with the
    station's sessions, the operator named), archived at the end (last line); a patient the archive does not know,
    or a patient without an operator, is refused in one line and nothing starts."""
    from app.cli import main
    from app.devices import registry
    from app.scripting import headless
    from tests.fakes import counter_factory

    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{tmp_path / 'clinic' / 'archive.sqlite3'}")
    with clinic.archive("room-A") as a:
        a.save_patient(PatientProfile(patient_id=PATIENT, full_name="Maria Esposito"), expected_version=None,
                       operator="dr_rossi")
    monkeypatch.setenv("LINARMPP_HOME", str(clinic.home("room-B")))
    monkeypatch.setattr(registry, "default_factories", lambda config: {"counter": counter_factory(tmp_path)})
    monkeypatch.setattr(headless, "_let_the_record_show_the_safe_state", lambda manager, app: None)
    script = tmp_path / "s.py"
    script.write_text("x = 1\n", encoding="utf-8")
    run = ["--config", str(clinic.config("room-B")), "--headless", "--script", str(script)]

    assert main([*run, "--patient", "PZ-NOBODY", "--operator", "dr_verdi"]) == 2
    assert "there is no patient PZ-NOBODY in the archive" in capsys.readouterr().err
    assert main([*run, "--patient", PATIENT]) == 2
    assert "--patient and --operator go together" in capsys.readouterr().err
    assert main([*run, "--patient", PATIENT, "--operator", "dr_verdi"]) == 0
    out = capsys.readouterr().out
    assert out.rstrip().splitlines()[-1] == "Session archived.", out
    with clinic.archive("room-A") as a:
        sessions = a.list_sessions(PATIENT)
        assert [(s.station, s.operator) for s in sessions] == [("room-B", "dr_verdi")]
        manifest = a.get_session(sessions[0].uuid).manifest
    assert (manifest["patient"] or {}).get("full_name") == "Maria Esposito"  # the patient's profile was applied
    folders = list((clinic.home("room-B") / "sessions" / PATIENT).iterdir())
    assert len(folders) == 1 and (folders[0] / ".archived").is_file()


def test_progress_with_the_archive_unreachable_is_this_stations_and_says_so(
        tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """The archive's share is not mounted: the report holds this station's sessions, stderr says why, exit 3
    (written, but incomplete)."""
    from app.cli import main

    share = tmp_path / "share"
    share.write_text("not mounted\n", encoding="utf-8")  # a file where the archive's folder should be
    clinic = Clinic(tmp_path / "clinic", f"sqlite:///{share / 'archive.sqlite3'}")
    clinic.session("room-B", "20260304-100000", 4)
    monkeypatch.setenv("LINARMPP_HOME", str(clinic.home("room-B")))
    out = tmp_path / "progress.pdf"
    assert main(["--config", str(clinic.config("room-B")), "--progress", PATIENT, "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "the progress report holds only this station's sessions" in err and "Progress report written" in err, err
    assert "Sessions 1 (2026-03-04 10:00" in pdf_text(out)
