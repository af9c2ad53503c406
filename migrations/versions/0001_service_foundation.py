"""Service foundation: keys, trips (+ raw uploads, tiles), dirty tiles, jobs/outbox.

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

TZ = sa.DateTime(timezone=True)


def upgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    op.create_table(
        "api_keys",
        sa.Column("id", sa.String(40), primary_key=True),
        sa.Column("key_sha256", sa.String(64), nullable=False, unique=True),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("vehicle_id", sa.String(64)),
        sa.Column("created_at", TZ, nullable=False),
        sa.Column("revoked_at", TZ),
    )
    op.create_table(
        "trips",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column("vehicle_id", sa.String(64), nullable=False),
        sa.Column("trip_id", sa.String(128), nullable=False),
        sa.Column("content_sha256", sa.String(64), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("schema_version", sa.String(16), nullable=False),
        sa.Column("started_at", sa.String(40), nullable=False),
        sa.Column("n_frames", sa.Integer, nullable=False),
        sa.Column("body_bytes", sa.Integer, nullable=False),
        sa.Column("json_bytes", sa.Integer, nullable=False),
        sa.Column("received_at", TZ, nullable=False),
        sa.Column("updated_at", TZ, nullable=False),
        sa.Column("length_km", sa.Float),
        sa.Column("error", sa.Text),
        sa.UniqueConstraint("vehicle_id", "trip_id", name="uq_trips_vehicle_trip"),
    )
    # The raw GNSS track: PostGIS geometry with a GiST index; EWKT text on SQLite (see
    # services.db.models.TrackGeometry). Added by hand: GeoAlchemy2's create-table hooks assume
    # SpatiaLite on SQLite.
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TABLE trips ADD COLUMN track geometry(LINESTRING, 4326)")
        op.execute("CREATE INDEX ix_trips_track ON trips USING gist (track)")
    else:
        op.add_column("trips", sa.Column("track", sa.Text, nullable=True))
    op.create_table(
        "trip_uploads",
        sa.Column("trip_pk", sa.String(36), sa.ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("encoding", sa.String(16), nullable=False),
        sa.Column("body", sa.LargeBinary, nullable=False),
    )
    op.create_table(
        "trip_tiles",
        sa.Column("trip_pk", sa.String(36), sa.ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("z", sa.Integer, primary_key=True),
        sa.Column("x", sa.Integer, primary_key=True),
        sa.Column("y", sa.Integer, primary_key=True),
        sa.Column("processed_job_id", sa.String(36)),
    )
    op.create_index("ix_trip_tiles_zxy", "trip_tiles", ["z", "x", "y"])
    op.create_table(
        "dirty_tiles",
        sa.Column("z", sa.Integer, primary_key=True),
        sa.Column("x", sa.Integer, primary_key=True),
        sa.Column("y", sa.Integer, primary_key=True),
        sa.Column("first_marked_at", TZ, nullable=False),
        sa.Column("last_marked_at", TZ, nullable=False),
        sa.Column("job_id", sa.String(36)),
    )
    op.create_table(
        "jobs",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("queue", sa.String(16), nullable=False),
        sa.Column("subject", sa.String(64), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("error", sa.Text),
        sa.Column("created_at", TZ, nullable=False),
        sa.Column("dispatched_at", TZ),
        sa.Column("started_at", TZ),
        sa.Column("finished_at", TZ),
        sa.Column("duration_s", sa.Float),
    )
    op.create_index("ix_jobs_state", "jobs", ["state"])
    op.create_index("ix_jobs_outbox", "jobs", ["dispatched_at", "created_at"])
    op.create_index("ix_jobs_subject", "jobs", ["subject"])


def downgrade() -> None:
    for table in ("jobs", "dirty_tiles", "trip_tiles", "trip_uploads", "trips", "api_keys"):
        op.drop_table(table)
