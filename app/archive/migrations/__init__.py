"""Alembic migrations of the archive's schema (run by app.archive.schema; batch mode on SQLite)."""
