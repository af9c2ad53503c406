"""The lane graph: lanes from the fused (directed) centrelines, with successors, predecessors,
left and right neighbours, split and merge points. Centrelines shorter than
``LANE_MIN_LENGTH_M`` (fragments) are not lanes.

- A centreline is cut where another centreline starts or ends on it (within ``CONNECT_M``,
  heading within ``CONNECT_MAX_ANGLE_RAD``, away from its own ends): a turn lane that leaves a
  through lane in its middle makes a split there. The pieces are the lanes (graph nodes
  ``"<feature_id>#<k>"``, attributes ``feature_id``, ``points_xy_world``, ``length_m``).
- ``successor`` edges: consecutive pieces of one centreline; a lane whose end is within
  ``CONNECT_M`` of another's start with continuous heading; a cut point to the lane starting
  there (split) and a lane ending there to the piece after the cut (merge).
- ``left`` / ``right`` edges: the lane with the same direction whose centreline lies at a
  lateral offset between ``MIN_LANE_WIDTH_M`` / 2 x 1.2 and ``MAX_LANE_WIDTH_M`` x 1.2 on that
  side over most of the lane (the nearest such).
- Split points: lanes with more than one successor; merge points: more than one predecessor.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.fusion import arclength
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

SUCCESSOR, LEFT, RIGHT = "successor", "left", "right"


@dataclass(frozen=True, slots=True)
class LaneGraph:
    """``graph``: networkx DiGraph of lanes; edge attribute ``kind`` in successor/left/right.
    ``split_points_xy (S, 2)`` / ``merge_points_xy (M, 2)``: where lanes split and merge."""

    graph: nx.DiGraph
    split_points_xy: np.ndarray
    merge_points_xy: np.ndarray

    def successors(self, lane: str) -> list[str]:
        return [v for v in self.graph.successors(lane) if self.graph.edges[lane, v]["kind"] == SUCCESSOR]

    def predecessors(self, lane: str) -> list[str]:
        return [u for u in self.graph.predecessors(lane) if self.graph.edges[u, lane]["kind"] == SUCCESSOR]

    def neighbour(self, lane: str, side: str) -> str | None:
        for v in self.graph.successors(lane):
            if self.graph.edges[lane, v]["kind"] == side:
                return v
        return None

    def lanes_of(self, feature_id: str) -> list[str]:
        return [n for n, a in self.graph.nodes(data=True) if a["feature_id"] == feature_id]


def end_heading(points: np.ndarray, at_end: bool, span_m: float = 3.0) -> np.ndarray:
    """Unit direction of a polyline over its last (``at_end``) or first ``span_m``."""
    s = arclength(points)
    if at_end:
        i = max(int(np.searchsorted(s, s[-1] - span_m)) - 1, 0)
        v = points[-1] - points[i]
    else:
        i = min(int(np.searchsorted(s, span_m)), len(points) - 1)
        v = points[i] - points[0]
    return v / max(float(np.linalg.norm(v)), 1e-12)


def build_lane_graph(features: Sequence[MapFeature], params: TopologyParams) -> LaneGraph:
    """Lanes of the centreline features (directed polylines, world frame, metres)."""
    cls = [
        f
        for f in features
        if f.type == ElementType.CENTERLINE
        and len(f.points_xy_world) >= 2
        and float(arclength(np.asarray(f.points_xy_world, float))[-1]) >= params.LANE_MIN_LENGTH_M
    ]
    cos_max = math.cos(params.CONNECT_MAX_ANGLE_RAD)
    lines = [resample_polyline(np.asarray(f.points_xy_world, float), 0.5) for f in cls]
    lines = [
        ln if len(ln) >= 2 else np.asarray(f.points_xy_world, float) for ln, f in zip(lines, cls, strict=True)
    ]
    total = [float(arclength(ln)[-1]) for ln in lines]
    starts = np.array([ln[0] for ln in lines]) if lines else np.zeros((0, 2))
    ends = np.array([ln[-1] for ln in lines]) if lines else np.zeros((0, 2))
    h_start = [end_heading(ln, False) for ln in lines]
    h_end = [end_heading(ln, True) for ln in lines]
    # 1. cut points: other lanes starting (split) or ending (merge) inside a centreline
    cuts: list[list[tuple[float, int, str]]] = [[] for _ in lines]
    tree_s = cKDTree(starts) if len(lines) else None
    if lines:
        xy = np.concatenate(lines)
        owner = np.repeat(np.arange(len(lines)), [len(ln) for ln in lines])
        s_of = np.concatenate([arclength(ln) for ln in lines])
        tan = np.concatenate([np.gradient(ln, axis=0) for ln in lines])
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
        tree = cKDTree(xy)
        for pts, heads, kind in ((starts, h_start, "split"), (ends, h_end, "merge")):
            for j, hits in enumerate(tree.query_ball_point(pts, params.CONNECT_M)):
                if not hits:
                    continue
                hits = np.asarray(hits)
                hits = hits[owner[hits] != j]
                dist = np.linalg.norm(xy[hits] - pts[j], axis=1)
                for i in np.unique(owner[hits]):
                    k = hits[owner[hits] == i][np.argmin(dist[owner[hits] == i])]
                    if not params.CONNECT_M < s_of[k] < total[i] - params.CONNECT_M:
                        continue
                    if float(np.dot(tan[k], heads[j])) >= cos_max:
                        cuts[i].append((float(s_of[k]), j, kind))
    # 2. lanes = pieces between cuts
    g = nx.DiGraph()
    piece_at: list[list[tuple[float, float, str]]] = []
    for i, ln in enumerate(lines):
        s_ln = arclength(ln)
        bounds = sorted({0.0, total[i], *[c[0] for c in cuts[i]]})
        merged = [bounds[0]]
        for b in bounds[1:]:
            if b - merged[-1] >= 1.0:
                merged.append(b)
        merged[-1] = total[i]
        pieces = []
        for k in range(len(merged) - 1):
            a, b = merged[k], merged[k + 1]
            name = f"{cls[i].feature_id}#{k}"
            sel = (s_ln >= a) & (s_ln <= b)
            pts = ln[sel] if sel.sum() >= 2 else ln[[int(np.searchsorted(s_ln, a)) - 1, -1]]
            g.add_node(name, feature_id=cls[i].feature_id, points_xy_world=pts, length_m=b - a)
            pieces.append((a, b, name))
            if k:
                g.add_edge(pieces[k - 1][2], name, kind=SUCCESSOR)
        piece_at.append(pieces)

    def piece(i: int, s: float, ending: bool) -> str:
        """The piece of line ``i`` that ends (``ending``) or starts at the cut ``s``: the nearest
        such bound (cuts closer than 1 m to each other were merged into one bound)."""
        return min(piece_at[i], key=lambda p: abs((p[1] if ending else p[0]) - s))[2]

    # 3. successor links: end -> start, and through the cut points
    for i in range(len(lines)):
        if tree_s is None:
            break
        for j in tree_s.query_ball_point(ends[i], params.CONNECT_M):
            if j != i and float(np.dot(h_end[i], h_start[j])) >= cos_max:
                g.add_edge(piece_at[i][-1][2], piece_at[j][0][2], kind=SUCCESSOR)
        for s, j, kind in cuts[i]:
            if kind == "split":
                g.add_edge(piece(i, s, ending=True), piece_at[j][0][2], kind=SUCCESSOR)
            else:
                g.add_edge(piece_at[j][-1][2], piece(i, s, ending=False), kind=SUCCESSOR)
    # 4. left / right neighbours: same direction, lateral offset about a lane width
    _neighbours(g, params, cos_max)
    splits = [
        g.nodes[n]["points_xy_world"][-1]
        for n in g.nodes
        if sum(1 for v in g.successors(n) if g.edges[n, v]["kind"] == SUCCESSOR) > 1
    ]
    merges = [
        g.nodes[n]["points_xy_world"][0]
        for n in g.nodes
        if sum(1 for u in g.predecessors(n) if g.edges[u, n]["kind"] == SUCCESSOR) > 1
    ]
    return LaneGraph(g, np.array(splits).reshape(-1, 2), np.array(merges).reshape(-1, 2))


def _midpoint(points: np.ndarray) -> np.ndarray:
    s = arclength(points)
    h = 0.5 * s[-1]
    return np.array([np.interp(h, s, points[:, 0]), np.interp(h, s, points[:, 1])])


def sampled_with_tangents(points_xy: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A lane's polyline resampled every ``spacing_m`` (P, 2) and its unit tangents (P, 2)."""
    p = resample_polyline(np.asarray(points_xy, float), spacing_m)
    t = np.gradient(p, axis=0) if len(p) >= 2 else np.zeros_like(p)
    return p, t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def _neighbours(g: nx.DiGraph, params: TopologyParams, cos_max: float) -> None:
    """Left/right edges: for every lane sample, the other lanes' nearest samples beside it
    (same direction, lateral offset within the lane-width band); per lane and side the lane
    beside most of it (at least 30 %), the nearest on ties."""
    names = list(g.nodes)
    pts, tans, own = [], [], []
    for k, n in enumerate(names):
        p, t = sampled_with_tangents(g.nodes[n]["points_xy_world"], 2.0)
        if len(p) < 2:
            continue
        pts.append(p)
        tans.append(t)
        own.append(np.full(len(p), k))
    if len(pts) < 2:
        return
    xy, tan, owner = np.concatenate(pts), np.concatenate(tans), np.concatenate(own)
    lo_w, hi_w = 0.6 * params.MIN_LANE_WIDTH_M, 1.2 * params.MAX_LANE_WIDTH_M
    pairs = cKDTree(xy).query_pairs(hi_w, output_type="ndarray")
    if not len(pairs):
        return
    fid = np.array([g.nodes[n]["feature_id"] for n in names])
    # another centreline, same direction: the same both ways, checked before the pairs are doubled
    pa, pb = pairs[:, 0], pairs[:, 1]
    pairs = pairs[(fid[owner[pa]] != fid[owner[pb]]) & ((tan[pa] * tan[pb]).sum(1) >= cos_max)]
    a, b = np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]]
    rel = xy[b] - xy[a]
    lat = tan[a, 0] * rel[:, 1] - tan[a, 1] * rel[:, 0]
    along = (tan[a] * rel).sum(1)
    ok = (np.abs(along) <= 1.0) & (np.abs(lat) >= lo_w) & (np.abs(lat) <= hi_w)
    a, b, lat = a[ok], b[ok], lat[ok]
    if not len(a):
        return
    n_samples = np.bincount(owner, minlength=len(names))
    # one vote per (sample, neighbour lane), its nearest sample: rows (lane, side, neighbour)
    order = np.lexsort((np.abs(lat), owner[b], a))
    a, b, lat = a[order], b[order], lat[order]
    first = np.r_[True, (a[1:] != a[:-1]) | (owner[b][1:] != owner[b][:-1])]
    a, b, lat = a[first], b[first], lat[first]
    keys, inv, votes = np.unique(
        np.c_[owner[a], (lat > 0).astype(np.int64), owner[b]], axis=0, return_inverse=True, return_counts=True
    )
    mean_d = np.bincount(inv.ravel(), weights=np.abs(lat), minlength=len(keys)) / votes
    best: dict[tuple[int, int], tuple[float, int]] = {}
    for (lane, left, other), v, dm in zip(keys.tolist(), votes.tolist(), mean_d.tolist(), strict=True):
        if v < 0.3 * n_samples[lane]:
            continue
        if (lane, left) not in best or dm < best[(lane, left)][0]:
            best[(lane, left)] = (dm, other)
    for (lane, left), (_, other) in best.items():
        g.add_edge(names[lane], names[other], kind=LEFT if left else RIGHT)
