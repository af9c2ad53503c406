"""Rendered tiles kept in the database, once per content, so that a cold read is a primary-key
lookup instead of an encoding.

A tile's content is fixed by the versions that *reach* it: the live (or pinned) versions of the
pipeline tiles near it whose feature extent (``tile_version_extents``) meets the tile's buffered
bounds. Their ``(z, x, y, version, id)`` tuples, the format, the encoder and the encoding version
hash to the strong ETag (``render.make_etag``), and the ETag is the key of ``tile_renders``.

:func:`after_write` runs inside ``versions.write_tile_version`` (same transaction): it records the
new version's extent and, when the version is published, renders the pipeline-zoom tiles whose
content it changes (the tile itself and the neighbours its old or new features reach), so a tile
version and its bytes become visible together. Any other tile (other zooms, pinned old versions)
is rendered on its first read and stored by :func:`store`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence

import shapely
from sqlalchemy import bindparam, delete, select, text
from sqlalchemy.orm import Session

from services.db import versions as vs
from services.db.models import TileRender, TileVersionExtent, utcnow
from services.tiles import mvt
from services.tiles.mercator import MAX_ZOOM, buffered_bounds_lonlat

log = logging.getLogger(__name__)

# Extents are compared with this slack (degrees, ~1 mm): the tile envelope of PostGIS and ours
# differ in the last bits.
_EXTENT_EPS_DEG = 1e-8

Bounds = tuple[float, float, float, float]


# --- extents --------------------------------------------------------------------------------------


def features_extent(features: Iterable[vs.VersionFeature]) -> Bounds | None:
    geoms = [f.geometry for f in features]
    if not geoms:
        return None
    west, south, east, north = shapely.total_bounds(geoms)
    return float(west), float(south), float(east), float(north)


def extents(session: Session, version_ids: Sequence[int]) -> dict[int, Bounds | None]:
    """``tile_version_id -> extent`` (``None``: no features) for the versions that have a row."""
    if not version_ids:
        return {}
    t = TileVersionExtent
    rows = session.execute(
        select(t.tile_version_id, t.west, t.south, t.east, t.north).where(
            t.tile_version_id.in_(list(version_ids))
        )
    )
    return {
        vid: (None if w is None or s is None or e is None or n is None else (w, s, e, n))
        for vid, w, s, e, n in rows
    }


def _meets(extent: Bounds, bounds: Bounds) -> bool:
    eps = _EXTENT_EPS_DEG
    return not (
        extent[2] < bounds[0] - eps
        or extent[0] > bounds[2] + eps
        or extent[3] < bounds[1] - eps
        or extent[1] > bounds[3] + eps
    )


def reaching_versions(
    session: Session, *, z: int, x: int, y: int, map_version: int | None
) -> list[tuple[int, int, int, int, int]]:
    """``(z, x, y, version, id)`` of the live (or pinned) versions whose features can appear in tile
    z/x/y: those near it (``versions.contributing_versions``) whose extent meets its buffered
    bounds, or that have no recorded extent."""
    bounds = buffered_bounds_lonlat(z, x, y, buffer_frac=mvt.BUFFER_FRAC)
    near = vs.contributing_versions(session, bbox_lonlat=bounds, map_version=map_version)
    known = extents(session, [v[-1] for v in near])
    out = []
    for v in near:
        vid = v[-1]
        if vid not in known:
            out.append(v)  # written before extents were recorded: assume it reaches
        elif known[vid] is not None and _meets(known[vid], bounds):  # type: ignore[arg-type]
            out.append(v)
    return out


# --- stored renders -------------------------------------------------------------------------------


def lookup(session: Session, etag: str) -> tuple[bool, bytes | None]:
    row = session.execute(select(TileRender.body).where(TileRender.etag == etag)).first()
    if row is None:
        return False, None
    return True, (bytes(row[0]) if row[0] is not None else None)


_INSERT = text(
    "INSERT INTO tile_renders (etag, kind, z, x, y, body, created_at) "
    "VALUES (:etag, :kind, :z, :x, :y, :body, :created_at) ON CONFLICT (etag) DO NOTHING"
).bindparams(bindparam("body", type_=TileRender.__table__.c.body.type))


def store(session: Session, *, etag: str, kind: str, z: int, x: int, y: int, body: bytes | None) -> None:
    """Keep a render (a no-op when another process stored the same content first)."""
    session.execute(
        _INSERT, {"etag": etag, "kind": kind, "z": z, "x": x, "y": y, "body": body, "created_at": utcnow()}
    )


# --- at publish time ------------------------------------------------------------------------------


def _tiles_meeting(z: int, x: int, y: int, extent: Bounds | None) -> set[tuple[int, int]]:
    """The zoom-z tiles of the 3x3 block around x/y whose buffered bounds meet ``extent``
    (``None``: unknown, all nine)."""
    out = set()
    n = 2**z
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            tx, ty = x + dx, y + dy
            if not (0 <= tx < n and 0 <= ty < n):
                continue
            bounds = buffered_bounds_lonlat(z, tx, ty, buffer_frac=mvt.BUFFER_FRAC)
            if extent is None or _meets(extent, bounds):
                out.add((tx, ty))
    return out


def _drop_superseded(session: Session, tiles: set[tuple[int, int]], z: int) -> None:
    """Forget the stored renders of every zoom that overlap the changed pipeline tiles: their
    content may have changed (a pinned URL of an older map version renders again on read)."""
    xs, ys = [t[0] for t in tiles], [t[1] for t in tiles]
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    r = TileRender
    for zoom in range(MAX_ZOOM + 1):
        shift = zoom - z
        if shift >= 0:
            lo_x, hi_x = x0 << shift, ((x1 + 1) << shift) - 1
            lo_y, hi_y = y0 << shift, ((y1 + 1) << shift) - 1
        else:
            lo_x, hi_x, lo_y, hi_y = x0 >> -shift, x1 >> -shift, y0 >> -shift, y1 >> -shift
        session.execute(delete(r).where(r.z == zoom, r.x.between(lo_x, hi_x), r.y.between(lo_y, hi_y)))


def after_write(
    session: Session,
    *,
    version: object,  # services.db.models.TileVersion, flushed
    features: Sequence[vs.VersionFeature],
    old_live_id: int | None,
    published: bool,
) -> None:
    """Record the new version's extent; when it went live, render (in this transaction) the
    pipeline-zoom tiles whose content it changed and drop their superseded renders."""
    from services.tiles import render  # render imports this module

    z, x, y = version.z, version.x, version.y  # type: ignore[attr-defined]
    extent = features_extent(features)
    session.add(
        TileVersionExtent(
            tile_version_id=version.id,  # type: ignore[attr-defined]
            **dict(zip(("west", "south", "east", "north"), extent or (None,) * 4, strict=True)),
        )
    )
    session.flush()
    if not published:
        return
    changed = _tiles_meeting(z, x, y, extent) | {(x, y)}
    if old_live_id is not None:  # where the features it replaced were
        old = extents(session, [old_live_id])
        if old_live_id not in old:
            changed |= _tiles_meeting(z, x, y, None)
        elif old[old_live_id] is not None:
            changed |= _tiles_meeting(z, x, y, old[old_live_id])
    _drop_superseded(session, changed, z)
    backend = render.backend_of(session)
    for tx, ty in sorted(changed):
        versions = reaching_versions(session, z=z, x=tx, y=ty, map_version=None)
        etag = render.make_etag("mvt", z, tx, ty, versions, backend)
        body = render.encode_tile(session, z=z, x=tx, y=ty, versions=versions, backend=backend)
        store(session, etag=etag, kind="mvt", z=z, x=tx, y=ty, body=body)
