"""The archive's schema version (Alembic): checked when an archive is opened, migrated on request.

* a new, empty database is created at the newest revision;
* a database at this application's newest revision opens;
* an older one is refused with :class:`NeedsUpgrade` ("linarmpp archive upgrade" migrates it);
* one at a revision this application does not know (made by a newer version) is refused with
  :class:`ArchiveTooNew` and never written to.

The migration scripts ship inside the package (``app/archive/migrations/versions``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine, inspect

from app.archive.api import ArchiveError, ArchiveTooNew, NeedsUpgrade
from app.archive.models import APPEND_ONLY, Base

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


def _config(connection: Connection | None = None) -> Config:
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["connection"] = connection
    return cfg


def scripts() -> ScriptDirectory:
    return ScriptDirectory.from_config(_config())


def head_revision() -> str:
    head = scripts().get_current_head()
    assert head is not None
    return head


def current_revision(connection: Connection) -> str | None:
    return MigrationContext.configure(connection).get_current_revision()


def upgrade(engine: Engine, revision: str = "head",
            before_change: Callable[[str], None] | None = None) -> tuple[str | None, str]:
    """Migrate to ``revision`` in one transaction; returns (before, after). Refuses an archive newer than this
    application. ``before_change(revision)`` is called before an existing archive's schema is changed (the
    embedded archive's copy: store.upgrade_archive); an exception from it changes nothing.

    SQLite: a batch migration copies a table, drops the old one and renames the copy; with the archive's foreign
    keys on, dropping a table others refer to (blobs, sessions, patients) is refused ("FOREIGN KEY constraint
    failed") and the upgrade could never run. So, as SQLite's own procedure for a changed table says, foreign keys
    are off while the migration runs (the pragma only takes effect outside a transaction), every reference is
    checked with ``PRAGMA foreign_key_check`` before the commit (a violation rolls everything back), and they are
    on again after."""
    where = str(engine.url.render_as_string(hide_password=True))
    with engine.connect() as connection:
        sqlite = connection.dialect.name == "sqlite"
        driver = connection.connection.driver_connection
        if sqlite:
            driver.execute("PRAGMA foreign_keys=OFF")  # before SQLAlchemy's BEGIN: inside one it is ignored
        try:
            with connection.begin():
                before = current_revision(connection)
                _refuse_unknown(before, where)
                if before is not None and before_change is not None and before != _target(revision):
                    before_change(before)
                command.upgrade(_config(connection), revision)
                if sqlite:
                    broken = connection.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
                    if broken:
                        table, rowid, parent, _ = broken[0]
                        raise ArchiveError(f"The archive at {where} was not upgraded: the migration left "
                                           f"{len(broken)} row(s) referring to nothing (first: {table} row {rowid} "
                                           f"refers to a missing {parent} row); nothing was changed.")
                after = current_revision(connection)
        finally:
            if sqlite:
                driver.execute("PRAGMA foreign_keys=ON")
    assert after is not None
    return before, after


def _target(revision: str) -> str:
    return head_revision() if revision == "head" else revision


def _refuse_unknown(revision: str | None, where: str) -> None:
    if revision is None:
        return
    known = {s.revision for s in scripts().walk_revisions()}
    if revision not in known:
        raise ArchiveTooNew(f"The archive at {where} was made by a newer version of LINarm++ Manager (schema "
                            f"{revision}; this version knows up to {head_revision()}): it is not opened, so nothing "
                            "in it can be damaged. Update LINarm++ Manager on this station.")


def check(engine: Engine, where: str, create: bool = True) -> str:
    """The archive's revision once it is usable: a fresh database is created (``create``), an older schema is
    refused with NeedsUpgrade, a newer one with ArchiveTooNew."""
    with engine.connect() as connection:
        revision = current_revision(connection)
        empty = revision is None and not inspect(connection).get_table_names()
    if empty and create:
        return upgrade(engine)[1]
    if revision is None:
        raise NeedsUpgrade(f"The archive at {where} has tables but no schema version: it was not made by LINarm++ "
                           "Manager, or its creation was interrupted; it is not opened.")
    _refuse_unknown(revision, where)
    head = head_revision()
    if revision != head:
        raise NeedsUpgrade(f"The archive at {where} has an older schema ({revision}; this version needs {head}): run "
                           "`linarmpp archive upgrade` (back it up first) on one station, then start again.")
    return revision


def grant_statements(app_role: str, schema: str = "public") -> list[str]:
    """The SQL a site runs (as the archive's owner) so the application's role may read everything, append to the
    journals and the other append-only tables, and change only what must change: the patient row (its version)
    and the plan (replaced with each save). No UPDATE or DELETE on the journal, histories or ledger."""
    role = '"' + app_role.replace('"', '""') + '"'
    tables = sorted(Base.metadata.tables)
    out = [f"GRANT USAGE ON SCHEMA {schema} TO {role}",
           f"GRANT SELECT ON {schema}.alembic_version TO {role}"]
    out += [f"GRANT SELECT, INSERT ON {schema}.{t} TO {role}" for t in tables]
    out += [f"GRANT UPDATE ON {schema}.patients TO {role}",
            f"GRANT DELETE ON {schema}.plan_steps TO {role}",
            f"GRANT USAGE, SELECT ON ALL SEQUENCES IN SCHEMA {schema} TO {role}"]
    assert not set(APPEND_ONLY) & {"patients", "plan_steps"}
    return out
