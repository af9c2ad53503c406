"""The accuracy certificate of a tile (``GET /v1/tiles/{z}/{x}/{y}/certificate``) and of the whole
map (TileJSON's ``certificate``): what the served features promise about their absolute and
relative lateral error (``csr_core.topology.absolute_uncertainty.tile_certificate``).

The elements of a tile are the features of the versions reaching it (as the tile routes serve
them), each cut to the tile's bounds and weighted by its geodesic length there (pyproj's
``Geod.geometry_length``; a polygon by its outline). The trips behind it are the distinct trips
merged into those versions and their predecessors (``TileVersion.trips``)."""

from __future__ import annotations

from collections.abc import Sequence

import shapely
from pyproj import Geod
from sqlalchemy import select
from sqlalchemy.orm import Session

from csr_core.topology.absolute_uncertainty import SIGMA_ABS_PROPERTY, TileCertificate, tile_certificate
from services.db import versions as vs
from services.db.models import TileHead, TileVersion
from services.tiles import store

_GEOD = Geod(ellps="WGS84")


def _number(value: object, default: float) -> float:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else default


def certificate_of(
    features: Sequence[vs.MapFeature],
    bounds_lonlat: tuple[float, float, float, float],
    trips: int,
    target_m: float,
) -> TileCertificate:
    """The certificate of ``features`` cut to ``bounds_lonlat`` (west, south, east, north)."""
    lengths, sigma_abs, sigma_rel, passes = [], [], [], []
    for f in features:
        props = f.feature.properties
        if SIGMA_ABS_PROPERTY not in props:
            continue  # written before the absolute sigma existed: it certifies nothing
        part = shapely.clip_by_rect(f.feature.geometry, *bounds_lonlat)
        if part.is_empty:
            continue
        outline = part.exterior if isinstance(part, shapely.Polygon) else part
        lengths.append(_GEOD.geometry_length(outline))
        sigma_abs.append(_number(props[SIGMA_ABS_PROPERTY], 0.0))
        sigma_rel.append(_number(props.get("uncertainty_m"), 0.0))
        passes.append(int(_number(props.get("support_trips"), 1.0)))
    return tile_certificate(lengths, sigma_abs, sigma_rel, passes, trips=trips, target_m=target_m)


def trips_behind(session: Session, reaching: Sequence[tuple[int, int, int, int, int]]) -> int:
    """Distinct trips merged into the tile versions ``reaching`` ((z, x, y, version, id)) or any
    earlier version of their tiles."""
    trips: set[str] = set()
    for z, x, y, version, _ in reaching:
        rows = session.scalars(
            select(TileVersion.trips).where(
                TileVersion.z == z, TileVersion.x == x, TileVersion.y == y, TileVersion.version <= version
            )
        ).all()
        trips.update(str(t) for row in rows for t in (row or ()))
    return len(trips)


def tile_certificate_at(
    session: Session, *, z: int, x: int, y: int, map_version: int | None, target_m: float
) -> TileCertificate:
    """The certificate of tile z/x/y, live or at ``map_version``."""
    bounds = vs.tile_bounds_lonlat(z, x, y)
    reaching = store.reaching_versions(session, z=z, x=x, y=y, map_version=map_version)
    features = vs.map_features(session, bbox_lonlat=bounds, versions=reaching)
    inside = [
        v
        for v in reaching
        if any(f.feature.feature_id.startswith(f"{v[0]}-{v[1]}-{v[2]}-") for f in features)
    ]
    return certificate_of(features, bounds, trips_behind(session, inside), target_m)


def map_certificate(session: Session, *, target_m: float) -> TileCertificate:
    """The certificate of every live tile together (TileJSON's summary)."""
    heads = session.execute(
        select(TileHead.z, TileHead.x, TileHead.y, TileHead.live_version, TileHead.live_version_id).where(
            TileHead.live_version_id.is_not(None)
        )
    ).all()
    reaching = [(int(z), int(x), int(y), int(v or 0), int(vid or 0)) for z, x, y, v, vid in heads]
    world = (-180.0, -90.0, 180.0, 90.0)
    features = vs.map_features(session, bbox_lonlat=world, versions=reaching)
    return certificate_of(features, world, trips_behind(session, reaching), target_m)
