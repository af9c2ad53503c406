"""The pieces the recipes of ``generate_topology`` and ``update_topology`` share: the result
type, members, fusion of one type with re-association of detached members, features and their
properties, ids, and the final lane graph + validation pass."""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

from csr_core.se2 import compose, inverse
from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.association import Member, associate_lines, associate_polygons
from csr_core.topology.derived_centerlines import derive_centerlines, is_derived
from csr_core.topology.fusion import (
    FusedInstance,
    absorb_pieces,
    fuse_group,
    fuse_lines,
    fuse_polygons,
    merge_twins,
)
from csr_core.topology.lane_graph import LaneGraph, build_lane_graph
from csr_core.topology.params import TopologyParams
from csr_core.topology.unseen_tails import trim_unseen_tails
from csr_core.topology.validation import (
    TileQuality,
    ValidationFlag,
    coverage_counts,
    passing_counts,
    seen_too_rarely,
    validate,
)
from csr_core.types import ElementNoise, ElementType, MapFeature, TripInstance


@dataclass(frozen=True, slots=True)
class TopologyResult:
    """The fused map and its checks.

    ``suppressed``: lines held back from the map (few of the trips that drove alongside them saw
    them: ghosts); they keep their ids and flags and are published once more trips confirm them.
    ``members`` (feature id -> the trip instances supporting it), ``trip_points`` (each trip's
    element points, for coverage) and ``trip_paths`` (each trip's driven path, for the trips that
    passed a line) are the state ``update_topology`` continues from.
    """

    features: tuple[MapFeature, ...]
    lane_graph: LaneGraph
    flags: tuple[ValidationFlag, ...]
    tile_quality: dict[tuple[int, int], TileQuality]
    members: dict[str, tuple[Member, ...]] = field(default_factory=dict)
    trip_points: dict[str, np.ndarray] = field(default_factory=dict)
    trip_times: dict[str, object] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    suppressed: tuple[MapFeature, ...] = ()
    rejected_members: tuple[Member, ...] = ()  # trip instances left out of fusion (zig-zag lines)
    trip_paths: dict[str, np.ndarray] = field(default_factory=dict)  # (P, 4) x, y, unit direction

    def flags_of(self, feature_id: str) -> list[ValidationFlag]:
        return [f for f in self.flags if f.feature_id == feature_id]


def _total_turning_rad(points_xy: np.ndarray, smoothing_m: float) -> float:
    """Total absolute heading change of a 1 m resampled line after Gaussian smoothing of its
    points with sigma ``smoothing_m`` (metres = samples) along it."""
    smooth = gaussian_filter1d(points_xy, smoothing_m, axis=0, mode="nearest")
    d = np.diff(smooth, axis=0)
    return float(np.abs(np.diff(np.unwrap(np.arctan2(d[:, 1], d[:, 0])))).sum())


def is_zigzag(points_xy: np.ndarray, params: TopologyParams) -> bool:
    """A line that oscillates sideways (a splice that hopped between neighbouring elements, a
    wobbling centreline): over at least ``ZIGZAG_MIN_LENGTH_M``, more than
    ``ZIGZAG_TURN_RAD_PER_M`` of turning per metre that smoothing over ``ZIGZAG_SMOOTHING_M``
    removes (total turning at 1 m minus at that scale). A corner, a bend or a roundabout keeps its
    turning at both scales; noise of a few centimetres adds well under 0.01 rad/m."""
    p = resample_polyline(np.asarray(points_xy, float), 1.0)
    length = float(len(p) - 1)
    if length < params.ZIGZAG_MIN_LENGTH_M:
        return False
    excess = _total_turning_rad(p, 1.0) - _total_turning_rad(p, params.ZIGZAG_SMOOTHING_M)
    return excess / length > params.ZIGZAG_TURN_RAD_PER_M


def make_members(
    instances_per_trip: Mapping[str, Sequence[TripInstance]],
    noise_per_trip: Mapping[str, Mapping[ElementType, ElementNoise]],
    params: TopologyParams,
) -> tuple[dict[ElementType, list[Member]], list[Member]]:
    """Members per type, and the rejected ones (zig-zag lines, left out of fusion)."""
    out: dict[ElementType, list[Member]] = {t: [] for t in ElementType}
    rejected: list[Member] = []
    for key, instances in instances_per_trip.items():
        noise = noise_per_trip.get(key, {})
        for k, inst in enumerate(instances):
            if len(inst.points_xy_world) < (3 if inst.type.is_polygon else 2):
                continue
            m = Member(key, k, inst, params.trip_sigma_m(noise.get(inst.type)))
            if not inst.type.is_polygon and is_zigzag(inst.points_xy_world, params):
                rejected.append(m)
            else:
                out[inst.type].append(m)
    return out, rejected


def fuse_type(
    members: Sequence[Member], element_type: ElementType, params: TopologyParams
) -> list[tuple[FusedInstance, tuple[Member, ...]]]:
    """Associate and fuse all members of one type. In each round a group gives a line for each
    of its regions (``fusion.fuse_group``: a group chained through junctions holds many); what
    a line does not support (the other side of a corner a chain of boundaries went round, the
    other branch of a split) is peeled off and, unless it lies along a line fused in the same
    round (``fusion.absorb_pieces``), associated and fused again with the members that waited,
    round after round, until nothing is left (after ``MAX_FUSION_ROUNDS`` the rest stand
    alone). Lines of a later round that are an earlier line again join it
    (``fusion.merge_twins``)."""
    out: list[tuple[FusedInstance, tuple[Member, ...]]] = []
    pending = list(members)
    for round_ in range(params.MAX_FUSION_ROUNDS + 1):
        if not pending:
            break
        last = round_ == params.MAX_FUSION_ROUNDS
        if element_type.is_polygon:
            groups = associate_polygons(pending, params)
        else:
            groups = (
                [[k] for k in range(len(pending))] if last else associate_lines(pending, element_type, params)
            )
        detached: list[Member] = []
        done = len(out)
        pieces: list[Member]
        for g in groups:
            gm = [pending[k] for k in g]
            if element_type.is_polygon:
                fused, pieces = [fuse_polygons(gm, element_type, params)], []
            elif last:
                fused, pieces = fuse_lines(gm, element_type, params), []
            else:
                fused, pieces = fuse_group(gm, element_type, params)
            out.extend((f, tuple(gm[k] for k in f.members)) for f in fused)
            detached.extend(pieces)
        if detached:  # pieces that are views of a line fused this round join it
            absorbed, rest = absorb_pieces(detached, [f.points_xy_world for f, _ in out[done:]], params)
            for k, line in absorbed:
                f, mem = out[done + line]
                out[done + line] = (f, (*mem, detached[k]))
            detached = rest
        pending = detached
    if not element_type.is_polygon and element_type not in params.WHOLE_ELEMENT_TYPES:
        out = merge_twins(out, params)
    return out


def _times(members: Sequence[Member], trip_times: Mapping[str, object] | None) -> tuple[object, object, str]:
    keys = sorted({m.trip_key for m in members})
    if trip_times and all(k in trip_times for k in keys):
        ordered = sorted(keys, key=lambda k: (trip_times[k], k))
        return trip_times[ordered[0]], trip_times[ordered[-1]], ordered[0]
    return None, None, keys[0]


def feature_from_fused(
    fused: FusedInstance,
    members: Sequence[Member],
    trip_times: Mapping[str, object] | None,
    feature_id: str = "",
) -> MapFeature:
    first, last, first_trip = _times(members, trip_times)
    trips = sorted({m.trip_key for m in members})
    outlier_trips = sorted({members[k].trip_key for k in fused.outlier_members if k < len(members)})
    props = {
        "support_trips": len(trips),
        "support_observations": int(sum(m.instance.n_observations for m in members)),
        "uncertainty_m": round(float(fused.uncertainty_m), 4),
        "first_seen": first,
        "last_confirmed": last,
        "style": fused.style.value if fused.style is not None else None,
        "trips": trips,
        "scatter_ratio": round(float(fused.scatter_ratio), 3),
        "rejected_weight_share": round(float(fused.rejected_weight_share), 3),
        "outlier_trips": outlier_trips,
        "max_internal_gap_m": round(float(fused.max_internal_gap_m), 2),
        "first_trip": first_trip,
    }
    return MapFeature(
        type=fused.type,
        points_xy_world=fused.points_xy_world,
        style=fused.style,
        feature_id=feature_id,
        properties=props,
    )


def trip_probe_points(
    instances_per_trip: Mapping[str, Sequence[TripInstance]], spacing_m: float = 5.0
) -> dict[str, np.ndarray]:
    out = {}
    for key, instances in instances_per_trip.items():
        pts = [
            resample_polyline(np.asarray(i.points_xy_world, float), spacing_m)
            for i in instances
            if len(i.points_xy_world) >= 2
        ]
        out[key] = np.concatenate(pts) if pts else np.zeros((0, 2))
    return out


def path_probes(
    paths_xy_per_trip: Mapping[str, np.ndarray] | None, spacing_m: float = 2.0
) -> dict[str, np.ndarray]:
    """Each trip's driven path as ``(P, 4)`` rows x, y, unit direction x, y every ``spacing_m``."""
    out = {}
    for key, xy in (paths_xy_per_trip or {}).items():
        p = resample_polyline(np.asarray(xy, float)[:, :2], spacing_m) if len(xy) >= 2 else np.zeros((0, 2))
        if len(p) < 2:
            continue
        t = np.gradient(p, axis=0)
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        out[key] = np.hstack([p, t])
    return out


def orient_centerlines(
    features: Sequence[MapFeature], probes: Mapping[str, np.ndarray], params: TopologyParams
) -> list[MapFeature]:
    """Centrelines point the way the trips that drove on them (path within a quarter lane)
    drove; without such trips they keep the direction most of their members had."""
    if not probes:
        return list(features)
    allp = np.concatenate(list(probes.values()))
    tree = cKDTree(allp[:, :2])
    out = []
    for f in features:
        p = np.asarray(f.points_xy_world, float)
        if f.type != ElementType.CENTERLINE or len(p) < 2:
            out.append(f)
            continue
        q = resample_polyline(p, 2.0)
        t = np.gradient(q, axis=0)
        dist, idx = tree.query(q, distance_upper_bound=0.25 * params.MIN_LANE_WIDTH_M)
        ok = np.isfinite(dist)
        vote = float(np.sum((allp[idx[ok], 2:] * t[ok]).sum(1))) if ok.any() else 0.0
        out.append(replace(f, points_xy_world=p[::-1].copy()) if vote < 0 else f)
    return out


def finish(
    features: Sequence[MapFeature],
    members: dict[str, tuple[Member, ...]],
    trip_points: dict[str, np.ndarray],
    params: TopologyParams,
    match_pairs: Sequence,
    timings_s: dict[str, float],
    trip_times: Mapping[str, object] | None = None,
    rejected_members: Sequence[Member] = (),
    trip_paths: Mapping[str, np.ndarray] | None = None,
    previous: Sequence[MapFeature] = (),
) -> TopologyResult:
    """Lines that at least ``SUPPRESS_MIN_PASSING`` trips drove alongside without seeing them,
    and that fewer than ``LOW_SUPPORT_SHARE`` of the trips with them in view saw, are held back
    (``suppressed``); centrelines are derived where the published lines have none
    (``derived_centerlines``; ids continue the derived ones of ``previous``, the earlier map);
    validation over the whole map, flags copied into each feature; the lane graph of the
    published ones. ``features``: the fused map (no derived centrelines); ``trip_paths``: see
    :func:`path_probes`."""
    t0 = time.perf_counter()
    if params.TRIM_UNSEEN_TAILS:
        features, _ = trim_unseen_tails(features, members, trip_paths or {}, params, params.END_WINDOW_M)
    passed = passing_counts(features, trip_paths or {}, params)
    held = [
        seen_too_rarely(int(f.properties["support_trips"]), n, params)
        for f, n in zip(features, passed, strict=True)
    ]
    published = [f for f, h in zip(features, held, strict=True) if not h]
    derived = derive_centerlines(
        published, trip_paths or {}, params, trip_times, [f for f in previous if is_derived(f)]
    )
    taken = {f.feature_id for f in features}
    for k, f in enumerate(derived):
        fid, n = f.feature_id, 2
        while fid in taken:
            fid, n = f"{f.feature_id}-d{n}", n + 1
        taken.add(fid)
        derived[k] = replace(f, feature_id=fid)
    features = [*features, *derived]
    passed += [0] * len(derived)  # never perceived, so never passed unseen
    held += [False] * len(derived)
    t1 = time.perf_counter()
    cover = coverage_counts(features, trip_points, params.COVERAGE_RADIUS_M)
    flags, quality = validate(features, cover, params, match_pairs, trip_sigmas(members.values()))
    by_feature: dict[str, list[str]] = {}
    for fl in flags:
        if fl.feature_id is not None:
            by_feature.setdefault(fl.feature_id, []).append(fl.kind)
    final = [
        replace(
            f,
            properties={
                **f.properties,
                "coverage_trips": c,
                "passed_trips": n,
                "flags": sorted(set(by_feature.get(f.feature_id, []))),
            },
        )
        for f, c, n in zip(features, cover, passed, strict=True)
    ]
    published_final = tuple(f for f, h in zip(final, held, strict=True) if not h)
    suppressed = tuple(f for f, h in zip(final, held, strict=True) if h)
    t2 = time.perf_counter()
    lane_graph = build_lane_graph(published_final, params)
    t3 = time.perf_counter()
    return TopologyResult(
        published_final,
        lane_graph,
        flags,
        quality,
        members,
        trip_points,
        dict(trip_times or {}),
        {**timings_s, "derive": t1 - t0, "validate": t2 - t1, "lane_graph": t3 - t2},
        suppressed,
        tuple(rejected_members),
        dict(trip_paths or {}),
    )


def trip_sigmas(member_groups: Iterable[Sequence[Member]]) -> dict[str, float]:
    """Trip key -> RMS over its element types of its instances' lateral sigma (``Member.sigma_m``:
    perception noise and alignment), for the residual a registration of two trips should have."""
    per_trip: dict[str, dict[ElementType, float]] = {}
    for group in member_groups:
        for m in group:
            per_trip.setdefault(m.trip_key, {})[m.instance.type] = m.sigma_m
    return {k: math.sqrt(sum(v * v for v in s.values()) / len(s)) for k, s in per_trip.items()}


def reposition_instances(
    instances: Sequence[TripInstance], from_xyyaw: np.ndarray, to_xyyaw: np.ndarray
) -> tuple[TripInstance, ...]:
    """A trip's instances placed with its poses ``from`` (world_T_vehicle ``(N, 3)``, e.g. the
    single-trip smoothed ones) re-placed with poses ``to`` (e.g. after alignment): each point
    moves with the correction ``to @ inv(from)`` of the frame, among the instance's frames,
    whose vehicle was nearest to it (long instances follow a correction that varies along)."""
    out = []
    for inst in instances:
        f0, f1 = int(inst.first_frame), int(inst.last_frame) + 1
        frames = np.arange(max(f0, 0), max(min(f1, len(from_xyyaw)), f0 + 1))
        _, i = cKDTree(from_xyyaw[frames, :2]).query(inst.points_xy_world)
        fr = frames[i]
        corr = compose(to_xyyaw[fr], inverse(from_xyyaw[fr]))  # (P, 3) to_T_from per point
        c, s = np.cos(corr[:, 2]), np.sin(corr[:, 2])
        p = inst.points_xy_world
        moved = np.column_stack(
            [c * p[:, 0] - s * p[:, 1] + corr[:, 0], s * p[:, 0] + c * p[:, 1] + corr[:, 1]]
        )
        out.append(replace(inst, points_xy_world=moved))
    return tuple(out)
