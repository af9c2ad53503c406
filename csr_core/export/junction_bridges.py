"""Bridges: connector centrelines across the gaps the lane graph leaves open.

A lane that ends with no successor (a *dead end*) and a lane that starts with no predecessor
(an *open start*) meet where the map has no connector between them: a junction the fleet's
trips crossed without a connector being derived (``derived_connectors`` needs a trip that drove
that very turn), a tile seam or a version boundary where one lane stops short of the next.
Every lane of a road network continues somewhere and comes from somewhere, so the export links
each dead end to the open starts a vehicle can reach from it:

1. Candidates: open starts within ``BRIDGE_MAX_M`` of the dead end, ahead of it (along its end
   heading) and not turning back (heading change at most ``BRIDGE_MAX_TURN_RAD``).
2. The connector is the cubic Hermite curve (``scipy.interpolate.CubicHermiteSpline``) from the
   dead end's end pose to the open start's pose, tangents scaled by the chord; it is kept if
   its curvature stays below ``BRIDGE_MAX_CURVATURE_PER_M`` (a car's tightest turn) and it does
   not overshoot (length at most ``BRIDGE_MAX_DETOUR`` times the chord).
3. It starts at the dead end's last point and ends at the open start's first, so the lane graph
   links both ends (``successor`` edges) and the lanelets share their end nodes.

Each bridge is a ``centerline`` feature with ``properties["derived"] = "junction_bridge"``,
``properties["derived_from"]``: the ids of the two centrelines, and their mean
``uncertainty_m`` where the map gives one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from csr_core.topology.lane_graph import SUCCESSOR, LaneGraph, build_lane_graph, end_heading
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

BRIDGE = "junction_bridge"
BRIDGE_ID_PREFIX = "bridge:"  # feature ids of bridges: bridge:<from lane>><to lane>


@dataclass(frozen=True, slots=True)
class BridgeParams:
    BRIDGE_MIN_M: float = 0.3  # ends closer than this are one point: no bridge needed
    BRIDGE_MAX_M: float = 40.0  # a bridge spans at most this (a large junction)
    BRIDGE_MAX_TURN_RAD: float = math.radians(120.0)  # heading change: more is a U-turn
    BRIDGE_MAX_CURVATURE_PER_M: float = 1.0 / 3.0  # a car's tightest turn at a corner: 3 m radius
    SEAM_M: float = 1.5  # ends closer than this (a lane shorter than a lane) are linked directly
    SEAM_SIGMAS: float = 3.0  # ... or within this many combined 1-sigma uncertainties of the two lanes
    BRIDGE_MAX_DETOUR: float = 1.6  # bridge length / chord
    SAMPLE_STEP_M: float = 1.0  # vertex spacing of a bridge


@dataclass(frozen=True, slots=True)
class Bridge:
    from_lane: str
    to_lane: str
    points_xy_world: np.ndarray  # (K, 2), from the dead end's end to the open start's start; (0, 2): a seam


def _hermite(
    p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray, params: BridgeParams
) -> np.ndarray | None:
    """The Hermite curve from pose (p0, t0) to (p1, t1) sampled ``(K, 2)``, or None where it
    turns tighter than the limit or overshoots."""
    chord = float(np.linalg.norm(p1 - p0))
    spline = CubicHermiteSpline([0.0, 1.0], np.vstack([p0, p1]), np.vstack([t0, t1]) * chord, axis=0)
    u = np.linspace(0.0, 1.0, 64)
    d1, d2 = spline(u, 1), spline(u, 2)
    speed = np.linalg.norm(d1, axis=1)
    if float(speed.min()) < 1e-6:
        return None
    curvature = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / speed**3
    xy = spline(u)
    length = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    if (
        float(curvature.max()) > params.BRIDGE_MAX_CURVATURE_PER_M
        or length > params.BRIDGE_MAX_DETOUR * chord
    ):
        return None
    n = max(int(math.ceil(length / params.SAMPLE_STEP_M)), 2) + 1
    out = spline(np.linspace(0.0, 1.0, n))
    out[0], out[-1] = p0, p1
    return np.asarray(out, float)


def _sigma_m(props: dict) -> float:
    v = props.get("uncertainty_m")
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else 0.0


def find_bridges(lane_graph: LaneGraph, centre_props: dict[str, dict], params: BridgeParams) -> list[Bridge]:
    """Bridges from every dead end to the open starts it reaches (see the module doc); a gap
    within ``SEAM_M`` or ``SEAM_SIGMAS`` combined uncertainties is a seam (no points)."""
    g = lane_graph.graph
    dead = [n for n in g.nodes if not lane_graph.successors(n)]
    open_starts = [n for n in g.nodes if not lane_graph.predecessors(n)]
    if not dead or not open_starts:
        return []
    start_xy = np.array([np.asarray(g.nodes[n]["points_xy_world"], float)[0] for n in open_starts])
    start_t = np.array(
        [end_heading(np.asarray(g.nodes[n]["points_xy_world"], float), False) for n in open_starts]
    )
    start_sigma_m = np.array([_sigma_m(centre_props.get(g.nodes[n]["feature_id"], {})) for n in open_starts])
    cos_turn = math.cos(params.BRIDGE_MAX_TURN_RAD)
    out = []
    for a in dead:
        pts = np.asarray(g.nodes[a]["points_xy_world"], float)
        p0, t0 = pts[-1], end_heading(pts, True)
        d = start_xy - p0
        dist = np.linalg.norm(d, axis=1)
        seam_m = np.maximum(
            params.SEAM_M,
            params.SEAM_SIGMAS
            * np.hypot(_sigma_m(centre_props.get(g.nodes[a]["feature_id"], {})), start_sigma_m),
        )
        ok = (dist <= params.BRIDGE_MAX_M) & (d @ t0 > -seam_m) & (start_t @ t0 >= cos_turn)
        for k in np.flatnonzero(ok).tolist():
            b = open_starts[k]
            if b == a:
                continue
            if dist[k] <= seam_m[k]:
                out.append(Bridge(a, b, np.zeros((0, 2))))
            elif float(d[k] @ t0) > 0.0:
                xy = _hermite(p0, t0, start_xy[k], start_t[k], params)
                if xy is not None:
                    out.append(Bridge(a, b, xy))
    return out


def bridge_lane_graph(
    features: Sequence[MapFeature], lane_graph: LaneGraph, topology: TopologyParams, params: BridgeParams
) -> tuple[tuple[MapFeature, ...], LaneGraph, int, int]:
    """(features with the bridges as ``centerline`` features, ids ``bridge:<from lane>><to lane>``;
    the lane graph of them with the seams as ``successor`` edges; bridges; seams)."""
    centre_props = {f.feature_id: f.properties for f in features if f.type == ElementType.CENTERLINE}
    bridges = find_bridges(lane_graph, centre_props, params)
    seams = [b for b in bridges if not len(b.points_xy_world)]
    g = lane_graph.graph
    added = []
    for b in bridges:
        if not len(b.points_xy_world):
            continue
        fa, fb = g.nodes[b.from_lane]["feature_id"], g.nodes[b.to_lane]["feature_id"]
        props: dict = {"derived": BRIDGE, "derived_from": [fa, fb], "direction": "assumed"}
        sigmas = [_sigma_m(centre_props.get(f, {})) for f in (fa, fb)]
        if any(sigmas):
            props["uncertainty_m"] = float(np.mean(sigmas))
        added.append(
            MapFeature(
                type=ElementType.CENTERLINE,
                points_xy_world=b.points_xy_world,
                feature_id=f"{BRIDGE_ID_PREFIX}{b.from_lane}>{b.to_lane}",
                properties=props,
            )
        )
    features = (*features, *added)
    if added:
        lane_graph = build_lane_graph(features, topology)
    for b in seams:
        if b.from_lane in lane_graph.graph and b.to_lane in lane_graph.graph:
            lane_graph.graph.add_edge(b.from_lane, b.to_lane, kind=SUCCESSOR)
    return features, lane_graph, len(added), len(seams)
