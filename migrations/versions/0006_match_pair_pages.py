"""A tile's match pairs in the listing's order (``confidence``, ``id``): the index of their keyset
pages (``GET /v1/tiles/{z}/{x}/{y}/match-pairs?limit=&cursor=``). It replaces the ``(z, x, y)``
index, which is its prefix.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-02
"""

from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_match_pairs_tile_order", "match_pairs", ["z", "x", "y", "confidence", "id"])
    op.drop_index("ix_match_pairs_zxy", table_name="match_pairs")


def downgrade() -> None:
    op.create_index("ix_match_pairs_zxy", "match_pairs", ["z", "x", "y"])
    op.drop_index("ix_match_pairs_tile_order", table_name="match_pairs")
