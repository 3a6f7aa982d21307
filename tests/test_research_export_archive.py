"""Everything reads the archive (issues #41 and #39): ``linarmpp export --format bids|xdf|edf SESSION…`` takes an
archived session's UUID as well as a session folder, reads it from the clinic's archive as it streams (never a copy
of the session in a folder first), and writes what the folder's export writes. The archives are real: an SQLite file
(the embedded default in ``<data>``, no configuration) and the PostgreSQL server of tests/postgres.py (``--config``
naming it); nothing of the archive is mocked."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import uuid as _uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.archive import folders
from app.archive.store import ARCHIVE_FILE, ArchivedFiles, SqlArchive, open_archive
from app.research_export.command import main as export_main
from tests.research_export_data import record_session, synth_session

pyxdf = pytest.importorskip("pyxdf")
pyedflib = pytest.importorskip("pyedflib")

FORMATS = ("xdf", "edf", "bids")
UNKNOWN = "6a1c7f0e-0000-4000-8000-000000000000"


@dataclass
class Recorded:
    folder: Path
    uuid: str
    reference: dict[str, Path]  # the folder's export in each format
    notes: dict[str, str]  # what it said on stderr


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Recorded:
    """A session made by the real recorder (device clocks, an e-stop, a grip onset), exported from its folder once."""
    root = tmp_path_factory.mktemp("archived-export")
    mp = pytest.MonkeyPatch()
    try:
        rec = record_session(root / "sessions", monkeypatch=mp)
    finally:
        mp.undo()
    reference, notes = {}, {}
    for fmt in FORMATS:
        reference[fmt] = root / f"folder-{fmt}"
        with contextlib.redirect_stderr(io.StringIO()) as err:
            assert export_main(["--format", fmt, str(rec.folder), "--out", str(reference[fmt]), "--quiet"]) == 0
        notes[fmt] = err.getvalue()
    return Recorded(rec.folder, folders.session_uuid(rec.folder), reference, notes)


@dataclass
class Clinic:
    """An archive holding the recorded session, and how the command names it: ``home`` (LINARMPP_HOME) and the
    ``--config`` arguments (none for the embedded SQLite archive: the default configuration finds it in <data>)."""

    kind: str
    home: Path
    config_args: list[str]
    open: Any  # () -> the archive, as station room-A

    def station(self, archive_uuid: str) -> str:
        with self.open() as archive:
            return str(archive.get_session(archive_uuid).info.station)


@pytest.fixture(scope="module")
def pg_server() -> Iterator[Any]:
    from tests.postgres import server_or_skip

    with server_or_skip() as server:
        yield server


def _clinic(kind: str, base: Path, request: Any) -> Clinic:
    home = base / f"home-{kind}"
    home.mkdir(parents=True)
    if kind == "sqlite":
        url = f"sqlite:///{home / ARCHIVE_FILE}"
        return Clinic(kind, home, [], lambda: open_archive(url=url, station="room-A"))
    from tests.postgres import APP

    db = request.getfixturevalue("pg_server").new_database()
    config = base / "clinic.yaml"
    config.write_text(f"archive: {{url: '{db.url(APP)}', password_file: {db.password_file(APP)}}}\n"
                      "station: room-B\n", encoding="utf-8")
    return Clinic(kind, home, ["--config", str(config)],
                  lambda: open_archive(url=db.url(APP), password_file=db.password_file(APP), station="room-A"))


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def clinic(request, recorded, tmp_path_factory) -> Clinic:
    """The recorded session uploaded to an archive by station room-A (as its outbox does at the session's end)."""
    made = _clinic(request.param, tmp_path_factory.mktemp(f"clinic-{request.param}"), request)
    with made.open() as archive:
        assert archive.upload_session(recorded.folder).outcome == "uploaded"
    return made


@pytest.fixture(scope="module")
def sqlite_clinic(recorded, tmp_path_factory, request) -> Clinic:
    made = _clinic("sqlite", tmp_path_factory.mktemp("clinic-one"), request)
    with made.open() as archive:
        archive.upload_session(recorded.folder)
    return made


@pytest.fixture
def on_station(monkeypatch) -> Any:
    """Run the command as on a station whose data folder is ``clinic.home``; counts the archives opened and closed,
    and fails a copy of an archived session into a folder (the export streams it)."""
    opened: list[SqlArchive] = []
    closed: list[SqlArchive] = []
    real_init, real_close = SqlArchive.__init__, SqlArchive.close

    def init(self, *args: Any, **kwargs: Any) -> None:
        real_init(self, *args, **kwargs)
        opened.append(self)

    def close(self) -> None:
        closed.append(self)
        real_close(self)

    def materialise(self, *args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the export copied the archived session into a folder")

    monkeypatch.setattr(SqlArchive, "__init__", init)
    monkeypatch.setattr(SqlArchive, "close", close)
    monkeypatch.setattr(ArchivedFiles, "materialise", materialise)

    def run(clinic: Clinic, *args: str) -> int:
        monkeypatch.setenv("LINARMPP_HOME", str(clinic.home))
        return export_main([*args, *clinic.config_args, "--quiet"])

    run.opened, run.closed = opened, closed  # type: ignore[attr-defined]
    return run


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _xdf_streams(path: Path) -> dict[str, tuple[np.ndarray, Any]]:
    data, _ = pyxdf.load_xdf(str(path), dejitter_timestamps=False)  # clocks synchronised (pyxdf's default)
    return {s["info"]["name"][0]: (s["time_stamps"], s["time_series"]) for s in data}


def _edf_signals(path: Path) -> dict[str, tuple[str, float, np.ndarray]]:
    reader = pyedflib.EdfReader(str(path))
    try:
        return {reader.getTransducer(i): (reader.getPhysicalDimension(i), reader.getSampleFrequency(i),
                                          reader.readSignal(i)) for i in range(reader.signals_in_file)}
    finally:
        reader.close()


# ---------------------------------------------------------------------------------------------- (1) the same data
def test_an_archived_session_exported_by_its_uuid_is_its_folders_export(clinic, recorded, on_station, tmp_path,
                                                                          capsys) -> None:
    """By UUID, from the archive, in each format: the files the folder's export wrote, byte for byte, and read back
    by the formats' readers the same samples at the same times (XDF after pyxdf's clock synchronisation)."""
    for fmt in FORMATS:
        out = tmp_path / fmt
        code = on_station(clinic, "--format", fmt, recorded.uuid, "--out", str(out))
        captured = capsys.readouterr()
        assert code == 0, captured.err
        assert captured.err == recorded.notes[fmt]  # (EDF's notes on samples its time grid cannot place)
        if fmt == "bids":
            assert [Path(p) for p in captured.out.split()] == [out]
            ours, theirs = _tree(out), _tree(recorded.reference["bids"])
            assert sorted(ours) == sorted(theirs) and len(ours) > 10
            assert {name for name in ours if ours[name] != theirs[name]} == set()
            continue
        (written,) = [Path(p) for p in captured.out.split()]
        (reference,) = recorded.reference[fmt].glob(f"*.{fmt}")
        assert written.name == reference.name  # <patient>_<start>.<fmt>, as from the folder
        if fmt == "xdf":
            ours_x, theirs_x = _xdf_streams(written), _xdf_streams(reference)
            assert sorted(ours_x) == sorted(theirs_x) and len(ours_x) == 10
            for name, (t, values) in theirs_x.items():
                assert np.array_equal(ours_x[name][0], t), name
                if isinstance(values, np.ndarray):
                    assert np.array_equal(ours_x[name][1], values, equal_nan=True), name
                else:  # the events and markers: strings
                    assert ours_x[name][1] == values, name
        else:
            ours_e, theirs_e = _edf_signals(written), _edf_signals(reference)
            assert sorted(ours_e) == sorted(theirs_e) and len(ours_e) > 20
            for name, (unit, rate, signal) in theirs_e.items():
                assert ours_e[name][:2] == (unit, rate), name
                assert np.array_equal(ours_e[name][2], signal), name
        assert written.read_bytes() == reference.read_bytes()
    assert len(on_station.opened) == len(FORMATS) == len(on_station.closed)  # opened for each export, then closed


# ---------------------------------------------------------------------------------------------- (2) one sentence
def test_an_unknown_uuid_an_unreachable_archive_and_a_refused_configuration_are_one_sentence(
        sqlite_clinic, recorded, on_station, tmp_path, capsys) -> None:
    def run(clinic: Clinic, *args: str) -> tuple[int, list[str]]:
        code = on_station(clinic, "--format", "xdf", *args, "--out", str(tmp_path / "out"))
        captured = capsys.readouterr()
        assert captured.out == ""
        return code, captured.err.strip().splitlines()

    # a UUID the archive does not hold: nothing written (exit 1), one line naming it
    code, err = run(sqlite_clinic, UNKNOWN)
    assert code == 1 and err == [f"Nothing was written: {UNKNOWN}: not exported: the archive has no session "
                                 f"{UNKNOWN}"], err
    # the archive cannot be reached (its share is not mounted: a file where its folder should be): exit 1, named
    share = tmp_path / "share"
    share.write_text("not mounted\n", encoding="utf-8")
    config = tmp_path / "unreachable.yaml"
    config.write_text(f"archive: {{url: 'sqlite:///{share / ARCHIVE_FILE}'}}\nstation: room-B\n", encoding="utf-8")
    clinic = Clinic("sqlite", tmp_path / "home", ["--config", str(config)], None)
    code, err = run(clinic, recorded.uuid)
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"Nothing was written: the archive at sqlite:///{share / ARCHIVE_FILE} cannot be "
                             "reached"), err
    # no archive anywhere (nothing configured, none in <data>): exit 1, said; nothing made in <data>
    code, err = run(Clinic("sqlite", tmp_path / "empty-home", [], None), recorded.uuid)
    assert code == 1 and len(err) == 1 and "this station has no archive" in err[0], err
    assert not (tmp_path / "empty-home" / ARCHIVE_FILE).exists()
    # a configuration refused: wrong arguments (exit 2), one line naming the file
    bad = tmp_path / "bad.yaml"
    bad.write_text("archive: {url: 3, colour: blue}\n", encoding="utf-8")
    code, err = run(Clinic("sqlite", sqlite_clinic.home, ["--config", str(bad)], None), recorded.uuid)
    assert code == 2 and len(err) == 1 and str(bad) in err[0] and "nothing was exported" in err[0], err
    assert not (tmp_path / "out").exists()
    # ... and read only when a UUID is named: folders alone are exported whatever it says
    assert on_station(Clinic("sqlite", sqlite_clinic.home, ["--config", str(bad)], None), "--format", "xdf",
                      str(recorded.folder), "--out", str(tmp_path / "out")) == 0
    assert len(list((tmp_path / "out").glob("*.xdf"))) == 1
    assert on_station.opened == on_station.closed  # every archive opened was closed


# ---------------------------------------------------------------------------------------------- (3) mixed
def test_folders_and_uuids_in_one_command(sqlite_clinic, recorded, on_station, tmp_path, capsys) -> None:
    """A folder and an archived session in one BIDS dataset; a folder, a UUID and an unknown UUID as XDF (exit 3,
    the unknown one listed); a session named twice (its folder and its UUID) is exported once; an archived session
    whose recording failed is exported as its folder is, and named as the report command names it."""
    other = synth_session(tmp_path / "local", "PC-002", 5.0, start_iso="2026-03-02T10:00:00+01:00",
                          folder_name="20260302-100000")
    station = sqlite_clinic.station(recorded.uuid)

    assert on_station(sqlite_clinic, "--format", "bids", str(other), recorded.uuid, "--out", str(tmp_path / "ds")) == 0
    capsys.readouterr()
    participants = (tmp_path / "ds" / "participants.tsv").read_text(encoding="utf-8")
    assert "PC-002" in participants and "PZ-017" in participants
    ours, theirs = _tree(tmp_path / "ds" / "sub-PZ017"), _tree(recorded.reference["bids"] / "sub-PZ017")
    assert ours == theirs  # the archived session's files are those of its folder's export

    code = on_station(sqlite_clinic, "--format", "xdf", str(other), recorded.uuid, UNKNOWN, str(recorded.folder),
                      recorded.uuid.upper(), "--out", str(tmp_path / "x"))
    captured = capsys.readouterr()
    assert code == 3, captured.err
    assert sorted(Path(p).name for p in captured.out.split()) == [
        "PC-002_20260302-100000.xdf", next(recorded.reference["xdf"].glob("*.xdf")).name]  # once, named thrice
    assert captured.err.strip().splitlines() == [
        "Written, but incomplete:", f"  - {UNKNOWN}: not exported: the archive has no session {UNKNOWN}"]

    # an archived session whose recording failed (the manifest could not say so: the recorder's sidecar does): the
    # same files and the same account of what is missing as from its folder, named by where it came from
    failed = tmp_path / "failed" / "PZ-017" / "20260301-090000"
    shutil.copytree(recorded.folder, failed)
    manifest = json.loads((failed / "manifest.json").read_text(encoding="utf-8"))
    manifest.update(status="recording", session_uuid=str(_uuid.uuid4()))
    manifest.pop("end", None)
    (failed / "manifest.json").write_text(json.dumps(manifest), encoding="utf-8")
    (failed / "recording-failed.txt").write_text(json.dumps({"error": "No space left on device",
                                                             "t_wall": "2026-03-01T09:00:04+01:00"}))
    with sqlite_clinic.open() as archive:
        archive.upload_session(failed)
    label = (f"archived session {manifest['session_uuid']} (recorded on station {station} as PZ-017/20260301-090000; "
             f"read from the archive at sqlite:///{sqlite_clinic.home / ARCHIVE_FILE})")
    errs = []
    for given, out in ((str(failed), tmp_path / "f-folder"), (manifest["session_uuid"], tmp_path / "f-uuid")):
        assert on_station(sqlite_clinic, "--format", "bids", given, "--out", str(out)) == 3
        errs.append(capsys.readouterr().err)
    assert f"{label}: the recording failed at 2026-03-01T09:00:04+01:00: No space left on device" in errs[1], errs[1]
    assert errs[1] == errs[0].replace(str(failed), label)
    assert _tree(tmp_path / "f-uuid") == _tree(tmp_path / "f-folder")
    assert "\tfailed" in (tmp_path / "f-uuid" / "sub-PZ017" / "sub-PZ017_sessions.tsv").read_text(encoding="utf-8")
    # every archive opened was closed: the three exports', the station's look-up and the upload's
    assert on_station.opened == on_station.closed and len(on_station.opened) == 5


def test_the_archive_is_closed_when_the_export_is_interrupted(sqlite_clinic, recorded, on_station, tmp_path,
                                                             monkeypatch, capsys) -> None:
    import app.research_export.xdf as xdf

    def interrupted(*args: Any, **kwargs: Any) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(xdf, "export_xdf", interrupted)
    assert on_station(sqlite_clinic, "--format", "xdf", recorded.uuid, "--out", str(tmp_path / "x")) == 130
    assert "Export interrupted" in capsys.readouterr().err
    assert len(on_station.opened) == 1 and on_station.closed == on_station.opened


def test_an_archived_file_that_does_not_match_its_hash_is_not_exported(sqlite_clinic, recorded, on_station, tmp_path,
                                                                      capsys) -> None:
    """One byte of a stream changed in the database: the export of that session says so (as ``archive verify``
    would), in one sentence; nothing is written."""
    from sqlalchemy import create_engine, text

    home = tmp_path / "home"
    home.mkdir()
    shutil.copy(sqlite_clinic.home / ARCHIVE_FILE, home / ARCHIVE_FILE)
    engine = create_engine(f"sqlite:///{home / ARCHIVE_FILE}")
    with engine.begin() as conn:
        sha = conn.execute(text("SELECT sha256 FROM session_files WHERE session_uuid = :u AND name = "
                                "'streams/linarm.vsa.csv'"), {"u": recorded.uuid}).scalar()
        data = bytearray(conn.execute(text("SELECT data FROM blob_chunks WHERE sha256 = :s AND seq = 0"),
                                      {"s": sha}).scalar())
        data[1000] ^= 0x01
        conn.execute(text("UPDATE blob_chunks SET data = :d WHERE sha256 = :s AND seq = 0"),
                     {"d": bytes(data), "s": sha})
    engine.dispose()
    for fmt in ("xdf", "bids"):
        code = on_station(Clinic("sqlite", home, [], None), "--format", fmt, recorded.uuid, "--out",
                          str(tmp_path / fmt))
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        assert code == 1 and captured.out == "" and len(err) == 1, captured.err
        assert f"the archived file streams/linarm.vsa.csv of session {recorded.uuid} does not match its SHA-256 " \
               "(the archive's copy was changed or damaged: run `linarmpp archive verify`)" in err[0], err
        assert not (tmp_path / fmt).exists() or not any((tmp_path / fmt).iterdir())
