"""When a trip's raw upload was deleted (``trips.raw_purged_at``): raw uploads are kept
``CSR_RAW_RETENTION_DAYS`` after they were received, then deleted; the trip record stays.

Revision ID: 0008
Revises: 0007
"""

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("trips") as batch:
        batch.add_column(sa.Column("raw_purged_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trips") as batch:
        batch.drop_column("raw_purged_at")
