"""Measure topology generation on a scenario folder (contract section 5) against its truth.

    python -m csr_core.topology.evaluate SCENARIO_DIR [--poses truth|smoothed|aligned] [--cache FILE]

Per trip, single-trip reconstruction (``csr_core.single_trip``) gives the instances; with
``--poses truth`` its pose smoothing is replaced by the trip's TRUE poses (truth/poses), so the
instances carry perception and splicing errors only and the map scores are the fusion's own
error floor; with ``--poses smoothed`` they are placed with each trip's own GNSS-smoothed poses
(no multi-trip alignment); with ``--poses aligned`` by ``alignment.align_trips`` (each point
moved with the correction of the frame nearest to it). Then ``generate_topology`` and:

- map scores per type exactly as contract section 6 (``csr_core.metrics.map_scores``), for the
  fused map and, for reference, for all trips' instances overlaid (no fusion);
- the validator: an instance is *really wrong* when at least ``WRONG_SHARE`` of its 0.5 m
  samples are more than 0.5 m from the truth of its type (inside the evaluated corridor);
  *flagged* when it has a suspect flag (only instances mostly within 12 m of a true frame
  are judged: truth beyond 15 m is cut away by the contract) (``validation.SUSPECT``). Recall = flagged wrong / wrong,
  precision = flagged wrong / flagged.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from csr_core import metrics
from csr_core.scenario import (
    geo_features_to_local,
    list_trip_files,
    load_trip,
    read_map_geojson,
    read_poses_dir,
    read_scenario_meta,
)
from csr_core.se2 import heading_deg_to_yaw_rad
from csr_core.topology import SUSPECT, TopologyResult, generate_topology, reposition_instances
from csr_core.types import ElementType, MapFeature

WRONG_SHARE = 0.2
CORRIDOR_INSIDE_M = 12.0  # truth is kept within 15 m of true frames; judge 3 m inside


def trip_instances(scenario_dir: str | Path, poses: str = "truth") -> dict:
    """trip key -> (instances, noise, poses used (N, 3), true poses (N, 3), started_at).

    ``poses``: ``truth`` (pose smoothing replaced by the true poses), ``smoothed`` (each trip's
    own), ``aligned`` (``alignment.align_trips`` over all trips, instances moved with it)."""
    import csr_core.single_trip as single_trip
    from csr_core.single_trip.pose_graph import SmoothedPoses

    scenario_dir = Path(scenario_dir)
    meta = read_scenario_meta(scenario_dir)
    frame = meta.frame
    truth = read_poses_dir(scenario_dir / "truth" / "poses")
    out = {}
    recs = []
    for tf in list_trip_files(scenario_dir):
        trip = load_trip(tf)
        pt = truth[tf.key]
        true_poses = np.column_stack([frame.to_local(pt.lonlat_deg), heading_deg_to_yaw_rad(pt.heading_deg)])
        if poses == "truth":
            n = len(true_poses)
            fixed = SmoothedPoses(true_poses, np.zeros(n), np.zeros(n), np.ones(n, bool), np.zeros(3))
            rec = single_trip.reconstruct_trip(trip, frame, smoothed=fixed)
        else:
            rec = single_trip.reconstruct_trip(trip, frame)
        recs.append(rec)
        out[tf.key] = (rec.instances, rec.noise, rec.poses_xyyaw_world, true_poses, trip.started_at)
    if poses == "aligned":
        from csr_core.alignment import align_trips

        aligned = align_trips(recs)
        for rec in recs:
            k = rec.trip.key
            if k not in aligned.poses_xyyaw_world:
                out.pop(k)
                continue
            to = aligned.poses_xyyaw_world[k]
            out[k] = (reposition_instances(rec.instances, rec.poses_xyyaw_world, to), rec.noise, to, out[k][3], out[k][4])
    return out


def validator_scores(result: TopologyResult, truth_map, true_xy: np.ndarray) -> dict:
    """Recall and precision of the suspect flags against really wrong instances (module
    docstring). Only samples well inside the evaluated corridor (``CORRIDOR_INSIDE_M`` of a true
    frame: truth beyond 15 m is cut away) are judged; instances mostly outside are left out."""
    from scipy.spatial import cKDTree

    frames = cKDTree(true_xy)
    wrong, flagged = [], []
    for etype in ElementType:
        feats = [f for f in (*result.features, *result.suppressed) if f.type == etype]
        if not feats:
            continue
        _, segs = metrics.truth_in_corridor([f for f in truth_map if f.type == etype], true_xy)
        for f in feats:
            samples = metrics.sample_features([f])
            inside = frames.query(samples)[0] <= CORRIDOR_INSIDE_M
            if inside.mean() < 0.5:
                continue
            d = metrics.distances_to_segments(samples[inside], segs)
            wrong.append(float(np.mean(d > metrics.MATCH_THRESHOLD_M)) >= WRONG_SHARE)
            flagged.append(bool(set(f.properties.get("flags", ())) & SUSPECT))
    w, fl = np.array(wrong), np.array(flagged)
    return {"instances": int(len(w)), "wrong": int(w.sum()), "flagged": int(fl.sum()),
            "recall": float((w & fl).sum() / max(w.sum(), 1)), "precision": float((w & fl).sum() / max(fl.sum(), 1))}


def evaluate_scenario(scenario_dir: str | Path, poses: str = "truth", cache: str | None = None) -> dict:
    scenario_dir = Path(scenario_dir)
    if cache and Path(cache).exists():
        data = pickle.loads(Path(cache).read_bytes())
    else:
        data = trip_instances(scenario_dir, poses)
        if cache:
            Path(cache).write_bytes(pickle.dumps(data))
    meta = read_scenario_meta(scenario_dir)
    truth_map = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), meta.frame)
    true_xy = np.concatenate([v[3][:, :2] for v in data.values()])
    t0 = time.perf_counter()
    result = generate_topology({k: v[0] for k, v in data.items()}, {k: v[1] for k, v in data.items()},
                               trip_times={k: v[4] for k, v in data.items()},
                               paths_xy_per_trip={k: v[2][:, :2] for k, v in data.items()})
    seconds = time.perf_counter() - t0
    # contract section 6 "aligned" figures: one rigid SE(2) of all poses onto truth, applied to the map
    truth_T_est = metrics.umeyama_se2(np.concatenate([v[2][:, :2] for v in data.values()]), true_xy)
    result = replace(result, features=metrics.transform_features(truth_T_est, result.features),
                     suppressed=metrics.transform_features(truth_T_est, result.suppressed))
    fused = metrics.map_scores(result.features, truth_map, true_xy)
    overlaid = metrics.map_scores(metrics.transform_features(truth_T_est, [
        MapFeature(i.type, i.points_xy_world, i.style) for v in data.values() for i in v[0]]), truth_map, true_xy)

    def table(ms: metrics.MapScores) -> dict:
        return {"mcd": ms.mcd, **{t.value: {"cd": s.cd, "completeness": s.completeness, "correctness": s.correctness}
                                  for t, s in ms.per_type.items() if np.isfinite(s.cd)}}

    return {"scenario": meta.name, "poses": poses, "truth_T_est": [round(float(v), 4) for v in truth_T_est],
            "trips": len(data), "features": len(result.features), "rejected_members": len(result.rejected_members),
            "topology_seconds": seconds, "fused": table(fused), "overlaid_instances": table(overlaid),
            "validator": validator_scores(result, truth_map, true_xy),
            "lane_graph": {"lanes": result.lane_graph.graph.number_of_nodes(),
                           "splits": len(result.lane_graph.split_points_xy),
                           "merges": len(result.lane_graph.merge_points_xy)}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--poses", choices=("truth", "smoothed", "aligned"), default="truth")
    ap.add_argument("--cache", help="pickle of the trips' instances (written if missing)")
    args = ap.parse_args(argv)
    r = evaluate_scenario(args.scenario, args.poses, args.cache)
    print(json.dumps(r, indent=1))  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
