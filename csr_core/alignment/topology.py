"""Algorithm 1, Step 1: global topology consistency (Eq. 3) and sliding-window voting.

Descriptors are read on a cross-section of each sub-map: the line through the circle centre
perpendicular to the circle's reference heading (world frame, initial poses), so sub-maps of
one circle are compared on the same line whatever their anchor frames. Each descriptor is of
the road its own vehicle drove; a trip none of whose pairs passes that is read again on the same
road, each vehicle's road as both sub-maps show it (:func:`same_road_consistent`: the two
carriageways of a divided road, each with only the other's trips).

- ``N_nl`` lane count: lateral crossings of dividers and boundaries (merged within 1 m) minus 1;
- ``N_rw`` road width: between the nearest boundary crossing on each side of the vehicle;
- ``N_sm`` split/merge count: divider and centreline ends strictly inside the circle;
- ``N_rc`` road centre: mid-point of those two boundaries (lateral coordinate).

A missing quantity (e.g. one boundary out of sight) leaves its test out instead of failing it.
Thresholds grow with the single-trip noise (boundary sigma, pose sigma), as the paper asks.
``N_sm`` is a count of element ends, and its noise is that of a count: a junction's pieces and
the breaks of occluded tracks come and go from trip to trip, so two sightings of one place
differ by about ``sqrt(N_sm^i + N_sm^j)`` (Poisson); ``tau_sm`` is at least ``z`` times that.
A fixed ``tau_sm = 3`` rejected one in eight same-road pairs on Karlsruhe (17 against 10 ends).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from csr_core.alignment.geometry import line_crossing
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.alignment.submaps import Circle, Submap
from csr_core.types import ElementType, TripReconstruction

_LINE_TYPES = (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY)
_END_TYPES = (ElementType.LANE_DIVIDER, ElementType.CENTERLINE)


@dataclass(frozen=True, slots=True)
class TopologyDescriptor:
    lane_count: int  # N_nl (-1: unknown)
    road_width_m: float  # N_rw (NaN: unknown)
    split_merge_count: int  # N_sm
    road_centre_m: float  # N_rc, lateral coordinate on the cross-section (NaN: unknown)
    pose_sigma_m: float  # smoothed-pose sigma at the anchor (sets tau_rc)


@dataclass(frozen=True, slots=True)
class CrossSection:
    """What one sub-map shows on its circle's cross-section (lateral coordinates, metres):
    crossings of dividers and boundaries (sorted), of boundaries alone, its vehicle's position,
    and the divider and centreline ends inside the circle."""

    crossings_m: np.ndarray
    boundaries_m: np.ndarray
    vehicle_m: float
    split_merge_count: int


def cross_section(submap: Submap, circle: Circle) -> CrossSection:
    direction = np.array([np.cos(circle.heading_rad), np.sin(circle.heading_rad)])
    normal = np.array([-direction[1], direction[0]])
    pts_world = submap.element_points_world()
    crossings: list[float] = []
    boundaries: list[float] = []
    ends = 0
    for e, pts in zip(submap.elements, pts_world, strict=False):
        if e.closed:
            continue
        if e.type in _LINE_TYPES:
            y = line_crossing(pts, circle.centre_xy_world, direction)
            if np.isfinite(y):
                crossings.append(y)
                if e.type == ElementType.ROAD_BOUNDARY:
                    boundaries.append(y)
        if e.type in _END_TYPES:
            r = np.linalg.norm(pts[[0, -1]] - circle.centre_xy_world, axis=1)
            ends += int(np.sum(r < circle.radius_m - 3.0))
    vehicle = float((submap.world_T_submap[:2] - circle.centre_xy_world) @ normal)
    return CrossSection(np.sort(np.asarray(crossings, float)), np.asarray(boundaries, float), vehicle, ends)


def descriptor_at(section: CrossSection, lateral_m: float, pose_sigma_m: float) -> TopologyDescriptor:
    """Eq. 3's quantities of the road around ``lateral_m`` on the cross-section (the nearest
    boundary on each side of it) as ``section`` shows it; unknown where it shows no boundary on
    one side."""
    xs, b = section.crossings_m, section.boundaries_m
    left, right = b[b > lateral_m], b[b < lateral_m]
    if len(left) and len(right):
        lo, hi = float(right.max()), float(left.min())
        width, centre = hi - lo, 0.5 * (hi + lo)
        lanes = int(np.sum((np.diff(xs) > 1.0) & (xs[1:] <= hi + 0.5) & (xs[:-1] >= lo - 0.5)))
    else:
        width, centre, lanes = float("nan"), float("nan"), -1
    return TopologyDescriptor(lanes, width, section.split_merge_count, centre, pose_sigma_m)


def topology_descriptor(submap: Submap, circle: Circle, pose_sigma_m: float) -> TopologyDescriptor:
    """Eq. 3's quantities of the road the sub-map's own vehicle drove."""
    section = cross_section(submap, circle)
    return descriptor_at(section, section.vehicle_m, pose_sigma_m)


def topology_consistent(
    a: TopologyDescriptor, b: TopologyDescriptor, noise: NoiseScales, params: AlignmentParams
) -> bool:
    """Eq. 3, each test only where both sub-maps define the quantity; ``tau_sm`` grows with the
    two counts' Poisson noise (module docstring)."""
    if (
        a.lane_count >= 0
        and b.lane_count >= 0
        and abs(a.lane_count - b.lane_count) > params.topo_lane_count_tol
    ):
        return False
    tau_rw = params.topo_road_width_k * np.sqrt(2.0) * noise.boundary_sigma_m
    if (
        np.isfinite(a.road_width_m)
        and np.isfinite(b.road_width_m)
        and abs(a.road_width_m - b.road_width_m) > tau_rw
    ):
        return False
    tau_sm = max(
        params.topo_split_merge_tol,
        params.topo_split_merge_z * np.sqrt(a.split_merge_count + b.split_merge_count),
    )
    if abs(a.split_merge_count - b.split_merge_count) > tau_sm:
        return False
    tau_rc = params.topo_road_centre_floor_m + params.topo_road_centre_k * np.sqrt(
        a.pose_sigma_m**2 + b.pose_sigma_m**2 + noise.boundary_sigma_m**2
    )
    if (
        np.isfinite(a.road_centre_m)
        and np.isfinite(b.road_centre_m)
        and abs(a.road_centre_m - b.road_centre_m) > tau_rc
    ):
        return False
    return True


def same_road_consistent(
    a: CrossSection,
    b: CrossSection,
    pose_sigma_a_m: float,
    pose_sigma_b_m: float,
    noise: NoiseScales,
    params: AlignmentParams,
) -> bool:
    """Eq. 3 on the same road: the road each of the two vehicles drove, as both sub-maps show it.

    Two trips on the two carriageways of a divided road (paired since the frame graph reaches
    across them, docs/alignment.md) each drove their own road; comparing one's
    carriageway with the other's compared two roads and always failed (road centres a median
    apart), so a trip that only ever met a trip on the other carriageway was failed
    (``no_consistent_match``). Compared at each vehicle's position, a carriageway is compared
    with itself where the other sub-map shows it and skipped where it does not; for two
    vehicles on one road both comparisons are the one before. ``topology_filter`` uses it only
    for trips that no pair ties otherwise: for every pair it tied the two carriageways of the
    benchmark's highways too, with right registrations, and lost ATE on two of four fleets
    (docs/alignment.md)."""
    return all(
        topology_consistent(
            descriptor_at(a, at, pose_sigma_a_m), descriptor_at(b, at, pose_sigma_b_m), noise, params
        )
        for at in {a.vehicle_m, b.vehicle_m}
    )


def sliding_window_vote(
    keys: Sequence[tuple], order: np.ndarray, votes: np.ndarray, half_window: int, min_fraction: float
) -> np.ndarray:
    """Smooth binary outcomes in time: within each group (same two trips), ordered by
    ``order``, a pair is kept when at least ``min_fraction`` of the ``2w+1`` outcomes around
    it (itself included) are positive, and its own outcome is positive."""
    votes = np.asarray(votes, bool)
    out = votes.copy()
    groups: dict[tuple, list[int]] = {}
    for i, k in enumerate(keys):
        groups.setdefault(k, []).append(i)
    idx: list[int] | np.ndarray  # a group's indices, then ordered in time
    for idx in groups.values():
        idx = np.asarray(idx)[np.argsort(np.asarray(order)[idx], kind="stable")]
        v = votes[idx].astype(float)
        for p in range(len(idx)):
            lo, hi = max(0, p - half_window), min(len(idx), p + half_window + 1)
            out[idx[p]] = votes[idx[p]] and v[lo:hi].mean() >= min_fraction
    return out


def topology_filter(
    pairs: Sequence[tuple[int, int]],
    submaps: Sequence[Submap],
    circles: Sequence[Circle],
    trips: Sequence[TripReconstruction],
    noise: NoiseScales,
    params: AlignmentParams,
) -> np.ndarray:
    """Step 1 for all candidate pairs: Eq. 3, then voting over each trip pair's sequence (a
    second reading for trips that meet nobody in the first, module docstring)."""
    sections: dict[int, CrossSection] = {}
    sigmas: dict[int, float] = {}
    for s in submaps:
        sigma = float(trips[s.trip_index].pose_sigma_xy_m[s.anchor_frame]) if not s.is_prior else 0.0
        sections[s.submap_id] = cross_section(s, circles[s.circle_id])
        sigmas[s.submap_id] = sigma if np.isfinite(sigma) else 1.0

    keys = [(submaps[i].trip_index, submaps[j].trip_index) for i, j in pairs]
    order = np.array([submaps[i].anchor_frame for i, _ in pairs], float)
    # Eq. 3 on each vehicle's own road (the road it drove against the road the other drove)
    own = {k: descriptor_at(sec, sec.vehicle_m, sigmas[k]) for k, sec in sections.items()}
    raw = np.array([topology_consistent(own[i], own[j], noise, params) for i, j in pairs], bool)
    kept = sliding_window_vote(keys, order, raw, params.voting_half_window, params.voting_min_fraction)
    # a trip none of whose pairs passed shares no road with the others by that reading: the two
    # carriageways of a divided road, when each only has the other. Its pairs are read again on
    # the same road (``same_road_consistent``), each carriageway against itself
    met = {t for (a, b), ok in zip(keys, kept, strict=True) if ok for t in (a, b)}
    alone = {t for k in keys for t in k if t >= 0} - met
    again = np.array([bool(alone & set(k)) for k in keys], bool)
    if again.any():
        raw[again] = [
            same_road_consistent(sections[i], sections[j], sigmas[i], sigmas[j], noise, params)
            for (i, j), a in zip(pairs, again, strict=True)
            if a
        ]
        kept = sliding_window_vote(keys, order, raw, params.voting_half_window, params.voting_min_fraction)
    return kept
