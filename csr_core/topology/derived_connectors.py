"""Lane connectors through junctions, from the paths of the trips that drove them.

Inside a junction no divider or boundary bounds a lane, so ``derived_centerlines`` stops at its
edge, and a perception stack may not report the turn paths either. A trip that left one
centreline and, within ``CONNECTOR_MAX_M`` of travel, joined another drove a connector between
the two. The connector is where such trips drove (drivers keep to the
middle of the turn path on average, the rule ``derived_centerlines`` uses beside kerbs):

1. Each trip's path probes (``instances.path_probes``) are matched to the map's centrelines: the
   nearest centreline sample within half a narrow lane whose direction is within
   ``PASS_MAX_ANGLE_RAD`` of the trip's.
2. A trip passes from centreline A to B when consecutive matched probes change from A to B with
   at most ``CONNECTOR_MAX_M`` of travel between, and it left A within ``END_REACH_M`` of A's end
   or joined B within ``END_REACH_M`` of B's start (a junction; a split leaves A's middle for B's
   start, a merge A's end for B's middle; a lane change, middle to middle, is no connector),
   and the two points are farther apart than the lane graph's own link (``CONNECT_M``). A pass
   that turns back (heading more than ``MAX_TURN_RAD`` from where it left A) is a U-turn, not a
   lane.
3. Each such pass gives the trip's path from where it left A to where it joined B; the passes of
   one (A, B) are averaged at equal shares of their length, smoothed over a metre (ends
   point-reflected), and moved to start on A and end on B.
4. A connector shorter than ``LANE_MIN_LENGTH_M`` is no lane (the lane graph leaves such
   fragments out; on the hard profile's perceived maps most connectors were 2.5-3 m bridges
   between two pieces of one centreline), and one mostly (more than half its length) within half
   a narrow lane of another centreline, in its direction, is there already: neither is added.

Each connector carries ``properties["derived"] = "trip_paths"``, ``properties["derived_from"]``:
the ids of A and B, and ``properties["direction"] = "driven"``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.fusion import smooth_point_reflected
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

END_REACH_M = 5.0  # a trip leaves a lane at its end / joins one at its start within this
CONNECTOR_MAX_M = 60.0  # travel between two lanes that a connector may span (a junction's size)
NEIGHBOURS = 4  # centreline samples considered per probe
MAX_TURN_RAD = math.radians(135.0)  # a pass that turns further is a U-turn (turnaround), not a lane


def _samples(
    centerlines: Sequence[MapFeature], spacing_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points, unit tangents, owner, arclength from the start and to the end of every
    centreline sample."""
    pts, tans, own, from_start, to_end = [], [], [], [], []
    for k, f in enumerate(centerlines):
        p = resample_polyline(np.asarray(f.points_xy_world, float), spacing_m)
        if len(p) < 2:
            continue
        t = np.gradient(p, axis=0)
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        pts.append(p)
        tans.append(t)
        own.append(np.full(len(p), k))
        from_start.append(s)
        to_end.append(s[-1] - s)
    return (
        np.concatenate(pts),
        np.concatenate(tans),
        np.concatenate(own),
        np.concatenate(from_start),
        np.concatenate(to_end),
    )


def _match(
    probes_xy_dir: np.ndarray, tree: cKDTree, tangents: np.ndarray, params: TopologyParams
) -> np.ndarray:
    """Step 1: index of the matched centreline sample per probe, -1 for none."""
    k = min(NEIGHBOURS, tree.n)
    dist, idx = tree.query(probes_xy_dir[:, :2], k=k, distance_upper_bound=0.5 * params.MIN_LANE_WIDTH_M)
    dist, idx = dist.reshape(len(probes_xy_dir), k), idx.reshape(len(probes_xy_dir), k)
    found = np.isfinite(dist)
    safe = np.where(found, idx, 0)
    aligned = (tangents[safe] * probes_xy_dir[:, None, 2:]).sum(2) >= math.cos(params.PASS_MAX_ANGLE_RAD)
    ok = found & aligned
    first = np.argmax(ok, axis=1)  # nearest first: query sorts by distance
    return np.where(ok.any(1), safe[np.arange(len(safe)), first], -1)


def _passes(
    sample: np.ndarray, owner: np.ndarray, from_start: np.ndarray, to_end: np.ndarray, spacing_m: float
) -> list[tuple[int, int, int, int]]:
    """Step 2 for one trip: (A, B, last probe on A, first probe on B) of each pass. The trip left
    A at its end or joined B at its start (a lane change leaves one lane and joins another
    alongside it in their middles, where the map has lanes already)."""
    matched = np.flatnonzero(sample >= 0)
    out = []
    for i, j in zip(matched[:-1], matched[1:], strict=True):
        si, sj = sample[i], sample[j]
        if (
            owner[si] != owner[sj]
            and (to_end[si] <= END_REACH_M or from_start[sj] <= END_REACH_M)
            and (j - i) * spacing_m <= CONNECTOR_MAX_M
        ):
            out.append((int(owner[si]), int(owner[sj]), int(i), int(j)))
    return out


def _pass_path(
    probes_xy: np.ndarray, a_xy: np.ndarray, a_tan: np.ndarray, b_xy: np.ndarray, b_tan: np.ndarray
) -> np.ndarray:
    """Step 3: the trip's path from where it left A (``a_xy``, A's direction there ``a_tan``) to
    where it joined B; probes behind the one or beyond the other left out."""
    ahead = ((probes_xy - a_xy) @ a_tan > 0.0) & ((probes_xy - b_xy) @ b_tan < 0.0)
    return np.vstack([a_xy, probes_xy[ahead], b_xy])


def _mean_path(paths: Sequence[np.ndarray], params: TopologyParams) -> np.ndarray:
    """Step 3: passes averaged at equal shares of their length, smoothed over a metre."""
    length = max(float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) for p in paths)
    n = max(int(math.ceil(length / params.OUTPUT_SPACING_M)) + 1, 3)
    u = np.linspace(0.0, 1.0, n)
    resampled = []
    for p in paths:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        s /= max(s[-1], 1e-9)
        resampled.append(np.column_stack([np.interp(u, s, p[:, 0]), np.interp(u, s, p[:, 1])]))
    return smooth_point_reflected(np.mean(resampled, axis=0), 1.0 / params.OUTPUT_SPACING_M)


def derive_connectors(
    centerlines: Sequence[MapFeature],
    probes: Mapping[str, np.ndarray],
    params: TopologyParams,
    trip_times: Mapping[str, object] | None = None,
) -> list[MapFeature]:
    """Connectors between the ``centerlines`` (perceived and derived, directed) from the trips'
    ``probes`` (trip key -> ``(P, 4)``); steps 1-4 of the module docstring. Ids are not set."""
    lines = [f for f in centerlines if len(f.points_xy_world) >= 2]
    if not lines or not probes:
        return []
    spacing = params.SAMPLE_SPACING_M
    pts, tans, owner, from_start, to_end = _samples(lines, spacing)
    tree = cKDTree(pts)
    by_pair: dict[tuple[int, int], list[tuple[str, np.ndarray]]] = {}
    for key in sorted(probes):
        pr = probes[key]
        if len(pr) < 2:
            continue
        step = float(np.median(np.linalg.norm(np.diff(pr[:, :2], axis=0), axis=1)))
        sample = _match(pr, tree, tans, params)
        for a, b, i, j in _passes(sample, owner, from_start, to_end, step):
            pa, pb, ta, tb = pts[sample[i]], pts[sample[j]], tans[sample[i]], tans[sample[j]]
            if np.linalg.norm(pa - pb) <= params.CONNECT_M or float(ta @ tb) < math.cos(MAX_TURN_RAD):
                continue
            by_pair.setdefault((a, b), []).append((key, _pass_path(pr[i : j + 1, :2], pa, ta, pb, tb)))
    out = []
    for (a, b), passes in sorted(by_pair.items()):
        path = _mean_path([p for _, p in passes], params)
        path = _onto_ends(path, pts[owner == a], pts[owner == b])
        length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
        if length < params.LANE_MIN_LENGTH_M or _covered(path, tree, tans, owner, (a, b), params):
            continue
        out.append(_connector(path, [k for k, _ in passes], (lines[a], lines[b]), trip_times))
    return out


def _onto_ends(path: np.ndarray, a_pts: np.ndarray, b_pts: np.ndarray) -> np.ndarray:
    """The mean path moved (linearly along it) so that it starts on A and ends on B."""
    start = a_pts[int(np.argmin(np.linalg.norm(a_pts - path[0], axis=1)))]
    end = b_pts[int(np.argmin(np.linalg.norm(b_pts - path[-1], axis=1)))]
    u = np.linspace(0.0, 1.0, len(path))
    return path + np.outer(1.0 - u, start - path[0]) + np.outer(u, end - path[-1])


def _covered(
    path: np.ndarray,
    tree: cKDTree,
    tans: np.ndarray,
    owner: np.ndarray,
    ends: tuple[int, int],
    params: TopologyParams,
) -> bool:
    """Step 4: more than half the connector within half a narrow lane of another centreline
    running its way (``tree``: every centreline sample, built once for all connectors)."""
    t = np.gradient(path, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    near = cKDTree(path).sparse_distance_matrix(tree, 0.5 * params.MIN_LANE_WIDTH_M, output_type="ndarray")
    i, j = near["i"].astype(np.intp), near["j"].astype(np.intp)
    ok = ~np.isin(owner[j], ends) & ((tans[j] * t[i]).sum(1) >= math.cos(params.PASS_MAX_ANGLE_RAD))
    along = np.zeros(len(path), bool)
    along[i[ok]] = True
    return bool(along.mean() > 0.5)


def derived_properties(
    trips: Sequence[str],
    trip_times: Mapping[str, object] | None,
    *,
    support_trips: int,
    support_observations: int,
    uncertainty_m: float,
    derived: str,
    derived_from: Sequence[MapFeature],
    direction: str,
) -> dict:
    """The properties of a derived centreline: those of a fused one (``instances.feature_from_fused``)
    with nothing rejected or scattered, plus ``derived``, ``derived_from`` (ids) and ``direction``."""
    trips = sorted(set(trips))
    times = {k: trip_times[k] for k in trips} if trip_times and all(k in trip_times for k in trips) else {}
    ordered = sorted(trips, key=lambda k: (times[k], k)) if times else trips
    return {
        "support_trips": support_trips,
        "support_observations": support_observations,
        "uncertainty_m": round(uncertainty_m, 4),
        "first_seen": times[ordered[0]] if times else None,
        "last_confirmed": times[ordered[-1]] if times else None,
        "style": None,
        "trips": trips,
        "scatter_ratio": 1.0,
        "rejected_weight_share": 0.0,
        "outlier_trips": [],
        "max_internal_gap_m": 0.0,
        "first_trip": ordered[0],
        "derived": derived,
        "derived_from": [f.feature_id for f in derived_from],
        "direction": direction,
    }


def _connector(
    path: np.ndarray,
    pass_trips: Sequence[str],
    ends: tuple[MapFeature, MapFeature],
    trip_times: Mapping[str, object] | None,
) -> MapFeature:
    props = derived_properties(
        pass_trips,
        trip_times,
        support_trips=len(set(pass_trips)),
        support_observations=len(pass_trips),
        uncertainty_m=max(float(e.properties.get("uncertainty_m", 0.1)) for e in ends),
        derived="trip_paths",
        derived_from=ends,
        direction="driven",
    )
    return MapFeature(ElementType.CENTERLINE, path, None, "", props)
