"""Single-trip reconstructions: smoothed poses, keyframes, instances and noise per trip.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "trip_reconstructions",
        sa.Column("trip_pk", sa.String(36), sa.ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("algorithm_version", sa.String(32), primary_key=True),
        sa.Column("origin_lat", sa.Float, nullable=False),
        sa.Column("origin_lon", sa.Float, nullable=False),
        sa.Column("n_frames", sa.Integer, nullable=False),
        sa.Column("n_keyframes", sa.Integer, nullable=False),
        sa.Column("n_instances", sa.Integer, nullable=False),
        sa.Column("arrays", sa.LargeBinary, nullable=False),
        sa.Column("instances", sa.JSON, nullable=False),
        sa.Column("noise", sa.JSON, nullable=False),
        sa.Column("diagnostics", sa.JSON, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("trip_reconstructions")
