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
- ``high_residual_pair``: an alignment match pair whose registration residual exceeds
  ``HIGH_RESIDUAL_SIGMAS`` x what the two trips' noise predicts (``expected_pair_residual_m``)
  involves one of its trips near it.

Informative (not suspect, severity 0): ``outlier_trip`` (the fused geometry ignores a minority
trip), ``gap`` (an unsupported stretch of at least ``GAP_MIN_M`` inside the instance, or a break
of up to ``MAX_GAP_M`` to a collinear instance of its type), ``low_support_marking`` (the
``low_support`` rule on a stop line or crosswalk: markings a vehicle crosses, seen whole from a
few metres and never spliced from tracks; on the hard profile those one trip saw were really
wrong less often than the map's average instance, 2 of 33 against 194 of 1193, so they are
reported and not counted as suspect -- the criterion that made ``gap`` informative).

What no check here can see: an offset shared by every trip in a region (the map as a whole
placed off there, e.g. all its trips under the same GNSS bias): it leaves no inconsistency
between trips. ``evaluate`` reports how many really wrong instances remain once such a local
offset is removed (``beyond_local_offset``).

Per tile (square ``TILE_SIZE_M`` tiles of the world plane): a quality score in [0, 1], 1 minus
the severity-weighted share of instance length flagged, and the list of flags.
"""

from __future__ import annotations

import itertools
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
SEVERITY = {
    "low_support": 1.0,
    "trips_disagree": 1.0,
    "implausible_lane_width": 1.0,
    "high_variance": 0.7,
    "high_residual_pair": 0.7,
    "gap": 0.0,
    "outlier_trip": 0.0,
    "low_support_marking": 0.0,
}
SUSPECT = frozenset(k for k, v in SEVERITY.items() if v > 0)
PAIR_RADIUS_M = 30.0  # a match pair speaks for the instances within this of its centre
#: crossed, not driven along: their ``low_support`` is reported as ``low_support_marking``
MARKING_TYPES = frozenset({ElementType.STOP_LINE, ElementType.CROSSWALK})


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
        # derived centrelines are no estimates of their own: a connector starts on the lane it leaves
        idx = [i for i, f in enumerate(features) if f.type == etype and "derived" not in f.properties]
        if len(idx) < 2:
            continue
        pts, tans, own = _samples([features[i] for i in idx], spacing)
        unc = np.array(
            [float(features[i].properties.get("uncertainty_m", params.DEFAULT_LATERAL_SIGMA_M)) for i in idx]
        )
        tree = cKDTree(pts)
        pairs = tree.query_pairs(params.MAX_LANE_WIDTH_M, output_type="ndarray")
        if not len(pairs):
            continue
        # samples a, b of two nearly parallel lines, b beside a (within a sample spacing along a's
        # tangent), either way round; checked pair by pair before the pairs are doubled
        pairs = pairs[own[pairs[:, 0]] != own[pairs[:, 1]]]
        pa, pb = pairs[:, 0], pairs[:, 1]
        pairs = pairs[np.abs((tans[pa] * tans[pb]).sum(1)) >= math.cos(math.radians(15))]
        pa, pb = pairs[:, 0], pairs[:, 1]
        rel = pts[pb] - pts[pa]  # reversed for b -> a: |along| the same
        beside_a = np.abs((tans[pa] * rel).sum(1)) <= spacing
        beside_b = np.abs((tans[pb] * rel).sum(1)) <= spacing
        a, b = np.r_[pa[beside_a], pb[beside_b]], np.r_[pb[beside_a], pa[beside_b]]
        rel = pts[b] - pts[a]
        lat = np.abs(tans[a, 0] * rel[:, 1] - tans[a, 1] * rel[:, 0])
        nearest = np.full(len(pts), np.inf)
        np.minimum.at(nearest, a, lat)
        finite = nearest[np.isfinite(nearest) & (nearest > gate)]
        typical = float(np.median(finite)) if len(finite) >= 20 else params.MIN_LANE_WIDTH_M / 0.7
        narrow = float(np.clip(0.7 * typical, 0.6 * params.MIN_LANE_WIDTH_M, params.MIN_LANE_WIDTH_M))
        noise = params.DUPLICATE_SIGMAS * np.hypot(unc[own[a]], unc[own[b]])
        # alongside: the samples of a with a sample of the other line beside them (either side)
        near = lat < narrow
        beside = np.unique(a[near] * len(idx) + own[b[near]])  # (sample, other line) once
        n_beside = Counter(zip(own[beside // len(idx)].tolist(), (beside % len(idx)).tolist(), strict=True))
        bad = (lat > noise) & near
        # per pair of features: the run of narrow samples, if the offset holds along it (a copy
        # is parallel: its offset varies less than the noise bound; branches that diverge do
        # not); blame the clearly less supported one, else both unless both are confirmed (two
        # lines each seen by several trips are the road's own narrow spacing, a taper or a lane
        # that ends, more often than one line twice)
        a, b, lat, noise = a[bad], b[bad], lat[bad], noise[bad]
        if not len(a):
            continue
        order = np.lexsort((lat, a, own[b], own[a]))
        a, b, lat, noise = a[order], b[order], lat[order], noise[order]
        first = np.r_[True, (own[a][1:] != own[a][:-1]) | (own[b][1:] != own[b][:-1]) | (a[1:] != a[:-1])]
        a, b, lat, noise = a[first], b[first], lat[first], noise[first]  # nearest partner sample only
        support = [int(features[i].properties.get("support_trips", 1)) for i in idx]
        length = np.bincount(own, minlength=len(idx)) * spacing
        key = own[a] * len(idx) + own[b]  # ascending (sorted by own[a], own[b] above)
        keys, starts = np.unique(key, return_index=True)
        for k, start, stop in zip(
            keys.tolist(), starts.tolist(), [*starts[1:].tolist(), len(key)], strict=True
        ):
            sel = slice(start, stop)  # this pair of features
            fa, fb = divmod(k, len(idx))
            run = float(stop - start) * spacing
            if run < min(params.WIDTH_RUN_M, 0.5 * length[fa]) or run < 0.5 * n_beside[(fa, fb)] * spacing:
                continue
            lo, hi = np.percentile(lat[sel], [10, 90])
            if hi - lo > float(np.median(noise[sel])):
                continue
            similar = not support[fb] <= 0.5 * support[fa]
            if support[fa] <= 0.5 * support[fb] or (similar and support[fa] < params.MIN_SUPPORT_TRIPS):
                out[idx[fa]] = max(out.get(idx[fa], 0.0), run)
    return out


def _breaks(features: Sequence[MapFeature], params: TopologyParams) -> set[int]:
    """Line features whose end is a short break from a collinear same-type line."""
    out: set[int] = set()
    lines = [
        (i, np.asarray(f.points_xy_world, float))
        for i, f in enumerate(features)
        if not f.type.is_polygon and len(f.points_xy_world) >= 3
    ]
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


def expected_pair_residual_m(
    trip_key_i: str, trip_key_j: str, trip_sigma_m: Mapping[str, float], params: TopologyParams
) -> float:
    """The RMS residual a registration of two trips' sub-maps has from noise alone: their
    lateral sigmas combined (``trip_sigma_m``: trip key -> RMS over its element types of
    ``TopologyParams.trip_sigma_m``). A side not in it (the pre-built map) counts as the other."""
    default = params.trip_sigma_m(None)
    a, b = trip_sigma_m.get(trip_key_i), trip_sigma_m.get(trip_key_j)
    a = a if a is not None else (b if b is not None else default)
    b = b if b is not None else a
    return math.hypot(a, b)


def validate(
    features: Sequence[MapFeature],
    coverage_trips: Sequence[int],
    params: TopologyParams,
    match_pairs: Sequence = (),
    trip_sigma_m: Mapping[str, float] | None = None,
) -> tuple[tuple[ValidationFlag, ...], dict[tuple[int, int], TileQuality]]:
    """Flags per instance and quality per tile.

    ``features`` carry the fusion statistics in ``properties`` (support_trips, scatter_ratio,
    rejected_weight_share, outlier_trips, max_internal_gap_m, trips); ``coverage_trips[i]`` is the
    number of trips that passed feature i; ``match_pairs`` objects with ``centre_xy_world``,
    ``residual_rms_m``, ``trip_key_i``, ``trip_key_j`` (``alignment.MatchPairRecord``);
    ``trip_sigma_m``: trip key -> its instances' lateral sigma (``expected_pair_residual_m``;
    missing trips take the default noise).
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
    bad_pairs = [
        mp
        for mp in match_pairs
        if float(mp.residual_rms_m)
        > params.HIGH_RESIDUAL_SIGMAS
        * expected_pair_residual_m(mp.trip_key_i, mp.trip_key_j, trip_sigma_m or {}, params)
    ]
    for k, f in enumerate(features):
        pr = f.properties
        tile = home[k]
        fid = f.feature_id
        support = int(pr.get("support_trips", 1))
        cover = int(coverage_trips[k])
        if support < params.MIN_SUPPORT_TRIPS or support < params.LOW_SUPPORT_SHARE * cover:
            kind = "low_support_marking" if f.type in MARKING_TYPES else "low_support"
            flags.append(ValidationFlag(kind, fid, tile, value=support / max(cover, 1)))
        if support >= 2 and pr.get("scatter_ratio", 0.0) > params.HIGH_VARIANCE_RATIO:
            flags.append(ValidationFlag("high_variance", fid, tile, value=float(pr["scatter_ratio"])))
        if pr.get("rejected_weight_share", 0.0) >= params.DISAGREE_WEIGHT_SHARE:
            flags.append(
                ValidationFlag(
                    "trips_disagree",
                    fid,
                    tile,
                    tuple(pr.get("outlier_trips", ())),
                    float(pr["rejected_weight_share"]),
                )
            )
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
                if {mp.trip_key_i, mp.trip_key_j} & trips and float(
                    np.min(np.linalg.norm(p - np.asarray(mp.centre_xy_world), axis=1))
                ) <= PAIR_RADIUS_M:
                    flags.append(
                        ValidationFlag(
                            "high_residual_pair",
                            fid,
                            tile,
                            (mp.trip_key_i, mp.trip_key_j),
                            float(mp.residual_rms_m),
                        )
                    )
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
        keys, inv = _unique_rows(tiles)
        total = np.bincount(inv, minlength=len(keys))
        bad = np.bincount(inv, weights=worst[own], minlength=len(keys))
        tile_feature = np.unique(inv * len(features) + own)  # (tile, feature) with samples there
        n_features = np.bincount(tile_feature // len(features), minlength=len(keys)).tolist()
        for t, key in enumerate(keys):
            tk = (int(key[0]), int(key[1]))
            n_feat = n_features[t]
            c = per_tile_flags.get(tk, Counter())
            quality[tk] = TileQuality(
                tk,
                float(1.0 - bad[t] / max(total[t], 1)),
                tuple(f"{kind}:{n}" for kind, n in sorted(c.items())),
                n_feat,
            )
    return tuple(flags), quality


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_inverse=True)`` of integer rows ``(N, 2)`` (tile indices),
    by one integer key per row (in the same lexicographic order)."""
    lo = rows.min(0)
    span = int(rows[:, 1].max() - lo[1]) + 1
    uniq, inv = np.unique((rows[:, 0] - lo[0]) * span + (rows[:, 1] - lo[1]), return_inverse=True)
    return np.column_stack([uniq // span + lo[0], uniq % span + lo[1]]), inv


def _labelled_tree(per_trip: Mapping[str, np.ndarray]):
    """The trips with rows, all their rows stacked, each row's trip (index into the keys) and a
    KD-tree over the rows' first two columns (x, y)."""
    keys = [k for k, p in per_trip.items() if len(p)]
    if not keys:
        return keys, None, None, None
    rows = np.concatenate([per_trip[k] for k in keys])
    label = np.concatenate([np.full(len(per_trip[k]), i) for i, k in enumerate(keys)])
    return keys, rows, label, cKDTree(rows[:, :2])


def _ball_hits(tree: cKDTree, points: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query_ball_point`` of ``points (P, 2)``, flattened: per point the number of rows
    within ``radius_m`` ``(P,)``, and those rows, point after point."""
    hits = tree.query_ball_point(points, radius_m)
    counts = np.fromiter(map(len, hits), np.int64, len(hits))
    return counts, np.fromiter(itertools.chain.from_iterable(hits), np.int64, int(counts.sum()))


def coverage_counts(
    features: Sequence[MapFeature], trip_points: Mapping[str, np.ndarray], radius_m: float
) -> list[int]:
    """For each feature, how many trips have some element point within ``radius_m`` of it
    (``trip_points``: each trip's element points, a few metres apart). All features' probes
    (every 5 m) at once, trip after trip (a count per probe, no lists of the points)."""
    probes = []
    for f in features:
        p = np.asarray(f.points_xy_world, float)
        probes.append(resample_polyline(p, 5.0) if len(p) >= 2 else p.reshape(-1, 2))
    if not probes:
        return []
    feature_of_probe = np.repeat(np.arange(len(features)), [len(p) for p in probes])
    all_probes = np.concatenate(probes)
    out = np.zeros(len(features), np.int64)
    for points in trip_points.values():
        if len(points):
            near = cKDTree(points).query_ball_point(all_probes, radius_m, return_length=True) > 0
            out += np.bincount(feature_of_probe[near], minlength=len(features)) > 0
    return out.tolist()


PASS_PROBE_SPACING_M = 5.0  # a line is checked every this many metres


def passing_counts(
    features: Sequence[MapFeature], trip_paths: Mapping[str, np.ndarray], params: TopologyParams
) -> list[int]:
    """For each line feature, how many trips that did not see it drove alongside it: the
    negative evidence against a ghost (``PASS_LATERAL_M``, ``PASS_MAX_ANGLE_RAD``,
    ``PASS_MIN_SHARE``). ``trip_paths``: each trip's driven path as ``(P, 4)`` rows x, y, unit
    direction x, y a few metres apart (``instances.path_probes``); ``properties["trips"]`` of a
    feature names the trips that saw it. Polygons and stop lines (crossed, not driven along) and
    derived centrelines (no perception saw them): 0. All lines' probes in one query."""
    keys, rows, label, tree = _labelled_tree(trip_paths)
    out = [0] * len(features)
    if not keys or not features:
        return out
    cos_max = math.cos(params.PASS_MAX_ANGLE_RAD)
    lines, probes, tangents = [], [], []
    for k, f in enumerate(features):
        p = np.asarray(f.points_xy_world, float)
        if (
            f.type.is_polygon
            or f.type in params.WHOLE_ELEMENT_TYPES
            or len(p) < 2
            or "derived" in f.properties
        ):
            continue  # derived centrelines (``derived_centerlines``) are never seen, so never passed unseen
        probe = resample_polyline(p, PASS_PROBE_SPACING_M)
        tangent = np.gradient(probe, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        lines.append(k)
        probes.append(probe)
        tangents.append(tangent)
    if not lines:
        return out
    n_keys = len(keys)
    counts, idx = _ball_hits(tree, np.concatenate(probes), params.PASS_LATERAL_M)
    at = np.repeat(np.arange(len(counts)), counts)
    along = np.abs(np.einsum("ij,ij->i", rows[idx, 2:], np.concatenate(tangents)[at])) >= cos_max
    probe_trip = np.unique(at[along] * n_keys + label[idx[along]])  # (probe, trip) with a pass
    line_of_probe = np.repeat(np.arange(len(lines)), [len(p) for p in probes])
    per_line_trip = np.bincount(
        line_of_probe[probe_trip // n_keys] * n_keys + probe_trip % n_keys, minlength=len(lines) * n_keys
    ).reshape(len(lines), n_keys)
    for j, k in enumerate(lines):
        seen_by = set(features[k].properties.get("trips", ()))
        out[k] = sum(
            1
            for i, key in enumerate(keys)
            if per_line_trip[j, i] >= params.PASS_MIN_SHARE * len(probes[j]) and key not in seen_by
        )
    return out


def seen_too_rarely(support_trips: int, passed_trips: int, params: TopologyParams) -> bool:
    """Held back: enough trips drove alongside without seeing it (``SUPPRESS_MIN_PASSING``) and
    fewer than ``LOW_SUPPORT_SHARE`` of all the trips that had it in view saw it. A real line is
    seen on nearly every pass (tens of frames in view), so this is what ghosts and one trip's
    mis-spliced lines look like."""
    return (
        params.SUPPRESS_MIN_PASSING > 0
        and passed_trips >= params.SUPPRESS_MIN_PASSING
        and support_trips < params.LOW_SUPPORT_SHARE * (support_trips + passed_trips)
    )
