"""The version store of the tiled map (OSM API 0.6 as the model): every tile version kept,
append-only; stable feature ids; change types per feature; compare-and-set on the tile's latest
version (a stale expected version is a :class:`VersionConflict`, the API's 409).

Map versions: ``tile_versions.id`` is global and increasing. The map at version N is, per tile,
the newest ``published`` or ``approved`` version with ``id <= N``; the live map is every tile's
``tile_heads.live_version_id``. For map versions to be immutable (pinned tile URLs are cached
forever) and for the ``changes?since=`` feed not to skip anything, ids must become visible in id
order: on PostgreSQL every writer takes a global transaction lock (:data:`_ORDER_LOCK_KEY`) before
it allocates its id and holds it until its commit (SQLite serialises writers anyway). Callers
therefore call :func:`write_tile_version` last in their transaction, once per transaction, and
commit at once.

All functions are keyword-only and work in the caller's session and transaction.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
import orjson
import shapely
from shapely.geometry import box, mapping
from shapely.geometry.base import BaseGeometry
from sqlalchemy import Text, func, insert, select, text, type_coerce
from sqlalchemy.orm import Session

from services.db.models import MapFeatureRow, TileHead, TileVersion, utcnow

LIVE_STATUSES = ("published", "approved")
CHANGE_TYPES = ("added", "modified", "unchanged", "removed")
# A feature whose geometry moved by at most this much (Hausdorff distance) is unchanged: ~1 mm
# above the storage quantum (coordinates are kept to 1e-8 degrees, 1.1 mm of latitude; new
# geometries are compared as they will be stored, so write and diff agree).
GEOMETRY_TOLERANCE_M = 1.5e-3
STORED_DECIMALS = 8
# Coordinates in GeoJSON answers: 1e-7 degrees (1.1 cm of latitude), well under the map's accuracy.
GEOJSON_DECIMALS = 7
_M_PER_DEG_LAT = 111_320.0
# Global advisory lock that orders id allocation with commits (PostgreSQL): any constant
# distinct from the migration lock (0x435352) and from the tile lock hashes (which are 62-bit).
_ORDER_LOCK_KEY = -0x43535256


@dataclass(frozen=True, slots=True)
class VersionFeature:
    feature_id: str  # stable across versions
    type: str  # contract element type: lane_divider, road_boundary, centerline, stop_line, crosswalk, road_marking
    style: str | None
    properties: dict  # JSON-able
    geometry: BaseGeometry  # shapely LineString / Polygon, lon/lat degrees (EPSG:4326)


@dataclass(frozen=True, slots=True)
class MapFeature:
    """A feature as read from one tile version (what the read side serves)."""

    feature: VersionFeature
    tile_version_id: int  # the map version that made the row
    z: int
    x: int
    y: int
    version: int  # the tile's version


class VersionConflict(Exception):
    """The expected version is not the tile's latest (OSM API's 409)."""

    def __init__(self, *, z: int, x: int, y: int, expected: int | None, latest: int | None):
        super().__init__(f"tile {z}/{x}/{y}: expected latest version {expected}, but the latest is {latest}")
        self.expected, self.latest = expected, latest


class VersionNotFound(LookupError):
    """A tile version that does not exist."""


class InvalidVersionAction(ValueError):
    """A rollback or approval that the version's status does not allow."""


# --- locks and reads -----------------------------------------------------------------------------


def _tile_lock_key(z: int, x: int, y: int) -> int:
    digest = hashlib.blake2b(f"csr-tile:{z}/{x}/{y}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") >> 2  # 62 bits: positive, never the order lock


def _is_postgres(session: Session) -> bool:
    return session.get_bind().dialect.name == "postgresql"


def _lock_tile(session: Session, *, z: int, x: int, y: int) -> None:
    if _is_postgres(session):
        session.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _tile_lock_key(z, x, y)})


def tile_head(session: Session, *, z: int, x: int, y: int) -> TileHead | None:
    return session.execute(
        select(TileHead).where(TileHead.z == z, TileHead.x == x, TileHead.y == y),
        execution_options={"populate_existing": True},
    ).scalar_one_or_none()


def has_version(session: Session, *, z: int, x: int, y: int) -> bool:
    """Whether the tile has any version (without loading one: a version row holds the topology state)."""
    return (
        session.scalar(
            select(TileVersion.id).where(TileVersion.z == z, TileVersion.x == x, TileVersion.y == y).limit(1)
        )
        is not None
    )


def latest_version(session: Session, *, z: int, x: int, y: int) -> TileVersion | None:
    return session.execute(
        select(TileVersion)
        .where(TileVersion.z == z, TileVersion.x == x, TileVersion.y == y)
        .order_by(TileVersion.version.desc())
        .limit(1)
    ).scalar_one_or_none()


def get_version(session: Session, *, z: int, x: int, y: int, version: int) -> TileVersion | None:
    return session.execute(
        select(TileVersion).where(
            TileVersion.z == z, TileVersion.x == x, TileVersion.y == y, TileVersion.version == version
        )
    ).scalar_one_or_none()


def tile_versions(session: Session, *, z: int, x: int, y: int) -> list[TileVersion]:
    """The tile's history, oldest first."""
    return list(
        session.execute(
            select(TileVersion)
            .where(TileVersion.z == z, TileVersion.x == x, TileVersion.y == y)
            .order_by(TileVersion.version)
        ).scalars()
    )


def current_map_version(session: Session) -> int:
    """The newest map version (0 for an empty map)."""
    return int(session.execute(select(func.coalesce(func.max(TileVersion.id), 0))).scalar_one())


def as_feature(row: MapFeatureRow) -> VersionFeature:
    return VersionFeature(
        feature_id=row.feature_id,
        type=row.type,
        style=row.style,
        properties=dict(row.properties or {}),
        geometry=row.geom,  # type: ignore[arg-type]
    )


def version_features(
    session: Session, *, tile_version_id: int, include_removed: bool = False
) -> list[VersionFeature]:
    """The features of one version (by its global id), ordered by feature id; removed rows
    (keeping the last geometry) only with ``include_removed``."""
    return [as_feature(row) for row in version_rows(session, tile_version_id, include_removed)]


def version_rows(session: Session, tile_version_id: int, include_removed: bool) -> list[MapFeatureRow]:
    query = select(MapFeatureRow).where(MapFeatureRow.tile_version_id == tile_version_id)
    if not include_removed:
        query = query.where(MapFeatureRow.change != "removed")
    return list(session.execute(query.order_by(MapFeatureRow.feature_id)).scalars())


# --- change detection ---------------------------------------------------------------------------


def _metric(geometry: BaseGeometry, lat_deg: float) -> BaseGeometry:
    """lon/lat degrees -> an equirectangular plane in metres around ``lat_deg`` (enough for mm tests)."""
    kx = _M_PER_DEG_LAT * math.cos(math.radians(lat_deg))
    return shapely.transform(geometry, lambda c: c * [kx, _M_PER_DEG_LAT])


def geometry_changed(
    old: BaseGeometry, new: BaseGeometry, *, tolerance_m: float = GEOMETRY_TOLERANCE_M
) -> bool:
    if old.geom_type != new.geom_type or old.is_empty != new.is_empty:
        return True
    if old.is_empty:
        return False
    lat = new.centroid.y
    return bool(shapely.hausdorff_distance(_metric(old, lat), _metric(new, lat)) > tolerance_m)


def as_stored(feature: VersionFeature) -> VersionFeature:
    """The feature with its coordinates rounded as the database keeps them."""
    geometry = shapely.transform(feature.geometry, lambda c: np.round(c, STORED_DECIMALS))
    return VersionFeature(feature.feature_id, feature.type, feature.style, feature.properties, geometry)


def change_type(old: VersionFeature | None, new: VersionFeature) -> str:
    """``added`` / ``modified`` (type, style or geometry beyond ~1 mm) / ``unchanged``."""
    if old is None:
        return "added"
    if old.type != new.type or old.style != new.style or geometry_changed(old.geometry, new.geometry):
        return "modified"
    return "unchanged"


# --- writes -------------------------------------------------------------------------------------


def write_tile_version(
    session: Session,
    *,
    z: int,
    x: int,
    y: int,
    features: Sequence[VersionFeature],
    reason: str,
    job_id: str | None,
    trips: Sequence[str],
    corrections: Sequence[str],
    quality: dict,
    origin_lat: float,
    origin_lon: float,
    state: bytes | None,
    publish: bool,
    expected_latest: int | None,
    status: str | None = None,
) -> TileVersion:
    """Append a version of tile z/x/y in the caller's transaction (see the module docstring).

    Locks the tile, compares ``expected_latest`` with the tile's latest version (``None``: the tile
    has none yet) and raises :class:`VersionConflict` when they differ. Change types are against the
    tile's *live* version; live features missing from ``features`` get a ``removed`` row keeping
    their last geometry. ``publish``: the version goes live (status ``published``, or ``status`` if
    given, e.g. ``approved``); otherwise it is a ``candidate``."""
    ids = [f.feature_id for f in features]
    if len(set(ids)) != len(ids):
        raise ValueError(f"tile {z}/{x}/{y}: duplicate feature ids in one version")
    _lock_tile(session, z=z, x=x, y=y)
    head = tile_head(session, z=z, x=x, y=y)
    latest = head.latest_version if head is not None else None
    if latest != expected_latest:
        raise VersionConflict(z=z, x=x, y=y, expected=expected_latest, latest=latest)

    live: dict[str, VersionFeature] = {}
    if head is not None and head.live_version_id is not None:
        live = {f.feature_id: f for f in version_features(session, tile_version_id=head.live_version_id)}
    rows: list[tuple[VersionFeature, str]] = [
        (f, change_type(live.get(f.feature_id), as_stored(f))) for f in features
    ]
    kept = set(ids)
    rows += [(old, "removed") for fid, old in sorted(live.items()) if fid not in kept]
    counts = dict.fromkeys(CHANGE_TYPES, 0)
    for _, change in rows:
        counts[change] += 1

    if _is_postgres(session):
        session.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _ORDER_LOCK_KEY})
    number = (latest or 0) + 1
    version = TileVersion(
        z=z,
        x=x,
        y=y,
        version=number,
        status=(status or "published") if publish else "candidate",
        job_id=job_id,
        parent_version=latest,
        reason=reason,
        trips=list(trips),
        corrections=list(corrections),
        quality=dict(quality),
        changes=counts,
        n_features=len(features),
        origin_lat=float(origin_lat),
        origin_lon=float(origin_lon),
        state=state,
        created_at=utcnow(),
    )
    session.add(version)
    session.flush()
    if rows:
        session.execute(
            insert(MapFeatureRow),
            [
                {
                    "tile_version_id": version.id,
                    "feature_id": f.feature_id,
                    "type": f.type,
                    "style": f.style,
                    "change": change,
                    "properties": f.properties,
                    "geom": f.geometry,
                }
                for f, change in rows
            ],
        )
    now = utcnow()
    old_live_id = head.live_version_id if head is not None else None
    if head is None:
        head = TileHead(z=z, x=x, y=y, latest_version=number, updated_at=now)
        session.add(head)
    head.latest_version, head.updated_at = number, now
    if publish:
        head.live_version, head.live_version_id = number, version.id
    session.flush()
    # The version's extent and, when it went live, the rendered tiles it changed: in this
    # transaction, so a version and its tile bytes appear together (docs/tiles.md).
    from services.tiles import signals, store  # they import this module

    store.after_write(session, version=version, features=features, old_live_id=old_live_id, published=publish)
    signals.tiles_written(session)
    if _is_postgres(session):  # the API processes drop their cached ETags at the commit
        session.execute(text("SELECT pg_notify('csr_tiles', :tile)"), {"tile": f"{z}/{x}/{y}"})
    return version


def _republish(
    session: Session, *, z: int, x: int, y: int, source: TileVersion, reason: str, status: str, review: dict
) -> TileVersion:
    head = tile_head(session, z=z, x=x, y=y)
    return write_tile_version(
        session,
        z=z,
        x=x,
        y=y,
        features=version_features(session, tile_version_id=source.id),
        reason=reason,
        job_id=None,
        trips=source.trips,
        corrections=source.corrections,
        quality={**(source.quality or {}), "review": review},
        origin_lat=source.origin_lat,
        origin_lon=source.origin_lon,
        state=source.state,
        publish=True,
        expected_latest=head.latest_version if head is not None else None,
        status=status,
    )


def rollback(
    session: Session,
    *,
    z: int,
    x: int,
    y: int,
    to_version: int,
    author: str,
    expected_latest: int | None = None,
) -> TileVersion:
    """Publish an old (once live) version's features and state as a new version, reason
    ``rollback to vN``. ``expected_latest``: the caller's view of the latest version (checked)."""
    source = get_version(session, z=z, x=x, y=y, version=to_version)
    if source is None:
        raise VersionNotFound(f"tile {z}/{x}/{y} has no version {to_version}")
    if source.status not in LIVE_STATUSES:
        raise InvalidVersionAction(
            f"tile {z}/{x}/{y} v{to_version} is a {source.status} that never went live: approve it instead"
        )
    _check_expected(session, z=z, x=x, y=y, expected_latest=expected_latest)
    review = {"action": "rollback", "by": author, "of_version": to_version}
    return _republish(
        session,
        z=z,
        x=x,
        y=y,
        source=source,
        reason=f"rollback to v{to_version}",
        status="published",
        review=review,
    )


def approve(
    session: Session, *, z: int, x: int, y: int, version: int, author: str, expected_latest: int | None = None
) -> TileVersion:
    """A candidate goes live, as a new version with status ``approved`` and reason ``approve vN``
    (the candidate row stays a candidate, so the map at any earlier version stays as it was)."""
    source = get_version(session, z=z, x=x, y=y, version=version)
    if source is None:
        raise VersionNotFound(f"tile {z}/{x}/{y} has no version {version}")
    if source.status != "candidate":
        raise InvalidVersionAction(f"tile {z}/{x}/{y} v{version} is {source.status}, not a candidate")
    _check_expected(session, z=z, x=x, y=y, expected_latest=expected_latest)
    review = {"action": "approve", "by": author, "of_version": version}
    return _republish(
        session, z=z, x=x, y=y, source=source, reason=f"approve v{version}", status="approved", review=review
    )


def _check_expected(session: Session, *, z: int, x: int, y: int, expected_latest: int | None) -> None:
    if expected_latest is None:
        return
    _lock_tile(session, z=z, x=x, y=y)
    head = tile_head(session, z=z, x=x, y=y)
    latest = head.latest_version if head is not None else None
    if latest != expected_latest:
        raise VersionConflict(z=z, x=x, y=y, expected=expected_latest, latest=latest)


# --- the map: live or at a map version -----------------------------------------------------------


def tile_bounds_lonlat(z: int, x: int, y: int) -> tuple[float, float, float, float]:
    """(west, south, east, north) of a web-mercator XYZ tile."""
    n = 2.0**z

    def lat(row: float) -> float:
        return math.degrees(math.atan(math.sinh(math.pi * (1.0 - 2.0 * row / n))))

    return (x / n * 360.0 - 180.0, lat(y + 1), (x + 1) / n * 360.0 - 180.0, lat(y))


def _tile_range(z: int, bbox: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
    """x0, y0, x1, y1 (inclusive) of the zoom-z tiles overlapping ``bbox``, one tile of margin
    (features of a tile may reach a little past its edge)."""
    n = 2**z
    west, south, east, north = bbox

    def col(lon: float) -> int:
        return int(math.floor((lon + 180.0) / 360.0 * n))

    def row(lat: float) -> int:
        lat = max(min(lat, 85.0511287798), -85.0511287798)
        s = math.log(math.tan(math.pi / 4 + math.radians(lat) / 2))
        return int(math.floor((1.0 - s / math.pi) / 2.0 * n))

    return (
        max(col(west) - 1, 0),
        max(row(north) - 1, 0),
        min(col(east) + 1, n - 1),
        min(row(south) + 1, n - 1),
    )


def contributing_versions(
    session: Session, *, bbox_lonlat: tuple[float, float, float, float], map_version: int | None = None
) -> list[tuple[int, int, int, int, int]]:
    """``(z, x, y, version, tile_version_id)`` of the tile versions that make the map (live, or at
    ``map_version``) near ``bbox_lonlat``, sorted: the identity of a tile's content (its ETag)."""
    out: list[tuple[int, int, int, int, int]] = []
    zooms = session.execute(select(TileHead.z).distinct()).scalars().all()
    for z in sorted(zooms):
        x0, y0, x1, y1 = _tile_range(z, bbox_lonlat)
        if map_version is None:
            query = select(
                TileHead.z, TileHead.x, TileHead.y, TileHead.live_version, TileHead.live_version_id
            ).where(
                TileHead.z == z,
                TileHead.x.between(x0, x1),
                TileHead.y.between(y0, y1),
                TileHead.live_version_id.is_not(None),
            )
            out += [tuple(r) for r in session.execute(query)]  # type: ignore[misc]
            continue
        newest = (
            select(TileVersion.x, TileVersion.y, func.max(TileVersion.id).label("vid"))
            .where(
                TileVersion.z == z,
                TileVersion.x.between(x0, x1),
                TileVersion.y.between(y0, y1),
                TileVersion.status.in_(LIVE_STATUSES),
                TileVersion.id <= map_version,
            )
            .group_by(TileVersion.x, TileVersion.y)
            .subquery()
        )
        query = select(TileVersion.z, TileVersion.x, TileVersion.y, TileVersion.version, TileVersion.id).join(
            newest, TileVersion.id == newest.c.vid
        )
        out += [tuple(r) for r in session.execute(query)]  # type: ignore[misc]
    return sorted(out)


def map_features(
    session: Session,
    *,
    bbox_lonlat: tuple[float, float, float, float],
    versions: Sequence[tuple[int, int, int, int, int]],
) -> list[MapFeature]:
    """The features of ``versions`` (see :func:`contributing_versions`) intersecting the bbox,
    ordered by feature id (removed rows excluded). PostgreSQL filters with the GiST index; on
    SQLite the geometries are parsed and tested in one vectorized shapely call, and only the kept
    rows' properties are decoded."""
    if not versions:
        return []
    by_id = {vid: (z, x, y, v) for z, x, y, v, vid in versions}
    west, south, east, north = bbox_lonlat
    table = MapFeatureRow.__table__
    raw_geom = type_coerce(table.c.geom, Text) if not _is_postgres(session) else table.c.geom
    query = (
        select(
            table.c.tile_version_id,
            table.c.feature_id,
            table.c.type,
            table.c.style,
            type_coerce(table.c.properties, Text),
            raw_geom,
        )
        .where(table.c.tile_version_id.in_(list(by_id)), table.c.change != "removed")
        .order_by(table.c.feature_id, table.c.tile_version_id)
    )
    if _is_postgres(session):
        envelope = func.ST_MakeEnvelope(west, south, east, north, 4326)
        query = query.where(func.ST_Intersects(table.c.geom, envelope))
    rows = session.execute(query).all()
    if not rows:
        return []
    if _is_postgres(session):
        geoms = [r[5] for r in rows]  # parsed by FeatureGeometry
        keep = np.ones(len(rows), dtype=bool)
    else:
        geoms = shapely.from_wkt([r[5].split(";", 1)[1] for r in rows])
        keep = shapely.intersects(geoms, box(west, south, east, north))
    out = []
    for row, geom, kept in zip(rows, geoms, keep, strict=True):
        if not kept:
            continue
        vid, fid, type_, style, props, _ = row
        properties = orjson.loads(props) if isinstance(props, str | bytes) else dict(props or {})
        z, x, y, v = by_id[vid]
        out.append(MapFeature(VersionFeature(fid, type_, style, properties, geom), vid, z, x, y, v))
    return out


def features_in_bbox(
    session: Session, *, bbox_lonlat: tuple[float, float, float, float], map_version: int | None = None
) -> list[VersionFeature]:
    """The live map (or: per tile, the newest published/approved version with id <= map_version),
    features intersecting ``bbox_lonlat`` (west, south, east, north degrees)."""
    versions = contributing_versions(session, bbox_lonlat=bbox_lonlat, map_version=map_version)
    return [f.feature for f in map_features(session, bbox_lonlat=bbox_lonlat, versions=versions)]


# --- history ------------------------------------------------------------------------------------


def geometry_json(geometry: BaseGeometry) -> dict[str, Any]:
    """GeoJSON geometry with coordinates rounded to :data:`GEOJSON_DECIMALS`."""
    rounded = shapely.transform(geometry, lambda c: np.round(c, GEOJSON_DECIMALS))
    return mapping(rounded)  # type: ignore[return-value]


def diff(session: Session, *, z: int, x: int, y: int, from_version: int, to_version: int) -> dict:
    """Per feature id between two versions of a tile: ``added`` / ``removed`` / ``modified``
    (with geometries; ``modified`` has ``before`` and ``after``) and the ``unchanged`` count."""
    versions = {}
    for v in (from_version, to_version):
        row = get_version(session, z=z, x=x, y=y, version=v)
        if row is None:
            raise VersionNotFound(f"tile {z}/{x}/{y} has no version {v}")
        versions[v] = {f.feature_id: f for f in version_features(session, tile_version_id=row.id)}
    old, new = versions[from_version], versions[to_version]

    def brief(f: VersionFeature) -> dict:
        return {"id": f.feature_id, "type": f.type, "style": f.style, "geometry": geometry_json(f.geometry)}

    added = [brief(new[i]) for i in sorted(new.keys() - old.keys())]
    removed = [brief(old[i]) for i in sorted(old.keys() - new.keys())]
    modified, unchanged = [], 0
    for i in sorted(old.keys() & new.keys()):
        if change_type(old[i], new[i]) == "modified":
            modified.append({"id": i, "before": brief(old[i]), "after": brief(new[i])})
        else:
            unchanged += 1
    return {
        "tile": f"{z}/{x}/{y}",
        "from": from_version,
        "to": to_version,
        "added": added,
        "removed": removed,
        "modified": modified,
        "unchanged": unchanged,
    }


def version_summary(version: TileVersion) -> dict[str, Any]:
    return {
        "tile": f"{version.z}/{version.x}/{version.y}",
        "version": version.version,
        "map_version": version.id,
        "status": version.status,
        "reason": version.reason,
        "job_id": version.job_id,
        "parent_version": version.parent_version,
        "trips": list(version.trips or []),
        "corrections": list(version.corrections or []),
        "quality": version.quality,
        "changes": version.changes,
        "n_features": version.n_features,
        "created_at": iso_utc(version.created_at),
    }


def iso_utc(moment: datetime) -> str:
    """ISO 8601 with the UTC offset (SQLite gives naive datetimes back)."""
    return (moment if moment.tzinfo else moment.replace(tzinfo=UTC)).isoformat()


def changes_since(session: Session, *, since_map_version: int, limit: int) -> list[dict]:
    """The changes feed: versions with map version > ``since_map_version``, oldest first (newest
    last), at most ``limit``; each with its changed features (``{"id", "change"}``, unchanged
    omitted). The next cursor is the last entry's ``map_version``."""
    versions = list(
        session.execute(
            select(TileVersion)
            .where(TileVersion.id > since_map_version)
            .order_by(TileVersion.id)
            .limit(limit)
        ).scalars()
    )
    changed: dict[int, list[dict]] = {v.id: [] for v in versions}
    if versions:
        rows = session.execute(
            select(MapFeatureRow.tile_version_id, MapFeatureRow.feature_id, MapFeatureRow.change)
            .where(MapFeatureRow.tile_version_id.in_(list(changed)), MapFeatureRow.change != "unchanged")
            .order_by(MapFeatureRow.tile_version_id, MapFeatureRow.feature_id)
        )
        for vid, fid, change in rows:
            changed[vid].append({"id": fid, "change": change})
    out = []
    for v in versions:
        entry = version_summary(v)
        entry["live"] = v.status in LIVE_STATUSES
        entry["features"] = changed[v.id]
        out.append(entry)
    return out


def feature_history(session: Session, *, feature_id: str) -> list[tuple[MapFeatureRow, TileVersion]]:
    """Every row of one feature across versions, oldest first."""
    return [
        (row, version)
        for row, version in session.execute(
            select(MapFeatureRow, TileVersion)
            .join(TileVersion, TileVersion.id == MapFeatureRow.tile_version_id)
            .where(MapFeatureRow.feature_id == feature_id)
            .order_by(TileVersion.id)
        ).all()
    ]
