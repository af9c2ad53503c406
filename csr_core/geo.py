"""Geodesy: the local transverse-Mercator plane of a region, and web-mercator XYZ tiles.

A local tmerc at k=1 centred on the region (not UTM: its 0.16 m/km scale error is far
larger than the accuracy we measure; see shared/LIBRARY-NOTES.md section 5).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import mercantile
import numpy as np
import pyproj

from csr_core.se2 import heading_deg_to_yaw_rad, yaw_rad_to_heading_deg

DEFAULT_TILE_ZOOM = 16


@dataclass(frozen=True)
class LocalFrame:
    """World frame of a region: x east, y north, metres, origin at ``(origin_lat, origin_lon)``."""

    origin_lat: float
    origin_lon: float

    @classmethod
    def around(cls, lonlat_deg: np.ndarray) -> LocalFrame:
        """A frame centred on the bounding box of ``lonlat_deg (N, 2)``, rounded to 1e-4 deg
        so that nearby batches of trips share one frame."""
        lonlat_deg = np.asarray(lonlat_deg, float)
        lo, hi = lonlat_deg.min(axis=0), lonlat_deg.max(axis=0)
        lon, lat = np.round((lo + hi) / 2, 4)
        return cls(origin_lat=float(lat), origin_lon=float(lon))

    @cached_property
    def _crs(self) -> pyproj.CRS:
        return pyproj.CRS.from_proj4(
            f"+proj=tmerc +lat_0={self.origin_lat!r} +lon_0={self.origin_lon!r} +k=1 "
            "+x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
        )

    @cached_property
    def _forward(self) -> pyproj.Transformer:
        return pyproj.Transformer.from_crs("EPSG:4326", self._crs, always_xy=True)

    @cached_property
    def _inverse(self) -> pyproj.Transformer:
        return pyproj.Transformer.from_crs(self._crs, "EPSG:4326", always_xy=True)

    def to_local(self, lonlat_deg: np.ndarray) -> np.ndarray:
        """``(N, 2)`` lon, lat degrees -> ``(N, 2)`` x east, y north metres."""
        lonlat_deg = np.asarray(lonlat_deg, float).reshape(-1, 2)
        x, y = self._forward.transform(lonlat_deg[:, 0], lonlat_deg[:, 1])
        return np.column_stack([x, y])

    def to_lonlat(self, points_xy_m: np.ndarray) -> np.ndarray:
        """``(N, 2)`` metres -> ``(N, 2)`` lon, lat degrees."""
        points_xy_m = np.asarray(points_xy_m, float).reshape(-1, 2)
        lon, lat = self._inverse.transform(points_xy_m[:, 0], points_xy_m[:, 1])
        return np.column_stack([lon, lat])

    def convergence_rad(self, lonlat_deg: np.ndarray) -> np.ndarray:
        """``(N,)`` meridian convergence at each point: the angle (radians, counter-clockwise) from
        the frame's grid north to true north there (pyproj's ``meridian_convergence``). Zero on the
        frame's central meridian, about ``(lon - lon_0) sin(lat)`` off it: 0.13 degrees 13 km east
        of it at 49 N, which a trip's GNSS course (clockwise from true north) must not bring into
        the plane as a heading bias. 0 where a point is not finite."""
        lonlat_deg = np.asarray(lonlat_deg, float).reshape(-1, 2)
        factors = self._proj.get_factors(lonlat_deg[:, 0], lonlat_deg[:, 1])
        gamma = np.radians(np.asarray(factors.meridian_convergence, float).reshape(-1))
        return np.where(np.isfinite(gamma), gamma, 0.0)

    def grid_heading_deg(self, true_heading_deg: np.ndarray | float, lonlat_deg: np.ndarray) -> np.ndarray:
        """Courses clockwise from true north (the upload's ``heading_deg``) at ``lonlat_deg (N, 2)``
        -> clockwise from the frame's grid north (what ``se2.heading_deg_to_yaw_rad`` turns into a
        yaw of this plane). NaN stays NaN."""
        grid = np.asarray(true_heading_deg, float) - np.degrees(self.convergence_rad(lonlat_deg))
        return np.mod(grid, 360.0)

    def true_heading_deg(self, grid_heading_deg: np.ndarray | float, lonlat_deg: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`grid_heading_deg`: clockwise from grid north -> from true north."""
        true = np.asarray(grid_heading_deg, float) + np.degrees(self.convergence_rad(lonlat_deg))
        return np.mod(true, 360.0)

    def yaw_rad(self, true_heading_deg: np.ndarray | float, lonlat_deg: np.ndarray) -> np.ndarray:
        """Headings clockwise from true north (a poses CSV's ``heading_deg``) at ``lonlat_deg (N, 2)``
        -> yaws in this plane (radians, counter-clockwise from grid east, in [-pi, pi))."""
        return np.asarray(heading_deg_to_yaw_rad(self.grid_heading_deg(true_heading_deg, lonlat_deg)))

    def heading_deg(self, yaw_rad: np.ndarray | float, lonlat_deg: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`yaw_rad`: yaws in this plane -> clockwise from true north, in [0, 360)."""
        return self.true_heading_deg(yaw_rad_to_heading_deg(yaw_rad), lonlat_deg)

    @cached_property
    def _proj(self) -> pyproj.Proj:
        return pyproj.Proj(self._crs)


def tiles_touched(lonlat_deg: np.ndarray, zoom: int = DEFAULT_TILE_ZOOM) -> list[tuple[int, int, int]]:
    """Sorted unique web-mercator XYZ tiles ``(z, x, y)`` containing any of the points.

    The points of a 10 Hz track are far denser than a tile, so vertices suffice.
    """
    lonlat_deg = np.asarray(lonlat_deg, float).reshape(-1, 2)
    n = 2.0**zoom
    lon, lat = lonlat_deg[:, 0], np.clip(lonlat_deg[:, 1], -85.05112878, 85.05112878)
    xt = np.floor((lon + 180.0) / 360.0 * n).astype(np.int64)
    lat_r = np.radians(lat)
    yt = np.floor((1.0 - np.log(np.tan(lat_r) + 1.0 / np.cos(lat_r)) / np.pi) / 2.0 * n).astype(np.int64)
    xt = np.clip(xt, 0, int(n) - 1)
    yt = np.clip(yt, 0, int(n) - 1)
    pairs = np.unique(np.column_stack([xt, yt]), axis=0)
    return [(zoom, int(x), int(y)) for x, y in pairs]


def tile_bounds_lonlat(z: int, x: int, y: int) -> tuple[float, float, float, float]:
    """``(west, south, east, north)`` degrees of an XYZ tile."""
    b = mercantile.bounds(x, y, z)
    return (b.west, b.south, b.east, b.north)


def polyline_length_m(points_xy_m: np.ndarray) -> float:
    points_xy_m = np.asarray(points_xy_m, float)
    if len(points_xy_m) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(points_xy_m, axis=0), axis=1).sum())


REGION_FRAME_ZOOM = 10  # ~40 km tiles: every trip starting in one shares that tile's frame


def region_frame_for(lonlat_deg, zoom: int = REGION_FRAME_ZOOM) -> LocalFrame:
    """The deterministic world frame of a region: a ``LocalFrame`` whose origin is the centre of
    the web-mercator XYZ tile at ``zoom`` containing the point ``lonlat_deg (2,)`` (lon, lat
    degrees). Trips that start in the same tile get the same frame, whatever else they cover."""
    lon, lat = (float(v) for v in np.asarray(lonlat_deg, float).reshape(2))
    ((_, x, y),) = tiles_touched(np.array([[lon, lat]]), zoom=zoom)
    # the tile's centre in web-mercator (the mean of its edge latitudes would be off-centre)
    centre = mercantile.ul(x + 0.5, y + 0.5, zoom)
    return LocalFrame(origin_lat=float(centre.lat), origin_lon=float(centre.lng))
