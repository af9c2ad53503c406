"""Centrelines derived from lane dividers and road boundaries where no perceived one exists.

Perception stacks with MapTR's classes (divider, boundary, crossing) report no centreline, and a
stack that does may miss a lane; the lane graph (``lane_graph``) is built from centrelines. A lane
is the strip between two neighbouring lane-bounding lines of the fused map (lane dividers, road
boundaries), and the trips' paths say where such strips are:

1. Every path probe (a trip's aligned position and direction every 2 m, ``instances.path_probes``)
   casts a ray along its normal, ``PASS_LATERAL_M`` each way (the lines a trip perceives well,
   as for the trips that drove alongside a line). It crosses the bounding lines that run within
   ``PASS_MAX_ANGLE_RAD`` of its direction.
2. Two consecutive crossings bound a lane when the painted width between them (below: a kerb
   lies a shoulder beyond the painted edge) is ``MIN_LANE_WIDTH_M`` to ``MAX_LANE_WIDTH_M`` (a
   wider strip is two lanes with a divider missing, or no lane: nothing is guessed there).
3. The lane's centre on the ray: midway between two painted edges, or between two kerbs. Where
   one edge is a road boundary (a kerb) and the other a divider, the painted lane ends a shoulder
   short of the kerb; the centre is half the painted width in from the divider. The shoulder is
   the map's own: the median of ``W - 2 d`` over the probes that drove in such lanes (``W`` the
   strip's width, ``d`` the trip's distance from the divider; drivers keep to the middle of the
   painted lane on average), ``shoulder_width_m``.
4. A perceived centreline takes precedence: centre points within half a narrow lane of one are
   dropped.
5. The centre points of one lane (one pair of bounding lines, from every probe and trip) are
   averaged per metre along the pair's first line, smoothed like a fused profile
   (``SMOOTH_SIGMA_M``), cut where nothing supports them for ``MAX_GAP_M``; pieces shorter than
   ``LANE_MIN_LENGTH_M`` are not lanes.
6. A strip beside a kerb that no trip drove in is left out: beside the kerb lie parking bays,
   cycle lanes and verges as often as lanes (on the Karlsruhe map, 16 of 16 such strips were no
   lane). Direction: the way the trips that drove in the lane went; a lane between two dividers
   that nobody drove in takes the direction of the trips that saw it (``properties["direction"]``:
   ``"driven"`` or ``"assumed"``).

7. Junction connectors (no bounding line inside a junction) come from the paths of the trips
   that drove from one centreline to the next (``derived_connectors``).

Each derived feature carries ``properties["derived"]`` (``"bounding_lines"``, a connector
``"trip_paths"``) and ``properties["derived_from"]``: the ids of its two bounding lines (a
connector: of the two centrelines it links).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.derived_connectors import derive_connectors, derived_properties
from csr_core.topology.fusion import smooth_point_reflected
from csr_core.topology.identity import assign_ids
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

BOUNDING_TYPES = (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY)
SEGMENT_M = 2.0  # bounding lines are cut into chords this long for the ray casts (3 cm off a 15 m radius)
SHOULDER_MIN_PROBES = 20  # fewer driven probes in kerb-side lanes: no shoulder is estimated (0 m)
SHOULDER_MAX_M = 1.0  # a kerb farther beyond the painted edge bounds a shoulder strip, not a lane
# rays cast per THIN_CELL_M square and heading octant at most (the first trips' in key order): the
# cost stays that of the road, not of the trips that drove it
THIN_CELL_M = 2.0
THIN_PER_CELL = 8


@dataclass(frozen=True, slots=True)
class LaneCrossings:
    """One row per lane strip a probe's ray crossed: the probe, its trip, the strip's edges
    (feature indices, right then left of the probe) and their lateral offsets (m, left +)."""

    probe: np.ndarray  # (L,) probe index
    trip: np.ndarray  # (L,) trip index
    right: np.ndarray  # (L,) feature index of the right edge
    left: np.ndarray  # (L,) feature index of the left edge
    s_right_m: np.ndarray  # (L,)
    s_left_m: np.ndarray  # (L,)

    @property
    def width_m(self) -> np.ndarray:
        return self.s_left_m - self.s_right_m

    @property
    def driven(self) -> np.ndarray:
        """The probe's own lane: its trip drove in it."""
        return (self.s_right_m < 0.0) & (self.s_left_m > 0.0)


def _segments(
    features: Sequence[MapFeature], indices: Sequence[int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start points, vectors and owner feature index of the bounding lines' 1 m segments."""
    starts, vecs, owner = [], [], []
    for i in indices:
        p = resample_polyline(np.asarray(features[i].points_xy_world, float), SEGMENT_M)
        if len(p) < 2:
            continue
        starts.append(p[:-1])
        vecs.append(np.diff(p, axis=0))
        owner.append(np.full(len(p) - 1, i))
    if not starts:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int)
    return np.concatenate(starts), np.concatenate(vecs), np.concatenate(owner)


def lane_crossings(
    features: Sequence[MapFeature], probes_xy_dir: np.ndarray, probe_trip: np.ndarray, params: TopologyParams
) -> LaneCrossings:
    """Step 1: each probe's ray against the bounding lines; consecutive crossings that may bound
    a lane (``MIN_LANE_WIDTH_M`` to ``MAX_LANE_WIDTH_M`` plus two shoulders apart: the painted
    width is checked once the shoulder is known, ``painted_lanes``). ``probes_xy_dir (P, 4)``: x,
    y, unit direction; ``probe_trip (P,)``."""
    empty = np.zeros(0, int)
    bounding = [i for i, f in enumerate(features) if f.type in BOUNDING_TYPES and len(f.points_xy_world) >= 2]
    a, d, owner = _segments(features, bounding)
    if len(a) == 0 or len(probes_xy_dir) == 0:
        return LaneCrossings(empty, empty, empty, empty, np.zeros(0), np.zeros(0))
    reach = params.PASS_LATERAL_M
    near = cKDTree(probes_xy_dir[:, :2]).sparse_distance_matrix(
        cKDTree(a + 0.5 * d), reach + SEGMENT_M, output_type="ndarray"
    )
    pi, si = near["i"].astype(np.intp), near["j"].astype(np.intp)
    o, t = probes_xy_dir[pi, :2], probes_xy_dir[pi, 2:]
    n = np.column_stack([-t[:, 1], t[:, 0]])  # the probe's left
    seg, w = d[si], a[si] - o
    den = n[:, 0] * seg[:, 1] - n[:, 1] * seg[:, 0]  # cross(n, d) = -dot(t, d)
    seg_len = np.linalg.norm(seg, axis=1)
    parallel = np.abs(den) >= math.cos(params.PASS_MAX_ANGLE_RAD) * seg_len
    den = np.where(parallel, den, 1.0)
    s = (w[:, 0] * seg[:, 1] - w[:, 1] * seg[:, 0]) / den  # cross(w, d) / cross(n, d)
    u = (w[:, 0] * n[:, 1] - w[:, 1] * n[:, 0]) / den  # cross(w, n) / cross(n, d)
    ok = parallel & (u >= 0.0) & (u < 1.0) & (np.abs(s) <= reach)
    pi, line, s = pi[ok], owner[si[ok]], s[ok]
    # one crossing per probe and line (the nearest), ordered across the ray
    order = np.lexsort((np.abs(s), line, pi))
    pi, line, s = pi[order], line[order], s[order]
    first = np.ones(len(pi), bool)
    first[1:] = (pi[1:] != pi[:-1]) | (line[1:] != line[:-1])
    pi, line, s = pi[first], line[first], s[first]
    order = np.lexsort((s, pi))
    pi, line, s = pi[order], line[order], s[order]
    pair = np.flatnonzero(pi[1:] == pi[:-1])
    width = s[pair + 1] - s[pair]
    lane = pair[
        (width >= params.MIN_LANE_WIDTH_M) & (width <= params.MAX_LANE_WIDTH_M + 2.0 * SHOULDER_MAX_M)
    ]
    return LaneCrossings(pi[lane], probe_trip[pi[lane]], line[lane], line[lane + 1], s[lane], s[lane + 1])


def thinned(probes_xy_dir: np.ndarray) -> np.ndarray:
    """Indices of the probes kept for the rays: at most ``THIN_PER_CELL`` per ``THIN_CELL_M``
    square and heading octant, the first ones in order."""
    octant = (
        np.floor((np.arctan2(probes_xy_dir[:, 3], probes_xy_dir[:, 2]) + np.pi) / (np.pi / 4)).astype(
            np.int64
        )
        % 8
    )
    cell = np.floor(probes_xy_dir[:, :2] / THIN_CELL_M).astype(np.int64)
    _, group = np.unique(np.column_stack([cell, octant]), axis=0, return_inverse=True)
    order = np.argsort(group, kind="stable")
    g = group[order]
    starts = np.r_[0, np.flatnonzero(np.diff(g)) + 1]
    rank = np.arange(len(g)) - np.repeat(starts, np.diff(np.r_[starts, len(g)]))
    return np.sort(order[rank < THIN_PER_CELL])


def shoulder_width_m(crossings: LaneCrossings, is_kerb: np.ndarray, params: TopologyParams) -> float:
    """Step 3: how far a kerb (road boundary) lies beyond the painted lane edge, from where the
    trips drove in strips between a divider and a kerb (median of ``W - 2 d``; strips at most a
    lane and ``SHOULDER_MAX_M`` wide); 0 m with fewer than ``SHOULDER_MIN_PROBES`` such probes."""
    kr, kl = is_kerb[crossings.right], is_kerb[crossings.left]
    one_kerb = crossings.driven & (kr != kl) & (crossings.width_m <= params.MAX_LANE_WIDTH_M + SHOULDER_MAX_M)
    if one_kerb.sum() < SHOULDER_MIN_PROBES:
        return 0.0
    d_from_divider = np.where(kr, crossings.s_left_m, -crossings.s_right_m)[one_kerb]
    return float(np.clip(np.median(crossings.width_m[one_kerb] - 2.0 * d_from_divider), 0.0, SHOULDER_MAX_M))


def painted_lanes(
    crossings: LaneCrossings, is_kerb: np.ndarray, shoulder_m: float, params: TopologyParams
) -> np.ndarray:
    """Step 2: the strips whose painted width (a shoulder less per kerb edge) is a lane's."""
    kerbs = is_kerb[crossings.right].astype(int) + is_kerb[crossings.left].astype(int)
    painted = crossings.width_m - kerbs * shoulder_m
    return (painted >= params.MIN_LANE_WIDTH_M) & (painted <= params.MAX_LANE_WIDTH_M)


def centre_offsets_m(crossings: LaneCrossings, is_kerb: np.ndarray, shoulder_m: float) -> np.ndarray:
    """Step 3: the lane centre's lateral offset on each probe's ray (left +)."""
    kr, kl = is_kerb[crossings.right], is_kerb[crossings.left]
    mid = 0.5 * (crossings.s_right_m + crossings.s_left_m)
    half_painted = 0.5 * np.maximum(crossings.width_m - shoulder_m, 0.0)
    return np.where(
        kr & ~kl,
        crossings.s_left_m - half_painted,
        np.where(kl & ~kr, crossings.s_right_m + half_painted, mid),
    )


def _fused_runs(
    points_xy: np.ndarray, reference_xy: np.ndarray, params: TopologyParams
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Step 5: centre points of one lane averaged per metre along ``reference_xy`` (its first
    bounding line), smoothed, cut at unsupported stretches of ``MAX_GAP_M``. Each run with the
    indices of the points it was made of."""
    ref = resample_polyline(reference_xy, params.BIN_M)
    _, k = cKDTree(ref).query(points_xy)
    bins, inverse = np.unique(k, return_inverse=True)
    sums = np.zeros((len(bins), 2))
    np.add.at(sums, inverse, points_xy)
    mean = sums / np.bincount(inverse)[:, None]
    cuts = np.flatnonzero(np.diff(bins) * params.BIN_M > params.MAX_GAP_M) + 1
    runs = []
    for j0, j1 in zip(np.r_[0, cuts], np.r_[cuts, len(bins)], strict=True):
        b, m = bins[j0:j1], mean[j0:j1]
        if (b[-1] - b[0]) * params.BIN_M < params.LANE_MIN_LENGTH_M:
            continue
        dense = np.column_stack([np.interp(np.arange(b[0], b[-1] + 1), b, m[:, c]) for c in (0, 1)])
        if len(dense) >= 3:
            dense = smooth_point_reflected(dense, params.SMOOTH_SIGMA_M / params.BIN_M)
        runs.append(
            (
                resample_polyline(dense, params.OUTPUT_SPACING_M),
                np.flatnonzero((inverse >= j0) & (inverse < j1)),
            )
        )
    return runs


def derive_centerlines(
    features: Sequence[MapFeature],
    probes: Mapping[str, np.ndarray],
    params: TopologyParams,
    trip_times: Mapping[str, object] | None = None,
    previous: Sequence[MapFeature] = (),
) -> list[MapFeature]:
    """The derived centrelines of the map ``features``: lanes (steps 1-6 of the module
    docstring) and connectors (step 7). ``probes``: trip key -> ``(P, 4)`` path probes
    (``instances.path_probes``); ``previous``: the map's earlier derived centrelines, whose ids
    continue."""
    if not params.DERIVE_CENTERLINES or not probes:
        return []
    lanes = derived_lanes(features, probes, params, trip_times)
    perceived = [f for f in features if f.type == ElementType.CENTERLINE]
    connectors = derive_connectors([*perceived, *lanes], probes, params, trip_times)
    return assign_ids(lanes + connectors, previous, params)


def derived_lanes(
    features: Sequence[MapFeature],
    probes: Mapping[str, np.ndarray],
    params: TopologyParams,
    trip_times: Mapping[str, object] | None = None,
) -> list[MapFeature]:
    """Steps 1-6: a centreline for each lane between the bounding lines that the trips' rays
    crossed, that no perceived centreline covers and, beside a kerb, that a trip drove in (ids
    not set)."""
    keys = sorted(probes)
    all_probes = np.concatenate([probes[k] for k in keys])
    probe_trip = np.concatenate([np.full(len(probes[k]), i) for i, k in enumerate(keys)])
    kept = thinned(all_probes)
    all_probes, probe_trip = all_probes[kept], probe_trip[kept]
    crossings = lane_crossings(features, all_probes, probe_trip, params)
    if len(crossings.probe) == 0:
        return []
    is_kerb = np.array([f.type == ElementType.ROAD_BOUNDARY for f in features])
    shoulder = shoulder_width_m(crossings, is_kerb, params)
    s_c = centre_offsets_m(crossings, is_kerb, shoulder)
    o, t = all_probes[crossings.probe, :2], all_probes[crossings.probe, 2:]
    centre = o + s_c[:, None] * np.column_stack([-t[:, 1], t[:, 0]])
    keep = painted_lanes(crossings, is_kerb, shoulder, params) & _away_from_perceived(
        centre, features, params
    )
    lane_key = np.minimum(crossings.right, crossings.left) * len(features) + np.maximum(
        crossings.right, crossings.left
    )
    lanes: list[MapFeature] = []
    for key in np.unique(lane_key[keep]):
        rows = np.flatnonzero(keep & (lane_key == key))
        i_a, i_b = divmod(int(key), len(features))
        for run, members in _fused_runs(
            centre[rows], np.asarray(features[i_a].points_xy_world, float), params
        ):
            r = rows[members]
            if (is_kerb[i_a] or is_kerb[i_b]) and not crossings.driven[r].any():
                continue  # a strip beside a kerb that nobody drove: parking, a cycle lane, a verge
            lanes.append(
                _feature(
                    run,
                    centre[r],
                    t[r],
                    crossings.driven[r],
                    [keys[i] for i in crossings.trip[r]],
                    (features[i_a], features[i_b]),
                    shoulder,
                    trip_times,
                )
            )
    return lanes


def _away_from_perceived(
    centre_xy: np.ndarray, features: Sequence[MapFeature], params: TopologyParams
) -> np.ndarray:
    """Step 4: centre points farther than half a narrow lane from every perceived centreline."""
    perceived = [
        resample_polyline(np.asarray(f.points_xy_world, float), params.SAMPLE_SPACING_M)
        for f in features
        if f.type == ElementType.CENTERLINE and len(f.points_xy_world) >= 2
    ]
    if not perceived:
        return np.ones(len(centre_xy), bool)
    dist, _ = cKDTree(np.concatenate(perceived)).query(centre_xy)
    return dist > 0.5 * params.MIN_LANE_WIDTH_M


def _feature(
    run_xy: np.ndarray,
    centre_xy: np.ndarray,
    probe_dir: np.ndarray,
    driven: np.ndarray,
    probe_trips: Sequence[str],
    edges: tuple[MapFeature, MapFeature],
    shoulder_m: float,
    trip_times: Mapping[str, object] | None,
) -> MapFeature:
    """Step 6 and the properties: direction from the trips that drove in the lane (else from
    those that saw it); ``trips``: those whose probes made the run; ``support_trips``: that of
    the less supported edge."""
    tangent = np.gradient(run_xy, axis=0)
    _, at = cKDTree(run_xy).query(centre_xy)
    along = (probe_dir * tangent[at]).sum(1)
    vote = along[driven].sum() if driven.any() else along.sum()
    if vote < 0:
        run_xy = run_xy[::-1].copy()
    u = [float(e.properties.get("uncertainty_m", 0.1)) for e in edges]
    kerbs = [e.type == ElementType.ROAD_BOUNDARY for e in edges]
    props = derived_properties(
        probe_trips,
        trip_times,
        # the lane is as well confirmed as the less confirmed of its edges (the validator's
        # low_support then says what it says of them)
        support_trips=min(int(e.properties.get("support_trips", len(set(probe_trips)))) for e in edges),
        support_observations=len(centre_xy),
        uncertainty_m=u[kerbs.index(False)] if kerbs[0] != kerbs[1] else 0.5 * math.hypot(*u),
        derived="bounding_lines",
        derived_from=edges,
        direction="driven" if driven.any() else "assumed",
    )
    props["shoulder_m"] = round(shoulder_m, 3) if kerbs[0] != kerbs[1] else 0.0
    return MapFeature(ElementType.CENTERLINE, run_xy, None, "", props)


def is_derived(feature: MapFeature) -> bool:
    """A centreline of this stage (recomputed with the map, never fused from trips)."""
    return "derived" in feature.properties
