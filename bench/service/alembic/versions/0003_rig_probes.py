"""rig probes: the newest `drivebench probe` of each rig (identity and checklist) for the rig page

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-25
"""
from alembic import op
import sqlalchemy as sa


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('rig_probes',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('rig', sa.String(length=200), nullable=False),
    sa.Column('by', sa.String(length=200), nullable=False),
    sa.Column('started_ts', sa.Float(), nullable=False),
    sa.Column('ended_ts', sa.Float(), nullable=False),
    sa.Column('exit_code', sa.Integer(), nullable=True),
    sa.Column('report', sa.JSON(), nullable=True),
    sa.Column('error', sa.Text(), nullable=True),
    sa.ForeignKeyConstraint(['rig'], ['rigs.name'], ),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('rig_probes', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_rig_probes_rig'), ['rig'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('rig_probes', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_rig_probes_rig'))
    op.drop_table('rig_probes')
