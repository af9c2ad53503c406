"""HTTP helpers shared by the tile, map and version routes: caching headers, CORS, parameters."""

from __future__ import annotations

import math
import threading
from typing import Any, Protocol

from fastapi.responses import Response
from sqlalchemy.orm import Session

from services.api.cors import CORS_HEADERS as CORS_HEADERS  # re-exported for the map routes
from services.api.cors import PREFLIGHT_HEADERS as PREFLIGHT_HEADERS
from services.api.errors import ApiError
from services.db import versions as vs
from services.tiles.mercator import MAX_ZOOM
from services.tiles.render import TileCache

# How long a cache may keep a live answer, and a pinned one (a map version never changes).
LIVE_MAX_AGE = "max-age=30"
PINNED_MAX_AGE = "max-age=31536000, immutable"
# /v1/map answers at most this bbox (square degrees; ~0.25: 50 km x 28 km at 49 deg N).
MAX_BBOX_AREA_DEG2 = 0.25

_lock = threading.Lock()


class HasApp(Protocol):
    """What :func:`caches` reads of a request: ``.app`` (also ``fastpath``'s stand-in)."""

    @property
    def app(self) -> Any: ...


def cache_control(*, pinned: bool, public_map: bool) -> str:
    """``Cache-Control`` of a map answer: ``private`` (only the caller's own cache keeps it: the
    answer needs a key) unless the map is public (``CSR_PUBLIC_MAP``)."""
    return f"{'public' if public_map else 'private'}, {PINNED_MAX_AGE if pinned else LIVE_MAX_AGE}"


def caches(request: HasApp) -> tuple[TileCache, TileCache]:
    """The app's tile cache (ETag -> bytes) and pinned-ETag cache ((kind, z/x/y, v) -> ETag)."""
    state = request.app.state
    if getattr(state, "tile_cache", None) is None:
        with _lock:
            if getattr(state, "tile_cache", None) is None:
                state.pinned_etags = TileCache(max_bytes=8 * 1024 * 1024, max_entries=100_000)
                state.tile_cache = TileCache()
    return state.tile_cache, state.pinned_etags


def check_tile(z: int, x: int, y: int) -> None:
    if not 0 <= z <= MAX_ZOOM:
        raise ApiError(422, "invalid_request", f"z: must be 0..{MAX_ZOOM}, not {z}", location="path.z")
    for name, value in (("x", x), ("y", y)):
        if not 0 <= value < 2**z:
            raise ApiError(
                422,
                "invalid_request",
                f"{name}: must be 0..{2**z - 1} at zoom {z}, not {value}",
                location=f"path.{name}",
            )


def check_map_version(session: Session, version: int | None, *, location: str) -> int | None:
    """A pinned map version must exist already (else its content could still change): 404 if not."""
    if version is None:
        return None
    if version < 0:
        raise ApiError(
            422, "invalid_request", f"{location}: must be >= 0, not {version}", location=f"query.{location}"
        )
    current = vs.current_map_version(session)
    if version > current:
        raise ApiError(
            404,
            "not_found",
            f"map version {version} does not exist (the current map version is {current})",
            location=f"query.{location}",
        )
    return version


def parse_bbox(raw: str) -> tuple[float, float, float, float]:
    def bad(why: str) -> ApiError:
        return ApiError(
            422,
            "invalid_request",
            f"bbox: {why} (expected minlon,minlat,maxlon,maxlat in degrees)",
            location="query.bbox",
        )

    parts = raw.split(",")
    if len(parts) != 4:
        raise bad(f"{len(parts)} numbers, not 4")
    try:
        west, south, east, north = (float(p) for p in parts)
    except ValueError as exc:
        raise bad("not a number") from exc
    if not all(math.isfinite(v) for v in (west, south, east, north)):
        raise bad("non-finite number")
    if not (-180.0 <= west < east <= 180.0):
        raise bad("need -180 <= minlon < maxlon <= 180")
    if not (-90.0 <= south < north <= 90.0):
        raise bad("need -90 <= minlat < maxlat <= 90")
    area = (east - west) * (north - south)
    if area > MAX_BBOX_AREA_DEG2:
        raise bad(
            f"area {area:.3g} square degrees is over the limit of {MAX_BBOX_AREA_DEG2}; request smaller boxes or tiles"
        )
    return west, south, east, north


def tile_response(
    body: bytes | None,
    *,
    etag: str,
    media_type: str,
    pinned: bool,
    public_map: bool,
    not_modified: bool,
    map_version: int | None,
) -> Response:
    headers = {
        **CORS_HEADERS,
        "ETag": etag,
        "Cache-Control": cache_control(pinned=pinned, public_map=public_map),
    }
    if map_version is not None:
        headers["X-Map-Version"] = str(map_version)
    if not_modified:
        return Response(status_code=304, headers=headers)
    if body is None:
        return Response(status_code=204, headers=headers)
    return Response(body, media_type=media_type, headers=headers)
