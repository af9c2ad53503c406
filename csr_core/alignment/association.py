"""Sub-map data association, Algorithm 1 of the paper, and its result record.

``associate`` is the recipe (steps 1-7 of Algorithm 1); the stages live in ``topology``
(Step 1), ``graph_matching`` + ``registration`` (Step 2), ``temporal`` (Step 3) and
``inter_trip`` (Step 4). ``match_pair`` is Step 2 for one candidate pair.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from csr_core import se2
from csr_core.alignment.graph_matching import (
    ElementSet,
    boundary_prealignment,
    element_distances,
    eq4_objective,
    node_similarity,
    rrwm_match,
)
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.alignment.registration import LandmarkSets, match_confidence, register_elements
from csr_core.alignment.submaps import Circle, Submap
from csr_core.types import TripReconstruction

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class PairMatch:
    """An accepted sub-map matching pair (kept for validation and human correction).

    ``delta_local_xyyaw`` maps sub-map ``j``'s elements (initial poses) onto sub-map ``i``'s in
    the circle's local frame (world axes, origin ``centre_xy_world``); ``information_local`` is
    its information matrix there. ``element_matches`` are ``(element of i, element of j)``
    indices, ``instance_matches`` the same as trip instance (or prior feature) indices.
    """

    i: int
    j: int
    trip_i: int
    trip_j: int
    circle_id: int
    centre_xy_world: np.ndarray
    delta_local_xyyaw: np.ndarray
    information_local: np.ndarray
    element_matches: tuple[tuple[int, int], ...]
    instance_matches: tuple[tuple[int, int], ...]
    match_confidences: np.ndarray  # Eq. 7 per element match
    confidence: float  # c_ij: mean of the element confidences
    residual_rms_m: float
    objective: float  # Eq. 4 value of the chosen association
    human: bool = False  # added by a human correction: a known inlier with a large weight
    # (3, 3) share of the start (GNSS relative) pose kept by the registration, local frame
    # (``Registration.prior_sensitivity``): what it does not measure, it repeats from GNSS
    prior_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def relative_pose(self, world_T_i: np.ndarray, world_T_j: np.ndarray) -> np.ndarray:
        """``T_reg^{i,j} = i_T_j`` implied by the registration (initial poses of i and j)."""
        c = np.array([self.centre_xy_world[0], self.centre_xy_world[1], 0.0])
        gi, gj = world_T_i - c, world_T_j - c
        return se2.between(gi, se2.compose(self.delta_local_xyyaw, gj))

    def information_body_j(self, world_T_j: np.ndarray) -> np.ndarray:
        """The registration information in the body frame of ``j`` (gtsam Pose2 tangent)."""
        c = np.array([self.centre_xy_world[0], self.centre_xy_world[1], 0.0])
        x, y, th = se2.compose(self.delta_local_xyyaw, world_T_j - c)
        cth, sth = np.cos(th), np.sin(th)
        ad = np.array([[cth, -sth, y], [sth, cth, -x], [0.0, 0.0, 1.0]])  # Pose2 AdjointMap
        return ad.T @ self.information_local @ ad


def element_set(
    submap: Submap, centre_xy_world: np.ndarray, world_T_submap: np.ndarray | None = None
) -> ElementSet:
    pts = submap.element_points_world(world_T_submap)
    return ElementSet(tuple(e.type for e in submap.elements), tuple(p - centre_xy_world for p in pts))


def landmark_pairs(
    si: Submap, sj: Submap, centre_xy_world: np.ndarray, noise: NoiseScales, params: AlignmentParams
) -> LandmarkSets | None:
    """Both sub-maps' dash-end landmarks in the circle's local frame, with the sigma of each
    (one sighting's along sigma over the square root of its sightings, at most 4 counted: the
    sightings share the trip's local pose error)."""
    if not params.landmarks or len(si.landmarks_xy_submap) == 0 or len(sj.landmarks_xy_submap) == 0:
        return None
    (pa, ua), (pb, ub) = si.landmarks_world(), sj.landmarks_world()
    sig = lambda n: noise.dash_end_sigma_m / np.sqrt(np.minimum(n, 4))  # noqa: E731
    return LandmarkSets(
        pa - centre_xy_world,
        ua,
        sig(si.landmark_counts),
        pb - centre_xy_world,
        ub,
        sig(sj.landmark_counts),
        params.landmark_gate_max_m,
    )


def _point_sigma(noise: NoiseScales) -> float:
    lat = [v for v in noise.lateral_sigma_m.values()]
    return float(np.sqrt(2.0) * np.sqrt(np.mean(np.square(lat))))


def _element_distances(
    submap: Submap, circle: Circle, elements: ElementSet, cache: dict[tuple[int, int], np.ndarray] | None
) -> np.ndarray:
    if cache is None:
        return element_distances(elements)
    key = (submap.submap_id, circle.circle_id)
    if key not in cache:
        cache[key] = element_distances(elements)
    return cache[key]


def match_pair(
    si: Submap,
    sj: Submap,
    circle: Circle,
    noise: NoiseScales,
    params: AlignmentParams,
    forced_matches: Sequence[tuple[int, int]] | None = None,
    initial_xyyaw: np.ndarray | None = None,
    distance_cache: dict[tuple[int, int], np.ndarray] | None = None,
) -> PairMatch | None:
    """Step 2 for one pair: pre-align by the road boundaries, match elements (Eq. 4-6, RRWM),
    register by GNC-TLS, confidence by Eq. 7. ``forced_matches`` skips the matching (Step 3
    re-registration). None when the pair cannot be registered. ``distance_cache``: element
    distances (Eq. 6) of sub-maps already seen in this circle, filled as pairs are matched."""
    a = element_set(si, circle.centre_xy_world)
    b = element_set(sj, circle.centre_xy_world)
    if len(a) < params.min_matched_elements or len(b) < params.min_matched_elements:
        return None
    e_a, e_b = (_element_distances(s, circle, e, distance_cache) for s, e in ((si, a), (sj, b)))
    direction = np.array([np.cos(circle.heading_rad), np.sin(circle.heading_rad)])
    if forced_matches is None:
        # hypotheses: the GNSS initial pose, and the road-boundary pre-alignment
        best = None
        prealign = boundary_prealignment(a, b, direction, params.max_prealign_shift_m)
        shifts = [prealign] if np.linalg.norm(prealign) < 0.25 * noise.sigma_p_m else [np.zeros(2), prealign]
        for shift in shifts:
            s_node = node_similarity(a, b.shifted(shift), noise, params)
            matches = rrwm_match(s_node, e_a, e_b, noise.sigma_e_m, params)
            obj = eq4_objective(matches, s_node, e_a, e_b, noise.sigma_e_m, params)
            if best is None or obj > best[0]:
                best = (obj, matches, shift)
        assert best is not None  # shifts is never empty and the first hypothesis always sets best
        objective, matches, shift = best
        initial = np.array([shift[0], shift[1], 0.0])
    else:
        matches, objective = list(forced_matches), float("nan")
        initial = np.zeros(3) if initial_xyyaw is None else initial_xyyaw
    if len(matches) < params.min_matched_elements:
        return None
    closed = [e.closed for e in si.elements]
    reg = register_elements(
        a,
        b,
        matches,
        _point_sigma(noise),
        params,
        closed,
        initial,
        landmark_pairs(si, sj, circle.centre_xy_world, noise, params),
    )
    if reg is None or reg.residual_rms_m > params.max_registration_rms_k * _point_sigma(noise):
        return None
    kept = [m for m, ok in zip(matches, reg.element_inlier, strict=False) if ok]
    b_aligned = ElementSet(b.types, tuple(se2.transform_points(reg.delta_xyyaw, p) for p in b.points))
    conf = match_confidence(a, b_aligned, kept, noise, params, target_distances=e_a)
    return PairMatch(
        si.submap_id,
        sj.submap_id,
        si.trip_index,
        sj.trip_index,
        circle.circle_id,
        circle.centre_xy_world.copy(),
        reg.delta_xyyaw,
        reg.information_xyyaw,
        tuple(kept),
        tuple((si.elements[k].instance_index, sj.elements[kp].instance_index) for k, kp in kept),
        conf,
        float(np.mean(conf)),
        reg.residual_rms_m,
        float(objective),
        prior_sensitivity=reg.prior_sensitivity,
    )


def associate(
    submaps: Sequence[Submap],
    circles: Sequence[Circle],
    pairs: Sequence[tuple[int, int]],
    trips: Sequence[TripReconstruction],
    noise: NoiseScales,
    params: AlignmentParams,
    trace: dict | None = None,
) -> list[PairMatch]:
    """Algorithm 1: the optimal data association D* over all candidate pairs. ``trace``
    (diagnostics) receives ``eq3_passed``: Step 1's outcome per candidate pair."""
    from csr_core.alignment.inter_trip import inter_trip_consistency
    from csr_core.alignment.temporal import temporal_consistency
    from csr_core.alignment.topology import topology_filter

    # 1-2: global topology consistency (Eq. 3) and sliding-window voting
    keep = topology_filter(pairs, submaps, circles, trips, noise, params)
    candidates = [p for p, ok in zip(pairs, keep, strict=False) if ok]
    if trace is not None:
        trace["eq3_passed"] = np.asarray(keep, bool)
    # 3-4: multi-order graph matching (Eq. 4-6), GNC relative pose, confidence (Eq. 7)
    distances: dict[tuple[int, int], np.ndarray] = {}
    matched = [
        m
        for i, j in candidates
        if (
            m := match_pair(
                submaps[i], submaps[j], circles[submaps[i].circle_id], noise, params, distance_cache=distances
            )
        )
        is not None
    ]
    # 5: intra-trip temporal consistency (Eq. 8)
    matched = temporal_consistency(matched, submaps, circles, noise, params)
    # 6: inter-trip consistency: maximum clique of consistent pairs
    inliers = inter_trip_consistency(matched, params)
    log.debug(
        "association: %d candidate pairs, %d after Eq. 3, %d matched, %d consistent",
        len(pairs),
        len(candidates),
        len(matched),
        len(inliers),
    )
    # 7: D*
    return inliers
