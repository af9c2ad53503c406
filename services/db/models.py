"""Tables. The same models and migrations serve PostGIS and the embedded SQLite file.

Geometry: on PostgreSQL a GeoAlchemy2 ``Geometry(LINESTRING, 4326)`` with a GiST index; on
SQLite the same value as EWKT text (SpatiaLite is not assumed). Write it with :func:`ewkt_linestring`.
"""

from __future__ import annotations

from datetime import UTC, datetime

from geoalchemy2 import Geometry
from sqlalchemy import (
    JSON,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column


class TrackGeometry(TypeDecorator):
    """A LineString in EPSG:4326: PostGIS ``geometry(LINESTRING, 4326)`` on PostgreSQL, EWKT text on
    SQLite. Bound as EWKT text (PostGIS parses it on insert); reads give EWKB hex on PostgreSQL and
    EWKT on SQLite. (A TypeDecorator rather than ``with_variant``: GeoAlchemy2's DDL hooks would
    call SpatiaLite functions on SQLite.)"""

    impl = Text
    cache_ok = True

    def load_dialect_impl(self, dialect):
        if dialect is None:  # GeoAlchemy2's DDL hooks ask without a dialect: not theirs to manage
            return Text()
        if dialect.name == "postgresql":
            return dialect.type_descriptor(Geometry("LINESTRING", srid=4326, spatial_index=False))
        return dialect.type_descriptor(Text())


def utcnow() -> datetime:
    return datetime.now(UTC)


class Base(DeclarativeBase):
    pass


class ApiKey(Base):
    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    key_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[str] = mapped_column(String(16))  # vehicle | reader | admin
    vehicle_id: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))


class Trip(Base):
    __tablename__ = "trips"
    __table_args__ = (UniqueConstraint("vehicle_id", "trip_id", name="uq_trips_vehicle_trip"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    vehicle_id: Mapped[str] = mapped_column(String(64))
    trip_id: Mapped[str] = mapped_column(String(128))
    content_sha256: Mapped[str] = mapped_column(String(64))  # of the decompressed body
    status: Mapped[str] = mapped_column(String(16), default="received")  # received|processing|aligned|failed
    schema_version: Mapped[str] = mapped_column(String(16))
    started_at: Mapped[str] = mapped_column(String(40))
    n_frames: Mapped[int] = mapped_column(Integer)
    body_bytes: Mapped[int] = mapped_column(Integer)  # as sent
    json_bytes: Mapped[int] = mapped_column(Integer)  # decompressed
    received_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    length_km: Mapped[float | None] = mapped_column(Float)
    track: Mapped[str | None] = mapped_column(TrackGeometry, nullable=True)  # raw GNSS fixes, EPSG:4326
    error: Mapped[str | None] = mapped_column(Text)


class TripUpload(Base):
    """The upload as received, gzip-compressed, kept so that trips can be reprocessed."""

    __tablename__ = "trip_uploads"

    trip_pk: Mapped[str] = mapped_column(ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True)
    encoding: Mapped[str] = mapped_column(String(16), default="gzip")
    body: Mapped[bytes] = mapped_column(LargeBinary)


class TripReconstructionRecord(Base):
    """Single-trip reconstruction of one trip (csr_core.single_trip) by one algorithm version,
    recomputable from the raw upload. Poses and instance points are metres in the trip's region
    frame: the local transverse Mercator (``csr_core.geo.LocalFrame``) at ``origin_lat/lon``, the
    centre of the zoom-10 web-mercator tile of the trip's first fix (``region_frame_for``).

    ``arrays``: ``np.savez_compressed`` bytes with ``poses_xyyaw_world (N, 3)``,
    ``pose_sigma_xy_m (N,)``, ``keyframe_indices (K,)`` and ``gnss_inlier (N,)`` (see
    ``services.reconstructions``). ``instances``: ``[{"type", "style", "points_xy", "n_observations",
    "first_frame", "last_frame"}]``; ``noise``: ``{type: {"lateral_sigma_m", "along_sigma_m",
    "n_samples"}}``."""

    __tablename__ = "trip_reconstructions"

    trip_pk: Mapped[str] = mapped_column(ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True)
    algorithm_version: Mapped[str] = mapped_column(String(32), primary_key=True)
    origin_lat: Mapped[float] = mapped_column(Float)
    origin_lon: Mapped[float] = mapped_column(Float)
    n_frames: Mapped[int] = mapped_column(Integer)
    n_keyframes: Mapped[int] = mapped_column(Integer)
    n_instances: Mapped[int] = mapped_column(Integer)
    arrays: Mapped[bytes] = mapped_column(LargeBinary)
    instances: Mapped[list] = mapped_column(JSON)
    noise: Mapped[dict] = mapped_column(JSON)
    diagnostics: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class TripTile(Base):
    """A web-mercator XYZ tile touched by a trip's GNSS track; ``processed_job_id`` once a tile job took it."""

    __tablename__ = "trip_tiles"
    __table_args__ = (Index("ix_trip_tiles_zxy", "z", "x", "y"),)

    trip_pk: Mapped[str] = mapped_column(ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True)
    z: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[int] = mapped_column(Integer, primary_key=True)
    y: Mapped[int] = mapped_column(Integer, primary_key=True)
    processed_job_id: Mapped[str | None] = mapped_column(String(36))


class DirtyTile(Base):
    """A tile with trips not yet processed; ``job_id`` is the tile job scheduled for it, if any."""

    __tablename__ = "dirty_tiles"

    z: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[int] = mapped_column(Integer, primary_key=True)
    y: Mapped[int] = mapped_column(Integer, primary_key=True)
    first_marked_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    last_marked_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    job_id: Mapped[str | None] = mapped_column(String(36))


class Job(Base):
    """Job state, and the transactional outbox: a row with ``dispatched_at`` NULL is not yet handed
    to a runner (Celery or the in-process pool)."""

    __tablename__ = "jobs"
    __table_args__ = (
        Index("ix_jobs_state", "state"),
        Index("ix_jobs_outbox", "dispatched_at", "created_at"),
        Index("ix_jobs_subject", "subject"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))  # ingest_trip | align_tile
    queue: Mapped[str] = mapped_column(String(16))  # ingest | align | merge
    subject: Mapped[str] = mapped_column(String(64))  # trip id or "z/x/y"
    state: Mapped[str] = mapped_column(String(16), default="queued")  # queued|running|done|failed
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    dispatched_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    duration_s: Mapped[float | None] = mapped_column(Float)


def ewkt_linestring(lonlat_deg) -> str:
    """``(N, 2)`` lon, lat degrees -> ``SRID=4326;LINESTRING(...)`` (what the track column takes)."""
    coords = ",".join(f"{lon!r} {lat!r}" for lon, lat in lonlat_deg.tolist())
    return f"SRID=4326;LINESTRING({coords})"
