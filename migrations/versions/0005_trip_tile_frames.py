"""The frames a trip has in each tile (``trip_tiles.frames``): the scheduler's estimate of a tile
job's cost (longest jobs first). NULL on rows written before: counted as one frame.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("trip_tiles") as batch:
        batch.add_column(sa.Column("frames", sa.Integer, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trip_tiles") as batch:
        batch.drop_column("frames")
