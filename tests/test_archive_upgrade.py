"""The embedded archive's upgrade in place (issue #39): an SQLite archive made by an older schema revision is
migrated by ``linarmpp archive upgrade`` (Alembic, batch mode on SQLite) keeping every row of every table, after a
copy of the file as it was; a migration that would leave a row referring to nothing changes nothing.

``tests/data/archive_oldest.sql.gz`` is an archive made by the oldest revision (0001) with data in every table
(two patients, one with three saves and an electrode choice; a short session with an emergency stop, its restart
and a refused run; an interrupted session), kept as SQLite's text dump (gzip: 45 kB instead of 0.5 MB). It must
never be remade by a newer version: it stands for the archives clinics already have (written by
``python -m tests.test_archive_upgrade`` at revision 0001).

A batch migration copies a table, drops it and renames the copy; the archive's foreign keys (on in every
connection) made SQLite refuse to drop a table that others refer to. Today's chain has one revision, so the
mechanism is also rehearsed with a revision that rebuilds every table in batch mode (a copy of the shipped
migrations plus that one, on a real SQLite file)."""

from __future__ import annotations

import gzip
import shutil
import sqlite3
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from app.archive import schema
from app.archive.api import NeedsUpgrade
from app.archive.store import open_archive

OLDEST_DUMP = Path(__file__).resolve().parent / "data" / "archive_oldest.sql.gz"
OLDEST = "0001"


def load_dump(dump: Path, db: Path) -> None:
    db.parent.mkdir(parents=True, exist_ok=True)
    with sqlite3.connect(db) as con:
        con.executescript(gzip.decompress(dump.read_bytes()).decode())
    db.chmod(0o600)


def every_row(db: Path) -> dict[str, list[dict[str, Any]]]:
    """Every row of every table (the schema version's aside), by column name, sorted."""
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
        con.row_factory = sqlite3.Row
        tables = [t for (t,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE "
                                            "'sqlite_%' AND name != 'alembic_version'")]
        out = {}
        for t in tables:
            rows = [dict(r) for r in con.execute(f'SELECT * FROM "{t}"')]
            out[t] = sorted(rows, key=lambda r: repr(sorted(r.items())))
    return out


def revision_of(db: Path) -> str:
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
        return str(con.execute("SELECT version_num FROM alembic_version").fetchone()[0])


def assert_every_row_kept(before: dict[str, list[dict[str, Any]]], after: dict[str, list[dict[str, Any]]]) -> None:
    """Every table of ``before`` is in ``after`` with the same rows, each with the same values in the columns it
    had (a column a migration added is not compared)."""
    assert set(before) <= set(after), set(before) - set(after)
    for table, rows in before.items():
        columns = set(rows[0]) if rows else set()
        kept = sorted(({k: r[k] for k in columns} for r in after[table]), key=lambda r: repr(sorted(r.items())))
        assert len(kept) == len(rows), f"{table}: {len(rows)} rows before, {len(kept)} after"
        for old, new in zip(rows, kept, strict=True):
            assert old == new, f"{table}: {old} became {new}"


def upgrade_command(data: Path, monkeypatch: Any, capsys: Any) -> tuple[int, str, str]:
    from app.cli import main

    monkeypatch.setenv("LINARMPP_HOME", str(data))
    code = main(["archive", "upgrade"])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def oldest_archive(tmp_path: Path) -> Iterator[Path]:
    """``<data>/archive.sqlite3`` (the embedded default) as the oldest revision left it."""
    db = tmp_path / "data" / "archive.sqlite3"
    load_dump(OLDEST_DUMP, db)
    assert revision_of(db) == OLDEST
    yield db


def test_every_table_of_the_oldest_archive_holds_rows(oldest_archive: Path) -> None:
    """The fixture checks something: no table of the oldest schema is empty."""
    rows = every_row(oldest_archive)
    assert sorted(rows) == sorted(schema_tables_at(OLDEST))
    assert all(rows.values()), [t for t, r in rows.items() if not r]


def schema_tables_at(revision: str) -> list[str]:
    with sqlite3.connect(":memory:") as con:
        from sqlalchemy import create_engine

        engine = create_engine("sqlite://", creator=lambda: con)
        schema.upgrade(engine, revision)
        return [t for (t,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name != "
                                          "'alembic_version'")]


def test_the_oldest_embedded_archive_is_upgraded_in_place_keeping_every_row(
        oldest_archive: Path, monkeypatch: Any, capsys: Any) -> None:
    from app.cli import main

    before = every_row(oldest_archive)
    head = schema.head_revision()
    if head != OLDEST:  # an older archive is refused until upgraded, in one sentence naming the command
        with pytest.raises(NeedsUpgrade, match="linarmpp archive upgrade"):
            open_archive(url=f"sqlite:///{oldest_archive}", station="room-A")
    code, out, err = upgrade_command(oldest_archive.parent, monkeypatch, capsys)
    assert code == 0, err
    assert (f"archive schema {OLDEST} -> {head}" if head != OLDEST else "already up to date") in out, out
    assert revision_of(oldest_archive) == head
    assert_every_row_kept(before, every_row(oldest_archive))
    assert main(["archive", "verify"]) == 0, capsys.readouterr().err  # every file and chain re-hashed
    with open_archive(url=f"sqlite:///{oldest_archive}", station="room-A") as archive:
        record = archive.get_patient("PZ-017")
        assert record.version == 3 and record.profile.fes.caps[1].max_current_ma == 15.0
        assert sorted(record.profile.fes.electrodes) == ["anterior deltoid", "triceps"]
        assert archive.count_sessions() == 2


def test_a_batch_migration_of_every_table_keeps_every_row_and_copies_the_file_first(
        oldest_archive: Path, tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    """The rehearsal: a revision rebuilding every table in batch mode (copy, drop, rename). Before the fix the
    archive's foreign keys refused it: ``FOREIGN KEY constraint failed [SQL: DROP TABLE blobs]``."""
    from app.cli import main

    rehearse(tmp_path, monkeypatch, """
    for table in sorted(Base.metadata.tables):
        with op.batch_alter_table(table, recreate="always") as batch:
            batch.add_column(sa.Column("rehearsal", sa.Text(), nullable=True))
""")
    before = every_row(oldest_archive)
    code, out, err = upgrade_command(oldest_archive.parent, monkeypatch, capsys)
    assert code == 0, err
    assert "archive schema 0001 -> 0002" in out, out
    assert revision_of(oldest_archive) == "0002"
    after = every_row(oldest_archive)
    assert all("rehearsal" in rows[0] for rows in after.values()), "not every table was rebuilt"
    assert_every_row_kept(before, after)
    # the file as it was, kept beside it (private), said by the command
    copies = list(oldest_archive.parent.glob("archive.before-upgrade-0001-*.sqlite3"))
    assert len(copies) == 1 and f"kept in {copies[0]}" in out, out
    assert copies[0].stat().st_mode & 0o077 == 0
    assert revision_of(copies[0]) == OLDEST and every_row(copies[0]) == before
    # the foreign keys are on again for the archive's connections, and every chain and file still matches
    with open_archive(url=f"sqlite:///{oldest_archive}", station="room-A") as archive:
        with archive.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    assert main(["archive", "verify"]) == 0, capsys.readouterr().err


def test_a_migration_leaving_rows_that_refer_to_nothing_changes_nothing(
        oldest_archive: Path, tmp_path: Path, monkeypatch: Any, capsys: Any) -> None:
    rehearse(tmp_path, monkeypatch, """
    with op.batch_alter_table("sessions", recreate="always") as batch:
        batch.add_column(sa.Column("rehearsal", sa.Text(), nullable=True))
    op.execute("DELETE FROM blobs")
""")
    before = every_row(oldest_archive)
    code, _out, err = upgrade_command(oldest_archive.parent, monkeypatch, capsys)
    assert code == 1
    assert err.count("\n") == 1 and "was not upgraded" in err and "nothing was changed" in err, err
    assert revision_of(oldest_archive) == OLDEST
    assert every_row(oldest_archive) == before


def rehearse(tmp_path: Path, monkeypatch: Any, body: str) -> None:
    """The shipped migrations plus revision 0002 running ``body``, used by the archive code for this test."""
    migrations = tmp_path / "migrations"
    shutil.copytree(schema.MIGRATIONS, migrations, ignore=shutil.ignore_patterns("__pycache__"))
    (migrations / "versions" / "0002_rehearsal.py").write_text(
        '"""A rehearsal revision (tests/test_archive_upgrade.py)."""\n'
        "import sqlalchemy as sa\nfrom alembic import op\n\nfrom app.archive.models import Base\n\n"
        'revision = "0002"\ndown_revision = "0001"\nbranch_labels = None\ndepends_on = None\n\n\n'
        "def upgrade() -> None:\n" + body)
    monkeypatch.setattr(schema, "MIGRATIONS", migrations)


# ---------------------------------------------------------------------------------------------- the fixture
def write_oldest_dump(out: Path) -> None:
    """Make ``tests/data/archive_oldest.sql.gz`` with this checkout's archive code (run it only at revision 0001)."""
    import tempfile

    from app.therapy.patients import ElectrodeChoice
    from tests.archive_data import full_profile
    from tests.run_sessions import RunSpec, clinic_day_runs, write_run_session

    assert schema.head_revision() == OLDEST, "the oldest archive is made by the oldest revision only"
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        db = base / "archive.sqlite3"
        with open_archive(url=f"sqlite:///{db}", station="room-A") as archive:
            profile = full_profile("PZ-017")
            v1 = archive.save_patient(profile, expected_version=None, operator="dr_rossi")
            caps = dict(profile.fes.caps)
            caps[1] = replace(caps[1], max_current_ma=15.0)
            v2 = archive.save_patient(replace(profile, fes=replace(profile.fes, caps=caps)),
                                      expected_version=v1.version, operator="dr_verdi", fields=["fes.caps"])
            archive.choose_electrodes("PZ-017", "triceps", ElectrodeChoice(channel=3, electrodes="5-6",
                                                                           chosen_by="dr_verdi"),
                                      expected_version=v2.version, operator="dr_verdi")
            archive.save_patient(replace(full_profile("PZ-018"), full_name="Luca Bianchi"), expected_version=None,
                                 operator="dr_rossi")
            # a short clinic day (an emergency stop, its restart, a refused run: every kind of journal row, small
            # files) and an interrupted session
            stopped, restart, _script, refused = clinic_day_runs()
            day = write_run_session(base / "sessions" / "PZ-017" / "20260302-100000",
                                    [replace(stopped, reps=1, failed=(1,)), replace(restart, reps=1), refused],
                                    start_iso="2026-03-02T10:00:00+01:00")
            cut = write_run_session(base / "sessions" / "PZ-017" / "20260305-100000",
                                    [RunSpec("Trigger reaching (grip-triggered passive movements)",
                                             "trigger_reaching", reps=1)],
                                    start_iso="2026-03-05T10:00:00+01:00", complete=False)
            for folder in (day, cut):
                archive.upload_session(folder)
        with sqlite3.connect(db) as con:
            text = "".join(line + "\n" for line in con.iterdump())
        out.write_bytes(gzip.compress(text.encode(), mtime=0))


if __name__ == "__main__":
    write_oldest_dump(Path(sys.argv[1]) if len(sys.argv) > 1 else OLDEST_DUMP)
