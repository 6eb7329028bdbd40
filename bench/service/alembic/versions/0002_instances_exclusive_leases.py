"""service instances with liveness leases, one unreleased run lease per real rig, run candidates per rig

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-25
"""
from alembic import op
import sqlalchemy as sa


revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None

ONE_RUN_WHERE = "kind = 'run' AND exclusive_rig AND released_ts IS NULL"
LIVE_INSTANCE_WHERE = "stopped_ts IS NULL"


def upgrade() -> None:
    op.create_table('service_instances',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('name', sa.String(length=200), nullable=False),
    sa.Column('hostname', sa.String(length=255), nullable=False),
    sa.Column('boot_id', sa.String(length=64), nullable=True),
    sa.Column('pid', sa.Integer(), nullable=False),
    sa.Column('pid_start', sa.BigInteger(), nullable=True),
    sa.Column('started_ts', sa.Float(), nullable=False),
    sa.Column('heartbeat_ts', sa.Float(), nullable=False),
    sa.Column('expires_ts', sa.Float(), nullable=False),
    sa.Column('stopped_ts', sa.Float(), nullable=True),
    sa.Column('stopped_by', sa.String(length=200), nullable=True),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('service_instances', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_service_instances_name'), ['name'], unique=False)
        batch_op.create_index('ux_instances_live_name', ['name'], unique=True,
                              sqlite_where=sa.text(LIVE_INSTANCE_WHERE),
                              postgresql_where=sa.text(LIVE_INSTANCE_WHERE))

    op.create_table('run_candidates',
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('rig', sa.String(length=200), nullable=False),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('run_id', 'rig')
    )
    with op.batch_alter_table('run_candidates', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_run_candidates_rig'), ['rig'], unique=False)

    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('instance_id', sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column('pid_start', sa.BigInteger(), nullable=True))
        batch_op.create_index(batch_op.f('ix_runs_instance_id'), ['instance_id'], unique=False)

    with op.batch_alter_table('leases', schema=None) as batch_op:
        batch_op.add_column(sa.Column('exclusive_rig', sa.Boolean(), nullable=False, server_default=sa.text('false')))

    bind = op.get_bind()
    # an unreleased run lease on a real rig holds it from now on: the newest per rig (the bug this fixes could have
    # left two), so that the unique index can be built
    bind.execute(sa.text(
        "UPDATE leases SET exclusive_rig = true WHERE id IN (SELECT max(l.id) FROM leases l JOIN rigs r "
        "ON r.name = l.rig WHERE l.kind = 'run' AND l.released_ts IS NULL AND NOT r.simulated GROUP BY l.rig)"))
    with op.batch_alter_table('leases', schema=None) as batch_op:
        batch_op.create_index('ux_leases_one_run_per_real_rig', ['rig'], unique=True,
                              sqlite_where=sa.text(ONE_RUN_WHERE), postgresql_where=sa.text(ONE_RUN_WHERE))

    # queued runs submitted by tag: their candidate rigs as rows (all rigs of the tag where none were listed)
    runs = sa.table('runs', sa.column('id', sa.Integer), sa.column('state', sa.String), sa.column('rig', sa.String),
                    sa.column('tag', sa.String), sa.column('candidates', sa.JSON))
    rigs = sa.table('rigs', sa.column('name', sa.String), sa.column('tags', sa.JSON))
    tags = {name: list(t or []) for name, t in bind.execute(sa.select(rigs.c.name, rigs.c.tags))}
    rows = []
    for run_id, tag, candidates in bind.execute(sa.select(runs.c.id, runs.c.tag, runs.c.candidates).where(
            runs.c.state == 'queued', runs.c.rig.is_(None))):
        names = candidates if candidates is not None else [n for n, t in tags.items() if tag in t]
        rows += [{'run_id': run_id, 'rig': n} for n in dict.fromkeys(names)]
    if rows:
        op.bulk_insert(sa.table('run_candidates', sa.column('run_id', sa.Integer), sa.column('rig', sa.String)),
                       rows)


def downgrade() -> None:
    with op.batch_alter_table('leases', schema=None) as batch_op:
        batch_op.drop_index('ux_leases_one_run_per_real_rig')
        batch_op.drop_column('exclusive_rig')
    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_runs_instance_id'))
        batch_op.drop_column('pid_start')
        batch_op.drop_column('instance_id')
    with op.batch_alter_table('run_candidates', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_run_candidates_rig'))
    op.drop_table('run_candidates')
    with op.batch_alter_table('service_instances', schema=None) as batch_op:
        batch_op.drop_index('ux_instances_live_name')
        batch_op.drop_index(batch_op.f('ix_service_instances_name'))
    op.drop_table('service_instances')
