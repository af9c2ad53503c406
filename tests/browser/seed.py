"""Test data for the browser tests: a few versions of one tile written straight into the version
store (``services.db.versions.write_tile_version``), so that the viewer has something to draw
without running the whole pipeline."""

from __future__ import annotations

import math

import sqlalchemy as sa
from shapely.geometry import LineString, Polygon
from sqlalchemy.orm import Session

from services.db import versions as vs

M_PER_DEG_LAT = 111_320.0


def _road(lon0: float, lat0: float, half_m: float):
    """A west-east road centred on ``(lon0, lat0)``: lon/lat helpers in metres from its centre."""
    m_per_deg_lon = M_PER_DEG_LAT * math.cos(math.radians(lat0))

    def pt(x_m: float, y_m: float) -> tuple[float, float]:
        return (lon0 + x_m / m_per_deg_lon, lat0 + y_m / M_PER_DEG_LAT)

    def line(y_m: float, x0: float = -half_m, x1: float = half_m) -> LineString:
        return LineString([pt(x, y_m) for x in (x0, (x0 + x1) / 2, x1)])

    return pt, line


def version_features(
    centre: tuple[float, float], step: int, half_m: float = 150.0
) -> list[vs.VersionFeature]:
    """Version ``step`` (1, 2, 3) of a road around ``centre`` (lon, lat): 2 moves the centre divider
    and adds a stop line and a validator flag, 3 removes the road marking."""
    pt, line = _road(*centre, half_m)
    props = {
        "support_trips": 4,
        "support_observations": 120,
        "uncertainty_m": 0.05,
        "first_seen": "2026-11-01T10:00:00+00:00",
        "last_confirmed": "2026-11-20T10:00:00+00:00",
        "flags": [],
    }

    def f(fid: str, type_: str, geom, style: str | None = None, **extra) -> vs.VersionFeature:
        return vs.VersionFeature(fid, type_, style, {**props, **extra}, geom)

    divider_shift = 0.0 if step == 1 else 1.5
    features = [
        f("rb-north", "road_boundary", line(7.0)),
        f("rb-south", "road_boundary", line(-7.0)),
        f("cl-east", "centerline", line(-1.75)),
        f("cl-west", "centerline", line(1.75)),
        f("ld-centre", "lane_divider", line(0.0 + divider_shift), "solid"),
        f("ld-north", "lane_divider", line(3.5), "dashed"),
        f("ld-south", "lane_divider", line(-3.5), "dashed"),
        f("cw-1", "crosswalk", Polygon([pt(-20, -7), pt(-14, -7), pt(-14, 7), pt(-20, 7)])),
    ]
    if step < 3:
        features.append(
            f("rm-arrow", "road_marking", Polygon([pt(30, -3), pt(36, -3), pt(36, -0.5), pt(30, -0.5)]))
        )
    if step >= 2:
        features.append(f("sl-1", "stop_line", LineString([pt(-22, -7), pt(-22, 0)])))
        features[0] = f("rb-north", "road_boundary", line(7.0), flags=["trips_disagree"], support_trips=2)
    return features


def seed_tile(
    db_url: str, z: int, x: int, y: int, centre: tuple[float, float], *, n_versions: int = 3
) -> None:
    """Versions 1..n of tile z/x/y (all published), the road centred on ``centre`` (lon, lat)."""
    engine = sa.create_engine(db_url)
    lon0, lat0 = centre
    try:
        for step in range(1, n_versions + 1):
            with Session(engine) as session, session.begin():
                vs.write_tile_version(
                    session,
                    z=z,
                    x=x,
                    y=y,
                    features=version_features(centre, step),
                    reason="merge",
                    job_id=None,
                    trips=[],
                    corrections=[],
                    quality={},
                    origin_lat=lat0,
                    origin_lon=lon0,
                    state=None,
                    publish=True,
                    expected_latest=step - 1 if step > 1 else None,
                )
    finally:
        engine.dispose()
