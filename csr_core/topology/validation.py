"""Automatic validation of the fused map (paper III-E: "the obtained instance geometry and
variance of noise are used to determine whether there is noise in the map").

Per instance (thresholds from the noise model, see ``TopologyParams``):

- ``low_support``: fewer than ``MIN_SUPPORT_TRIPS`` trips saw it (a single trip: nobody checked
  it), or fewer than ``LOW_SUPPORT_SHARE`` of the trips that passed it (trips with any element
  within ``COVERAGE_RADIUS_M``);
- ``high_variance``: the inlier trips scatter around the fused line by more than
  ``HIGH_VARIANCE_RATIO`` times their own sigma (chi-like ratio; 1 when the noise model holds);
- ``trips_disagree``: trips the robust fit rejected hold at least ``DISAGREE_WEIGHT_SHARE`` of
  the weight (two populations: which one is right is not clear);
- ``implausible_lane_width``: a parallel line of its type (any line type) farther than two
  estimates of one line differ by noise (``DUPLICATE_SIGMAS`` x the combined ``uncertainty_m``)
  but closer than a plausible lane (0.7 x the data's median spacing, within 0.6 - 1 x
  ``MIN_LANE_WIDTH_M``), at an offset that holds (varies less than that noise bound) over
  ``WIDTH_RUN_M`` (or half the instance) and over at least half of what lies beside it: one
  element in the map twice, one copy off;
- ``high_residual_pair``: an alignment match pair whose residual exceeds
  ``HIGH_RESIDUAL_SIGMAS`` x ``ALIGNMENT_SIGMA_M`` involves one of its trips near it.

Informative (not suspect, severity 0): ``outlier_trip`` (the fused geometry ignores a minority
trip), ``gap`` (an unsupported stretch of at least ``GAP_MIN_M`` inside the instance, or a break
of up to ``MAX_GAP_M`` to a collinear instance of its type).

What no check here can see: an offset shared by every trip in a region (the map as a whole
placed off there, e.g. all its trips under the same GNSS bias): it leaves no inconsistency
between trips. ``evaluate`` reports how many really wrong instances remain once such a local
offset is removed (``beyond_local_offset``).

Per tile (square ``TILE_SIZE_M`` tiles of the world plane): a quality score in [0, 1], 1 minus
the severity-weighted share of instance length flagged, and the list of flags.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.params import TopologyParams
from csr_core.types import ElementType, MapFeature

# severity of each flag in the tile score; ``outlier_trip`` and ``gap`` are informative and do not
# make an instance suspect (a gap is spanned by the fit or is a break between two pieces: on the
# hard and standard profiles an instance flagged by it alone was really wrong less often than the
# map's average instance)
SEVERITY = {"low_support": 1.0, "trips_disagree": 1.0, "implausible_lane_width": 1.0, "high_variance": 0.7,
            "high_residual_pair": 0.7, "gap": 0.0, "outlier_trip": 0.0}
SUSPECT = frozenset(k for k, v in SEVERITY.items() if v > 0)
PAIR_RADIUS_M = 30.0  # a match pair speaks for the instances within this of its centre


@dataclass(frozen=True, slots=True)
class ValidationFlag:
    kind: str
    feature_id: str | None
    tile: tuple[int, int]
    trip_keys: tuple[str, ...] = ()
    value: float = float("nan")


@dataclass(frozen=True, slots=True)
class TileQuality:
    tile: tuple[int, int]
    score: float  # 1: nothing suspect
    flags: tuple[str, ...]  # "kind:count", sorted
    n_features: int


def tile_of(points_xy: np.ndarray, tile_size_m: float) -> np.ndarray:
    return np.floor(np.asarray(points_xy, float) / tile_size_m).astype(np.int64)


def _samples(features: Sequence[MapFeature], spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts, tans, own = [], [], []
    for k, f in enumerate(features):
        p = np.asarray(f.points_xy_world, float)
        if f.type.is_polygon and len(p) >= 3:
            p = np.vstack([p, p[:1]])
        p = resample_polyline(p, spacing) if len(p) >= 2 else p
        t = np.gradient(p, axis=0) if len(p) >= 2 else np.array([[1.0, 0.0]])
        t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        pts.append(p)
        tans.append(t)
        own.append(np.full(len(p), k))
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int)
    return np.concatenate(pts), np.concatenate(tans), np.concatenate(own)


def _narrow_spacing(features: Sequence[MapFeature], params: TopologyParams) -> dict[int, float]:
    """Feature index -> run length (m) along which a same-type parallel line lies implausibly
    close: farther than two estimates of one line differ by noise (``DUPLICATE_SIGMAS`` x the
    combined ``uncertainty_m`` of the two) but closer than two distinct parallel elements of the
    type can be (0.7 x the data's median spacing, within 0.6 - 1 x ``MIN_LANE_WIDTH_M``). One
    element is in the map twice, one copy (or both) off. The run must hold over ``WIDTH_RUN_M``
    or half the instance, whichever is shorter (short pieces are copies too)."""
    out: dict[int, float] = {}
    spacing = params.SAMPLE_SPACING_M
    gate = params.GATE_MAX_SHARE_OF_LANE * params.MIN_LANE_WIDTH_M
    for etype in ElementType:
        if etype.is_polygon:
            continue
        idx = [i for i, f in enumerate(features) if f.type == etype]
        if len(idx) < 2:
            continue
        pts, tans, own = _samples([features[i] for i in idx], spacing)
        unc = np.array([float(features[i].properties.get("uncertainty_m", params.DEFAULT_LATERAL_SIGMA_M))
                        for i in idx])
        tree = cKDTree(pts)
        pairs = tree.query_pairs(params.MAX_LANE_WIDTH_M, output_type="ndarray")
        if not len(pairs):
            continue
        a, b = np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]]
        keep = (own[a] != own[b]) & (np.abs((tans[a] * tans[b]).sum(1)) >= math.cos(math.radians(15)))
        a, b = a[keep], b[keep]
        rel = pts[b] - pts[a]
        lat = np.abs(tans[a, 0] * rel[:, 1] - tans[a, 1] * rel[:, 0])
        along = np.abs((tans[a] * rel).sum(1))
        ok = along <= spacing
        a, b, lat = a[ok], b[ok], lat[ok]
        nearest = np.full(len(pts), np.inf)
        np.minimum.at(nearest, a, lat)
        finite = nearest[np.isfinite(nearest) & (nearest > gate)]
        typical = float(np.median(finite)) if len(finite) >= 20 else params.MIN_LANE_WIDTH_M / 0.7
        narrow = float(np.clip(0.7 * typical, 0.6 * params.MIN_LANE_WIDTH_M, params.MIN_LANE_WIDTH_M))
        noise = params.DUPLICATE_SIGMAS * np.hypot(unc[own[a]], unc[own[b]])
        # alongside: the samples of a with a sample of the other line beside them (either side)
        near = lat < narrow
        beside = np.unique(np.c_[own[a[near]], own[b[near]], a[near]], axis=0)
        n_beside = Counter(zip(beside[:, 0].tolist(), beside[:, 1].tolist(), strict=True))
        bad = (lat > noise) & near
        # per pair of features: the run of narrow samples, if the offset holds along it (a copy
        # is parallel: its offset varies less than the noise bound; branches that diverge do
        # not); blame the clearly less supported one, else both
        a, b, lat, noise = a[bad], b[bad], lat[bad], noise[bad]
        if not len(a):
            continue
        order = np.lexsort((lat, a, own[b], own[a]))
        a, b, lat, noise = a[order], b[order], lat[order], noise[order]
        first = np.r_[True, (own[a][1:] != own[a][:-1]) | (own[b][1:] != own[b][:-1]) | (a[1:] != a[:-1])]
        a, b, lat, noise = a[first], b[first], lat[first], noise[first]  # nearest partner sample only
        support = [int(features[i].properties.get("support_trips", 1)) for i in idx]
        length = np.bincount(own, minlength=len(idx)) * spacing
        key = own[a] * len(idx) + own[b]
        for k in np.unique(key):
            sel = key == k
            fa, fb = divmod(int(k), len(idx))
            run = float(sel.sum()) * spacing
            if run < min(params.WIDTH_RUN_M, 0.5 * length[fa]) or run < 0.5 * n_beside[(fa, fb)] * spacing:
                continue
            lo, hi = np.percentile(lat[sel], [10, 90])
            if hi - lo > float(np.median(noise[sel])):
                continue
            if support[fa] <= 0.5 * support[fb] or not support[fb] <= 0.5 * support[fa]:
                out[idx[fa]] = max(out.get(idx[fa], 0.0), run)
    return out


def _breaks(features: Sequence[MapFeature], params: TopologyParams) -> set[int]:
    """Line features whose end is a short break from a collinear same-type line."""
    out: set[int] = set()
    lines = [(i, np.asarray(f.points_xy_world, float)) for i, f in enumerate(features)
             if not f.type.is_polygon and len(f.points_xy_world) >= 3]
    for etype in ElementType:
        sel = [(i, p) for i, p in lines if features[i].type == etype]
        if len(sel) < 2:
            continue
        ends, dirs, owner = [], [], []
        for i, p in sel:
            for e in (0, 1):
                q = p[-1] if e else p[0]
                r = p[-3] if e else p[2]
                v = q - r
                ends.append(q)
                dirs.append(v / max(float(np.linalg.norm(v)), 1e-12))  # outward
                owner.append(i)
        ends_a, dirs_a = np.array(ends), np.array(dirs)
        tree = cKDTree(ends_a)
        for u, v in tree.query_pairs(params.MAX_GAP_M):
            if owner[u] == owner[v]:
                continue
            gap = ends_a[v] - ends_a[u]
            dist = float(np.linalg.norm(gap))
            if dist < params.SAMPLE_SPACING_M:
                continue
            g = gap / dist
            if float(dirs_a[u] @ g) > 0.95 and float(-dirs_a[v] @ g) > 0.95:
                out.update((owner[u], owner[v]))
    return out


def validate(features: Sequence[MapFeature], coverage_trips: Sequence[int], params: TopologyParams,
             match_pairs: Sequence = ()) -> tuple[tuple[ValidationFlag, ...], dict[tuple[int, int], TileQuality]]:
    """Flags per instance and quality per tile.

    ``features`` carry the fusion statistics in ``properties`` (support_trips, scatter_ratio,
    rejected_weight_share, outlier_trips, max_internal_gap_m, trips); ``coverage_trips[i]`` is the
    number of trips that passed feature i; ``match_pairs`` objects with ``centre_xy_world``,
    ``residual_rms_m``, ``trip_key_i``, ``trip_key_j`` (``alignment.MatchPairRecord``).
    """
    flags: list[ValidationFlag] = []
    narrow = _narrow_spacing(features, params)
    breaks = _breaks(features, params)
    pts, _, own = _samples(features, params.SAMPLE_SPACING_M)
    tiles = tile_of(pts, params.TILE_SIZE_M)
    home: dict[int, tuple[int, int]] = {}
    for k, f in enumerate(features):
        p = np.asarray(f.points_xy_world, float)
        tx, ty = tile_of(p[len(p) // 2], params.TILE_SIZE_M)
        home[k] = (int(tx), int(ty))
    bad_pairs = [mp for mp in match_pairs
                 if float(mp.residual_rms_m) > params.HIGH_RESIDUAL_SIGMAS * params.ALIGNMENT_SIGMA_M]
    for k, f in enumerate(features):
        pr = f.properties
        tile = home[k]
        fid = f.feature_id
        support = int(pr.get("support_trips", 1))
        cover = int(coverage_trips[k])
        if support < params.MIN_SUPPORT_TRIPS or support < params.LOW_SUPPORT_SHARE * cover:
            flags.append(ValidationFlag("low_support", fid, tile, value=support / max(cover, 1)))
        if support >= 2 and pr.get("scatter_ratio", 0.0) > params.HIGH_VARIANCE_RATIO:
            flags.append(ValidationFlag("high_variance", fid, tile, value=float(pr["scatter_ratio"])))
        if pr.get("rejected_weight_share", 0.0) >= params.DISAGREE_WEIGHT_SHARE:
            flags.append(ValidationFlag("trips_disagree", fid, tile, tuple(pr.get("outlier_trips", ())),
                                        float(pr["rejected_weight_share"])))
        elif pr.get("outlier_trips"):
            flags.append(ValidationFlag("outlier_trip", fid, tile, tuple(pr["outlier_trips"])))
        if pr.get("max_internal_gap_m", 0.0) >= params.GAP_MIN_M or k in breaks:
            flags.append(ValidationFlag("gap", fid, tile, value=float(pr.get("max_internal_gap_m", 0.0))))
        if k in narrow:
            flags.append(ValidationFlag("implausible_lane_width", fid, tile, value=narrow[k]))
        if bad_pairs:
            trips = set(pr.get("trips", ()))
            p = np.asarray(f.points_xy_world, float)
            for mp in bad_pairs:
                if {mp.trip_key_i, mp.trip_key_j} & trips and \
                        float(np.min(np.linalg.norm(p - np.asarray(mp.centre_xy_world), axis=1))) <= PAIR_RADIUS_M:
                    flags.append(ValidationFlag("high_residual_pair", fid, tile, (mp.trip_key_i, mp.trip_key_j),
                                                float(mp.residual_rms_m)))
                    break
    # tiles: severity-weighted share of sample length flagged
    worst = np.zeros(len(features))
    index = {f.feature_id: k for k, f in enumerate(features)}
    per_tile_flags: dict[tuple[int, int], Counter] = {}
    for fl in flags:
        if fl.feature_id in index:
            worst[index[fl.feature_id]] = max(worst[index[fl.feature_id]], SEVERITY[fl.kind])
        per_tile_flags.setdefault(fl.tile, Counter())[fl.kind] += 1
    quality: dict[tuple[int, int], TileQuality] = {}
    if len(pts):
        keys, inv = np.unique(tiles, axis=0, return_inverse=True)
        inv = inv.ravel()
        total = np.bincount(inv, minlength=len(keys))
        bad = np.bincount(inv, weights=worst[own], minlength=len(keys))
        for t, key in enumerate(keys):
            tk = (int(key[0]), int(key[1]))
            n_feat = len(np.unique(own[inv == t]))
            c = per_tile_flags.get(tk, Counter())
            quality[tk] = TileQuality(tk, float(1.0 - bad[t] / max(total[t], 1)),
                                      tuple(f"{kind}:{n}" for kind, n in sorted(c.items())), n_feat)
    return tuple(flags), quality


def _labelled_tree(per_trip: Mapping[str, np.ndarray]):
    """The trips with rows, all their rows stacked, each row's trip (index into the keys) and a
    KD-tree over the rows' first two columns (x, y)."""
    keys = [k for k, p in per_trip.items() if len(p)]
    if not keys:
        return keys, None, None, None
    rows = np.concatenate([per_trip[k] for k in keys])
    label = np.concatenate([np.full(len(per_trip[k]), i) for i, k in enumerate(keys)])
    return keys, rows, label, cKDTree(rows[:, :2])


def coverage_counts(features: Sequence[MapFeature], trip_points: Mapping[str, np.ndarray],
                    radius_m: float) -> list[int]:
    """For each feature, how many trips have some element point within ``radius_m`` of it
    (``trip_points``: each trip's element points, a few metres apart)."""
    keys, _, label, tree = _labelled_tree(trip_points)
    if not keys or not features:
        return [0] * len(features)
    out = []
    for f in features:
        p = np.asarray(f.points_xy_world, float)
        probe = resample_polyline(p, 5.0) if len(p) >= 2 else p
        hits = tree.query_ball_point(probe, radius_m)
        idx = np.fromiter((i for h in hits for i in h), dtype=np.int64)
        out.append(int(len(np.unique(label[idx]))))
    return out


PASS_PROBE_SPACING_M = 5.0  # a line is checked every this many metres


def passing_counts(features: Sequence[MapFeature], trip_paths: Mapping[str, np.ndarray],
                   params: TopologyParams) -> list[int]:
    """For each line feature, how many trips that did not see it drove alongside it: the
    negative evidence against a ghost (``PASS_LATERAL_M``, ``PASS_MAX_ANGLE_RAD``,
    ``PASS_MIN_SHARE``). ``trip_paths``: each trip's driven path as ``(P, 4)`` rows x, y, unit
    direction x, y a few metres apart (``instances.path_probes``); ``properties["trips"]`` of a
    feature names the trips that saw it. Polygons and stop lines (crossed, not driven along): 0."""
    keys, rows, label, tree = _labelled_tree(trip_paths)
    if not keys or not features:
        return [0] * len(features)
    cos_max = math.cos(params.PASS_MAX_ANGLE_RAD)
    out = []
    for f in features:
        p = np.asarray(f.points_xy_world, float)
        if f.type.is_polygon or f.type in params.WHOLE_ELEMENT_TYPES or len(p) < 2:
            out.append(0)
            continue
        probe = resample_polyline(p, PASS_PROBE_SPACING_M)
        tangent = np.gradient(probe, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        hits = tree.query_ball_point(probe, params.PASS_LATERAL_M)
        counts = np.fromiter((len(h) for h in hits), np.int64, len(probe))
        idx = np.fromiter((i for h in hits for i in h), np.int64, int(counts.sum()))
        at = np.repeat(np.arange(len(probe)), counts)
        along = np.abs(np.einsum("ij,ij->i", rows[idx, 2:], tangent[at])) >= cos_max
        probe_trip = np.unique(at[along] * len(keys) + label[idx[along]])  # (probe, trip) with a pass
        per_trip = np.bincount(probe_trip % len(keys), minlength=len(keys))
        seen_by = set(f.properties.get("trips", ()))
        out.append(sum(1 for i, k in enumerate(keys)
                       if per_trip[i] >= params.PASS_MIN_SHARE * len(probe) and k not in seen_by))
    return out
