"""Tile serving: the extent of every tile version's features (which tiles a version can reach) and
the rendered tile bodies, stored once per content (keyed by the strong ETag); on PostgreSQL a
trigger that announces key revocations to the API processes (``NOTIFY csr_keys``).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

TZ = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "tile_version_extents",
        sa.Column(
            "tile_version_id",
            sa.Integer,
            sa.ForeignKey("tile_versions.id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("west", sa.Float),
        sa.Column("south", sa.Float),
        sa.Column("east", sa.Float),
        sa.Column("north", sa.Float),
    )
    op.create_table(
        "tile_renders",
        sa.Column("etag", sa.String(40), primary_key=True),
        sa.Column("kind", sa.String(8), nullable=False),
        sa.Column("z", sa.Integer, nullable=False),
        sa.Column("x", sa.Integer, nullable=False),
        sa.Column("y", sa.Integer, nullable=False),
        sa.Column("body", sa.LargeBinary),
        sa.Column("created_at", TZ, nullable=False),
    )
    op.create_index("ix_tile_renders_zxy", "tile_renders", ["z", "x", "y"])
    if op.get_bind().dialect.name == "postgresql":
        op.execute(
            """
            CREATE FUNCTION csr_notify_keys() RETURNS trigger LANGUAGE plpgsql AS $$
            BEGIN
              PERFORM pg_notify('csr_keys', '');
              RETURN NULL;
            END $$;
            """
        )
        op.execute(
            "CREATE TRIGGER api_keys_notify AFTER UPDATE OR DELETE ON api_keys "
            "FOR EACH STATEMENT EXECUTE FUNCTION csr_notify_keys()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("DROP TRIGGER IF EXISTS api_keys_notify ON api_keys")
        op.execute("DROP FUNCTION IF EXISTS csr_notify_keys()")
    op.drop_table("tile_renders")
    op.drop_table("tile_version_extents")
