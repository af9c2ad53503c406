"""Per-tile pipeline: alignment results per trip and tile, final poses, match pairs, tile versions
(append-only history), the features of every version, and human corrections.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

TZ = sa.DateTime(timezone=True)


def _geometry():
    if op.get_bind().dialect.name == "postgresql":
        from geoalchemy2 import Geometry

        return Geometry("GEOMETRY", srid=4326, spatial_index=False)
    return sa.Text()


def upgrade() -> None:
    op.create_table(
        "trip_tile_alignments",
        sa.Column("trip_pk", sa.String(36), sa.ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("z", sa.Integer, primary_key=True),
        sa.Column("x", sa.Integer, primary_key=True),
        sa.Column("y", sa.Integer, primary_key=True),
        sa.Column("job_id", sa.String(36), nullable=False),
        sa.Column("origin_lat", sa.Float, nullable=False),
        sa.Column("origin_lon", sa.Float, nullable=False),
        sa.Column("arrays", sa.LargeBinary, nullable=False),
        sa.Column("instances", sa.JSON, nullable=False),
        sa.Column("noise", sa.JSON, nullable=False),
        sa.Column("failed_reason", sa.Text),
        sa.Column("merged_version_id", sa.Integer),
        sa.Column("created_at", TZ, nullable=False),
    )
    op.create_index("ix_trip_tile_alignments_zxy", "trip_tile_alignments", ["z", "x", "y"])
    op.create_table(
        "trip_poses",
        sa.Column("trip_pk", sa.String(36), sa.ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("job_id", sa.String(36), nullable=False),
        sa.Column("arrays", sa.LargeBinary, nullable=False),
        sa.Column("created_at", TZ, nullable=False),
    )
    op.create_table(
        "match_pairs",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column("z", sa.Integer, nullable=False),
        sa.Column("x", sa.Integer, nullable=False),
        sa.Column("y", sa.Integer, nullable=False),
        sa.Column("job_id", sa.String(36), nullable=False),
        sa.Column("trip_pk_i", sa.String(36)),
        sa.Column("trip_pk_j", sa.String(36)),
        sa.Column("confidence", sa.Float, nullable=False),
        sa.Column("residual_rms_m", sa.Float, nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("record", sa.JSON, nullable=False),
        sa.Column("created_at", TZ, nullable=False),
    )
    op.create_index("ix_match_pairs_zxy", "match_pairs", ["z", "x", "y"])
    op.create_table(
        "tile_versions",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("z", sa.Integer, nullable=False),
        sa.Column("x", sa.Integer, nullable=False),
        sa.Column("y", sa.Integer, nullable=False),
        sa.Column("version", sa.Integer, nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("job_id", sa.String(36)),
        sa.Column("parent_version", sa.Integer),
        sa.Column("reason", sa.Text, nullable=False),
        sa.Column("trips", sa.JSON, nullable=False),
        sa.Column("corrections", sa.JSON, nullable=False),
        sa.Column("quality", sa.JSON, nullable=False),
        sa.Column("changes", sa.JSON, nullable=False),
        sa.Column("n_features", sa.Integer, nullable=False),
        sa.Column("origin_lat", sa.Float, nullable=False),
        sa.Column("origin_lon", sa.Float, nullable=False),
        sa.Column("state", sa.LargeBinary),
        sa.Column("created_at", TZ, nullable=False),
        sa.UniqueConstraint("z", "x", "y", "version", name="uq_tile_versions_zxyv"),
    )
    op.create_table(
        "tile_heads",
        sa.Column("z", sa.Integer, primary_key=True),
        sa.Column("x", sa.Integer, primary_key=True),
        sa.Column("y", sa.Integer, primary_key=True),
        sa.Column("latest_version", sa.Integer, nullable=False),
        sa.Column("live_version", sa.Integer),
        sa.Column("live_version_id", sa.Integer, sa.ForeignKey("tile_versions.id")),
        sa.Column("updated_at", TZ, nullable=False),
    )
    op.create_table(
        "map_features",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column(
            "tile_version_id",
            sa.Integer,
            sa.ForeignKey("tile_versions.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("feature_id", sa.String(96), nullable=False),
        sa.Column("type", sa.String(24), nullable=False),
        sa.Column("style", sa.String(16)),
        sa.Column("change", sa.String(16), nullable=False),
        sa.Column("properties", sa.JSON, nullable=False),
        sa.Column("geom", _geometry(), nullable=False),
    )
    op.create_index("ix_map_features_version", "map_features", ["tile_version_id"])
    op.create_index("ix_map_features_feature", "map_features", ["feature_id"])
    if op.get_bind().dialect.name == "postgresql":
        op.execute("CREATE INDEX ix_map_features_geom ON map_features USING GIST (geom)")
    op.create_table(
        "corrections",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column("z", sa.Integer, nullable=False),
        sa.Column("x", sa.Integer, nullable=False),
        sa.Column("y", sa.Integer, nullable=False),
        sa.Column("kind", sa.String(24), nullable=False),
        sa.Column("payload", sa.JSON, nullable=False),
        sa.Column("author_key_id", sa.String(40), nullable=False),
        sa.Column("created_at", TZ, nullable=False),
        sa.Column("undone_at", TZ),
        sa.Column("undone_by", sa.String(40)),
        sa.Column("result_version_id", sa.Integer),
        sa.Column("job_id", sa.String(36)),
    )
    op.create_index("ix_corrections_zxy", "corrections", ["z", "x", "y"])


def downgrade() -> None:
    for table in (
        "corrections",
        "map_features",
        "tile_heads",
        "tile_versions",
        "match_pairs",
        "trip_poses",
        "trip_tile_alignments",
    ):
        op.drop_table(table)
