"""Tiles, GeoJSON and TileJSON from the version store, with their ETags and an in-process cache.

A tile's content is fixed by the tile versions that reach it (``store.reaching_versions``: the
live or pinned versions near it whose feature extent meets its buffered bounds), so its strong ETag
is a hash of those ``(z, x, y, version, id)`` tuples, the format, the encoder (PostGIS or Python)
and :data:`mvt.ENCODING_VERSION`. The body is looked up by ETag in the in-process LRU, then in
``tile_renders`` (rendered at publish time, or at the first read), and only then encoded (and
stored). A read encodes in a read-only transaction and stores the new body afterwards in a short
write of its own that never waits for the write lock (``render_then_keep``). The HTTP fast path
in front of FastAPI (``services.tiles.fastpath``) caches the ETag itself.
"""

from __future__ import annotations

import hashlib
import logging
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np
import orjson
import shapely
from shapely.geometry import shape
from sqlalchemy import func, select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from services.db import versions as vs
from services.db.engine import read_only, without_waiting
from services.db.models import MapFeatureRow, TileHead
from services.tiles import mvt, store
from services.tiles.flag_levels import flag_levels
from services.tiles.mercator import MAX_ZOOM, buffered_bounds_lonlat

log = logging.getLogger(__name__)

CACHE_MAX_BYTES = 64 * 1024 * 1024
CACHE_MAX_ENTRIES = 4096


class TileCache:
    """LRU of encoded tiles by ETag (bytes, or ``None`` for an empty tile); thread-safe."""

    def __init__(self, max_bytes: int = CACHE_MAX_BYTES, max_entries: int = CACHE_MAX_ENTRIES) -> None:
        self._items: OrderedDict[str, bytes | None] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.max_bytes, self.max_entries = max_bytes, max_entries

    def get(self, etag: str) -> tuple[bool, bytes | None]:
        with self._lock:
            if etag not in self._items:
                return False, None
            self._items.move_to_end(etag)
            return True, self._items[etag]

    def put(self, etag: str, body: bytes | None) -> None:
        size = len(body or b"")
        if size > self.max_bytes // 4:
            return
        with self._lock:
            if etag in self._items:
                return
            self._items[etag] = body
            self._bytes += size
            while self._bytes > self.max_bytes or len(self._items) > self.max_entries:
                _, old = self._items.popitem(last=False)
                self._bytes -= len(old or b"")

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0


class TileSource(str, Enum):
    """Where a tile answer came from (the metric ``csr_tile_requests_total{source}``)."""

    FAST_PATH = "fast_path"  # the fast path's caches: no database query, no thread hop
    NOT_MODIFIED = "not_modified"  # 304: the ETag was looked up, no body needed
    MEMORY = "memory"  # the ETag was looked up, the body was in the in-process LRU
    STORED = "stored"  # the body was in tile_renders
    ENCODED = "encoded"  # the body was encoded for this request (the only miss)


@dataclass(frozen=True, slots=True)
class Tile:
    body: bytes | None  # None: an empty tile (204)
    etag: str  # strong, quoted
    media_type: str
    encoded: bool = False  # encoded by this call (not found in a cache or in tile_renders)
    source: TileSource = TileSource.MEMORY


def make_etag(kind: str, z: int, x: int, y: int, versions: Sequence[tuple], backend: str) -> str:
    key = f"{kind}|{backend}|{mvt.ENCODING_VERSION}|{z}/{x}/{y}|" + ";".join(
        ",".join(map(str, v)) for v in versions
    )
    return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


def backend_of(session: Session) -> str:
    """The encoder of the deployment: ``postgis`` (ST_AsMVT) on PostgreSQL, ``python`` otherwise."""
    return "postgis" if session.get_bind().dialect.name == "postgresql" else "python"


def tile_versions_for(session: Session, *, z: int, x: int, y: int, map_version: int | None) -> list[tuple]:
    """The versions that make tile z/x/y (live, or at ``map_version``): its content's identity."""
    return store.reaching_versions(session, z=z, x=x, y=y, map_version=map_version)


def tile_etag(
    session: Session, *, kind: str, z: int, x: int, y: int, map_version: int | None
) -> tuple[str, list]:
    versions = tile_versions_for(session, z=z, x=x, y=y, map_version=map_version)
    return make_etag(kind, z, x, y, versions, backend_of(session)), versions


def encode_tile(
    session: Session, *, z: int, x: int, y: int, versions: Sequence[tuple], backend: str | None = None
) -> bytes | None:
    """MVT bytes of the tile from ``versions`` (PostGIS on PostgreSQL, Python otherwise, or as
    ``backend`` says: ``postgis`` | ``python``)."""
    backend = backend or backend_of(session)
    if backend == "postgis":
        return mvt.encode_sql(session, z=z, x=x, y=y, tile_version_ids=[v[-1] for v in versions])
    bounds = buffered_bounds_lonlat(z, x, y, buffer_frac=mvt.BUFFER_FRAC)
    features = vs.map_features(session, bbox_lonlat=bounds, versions=versions)
    return mvt.encode_python(features, z=z, x=x, y=y)


def feature_json(
    feature: vs.MapFeature | None, *, f: vs.VersionFeature | None = None, extra: dict | None = None
) -> dict:
    """A GeoJSON Feature as ``GET /v1/map`` gives it (contract section 3; like ``csr reconstruct``)."""
    f = f or feature.feature  # type: ignore[union-attr]
    props: dict[str, Any] = {"type": f.type, "id": f.feature_id}
    if f.style is not None:
        props["style"] = f.style
    if feature is not None:
        props["tile"] = f"{feature.z}/{feature.x}/{feature.y}"
        props["tile_version"] = feature.version
    if extra:
        props.update(extra)
    props.update({k: v for k, v in f.properties.items() if k not in props})
    return {
        "type": "Feature",
        "id": f.feature_id,
        "geometry": vs.geometry_json(f.geometry),
        "properties": props,
    }


def geojson_bbox(features: Sequence[dict]) -> list[float] | None:
    """RFC 7946 ``bbox`` ``[west, south, east, north]`` of the features' coordinates as written
    (``None`` without any coordinate)."""
    geometries = [shape(f["geometry"]) for f in features if f.get("geometry")]
    if not geometries:
        return None
    bounds = shapely.total_bounds(geometries)
    return [float(v) for v in bounds] if np.isfinite(bounds).all() else None


def feature_collection(features: Sequence[dict], **members: Any) -> bytes:
    """A FeatureCollection; its ``bbox`` is that of the features (left out when there is none)."""
    bbox = geojson_bbox(features)
    head: dict[str, Any] = {"type": "FeatureCollection"}
    if bbox is not None:
        head["bbox"] = bbox
    return orjson.dumps({**head, **members, "features": list(features)})


def render(
    session: Session,
    cache: TileCache,
    *,
    kind: str,
    z: int,
    x: int,
    y: int,
    map_version: int | None,
    if_none_match: str | None = None,
    pinned_etags: TileCache | None = None,
    store_renders: bool = True,
) -> tuple[Tile, bool]:
    """The tile (``kind``: ``mvt`` | ``geojson``) and whether ``if_none_match`` matched (304).
    ``pinned_etags`` remembers the ETag of a pinned tile (it never changes); a body that had to be
    encoded is kept in ``tile_renders`` (``store_renders``, in the caller's transaction)."""
    media = "application/vnd.mapbox-vector-tile" if kind == "mvt" else "application/geo+json"
    pin_key = f"{kind}|{z}/{x}/{y}|{map_version}"
    versions: list | None = None
    etag = None
    if map_version is not None and pinned_etags is not None:
        hit, raw = pinned_etags.get(pin_key)
        etag = raw.decode() if hit and raw else None
    if etag is None:
        etag, versions = tile_etag(session, kind=kind, z=z, x=x, y=y, map_version=map_version)
        if map_version is not None and pinned_etags is not None:
            pinned_etags.put(pin_key, etag.encode())
    if if_none_match and etag_matches(if_none_match, etag):
        return Tile(None, etag, media, source=TileSource.NOT_MODIFIED), True
    hit, body = cache.get(etag)
    source = TileSource.MEMORY
    if not hit:
        hit, body = store.lookup(session, etag)
        source = TileSource.STORED
    if not hit:
        if versions is None:
            versions = tile_versions_for(session, z=z, x=x, y=y, map_version=map_version)
        if kind == "mvt":
            body = encode_tile(session, z=z, x=x, y=y, versions=versions)
        else:
            bounds = buffered_bounds_lonlat(z, x, y, buffer_frac=mvt.BUFFER_FRAC)
            features = vs.map_features(session, bbox_lonlat=bounds, versions=versions)
            body = (
                feature_collection([feature_json(f) for f in features], tile=f"{z}/{x}/{y}")
                if features
                else None
            )
        if store_renders:
            store.store(session, etag=etag, kind=kind, z=z, x=x, y=y, body=body)
        cache.put(etag, body)
        return Tile(body, etag, media, encoded=True, source=TileSource.ENCODED), False
    cache.put(etag, body)
    return Tile(body, etag, media, source=source), False


def render_then_keep(
    session_factory: sessionmaker[Session],
    cache: TileCache,
    *,
    kind: str,
    z: int,
    x: int,
    y: int,
    **options: Any,
) -> tuple[Tile, bool]:
    """``render`` for a request: read in a read-only transaction (it never waits for a job's write),
    then keep a newly encoded body in ``tile_renders`` without waiting (``keep_render``)."""
    with read_only(session_factory)() as session, session.begin():
        tile, not_modified = render(session, cache, kind=kind, z=z, x=x, y=y, store_renders=False, **options)
    if tile.encoded:
        keep_render(session_factory, tile, kind=kind, z=z, x=x, y=y)
    return tile, not_modified


def keep_render(
    session_factory: sessionmaker[Session], tile: Tile, *, kind: str, z: int, x: int, y: int
) -> None:
    """Store an encoded tile if the write lock is free now; otherwise it stays in the in-process
    cache and a later read stores it (a stored render is an optimisation, never required)."""
    try:
        with without_waiting(session_factory).begin() as session:
            store.store(session, etag=tile.etag, kind=kind, z=z, x=x, y=y, body=tile.body)
    except OperationalError as exc:
        log.info("tile %s/%s/%s: render not stored now (%s)", z, x, y, exc.orig)


def etag_matches(if_none_match: str, etag: str) -> bool:
    """RFC 9110 If-None-Match (weak comparison): ``*`` or any listed tag equal to ours."""
    if if_none_match.strip() == "*":
        return True
    tags = [t.strip() for t in if_none_match.split(",")]
    return any(t.removeprefix("W/") == etag for t in tags)


# --- TileJSON ----------------------------------------------------------------------------------------


def data_bounds(session: Session) -> list[float] | None:
    """[west, south, east, north] of the live tiles (their tile bounds)."""
    heads = session.execute(
        select(TileHead.z, TileHead.x, TileHead.y).where(TileHead.live_version_id.is_not(None))
    ).all()
    if not heads:
        return None
    boxes = [vs.tile_bounds_lonlat(z, x, y) for z, x, y in heads]
    return [
        min(b[0] for b in boxes),
        min(b[1] for b in boxes),
        max(b[2] for b in boxes),
        max(b[3] for b in boxes),
    ]


def property_fields(session: Session, *, sample: int = 500) -> dict[str, str]:
    """The layer's fields (TileJSON ``vector_layers``): the fixed ones and the scalar properties seen
    in a sample of live features."""
    fields = {
        "id": "String: stable feature id (across versions)",
        "type": "String: lane_divider | road_boundary | centerline | stop_line | crosswalk | road_marking",
        "style": "String: e.g. solid | dashed (when known)",
        mvt.FLAGS: "String: the validator's flag kinds, the JSON text of a list (when flagged)",
    }
    live_ids = select(TileHead.live_version_id).where(TileHead.live_version_id.is_not(None))
    rows = session.execute(
        select(MapFeatureRow.properties).where(MapFeatureRow.tile_version_id.in_(live_ids)).limit(sample)
    ).scalars()
    for props in rows:
        for key, value in mvt.scalar_properties(props or {}).items():
            fields.setdefault(
                key,
                "Boolean"
                if isinstance(value, bool)
                else "Number"
                if isinstance(value, int | float)
                else "String",
            )
    return fields


def tilejson(session: Session, *, base_url: str, tile_zoom: int) -> dict:
    map_version = vs.current_map_version(session)
    bounds = data_bounds(session)
    live_template = f"{base_url}/v1/tiles/{{z}}/{{x}}/{{y}}.mvt"
    fields = property_fields(session)
    doc: dict[str, Any] = {
        "tilejson": "3.0.0",
        "name": "CSR road structure",
        "description": "Crowdsourced road structure (lane dividers, road boundaries, centerlines, stop lines, "
        "crosswalks, road markings); one layer 'road', property 'type' per element.",
        "version": "1.0.0",
        "scheme": "xyz",
        "tiles": [f"{live_template}?v={map_version}" if map_version else live_template],
        "minzoom": 0,
        "maxzoom": MAX_ZOOM,
        "bounds": bounds or [-180.0, -85.0511287798, 180.0, 85.0511287798],
        "center": (
            [(bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2, tile_zoom] if bounds else [0.0, 0.0, 0]
        ),
        "vector_layers": [
            {
                "id": mvt.LAYER,
                "description": "one feature per road element; filter on 'type'",
                "minzoom": 0,
                "maxzoom": MAX_ZOOM,
                "fields": fields,
            }
        ],
        "map_version": map_version,
        "live_tiles": [live_template],
        "geojson_tiles": [f"{base_url}/v1/tiles/{{z}}/{{x}}/{{y}}.geojson"],
        "pipeline_zoom": tile_zoom,
        "flag_levels": {kind: str(level) for kind, level in flag_levels().items()},
        "feature_count": int(
            session.execute(
                select(func.count())
                .select_from(MapFeatureRow)
                .where(
                    MapFeatureRow.tile_version_id.in_(
                        select(TileHead.live_version_id).where(TileHead.live_version_id.is_not(None))
                    ),
                    MapFeatureRow.change != "removed",
                )
            ).scalar_one()
        ),
    }
    return doc
