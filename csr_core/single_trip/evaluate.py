"""Measure single-trip reconstruction on a scenario folder (contract section 5) against its truth.

    python -m csr_core.single_trip.evaluate SCENARIO_DIR [SCENARIO_DIR ...] [--true-poses] [--json]

Per scenario, over all trips (trip-level figures, pooled):
- ATE / RPE (10 m, contract section 6 definitions via ``csr_core.metrics``) of the smoothed
  poses and of the raw GNSS (frames without a fix take the last fix, as a receiver log would);
  no global alignment (raw figures).
- jumps: frames whose raw GNSS is more than 5 m from truth; the largest smoothed error there.
- instances, scored per type with the contract map metric (0.5 m samples, 0.5 m threshold)
  against the truth kept within 15 m of the trip's true frames (the lateral reach of the BEV
  range); correctness and completeness pooled over trips and over all types, twice:
  - ``rigid`` (the single-trip targets' figure): each trip's instances moved by the trip's own rigid offset
    (SE(2) least squares of its smoothed onto its true positions);
  - ``local`` (diagnostic): each instance moved instead by the rigid offset of the trip's poses
    over the frames from ``local_offset_m / 2`` of travel before it was first seen to
    ``local_offset_m / 2`` after it was last seen. The within-trip GNSS drift (a Gauss-Markov
    bias of tens of seconds) is not a rigid offset of the whole trip, but it is nearly one over
    a sub-map, and III-D aligns trips sub-map by sub-map.
- ``true_poses``: the same with the pose smoothing replaced by the true poses (the element
  stages alone; the pose figures are then zero).
- noise (with ``true_poses`` only, where a point's error is the perception's alone):
  per line type, the lateral sigma the stage estimated (``TripReconstruction.noise``, mean
  over trips) against the sigma of the detections' distances to the truth (1.4826 x the
  median distance of their points, so ghosts and false positives do not count). The estimate
  is of the frame-to-frame noise: the share of the error that an element keeps through all
  the frames of a trip cannot be seen within the trip, so the estimate is expected lower.
- speed: CPU seconds (``time.process_time``, one core; the host is shared) of
  ``reconstruct_trip`` per km of trip, in all and per stage (``single_trip.STAGES``: poses,
  tracking, splicing, unseen cut, noise); the compiled kernels are loaded first
  (``compiled.warm_up``), as a worker process loads them once.

``csr bench-single-trip`` runs this over the benchmark's fleets and writes BENCHMARKS.md's
single-trip section.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from csr_core import metrics, se2
from csr_core.geo import LocalFrame
from csr_core.param_overrides import replace_fields
from csr_core.scenario import (
    geo_features_to_local,
    list_trip_files,
    load_trip,
    read_map_geojson,
    read_poses_dir,
    read_scenario_meta,
)
from csr_core.single_trip import STAGES, reconstruct_trip
from csr_core.single_trip.compiled.warm_up import warm_up
from csr_core.single_trip.params import DEFAULT, SingleTripParams
from csr_core.single_trip.pose_graph import SmoothedPoses
from csr_core.types import ElementType, GnssStatus, MapFeature, Trip

JUMP_M = 5.0
LOCAL_OFFSET_M = 100.0  # about a sub-map's extent (a circle of 50 m radius, III-D)


@dataclass(frozen=True, slots=True)
class LoadedTrip:
    trip: Trip
    true_poses_xyyaw: np.ndarray  # (N, 3) world (the scenario's local plane)


@dataclass(frozen=True, slots=True)
class LoadedScenario:
    """A scenario read once: its trips, their true poses and the truth map, in its local plane."""

    name: str
    frame: LocalFrame
    trips: tuple[LoadedTrip, ...]
    truth_map: tuple[MapFeature, ...]


def load_scenario(scenario_dir: str | Path) -> LoadedScenario:
    meta = read_scenario_meta(scenario_dir)
    frame = meta.frame
    truth_poses = read_poses_dir(Path(scenario_dir) / "truth" / "poses")
    truth_map = geo_features_to_local(read_map_geojson(Path(scenario_dir) / "truth" / "map.geojson"), frame)
    trips = []
    for tf in list_trip_files(scenario_dir):
        track = truth_poses[tf.key]
        true_xy = frame.to_local(track.lonlat_deg)
        trips.append(
            LoadedTrip(
                load_trip(tf), np.column_stack([true_xy, frame.yaw_rad(track.heading_deg, track.lonlat_deg)])
            )
        )
    return LoadedScenario(meta.name, frame, tuple(trips), tuple(truth_map))


def _forward_fill(xy: np.ndarray, has_fix: np.ndarray) -> np.ndarray:
    idx = np.where(has_fix, np.arange(len(xy)), 0)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.argmax(has_fix)) if has_fix.any() else 0
    idx[:first] = first
    return xy[idx]


def _local_offsets(instances, est_xy: np.ndarray, true_xy: np.ndarray, window_m: float) -> list[np.ndarray]:
    """Per instance: the SE(2) of est onto true over the frames within window_m / 2 of travel of
    the frames that saw it."""
    travel = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(true_xy, axis=0), axis=1))]
    out = []
    for inst in instances:
        i0 = int(np.searchsorted(travel, travel[inst.first_frame] - window_m / 2))
        i1 = int(np.searchsorted(travel, travel[inst.last_frame] + window_m / 2))
        out.append(metrics.umeyama_se2(est_xy[i0 : i1 + 1], true_xy[i0 : i1 + 1]))
    return out


NOISE_TYPES = (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE)


def detection_distances_m(trip: Trip, poses_xyyaw: np.ndarray, truth_map, etype: ElementType) -> np.ndarray:
    """Distance of every detected point of type ``etype`` (placed with ``poses_xyyaw``, the
    true poses) to the truth of that type, capped at ``metrics.CD_CAP_M``; ``(P,)``."""
    pts = [
        se2.transform_points(poses_xyyaw[k], e.points_xy_vehicle)
        for k, frame_elements in enumerate(trip.elements)
        for e in frame_elements
        if e.type == etype
    ]
    segments = metrics._segments(metrics._as_chains([f for f in truth_map if f.type == etype]))
    if not pts or not len(segments):
        return np.zeros(0)
    return metrics.distances_to_segments(np.vstack(pts), segments)


class _InstanceHits:
    """Per type: samples within 0.5 m on the predicted side and on the truth side, pooled."""

    def __init__(self) -> None:
        self.hits = {t: np.zeros(4) for t in ElementType}  # correct, n_pred, complete, n_truth

    def add(self, predicted: list[MapFeature], truth_map, true_xy: np.ndarray) -> None:
        for etype in ElementType:
            t_feats = [f for f in truth_map if f.type == etype]
            p_feats = [f for f in predicted if f.type == etype]
            samples, segs = metrics.truth_in_corridor(t_feats, true_xy)
            if not len(samples) and not p_feats:
                continue
            d_pred = metrics.distances_to_segments(metrics.sample_features(p_feats), segs)
            d_truth = metrics.distances_to_segments(samples, metrics._segments(metrics._as_chains(p_feats)))
            self.hits[etype] += np.array(
                [
                    np.sum(d_pred <= metrics.MATCH_THRESHOLD_M),
                    len(d_pred),
                    np.sum(d_truth <= metrics.MATCH_THRESHOLD_M),
                    len(d_truth),
                ],
                float,
            )

    def scores(self) -> dict:
        total = np.sum(np.stack(list(self.hits.values())), axis=0)
        return {
            "correctness": float(total[0] / max(total[1], 1)),
            "completeness": float(total[2] / max(total[3], 1)),
            "per_type": {
                t.value: {
                    "correctness": float(h[0] / h[1]) if h[1] else None,
                    "completeness": float(h[2] / h[3]) if h[3] else None,
                }
                for t, h in self.hits.items()
                if h[1] or h[3]
            },
        }


def evaluate_loaded(
    scenario: LoadedScenario,
    params: SingleTripParams = DEFAULT,
    true_poses: bool = False,
    local_offset_m: float = LOCAL_OFFSET_M,
) -> dict:
    """The figures of the module docstring for one loaded scenario. ``true_poses``: the pose
    smoothing is replaced by the true poses, which isolates the element stages (tracking,
    splicing, ghost rejection) from the pose error."""
    frame = scenario.frame
    ate_s, ate_g, rpe_s, rpe_g, jump_err, ate_local = [], [], [], [], [], []
    rigid, local = _InstanceHits(), _InstanceHits()
    estimated: dict[ElementType, list[float]] = {t: [] for t in NOISE_TYPES}
    observed: dict[ElementType, list[np.ndarray]] = {t: [] for t in NOISE_TYPES}
    seconds, km = 0.0, 0.0
    stage_seconds = dict.fromkeys(STAGES, 0.0)
    warm_up()  # the compiled kernels loaded before the clock starts, as the modules are imported
    for loaded in scenario.trips:
        trip, true_xy = loaded.trip, loaded.true_poses_xyyaw[:, :2]
        fixed = SmoothedPoses.given(loaded.true_poses_xyyaw) if true_poses else None
        t0 = time.process_time()  # CPU seconds of this process: one core, unaffected by other load
        rec = reconstruct_trip(trip, frame, params, smoothed=fixed)
        seconds += time.process_time() - t0
        for stage, cpu_s in rec.diagnostics["cpu_seconds"].items():
            stage_seconds[stage] += cpu_s
        km += float(np.linalg.norm(np.diff(true_xy, axis=0), axis=1).sum()) / 1000.0
        est_xy = rec.poses_xyyaw_world[:, :2]
        gnss_xy = _forward_fill(frame.to_local(trip.gnss_lonlat_deg), trip.gnss_status != GnssStatus.NONE)
        truth_T_est = metrics.umeyama_se2(est_xy, true_xy)
        ate_s.append(metrics.position_errors(est_xy, true_xy))
        ate_local.append(metrics.position_errors(metrics.apply_se2(truth_T_est, est_xy), true_xy))
        ate_g.append(metrics.position_errors(gnss_xy, true_xy))
        rpe_s.append(metrics.rpe_errors(est_xy, true_xy))
        rpe_g.append(metrics.rpe_errors(gnss_xy, true_xy))
        jumps = (ate_g[-1] > JUMP_M) & (trip.gnss_status != GnssStatus.NONE)
        jump_err.append(ate_s[-1][jumps])
        if true_poses:
            for t in NOISE_TYPES:
                if t in rec.noise and rec.noise[t].n_samples:
                    estimated[t].append(rec.noise[t].lateral_sigma_m)
                observed[t].append(
                    detection_distances_m(trip, loaded.true_poses_xyyaw, scenario.truth_map, t)
                )
        for hits, offsets in (
            (rigid, [truth_T_est] * len(rec.instances)),
            (local, _local_offsets(rec.instances, est_xy, true_xy, local_offset_m)),
        ):
            predicted = [
                MapFeature(i.type, metrics.apply_se2(T, i.points_xy_world), i.style)
                for i, T in zip(rec.instances, offsets, strict=True)
            ]
            hits.add(predicted, scenario.truth_map, true_xy)

    def rms(parts: list[np.ndarray]) -> float:
        a = np.concatenate(parts) if parts else np.zeros(0)
        return float(np.sqrt(np.mean(a * a))) if len(a) else float("nan")

    je = np.concatenate(jump_err) if jump_err else np.zeros(0)
    noise = {}
    for t in NOISE_TYPES:
        d = np.concatenate(observed[t]) if observed[t] else np.zeros(0)
        d = d[d < metrics.CD_CAP_M]  # at the cap: not a view of a true element (or beyond the truth kept)
        if estimated[t] and len(d):
            noise[t.value] = {
                "estimated_lateral_sigma_m": float(np.mean(estimated[t])),
                "observed_lateral_sigma_m": float(1.4826 * np.median(d)),
            }
    return {
        "scenario": scenario.name,
        "true_poses": true_poses,
        "trips": len(ate_s),
        "km": round(km, 2),
        "ate_raw_gnss_m": rms(ate_g),
        "ate_smoothed_m": rms(ate_s),
        "ate_trip_aligned_m": rms(ate_local),
        "rpe_raw_gnss_m": rms(rpe_g),
        "rpe_smoothed_m": rms(rpe_s),
        "jump_frames": int(len(je)),
        "jump_max_smoothed_err_m": float(je.max()) if len(je) else float("nan"),
        "rigid": rigid.scores(),
        "local": local.scores(),
        "local_offset_m": local_offset_m,
        "noise": noise,
        "seconds_per_km": seconds / max(km, 1e-9),
        "stage_seconds_per_km": {stage: v / max(km, 1e-9) for stage, v in stage_seconds.items()},
    }


def evaluate_scenario(
    scenario_dir: str | Path,
    params: SingleTripParams = DEFAULT,
    true_poses: bool = False,
    local_offset_m: float = LOCAL_OFFSET_M,
) -> dict:
    """:func:`evaluate_loaded` on a scenario folder."""
    return evaluate_loaded(load_scenario(scenario_dir), params, true_poses, local_offset_m)


def pose_only(scenario_dir: str | Path, params: SingleTripParams = DEFAULT) -> dict:
    """ATE / trip-aligned ATE / RPE of the smoothed poses only (quick parameter studies)."""
    from csr_core.single_trip.pose_graph import smooth_poses

    meta = read_scenario_meta(scenario_dir)
    frame = meta.frame
    truth_poses = read_poses_dir(Path(scenario_dir) / "truth" / "poses")
    a, al, r = [], [], []
    for tf in list_trip_files(scenario_dir):
        trip = load_trip(tf)
        true_xy = frame.to_local(truth_poses[tf.key].lonlat_deg)
        sp = smooth_poses(
            trip.timestamps_s,
            frame.to_local(trip.gnss_lonlat_deg),
            trip.fix_status,
            trip.gnss_std_m,
            frame.grid_heading_deg(trip.gnss_heading_deg, trip.gnss_lonlat_deg),
            trip.odom_xyyaw,
            params,
        )
        est = sp.poses_xyyaw_world[:, :2]
        a.append(metrics.position_errors(est, true_xy))
        al.append(metrics.position_errors(metrics.apply_se2(metrics.umeyama_se2(est, true_xy), est), true_xy))
        r.append(metrics.rpe_errors(est, true_xy))
    rms = lambda x: float(np.sqrt(np.mean(np.concatenate(x) ** 2)))  # noqa: E731
    return {"ate": rms(a), "ate_trip_aligned": rms(al), "rpe": rms(r)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="+")
    ap.add_argument("--json", action="store_true", help="one JSON object per scenario")
    ap.add_argument(
        "--true-poses",
        action="store_true",
        help="replace the pose smoothing by the true poses (element stages alone)",
    )
    ap.add_argument(
        "--local-offset-m",
        type=float,
        default=LOCAL_OFFSET_M,
        help="travel around an instance over which the 'local' figures remove the pose offset "
        f"(default {LOCAL_OFFSET_M:g}; the issue's figure is 'rigid', the trip's own offset)",
    )
    ap.add_argument(
        "--gnss-bias-state",
        action=argparse.BooleanOptionalAction,
        default=DEFAULT.GNSS_BIAS_STATE,
        help="the last pose solve with the GNSS error as a Gauss-Markov state (gnss_bias.py; "
        f"default {DEFAULT.GNSS_BIAS_STATE})",
    )
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a SingleTripParams field to change (repeatable), e.g. DASH_CHAINING=false",
    )
    args = ap.parse_args(argv)
    try:
        params = replace_fields(replace(DEFAULT, GNSS_BIAS_STATE=args.gnss_bias_state), args.param)
    except ValueError as exc:
        ap.error(str(exc))
    cols = (
        "scenario",
        "trips",
        "km",
        "ate_raw_gnss_m",
        "ate_smoothed_m",
        "ate_trip_aligned_m",
        "rpe_raw_gnss_m",
        "rpe_smoothed_m",
        "jump_frames",
        "jump_max_smoothed_err_m",
        "rigid",
        "local",
        "seconds_per_km",
    )
    if not args.json:
        print("| " + " | ".join(cols) + " |")  # noqa: T201
        print("|" + "---|" * len(cols))  # noqa: T201
    for sc in args.scenarios:
        r = evaluate_scenario(sc, params, true_poses=args.true_poses, local_offset_m=args.local_offset_m)
        if args.json:
            print(json.dumps(r))  # noqa: T201
            continue
        cells = []
        for c in cols:
            v = r[c]
            if isinstance(v, dict):  # correctness / completeness
                cells.append(f"{v['correctness']:.3f} / {v['completeness']:.3f}")
            else:
                cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")  # noqa: T201
        for name in ("rigid", "local"):
            print(f"  per type, {name}: " + json.dumps(r[name]["per_type"]))  # noqa: T201
        print(  # noqa: T201
            "  CPU s/km per stage: "
            + ", ".join(
                f"{k} {v:.3f}"  # noqa: T201
                for k, v in r["stage_seconds_per_km"].items()
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
