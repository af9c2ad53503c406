"""Mapbox Vector Tiles of the road structure: one layer ``road``, one feature per map element with
the properties ``id`` (the stable feature id), ``type`` (the contract element type), ``style``
(when set), the element's scalar properties and its validator ``flags`` as JSON text (other nested
values are left out). Extent 4096, buffer
256 (1/16 of the tile); the MVT feature id is a 48-bit hash of the feature id (stable across
versions, exact in JavaScript numbers).

Two encoders give the same features (tested): :func:`encode_sql` (``ST_AsMVT`` /
``ST_AsMVTGeom`` / ``ST_TileEnvelope`` in PostGIS) and :func:`encode_python` (mapbox_vector_tile,
for the embedded SQLite). The Python one follows what ``ST_AsMVTGeom`` does: drop vertices
closer than half a pixel and simplify (Douglas-Peucker, half a pixel), clip to the buffered tile,
snap to the integer grid (y down), drop what collapsed.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence

import mapbox_vector_tile
import numpy as np
import shapely
from shapely.geometry.base import BaseGeometry
from sqlalchemy import text
from sqlalchemy.orm import Session

from services.db.versions import MapFeature
from services.tiles.mercator import lonlat_to_m, tile_bounds_m

LAYER = "road"
EXTENT = 4096
BUFFER = 256
BUFFER_FRAC = BUFFER / EXTENT
RESERVED = ("id", "type", "style")
FLAGS = "flags"  # a list of flag kinds: carried as its JSON text
# Bump when the encoding changes: it is part of every ETag.
ENCODING_VERSION = "mvt-2"


def mvt_feature_id(feature_id: str) -> int:
    """The MVT (uint64) id of a feature: the first 48 bits of the MD5 of its id (as the SQL does)."""
    return int(hashlib.md5(feature_id.encode()).hexdigest()[:12], 16)


def scalar_properties(properties: dict) -> dict:
    """What of a feature's properties an MVT can carry: strings, booleans and finite numbers; and
    the validator's ``flags`` (a list) as its JSON text, ``'["gap", "low_support"]'``, when not
    empty (PostgreSQL's text of a jsonb array, which the SQL encoder gives)."""
    out = {}
    for key, value in properties.items():
        if key in RESERVED or value is None:
            continue
        if isinstance(value, bool | str) or (isinstance(value, int | float) and math.isfinite(value)):
            out[key] = value
        elif key == FLAGS and isinstance(value, list) and value:
            out[key] = json.dumps(value)
    return out


def tile_properties(feature: MapFeature) -> dict:
    f = feature.feature
    props = {"id": f.feature_id, "type": f.type}
    if f.style is not None:
        props["style"] = f.style
    props.update(scalar_properties(f.properties))
    return props


# --- Python (embedded SQLite) ----------------------------------------------------------------------


def _to_tile_units(geometries: np.ndarray, z: int, x: int, y: int) -> np.ndarray:
    left, _, right, top = tile_bounds_m(z, x, y)
    scale = EXTENT / (right - left)

    def fn(lonlat: np.ndarray) -> np.ndarray:
        xy = lonlat_to_m(lonlat)
        return np.column_stack([(xy[:, 0] - left) * scale, (top - xy[:, 1]) * scale])

    return shapely.transform(geometries, fn)


def _grid(geometry: BaseGeometry) -> BaseGeometry | None:
    """Snap to integer tile units (round half to even, as PostGIS), drop repeated vertices and
    whatever collapsed; polygons made valid."""
    snapped = shapely.remove_repeated_points(shapely.transform(geometry, np.rint))
    if snapped.is_empty:
        return None
    if snapped.geom_type in ("Polygon", "MultiPolygon"):
        if not snapped.is_valid:
            snapped = shapely.make_valid(snapped)
        polys = [g for g in shapely.get_parts(snapped) if g.geom_type == "Polygon" and g.area > 0]
        if not polys:
            return None
        return polys[0] if len(polys) == 1 else shapely.MultiPolygon(polys)
    lines = [g for g in shapely.get_parts(snapped) if g.geom_type == "LineString" and g.length > 0]
    if not lines:
        return None
    return lines[0] if len(lines) == 1 else shapely.MultiLineString(lines)


def encode_python(features: Sequence[MapFeature], *, z: int, x: int, y: int) -> bytes | None:
    """The tile's MVT bytes, or ``None`` when nothing is left in it."""
    if not features:
        return None
    geoms = np.array([f.feature.geometry for f in features], dtype=object)
    geoms = _to_tile_units(geoms, z, x, y)
    geoms = shapely.remove_repeated_points(geoms, 0.5)
    geoms = shapely.simplify(geoms, 0.5, preserve_topology=False)
    lo, hi = -BUFFER - 0.5, EXTENT + BUFFER + 0.5
    geoms = shapely.clip_by_rect(geoms, lo, lo, hi, hi)
    out = []
    for feature, geom in zip(features, geoms, strict=True):
        if geom is None or geom.is_empty:
            continue
        gridded = _grid(geom)
        if gridded is None:
            continue
        out.append(
            {
                "geometry": gridded,
                "properties": tile_properties(feature),
                "id": mvt_feature_id(feature.feature.feature_id),
            }
        )
    if not out:
        return None
    return mapbox_vector_tile.encode(
        [{"name": LAYER, "features": out}],
        default_options={"y_coord_down": True, "extents": EXTENT},
    )


# --- PostGIS -----------------------------------------------------------------------------------------

_SQL = text(
    """
    SELECT ST_AsMVT(t, :layer, :extent, 'geom', 'mvt_id') FROM (
      SELECT ('x' || substr(md5(mf.feature_id), 1, 12))::bit(48)::bigint AS mvt_id,
             mf.feature_id AS id,
             mf.type AS type,
             mf.style AS style,
             (SELECT coalesce(jsonb_object_agg(p.key, p.value), '{}'::jsonb)
                FROM (SELECT e.key, e.value FROM jsonb_each(mf.properties::jsonb) AS e
                       WHERE jsonb_typeof(e.value) IN ('string', 'number', 'boolean')
                         AND e.key NOT IN ('id', 'type', 'style')
                      UNION ALL
                      SELECT 'flags', to_jsonb((mf.properties::jsonb -> 'flags')::text)
                       WHERE jsonb_typeof(mf.properties::jsonb -> 'flags') = 'array'
                         AND jsonb_array_length(mf.properties::jsonb -> 'flags') > 0) AS p) AS props,
             ST_AsMVTGeom(ST_Transform(mf.geom, 3857), ST_TileEnvelope(:z, :x, :y), :extent, :buffer, true)
               AS geom
        FROM map_features mf
       WHERE mf.tile_version_id = ANY(:ids)
         AND mf.change <> 'removed'
         AND mf.geom && ST_Transform(ST_TileEnvelope(:z, :x, :y, margin => :margin), 4326)
       ORDER BY mf.feature_id
    ) AS t
    WHERE t.geom IS NOT NULL
    """
)


def encode_sql(session: Session, *, z: int, x: int, y: int, tile_version_ids: Sequence[int]) -> bytes | None:
    """The tile's MVT bytes built by PostGIS from the features of ``tile_version_ids``, or ``None``."""
    if not tile_version_ids:
        return None
    body = session.execute(
        _SQL,
        {
            "layer": LAYER,
            "extent": EXTENT,
            "buffer": BUFFER,
            "margin": BUFFER_FRAC,
            "z": z,
            "x": x,
            "y": y,
            "ids": list(tile_version_ids),
        },
    ).scalar_one()
    return bytes(body) if body else None
