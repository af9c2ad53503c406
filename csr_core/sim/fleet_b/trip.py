"""One fleet-b trip: the shared route generator and driver, then fleet b's sensors, assembled
into a contract upload (``trip-upload.schema.json``) and its truth."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from csr_core.geo import LocalFrame
from csr_core.sim.fleet_b.gnss import ReceiverB, draw_receiver_b, simulate_gnss_b
from csr_core.sim.fleet_b.odometry import OdometerB, draw_odometer_b, simulate_odometry_b
from csr_core.sim.fleet_b.params import FleetBParams
from csr_core.sim.fleet_b.perception import TruthIndexB, perceive_trip_b
from csr_core.sim.routes import drive, looping_route, random_route
from csr_core.sim.world import World
from csr_core.types import GnssStatus
from csr_core.upload import SCHEMA_VERSION

_STATUS_NAMES = tuple(s.wire_name for s in GnssStatus)


@dataclass(frozen=True, slots=True)
class VehicleB:
    """Per-vehicle traits of fleet b, shared by all of its trips."""

    vehicle_id: str
    receiver: ReceiverB
    odometer: OdometerB
    rig_xyyaw: tuple[float, float, float]  # perception rig misalignment (m, m, rad)


def draw_vehicle_b(vehicle_id: str, params: FleetBParams, rng: np.random.Generator) -> VehicleB:
    p = params.perception
    rig = (
        float(rng.normal(0.0, p.extrinsic_xy_sigma_m)),
        float(rng.normal(0.0, p.extrinsic_xy_sigma_m)),
        float(rng.normal(0.0, p.extrinsic_yaw_sigma_rad)),
    )
    return VehicleB(vehicle_id, draw_receiver_b(params.gnss, rng), draw_odometer_b(params.odometry, rng), rig)


@dataclass(frozen=True)
class TripB:
    key: str
    upload: dict[str, Any]
    timestamps_s: np.ndarray  # (N,)
    true_poses_xyyaw_world: np.ndarray  # (N, 3)
    info: dict[str, Any]


def simulate_trip_b(
    world: World,
    frame: LocalFrame,
    index: TruthIndexB,
    params: FleetBParams,
    seed_seq: np.random.SeedSequence,
    vehicle: VehicleB,
    trip_id: str,
    started_at: str,
    trip_length_m: float,
) -> TripB:
    """Route, drive, sense with fleet b; the upload document and the truth."""
    rng_route, rng_drive, rng_gnss, rng_odom, rng_perc = (np.random.default_rng(s) for s in seed_seq.spawn(5))
    traffic = params.traffic
    loops = bool(rng_route.random() < traffic.loop_route_share)
    if loops:
        route = looping_route(world, rng_route, trip_length_m, traffic)
    else:
        route = random_route(world, rng_route, trip_length_m, traffic)
    truth = drive(route, rng_drive, traffic)
    t, poses = truth.timestamps_s, truth.poses_xyyaw_world
    gnss = simulate_gnss_b(t, poses, params.gnss, world.canyon_zones_xyr, rng_gnss, vehicle.receiver)
    odom, odom_info = simulate_odometry_b(t, poses, params.odometry, rng_odom, vehicle.odometer)
    elements, perc_info = perceive_trip_b(
        index, t, poses, truth.speed_mps, params.perception, np.array(vehicle.rig_xyyaw), rng_perc
    )
    upload = _upload(frame, t, gnss, odom, elements, params, vehicle.vehicle_id, trip_id, started_at)
    has_fix = gnss.status != GnssStatus.NONE
    err = np.linalg.norm(gnss.error_xy_m[has_fix], axis=1)
    key = f"{vehicle.vehicle_id}__{trip_id}"
    info = {
        "key": key,
        "frames": len(t),
        "duration_s": round(float(t[-1]), 1),
        "length_m": round(float(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1).sum()), 1),
        "route": "loop" if loops else "random",
        "gnss_status_share": {
            n: round(float(np.mean(gnss.status == s)), 3) for s, n in enumerate(_STATUS_NAMES)
        },
        "gnss_error_median_m": round(float(np.median(err)), 3) if err.size else None,
        "gnss_receiver": vehicle.receiver.kind,
        "gnss_latency_s": round(vehicle.receiver.latency_s, 4),
        "odometry": {k: round(v, 6) for k, v in odom_info.items()},
        "perception": perc_info,
        "rig_xyyaw": [round(v, 6) for v in vehicle.rig_xyyaw],
    }
    return TripB(key, upload, t, poses, info)


def _upload(
    frame: LocalFrame,
    t: np.ndarray,
    gnss,
    odom: np.ndarray,
    elements: list[list[dict]],
    params: FleetBParams,
    vehicle_id: str,
    trip_id: str,
    started_at: str,
) -> dict[str, Any]:
    status = gnss.status
    has_fix = status != GnssStatus.NONE
    # during an outage the receiver repeats its last fix (lat/lon are ignored then)
    idx = np.maximum.accumulate(np.where(has_fix, np.arange(len(t)), 0))
    lonlat_deg = frame.to_lonlat(gnss.position_xy_world[idx])
    lonlat = np.round(lonlat_deg, 9).tolist()
    course = np.round(frame.true_heading_deg(gnss.course_deg, lonlat_deg), 3)
    course = np.where(np.mod(course, 360.0) >= 359.9995, 0.0, np.mod(course, 360.0)).tolist()
    std = np.round(np.maximum(np.nan_to_num(gnss.std_m, nan=1.0), 0.001), 3).tolist()
    odom_r = np.column_stack([np.round(odom[:, :2], 3), np.round(odom[:, 2], 6)]).tolist()
    t_list = np.round(t, 3).tolist()
    codes = status.tolist()
    frames = []
    for k, tk in enumerate(t_list):
        g: dict[str, Any] = {"lat": lonlat[k][1], "lon": lonlat[k][0], "status": _STATUS_NAMES[codes[k]]}
        if codes[k] != GnssStatus.NONE:
            if not math.isnan(course[k]):
                g["heading_deg"] = course[k]
            g["std_m"] = std[k]
        o = odom_r[k]
        frames.append(
            {"t": tk, "gnss": g, "odom": {"x": o[0], "y": o[1], "yaw": o[2]}, "elements": elements[k]}
        )
    p = params.perception
    return {
        "schema_version": SCHEMA_VERSION,
        "vehicle_id": vehicle_id,
        "trip_id": trip_id,
        "started_at": started_at,
        "sensor_setup": {
            "model": "csr-sim fleet-b maptr-style bev instances",
            "bev_range_m": {"x": list(p.range_x_m), "y": list(p.range_y_m)},
            "points_per_instance": p.points_per_instance,
            "rate_hz": params.traffic.frame_rate_hz,
        },
        "frames": frames,
    }
