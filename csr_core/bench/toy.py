"""A tiny hand-made scenario (contract section 5) for unit tests and smoke runs.

One gently curving two-way road (lane dividers, centerlines, boundaries, a crosswalk and a stop
line), trips driving it in the right-hand lane at 10 m/s, 10 Hz. Per trip: GNSS = truth + a
constant bias (``gnss_bias_sigma_m`` per axis) + white noise (``gnss_noise_m``); odometry =
truth increments with small noise; perception = the truth within x in [-15, 30], |y| <= 15 m of
the true vehicle pose, resampled every 2 m, plus ``perception_noise_m`` white noise. Not the
simulator (``csr simulate``): just enough ground truth to test metrics and baselines by hand.
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import orjson
import shapely

from csr_core.geo import LocalFrame
from csr_core.scenario import map_features_to_geojson
from csr_core.se2 import between, compose, inverse
from csr_core.types import DividerStyle, ElementType, GnssStatus, MapFeature, PerceivedElement, Trip
from csr_core.upload import encode_trip

TOY_ORIGIN_LAT, TOY_ORIGIN_LON = 48.0, 11.0
LANE_WIDTH_M = 3.5


@dataclass(frozen=True, slots=True)
class ToySpec:
    n_trips: int = 3
    length_m: float = 300.0
    speed_mps: float = 10.0
    rate_hz: float = 10.0
    gnss_bias_sigma_m: float = 0.5
    gnss_noise_m: float = 0.2
    perception_noise_m: float = 0.03
    odom_noise_m: float = 0.002
    outage: tuple[int, int] | None = None  # frame range without GNSS fix, in every trip
    seed: int = 0


def road_centre_xy(length_m: float, step_m: float = 1.0) -> np.ndarray:
    """``(N, 2)`` the road's centre: a gentle S-curve starting at (-length/2, 0)."""
    s = np.arange(0.0, length_m + step_m, step_m)
    yaw = 0.15 * np.sin(2 * np.pi * s / length_m)
    xy = np.column_stack([np.cumsum(np.cos(yaw)), np.cumsum(np.sin(yaw))]) * step_m
    return xy - [length_m / 2, 0.0]


def _offset(xy: np.ndarray, left_m: float) -> np.ndarray:
    t = np.gradient(xy, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return xy + left_m * np.column_stack([-t[:, 1], t[:, 0]])


def toy_truth_map(length_m: float) -> tuple[MapFeature, ...]:
    """The road's elements in the toy world plane."""
    c = road_centre_xy(length_m)
    lw = LANE_WIDTH_M
    feats = [
        MapFeature(ElementType.LANE_DIVIDER, c.copy(), DividerStyle.DOUBLE),
        MapFeature(ElementType.LANE_DIVIDER, _offset(c, -lw), DividerStyle.DASHED),
        MapFeature(ElementType.LANE_DIVIDER, _offset(c, lw), DividerStyle.DASHED),
        MapFeature(ElementType.ROAD_BOUNDARY, _offset(c, -2 * lw)),
        MapFeature(ElementType.ROAD_BOUNDARY, _offset(c, 2 * lw)),
    ]
    feats += [MapFeature(ElementType.CENTERLINE, _offset(c, k * lw / 2)) for k in (-3, -1, 1, 3)]
    i = len(c) * 2 // 3
    t = c[i + 1] - c[i]
    t /= np.linalg.norm(t)
    n = np.array([-t[1], t[0]])
    feats.append(MapFeature(ElementType.STOP_LINE, np.array([c[i] - 2 * lw * n, c[i]])))
    corners = [
        c[i] + 2 * t - 2 * lw * n,
        c[i] + 6 * t - 2 * lw * n,
        c[i] + 6 * t + 2 * lw * n,
        c[i] + 2 * t + 2 * lw * n,
    ]
    feats.append(MapFeature(ElementType.CROSSWALK, np.array(corners)))
    return tuple(
        MapFeature(f.type, f.points_xy_world, f.style, feature_id=f"truth{k}") for k, f in enumerate(feats)
    )


def _true_poses(spec: ToySpec) -> np.ndarray:
    lane = _offset(road_centre_xy(spec.length_m), -LANE_WIDTH_M / 2)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(lane, axis=0), axis=1))])
    st = np.arange(2.0, s[-1] - 2.0, spec.speed_mps / spec.rate_hz)
    xy = np.column_stack([np.interp(st, s, lane[:, 0]), np.interp(st, s, lane[:, 1])])
    d = np.gradient(xy, axis=0)
    return np.column_stack([xy, np.arctan2(d[:, 1], d[:, 0])])


def _perceive(
    world_T_vehicle: np.ndarray, truth: tuple[MapFeature, ...], rng: np.random.Generator, noise_m: float
) -> tuple[PerceivedElement, ...]:
    v_T_w = inverse(world_T_vehicle)
    c, s = np.cos(v_T_w[2]), np.sin(v_T_w[2])
    out = []
    for k, f in enumerate(truth):
        p = f.points_xy_world @ np.array([[c, -s], [s, c]]).T + v_T_w[:2]
        if f.type.is_polygon:
            if np.all((p[:, 0] > -15) & (p[:, 0] < 30) & (np.abs(p[:, 1]) < 15)):
                out.append(PerceivedElement(f.type, p + rng.normal(0, noise_m, p.shape), track_id=k))
            continue
        g = shapely.clip_by_rect(shapely.linestrings(p), -15, -15, 30, 15)
        for part in shapely.get_parts(g):
            if part.length < 1.0:
                continue
            d = np.append(np.arange(0.0, part.length, 2.0), part.length)
            q = shapely.get_coordinates(shapely.line_interpolate_point(part, d))
            out.append(
                PerceivedElement(
                    f.type, q + rng.normal(0, noise_m, q.shape), style=f.style, score=0.9, track_id=k
                )
            )
    return tuple(out)


def make_toy_trips(
    spec: ToySpec = ToySpec(),
) -> tuple[list[Trip], dict[str, np.ndarray], tuple[MapFeature, ...], LocalFrame]:
    """``(trips, true poses (N, 3) per key in the toy plane, truth map, the toy plane)``."""
    rng = np.random.default_rng(spec.seed)
    frame = LocalFrame(TOY_ORIGIN_LAT, TOY_ORIGIN_LON)
    truth = toy_truth_map(spec.length_m)
    poses = _true_poses(spec)
    n = len(poses)
    trips, true_by_key = [], {}
    for k in range(spec.n_trips):
        bias = rng.normal(0, spec.gnss_bias_sigma_m, 2)
        gnss_xy = poses[:, :2] + bias + rng.normal(0, spec.gnss_noise_m, (n, 2))
        status = np.full(n, GnssStatus.DGPS, np.uint8)
        if spec.outage is not None:
            status[spec.outage[0] : spec.outage[1]] = GnssStatus.NONE
        incr = between(poses[:-1], poses[1:]) + rng.normal(0, spec.odom_noise_m, (n - 1, 3)) * [1, 1, 0.1]
        odom = [np.array([0.0, 0.0, 0.0])]
        for d in incr:
            odom.append(compose(odom[-1], d))
        heading = frame.heading_deg(poses[:, 2] + rng.normal(0, 0.005, n), frame.to_lonlat(poses[:, :2]))
        trip = Trip(
            vehicle_id=f"toy-{k % 2}",
            trip_id=f"trip-{k:03d}",
            started_at="2026-11-21T08:00:00Z",
            timestamps_s=np.arange(n) / spec.rate_hz,
            gnss_lonlat_deg=frame.to_lonlat(gnss_xy),
            gnss_status=status,
            gnss_std_m=np.full(n, spec.gnss_noise_m),
            gnss_heading_deg=np.asarray(heading) % 360.0,
            odom_xyyaw=np.array(odom),
            elements=tuple(_perceive(p, truth, rng, spec.perception_noise_m) for p in poses),
        )
        trips.append(trip)
        true_by_key[trip.key] = poses.copy()
    return trips, true_by_key, truth, frame


def write_toy_scenario(out_dir: str | Path, spec: ToySpec = ToySpec()) -> Path:
    """Write the toy as a scenario folder (contract section 5)."""
    out_dir = Path(out_dir)
    (out_dir / "trips").mkdir(parents=True, exist_ok=True)
    (out_dir / "truth" / "poses").mkdir(parents=True, exist_ok=True)
    trips, true_by_key, truth, frame = make_toy_trips(spec)
    (out_dir / "scenario.json").write_bytes(
        orjson.dumps(
            {
                "name": "toy",
                "origin": {"lat": TOY_ORIGIN_LAT, "lon": TOY_ORIGIN_LON},
                "profile": {
                    "gnss_bias_sigma_m": spec.gnss_bias_sigma_m,
                    "gnss_noise_m": spec.gnss_noise_m,
                    "perception_noise_m": spec.perception_noise_m,
                },
            }
        )
    )
    for trip in trips:
        (out_dir / "trips" / f"{trip.key}.json.gz").write_bytes(
            gzip.compress(orjson.dumps(encode_trip(trip)))
        )
        p = true_by_key[trip.key]
        lonlat = frame.to_lonlat(p[:, :2])
        rows = ["t,lat,lon,heading_deg"] + [
            f"{t:.3f},{la:.9f},{lo:.9f},{h:.4f}"
            for t, la, lo, h in zip(
                trip.timestamps_s,
                lonlat[:, 1],
                lonlat[:, 0],
                frame.heading_deg(p[:, 2], lonlat),
                strict=False,
            )
        ]
        (out_dir / "truth" / "poses" / f"{trip.key}.csv").write_text("\n".join(rows) + "\n")
    (out_dir / "truth" / "map.geojson").write_bytes(orjson.dumps(map_features_to_geojson(truth, frame)))
    return out_dir
