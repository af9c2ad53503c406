"""Association of the aligned instances of all trips (paper III-E: "the semantic elements of
different trips are matched together"), per element type.

Lines: every instance is sampled every ``SAMPLE_SPACING_M``. For each sample, the nearest
sample of every other instance within reach gives a signed offset in that instance's local
frame (its tangent): the lateral distance, and whether the foot lies inside the other
instance's extent (not past one of its ends). Over each ordered pair of instances:

- *alongside*: samples inside the other's extent, within ``WINDOW_GATES`` gates of it and
  nearly parallel (either way: a trip's instance runs the way the trip drove);
- *close*: of those, the ones within the gate (``TopologyParams.gate_m`` of the two trips'
  sigmas).

Two instances are one element when their close overlap is at least ``MIN_OVERLAP_M`` (or half
the shorter one: a trip may see only part of a long divider) and most of what lies alongside
is close (``MIN_CLOSE_SHARE``: two branches of a split are alongside but drift apart). Groups
are the connected components of these links, so chains of partial overlaps join. Fusion may
detach a member that the fused geometry does not support (``fusion.detach``).

Polygons: two outlines are one element when they intersect with IoU >= 0.2 or their
centroids are within the polygon gate.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, TripInstance

MAP_MEMBER_KEY = "<map>"  # trip key of a map instance standing for its members (incremental update)
NEIGHBOUR_BLOCK_SAMPLES = 10_000  # samples per block of the neighbour searches (``neighbour_pairs``)


@dataclass(frozen=True, slots=True)
class Member:
    """One aligned trip instance taking part in fusion; ``sigma_m`` its lateral 1-sigma
    (``TopologyParams.trip_sigma_m``)."""

    trip_key: str
    index: int
    instance: TripInstance
    sigma_m: float


@dataclass(frozen=True, slots=True)
class LineSamples:
    """All members' samples, flattened: ``points_xy (N, 2)``, unit ``tangents (N, 2)``,
    ``owner (N,)`` member index, ``is_first``/``is_last (N,)`` end samples of their member."""

    points_xy: np.ndarray
    tangents: np.ndarray
    owner: np.ndarray
    is_first: np.ndarray
    is_last: np.ndarray


def sample_members(members: Sequence[Member], spacing_m: float) -> LineSamples:
    return sample_lines([m.instance.points_xy_world for m in members], spacing_m)


def sample_lines(lines_xy: Sequence[np.ndarray], spacing_m: float) -> LineSamples:
    """Polylines ``(M, 2)`` resampled every ``spacing_m``, flattened (``owner``: the line)."""
    pts = [resample_polyline(np.asarray(xy, float), spacing_m) for xy in lines_xy]
    if not pts:
        z = np.zeros((0, 2))
        return LineSamples(z, z, np.zeros(0, int), np.zeros(0, bool), np.zeros(0, bool))
    own = np.repeat(np.arange(len(pts)), [len(p) for p in pts])
    first = np.r_[True, own[1:] != own[:-1]]
    last = np.r_[own[1:] != own[:-1], True]
    points = np.concatenate(pts)
    return LineSamples(points, _unit_tangents(points, first, last), own, first, last)


def _unit_tangents(points: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Unit tangents ``(N, 2)`` of polylines stacked in ``points (N, 2)`` (``first``/``last``:
    their end rows), for all at once as ``np.gradient`` gives them for each: central
    differences, one-sided at the ends; (1, 0) for a single point."""
    row = np.arange(len(points))
    after = np.where(last, row, row + 1)
    before = np.where(first, row, row - 1)
    tan = points[after] - points[before]
    inner = ~first & ~last
    tan[inner] /= 2.0
    tan[first & last] = (1.0, 0.0)
    return tan / np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)


def _first_min_per_group(group: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Index of the smallest ``value`` in each group (the first one on ties), groups in
    ascending order. ``group (K,)`` non-negative integer keys.

    One sort of a single integer key, ``group`` in the high bits and the index in the low bits
    (each group's rows stay in index order), instead of a lexsort over (group, value): the
    group's minimum by ``np.minimum.reduceat``, then its first row reaching it."""
    index_bits = max(int(len(group)).bit_length(), 1)
    group = np.asarray(group, dtype=np.int64)
    if int(group.max()) < 1 << (62 - index_bits):
        # timsort ("stable"): the keys come in runs (pairs by KD-tree leaf), about twice as fast here
        packed = np.sort((group << index_bits) | np.arange(len(group), dtype=np.int64), kind="stable")
        index = packed & ((1 << index_bits) - 1)
    else:  # keys too large to pack with the index
        index = np.argsort(group, kind="stable")
    group_sorted = group[index]
    value_sorted = value[index]
    starts = np.flatnonzero(np.r_[True, group_sorted[1:] != group_sorted[:-1]])
    group_min = np.minimum.reduceat(value_sorted, starts)
    at_min = np.flatnonzero(value_sorted == np.repeat(group_min, np.diff(np.r_[starts, len(index)])))
    first = np.r_[True, group_sorted[at_min][1:] != group_sorted[at_min][:-1]]
    return index[at_min[first]]


def neighbour_pairs(
    points_xy: np.ndarray, owner: np.ndarray, radius_m: float, tree: cKDTree | None = None
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every ordered pair of samples ``(a, b)`` of different owners within ``radius_m``, with
    their distance, as ``(a, b, distance_m)`` arrays, block by block of ``a`` (ascending blocks of
    ``NEIGHBOUR_BLOCK_SAMPLES``). At ten trips a place a sample has a hundred or more neighbours,
    and the arrays of all pairs at once cost more to allocate than to use. ``tree``: a KD-tree
    over ``points_xy`` if the caller has one."""
    tree = tree if tree is not None else cKDTree(points_xy)
    for lo in range(0, len(points_xy), NEIGHBOUR_BLOCK_SAMPLES):
        block = (
            tree
            if len(points_xy) <= NEIGHBOUR_BLOCK_SAMPLES
            else cKDTree(points_xy[lo : lo + NEIGHBOUR_BLOCK_SAMPLES])
        )
        near = block.sparse_distance_matrix(tree, radius_m, output_type="ndarray")
        a, b = near["i"].astype(np.int64) + lo, near["j"].astype(np.int64)
        other = owner[a] != owner[b]  # pairs within one owner never count
        yield a[other], b[other], near["v"][other]


def nearest_offsets(
    samples: LineSamples, reach_m: float, spacing_m: float, directed: bool, max_angle_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every sample ``a`` and every other member with a sample within ``reach_m``: that
    member, the lateral distance of ``a`` to it (along its nearest sample's tangent) and whether
    ``a`` lies inside its extent and is parallel to it. Returns ``(a, member, lateral_m, inside)``,
    ordered by ``a``, then member."""
    own = samples.owner
    n_members = int(own.max()) + 1 if len(own) else 0
    nearest_a, nearest_b = [], []
    for a, b, dist in neighbour_pairs(samples.points_xy, own, reach_m):
        if len(a):  # nearest sample of each other member, per sample a
            nearest = _first_min_per_group(a * n_members + own[b], dist)
            nearest_a.append(a[nearest])
            nearest_b.append(b[nearest])
    if not nearest_a:
        e = np.zeros(0, int)
        return e, e, np.zeros(0), np.zeros(0, bool)
    a, b = np.concatenate(nearest_a), np.concatenate(nearest_b)
    rel = samples.points_xy[a] - samples.points_xy[b]
    tb = samples.tangents[b]
    along = rel[:, 0] * tb[:, 0] + rel[:, 1] * tb[:, 1]
    lateral = np.abs(tb[:, 0] * rel[:, 1] - tb[:, 1] * rel[:, 0])
    half = 0.5 * spacing_m
    outside = (samples.is_last[b] & (along > half)) | (samples.is_first[b] & (along < -half))
    cos = (samples.tangents[a] * tb).sum(1)
    parallel = (cos if directed else np.abs(cos)) >= math.cos(max_angle_rad)
    return a, own[b], lateral, ~outside & parallel


def _components(n: int, i: np.ndarray, j: np.ndarray) -> list[list[int]]:
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    groups: dict[int, list[int]] = {}
    for k, lab in enumerate(labels):
        groups.setdefault(int(lab), []).append(k)
    return list(groups.values())


def associate_lines(
    members: Sequence[Member], element_type: ElementType, params: TopologyParams
) -> list[list[int]]:
    """Groups (lists of member indices) of line instances that are the same element."""
    n = len(members)
    if n == 0:
        return []
    spacing = params.SAMPLE_SPACING_M
    samples = sample_members(members, spacing)
    sigma = np.array([m.sigma_m for m in members])
    max_gate = max(
        params.gate_m(s1, s2) for s1 in (sigma.min(), sigma.max()) for s2 in (sigma.min(), sigma.max())
    )
    reach = params.WINDOW_GATES * max_gate + 0.5 * spacing
    # undirected for every type: a trip's instance runs the way the trip drove, not the lane
    a, mb, lateral, inside = nearest_offsets(samples, reach, spacing, False, params.MAX_ANGLE_RAD)
    ma = samples.owner[a]
    gate = np.minimum(
        params.GATE_SIGMAS * np.hypot(sigma[ma], sigma[mb]),
        params.GATE_MAX_SHARE_OF_LANE * params.MIN_LANE_WIDTH_M,
    )
    alongside = inside & (lateral <= params.WINDOW_GATES * gate)
    close = alongside & (lateral <= gate)
    key = ma * n + mb
    n_along = np.bincount(key[alongside], minlength=n * n).reshape(n, n).astype(float)
    n_close = np.bincount(key[close], minlength=n * n).reshape(n, n).astype(float)
    lengths = np.bincount(samples.owner, minlength=n) * spacing
    both_close = np.minimum(n_close, n_close.T) * spacing
    share = (n_close + n_close.T) / np.maximum(n_along + n_along.T, 1.0)
    need = np.minimum(params.MIN_OVERLAP_M, 0.5 * np.minimum(lengths[:, None], lengths[None, :]))
    linked = (both_close >= need) & (share >= params.MIN_CLOSE_SHARE) & (n_close + n_close.T > 0)
    i, j = np.nonzero(np.triu(linked, 1))
    return _components(n, i, j)


def _outline_polygon(points_xy: np.ndarray) -> shapely.Geometry:
    points_xy = np.asarray(points_xy, float)
    if len(points_xy) >= 3:
        return shapely.Polygon(points_xy)
    return shapely.MultiPoint(points_xy).convex_hull


def associate_polygons(members: Sequence[Member], params: TopologyParams) -> list[list[int]]:
    """Groups of polygon instances (crosswalks, road markings) that are the same element."""
    n = len(members)
    if n == 0:
        return []
    # outlines differ in vertex count: one Polygon each (a degenerate one as its points' hull)
    polys = shapely.make_valid(
        np.array([_outline_polygon(m.instance.points_xy_world) for m in members], dtype=object)
    )
    tree = shapely.STRtree(polys)
    i, j = tree.query(polys, predicate="intersects")
    keep = i < j
    i, j = i[keep], j[keep]
    inter = shapely.area(shapely.intersection(polys[i], polys[j]))
    union = np.maximum(shapely.area(shapely.union(polys[i], polys[j])), 1e-9)
    cent = shapely.get_coordinates(shapely.centroid(polys))
    sigma = np.array([m.sigma_m for m in members])
    gate = np.maximum(params.POLYGON_GATE_M, params.GATE_SIGMAS * np.hypot(sigma[i], sigma[j]))
    near = np.linalg.norm(cent[i] - cent[j], axis=1) <= gate
    ok = (inter / union >= 0.2) | near
    return _components(n, i[ok], j[ok])
