"""Single-trip reconstruction (paper section III-C): one uploaded trip, on its own, becomes a
smooth trajectory and a clean set of trip-level road elements with noise estimates.

    reconstruct_trip(trip, frame) -> TripReconstruction

The recipe, one module per step: smooth the poses (Eq. 2, ``pose_graph``), pick keyframes
(``keyframes``), track the elements across frames (``tracking``), splice each track into one
instance and drop ghosts and false positives (``splicing``), estimate each type's noise from
the residuals (``noise``). Everything is recomputed from the raw upload alone.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections import Counter
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from csr_core.geo import LocalFrame
from csr_core.single_trip.compiled import checks, observations, search
from csr_core.single_trip.dash_chaining import chain_dash_tracks
from csr_core.single_trip.gnss_bias import (
    TRIP_BIAS_LENGTH_KEY,
    TRIP_BIAS_SIGMA_KEY,
    bias_correlation_length_m,
    trip_bias_sigma_m,
)
from csr_core.single_trip.integrity import TripQuality, TripVerdict, smooth_poses_checked
from csr_core.single_trip.keyframes import select_keyframes, select_tracking_frames
from csr_core.single_trip.noise import estimate_noise, robust_sigma
from csr_core.single_trip.paint_breaks import (
    ObservedPoints,
    barrier_geometry,
    cut_at_paint_breaks,
    cut_unseen,
)
from csr_core.single_trip.params import DEFAULT, SingleTripParams
from csr_core.single_trip.pose_graph import SmoothedPoses
from csr_core.single_trip.splicing import (
    SplicedLine,
    resample_polyline,
    runs_along_observations,
    splice_line,
    splice_polygon,
    unique_ids,
)
from csr_core.single_trip.tracking import TYPE_CODES, regroup_observations, track_elements
from csr_core.types import DividerStyle, ElementNoise, ElementType, TripInstance, TripReconstruction

log = logging.getLogger(__name__)
# types with no dash gaps: an unseen stretch of one is not part of it (paint_breaks.cut_unseen)
_CONTINUOUS = frozenset({ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE})

__all__ = ["DEFAULT", "SingleTripParams", "TripQuality", "TripVerdict", "bev_range_m", "reconstruct_trip"]


#: the stages whose CPU seconds ``reconstruct_trip`` reports (``diagnostics["cpu_seconds"]``):
#: pose smoothing (Eq. 2), keyframes and tracking (with dash chaining), splicing with its ghost
#: and false-positive tests, the unseen cut, the noise estimate with the mixture test
STAGES = ("poses", "tracking", "splicing", "unseen_cut", "noise")


def bev_range_m(trip, quantile: float = 0.002) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the perception range in the vehicle frame: from
    ``sensor_setup.bev_range_m`` when the vehicle states it, else from the detections."""
    rng: Any = trip.sensor_setup.get("bev_range_m") if isinstance(trip.sensor_setup, dict) else None
    try:
        (x0, x1), (y0, y1) = rng["x"], rng["y"]
        return float(x0), float(x1), float(y0), float(y1)
    except (TypeError, KeyError, ValueError):
        pass
    pts = [e.points_xy_vehicle for frame in trip.elements for e in frame]
    if not pts:
        return (-15.0, 30.0, -15.0, 15.0)
    allp = np.concatenate(pts)
    lo = np.quantile(allp, quantile, axis=0)
    hi = np.quantile(allp, 1.0 - quantile, axis=0)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _inside(points_v: np.ndarray, box: tuple[float, float, float, float], margin: float) -> np.ndarray:
    x0, x1, y0, y1 = box
    return (
        (points_v[..., 0] >= x0 + margin)
        & (points_v[..., 0] <= x1 - margin)
        & (points_v[..., 1] >= y0 + margin)
        & (points_v[..., 1] <= y1 - margin)
    )


def _visibility_ratio(
    points_w: np.ndarray,
    seen_frames: np.ndarray,
    frames: np.ndarray,
    poses: np.ndarray,
    box: tuple[float, float, float, float],
    margin: float,
    same_type_tree: cKDTree | None,
    same_type_frame: np.ndarray,
    corroborate_m: float,
    enough: float = 1.0,
) -> float:
    """Tracked frames that saw the element / tracked frames that had it inside the BEV range
    (shrunk by ``margin``), over the frames whose vehicle is within reach of it.

    A frame whose own detections of the element's type (``same_type_tree`` a KD-tree of their
    resampled points, ``same_type_frame (P,)`` their tracked-frame index) pass within
    ``corroborate_m`` of it also saw it, even when they went to another track: a road driven
    twice (out and back, a loop) or an element whose track broke in two is then not taken for a
    ghost.

    Returns early with a lower bound (seen / all frames near it) once that reaches ``enough``."""
    samples = resample_polyline(points_w, 2.0) if len(points_w) > 1 else points_w
    reach = max(abs(box[0]), abs(box[1]), abs(box[2]), abs(box[3]))
    # frames farther than the box's corner from every sample cannot have it in range
    corner = float(np.hypot(max(abs(box[0]), abs(box[1])), max(abs(box[2]), abs(box[3]))))
    cand = checks.frames_near(np.ascontiguousarray(samples, dtype=float), poses, frames, reach, corner)
    if len(cand) == 0:
        return 1.0
    seen_mask = np.zeros(len(frames), dtype=bool)
    seen_mask[seen_frames] = True
    was_seen = seen_mask[cand]
    n_seen = int(was_seen.sum())
    if n_seen >= enough * len(cand):
        return n_seen / len(cand)
    rest = cand[~was_seen]  # only the frames that did not see it are tested
    x0, x1, y0, y1 = box
    in_range = checks.frames_in_range(
        np.ascontiguousarray(samples, dtype=float),
        poses[frames[rest]],
        np.array([x0 + margin, x1 - margin, y0 + margin, y1 - margin]),
    )
    rest = rest[in_range]
    n_corroborated = 0
    if len(rest) and same_type_tree is not None:
        dense = resample_polyline(points_w, corroborate_m / 2) if len(points_w) > 1 else points_w
        near = cKDTree(dense).query_ball_tree(same_type_tree, corroborate_m)
        hit = np.fromiter(itertools.chain.from_iterable(near), dtype=np.int64)
        if len(hit):
            corroborating = np.zeros(len(frames), dtype=bool)
            corroborating[same_type_frame[hit]] = True
            n_corroborated = int(corroborating[rest].sum())
    return float(n_seen + n_corroborated) / max(n_seen + len(rest), 1)


def _within_reach(
    points_w: np.ndarray, path: search.SortedPoints, reach_m: float, is_polygon: bool
) -> list[np.ndarray]:
    """The parts of an instance within ``reach_m`` of the vehicle path: a trip covers the lateral
    reach of its BEV range around its path. Beyond it an element was only seen far ahead
    (at the far end of the range, where the detector is noisiest) in the few frames before the
    vehicle turned away; the trips that drive past it see it better. Lines are cut into their
    runs inside the reach; a polygon is kept whole when its centroid is inside."""
    if is_polygon:
        return [points_w] if path.within(points_w.mean(0)[None], reach_m)[0] else []
    inside = path.within(points_w, reach_m)
    if inside.all():
        return [points_w]
    edges = np.flatnonzero(np.diff(np.concatenate(([0], inside.astype(np.int8), [0]))))
    return [points_w[a:b] for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= 2]


def _resplice_mixture(
    obs: np.ndarray,
    obs_points_w: np.ndarray,
    obs_frame: np.ndarray,
    pts_w: np.ndarray,
    obs_id: np.ndarray,
    offsets: np.ndarray,
    end_free: np.ndarray,
    original: np.ndarray,
    params: SingleTripParams,
) -> list[SplicedLine]:
    """The observations ``obs`` of a splice that mixes elements, regrouped by
    ``regroup_observations`` and spliced group by group on their own shapes (observation
    indices kept)."""
    labels = regroup_observations(
        obs_points_w[obs],
        obs_frame[obs],
        params.SPLICE_MODE_GATE_M,
        params.TRACK_MAX_ANGLE_RAD,
        params.TRACK_MAX_SKIP_FRAMES,
        params.TRACK_MAX_EXTRAPOLATION_M,
    )
    out = []
    for lab in np.unique(labels):
        group = obs[labels == lab]
        if len(np.unique(obs_frame[group])) < params.TRACK_MIN_FRAMES:
            continue
        in_group = np.zeros(len(offsets) - 1, dtype=bool)
        in_group[group] = True
        take = in_group[obs_id]  # np.isin(obs_id, group), without its sort
        counts = np.diff(offsets)[group]
        sub_off = np.concatenate([[0], np.cumsum(counts)])
        sub_ends = np.column_stack([sub_off[:-1], sub_off[1:] - 1])
        # each group on its own shape (junction connectors do not follow the path)
        for part in splice_line(
            pts_w[take],
            np.repeat(np.arange(len(group)), counts),
            sub_ends,
            end_free[group],
            None,
            params,
            original[take],
        ):
            out.append(
                SplicedLine(
                    part.points_xy_world,
                    part.lateral_residuals_m,
                    part.along_residuals_m,
                    group[part.observations],
                )
            )
    return out


def _inside_polygon(point: np.ndarray, outline: np.ndarray) -> bool:
    """Even-odd rule."""
    x, y = outline[:, 0], outline[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    crosses = (y > point[1]) != (yn > point[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x + (point[1] - y) * (xn - x) / (yn - y)
    return bool(np.count_nonzero(crosses & (point[0] < x_at)) % 2)


def _without_duplicate_polygons(candidates: list, whole_ids: dict[int, np.ndarray]) -> list:
    """One instance per polygon: a crosswalk passed twice (out and back, a loop) or seen whole on
    one pass and only clipped by the BEV range on another comes out of two tracks. Of polygons of
    one type whose centroids lie inside each other's outlines, the one fused from whole outlines
    and seen most often is kept (a rectangle fitted to clipped outlines covers only the part seen;
    Karlsruhe s11: two such rectangles were 40 m of false crosswalk outline)."""
    polys = [i for i, c in enumerate(candidates) if c[0].type.is_polygon]
    if len(polys) < 2:
        return candidates

    def rank(i: int) -> tuple[bool, int]:
        inst = candidates[i][0]
        return id(inst.points_xy_world) in whole_ids, inst.n_observations

    centre = np.array([candidates[i][0].points_xy_world.mean(0) for i in polys])
    diagonal = np.array([np.hypot(*np.ptp(candidates[i][0].points_xy_world, axis=0)) for i in polys])
    near = cKDTree(centre).query_pairs(float(diagonal.max()) + 1e-6, output_type="ndarray")
    partners: dict[int, list[int]] = {}
    for (
        u,
        v,
    ) in near.tolist():  # a point inside an outline is within its bounding box's diagonal of its centre
        partners.setdefault(polys[u], []).append(v)
        partners.setdefault(polys[v], []).append(u)
    dropped: set[int] = set()
    for i in sorted(polys, key=rank, reverse=True):
        if i in dropped:
            continue
        a = candidates[i][0]
        ca = centre[polys.index(i)]
        for k in partners.get(i, []):
            j = polys[k]
            b = candidates[j][0]
            if j in dropped or b.type != a.type:
                continue
            cb = centre[k]
            if _inside_polygon(cb, a.points_xy_world) or _inside_polygon(ca, b.points_xy_world):
                log.debug(
                    "dropped %s at %s: duplicate of the one at %s",
                    b.type.value,
                    np.round(cb, 1),
                    np.round(ca, 1),
                )
                dropped.add(j)
    return [c for i, c in enumerate(candidates) if i not in dropped]


def _unseen_gate_m(noise: ElementNoise, params: SingleTripParams) -> float:
    """How near one of its observations a vertex of a road boundary or centreline must lie to have
    been seen: ``UNSEEN_CUT_SIGMAS`` of the type's lateral noise in this trip (floored at
    ``INSTANCE_MIXTURE_MIN_SIGMA_M``, as for a near-noiseless perception) plus half the spacing of
    the observation points, and never more than one splice bin (``PAINT_BREAK_GATE_M``, the gate
    used for every trip alike when UNSEEN_CUT_SIGMAS is 0)."""
    if not params.UNSEEN_CUT_SIGMAS:
        return params.PAINT_BREAK_GATE_M
    sigma_m = max(noise.lateral_sigma_m, params.INSTANCE_MIXTURE_MIN_SIGMA_M)
    return min(params.UNSEEN_CUT_SIGMAS * sigma_m + params.UNSEEN_CUT_STEP_M / 2, params.PAINT_BREAK_GATE_M)


def _cut_where_unseen(candidates: list, params: SingleTripParams) -> tuple[list, int]:
    """Lane dividers cut where an unseen stretch of theirs meets a stop line or crosswalk of the
    trip, road boundaries and centrelines at every unseen stretch (``paint_breaks``; "unseen" for
    these by the noise of their type in the trip, :func:`_unseen_gate_m`); parts shorter than the
    type's minimum length are dropped (counted), the residuals stay with the longest part, and
    every part keeps the track's frames and observation count."""
    barrier = (
        barrier_geometry(
            [c[0].points_xy_world for c in candidates if c[0].type == ElementType.STOP_LINE],
            [c[0].points_xy_world for c in candidates if c[0].type == ElementType.CROSSWALK],
            params.PAINT_BREAK_REACH_M,
        )
        if params.PAINT_BREAKS
        else None
    )
    noise = estimate_noise({t: [c[1] for c in candidates if c[0].type == t] for t in _CONTINUOUS}, {}, params)
    step_m = params.UNSEEN_CUT_STEP_M if params.UNSEEN_CUT_SIGMAS else None  # None: as spliced
    tracks: dict[
        int, ObservedPoints
    ] = {}  # one per track: the instances cut from one track share its observations

    def observed_points(observed: tuple[np.ndarray, np.ndarray], dense_m: float | None) -> ObservedPoints:
        """The track's observed points (world, with their detections' offsets), densified to
        ``dense_m`` when given (a track has one type, so one spacing)."""
        points_w, offsets = observed
        if id(points_w) not in tracks:
            tracks[id(points_w)] = ObservedPoints(points_w, offsets, dense_m)
        return tracks[id(points_w)]

    out, n_dropped = [], 0
    for cand in candidates:
        inst, lat, alo, observed = cand
        if observed is None:
            out.append(cand)
            continue
        if inst.type == ElementType.LANE_DIVIDER and barrier is not None:
            parts = cut_at_paint_breaks(
                inst.points_xy_world, observed_points(observed, None), barrier, params.PAINT_BREAK_GATE_M
            )
        elif inst.type in _CONTINUOUS and params.CONTINUOUS_UNSEEN_CUT:
            parts = cut_unseen(
                inst.points_xy_world,
                observed_points(observed, step_m),
                _unseen_gate_m(noise[inst.type], params),
            )
        else:
            parts = [inst.points_xy_world]
        if len(parts) == 1 and len(parts[0]) == len(inst.points_xy_world):
            out.append(cand)
            continue
        log.debug(
            "%s from %s: cut where it was not seen, %d parts",
            inst.type.value,
            np.round(inst.points_xy_world[0], 1),
            len(parts),
        )
        kept = 0
        for points_w in sorted(parts, key=len, reverse=True):
            if float(np.linalg.norm(np.diff(points_w, axis=0), axis=1).sum()) < params.min_length_m(
                inst.type
            ):
                continue
            out.append(
                (
                    replace(inst, points_xy_world=points_w),
                    lat if not kept else lat[:0],
                    alo if not kept else alo[:0],
                    observed,
                )
            )
            kept += 1
        n_dropped += len(parts) - kept if parts else 1
    return out, n_dropped


def _style(styles: list) -> DividerStyle | None:
    votes = Counter(s for s in styles if s is not None and s != DividerStyle.UNKNOWN)
    if votes:
        return votes.most_common(1)[0][0]
    return DividerStyle.UNKNOWN if any(s is not None for s in styles) else None


def reconstruct_trip(
    trip, frame: LocalFrame, params: SingleTripParams = DEFAULT, smoothed: SmoothedPoses | None = None
) -> TripReconstruction:
    """Single-trip reconstruction of ``trip`` in the world frame ``frame`` (paper III-C).

    ``smoothed`` replaces the pose smoothing of step 2 with given poses (for evaluating the
    element stages in isolation, e.g. on true poses); normally it is computed here.

    Returns smoothed world_T_vehicle poses of every frame (Eq. 2) with marginal sigmas,
    keyframes, trip-level instances and per-type noise (lateral/along sigma, metres).
    Raises ``ReconstructionError`` when the trip has no usable GNSS fix.
    """
    t_start = time.perf_counter()
    cpu = [time.process_time()]  # CPU seconds at each stage's end (STAGES)
    # 1. GNSS into the local plane (status none rows carry no fix)
    gnss_xy = frame.to_local(trip.gnss_lonlat_deg)
    # 2. pose smoothing, Eq. 2, tested against the trip's own GNSS (repaired or marked degraded)
    quality: TripQuality | None = None
    if smoothed is None:
        smoothed, quality = smooth_poses_checked(
            trip.timestamps_s,
            gnss_xy,
            trip.fix_status,
            trip.gnss_std_m,
            frame.grid_heading_deg(trip.gnss_heading_deg, trip.gnss_lonlat_deg),
            trip.odom_xyyaw,
            params,
        )
    poses = smoothed.poses_xyyaw_world
    travel = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1))]
    t_pose = time.perf_counter()
    cpu.append(time.process_time())
    # 3. keyframes by distance and time
    keyframes = select_keyframes(
        poses, trip.timestamps_s, params.KEYFRAME_DISTANCE_M, params.KEYFRAME_PERIOD_S
    )
    # 4. element tracking on frames spaced by travel/time
    box = bev_range_m(trip)
    perceived = np.fromiter((len(e) > 0 for e in trip.elements), bool, trip.n_frames)
    frames = select_tracking_frames(
        poses, trip.timestamps_s, params.TRACK_STEP_M, params.TRACK_STEP_S, perceived=perceived
    )
    pieces, tracks = track_elements(frames, poses, travel, trip.elements, params)
    if params.DASH_CHAINING:
        tracks = chain_dash_tracks(pieces, tracks, trip.elements, frames, params)
    t_track = time.perf_counter()
    cpu.append(time.process_time())
    # 5. splicing; short-lived tracks (false positives) and ghosts dropped
    instances: list[TripInstance] = []
    lateral: dict[ElementType, list[np.ndarray]] = {}
    along: dict[ElementType, list[np.ndarray]] = {}
    n_dropped = 0
    # (instance, lateral residuals, along residuals, its track's observed points and their
    # detections' offsets, or None for a polygon)
    candidates: list[tuple[TripInstance, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]] = []
    whole_polygons: dict[
        int, np.ndarray
    ] = {}  # polygon outlines fused from whole (unclipped) outlines, by id (kept alive)
    edge_margin = params.BEV_RANGE_MARGIN_M / 2
    reach = max(abs(v) for v in box)
    lateral_reach = min(max(abs(box[2]), abs(box[3])), params.INSTANCE_MAX_LATERAL_M)
    path = search.SortedPoints(
        resample_polyline(poses[:, :2], params.SPLICE_BIN_M) if len(poses) > 1 else poses[:, :2]
    )
    k_pts = pieces.points_w.shape[1]
    type_points = {}  # per type: KD-tree of all its detections' resampled points, their tracked frame
    for t, code in TYPE_CODES.items():
        of_type = pieces.type_code == code
        pts = pieces.points_w[of_type].reshape(-1, 2)
        type_points[t] = (cKDTree(pts) if len(pts) else None, np.repeat(pieces.frame[of_type], k_pts))
    for track in tracks:
        track_frames = pieces.frame[track.pieces]
        cut_short = len(track.frames) < params.TRACK_MIN_FRAMES
        at_trip_end = track_frames.min() == 0 or track_frames.max() == len(frames) - 1
        if cut_short and not (at_trip_end and len(track.frames) >= params.TRACK_MIN_FRAMES_AT_TRIP_END):
            n_dropped += 1
            continue
        # a track cut short by the trip's start or end: its splice needs no more frames than it has,
        # and it must have been seen in every tracked frame that had it in range (a false positive is not)
        track_params = replace(params, TRACK_MIN_FRAMES=len(track.frames)) if cut_short else params
        min_visibility = 1.0 if cut_short else params.TRACK_MIN_VISIBILITY_RATIO
        upload_frames = frames[track_frames]
        yaw = poses[upload_frames, 2]
        # the detections as sent, densified (not polygons: their vertices are corners), in the world
        pts_v, offsets, original, pts_w, obs_id = observations.track_observations(
            pieces.raw_points_v,
            pieces.raw_offsets,
            track.pieces,
            np.cos(yaw),
            np.sin(yaw),
            poses[upload_frames, 0],
            poses[upload_frames, 1],
            0.0 if track.type.is_polygon else float(params.SPLICE_BIN_M),
        )
        spliced: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        observed = None if track.type.is_polygon else (pts_w, offsets)  # for _cut_where_unseen
        if track.type.is_polygon:
            inside = _inside(pts_v, box, edge_margin)
            whole = np.logical_and.reduceat(inside, offsets[:-1])
            obs_w = np.split(pts_w, offsets[1:-1])
            outline, lat, alo = splice_polygon(
                obs_w,
                whole,
                poses[upload_frames, 2],
                np.split(inside, offsets[1:-1]) if params.POLYGON_EDGE_AXES else None,
            )
            spliced.append((outline, lat, alo, track.frames))
            if whole.any():
                whole_polygons[id(outline)] = outline
        else:
            obs_ends = np.column_stack([offsets[:-1], offsets[1:] - 1])
            end_free = _inside(pts_v[obs_ends], box, edge_margin)
            # the vehicle path while the element was in reach guides the splice
            t0 = np.searchsorted(travel, travel[upload_frames.min()] - reach)
            t1 = np.searchsorted(travel, travel[upload_frames.max()] + reach)
            guide = poses[t0 : t1 + 1, :2]
            mixed_above = params.INSTANCE_MAX_SIGMA_RATIO * params.NOISE_PRIOR_LATERAL_M
            for piece in splice_line(
                pts_w,
                obs_id,
                obs_ends,
                end_free,
                guide,
                track_params,
                original,
                follow_bends=track.type == ElementType.LANE_DIVIDER,
            ):
                lat = piece.lateral_residuals_m
                parts = [piece]
                resplit = False
                if len(lat) >= params.NOISE_MIN_SAMPLES and robust_sigma(lat) > mixed_above:
                    # a mixture of elements (a junction): split its observations apart, splice each
                    parts = _resplice_mixture(
                        piece.observations,
                        pieces.points_w[track.pieces],
                        track_frames,
                        pts_w,
                        obs_id,
                        offsets,
                        end_free,
                        original,
                        track_params,
                    )
                    resplit = True
                queue = list(parts)
                while queue:
                    part = queue.pop(0)
                    kept = runs_along_observations(
                        part.points_xy_world,
                        pts_w,
                        obs_id,
                        part.observations,
                        params.TRACK_MAX_ANGLE_RAD,
                        params.TRACK_GATE_M,
                        params.SPLICE_ACROSS_WINDOW_M,
                    )
                    if not kept and not resplit and params.SPLICE_REGROUP_ACROSS:
                        # no part of it runs along its observations: it joined elements that meet at
                        # an angle (a kerb's two legs at an island's corner); regroup and splice each
                        log.debug(
                            "%s from %s: runs across its observations everywhere, regrouped",
                            track.type.value,
                            np.round(part.points_xy_world[0], 1),
                        )
                        queue = _resplice_mixture(
                            part.observations,
                            pieces.points_w[track.pieces],
                            track_frames,
                            pts_w,
                            obs_id,
                            offsets,
                            end_free,
                            original,
                            track_params,
                        )
                        resplit = True
                        n_dropped += not queue
                        continue
                    if len(kept) != 1 or len(kept[0]) != len(part.points_xy_world):
                        log.debug(
                            "%s from %s: cut where it runs across its observations, %d parts left",
                            track.type.value,
                            np.round(part.points_xy_world[0], 1),
                            len(kept),
                        )
                        n_dropped += not kept
                    # residuals stay with the longest part (as for the parts within reach, below)
                    for k, kept_xy in enumerate(sorted(kept, key=len, reverse=True)):
                        spliced.append(
                            (
                                kept_xy,
                                part.lateral_residuals_m if k == 0 else part.lateral_residuals_m[:0],
                                part.along_residuals_m if k == 0 else part.along_residuals_m[:0],
                                unique_ids(track_frames[part.observations]),
                            )
                        )
        spliced = [
            (part, lat if k == 0 else lat[:0], alo if k == 0 else alo[:0], seen)
            for points_w, lat, alo, seen in spliced
            for k, part in enumerate(
                sorted(
                    _within_reach(points_w, path, lateral_reach, track.type.is_polygon), key=len, reverse=True
                )
            )
        ]
        style: list[DividerStyle | None] | None = None  # the track's, voted once
        for points_w, lat, alo, seen in spliced:
            step = points_w[1:] - points_w[:-1]
            length = float(
                np.sqrt(step[:, 0] * step[:, 0] + step[:, 1] * step[:, 1]).sum()
            )  # as np.linalg.norm
            if len(seen) < track_params.TRACK_MIN_FRAMES or (
                not track.type.is_polygon and length < params.min_length_m(track.type)
            ):
                log.debug(
                    "dropped %s (%.0f m from %s): %d frames",
                    track.type.value,
                    length,
                    np.round(points_w[0], 1),
                    len(seen),
                )
                n_dropped += 1
                continue
            ratio = _visibility_ratio(
                points_w,
                seen,
                frames,
                poses,
                box,
                params.BEV_RANGE_MARGIN_M,
                *type_points[track.type],
                params.TRACK_GATE_M,
                enough=min_visibility,
            )
            if ratio < min_visibility:
                log.debug(
                    "dropped %s (%.0f m from %s): visibility %.2f",
                    track.type.value,
                    length,
                    np.round(points_w[0], 1),
                    ratio,
                )
                n_dropped += 1
                continue
            if style is None:
                style = [
                    _style(
                        [
                            trip.elements[f][j].style  # (plain ints index the tuples faster)
                            for f, j in zip(
                                upload_frames.tolist(), pieces.element[track.pieces].tolist(), strict=True
                            )
                        ]
                    )
                ]
            candidates.append(
                (
                    TripInstance(
                        type=track.type,
                        points_xy_world=points_w,
                        style=style[0],
                        n_observations=len(seen),
                        first_frame=int(frames[seen[0]]),
                        last_frame=int(frames[seen[-1]]),
                    ),
                    lat,
                    alo,
                    observed,
                )
            )
    candidates = _without_duplicate_polygons(candidates, whole_polygons)
    cpu.append(time.process_time())
    if params.PAINT_BREAKS or params.CONTINUOUS_UNSEEN_CUT:
        candidates, n_cut = _cut_where_unseen(candidates, params)
        n_dropped += n_cut
    cpu.append(time.process_time())
    # 6. noise per element type from the residuals; a line whose own residuals are far wider
    # than its type's (a mixture of elements: connectors crossing in a junction) is dropped.
    # Not a polygon: its vertex residuals include vertices sliding along a side (a crosswalk's
    # intermediate vertices), so a whole, well-seen crosswalk looked like a mixture.
    noise = estimate_noise(
        {t: [c[1] for c in candidates if c[0].type == t] for t in ElementType},
        {t: [c[2] for c in candidates if c[0].type == t] for t in ElementType},
        params,
    )
    for inst, lat, alo, _ in candidates:
        ref = noise[inst.type]
        if (
            not inst.type.is_polygon
            and len(lat) >= params.NOISE_MIN_SAMPLES
            and ref.n_samples >= params.NOISE_MIN_SAMPLES
            and robust_sigma(lat)
            > max(params.INSTANCE_MAX_SIGMA_RATIO * ref.lateral_sigma_m, params.INSTANCE_MIXTURE_MIN_SIGMA_M)
        ):
            log.debug(
                "dropped %s from %s: lateral sigma %.2f m vs type %.2f m",
                inst.type.value,
                np.round(inst.points_xy_world[0], 1),
                robust_sigma(lat),
                ref.lateral_sigma_m,
            )
            n_dropped += 1
            continue
        lateral.setdefault(inst.type, []).append(lat)
        along.setdefault(inst.type, []).append(alo)
        instances.append(inst)
    noise = estimate_noise(lateral, along, params)
    t_end = time.perf_counter()
    cpu.append(time.process_time())
    log.info(
        "trip %s: %d frames, %d tracks, %d instances (%d dropped); %.3f s (poses %.3f, tracking %.3f)",
        trip.key,
        trip.n_frames,
        len(tracks),
        len(instances),
        n_dropped,
        t_end - t_start,
        t_pose - t_start,
        t_track - t_pose,
    )
    diagnostics = {
        "odom_scale": smoothed.odom_scale,
        "odom_yaw_rate_bias_deg_s": float(np.degrees(smoothed.odom_yaw_rate_bias_rad_s)),
        "gnss_latency_s": smoothed.gnss_latency_s,
        TRIP_BIAS_SIGMA_KEY: trip_bias_sigma_m(trip.fix_status, trip.gnss_std_m, params),
        TRIP_BIAS_LENGTH_KEY: bias_correlation_length_m(trip.timestamps_s, poses[:, :2], params),
        "gnss_rejected_share": float(1.0 - smoothed.gnss_inlier[trip.has_fix].mean())
        if trip.has_fix.any()
        else 0.0,
        "tracked_frames": int(len(frames)),
        "tracks": len(tracks),
        "dropped": n_dropped,
        "seconds": {"poses": t_pose - t_start, "tracking": t_track - t_pose, "total": t_end - t_start},
        "cpu_seconds": dict(zip(STAGES, np.diff(cpu).tolist(), strict=True)),
    }
    if quality is not None:
        diagnostics["quality"] = quality.as_dict()
    return TripReconstruction(
        trip=trip,
        poses_xyyaw_world=poses,
        pose_sigma_xy_m=smoothed.sigma_xy_m,
        keyframe_indices=keyframes,
        instances=tuple(instances),
        noise=noise,
        gnss_inlier=smoothed.gnss_inlier,
        diagnostics=diagnostics,
        white_poses_xyyaw_world=smoothed.white_poses_xyyaw_world,
    )
