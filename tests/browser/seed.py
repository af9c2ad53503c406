"""Test data for the browser tests: a few versions of one tile written straight into the version
store (``services.db.versions.write_tile_version``), so that the viewer has something to draw
without running the whole pipeline; and a tile version made by the real merge job from planted trip
alignments, with lines held back from it (as ``tests/integration/test_held_back.py`` builds it)."""

from __future__ import annotations

import io
import math
import secrets

import mercantile
import numpy as np
import sqlalchemy as sa
from shapely.geometry import LineString, Polygon
from sqlalchemy.orm import Session, sessionmaker

from csr_core.types import DividerStyle, ElementNoise, ElementType, TripInstance
from services.db import versions as vs
from services.db.models import Trip, TripTileAlignment
from services.reconstructions import instance_json, noise_json
from services.settings import Settings
from services.tile_frames import tile_frame
from workers import tile_jobs

M_PER_DEG_LAT = 111_320.0

MERGED_ROAD_LENGTH_M = 200.0  # centred in the tile (~400 m wide at zoom 16 and Munich's latitude)
MERGED_TRIPS = 4  # one may see the ghosts; three drive alongside without (SUPPRESS_MIN_PASSING = 3)
DIVIDER_Y_M = 1.75  # the real dividers, either side of the trips' path (metres north of it)
GHOST_DIVIDER_Y_M = 5.25  # the ghost divider, a lane further out (north)
GHOST_BOUNDARY_Y_M = -5.25  # the ghost road boundary (south)


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
    and adds a stop line and validator flags of each level, 3 removes the road marking."""
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
        # no perceived centreline in the outer lanes: derived between their divider and kerb
        f(
            "cl-outer",
            "centerline",
            line(-5.25),
            derived="bounding_lines",
            derived_from=["ld-south", "rb-south"],
            direction="assumed",
        ),
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
        # validator flags of each level (services.tiles.flag_levels): severe, severe among an
        # informative one, a warning, informative
        features[0] = f("rb-north", "road_boundary", line(7.0), flags=["trips_disagree"], support_trips=2)
        features[1] = f("rb-south", "road_boundary", line(-7.0), flags=["gap", "implausible_lane_width"])
        features[6] = f("ld-north", "lane_divider", line(3.5), "dashed", flags=["low_support"])
        features[3] = f("cl-west", "centerline", line(1.75), flags=["gap"])
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


def _npz(**arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    # mypy checks the **arrays values against allow_pickle: bool too (no key is named so)
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def seed_merged_tile(db_url: str, z: int, x: int, y: int, *, ghosts: bool) -> tuple[float, float]:
    """Version 1 of tile z/x/y made by the real merge job (``compute_merge_tile`` +
    ``persist_merge_tile``) from four planted trip alignments (``trip_tile_alignments`` rows, what
    ``align_tile`` stores) along a straight west-east road in the tile's centre, each seeing its two
    lane dividers. With ``ghosts`` one trip also sees a ghost divider (north) and a ghost road
    boundary (south) that the three others drove alongside without seeing: the merge holds both
    back. Returns the road's centre (lon, lat)."""
    frame = tile_frame(z, x, y)
    centre_lonlat = mercantile.ul(x + 0.5, y + 0.5, z)
    centre_xy_m = frame.to_local(np.array([centre_lonlat]))[0]

    def line_xy_m(y_m: float, x0_m: float = 0.0, x1_m: float = MERGED_ROAD_LENGTH_M) -> np.ndarray:
        """A straight line ``(N, 2)`` at ``y_m`` north of the road, metre spacing, tile frame."""
        x_m = np.arange(x0_m, x1_m + 1e-9, 1.0) - MERGED_ROAD_LENGTH_M / 2
        return centre_xy_m + np.column_stack([x_m, np.full_like(x_m, y_m)])

    path_xy_m = line_xy_m(0.0)
    poses_xyyaw = np.column_stack([path_xy_m, np.zeros(len(path_xy_m))])
    noise = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}
    real = [
        TripInstance(ElementType.LANE_DIVIDER, line_xy_m(y_m), DividerStyle.SOLID, 10)
        for y_m in (DIVIDER_Y_M, -DIVIDER_Y_M)
    ]
    ghost = [
        TripInstance(
            ElementType.LANE_DIVIDER, line_xy_m(GHOST_DIVIDER_Y_M, 60.0, 140.0), DividerStyle.SOLID, 10
        ),
        TripInstance(ElementType.ROAD_BOUNDARY, line_xy_m(GHOST_BOUNDARY_Y_M, 50.0, 150.0), None, 10),
    ]
    engine = sa.create_engine(db_url)
    sessions = sessionmaker(engine)
    try:
        with sessions.begin() as session:
            for k in range(MERGED_TRIPS):
                trip = Trip(
                    id=f"seed-{secrets.token_hex(6)}",
                    vehicle_id="veh-seed",
                    trip_id=f"t{x}-{k}",
                    content_sha256="0" * 64,
                    status="aligned",
                    schema_version="1.0",
                    started_at=f"2026-11-0{k + 1}T08:00:00Z",
                    n_frames=len(poses_xyyaw),
                    body_bytes=1,
                    json_bytes=1,
                )
                session.add(trip)
                session.flush()
                instances = real + ghost if ghosts and k == 0 else real
                session.add(
                    TripTileAlignment(
                        trip_pk=trip.id,
                        z=z,
                        x=x,
                        y=y,
                        job_id="seed-align",
                        origin_lat=frame.origin_lat,
                        origin_lon=frame.origin_lon,
                        arrays=_npz(
                            frame_indices=np.arange(len(poses_xyyaw), dtype=np.int32),
                            poses_xyyaw=poses_xyyaw,
                            weights=np.ones(len(poses_xyyaw), np.float32),
                            residuals_m=np.zeros(len(poses_xyyaw), np.float32),
                        ),
                        instances=[instance_json(i) for i in instances],
                        noise=noise_json(noise),
                        failed_reason=None,
                    )
                )
        result = tile_jobs.compute_merge_tile(sessions, Settings(database_url=db_url), z, x, y)
        assert not result.nothing_to_do and result.state is not None
        with sessions.begin() as session:
            tile_jobs.persist_merge_tile(session, "seed-merge", z, x, y, result)
    finally:
        engine.dispose()
    return (centre_lonlat.lng, centre_lonlat.lat)
