"""Measure the lane graph against the truth's centrelines (``topology.evaluate`` calls it).

The truth has no lane graph of its own, only directed centrelines: its graph is built from
them by the same ``build_lane_graph``, so what is compared is what the fused centrelines
connect, not how the builder reads a junction. Compared are *connections*: successor edges
(where one lane hands over to another: a junction, a split, a merge; lanes are centrelines cut
where others start or end on them), each as the point where it happens, the heading in, and
where the lane it hands over to is ``LOOKAHEAD_M`` on (a turn lane leaves its through lane
tangentially: only further on do the two part).

- precision: of the map's connections (inside the evaluated corridor), the share where the
  truth goes on the same way: a truth connection within ``MATCH_M``, heading in within
  ``MATCH_ANGLE_RAD``, its lane ``LOOKAHEAD_M`` on within ``MATCH_M``; or a truth lane running
  through the point that way (the map's centreline is in two pieces where the truth's is one);
- recall: of the truth's connections (on centrelines inside the corridor), the share the map
  has, the same way round;
- split and merge points: matched one way and the other within ``MATCH_M``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.lane_graph import (
    SUCCESSOR,
    LaneGraph,
    build_lane_graph,
    end_heading,
    sampled_with_tangents,
)
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

MATCH_M = 2.0  # a connection is where the other graph has one within this
MATCH_ANGLE_RAD = math.radians(30.0)
LOOKAHEAD_M = 10.0
SPACING_M = 0.5


def connections(lane_graph: LaneGraph) -> np.ndarray:
    """``(C, 6)`` rows x, y, heading-in x, y, and the point ``LOOKAHEAD_M`` along the lane handed
    over to (its end if shorter), of the successor edges (at the end of the lane handing over)."""
    g = lane_graph.graph
    rows = []
    for u, v, kind in g.edges(data="kind"):
        if kind != SUCCESSOR:
            continue
        pu = resample_polyline(np.asarray(g.nodes[u]["points_xy_world"], float), SPACING_M)
        pv = resample_polyline(np.asarray(g.nodes[v]["points_xy_world"], float), SPACING_M)
        if len(pu) < 2 or len(pv) < 2:
            continue
        rows.append(np.r_[pu[-1], end_heading(pu, True), pv[min(len(pv) - 1, int(LOOKAHEAD_M / SPACING_M))]])
    return np.array(rows).reshape(-1, 6)


def _lane_samples(lane_graph: LaneGraph) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All lanes sampled every ``SPACING_M``: points (P, 2), unit tangents (P, 2), the point
    ``LOOKAHEAD_M`` further along the lane (its end if shorter) (P, 2), and the distance to the
    lane's start (P,)."""
    pts, tans, ahead, from_start = [], [], [], []
    k = int(LOOKAHEAD_M / SPACING_M)
    for _, data in lane_graph.graph.nodes(data=True):
        p, t = sampled_with_tangents(data["points_xy_world"], SPACING_M)
        if len(p) < 2:
            continue
        pts.append(p)
        tans.append(t)
        ahead.append(p[np.minimum(np.arange(len(p)) + k, len(p) - 1)])
        from_start.append(np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    return np.concatenate(pts), np.concatenate(tans), np.concatenate(ahead), np.concatenate(from_start)


def _found(rows: np.ndarray, other_rows: np.ndarray,
           other_lanes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Per connection of ``rows``: does the other graph go on the same way there (a connection
    there, or a lane through the point, heading in alike and ``LOOKAHEAD_M`` on at the same
    place)."""
    cos_max = math.cos(MATCH_ANGLE_RAD)
    out = np.zeros(len(rows), dtype=bool)
    if not len(rows):
        return out
    if len(other_rows):
        for i, hits in enumerate(cKDTree(other_rows[:, :2]).query_ball_point(rows[:, :2], MATCH_M)):
            h = other_rows[hits]
            out[i] = bool(((h[:, 2:4] @ rows[i, 2:4] >= cos_max)
                           & (np.linalg.norm(h[:, 4:6] - rows[i, 4:6], axis=1) <= MATCH_M)).any())
    pts, tans, ahead, from_start = other_lanes
    if len(pts):
        for i, hits in enumerate(cKDTree(pts).query_ball_point(rows[:, :2], MATCH_M)):
            if out[i] or not hits:
                continue
            hits = np.asarray(hits)
            hits = hits[from_start[hits] >= MATCH_M]  # through the point, not starting at it
            out[i] = bool(((tans[hits] @ rows[i, 2:4] >= cos_max)
                           & (np.linalg.norm(ahead[hits] - rows[i, 4:6], axis=1) <= MATCH_M)).any())
    return out


def _points_matched(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if not len(a):
        return np.zeros(0, dtype=bool)
    if not len(b):
        return np.zeros(len(a), dtype=bool)
    return np.isfinite(cKDTree(b).query(a, distance_upper_bound=MATCH_M)[0])


def lane_graph_scores(features: Sequence[MapFeature], truth_map: Sequence[MapFeature], inside_xy: np.ndarray,
                      corridor_m: float, params: TopologyParams) -> dict:
    """Connection precision and recall, split / merge point precision and recall of the lane
    graph of ``features`` against that of the truth's centrelines (both world frame). Only
    what lies within ``corridor_m`` of ``inside_xy`` (the true frames) counts: truth
    centrelines mostly inside it, and connections and points inside it."""
    frames = cKDTree(inside_xy)

    def inside(xy: np.ndarray) -> np.ndarray:
        return frames.query(xy)[0] <= corridor_m if len(xy) else np.zeros(0, dtype=bool)

    truth_cl = [f for f in truth_map if f.type == ElementType.CENTERLINE and len(f.points_xy_world) >= 2
                and inside(resample_polyline(np.asarray(f.points_xy_world, float), 2.0)).mean() >= 0.5]
    ours = build_lane_graph(features, params)
    truth = build_lane_graph(truth_cl, params)
    c_ours, c_truth = connections(ours), connections(truth)
    c_ours, c_truth = c_ours[inside(c_ours[:, :2])], c_truth[inside(c_truth[:, :2])]
    right = _found(c_ours, c_truth, _lane_samples(truth))
    got = _found(c_truth, c_ours, _lane_samples(ours))
    out = {"lanes": ours.graph.number_of_nodes(), "truth_lanes": truth.graph.number_of_nodes(),
           "connections": int(len(c_ours)), "truth_connections": int(len(c_truth)),
           "connection_precision": float(right.mean()) if len(right) else float("nan"),
           "connection_recall": float(got.mean()) if len(got) else float("nan")}
    for name in ("split", "merge"):
        a = getattr(ours, f"{name}_points_xy")
        b = getattr(truth, f"{name}_points_xy")
        a, b = a[inside(a)], b[inside(b)]
        out[f"{name}s"], out[f"truth_{name}s"] = int(len(a)), int(len(b))
        out[f"{name}_precision"] = float(_points_matched(a, b).mean()) if len(a) else float("nan")
        out[f"{name}_recall"] = float(_points_matched(b, a).mean()) if len(b) else float("nan")
    return out
