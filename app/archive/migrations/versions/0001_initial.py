"""The archive's first schema: patients, plans, electrode choices, patient history, sessions, runs, repetitions,
journal, session files, blobs, ledger (docs/archive.md).

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision: str | None = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('blobs',
    sa.Column('sha256', sa.String(length=64), nullable=False),
    sa.Column('size', sa.BigInteger(), nullable=False),
    sa.Column('chunks', sa.Integer(), nullable=False),
    sa.PrimaryKeyConstraint('sha256')
    )
    op.create_table('ledger',
    sa.Column('seq', sa.Integer(), autoincrement=False, nullable=False),
    sa.Column('kind', sa.String(length=16), nullable=False),
    sa.Column('key', sa.Text(), nullable=False),
    sa.Column('version', sa.Integer(), nullable=False),
    sa.Column('head', sa.String(length=64), nullable=False),
    sa.Column('at', sa.String(length=40), nullable=False),
    sa.Column('station', sa.Text(), nullable=False),
    sa.Column('prev_hash', sa.String(length=64), nullable=False),
    sa.Column('hash', sa.String(length=64), nullable=False),
    sa.PrimaryKeyConstraint('seq')
    )
    op.create_table('patient_history',
    sa.Column('patient_id', sa.String(length=64), nullable=False),
    sa.Column('version', sa.Integer(), nullable=False),
    sa.Column('fields', sa.Text(), nullable=False),
    sa.Column('values', sa.Text(), nullable=False),
    sa.Column('changed_by', sa.Text(), nullable=False),
    sa.Column('changed_station', sa.Text(), nullable=False),
    sa.Column('changed_at', sa.String(length=40), nullable=False),
    sa.Column('reason', sa.Text(), nullable=False),
    sa.Column('prev_hash', sa.String(length=64), nullable=False),
    sa.Column('hash', sa.String(length=64), nullable=False),
    sa.PrimaryKeyConstraint('patient_id', 'version')
    )
    op.create_table('patients',
    sa.Column('patient_id', sa.String(length=64), nullable=False),
    sa.Column('version', sa.Integer(), nullable=False),
    sa.Column('full_name', sa.Text(), nullable=False),
    sa.Column('birth_date', sa.String(length=10), nullable=False),
    sa.Column('record_number', sa.Text(), nullable=False),
    sa.Column('affected_side', sa.String(length=16), nullable=False),
    sa.Column('notes', sa.Text(), nullable=False),
    sa.Column('fes_profile', sa.Text(), nullable=False),
    sa.Column('scores', sa.Text(), nullable=False),
    sa.Column('assistance', sa.Text(), nullable=False),
    sa.Column('robot', sa.Text(), nullable=False),
    sa.Column('fes_caps', sa.Text(), nullable=False),
    sa.Column('search_text', sa.Text(), nullable=False),
    sa.Column('created', sa.String(length=40), nullable=False),
    sa.Column('updated', sa.String(length=40), nullable=False),
    sa.Column('changed_at', sa.String(length=40), nullable=False),
    sa.Column('changed_by', sa.Text(), nullable=False),
    sa.Column('changed_station', sa.Text(), nullable=False),
    sa.PrimaryKeyConstraint('patient_id')
    )
    op.create_table('sessions',
    sa.Column('uuid', sa.String(length=36), nullable=False),
    sa.Column('patient_id', sa.String(length=64), nullable=False),
    sa.Column('station', sa.Text(), nullable=False),
    sa.Column('operator', sa.Text(), nullable=False),
    sa.Column('note', sa.Text(), nullable=False),
    sa.Column('start_iso', sa.String(length=40), nullable=False),
    sa.Column('start_epoch_s', sa.Float(), nullable=False),
    sa.Column('end_iso', sa.String(length=40), nullable=False),
    sa.Column('duration_s', sa.Float(), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('app_version', sa.Text(), nullable=False),
    sa.Column('format_version', sa.Integer(), nullable=False),
    sa.Column('folder_name', sa.Text(), nullable=False),
    sa.Column('manifest', sa.Text(), nullable=False),
    sa.Column('exercises', sa.Text(), nullable=False),
    sa.Column('alarms', sa.Integer(), nullable=False),
    sa.Column('summary', sa.Text(), nullable=False),
    sa.Column('problems', sa.Text(), nullable=False),
    sa.Column('content_digest', sa.String(length=64), nullable=False),
    sa.Column('journal_head', sa.String(length=64), nullable=False),
    sa.Column('journal_rows', sa.Integer(), nullable=False),
    sa.Column('archived_at', sa.String(length=40), nullable=False),
    sa.Column('archived_station', sa.Text(), nullable=False),
    sa.PrimaryKeyConstraint('uuid')
    )
    op.create_index('ix_sessions_patient_start', 'sessions', ['patient_id', 'start_epoch_s'], unique=False)
    op.create_index('ix_sessions_start', 'sessions', ['start_epoch_s'], unique=False)
    op.create_table('blob_chunks',
    sa.Column('sha256', sa.String(length=64), nullable=False),
    sa.Column('seq', sa.Integer(), nullable=False),
    sa.Column('chunk_sha256', sa.String(length=64), nullable=False),
    sa.Column('data', sa.LargeBinary(), nullable=False),
    sa.ForeignKeyConstraint(['sha256'], ['blobs.sha256'], ),
    sa.PrimaryKeyConstraint('sha256', 'seq')
    )
    op.create_table('electrode_choices',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('patient_id', sa.String(length=64), nullable=False),
    sa.Column('district', sa.Text(), nullable=False),
    sa.Column('patient_version', sa.Integer(), nullable=False),
    sa.Column('cleared', sa.Boolean(), nullable=False),
    sa.Column('choice', sa.Text(), nullable=False),
    sa.Column('channel', sa.Integer(), nullable=True),
    sa.Column('electrodes', sa.Text(), nullable=False),
    sa.Column('chosen_at', sa.String(length=40), nullable=False),
    sa.Column('chosen_by', sa.Text(), nullable=False),
    sa.Column('session', sa.Text(), nullable=False),
    sa.ForeignKeyConstraint(['patient_id'], ['patients.patient_id'], ),
    sa.PrimaryKeyConstraint('id')
    )
    op.create_index('ix_electrode_choices_patient', 'electrode_choices', ['patient_id', 'district'], unique=False)
    op.create_table('journal',
    sa.Column('session_uuid', sa.String(length=36), nullable=False),
    sa.Column('seq', sa.Integer(), nullable=False),
    sa.Column('t_wall', sa.Text(), nullable=False),
    sa.Column('t_mono', sa.Float(), nullable=True),
    sa.Column('kind', sa.Text(), nullable=False),
    sa.Column('who', sa.Text(), nullable=False),
    sa.Column('origin', sa.Text(), nullable=False),
    sa.Column('data', sa.Text(), nullable=False),
    sa.Column('prev_hash', sa.String(length=64), nullable=False),
    sa.Column('hash', sa.String(length=64), nullable=False),
    sa.ForeignKeyConstraint(['session_uuid'], ['sessions.uuid'], ),
    sa.PrimaryKeyConstraint('session_uuid', 'seq')
    )
    op.create_index('ix_journal_kind', 'journal', ['session_uuid', 'kind'], unique=False)
    op.create_table('plan_steps',
    sa.Column('patient_id', sa.String(length=64), nullable=False),
    sa.Column('position', sa.Integer(), nullable=False),
    sa.Column('exercise', sa.Text(), nullable=False),
    sa.Column('params', sa.Text(), nullable=False),
    sa.Column('note', sa.Text(), nullable=False),
    sa.ForeignKeyConstraint(['patient_id'], ['patients.patient_id'], ),
    sa.PrimaryKeyConstraint('patient_id', 'position')
    )
    op.create_table('repetitions',
    sa.Column('session_uuid', sa.String(length=36), nullable=False),
    sa.Column('run_position', sa.Integer(), nullable=False),
    sa.Column('idx', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Text(), nullable=False),
    sa.Column('metrics', sa.Text(), nullable=False),
    sa.ForeignKeyConstraint(['session_uuid'], ['sessions.uuid'], ),
    sa.PrimaryKeyConstraint('session_uuid', 'run_position', 'idx')
    )
    op.create_table('runs',
    sa.Column('session_uuid', sa.String(length=36), nullable=False),
    sa.Column('position', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Text(), nullable=False),
    sa.Column('program', sa.Text(), nullable=False),
    sa.Column('title', sa.Text(), nullable=False),
    sa.Column('parameters', sa.Text(), nullable=False),
    sa.Column('source', sa.Text(), nullable=False),
    sa.Column('operator', sa.Text(), nullable=False),
    sa.Column('restart_of', sa.Text(), nullable=True),
    sa.Column('started_s', sa.Float(), nullable=False),
    sa.Column('ended_s', sa.Float(), nullable=True),
    sa.Column('end_reason', sa.Text(), nullable=True),
    sa.Column('end_detail', sa.Text(), nullable=False),
    sa.Column('summary', sa.Text(), nullable=False),
    sa.ForeignKeyConstraint(['session_uuid'], ['sessions.uuid'], ),
    sa.PrimaryKeyConstraint('session_uuid', 'position')
    )
    op.create_table('session_files',
    sa.Column('session_uuid', sa.String(length=36), nullable=False),
    sa.Column('name', sa.Text(), nullable=False),
    sa.Column('size', sa.BigInteger(), nullable=False),
    sa.Column('sha256', sa.String(length=64), nullable=False),
    sa.ForeignKeyConstraint(['session_uuid'], ['sessions.uuid'], ),
    sa.ForeignKeyConstraint(['sha256'], ['blobs.sha256'], ),
    sa.PrimaryKeyConstraint('session_uuid', 'name')
    )


def downgrade() -> None:
    op.drop_table('session_files')
    op.drop_table('runs')
    op.drop_table('repetitions')
    op.drop_table('plan_steps')
    op.drop_index('ix_journal_kind', table_name='journal')
    op.drop_table('journal')
    op.drop_index('ix_electrode_choices_patient', table_name='electrode_choices')
    op.drop_table('electrode_choices')
    op.drop_table('blob_chunks')
    op.drop_index('ix_sessions_start', table_name='sessions')
    op.drop_index('ix_sessions_patient_start', table_name='sessions')
    op.drop_table('sessions')
    op.drop_table('patients')
    op.drop_table('patient_history')
    op.drop_table('ledger')
    op.drop_table('blobs')
