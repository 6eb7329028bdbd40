"""initial schema: tokens, rigs, runs, criterion values, leases

Revision ID: 0001
Revises: 
Create Date: 2026-11-24
"""
from alembic import op
import sqlalchemy as sa


revision = '0001'
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('rigs',
    sa.Column('name', sa.String(length=200), nullable=False),
    sa.Column('bench', sa.Text(), nullable=False),
    sa.Column('tags', sa.JSON(), nullable=False),
    sa.Column('simulated', sa.Boolean(), nullable=False),
    sa.Column('max_concurrent', sa.Integer(), nullable=False),
    sa.Column('enabled', sa.Boolean(), nullable=False),
    sa.Column('lock_seq', sa.Integer(), nullable=False),
    sa.PrimaryKeyConstraint('name')
    )
    op.create_table('runs',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('state', sa.String(length=20), nullable=False),
    sa.Column('verdict', sa.String(length=20), nullable=True),
    sa.Column('rig', sa.String(length=200), nullable=True),
    sa.Column('tag', sa.String(length=200), nullable=True),
    sa.Column('candidates', sa.JSON(), nullable=True),
    sa.Column('scenario', sa.Text(), nullable=False),
    sa.Column('scenario_file', sa.Text(), nullable=False),
    sa.Column('scenario_name', sa.String(length=300), nullable=True),
    sa.Column('scenario_sha256', sa.String(length=64), nullable=True),
    sa.Column('seed', sa.BigInteger(), nullable=True),
    sa.Column('owner', sa.String(length=200), nullable=False),
    sa.Column('owner_token_id', sa.Integer(), nullable=True),
    sa.Column('submitted_ts', sa.Float(), nullable=False),
    sa.Column('started_ts', sa.Float(), nullable=True),
    sa.Column('ended_ts', sa.Float(), nullable=True),
    sa.Column('duration_s', sa.Float(), nullable=True),
    sa.Column('progress_s', sa.Float(), nullable=True),
    sa.Column('scenario_duration_s', sa.Float(), nullable=True),
    sa.Column('host', sa.String(length=200), nullable=True),
    sa.Column('pid', sa.Integer(), nullable=True),
    sa.Column('run_dir', sa.Text(), nullable=True),
    sa.Column('reason', sa.Text(), nullable=True),
    sa.Column('abort_requested_by', sa.String(length=200), nullable=True),
    sa.Column('aborted_by', sa.String(length=200), nullable=True),
    sa.Column('drive', sa.JSON(), nullable=True),
    sa.Column('firmware_version', sa.String(length=200), nullable=True),
    sa.Column('revision', sa.String(length=64), nullable=True),
    sa.Column('software', sa.JSON(), nullable=True),
    sa.Column('criteria', sa.JSON(), nullable=True),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_runs_revision'), ['revision'], unique=False)
        batch_op.create_index(batch_op.f('ix_runs_rig'), ['rig'], unique=False)
        batch_op.create_index(batch_op.f('ix_runs_scenario_name'), ['scenario_name'], unique=False)
        batch_op.create_index(batch_op.f('ix_runs_state'), ['state'], unique=False)

    op.create_table('tokens',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('name', sa.String(length=200), nullable=False),
    sa.Column('role', sa.String(length=20), nullable=False),
    sa.Column('sha256', sa.String(length=64), nullable=False),
    sa.Column('created_ts', sa.Float(), nullable=False),
    sa.Column('revoked', sa.Boolean(), nullable=False),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('tokens', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_tokens_sha256'), ['sha256'], unique=True)

    op.create_table('criterion_values',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('name', sa.String(length=300), nullable=False),
    sa.Column('signal', sa.String(length=200), nullable=True),
    sa.Column('value', sa.Float(), nullable=True),
    sa.Column('limit', sa.Float(), nullable=True),
    sa.Column('passed', sa.Boolean(), nullable=False),
    sa.Column('status', sa.String(length=20), nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('criterion_values', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_criterion_values_name'), ['name'], unique=False)
        batch_op.create_index(batch_op.f('ix_criterion_values_run_id'), ['run_id'], unique=False)

    op.create_table('leases',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('rig', sa.String(length=200), nullable=False),
    sa.Column('holder', sa.String(length=200), nullable=False),
    sa.Column('kind', sa.String(length=20), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=True),
    sa.Column('reason', sa.Text(), nullable=True),
    sa.Column('created_ts', sa.Float(), nullable=False),
    sa.Column('expires_ts', sa.Float(), nullable=False),
    sa.Column('released_ts', sa.Float(), nullable=True),
    sa.Column('released_by', sa.String(length=200), nullable=True),
    sa.ForeignKeyConstraint(['rig'], ['rigs.name'], ),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('leases', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_leases_expires_ts'), ['expires_ts'], unique=False)
        batch_op.create_index(batch_op.f('ix_leases_rig'), ['rig'], unique=False)



def downgrade() -> None:
    with op.batch_alter_table('leases', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_leases_rig'))
        batch_op.drop_index(batch_op.f('ix_leases_expires_ts'))

    op.drop_table('leases')
    with op.batch_alter_table('criterion_values', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_criterion_values_run_id'))
        batch_op.drop_index(batch_op.f('ix_criterion_values_name'))

    op.drop_table('criterion_values')
    with op.batch_alter_table('tokens', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_tokens_sha256'))

    op.drop_table('tokens')
    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_runs_state'))
        batch_op.drop_index(batch_op.f('ix_runs_scenario_name'))
        batch_op.drop_index(batch_op.f('ix_runs_rig'))
        batch_op.drop_index(batch_op.f('ix_runs_revision'))

    op.drop_table('runs')
    op.drop_table('rigs')
