"""Multi-trip alignment (paper section III-D): coarse (sub-map) then fine (frame) alignment of
many trips into one frame, incrementally against a pre-built map.

``align_trips`` reads like the paper's Fig. 3; one module per stage:

- ``submaps``        sub-map splitting and matching pairs (Fig. 4)
- ``topology``       Algorithm 1 Step 1: global topology consistency (Eq. 3) + voting
- ``graph_matching`` Step 2: multi-order graph matching (Eq. 4-6, RRWM)
- ``registration``   Step 2: relative pose by GNC-TLS, confidence (Eq. 7)
- ``temporal``       Step 3: intra-trip temporal consistency (Eq. 8)
- ``inter_trip``     Step 4: inter-trip consistency (maximum clique)
- ``association``    Algorithm 1 as one recipe, and the match-pair record
- ``pose_graph``     incremental pose graph optimisation (Eq. 9-12, gtsam)
- ``fine``           fine alignment with single-frame perception
- ``corrections``    human corrections of the association (rejected / added pairs)
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np

from csr_core.alignment.association import PairMatch, associate
from csr_core.alignment.bias_messages import GnssBiasMessage, bias_message
from csr_core.alignment.corrections import MatchCorrections, PairConstraint, apply_corrections
from csr_core.alignment.fine import dash_ends, detections, frame_points, frame_residuals, refine_frames
from csr_core.alignment.observability import own_gnss_error_m, unobservable_reason
from csr_core.alignment.params import DEFAULT, AlignmentParams, noise_scales
from csr_core.alignment.pose_graph import frame_poses_from_submaps, optimize_submap_poses
from csr_core.alignment.submaps import Submap, prior_patches, reduce_prior_map, split_submaps, submap_pairs
from csr_core.errors import AlignmentFailed
from csr_core.types import MapFeature, TripReconstruction

log = logging.getLogger(__name__)

__all__ = [
    "AlignmentParams",
    "DEFAULT",
    "AlignmentResult",
    "GnssBiasMessage",
    "MatchCorrections",
    "MatchPairRecord",
    "PairConstraint",
    "PriorMap",
    "align_trips",
    "bias_message",
]


@dataclass(frozen=True, slots=True)
class PriorMap:
    """A pre-built road structure (world frame) and how firmly it holds (its weight)."""

    features: tuple[MapFeature, ...]
    sigma_xy_m: float = 0.10
    sigma_yaw_rad: float = 0.005


@dataclass(frozen=True, slots=True)
class MatchPairRecord:
    """One accepted sub-map matching pair, for validation and human correction.

    ``trip_key_i == "<prior>"`` for a pair with the pre-built map (P_sub-pre).
    ``relative_pose_xyyaw`` is ``T_reg^{i,j}`` (sub-map j in sub-map i's frame);
    ``instance_matches`` pairs trip instance indices (prior: map feature indices).
    """

    submap_i: int
    submap_j: int
    trip_key_i: str
    trip_key_j: str
    frames_i: tuple[int, int]
    frames_j: tuple[int, int]
    centre_xy_world: tuple[float, float]
    relative_pose_xyyaw: tuple[float, float, float]
    confidence: float
    residual_rms_m: float
    instance_matches: tuple[tuple[int, int], ...]
    match_confidences: tuple[float, ...]
    pose_graph_inlier: bool
    human: bool = False  # added by a human correction


@dataclass(frozen=True, slots=True)
class AlignmentResult:
    """``poses_xyyaw_world``: final world_T_vehicle of every frame of every aligned trip;
    failed trips are absent there and present in ``failed`` with a reason."""

    poses_xyyaw_world: dict[str, np.ndarray]
    failed: dict[str, str]
    match_pairs: tuple[MatchPairRecord, ...]
    frame_residuals_m: dict[str, np.ndarray]
    diagnostics: dict = field(default_factory=dict)


def align_trips(
    trips: Sequence[TripReconstruction],
    prior_map: PriorMap | None = None,
    params: AlignmentParams = DEFAULT,
    corrections: MatchCorrections | None = None,
    inspect_matches: Callable[[list[PairMatch], list[Submap]], list[PairMatch]] | None = None,
    bias_messages: Mapping[str, Sequence[GnssBiasMessage]] | None = None,
) -> AlignmentResult:
    """Coarse-to-fine multi-trip alignment (Fig. 3), against ``prior_map`` when given, with the
    map team's ``corrections`` of the sub-map association when given, and with what other
    alignments (a neighbouring tile's) learnt of the trips' GNSS biases when given
    (``bias_messages`` by trip key, :mod:`csr_core.alignment.bias_messages`).

    ``inspect_matches`` (diagnostics, ``evaluate_floor``): called with the accepted matches and
    the sub-maps before the pose graph; what it returns goes to the pose graph instead."""
    if not trips:
        raise AlignmentFailed("no trips to align", reason="empty")
    if prior_map is not None:
        params = replace(
            params, prior_map_sigma_xy_m=prior_map.sigma_xy_m, prior_map_sigma_yaw_rad=prior_map.sigma_yaw_rad
        )
        # 0. the part of the pre-built map these trips can touch, duplicates removed
        prior_map = replace(prior_map, features=reduce_prior_map(prior_map.features, trips, params))
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    noise = noise_scales(trips, params)
    poses = {t.trip.key: t.poses_xyyaw_world.copy() for t in trips}
    # dash-end sightings (along-road landmarks of the coarse and the fine stage), read once
    dets = [detections(t) for t in trips]
    dashes = (
        [dash_ends(t, dets=d) for t, d in zip(trips, dets, strict=True)]
        if (params.landmarks and params.coarse) or params.fine_dashes
        else None
    )
    submaps: list[Submap] = []
    matches: list[PairMatch] = []
    pairs: list[tuple[int, int]] = []
    inlier = np.zeros(0, bool)
    trace: dict = {"eq3_passed": np.zeros(0, bool)}
    prior_shifts: list[float] = []
    own_error: dict = {}
    scale_correction: dict[str, float] = {}
    if params.coarse:
        # 1. sub-map splitting, and matching pairs with other trips and the pre-built map (Fig. 4)
        circles, submaps = split_submaps(trips, params, dashes)
        if prior_map is not None:
            submaps += prior_patches(circles, prior_map.features, params, first_id=len(submaps))
        pairs = submap_pairs(submaps, params)
        timings["split_s"] = time.perf_counter() - clock
        # 2. sub-map data association: topology, graph matching + GNC, temporal, inter-trip (Alg. 1)
        matches = associate(submaps, circles, pairs, trips, noise, params, trace)
        if corrections:  # the map team's rejected and added pairs (human correction)
            matches = apply_corrections(matches, submaps, circles, noise, params, corrections)
        timings["associate_s"] = time.perf_counter() - clock - sum(timings.values())
        # 3. incremental pose graph optimisation with adaptive weights (Eq. 9-12)
        if inspect_matches is not None:
            matches = inspect_matches(matches, submaps)
        graph = optimize_submap_poses(trips, submaps, matches, params, bias_messages=bias_messages)
        inlier = graph.registration_inlier
        prior_shifts = [
            float(np.linalg.norm(graph.poses_xyyaw[s.submap_id][:2] - s.world_T_submap[:2]))
            for s in submaps
            if s.is_prior
        ]
        scale_correction = {trips[k].trip.key: v for k, v in graph.odom_scale_correction.items()}
        own_error = own_gnss_error_m(trips, submaps, graph.own_gnss_gain, {s for p in pairs for s in p})
        # 4. sub-map poses -> pose of every frame
        for k, t in enumerate(trips):
            poses[t.trip.key] = frame_poses_from_submaps(
                t, [s for s in submaps if s.trip_index == k], graph.poses_xyyaw
            )
        timings["pose_graph_s"] = time.perf_counter() - clock - sum(timings.values())
    fps = [frame_points(t, d) for t, d in zip(trips, dets, strict=True)]
    if params.fine:
        # 5. fine alignment: the same flow with single-frame perception as the primitive
        poses = refine_frames(
            trips, fps, poses, prior_map.features if prior_map else (), noise, params, dashes
        )
        timings["fine_s"] = time.perf_counter() - clock - sum(timings.values())
    # 6. per-frame residuals, failed trips, and the match pairs kept for validation
    residuals = frame_residuals(trips, fps, poses, prior_map.features if prior_map else (), noise, params)
    failed = (
        _failed_trips(trips, submaps, pairs, matches, inlier, prior_map is not None) if params.coarse else {}
    )
    for k, err in own_error.items():  # held by nothing but its own GNSS: not an alignment
        if (
            params.mark_unobservable
            and err.rms_m > params.max_own_gnss_error_m
            and trips[k].trip.key not in failed
        ):
            failed[trips[k].trip.key] = unobservable_reason(err, params.max_own_gnss_error_m)
    records = tuple(_record(m, submaps, trips, bool(ok)) for m, ok in zip(matches, inlier, strict=False))
    timings["total_s"] = time.perf_counter() - clock
    return AlignmentResult(
        {k: v for k, v in poses.items() if k not in failed},
        failed,
        records,
        residuals,
        {
            "timings": timings,
            "n_submaps": len(submaps),
            "n_candidate_pairs": len(pairs),
            "candidate_pairs": pairs,
            "eq3_passed": trace["eq3_passed"],
            "n_matches": len(matches),
            "n_pose_graph_inliers": int(inlier.sum()),
            "prior_patch_shifts_m": prior_shifts,
            "odom_scale_correction": scale_correction,
            "own_gnss_error_m": {trips[k].trip.key: e for k, e in own_error.items()},
            "unaligned_poses": {k: poses[k] for k in failed},
        },
    )


def _failed_trips(trips, submaps, pairs, matches, inlier, has_prior) -> dict[str, str]:
    """A trip with partners that no consistent registration ties to them is not aligned."""
    if len(trips) < 2 and not has_prior:
        return {}
    in_pair = {s for p in pairs for s in p}
    registered = {s for m, ok in zip(matches, inlier, strict=False) if ok for s in (m.i, m.j)}
    failed = {}
    for k, t in enumerate(trips):
        mine = [s.submap_id for s in submaps if s.trip_index == k]
        overlapping = [s for s in mine if s in in_pair]
        if not overlapping:
            failed[t.trip.key] = "no_overlap: no other trip or map area shares this trip's road"
        elif not any(s in registered for s in overlapping):
            failed[t.trip.key] = (
                f"no_consistent_match: none of {len(overlapping)} overlapping sub-maps "
                "passed topology, matching and consistency checks"
            )
    return failed


def _record(
    m: PairMatch, submaps: Sequence[Submap], trips: Sequence[TripReconstruction], ok: bool
) -> MatchPairRecord:
    si, sj = submaps[m.i], submaps[m.j]
    key = lambda s: "<prior>" if s.is_prior else trips[s.trip_index].trip.key  # noqa: E731
    rel = m.relative_pose(si.world_T_submap, sj.world_T_submap)
    return MatchPairRecord(
        m.i,
        m.j,
        key(si),
        key(sj),
        (si.first_frame, si.last_frame),
        (sj.first_frame, sj.last_frame),
        (float(m.centre_xy_world[0]), float(m.centre_xy_world[1])),
        cast(tuple[float, float, float], tuple(float(v) for v in rel)),
        m.confidence,
        m.residual_rms_m,
        m.instance_matches,
        tuple(float(c) for c in m.match_confidences),
        ok,
        m.human,
    )
