"""Web-mercator XYZ tile arithmetic (EPSG:3857, the spherical formula PostGIS and PROJ use)."""

from __future__ import annotations

import math

import numpy as np

EARTH_RADIUS_M = 6378137.0
HALF_WORLD_M = math.pi * EARTH_RADIUS_M  # 20037508.342789244
MAX_ZOOM = 22


def valid_tile(z: int, x: int, y: int) -> bool:
    return 0 <= z <= MAX_ZOOM and 0 <= x < 2**z and 0 <= y < 2**z


def tile_size_m(z: int) -> float:
    return 2.0 * HALF_WORLD_M / 2**z


def tile_bounds_m(z: int, x: int, y: int) -> tuple[float, float, float, float]:
    """(left, bottom, right, top) of the tile in EPSG:3857 metres (as ``ST_TileEnvelope``)."""
    size = tile_size_m(z)
    left, top = -HALF_WORLD_M + x * size, HALF_WORLD_M - y * size
    return left, top - size, left + size, top


def lonlat_to_m(lonlat_deg: np.ndarray) -> np.ndarray:
    """(N, 2) lon, lat degrees -> (N, 2) EPSG:3857 metres."""
    lonlat = np.asarray(lonlat_deg, float)
    lat = np.clip(np.radians(lonlat[:, 1]), -1.4844222297453324, 1.4844222297453324)  # +-85.0511 deg
    return np.column_stack(
        [EARTH_RADIUS_M * np.radians(lonlat[:, 0]), EARTH_RADIUS_M * np.log(np.tan(np.pi / 4 + lat / 2))]
    )


def m_to_lonlat(xy_m: tuple[float, float]) -> tuple[float, float]:
    x, y = xy_m
    return math.degrees(x / EARTH_RADIUS_M), math.degrees(
        2 * math.atan(math.exp(y / EARTH_RADIUS_M)) - math.pi / 2
    )


def buffered_bounds_lonlat(
    z: int, x: int, y: int, *, buffer_frac: float
) -> tuple[float, float, float, float]:
    """(west, south, east, north) of the tile grown by ``buffer_frac`` of its size on every side
    (``ST_Transform(ST_TileEnvelope(z, x, y, margin => buffer_frac), 4326)``)."""
    left, bottom, right, top = tile_bounds_m(z, x, y)
    pad = (right - left) * buffer_frac
    west, south = m_to_lonlat((left - pad, bottom - pad))
    east, north = m_to_lonlat((right + pad, top + pad))
    return west, south, east, north
