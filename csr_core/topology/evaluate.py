"""Measure topology generation on a scenario folder (contract section 5) against its truth.

    python -m csr_core.topology.evaluate SCENARIO_DIR [--poses truth|smoothed|aligned] [--cache FILE]
        [--lane-graph-figure PNG] [--validator-figure PNG] [--bbox X0,X1,Y0,Y1]

Per trip, single-trip reconstruction (``csr_core.single_trip``) gives the instances; with
``--poses truth`` its pose smoothing is replaced by the trip's TRUE poses (truth/poses), so the
instances carry perception and splicing errors only and the map scores are the fusion's own
error floor; with ``--poses smoothed`` they are placed with each trip's own GNSS-smoothed poses
(no multi-trip alignment); with ``--poses aligned`` by ``alignment.align_trips`` (each point
moved with the correction of the frame nearest to it; its match pairs go to the validator, as
in the pipeline). Then ``generate_topology`` and:

- map scores per type exactly as contract section 6 (``csr_core.metrics.map_scores``), for the
  fused map and, for reference, for all trips' instances overlaid (no fusion);
- the lane graph against the one the truth's centrelines give (``evaluate_lane_graph``):
  connection and split / merge precision and recall;
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
from csr_core.param_overrides import replace_fields
from csr_core.scenario import (
    geo_features_to_local,
    list_trip_files,
    load_trip,
    read_map_geojson,
    read_poses_dir,
    read_scenario_meta,
)
from csr_core.topology import (
    DEFAULT,
    SUSPECT,
    TopologyParams,
    TopologyResult,
    generate_topology,
    reposition_instances,
)
from csr_core.topology.evaluate_lane_graph import compare_lane_graphs, plot_comparison
from csr_core.types import ElementType, MapFeature

WRONG_SHARE = 0.2
CORRIDOR_INSIDE_M = 12.0  # truth is kept within 15 m of true frames; judge 3 m inside
LOCAL_RADIUS_M = 50.0  # diagnostic: the map offset shared by the instances this close


def trip_instances(
    scenario_dir: str | Path, poses: str = "truth", match_pairs_out: list | None = None
) -> dict:
    """trip key -> (instances, noise, poses used (N, 3), true poses (N, 3), started_at).

    ``poses``: ``truth`` (pose smoothing replaced by the true poses), ``smoothed`` (each trip's
    own), ``aligned`` (``alignment.align_trips`` over all trips, instances moved with it; its
    match pairs are appended to ``match_pairs_out`` when given, as the pipeline hands them to
    the validator)."""
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
        true_poses = np.column_stack(
            [frame.to_local(pt.lonlat_deg), frame.yaw_rad(pt.heading_deg, pt.lonlat_deg)]
        )
        if poses == "truth":
            rec = single_trip.reconstruct_trip(trip, frame, smoothed=SmoothedPoses.given(true_poses))
        else:
            rec = single_trip.reconstruct_trip(trip, frame)
        recs.append(rec)
        out[tf.key] = (rec.instances, rec.noise, rec.poses_xyyaw_world, true_poses, trip.started_at)
    if poses == "aligned":
        from csr_core.alignment import align_trips

        aligned = align_trips(recs)
        if match_pairs_out is not None:
            match_pairs_out.extend(aligned.match_pairs)
        for rec in recs:
            k = rec.trip.key
            if k not in aligned.poses_xyyaw_world:
                out.pop(k)
                continue
            to = aligned.poses_xyyaw_world[k]
            out[k] = (
                reposition_instances(rec.instances, rec.poses_xyyaw_world, to),
                rec.noise,
                to,
                out[k][3],
                out[k][4],
            )
    return out


def judge_instances(
    result: TopologyResult, truth_map, true_xy: np.ndarray
) -> list[tuple[MapFeature, bool, bool]]:
    """(instance, really wrong, wrong beyond the local map offset) for every judged instance
    (published or suppressed): only samples well inside the evaluated corridor
    (``CORRIDOR_INSIDE_M`` of a true frame: truth beyond 15 m is cut away) are judged;
    instances mostly outside are left out.

    The third value is a diagnostic, not the score: the instance judged again after removing
    the offset that the *other* instances within ``LOCAL_RADIUS_M`` share (least-squares
    translation from their samples' normal offsets to truth). An error shared by every trip
    in a region (the map as a whole placed off there) is invisible to checks that compare trips
    with each other; this separates it from errors of the instance itself."""
    from scipy.spatial import cKDTree

    frames = cKDTree(true_xy)
    judged: list[tuple[MapFeature, np.ndarray, np.ndarray]] = []
    normals, offsets, where = [], [], []  # per judged sample: truth normal, signed offset, (feature, xy)
    for etype in ElementType:
        feats = [f for f in (*result.features, *result.suppressed) if f.type == etype]
        if not feats:
            continue
        truth_xy, segs = metrics.truth_in_corridor([f for f in truth_map if f.type == etype], true_xy)
        tree = cKDTree(truth_xy) if len(truth_xy) >= 2 else None
        for f in feats:
            samples = metrics.sample_features([f])
            inside = frames.query(samples)[0] <= CORRIDOR_INSIDE_M
            if inside.mean() < 0.5:
                continue
            judged.append((f, samples[inside], segs))
            if tree is None:
                continue
            q = samples[inside]
            dist, i = tree.query(q, k=2, distance_upper_bound=2.0)
            ok = np.isfinite(dist).all(axis=1)
            if not ok.any():
                continue
            tan = truth_xy[i[ok, 1]] - truth_xy[i[ok, 0]]
            tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
            nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
            normals.append(nrm)
            offsets.append(((truth_xy[i[ok, 0]] - q[ok]) * nrm).sum(1))
            where.append(np.column_stack([np.full(ok.sum(), len(judged) - 1), q[ok]]))
    out = []
    nrm = np.concatenate(normals) if normals else np.zeros((0, 2))
    off = np.concatenate(offsets) if offsets else np.zeros(0)
    wh = np.concatenate(where) if where else np.zeros((0, 3))
    near = cKDTree(wh[:, 1:]) if len(wh) else None
    for k, (f, q, segs) in enumerate(judged):
        d = metrics.distances_to_segments(q, segs)
        wrong = float(np.mean(d > metrics.MATCH_THRESHOLD_M)) >= WRONG_SHARE
        shift = np.zeros(2)
        if near is not None:
            idx = np.array(near.query_ball_point(q[len(q) // 2], LOCAL_RADIUS_M), dtype=np.int64)
            idx = idx[wh[idx, 0] != k] if len(idx) else idx
            if len(idx) >= 20:
                a = nrm[idx].T @ nrm[idx]
                if np.linalg.eigvalsh(a)[0] > 0.1 * len(idx):  # constrained in both directions
                    shift = np.linalg.solve(a, nrm[idx].T @ off[idx])
        d_local = metrics.distances_to_segments(q + shift, segs)
        out.append((f, wrong, float(np.mean(d_local > metrics.MATCH_THRESHOLD_M)) >= WRONG_SHARE))
    return out


def judged_rows(judged: list[tuple[MapFeature, bool, bool]]) -> list[dict]:
    """One flat record per judged instance (``judge_instances``): its type, length, the truth's
    verdicts, whether it carries a suspect flag, and its scalar properties (support, coverage,
    trips that drove alongside, uncertainty, scatter, ...) as the map serves them."""
    rows = []
    for f, wrong, wrong_local in judged:
        pts = np.asarray(f.points_xy_world, float)
        flags = sorted(set(f.properties.get("flags", ())))
        rows.append(
            {
                "feature_id": f.feature_id,
                "type": f.type.value,
                "length_m": float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
                if len(pts) > 1
                else 0.0,
                "wrong": bool(wrong),
                "wrong_beyond_local_offset": bool(wrong_local),
                "suspect": bool(set(flags) & SUSPECT),
                "flags": flags,
                **{
                    k: v
                    for k, v in f.properties.items()
                    if isinstance(v, (bool, int, float, str)) and k not in ("flags", "feature_id")
                },
            }
        )
    return rows


def _recall_precision(wrong: np.ndarray, flagged: np.ndarray) -> dict:
    return {
        "wrong": int(wrong.sum()),
        "flagged": int(flagged.sum()),
        "recall": float((wrong & flagged).sum() / max(wrong.sum(), 1)),
        "precision": float((wrong & flagged).sum() / max(flagged.sum(), 1)),
    }


def validator_scores(
    result: TopologyResult,
    truth_map,
    true_xy: np.ndarray,
    judged: list[tuple[MapFeature, bool, bool]] | None = None,
) -> dict:
    """Recall and precision of the suspect flags against really wrong instances (module
    docstring). Diagnostics: per flag kind, how many judged instances carry it (``flagged``),
    how many of those are really wrong (``wrong``), and the same for the instances whose only
    suspect flag it is (``alone``, ``alone_wrong``); ``beyond_local_offset``: the same recall and
    precision against instances still wrong once the offset shared by the map around them is
    removed (``judge_instances``; ``judged``: its result, when already at hand)."""
    judged = judge_instances(result, truth_map, true_xy) if judged is None else judged
    w = np.array([wr for _, wr, _ in judged], bool)
    w_local = np.array([wl for _, _, wl in judged], bool)
    kinds = [set(f.properties.get("flags", ())) for f, _, _ in judged]
    fl = np.array([bool(k & SUSPECT) for k in kinds], bool)
    per_flag = {}
    for kind in sorted(set().union(*kinds)) if kinds else ():
        has = np.array([kind in k for k in kinds], bool)
        alone = np.array([(k & SUSPECT) == {kind} for k in kinds], bool)
        per_flag[kind] = {
            "flagged": int(has.sum()),
            "wrong": int((has & w).sum()),
            "alone": int(alone.sum()),
            "alone_wrong": int((alone & w).sum()),
        }
    return {
        "instances": int(len(w)),
        **_recall_precision(w, fl),
        "per_flag": per_flag,
        "beyond_local_offset": _recall_precision(w_local, fl),
    }


def cached_trip_instances(scenario_dir: str | Path, poses: str, cache: str | None) -> tuple[dict, tuple]:
    """``trip_instances`` and the alignment's match pairs (``()`` unless ``poses="aligned"``),
    read from the pickle ``cache`` if it exists, else computed and written there."""
    if cache and Path(cache).exists():
        stored = pickle.loads(Path(cache).read_bytes())
        if "trips" in stored and "match_pairs" in stored:
            return stored["trips"], tuple(stored["match_pairs"])
        return stored, ()  # written before the match pairs were kept
    pairs: list = []
    data = trip_instances(scenario_dir, poses, pairs)
    if cache:
        Path(cache).write_bytes(pickle.dumps({"trips": data, "match_pairs": pairs}))
    return data, tuple(pairs)


def evaluate_scenario(
    scenario_dir: str | Path,
    poses: str = "truth",
    cache: str | None = None,
    lane_graph_figure: str | Path | None = None,
    figure_bbox_xy: tuple[float, float, float, float] | None = None,
    validator_figure: str | Path | None = None,
    params: TopologyParams = DEFAULT,
    instances_jsonl: str | Path | None = None,
    keep_instances: bool = False,
) -> dict:
    """The figures of the module docstring; ``lane_graph_figure``: also a picture of the lane
    graph against the truth's there (``evaluate_lane_graph.plot_comparison``, zoomed to
    ``figure_bbox_xy`` in the scenario's local frame if given); ``validator_figure``: a picture
    of the judged instances, caught / missed / false alarm (``validator_figure.plot_validator``);
    ``params``: the topology's (``--param NAME=VALUE``); ``instances_jsonl``: also every judged
    instance as a line of JSON (``judged_rows``), for studies of what tells the wrong ones apart;
    ``keep_instances``: the same records under ``"instances"`` in the result."""
    scenario_dir = Path(scenario_dir)
    data, match_pairs = cached_trip_instances(scenario_dir, poses, cache)
    meta = read_scenario_meta(scenario_dir)
    truth_map = geo_features_to_local(read_map_geojson(scenario_dir / "truth" / "map.geojson"), meta.frame)
    true_xy = np.concatenate([v[3][:, :2] for v in data.values()])
    t0 = time.perf_counter()
    result = generate_topology(
        {k: v[0] for k, v in data.items()},
        {k: v[1] for k, v in data.items()},
        params,
        trip_times={k: v[4] for k, v in data.items()},
        paths_xy_per_trip={k: v[2][:, :2] for k, v in data.items()},
        match_pairs=match_pairs,
    )
    seconds = time.perf_counter() - t0
    # contract section 6 "aligned" figures: one rigid SE(2) of all poses onto truth, applied to the map
    truth_T_est = metrics.umeyama_se2(np.concatenate([v[2][:, :2] for v in data.values()]), true_xy)
    result = replace(
        result,
        features=metrics.transform_features(truth_T_est, result.features),
        suppressed=metrics.transform_features(truth_T_est, result.suppressed),
    )
    fused = metrics.map_scores(result.features, truth_map, true_xy)
    overlaid = metrics.map_scores(
        metrics.transform_features(
            truth_T_est, [MapFeature(i.type, i.points_xy_world, i.style) for v in data.values() for i in v[0]]
        ),
        truth_map,
        true_xy,
    )

    def table(ms: metrics.MapScores) -> dict:
        return {
            "mcd": ms.mcd,
            **{
                t.value: {"cd": s.cd, "completeness": s.completeness, "correctness": s.correctness}
                for t, s in ms.per_type.items()
                if np.isfinite(s.cd)
            },
        }

    lane_graph = compare_lane_graphs(result.features, truth_map, true_xy, CORRIDOR_INSIDE_M, params)
    if lane_graph_figure is not None:
        plot_comparison(lane_graph, lane_graph_figure, figure_bbox_xy)
    judged = judge_instances(result, truth_map, true_xy)
    rows = judged_rows(judged) if instances_jsonl is not None or keep_instances else []
    if instances_jsonl is not None:
        Path(instances_jsonl).write_text("".join(json.dumps(row) + "\n" for row in rows))
    if validator_figure is not None:
        from csr_core.topology.validator_figure import plot_validator

        plot_validator(judged, truth_map, true_xy, validator_figure, meta.name, figure_bbox_xy)
    return {
        "scenario": meta.name,
        "poses": poses,
        "truth_T_est": [round(float(v), 4) for v in truth_T_est],
        "trips": len(data),
        "features": len(result.features),
        "rejected_members": len(result.rejected_members),
        "topology_seconds": seconds,
        "fused": table(fused),
        "overlaid_instances": table(overlaid),
        "validator": validator_scores(result, truth_map, true_xy, judged),
        "lane_graph": {
            "lanes": result.lane_graph.graph.number_of_nodes(),
            "splits": len(result.lane_graph.split_points_xy),
            "merges": len(result.lane_graph.merge_points_xy),
            "against_truth": lane_graph.scores(),
        },
        **({"instances": rows} if keep_instances else {}),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--poses", choices=("truth", "smoothed", "aligned"), default="truth")
    ap.add_argument("--cache", help="pickle of the trips' instances (written if missing)")
    ap.add_argument("--lane-graph-figure", metavar="PNG", help="also draw the lane graph against the truth's")
    ap.add_argument(
        "--validator-figure",
        metavar="PNG",
        help="also draw the judged instances: flagged and wrong, flagged and right, missed",
    )
    ap.add_argument(
        "--bbox", metavar="X0,X1,Y0,Y1", help="zoom the figures to this box (metres, local frame)"
    )
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a TopologyParams field changed, e.g. DERIVE_CENTERLINES=false (repeatable)",
    )
    ap.add_argument(
        "--instances-jsonl",
        metavar="FILE",
        help="also write every judged instance (verdicts, flags, support, ...) as JSON lines",
    )
    args = ap.parse_args(argv)
    try:
        params = replace_fields(DEFAULT, args.param)
    except ValueError as exc:
        ap.error(str(exc))
    bbox = None
    if args.bbox:
        try:
            x0, x1, y0, y1 = (float(v) for v in args.bbox.split(","))
        except ValueError:
            ap.error(f"--bbox must be four numbers X0,X1,Y0,Y1, got {args.bbox!r}")
        bbox = (x0, x1, y0, y1)
    r = evaluate_scenario(
        args.scenario,
        args.poses,
        args.cache,
        args.lane_graph_figure,
        bbox,
        args.validator_figure,
        params,
        args.instances_jsonl,
    )
    print(json.dumps(r, indent=1))  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
