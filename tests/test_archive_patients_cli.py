"""``linarmpp archive patients`` and ``linarmpp archive patient add`` (issue #39): a patient made and listed from the
command line, on the embedded SQLite archive (nothing configured) and on the real PostgreSQL server of
tests/postgres.py (the fixture of tests/test_archive_postgres.py: one server per worker), with the Patients form's
fields, checks and save (app.archive.patient_form); a refused patient writes nothing, a duplicate id names who has
it."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from app.archive.store import SqlArchive, open_archive
from app.cli import main
from tests.postgres import APP, PostgresServer
from tests.run_sessions import RunSpec, write_run_session
from tests.test_archive_postgres import pg_server  # noqa: F401  (the session's server, shared with that file)

PZ = "PZ-301"
# Every field the Patients form edits, as the command takes it.
EVERY_FIELD = ["--name", "Maria Esposito", "--birth-date", "1956-04-23", "--record-number", "0123",
               "--side", "left", "--k-r", "0.7", "--k-f", "0.3", "--fes-profile", "reach_biceps_triceps.yaml",
               "--score", "fugl_meyer_ue=31", "--score", "modified_ashworth=1.5",
               "--score", "action_research_arm_test=20", "--score", "box_and_block=12",
               "--score", "assessed_on=2025-03-01",
               "--robot", "position_min_m=0.05", "--robot", "position_max_m=0.4", "--robot", "max_velocity_m_s=0.2",
               "--robot", "max_acceleration_m_s2=1.0", "--robot", "max_interaction_force_n=40",
               "--robot", "max_stiffness_n_m=800", "--robot", "max_delta_m=0.02",
               "--cap", "1:max_current_ma=15", "--cap", "1:max_pulse_width_us=250", "--cap", "1:max_rms_current_ma=6",
               "--cap", "5:max_current_ma=20", "--notes", "Shoulder pain above 0.4 m.", "--operator", "dr_rossi"]
# The site's limits (the tests' configuration): a patient may only narrow them.
SAFETY = "safety: {robot: {max_velocity_m_s: 0.3}}\n"


@dataclass
class Stations:
    """Two stations of one archive: room-A's and room-B's configuration files and data folders."""

    base: Path
    engine: str
    url: str
    password_file: str

    def config(self, name: str) -> str:
        return str(self.base / f"{name}.yaml")

    def archive(self) -> SqlArchive:
        return open_archive(url=self.url, password_file=self.password_file, station="check")


@pytest.fixture(params=["sqlite", "postgresql"])
def stations(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Stations]:
    home = tmp_path / "room-A"
    monkeypatch.setenv("LINARMPP_HOME", str(home))
    if request.param == "sqlite":  # room-A: nothing configured (the archive in its data folder); room-B: that file
        url, password_file = f"sqlite:///{home / 'archive.sqlite3'}", ""
        archive_a = ""
    else:
        server: PostgresServer = request.getfixturevalue("pg_server")
        db = server.new_database()
        url, password_file = db.url(APP), db.password_file(APP)
        archive_a = f"archive: {{url: '{url}', password_file: '{password_file}'}}\n"
    (tmp_path / "room-A.yaml").write_text(f"{archive_a}station: room-A\n{SAFETY}", encoding="utf-8")
    pw = f", password_file: '{password_file}'" if password_file else ""
    (tmp_path / "room-B.yaml").write_text(f"archive: {{url: '{url}'{pw}}}\nstation: room-B\n{SAFETY}",
                                          encoding="utf-8")
    yield Stations(tmp_path, request.param, url, password_file)


def cli(capsys: pytest.CaptureFixture[str], station: Stations, name: str, *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["archive", "--config", station.config(name), *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_a_patient_added_on_one_station_is_listed_on_the_other_with_its_station_and_sessions(
        stations: Stations, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, out, err = cli(capsys, stations, "room-A", "patient", "add", PZ, *EVERY_FIELD)
    assert code == 0, err
    assert out.startswith(f"Patient {PZ} added to the archive at ") and "by dr_rossi on station room-A" in out
    with stations.archive() as a:
        record = a.get_patient(PZ)
        p = record.profile
        assert (record.version, record.changed_by, record.changed_station) == (1, "dr_rossi", "room-A")
        assert (p.full_name, p.birth_date, p.record_number, p.affected_side) == (
            "Maria Esposito", "1956-04-23", "0123", "left")  # "0123" stays text, as in the form
        assert (p.assistance.k_r, p.assistance.k_f, p.fes.profile) == (0.7, 0.3, "reach_biceps_triceps.yaml")
        s = p.scores
        assert (s.fugl_meyer_ue, s.modified_ashworth, s.action_research_arm_test, s.box_and_block,
                s.assessed_on) == (31, 1.5, 20, 12, "2025-03-01")
        r = p.robot
        assert (r.position_min_m, r.position_max_m, r.max_velocity_m_s, r.max_acceleration_m_s2,
                r.max_interaction_force_n, r.max_stiffness_n_m, r.max_delta_m) == (0.05, 0.4, 0.2, 1.0, 40, 800, 0.02)
        caps = {ch: (c.max_current_ma, c.max_pulse_width_us, c.max_rms_current_ma) for ch, c in p.fes.caps.items()}
        assert caps == {1: (15.0, 250.0, 6.0), 5: (20.0, 300.0, None)}
        assert p.notes == "Shoulder pain above 0.4 m." and p.therapy_plan == [] and p.fes.electrodes == {}
        assert [(h.version, h.reason, h.changed_station) for h in a.patient_history(PZ)] == [(1, "save", "room-A")]
        folder = write_run_session(tmp_path / "sessions" / PZ / "20260302-100000", [RunSpec("Trigger reaching",
                                                                                          "trigger_reaching", reps=2)])
        assert a.upload_session(folder).outcome == "uploaded"

    code, out, err = cli(capsys, stations, "room-B", "patients")  # the other station's table
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].split() == ["ID", "Name", "Last", "changed", "on", "Sessions"]
    assert lines[1].split() == [PZ, "Maria", "Esposito", "room-A", "1"]
    assert lines[-1].startswith("1 patient in the archive at ")
    code, out, err = cli(capsys, stations, "room-B", "patients", "--json")
    assert code == 0, err
    (item,) = json.loads(out)
    assert {k: item[k] for k in ("id", "name", "record_number", "station", "changed_by", "version", "sessions")} == {
        "id": PZ, "name": "Maria Esposito", "record_number": "0123", "station": "room-A", "changed_by": "dr_rossi",
        "version": 1, "sessions": 1}
    assert item["last_session"].startswith("2026-03-01T10:00:00")
    code, out, _ = cli(capsys, stations, "room-B", "patients", "--json", "--search", "nobody")
    assert (code, json.loads(out)) == (0, [])


def ledger_rows(stations: Stations) -> int:
    with stations.archive() as a, a.engine.connect() as conn:
        return int(conn.exec_driver_sql("SELECT count(*) FROM ledger").scalar() or 0)


def test_a_duplicate_id_is_refused_naming_who_has_it_and_nothing_is_written(
        stations: Stations, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(capsys, stations, "room-A", "patient", "add", PZ, "--name", "Maria Esposito",
               "--operator", "dr_rossi")[0] == 0
    before = ledger_rows(stations)
    code, out, err = cli(capsys, stations, "room-B", "patient", "add", PZ, "--name", "Someone Else",
                         "--operator", "dr_verdi")
    assert (code, out) == (1, "")
    assert err.count("\n") == 1 and err.startswith(f"Patient not added: {PZ} is already in the archive at ")
    assert "Maria Esposito, last changed by dr_rossi on station room-A at " in err
    with stations.archive() as a:
        record = a.get_patient(PZ)
        assert (record.version, record.profile.full_name, len(a.patient_history(PZ))) == (1, "Maria Esposito", 1)
    assert ledger_rows(stations) == before


@pytest.mark.parametrize(("args", "words"), [
    (["PZ 302"], "patient_id 'PZ 302' may hold only letters, digits, '-' and '_' (at most 64, starting with a "
                 "letter or digit) (ID)."),
    ([PZ, "--birth-date", "1956-13-01"], "birth_date '1956-13-01' is not a date: write it as YYYY-MM-DD, e.g. "
                                         "1956-04-23 (--birth-date)."),
    ([PZ, "--k-r", "2"], "2.0 is outside the allowed range 0 .. 1 (--k-r)."),
    ([PZ, "--side", "up"], "expected one of 'left', 'right', 'both', 'unknown', got 'up' (--side)."),
    ([PZ, "--score", "fugl_meyer_ue=abc"], "expected a whole number, got 'abc' (--score fugl_meyer_ue)."),
    ([PZ, "--cap", "9:max_current_ma=10"], "caps: channel 9 does not exist; the stimulator has channels 1..8 (--cap)."),
    # the site's limit (0.3 m/s) is narrower than the schema's range: the configuration is the envelope
    ([PZ, "--robot", "max_velocity_m_s=0.5"], "0.5 exceeds the configured limit 0.3; a patient limit may only be "
                                              "tighter (--robot max_velocity_m_s)."),
])
def test_a_refused_patient_is_one_sentence_and_nothing_is_made(
        args: list[str], words: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    home = tmp_path / "home"
    monkeypatch.setenv("LINARMPP_HOME", str(home))
    config = tmp_path / "station.yaml"
    config.write_text(f"station: room-A\n{SAFETY}", encoding="utf-8")
    assert main(["archive", "--config", str(config), "patient", "add", *args]) == 1
    out, err = capsys.readouterr()
    assert (out, err) == ("", f"Patient not added: {words}\n")
    assert not (home / "archive.sqlite3").exists()  # checked before the archive is opened: nothing made


def test_a_malformed_option_is_a_usage_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    assert main(["archive", "patient", "add", PZ, "--cap", "1=15"]) == 2
    assert capsys.readouterr().err == ("Patient not added: --cap '1=15' is not CH:KEY=VALUE (e.g. --cap "
                                       "1:max_current_ma=15).\n")
    assert main(["archive", "patient", "add"]) == 2  # no ID: argparse's usage
    assert not (tmp_path / "home" / "archive.sqlite3").exists()


def test_the_command_makes_the_profile_the_patients_form_makes(qtbot, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """The same texts typed in the Patients form's New patient and given to the command: the same profile."""
    from PySide6.QtWidgets import QTableWidgetItem

    from app.core.config import load_config
    from app.ui.patient_dialog import PatientDialog

    home = tmp_path / "home"
    monkeypatch.setenv("LINARMPP_HOME", str(home))
    config = tmp_path / "station.yaml"
    config.write_text(f"station: room-A\n{SAFETY}", encoding="utf-8")
    assert main(["archive", "--config", str(config), "patient", "add", PZ, *EVERY_FIELD]) == 0, capsys.readouterr()
    with open_archive(url=f"sqlite:///{home / 'archive.sqlite3'}") as a:
        by_command = a.get_patient(PZ).profile
        form = PatientDialog(None, load_config(config).safety, archive=a, operator="dr_rossi")
        qtbot.addWidget(form)
        values = dict(zip(EVERY_FIELD[0::2], EVERY_FIELD[1::2], strict=True))
        form.id_edit.setText("PZ-302")
        form.name_edit.setText(values["--name"])
        form.birth_edit.setText(values["--birth-date"])
        form.record_edit.setText(values["--record-number"])
        form.side_box.setCurrentIndex(form.side_box.findData("left"))
        form.k_r.setText("0.7")
        form.k_f.setText("0.3")
        form.fes_profile.setText(values["--fes-profile"])
        pairs = [EVERY_FIELD[k + 1] for k in range(0, len(EVERY_FIELD), 2)]
        for option, value in zip(EVERY_FIELD[0::2], pairs, strict=True):
            if option in ("--score", "--robot"):
                key, _, text = value.partition("=")
                form.fields[f"{'scores' if option == '--score' else 'robot'}.{key}"].setText(text)  # type: ignore
        columns = ["max_current_ma", "max_pulse_width_us", "max_rms_current_ma"]
        for option, value in zip(EVERY_FIELD[0::2], pairs, strict=True):
            if option == "--cap":
                ch, _, rest = value.partition(":")
                key, _, text = rest.partition("=")
                form.caps_table.setItem(int(ch) - 1, columns.index(key), QTableWidgetItem(text))
        form.notes.setPlainText(values["--notes"])
        form.accept()
        assert form.result() == form.DialogCode.Accepted, form.error_label.text()
        by_form = a.get_patient("PZ-302")
    from dataclasses import replace

    assert by_form.changed_by == "dr_rossi"
    assert replace(by_form.profile, patient_id=PZ, created="", updated="") == replace(by_command, created="",
                                                                                      updated="")


def test_an_unreachable_archive_is_one_sentence(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("LINARMPP_HOME", str(tmp_path / "home"))
    config = tmp_path / "station.yaml"  # nobody listens on port 9 of loopback
    config.write_text("archive: {url: 'postgresql+psycopg://nobody@127.0.0.1:9/none'}\nstation: room-A\n",
                      encoding="utf-8")
    assert main(["archive", "--config", str(config), "patients"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("The archive at postgresql+psycopg://nobody@127.0.0.1:9/none cannot be reached (")
    assert err.count("\n") == 1
    assert not (tmp_path / "home" / "archive.sqlite3").exists()  # nothing made in the data folder either
