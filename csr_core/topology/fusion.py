"""Fusion of one associated group into one map instance (paper III-E: "fused into instances
using the same method as the single-trip semantic reconstruction procedure").

Lines, as single-trip splicing does for one track's observations (``single_trip.splicing``):
every member sample is projected on a backbone (arclength s, signed lateral offset d), the
lateral profile d(s) is estimated per arclength bin robustly, smoothed by a Gaussian kernel
along s and turned back into a polyline; unsupported stretches longer than ``MAX_GAP_M``
split. What multi-trip fusion adds:

- backbone: the member most others agree with, prolonged by the members that run on past
  its ends (partial overlaps: each trip sees a different part of a long divider), smoothed
  and prolonged straight a little so that every member's end projects inside it;
- weights: each trip's samples weigh 1 / sigma^2 (its noise estimate plus the alignment
  error), every trip contributes the same number of samples per metre (support = trips);
- robust: a weighted median starts an IRLS with Tukey's biweight (c = ``TUKEY_C_SIGMAS`` x
  the larger of the trip's sigma and the group's robust scatter), so one bad trip gets weight
  zero where it is off instead of bending the line;
- peeling: what the fused line does not support (members mostly off it, runs of members off
  it) is handed back as ``detached`` pieces to be associated again (``instances.fuse_type``);
- many lines per group (``fuse_group``): association chains partial overlaps, so at junctions
  (turns overlap the lanes they leave and enter) a city's centrelines are one group; in each
  round its regions are fused one after the other, each from the member most of those left
  agree with, and pieces that lie along a line of the same round join it (``absorb_pieces``);
- statistics for validation and the map properties: the standard error of the profile per
  bin (model and empirical, the larger), the scatter of the trips around it in units of their
  sigma, and the share of weight held by trips the fit rejected.

Polygons: the single-trip polygon splice (per-vertex median after vertex alignment) over the
members' outlines. Styles: a vote weighted by observations.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.sparse import csc_matrix
from scipy.spatial import cKDTree

from csr_core.single_trip.splicing import _robust_ends, polygon_area, resample_polyline
from csr_core.topology.association import (
    MAP_MEMBER_KEY,
    Member,
    neighbour_pairs,
    sample_lines,
    sample_members,
)
from csr_core.topology.params import TopologyParams
from csr_core.types import DividerStyle, ElementType


@dataclass(frozen=True, slots=True)
class FusedInstance:
    """One fused element and what validation needs to know about it.

    ``members``: indices (into the group) that support it; ``detached``: members, or runs of
    members, the fused geometry does not support (to be associated again on their own).
    """

    type: ElementType
    points_xy_world: np.ndarray  # (M, 2)
    style: DividerStyle | None
    members: tuple[int, ...]
    detached: tuple[Member, ...]
    uncertainty_m: float  # median standard error of the lateral position
    scatter_ratio: float  # RMS of inlier trips' offsets / their sigma (about 1 when consistent)
    rejected_weight_share: float  # weight of trips the robust fit rejected / all
    outlier_members: tuple[int, ...]  # members mostly rejected by the robust fit
    max_internal_gap_m: float  # longest unsupported stretch spanned inside
    member_scatter2: tuple[
        float, ...
    ] = ()  # per member: mean (offset / sigma)^2 of its used samples (nan: none)


def arclength(points: np.ndarray) -> np.ndarray:
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]


@dataclass(frozen=True, slots=True)
class PolylineFrame:
    """A densely sampled polyline ``points (B, 2)`` ready for projections, computed once per
    line: its arclength ``s_m (B,)``, unit tangents ``(B, 2)`` and a KD-tree over its points."""

    points: np.ndarray
    s_m: np.ndarray
    tangents: np.ndarray
    tree: cKDTree


def polyline_frame(line: np.ndarray) -> PolylineFrame:
    tan = np.gradient(line, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    return PolylineFrame(line, arclength(line), tan, cKDTree(line))


def project_on_frame(points: np.ndarray, frame: PolylineFrame) -> tuple[np.ndarray, np.ndarray]:
    """``project_on_polyline`` on a line prepared by ``polyline_frame``."""
    _, i = frame.tree.query(points)
    rel = points - frame.points[i]
    tan = frame.tangents[i]
    s = frame.s_m[i] + (rel * tan).sum(1)
    d = tan[:, 0] * rel[:, 1] - tan[:, 1] * rel[:, 0]
    return s, d


def project_on_polyline(points: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arclength ``s`` and signed lateral offset ``d`` (left positive) of ``points (P, 2)`` on a
    densely sampled ``line (B, 2)``; beyond the ends, s continues along the end tangents."""
    return project_on_frame(points, polyline_frame(line))


def _weighted_median_per_bin(
    bins: np.ndarray, values: np.ndarray, weights: np.ndarray, n_bins: int
) -> np.ndarray:
    order = np.lexsort((values, bins))
    b, v, w = bins[order], values[order], weights[order]
    cw = np.cumsum(w)
    tot = np.bincount(b, weights=w, minlength=n_bins)
    start = np.r_[0.0, np.cumsum(tot)[:-1]]
    half = start[b] + 0.5 * tot[b]
    out = np.full(n_bins, np.nan)
    hit = cw >= half
    # first sample of each bin reaching half its weight
    idx = np.flatnonzero(hit)
    first = idx[np.r_[True, b[idx][1:] != b[idx][:-1]]]
    out[b[first]] = v[first]
    return out


def _smooth_profile(
    bins: np.ndarray, d: np.ndarray, w: np.ndarray, n_bins: int, sigma_bins: float
) -> tuple[np.ndarray, np.ndarray]:
    # both sums smoothed in one call (row by row, as two calls would)
    num, den = gaussian_filter1d(
        np.stack(
            [
                np.bincount(bins, weights=w * d, minlength=n_bins),
                np.bincount(bins, weights=w, minlength=n_bins),
            ]
        ),
        sigma_bins,
        axis=1,
        mode="nearest",
    )
    prof = np.where(den > 1e-12, num / np.maximum(den, 1e-12), np.nan)
    good = np.isfinite(prof)
    if good.any() and not good.all():
        x = np.arange(n_bins)
        prof = np.interp(x, x[good], prof[good])
    return prof, den


def _grow_backbone(
    lines: Sequence[np.ndarray],
    gates: np.ndarray,
    spacing: float,
    weights: np.ndarray,
    anchored: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """The backbone of a group: grown (``_grow_from_seed``) from the member most others agree
    with (x weight). Returns the backbone and the index of its seed member."""
    pts = np.concatenate(lines)
    own = np.repeat(np.arange(len(lines)), [len(p) for p in lines])
    tree = cKDTree(pts)
    seed = int(np.argmax(_consensus(pts, own, gates, len(lines), tree) * weights))
    keep_seed = anchored is not None and bool(anchored[seed])
    return _grow_from_seed(lines, gates, spacing, seed, keep_seed, tree, own, np.ones(len(lines), bool)), seed


def _grow_from_seed(
    lines: Sequence[np.ndarray],
    gates: np.ndarray,
    spacing: float,
    seed: int,
    keep_seed: bool,
    tree: cKDTree,
    own: np.ndarray,
    active: np.ndarray,
) -> np.ndarray:
    """Member ``seed``'s line prolonged at either end by the contiguous part of the ``active``
    member that runs on past it furthest (the member must be within its gate of the backbone
    near that end): partial overlaps chain, branches do not jump. The backbone is smoothed,
    except a ``keep_seed`` (the map's fused line in an incremental update: smoothing it again
    at every update would flatten curves a little more each time). ``tree``: a KD-tree over all
    lines' points, ``own`` their member."""
    backbone = lines[seed]
    keep_seed = keep_seed and len(backbone) >= 2
    n_before = 0
    used = {seed}
    near_end = 3.0 * spacing
    for _ in range(2 * len(lines)):
        if len(backbone) < 2:
            break
        # the members near either end (not yet used), projected on the backbone all at once
        cands_per_end = [
            sorted(
                {
                    int(own[h])
                    for h in tree.query_ball_point(backbone[-1 if end else 0], near_end + float(gates.max()))
                    if active[own[h]]
                }
                - used
            )
            for end in (0, 1)
        ]
        if not any(len(lines[k]) >= 2 for k in (*cands_per_end[0], *cands_per_end[1])):
            break
        frame = polyline_frame(backbone)
        total = frame.s_m[-1]
        projected = _project_members(lines, sorted(set(cands_per_end[0]) | set(cands_per_end[1])), frame)
        best = None  # (reach, end, points, member)
        for end, cands in enumerate(cands_per_end):
            for k in cands:
                if len(lines[k]) < 2:
                    continue
                s, d = projected[k]
                close = np.abs(d) <= gates[k]
                cand = np.flatnonzero(
                    close & ((s >= total - near_end) & (s <= total) if end else (s <= near_end) & (s >= 0))
                )
                if not len(cand):
                    continue
                i0 = int(cand[np.argmax(s[cand])] if end else cand[np.argmin(s[cand])])
                fwd = i0 + 1 < len(s) and (s[i0 + 1] > s[i0]) == bool(end)
                idx = np.arange(i0 + 1, len(s)) if fwd else np.arange(i0 - 1, -1, -1)
                beyond = s[idx] > total if end else s[idx] < 0
                run = idx[: int(np.argmin(beyond)) if not beyond.all() else len(idx)]
                if len(run) < 2:
                    continue
                reach = len(run) * spacing
                if best is None or reach > best[0]:
                    best = (reach, end, lines[k][run], k)
        if best is None:
            break
        _, end, ext, k = best
        used.add(k)
        backbone = np.vstack([backbone, ext]) if end else np.vstack([ext[::-1], backbone])
        n_before += 0 if end else len(ext)
    if keep_seed:
        return _extend_straight(_smooth_around(backbone, n_before, len(lines[seed]), spacing), 3.0, spacing)
    backbone = resample_polyline(backbone, spacing)
    if len(backbone) >= 5:
        # smoothed with point-reflected ends (a straight line stays straight and keeps its
        # length), then prolonged straight so that the members' ends project inside it
        backbone = resample_polyline(smooth_point_reflected(backbone, 2.0 / spacing), spacing)
    return _extend_straight(backbone, 3.0, spacing)


def _project_members(
    lines: Sequence[np.ndarray], members: Sequence[int], frame: PolylineFrame
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``project_on_frame`` of the lines of ``members`` (of at least 2 points), in one query."""
    members = [k for k in members if len(lines[k]) >= 2]
    if not members:
        return {}
    s, d = project_on_frame(np.concatenate([lines[k] for k in members]), frame)
    cuts = np.cumsum([len(lines[k]) for k in members])[:-1]
    return dict(zip(members, zip(np.split(s, cuts), np.split(d, cuts), strict=True), strict=True))


def smooth_point_reflected(points: np.ndarray, sigma_samples: float) -> np.ndarray:
    """Gaussian smoothing along a polyline (x and y, ``sigma_samples`` in samples) with its ends
    point-reflected: a straight line stays straight, keeps its ends and its length, and a curve
    is not pulled in at its ends."""
    pad = int(np.ceil(3 * sigma_samples))
    head = 2 * points[0] - points[1 : pad + 1][::-1]
    tail = 2 * points[-1] - points[-pad - 1 : -1][::-1]
    padded = np.vstack([head, points, tail])
    smooth = gaussian_filter1d(padded, sigma_samples, axis=0, mode="nearest")  # x and y, column by column
    return smooth[len(head) : len(head) + len(points)]


def _smooth_around(backbone: np.ndarray, start: int, count: int, spacing: float) -> np.ndarray:
    """``backbone`` with its rows ``[start, start + count)`` (the anchored seed) as they are and
    the prolongations on either side smoothed (2 m Gaussian, rows about ``spacing`` apart)."""
    out = backbone.copy()
    if len(backbone) > count:
        sm = np.column_stack(
            [gaussian_filter1d(backbone[:, i], 2.0 / spacing, mode="nearest") for i in (0, 1)]
        )
        out[:start] = sm[:start]
        out[start + count :] = sm[start + count :]
    return resample_polyline(out, spacing)


def _extend_straight(line: np.ndarray, length_m: float, spacing: float) -> np.ndarray:
    """``line`` prolonged by ``length_m`` along its end tangents (over 2 m) at both ends."""
    if len(line) < 3:
        return line
    k = min(max(int(2.0 / spacing), 1), len(line) - 1)
    t0 = line[0] - line[k]
    t1 = line[-1] - line[-1 - k]
    t0 /= max(float(np.linalg.norm(t0)), 1e-12)
    t1 /= max(float(np.linalg.norm(t1)), 1e-12)
    q = np.arange(spacing, length_m + 1e-9, spacing)[:, None]
    return np.vstack([line[0] + q[::-1] * t0, line, line[-1] + q * t1])


def _consensus(
    pts: np.ndarray, own: np.ndarray, gates: np.ndarray, n: int, tree: cKDTree | None = None
) -> np.ndarray:
    """Per member: over its samples, how many other members pass within the gate (the member
    most others agree with seeds the backbone, not the longest stray one). ``tree``: a KD-tree
    over ``pts`` if the caller has one."""
    if n == 1:
        return np.ones(1)
    return np.asarray(_agreement(pts, own, gates, n, tree).sum(axis=1)).ravel() + 1e-3 * np.bincount(
        own, minlength=n
    )


def _agreement(
    pts: np.ndarray, own: np.ndarray, gates: np.ndarray, n: int, tree: cKDTree | None = None
) -> csc_matrix:
    """``(n, n)`` sparse: entry (i, j) the number of member i's samples with a sample of member
    j within i's gate."""
    rows, cols = [], []
    for a, b, dist in neighbour_pairs(pts, own, float(gates.max()), tree):
        ok = dist <= gates[own[a]]  # (sample, other member) within the sample's member gate, once
        uniq = _unique_ints(a[ok] * n + own[b[ok]])
        rows.append(own[uniq // n])
        cols.append(uniq % n)
    if not rows:
        return csc_matrix((n, n))
    r, c = np.concatenate(rows), np.concatenate(cols)
    return csc_matrix((np.ones(len(r)), (r, c)), shape=(n, n))  # duplicates summed


def _unique_ints(values: np.ndarray) -> np.ndarray:
    """``np.unique`` of an integer array by one sort (faster here than its hash table; timsort,
    "stable", as the values come in runs: pairs by KD-tree leaf)."""
    srt = np.sort(values, kind="stable")
    return srt[np.r_[True, srt[1:] != srt[:-1]]] if len(srt) else srt


def _runs_per_member(mask: np.ndarray, own: np.ndarray) -> tuple[list[int], list[int], list[int]]:
    """The runs of True in a 1-D ``mask`` over all members' samples (``own``: their member,
    ascending), cut where one member's samples end: each run's member and its [start, stop)
    among that member's samples, in sample order."""
    first = np.r_[True, own[1:] != own[:-1]]
    last = np.r_[own[1:] != own[:-1], True]
    starts = np.flatnonzero(mask & (first | ~np.r_[False, mask[:-1]]))
    stops = np.flatnonzero(mask & (last | ~np.r_[mask[1:], False])) + 1
    member = own[starts]
    member_start = np.flatnonzero(first)[np.searchsorted(own[first], member)]
    return member.tolist(), (starts - member_start).tolist(), (stops - member_start).tolist()


def _straight_axis(
    lines: Sequence[np.ndarray],
    gates: np.ndarray,
    sigma: np.ndarray,
    weights: np.ndarray,
    spacing: float,
    params: TopologyParams,
) -> tuple[np.ndarray, int, np.ndarray]:
    """Backbone of a short straight element (a stop line; a trip's instance is a view of all or
    part of it): the robust weighted principal axis of the members' samples. It starts from the
    chord of the member most others agree with; then IRLS with Tukey's biweight (c =
    ``TUKEY_C_SIGMAS``) twice over: per member on its RMS distance to the axis in units of its
    sigma (an instance that crosses at an angle, bends away or runs on into something else is
    rejected as a whole: its samples near the crossing would tilt the axis), and per sample on
    the distance in sigmas; weights 1 / sigma^2, then the weighted centroid and principal
    direction of what is kept. Unlike backbone growth (``_grow_backbone``, which follows partial
    views of long lines) a member running on past the others does not prolong it. The axis spans the kept samples plus
    3 m at both ends (the members' ends then project inside it).

    Returns the backbone (rows ``spacing`` apart), the seed member and the members kept (bool)."""
    n = len(lines)
    pts = np.concatenate(lines)
    own = np.repeat(np.arange(n), [len(p) for p in lines])
    seed = int(np.argmax(_consensus(pts, own, gates, n) * weights))
    ref = lines[seed]
    axis = ref[-1] - ref[0]
    if float(np.linalg.norm(axis)) < 1e-6:  # a degenerate seed: the direction of all samples
        axis = np.linalg.eigh(np.cov((pts - pts.mean(0)).T))[1][:, -1]
    axis = axis / np.linalg.norm(axis)
    centre = ref.mean(0)
    cnt = np.maximum(np.bincount(own, minlength=n), 1)
    w0 = weights[own]
    w = w0
    kept = np.ones(n, bool)
    for _ in range(params.IRLS_ITERATIONS):
        z = ((pts - centre) @ np.array([-axis[1], axis[0]])) / sigma[own]
        z_member = np.sqrt(np.bincount(own, weights=z**2, minlength=n) / cnt)
        u_member = z_member / params.TUKEY_C_SIGMAS
        u = z / params.TUKEY_C_SIGMAS
        w_new = (
            w0
            * np.where(np.abs(u) < 1.0, (1.0 - u**2) ** 2, 0.0)
            * np.where(u_member < 1.0, (1.0 - u_member**2) ** 2, 0.0)[own]
        )
        if w_new.sum() <= 0:
            break
        w, kept = w_new, u_member < 1.0
        centre = (w[:, None] * pts).sum(0) / w.sum()
        rel = pts - centre
        new = np.linalg.eigh((w[:, None] * rel).T @ rel)[1][:, -1]
        axis = new if float(new @ axis) >= 0 else -new
    s = (pts - centre) @ axis
    s_kept = s[w > 0] if (w > 0).any() else s
    q = np.arange(float(s_kept.min()) - 3.0, float(s_kept.max()) + 3.0 + 1e-9, spacing)
    return centre + q[:, None] * axis, seed, kept


def _member_lines(
    members: Sequence[Member], params: TopologyParams, spacing: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """Per member: lateral sigma, weight 1 / sigma^2, gate, its line resampled every
    ``spacing`` and whether it is an anchored map line."""
    sigma = np.array([m.sigma_m for m in members])
    gates = np.array([params.gate_m(sg, sg) for sg in sigma])
    lines = [resample_polyline(np.asarray(m.instance.points_xy_world, float), spacing) for m in members]
    anchored = np.array([m.trip_key == MAP_MEMBER_KEY for m in members])
    return sigma, 1.0 / sigma**2, gates, lines, anchored


def fuse_lines(
    members: Sequence[Member],
    element_type: ElementType,
    params: TopologyParams,
    backbone_seed: tuple[np.ndarray, int] | None = None,
) -> list[FusedInstance]:
    """A group of line members -> fused polylines (usually one; a gap longer than
    ``MAX_GAP_M`` splits). Shapes: each member's ``points_xy_world (M, 2)`` in metres.

    Types in ``params.WHOLE_ELEMENT_TYPES`` (short and straight: stop lines) take a robust
    straight axis as backbone (``_straight_axis``); a member it rejects is an outlier of the
    element (it neither shapes nor prolongs it), not a piece of another one.

    ``backbone_seed``: the backbone and its seed member, if the caller grew it (``fuse_group``)."""
    spacing = 0.5 * params.BIN_M
    sigma, w_member, gate, lines, anchored = _member_lines(members, params, spacing)
    whole = element_type in params.WHOLE_ELEMENT_TYPES
    fits = np.ones(len(members), bool)  # members whose samples speak for the geometry
    if backbone_seed is not None:
        backbone, seed = backbone_seed
    elif whole:
        backbone, seed, fits = _straight_axis(lines, gate, sigma, w_member, spacing, params)
    else:
        backbone, seed = _grow_backbone(lines, gate, spacing, w_member, anchored if anchored.any() else None)
    if len(backbone) < 3:
        return []
    # an anchored seed's own vertices are the output where it reaches (no re-interpolation drift)
    anchor_xy = np.asarray(members[seed].instance.points_xy_world, float) if anchored[seed] else None
    # 1. all member samples on the backbone
    points = np.concatenate(lines)
    own = np.repeat(np.arange(len(lines)), [len(p) for p in lines])
    frame = polyline_frame(backbone)
    s_b = frame.s_m
    s, d = project_on_frame(points, frame)
    # only samples alongside the backbone (within the association window of it) speak for its
    # profile: in a group chained through splits and merges the other lanes may outnumber it
    on_backbone = (s >= -spacing) & (s <= s_b[-1] + spacing) & (np.abs(d) <= params.WINDOW_GATES * gate[own])
    fit = on_backbone & fits[own]
    s0 = float(s.min())
    bins = np.floor((s - s0) / params.BIN_M).astype(np.int64)
    n_bins = int(bins.max()) + 1
    w0 = w_member[own]
    sig = sigma[own]
    # 2. robust weighted profile: weighted median, then Tukey IRLS on the smoothed profile
    if not fit.any():
        return []
    mu = _weighted_median_per_bin(bins[fit], d[fit], w0[fit], n_bins)
    ok = np.isfinite(mu)
    mu = np.interp(np.arange(n_bins), np.flatnonzero(ok), mu[ok])
    r = d - mu[bins]
    scale = max(1.4826 * float(np.median(np.abs(r[fit]))), 1e-3)
    c = params.TUKEY_C_SIGMAS * np.maximum(sig, scale)
    sm_bins = params.SMOOTH_SIGMA_M / params.BIN_M
    w = w0
    for _ in range(params.IRLS_ITERATIONS):
        u = r / c
        w = w0 * np.where((np.abs(u) < 1.0) & fit, (1.0 - u**2) ** 2, 0.0)
        if w.sum() <= 0:
            w = w0
        mu, _ = _smooth_profile(bins, d, w, n_bins, sm_bins)
        r = d - mu[bins]
    inlier = w > 0
    # 3. members: runs off the fused line are peeled off (associated again on their own: the
    #    other branch of a split, a trip that was associated by a chain but lies elsewhere);
    #    outliers: members mostly rejected where they are alongside
    n_m = len(members)
    cnt = np.bincount(own, minlength=n_m).astype(float)
    off = ~on_backbone | (np.abs(r) > gate[own])
    close_share = np.bincount(own[~off], minlength=n_m) / np.maximum(cnt, 1)
    keep_m = close_share >= params.DETACH_CLOSE_SHARE if n_m > 1 else np.ones(1, bool)
    if (
        whole
    ):  # every member observed this one element: an inconsistent one is an outlier, not another element
        keep_m = np.ones(n_m, bool)
    if not keep_m.any():
        keep_m[int(np.argmax(close_share))] = True
    detached: list[Member] = []
    min_run = max(int(params.MIN_OVERLAP_M / spacing), 2)
    # a member kept: its runs off the line; one not kept: all of it (those that fit the element)
    for k, a, b in zip(*_runs_per_member(fits[own] & (off | ~keep_m[own]), own), strict=True):
        if b - a >= min_run or not keep_m[k]:
            m = members[k]
            detached.append(
                Member(m.trip_key, m.index, replace(m.instance, points_xy_world=lines[k][a:b]), m.sigma_m)
            )
    in_share = np.bincount(own[inlier & ~off], minlength=n_m) / np.maximum(cnt, 1)
    outliers = [k for k in range(n_m) if keep_m[k] and (in_share[k] < 0.5 * close_share[k] or not fits[k])]
    use = inlier & keep_m[own] & ~off
    if not use.any():
        return []
    rejected_share = float(w_member[outliers].sum() / w_member[keep_m].sum()) if outliers else 0.0
    # 4. support, gaps and ends
    support = np.bincount(bins[use], minlength=n_bins) > 0
    idx = np.flatnonzero(support)
    cuts = np.flatnonzero(np.diff(idx) * params.BIN_M > params.MAX_GAP_M)
    spans = np.split(idx, cuts + 1)
    tan = frame.tangents
    normal = np.column_stack([-tan[:, 1], tan[:, 0]])
    centers = s0 + (np.arange(n_bins) + 0.5) * params.BIN_M
    # per-bin standard error: model (independent trips) and empirical (trip scatter)
    per_trip_bin = params.BIN_M / spacing
    w_bin = np.bincount(bins[use], weights=w[use], minlength=n_bins) / per_trip_bin
    se_model = 1.0 / np.sqrt(np.maximum(w_bin, 1e-12))
    r2 = np.bincount(bins[use], weights=(w[use] * r[use] ** 2), minlength=n_bins)
    n_bin = np.bincount(bins[use], minlength=n_bins) / per_trip_bin
    var_emp = r2 / np.maximum(np.bincount(bins[use], weights=w[use], minlength=n_bins), 1e-12)
    se_emp = np.sqrt(var_emp / np.maximum(n_bin - 1, 1))
    # an anchored map line's sigma is already its standard error, empirical scatter included:
    # with it the model error is the recursive update (the spread of two members says nothing)
    se = se_model if anchored.any() else np.maximum(se_model, np.where(n_bin >= 2, se_emp, 0.0))
    scatter = float(np.sqrt(np.mean((r[use] / sig[use]) ** 2)))
    z2_sum = np.bincount(own[use], weights=(r[use] / sig[use]) ** 2, minlength=n_m)
    z2_cnt = np.bincount(own[use], minlength=n_m)
    member_scatter2 = tuple(float(v) for v in np.where(z2_cnt > 0, z2_sum / np.maximum(z2_cnt, 1), np.nan))
    style = vote_style([members[k] for k in range(n_m) if keep_m[k]])
    out = []
    for span in spans:
        in_span = use & (bins >= span[0]) & (bins <= span[-1])
        if not in_span.any():
            continue
        s_lo, s_hi = _robust_ends(s[in_span], own[in_span], params.END_WINDOW_M)
        if s_hi - s_lo < params.BIN_M:
            continue
        q = np.arange(s_lo, s_hi, params.OUTPUT_SPACING_M)
        q = np.r_[q, s_hi] if len(q) == 0 or s_hi - q[-1] > 1e-3 else q
        base = np.column_stack([np.interp(q, s_b, backbone[:, 0]), np.interp(q, s_b, backbone[:, 1])])
        if anchor_xy is not None:
            q, base = _with_anchor_vertices(q, base, anchor_xy, frame, params.OUTPUT_SPACING_M)
        dq = np.interp(q, centers, mu)
        nx = np.interp(q, s_b, normal[:, 0])
        ny = np.interp(q, s_b, normal[:, 1])
        nn = np.maximum(np.hypot(nx, ny), 1e-12)
        line = base + np.column_stack([dq * nx / nn, dq * ny / nn])
        span_members = tuple(int(k) for k in np.unique(own[in_span]))
        gaps = np.diff(span) * params.BIN_M - params.BIN_M
        if element_type == ElementType.CENTERLINE:
            line = _orient(line, [members[k] for k in span_members], w_member[list(span_members)])
        out.append(
            FusedInstance(
                type=element_type,
                points_xy_world=line,
                style=style,
                members=span_members,
                detached=tuple(detached),
                uncertainty_m=float(np.median(se[span[0] : span[-1] + 1][support[span[0] : span[-1] + 1]])),
                scatter_ratio=scatter,
                rejected_weight_share=rejected_share,
                outlier_members=tuple(k for k in outliers if k in span_members),
                max_internal_gap_m=float(gaps.max()) if len(gaps) else 0.0,
                member_scatter2=member_scatter2,
            )
        )
    return out


def fuse_group(
    members: Sequence[Member], element_type: ElementType, params: TopologyParams
) -> tuple[list[FusedInstance], list[Member]]:
    """The lines of an associated group that one round can fuse, one ``fuse_lines`` pass per
    line: the line grown from the member most of the members left agree with and fitted to the
    members within reach of it. Every member within reach leaves the group: the ones the line
    took with their runs off it peeled off, the others whole (they wait for the next round, to
    be associated again with those pieces, as when a group gave one line per round). Members
    out of reach of every line so far give further lines. A group chained through junctions
    (centrelines: every lane runs on into the next one and turns into the crossing ones) holds
    hundreds of lines far apart; one line per round would leave most of them undone.

    Returns the instances (``members`` etc. index ``members``) and the members and pieces for
    the next round. Agreement is counted once (``_agreement``) and decremented as members
    leave; each pass touches only the members within reach of its backbone."""
    if element_type in params.WHOLE_ELEMENT_TYPES or len(members) == 1:
        fused = fuse_lines(members, element_type, params)
        if not fused and len(members) > 1:  # nothing fused: the members on their own
            return [
                _in_group(f, np.array([k]))
                for k in range(len(members))
                for f in fuse_lines([members[k]], element_type, params)
            ], []
        return fused, list(fused[0].detached) if fused else []
    n = len(members)
    spacing = 0.5 * params.BIN_M
    _, weights, gates, lines, anchored = _member_lines(members, params, spacing)
    pts = np.concatenate(lines)
    own = np.repeat(np.arange(n), [len(p) for p in lines])
    tree = cKDTree(pts)
    agreement = _agreement(pts, own, gates, n, tree)
    consensus = np.asarray(agreement.sum(axis=1)).ravel() + 1e-3 * np.bincount(own, minlength=n)
    reach = params.WINDOW_GATES * float(gates.max())
    active = np.ones(n, bool)
    out: list[FusedInstance] = []
    detached: list[Member] = []

    def leave(gone: np.ndarray) -> None:
        active[gone] = False
        consensus[:] -= np.asarray(agreement[:, gone].sum(axis=1)).ravel()

    while active.any():
        seed = int(np.argmax(np.where(active, consensus * weights, -np.inf)))
        backbone = _grow_from_seed(lines, gates, spacing, seed, bool(anchored[seed]), tree, own, active)
        near = cKDTree(backbone).sparse_distance_matrix(tree, reach, output_type="ndarray")["j"]
        within_reach = _unique_ints(own[near])
        local = np.union1d(within_reach[active[within_reach]], [seed])
        fused = (
            fuse_lines(
                [members[k] for k in local],
                element_type,
                params,
                (backbone, int(np.searchsorted(local, seed))),
            )
            if len(backbone) >= 3
            else []
        )
        if not fused:  # nothing alongside its backbone: the seed on its own
            leave(np.array([seed]))
            out.extend(
                _in_group(f, np.array([seed])) for f in fuse_lines([members[seed]], element_type, params)
            )
            continue
        # every member within reach was offered this line: the ones it took leave with their
        # pieces off it peeled, the others leave whole, to be associated again with those pieces
        leave(local)
        out.extend(_in_group(f, local) for f in fused)
        detached.extend(piece for piece in fused[0].detached if len(piece.instance.points_xy_world) >= 2)
    return out, detached


def absorb_pieces(
    pieces: Sequence[Member], lines_xy: Sequence[np.ndarray], params: TopologyParams
) -> tuple[list[tuple[int, int]], list[Member]]:
    """Pieces peeled off in one round that are views of a line already fused: a piece with at
    least ``DETACH_CLOSE_SHARE`` of its samples within its gate of one fused line, parallel to
    it, joins that line's support (its geometry, fitted to many trips, stays); its runs of at
    least ``MIN_OVERLAP_M`` off the line (it runs on past the line's end) stay pieces. Lines of a
    group are fused pass after pass in one round (``fuse_group``), so a piece peeled off an
    early line finds the element it belongs to already fused by a later one; associated again
    on its own it would be a second, shorter copy. Returns ``(piece index, line index)`` of the
    absorbed and the pieces left."""
    if not pieces or not lines_xy:
        return [], list(pieces)
    spacing = params.SAMPLE_SPACING_M
    fused = sample_lines(lines_xy, spacing)
    smp = sample_members(pieces, spacing)
    gate = np.array([params.gate_m(m.sigma_m, m.sigma_m) for m in pieces])[smp.owner]
    dist, nearest = cKDTree(fused.points_xy).query(smp.points_xy, distance_upper_bound=float(gate.max()))
    ok = np.isfinite(dist)
    nearest = np.where(ok, nearest, 0)
    parallel = np.abs((smp.tangents * fused.tangents[nearest]).sum(1)) >= np.cos(params.MAX_ANGLE_RAD)
    line_of = np.where(ok & (dist <= gate) & parallel, fused.owner[nearest], -1)
    min_run = max(int(round(params.MIN_OVERLAP_M / spacing)), 2)
    absorbed, rest = [], []
    for k, piece in enumerate(pieces):
        mine = smp.owner == k
        labels = line_of[mine]
        hits = labels[labels >= 0]
        best = int(np.bincount(hits).argmax()) if len(hits) else -1
        if best < 0 or np.mean(labels == best) < params.DETACH_CLOSE_SHARE:
            rest.append(piece)
            continue
        absorbed.append((k, best))
        points = smp.points_xy[mine]
        for _, a, b in zip(*_runs_per_member(labels != best, np.zeros(len(labels), np.int64)), strict=True):
            if b - a >= min_run:
                rest.append(
                    Member(
                        piece.trip_key,
                        piece.index,
                        replace(piece.instance, points_xy_world=points[a:b]),
                        piece.sigma_m,
                    )
                )
    return absorbed, rest


def _in_group(fused: FusedInstance, local: np.ndarray) -> FusedInstance:
    """``fused`` (fitted to the members ``local`` of a group) with its member indices in the group."""
    n_group = int(local.max()) + 1
    scatter2 = np.full(n_group, np.nan)
    scatter2[local[: len(fused.member_scatter2)]] = fused.member_scatter2
    return replace(
        fused,
        members=tuple(int(local[k]) for k in fused.members),
        outlier_members=tuple(int(local[k]) for k in fused.outlier_members),
        member_scatter2=tuple(float(v) for v in scatter2),
    )


def _with_anchor_vertices(
    q: np.ndarray, base: np.ndarray, anchor_xy: np.ndarray, backbone: PolylineFrame, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Output stations ``q`` and base points: inside the span of the anchored seed its own
    vertices (a curve sampled again at other stations would be cut a little inside at every
    update), the regular stations beyond it. ``backbone``: the fused line's backbone
    (``polyline_frame``)."""
    s_v, _ = project_on_frame(anchor_xy, backbone)
    inside = (s_v >= q[0]) & (s_v <= q[-1])
    if inside.sum() < 2 or bool((np.diff(s_v[inside]) <= 0).any()):
        return q, base
    lo, hi = float(s_v[inside][0]), float(s_v[inside][-1])
    before = q < lo - 0.5 * spacing_m
    after = q > hi + 0.5 * spacing_m
    return (
        np.r_[q[before], s_v[inside], q[after]],
        np.vstack([base[before], anchor_xy[inside], base[after]]),
    )


def _orient(line: np.ndarray, members: Sequence[Member], weights: np.ndarray) -> np.ndarray:
    """Directed elements (centrelines) point the way most of their members' weight points."""
    if len(line) < 2:
        return line
    tangent = line[-1] - line[0]
    vote = 0.0
    for m, w in zip(members, weights, strict=True):
        p = np.asarray(m.instance.points_xy_world, float)
        if len(p) >= 2:
            vote += w * np.sign(float(np.dot(p[-1] - p[0], tangent)))
    return line[::-1].copy() if vote < 0 else line


def vote_style(members: Sequence[Member]) -> DividerStyle | None:
    """The style most observations gave (unknown only when none said otherwise)."""
    votes: Counter = Counter()
    for m in members:
        st = m.instance.style
        if st is not None and st != DividerStyle.UNKNOWN:
            votes[st] += max(m.instance.n_observations, 1)
    if votes:
        return votes.most_common(1)[0][0]
    return DividerStyle.UNKNOWN if any(m.instance.style is not None for m in members) else None


def _corresponding_outlines(polys: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Outlines of one element -> ``(stack (n, m, 2), used (K,) member indices)``: counter-clockwise,
    each rolled to the cyclic shift closest to the reference (the median-area outline); only the
    outlines with the reference's vertex count (the same outline model) are stacked."""
    ccw = [p if polygon_area(p) >= 0 else p[::-1] for p in polys]
    areas = np.array([abs(polygon_area(p)) for p in ccw])
    ref = ccw[int(np.argsort(areas)[len(areas) // 2])]
    m = len(ref)
    roll = (np.arange(m)[:, None] + np.arange(m)[None, :]) % m  # row k: np.roll(p, -k) as an index
    stack, used = [], []
    for i, p in enumerate(ccw):
        if len(p) != m:
            continue
        shifts = p[roll]
        stack.append(shifts[int(np.argmin(np.linalg.norm(shifts - ref[None], axis=-1).sum(1)))])
        used.append(i)
    return np.stack(stack), np.array(used, dtype=np.intp)


def _tukey_mean_per_vertex(
    stack: np.ndarray, sigma: np.ndarray, params: TopologyParams
) -> tuple[np.ndarray, np.ndarray]:
    """Robust weighted mean per vertex of corresponding outlines ``stack (k, m, 2)``: started from
    the per-vertex median, IRLS with Tukey's biweight on the vertex distance (c =
    ``TUKEY_C_SIGMAS`` x the larger of the member's ``sigma (k,)`` and the group's robust scatter),
    weights 1 / sigma^2. Returns the outline ``(m, 2)`` and the final weights ``(k, m)``."""
    w0 = 1.0 / sigma**2
    fused = np.median(stack, axis=0)
    w = np.broadcast_to(w0[:, None], stack.shape[:2])
    if len(stack) < 2:
        return fused, w
    for _ in range(params.IRLS_ITERATIONS):
        dist = np.linalg.norm(stack - fused[None], axis=-1)  # (k, m)
        scale = 1.4826 * float(np.median(dist)) / 1.1774  # median of a 2-D Gaussian norm = 1.1774 sigma
        u = dist / (params.TUKEY_C_SIGMAS * np.maximum(sigma[:, None], scale))
        w = w0[:, None] * np.where(u < 1.0, (1.0 - u**2) ** 2, 0.0)
        tot = w.sum(0)
        fused = np.where(
            tot[:, None] > 0, (w[..., None] * stack).sum(0) / np.maximum(tot, 1e-12)[:, None], fused
        )
    return fused, w


def fuse_polygons(
    members: Sequence[Member], element_type: ElementType, params: TopologyParams
) -> FusedInstance:
    """A group of polygon members -> one outline (crosswalks, road markings).

    Vertices are put in correspondence (``_corresponding_outlines``; members with another vertex
    count still count as support but do not shape it). A trip's outline is off by a translation
    (its perception bias for the element, its pose error there: heavy-tailed across trips, and
    the trips' sigmas do not say which trip is off) plus noise per vertex. So the two are fused
    apart: the *shape*, the outlines with their vertex centroid removed, by a robust weighted
    mean per vertex (``_tukey_mean_per_vertex``: with a few consistent members their mean, not
    the median, which has 1.35 x the variance for three Gaussian copies); the *position* by the
    median of the members' centroids (per coordinate, unweighted: the trips' sigmas did not
    predict which trip's crosswalk is off, measured on the urban and roundabout benchmark
    worlds). Members rejected (Tukey, as above, on their distance to the fused outline) at half
    of their vertices or more are the outliers (``rejected_weight_share``)."""
    polys = [np.asarray(m.instance.points_xy_world, float) for m in members]
    n = len(polys)
    stack, used = _corresponding_outlines(polys)
    sig = np.array([m.sigma_m for m in members])
    w0 = 1.0 / sig[used] ** 2
    centre = stack.mean(axis=1)  # (k, 2) each outline's vertex centroid
    shape, _ = _tukey_mean_per_vertex(stack - centre[:, None], sig[used], params)
    fused = shape + np.median(centre, axis=0)
    # members' agreement with the result: one Tukey pass on their vertex distances
    dist = np.linalg.norm(stack - fused[None], axis=-1)
    scale = 1.4826 * float(np.median(dist)) / 1.1774
    inlier = dist < params.TUKEY_C_SIGMAS * np.maximum(sig[used][:, None], scale)
    res = stack - fused[None]
    kept = inlier.mean(1) > 0.5  # members used at most of their vertices
    spread = 1.4826 * float(np.median(np.abs(res[inlier]))) if inlier.any() else 0.0
    n_kept = int(kept.sum())
    se = max(
        float(np.sqrt(1.0 / np.sum(w0[kept] if kept.any() else w0))), spread / np.sqrt(max(n_kept - 1, 1))
    )
    z = res[inlier] / sig[used][:, None, None].repeat(res.shape[1], 1)[inlier]
    scatter = float(np.sqrt(np.mean(z**2))) if n_kept >= 3 and len(z) else 1.0
    outliers = tuple(int(used[k]) for k in np.flatnonzero(~kept)) if len(used) >= 2 else ()
    w_all = 1.0 / sig**2
    return FusedInstance(
        type=element_type,
        points_xy_world=fused,
        style=vote_style(members),
        members=tuple(range(n)),
        detached=(),
        uncertainty_m=se,
        scatter_ratio=scatter,
        rejected_weight_share=float(w_all[list(outliers)].sum() / w_all.sum()) if outliers else 0.0,
        outlier_members=outliers,
        max_internal_gap_m=0.0,
    )


def merge_twins(
    fused: Sequence[tuple[FusedInstance, tuple[Member, ...]]], params: TopologyParams
) -> list[tuple[FusedInstance, tuple[Member, ...]]]:
    """One element fused twice, once per round, becomes one line. A member within reach of a
    round's line that the line did not take (less than ``DETACH_CLOSE_SHARE`` of it lies along
    it: a trip's centreline that follows a lane and then turns off) waits for the next round
    whole; the members that waited with it fuse there into a *twin*, the lane again plus the
    turn. Lines are visited from the best supported (trips, then length): a line with at least
    ``DETACH_CLOSE_SHARE`` of its samples within the association gate of one line already kept,
    parallel to it, is that line again; its trips join that line's support (its geometry,
    fitted to more trips, stays) and its runs of at least ``MIN_OVERLAP_M`` off it (the turn)
    stay lines of their own. ``fused``: (instance, its members) of one type."""
    n = len(fused)
    if n < 2:
        return list(fused)
    spacing = params.SAMPLE_SPACING_M
    smp = sample_lines([f.points_xy_world for f, _ in fused], spacing)
    sigma = np.array([float(np.median([m.sigma_m for m in mem])) for _, mem in fused])
    trips = [len({m.trip_key for m in mem}) for _, mem in fused]
    length = np.bincount(smp.owner, minlength=n)
    first_sample = np.r_[0, np.cumsum(length)[:-1]]
    gate_max = params.gate_m(float(sigma.max()), float(sigma.max()))
    pairs = cKDTree(smp.points_xy).query_pairs(gate_max, output_type="ndarray")
    pairs = pairs[smp.owner[pairs[:, 0]] != smp.owner[pairs[:, 1]]]
    a, b = (
        np.r_[pairs[:, 0], pairs[:, 1]],
        np.r_[pairs[:, 1], pairs[:, 0]],
    )  # sample a of one line near sample b of another
    dist = np.linalg.norm(smp.points_xy[a] - smp.points_xy[b], axis=1)
    la, lb = smp.owner[a], smp.owner[b]
    line_pairs, pair_of = np.unique(la * n + lb, return_inverse=True)  # the gate once per pair of lines
    gate = np.array([params.gate_m(float(sigma[p // n]), float(sigma[p % n])) for p in line_pairs.tolist()])[
        pair_of
    ]
    parallel = np.abs((smp.tangents[a] * smp.tangents[b]).sum(1)) >= np.cos(params.MAX_ANGLE_RAD)
    near = (dist <= gate) & parallel
    a, la, lb, dist = a[near], la[near], lb[near], dist[near]
    by_line = np.argsort(la, kind="stable")
    starts = np.searchsorted(la[by_line], np.arange(n + 1))
    kept = np.zeros(n, bool)
    merged_into: dict[int, list[Member]] = {}
    pieces: list[tuple[FusedInstance, tuple[Member, ...]]] = []
    min_run = max(int(round(params.MIN_OVERLAP_M / spacing)), 2)
    for k in sorted(range(n), key=lambda i: (-trips[i], -length[i])):
        rows = by_line[starts[k] : starts[k + 1]]
        rows = rows[kept[lb[rows]]]
        if not len(rows):
            kept[k] = True
            continue
        # per sample of line k: the nearest kept line within the gate
        order = np.lexsort((dist[rows], a[rows]))
        rows = rows[order]
        first = np.r_[True, a[rows][1:] != a[rows][:-1]]
        label = np.full(int(length[k]), -1)
        label[a[rows][first] - first_sample[k]] = lb[rows][first]
        hits = label[label >= 0]
        best = int(np.bincount(hits).argmax())
        # a line one trip saw is no evidence that another is the same element
        if np.mean(label == best) < params.DETACH_CLOSE_SHARE or trips[best] < params.MIN_SUPPORT_TRIPS:
            kept[k] = True
            continue
        f, mem = fused[k]
        merged_into.setdefault(best, []).extend(mem)
        points = smp.points_xy[first_sample[k] : first_sample[k] + length[k]]
        for _, lo, hi in zip(*_runs_per_member(label != best, np.zeros(len(label), np.int64)), strict=True):
            if hi - lo >= min_run:
                pieces.append((replace(f, points_xy_world=points[lo:hi]), mem))
    out = []
    for k, (f, mem) in enumerate(fused):
        if kept[k]:
            seen = {(m.trip_key, m.index) for m in mem}
            more = {
                (m.trip_key, m.index): m for m in merged_into.get(k, ()) if (m.trip_key, m.index) not in seen
            }
            out.append((f, (*mem, *more.values())))
    return out + pieces
