"""Measure the lane graph against the truth's centrelines (``topology.evaluate`` calls it).

The truth has no lane graph of its own, only directed centrelines: its graph is built from
them by the same ``build_lane_graph``, so what is compared is what the fused centrelines
connect, not how the builder reads a junction. Compared are *connections*: successor edges
(where one lane hands over to another: a junction, a split, a merge; lanes are centrelines cut
where others start or end on them), each as the point where it happens, the heading in, and
where the lane it hands over to is ``LOOKAHEAD_M`` on, on into that lane's successors where it
is shorter (a turn lane leaves its through lane tangentially: only further on do the two part;
and the truth's lanes are cut into short pieces at every lanelet border).

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
from dataclasses import dataclass
from pathlib import Path

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


class _Ahead:
    """Where a lane goes ``LOOKAHEAD_M`` on from a point on it: walked along the lane and, past
    its end, into each of its successors (a lane cut short by the next lane's start goes on
    there), so one point per path; the lane's end if it has no successor. Lanes are resampled
    once, every ``SPACING_M``."""

    def __init__(self, lane_graph: LaneGraph) -> None:
        self.graph = lane_graph.graph
        self.lanes = {
            n: sampled_with_tangents(d["points_xy_world"], SPACING_M)[0]
            for n, d in self.graph.nodes(data=True)
        }

    def points(
        self, lane: str, index: int, distance_m: float = LOOKAHEAD_M, depth: int = 0
    ) -> list[np.ndarray]:
        p = self.lanes[lane]
        k = int(round(distance_m / SPACING_M))
        if index + k < len(p):
            return [p[index + k]]
        nxt = [v for v in self.graph.successors(lane) if self.graph.edges[lane, v]["kind"] == SUCCESSOR]
        if not nxt or depth >= 4:
            return [p[-1]]
        rest = distance_m - (len(p) - 1 - index) * SPACING_M
        return [q for v in nxt if len(self.lanes[v]) >= 2 for q in self.points(v, 0, rest, depth + 1)] or [
            p[-1]
        ]


def connections(lane_graph: LaneGraph, ahead: _Ahead | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """``(C, 4)`` rows x, y, heading-in x, y of the successor edges (at the end of the lane
    handing over), and per edge the points ``LOOKAHEAD_M`` on along the lane handed over to
    (``_Ahead``: on into its successors) ``(K, 2)``."""
    ahead = ahead or _Ahead(lane_graph)
    g = lane_graph.graph
    rows, on = [], []
    for u, v, kind in g.edges(data="kind"):
        if kind != SUCCESSOR:
            continue
        pu, pv = ahead.lanes[u], ahead.lanes[v]
        if len(pu) < 2 or len(pv) < 2:
            continue
        rows.append(np.r_[pu[-1], end_heading(pu, True)])
        on.append(np.array(ahead.points(v, 0)))
    return np.array(rows).reshape(-1, 4), on


def _lane_samples(lane_graph: LaneGraph) -> tuple[np.ndarray, np.ndarray, list[tuple[str, int]], np.ndarray]:
    """All lanes sampled every ``SPACING_M``: points (P, 2), unit tangents (P, 2), each
    sample's (lane, index), and the distance to the lane's start (P,)."""
    pts: list[np.ndarray] = []
    tans: list[np.ndarray] = []
    where: list[tuple[str, int]] = []
    from_start: list[np.ndarray] = []
    for n, data in lane_graph.graph.nodes(data=True):
        p, t = sampled_with_tangents(data["points_xy_world"], SPACING_M)
        if len(p) < 2:
            continue
        pts.append(p)
        tans.append(t)
        where.extend((n, i) for i in range(len(p)))
        from_start.append(np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2)), [], np.zeros(0)
    return np.concatenate(pts), np.concatenate(tans), where, np.concatenate(from_start)


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    """Some point of ``a (K, 2)`` within ``MATCH_M`` of some point of ``b (L, 2)``."""
    return bool((np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2) <= MATCH_M).any())


def _found(
    rows: np.ndarray,
    rows_on: list[np.ndarray],
    other_rows: np.ndarray,
    other_on: list[np.ndarray],
    other: LaneGraph,
    other_ahead: _Ahead,
) -> np.ndarray:
    """Per connection of ``rows``: does the other graph go on the same way there (a connection
    there, or a lane through the point, heading in alike and ``LOOKAHEAD_M`` on at the same
    place)."""
    cos_max = math.cos(MATCH_ANGLE_RAD)
    out = np.zeros(len(rows), dtype=bool)
    if not len(rows):
        return out
    if len(other_rows):
        for i, hits in enumerate(cKDTree(other_rows[:, :2]).query_ball_point(rows[:, :2], MATCH_M)):
            out[i] = any(
                other_rows[h, 2:4] @ rows[i, 2:4] >= cos_max and _close(other_on[h], rows_on[i]) for h in hits
            )
    pts, tans, where, from_start = _lane_samples(other)
    if len(pts):
        for i, hits in enumerate(cKDTree(pts).query_ball_point(rows[:, :2], MATCH_M)):
            if out[i] or not hits:
                continue
            hits = np.asarray(hits)
            hits = hits[
                (from_start[hits] >= MATCH_M) & (tans[hits] @ rows[i, 2:4] >= cos_max)
            ]  # through the point
            out[i] = any(_close(np.array(other_ahead.points(*where[h])), rows_on[i]) for h in hits)
    return out


def _points_matched(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if not len(a):
        return np.zeros(0, dtype=bool)
    if not len(b):
        return np.zeros(len(a), dtype=bool)
    return np.isfinite(cKDTree(b).query(a, distance_upper_bound=MATCH_M)[0])


@dataclass(frozen=True)
class LaneGraphComparison:
    """The two lane graphs and what of them lies inside the corridor: connections
    ``ours_rows``/``truth_rows`` ``(C, 4)`` as :func:`connections`, ``*_on`` the points
    ``LOOKAHEAD_M`` on, ``right`` (ours the truth has) and ``got`` (the truth's we have); split
    and merge points; the truth centrelines compared."""

    ours: LaneGraph
    truth: LaneGraph
    ours_rows: np.ndarray
    ours_on: list[np.ndarray]
    truth_rows: np.ndarray
    truth_on: list[np.ndarray]
    right: np.ndarray
    got: np.ndarray
    truth_centerlines: list[MapFeature]
    points_inside: dict[str, tuple[np.ndarray, np.ndarray]]  # "split"/"merge" -> (ours, truth)

    def scores(self) -> dict:
        """Connection precision and recall, split / merge point precision and recall."""
        right, got = self.right, self.got
        out = {
            "lanes": self.ours.graph.number_of_nodes(),
            "truth_lanes": self.truth.graph.number_of_nodes(),
            "connections": int(len(self.ours_rows)),
            "truth_connections": int(len(self.truth_rows)),
            "connection_precision": float(right.mean()) if len(right) else float("nan"),
            "connection_recall": float(got.mean()) if len(got) else float("nan"),
        }
        for name, (a, b) in self.points_inside.items():
            out[f"{name}s"], out[f"truth_{name}s"] = int(len(a)), int(len(b))
            out[f"{name}_precision"] = float(_points_matched(a, b).mean()) if len(a) else float("nan")
            out[f"{name}_recall"] = float(_points_matched(b, a).mean()) if len(b) else float("nan")
        return out


def compare_lane_graphs(
    features: Sequence[MapFeature],
    truth_map: Sequence[MapFeature],
    inside_xy: np.ndarray,
    corridor_m: float,
    params: TopologyParams,
) -> LaneGraphComparison:
    """The lane graph of ``features`` against that of the truth's centrelines (both world
    frame). Only what lies within ``corridor_m`` of ``inside_xy`` (the true frames) counts:
    truth centrelines mostly inside it, and connections and split / merge points inside it."""
    frames = cKDTree(inside_xy)

    def inside(xy: np.ndarray) -> np.ndarray:
        return frames.query(xy)[0] <= corridor_m if len(xy) else np.zeros(0, dtype=bool)

    truth_cl = [
        f
        for f in truth_map
        if f.type == ElementType.CENTERLINE
        and len(f.points_xy_world) >= 2
        and inside(resample_polyline(np.asarray(f.points_xy_world, float), 2.0)).mean() >= 0.5
    ]
    ours = build_lane_graph(features, params)
    truth = build_lane_graph(truth_cl, params)
    ahead_ours, ahead_truth = _Ahead(ours), _Ahead(truth)
    (c_ours, on_ours), (c_truth, on_truth) = connections(ours, ahead_ours), connections(truth, ahead_truth)
    keep_ours, keep_truth = inside(c_ours[:, :2]), inside(c_truth[:, :2])
    c_ours, on_ours = c_ours[keep_ours], [a for a, k in zip(on_ours, keep_ours, strict=True) if k]
    c_truth, on_truth = c_truth[keep_truth], [a for a, k in zip(on_truth, keep_truth, strict=True) if k]
    right = _found(c_ours, on_ours, c_truth, on_truth, truth, ahead_truth)
    got = _found(c_truth, on_truth, c_ours, on_ours, ours, ahead_ours)
    points = {}
    for name in ("split", "merge"):
        a, b = getattr(ours, f"{name}_points_xy"), getattr(truth, f"{name}_points_xy")
        points[name] = (a[inside(a)], b[inside(b)])
    return LaneGraphComparison(ours, truth, c_ours, on_ours, c_truth, on_truth, right, got, truth_cl, points)


def plot_comparison(
    cmp: LaneGraphComparison, out_png: str | Path, bbox_xy: tuple[float, float, float, float] | None = None
) -> None:
    """A picture of ``cmp``: the truth's centrelines (grey, wide), the map's lanes (blue, with
    their direction), the truth's connections the map misses (red crosses, dotted to where they
    go on) and the map's connections the truth does not have (orange circles, lines to where
    they go on). ``bbox_xy``: (x_min, x_max, y_min, y_max) to zoom into."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 11))
    for f in cmp.truth_centerlines:
        p = np.asarray(f.points_xy_world, float)
        ax.plot(p[:, 0], p[:, 1], color="0.8", lw=4, solid_capstyle="round", zorder=1)
    for _, data in cmp.ours.graph.nodes(data=True):
        p = np.asarray(data["points_xy_world"], float)
        ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=0.9, zorder=2)
        if len(p) >= 2:
            ax.annotate(
                "", p[-1], p[-2], arrowprops=dict(arrowstyle="->", color="tab:blue", lw=0.9), zorder=2
            )
    for rows, on, ok, color, ls in (
        (cmp.truth_rows, cmp.truth_on, cmp.got, "red", ":"),
        (cmp.ours_rows, cmp.ours_on, cmp.right, "orange", "-"),
    ):
        for r, ahead in zip(rows[~ok], [a for a, k in zip(on, ok, strict=True) if not k], strict=True):
            for q in ahead:
                ax.plot([r[0], q[0]], [r[1], q[1]], lw=1.0, zorder=3, color=color, ls=ls)
    miss, false = cmp.truth_rows[~cmp.got], cmp.ours_rows[~cmp.right]
    ax.scatter(
        miss[:, 0],
        miss[:, 1],
        marker="x",
        color="red",
        s=70,
        zorder=4,
        label=f"truth connection the map misses ({len(miss)} of {len(cmp.got)})",
    )
    ax.scatter(
        false[:, 0],
        false[:, 1],
        marker="o",
        facecolors="none",
        edgecolors="orange",
        s=70,
        zorder=4,
        label=f"map connection the truth does not have ({len(false)} of {len(cmp.right)})",
    )
    ax.plot([], [], color="0.8", lw=4, label="truth centrelines")
    ax.plot([], [], color="tab:blue", lw=0.9, label="map lanes")
    if bbox_xy is not None:
        ax.set_xlim(bbox_xy[0], bbox_xy[1])
        ax.set_ylim(bbox_xy[2], bbox_xy[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"Lane graph connections: precision {cmp.right.mean():.2f}, recall {cmp.got.mean():.2f}")
    fig.savefig(out_png, dpi=90, bbox_inches="tight")
    plt.close(fig)
