"""Tables. The same models and migrations serve PostGIS and the embedded SQLite file.

Geometry: on PostgreSQL a GeoAlchemy2 ``Geometry(LINESTRING, 4326)`` with a GiST index; on
SQLite the same value as EWKT text (SpatiaLite is not assumed). Write it with :func:`ewkt_linestring`.
"""

from __future__ import annotations

from datetime import UTC, datetime

import shapely
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


class FeatureGeometry(TypeDecorator):
    """Any geometry in EPSG:4326 (LineString, Polygon), exchanged as a shapely geometry: PostGIS
    ``geometry(GEOMETRY, 4326)`` on PostgreSQL (GiST-indexed, what ``ST_AsMVT`` reads), EWKT text on
    SQLite."""

    impl = Text
    cache_ok = True

    def load_dialect_impl(self, dialect):
        if dialect is None:
            return Text()
        if dialect.name == "postgresql":
            return dialect.type_descriptor(Geometry("GEOMETRY", srid=4326, spatial_index=False))
        return dialect.type_descriptor(Text())

    def bind_expression(self, bindvalue):
        return bindvalue

    def process_bind_param(self, value, dialect):
        if value is None or isinstance(value, str):
            return value
        return f"SRID=4326;{shapely.to_wkt(value, rounding_precision=8, trim=True)}"

    def process_result_value(self, value, dialect):
        if value is None:
            return None
        text = str(value)
        if text.startswith("SRID="):
            return shapely.from_wkt(text.split(";", 1)[1])
        return shapely.from_wkb(
            bytes.fromhex(text) if not isinstance(value, bytes | memoryview) else bytes(value)
        )


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
    # when the raw upload was deleted (retention, services.retention); NULL while it is kept
    raw_purged_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))


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
    """A web-mercator XYZ tile owning some of a trip's frames (``frames``: how many; NULL on rows
    from before migration 0005); ``processed_job_id`` once a tile job took it."""

    __tablename__ = "trip_tiles"
    __table_args__ = (Index("ix_trip_tiles_zxy", "z", "x", "y"),)

    trip_pk: Mapped[str] = mapped_column(ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True)
    z: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[int] = mapped_column(Integer, primary_key=True)
    y: Mapped[int] = mapped_column(Integer, primary_key=True)
    processed_job_id: Mapped[str | None] = mapped_column(String(36))
    frames: Mapped[int | None] = mapped_column(Integer)


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
    to a runner (Celery or the in-process pool). A running job holds a lease until
    ``lease_expires_at``, renewed by its runner while it works (``workers.lease``); a running job
    whose lease ran out, or that has none, is no longer worked on."""

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
    lease_expires_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))


class TripTileAlignment(Base):
    """What one ``align_tile`` job made of one trip in one tile (coarse + fine alignment of the trip's
    frames in the tile and its halo). Poses and instance points are metres in the tile's region frame
    (``origin_lat/lon``). ``arrays``: ``frame_indices (F,)``, ``poses_xyyaw (F, 3)``,
    ``weights (F,)`` (blend weights; 0 where the trip's piece was not tied to other trips here),
    ``residuals_m (F,)``; ``instances``: the trip's instances moved with its alignment (JSON as in
    ``trip_reconstructions``). ``failed_reason``: set when the trip could not be aligned here.
    ``merged_version_id``: the tile version that took these instances in (NULL until merged)."""

    __tablename__ = "trip_tile_alignments"
    __table_args__ = (Index("ix_trip_tile_alignments_zxy", "z", "x", "y"),)

    trip_pk: Mapped[str] = mapped_column(ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True)
    z: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[int] = mapped_column(Integer, primary_key=True)
    y: Mapped[int] = mapped_column(Integer, primary_key=True)
    job_id: Mapped[str] = mapped_column(String(36))
    origin_lat: Mapped[float] = mapped_column(Float)
    origin_lon: Mapped[float] = mapped_column(Float)
    arrays: Mapped[bytes] = mapped_column(LargeBinary)
    instances: Mapped[list] = mapped_column(JSON)
    noise: Mapped[dict] = mapped_column(JSON)
    failed_reason: Mapped[str | None] = mapped_column(Text)
    merged_version_id: Mapped[int | None] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class TripPoses(Base):
    """The final globally aligned pose of every uploaded frame (``GET /v1/trips/{id}/poses``):
    ``arrays`` holds ``t (N,)``, ``lat (N,)``, ``lon (N,)``, ``heading_deg (N,)``."""

    __tablename__ = "trip_poses"

    trip_pk: Mapped[str] = mapped_column(ForeignKey("trips.id", ondelete="CASCADE"), primary_key=True)
    job_id: Mapped[str] = mapped_column(String(36))
    arrays: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class MatchPair(Base):
    """An accepted sub-map matching pair of a tile's alignment (``csr_core.alignment.MatchPairRecord``
    as JSON in ``record``), kept for validation and human correction. ``trip_pk_i`` is NULL for a
    pair with the pre-built map. ``status``: ``active`` | ``rejected`` (by a correction) |
    ``added`` (made by a correction) | ``superseded`` (a later alignment of the tile replaced it)."""

    __tablename__ = "match_pairs"
    # a tile's pairs in the listing's order (confidence, id): its pages are index range scans
    __table_args__ = (Index("ix_match_pairs_tile_order", "z", "x", "y", "confidence", "id"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    z: Mapped[int] = mapped_column(Integer)
    x: Mapped[int] = mapped_column(Integer)
    y: Mapped[int] = mapped_column(Integer)
    job_id: Mapped[str] = mapped_column(String(36))
    trip_pk_i: Mapped[str | None] = mapped_column(String(36))
    trip_pk_j: Mapped[str | None] = mapped_column(String(36))
    confidence: Mapped[float] = mapped_column(Float)
    residual_rms_m: Mapped[float] = mapped_column(Float)
    status: Mapped[str] = mapped_column(String(16), default="active")
    record: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class TileVersion(Base):
    """One version of one tile's road structure; append-only (never updated but ``status``).

    ``id`` is global and increasing: the map version (``GET /v1/map?version=N`` shows, per tile, the
    newest published version with ``id <= N``). ``version`` counts per tile from 1. ``status``:
    ``published`` (went live when made), ``candidate`` (failed the publish gate: for review),
    ``approved`` (a candidate later published). ``reason``: ``merge`` | ``correction`` |
    ``rollback to vN`` | ``approve vN``. ``trips``: trip ids merged by it; ``corrections``: correction
    ids applied; ``quality``: the validator's tile quality; ``changes``: counts per change type.
    ``state``: the topology state (``csr_core.topology.TopologyResult``, zlib-compressed pickle) that the
    next incremental merge continues from."""

    __tablename__ = "tile_versions"
    __table_args__ = (UniqueConstraint("z", "x", "y", "version", name="uq_tile_versions_zxyv"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    z: Mapped[int] = mapped_column(Integer)
    x: Mapped[int] = mapped_column(Integer)
    y: Mapped[int] = mapped_column(Integer)
    version: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16))
    job_id: Mapped[str | None] = mapped_column(String(36))
    parent_version: Mapped[int | None] = mapped_column(Integer)
    reason: Mapped[str] = mapped_column(Text)
    trips: Mapped[list] = mapped_column(JSON)
    corrections: Mapped[list] = mapped_column(JSON)
    quality: Mapped[dict] = mapped_column(JSON)
    changes: Mapped[dict] = mapped_column(JSON)
    n_features: Mapped[int] = mapped_column(Integer)
    origin_lat: Mapped[float] = mapped_column(Float)
    origin_lon: Mapped[float] = mapped_column(Float)
    state: Mapped[bytes | None] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class TileHead(Base):
    """Per tile: the newest version made and the live one (what tiles and the map serve). Writers
    compare-and-set ``latest_version`` (the expected version, as the OSM API's 409)."""

    __tablename__ = "tile_heads"

    z: Mapped[int] = mapped_column(Integer, primary_key=True)
    x: Mapped[int] = mapped_column(Integer, primary_key=True)
    y: Mapped[int] = mapped_column(Integer, primary_key=True)
    latest_version: Mapped[int] = mapped_column(Integer)
    live_version: Mapped[int | None] = mapped_column(Integer)
    live_version_id: Mapped[int | None] = mapped_column(ForeignKey("tile_versions.id"))
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class MapFeatureRow(Base):
    """One element of one tile version, clipped to the tile. ``feature_id`` is stable across versions
    (``<z>-<x>-<y>-<topology id>``). ``change`` against the tile's previous version: ``added`` |
    ``modified`` | ``unchanged`` | ``removed`` (a removed element keeps its last geometry here and is
    not part of the version's map). ``properties``: support, uncertainty, first/last seen, flags."""

    __tablename__ = "map_features"
    __table_args__ = (
        Index("ix_map_features_version", "tile_version_id"),
        Index("ix_map_features_feature", "feature_id"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    tile_version_id: Mapped[int] = mapped_column(ForeignKey("tile_versions.id", ondelete="CASCADE"))
    feature_id: Mapped[str] = mapped_column(String(96))
    type: Mapped[str] = mapped_column(String(24))
    style: Mapped[str | None] = mapped_column(String(16))
    change: Mapped[str] = mapped_column(String(16))
    properties: Mapped[dict] = mapped_column(JSON)
    geom: Mapped[object] = mapped_column(FeatureGeometry)


class Correction(Base):
    """A human correction of a tile's alignment (issue on validation and correction): ``kind``
    ``reject_pair`` (payload ``{"pair_id"}``) or ``add_pair`` (payload: the two trips' frames or
    elements and the weight); who (``author_key_id``), when, the job that applied it and the tile
    version it produced; ``undone_at`` / ``undone_by`` when undone (which makes a new version too)."""

    __tablename__ = "corrections"
    __table_args__ = (Index("ix_corrections_zxy", "z", "x", "y"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    z: Mapped[int] = mapped_column(Integer)
    x: Mapped[int] = mapped_column(Integer)
    y: Mapped[int] = mapped_column(Integer)
    kind: Mapped[str] = mapped_column(String(24))
    payload: Mapped[dict] = mapped_column(JSON)
    author_key_id: Mapped[str] = mapped_column(String(40))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    undone_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    undone_by: Mapped[str | None] = mapped_column(String(40))
    result_version_id: Mapped[int | None] = mapped_column(Integer)
    job_id: Mapped[str | None] = mapped_column(String(36))


def ewkt_linestring(lonlat_deg) -> str:
    """``(N, 2)`` lon, lat degrees -> ``SRID=4326;LINESTRING(...)`` (what the track column takes)."""
    coords = ",".join(f"{lon!r} {lat!r}" for lon, lat in lonlat_deg.tolist())
    return f"SRID=4326;LINESTRING({coords})"


class TileVersionExtent(Base):
    """The lon/lat bounding box of a tile version's features (all ``None``: it has none). A served
    tile's content depends only on the live versions whose extent meets its buffered bounds, so
    their ids are its identity (the ETag and the key of :class:`TileRender`). A version without a
    row (written before this table) counts as reaching everywhere near its tile."""

    __tablename__ = "tile_version_extents"

    tile_version_id: Mapped[int] = mapped_column(
        ForeignKey("tile_versions.id", ondelete="CASCADE"), primary_key=True
    )
    west: Mapped[float | None] = mapped_column(Float)
    south: Mapped[float | None] = mapped_column(Float)
    east: Mapped[float | None] = mapped_column(Float)
    north: Mapped[float | None] = mapped_column(Float)


class TileRender(Base):
    """A served tile's body, stored once per content: ``etag`` (the strong ETag, which hashes the
    format, the encoder and the contributing versions) -> ``body`` (``None``: an empty tile, 204).
    Written when a version is published (the pipeline-zoom tiles it changes, in the same
    transaction) and on the first read of any other tile; never updated."""

    __tablename__ = "tile_renders"
    __table_args__ = (Index("ix_tile_renders_zxy", "z", "x", "y"),)

    etag: Mapped[str] = mapped_column(String(40), primary_key=True)
    kind: Mapped[str] = mapped_column(String(8))  # mvt | geojson
    z: Mapped[int] = mapped_column(Integer)
    x: Mapped[int] = mapped_column(Integer)
    y: Mapped[int] = mapped_column(Integer)
    body: Mapped[bytes | None] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
