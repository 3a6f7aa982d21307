"""Alembic's environment for the archive: run by app.archive.schema with the archive's own connection (no
alembic.ini). SQLite migrations run in batch mode (a copy of the table), since SQLite's ALTER TABLE is limited."""

from __future__ import annotations

from alembic import context

from app.archive.models import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata,
                  render_as_batch=connection.dialect.name == "sqlite")
with context.begin_transaction():
    context.run_migrations()
