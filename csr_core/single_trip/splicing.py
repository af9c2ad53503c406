"""Splicing a track's observations into one trip-level instance (paper III-C).

Lines: every observation point (world frame) is projected on a backbone (arclength s, signed
lateral offset d): the vehicle's own path while the element was seen when the element runs
along it (any curvature: curves, roundabouts), else the principal axis of the points (stop
lines, lines across the road), refined by a second pass on the first result. The lateral
profile d(s) is estimated per arclength bin by a median with outlier rejection (ghost points,
mis-assignments), smoothed by a Gaussian kernel along s, and turned back into a polyline. Gaps up to ``SPLICE_MAX_GAP_M`` (dashes, missed frames) are spanned, so a dashed
divider stays one instance; longer gaps split the instance. A Gaussian kernel along arclength
stands in for Qiao et al.'s Catmull-Rom fit: same role (a smooth curve through denoised
control points), closed form and vectorised.

Polygons (crosswalk, road marking): observations clipped by the BEV range are left out when
whole ones exist; the vertices of the others are brought into the order of the median-area
one and averaged by a per-vertex median.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.ndimage import gaussian_filter1d, label
from scipy.spatial import cKDTree

from csr_core.single_trip.noise import middle_sorted
from csr_core.single_trip.params import SingleTripParams

_INT16_MAX = int(np.iinfo(np.int16).max)
_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)  # _cluster_sd: cells touching by a side or a corner
_MAX_GROWTH_CURVATURE = 0.1  # grow_backbone follows bends of at least 10 m radius (as _extend_ends)
_BEND_MIN_RADIUS_M = 6.0  # no marking turns tighter than a car's turning circle
_BEND_SHAPE_TOL_M = 0.5  # an observation continuing a bend lies on its circle this close


@dataclass(frozen=True, slots=True)
class SplicedLine:
    points_xy_world: np.ndarray  # (M, 2)
    lateral_residuals_m: np.ndarray  # (R,) of inlier observation points
    along_residuals_m: np.ndarray  # (A,) of observed element ends (not BEV cuts)
    observations: np.ndarray  # (m,) observations (indices) that support the instance


def _arclength(points: np.ndarray) -> np.ndarray:
    out = np.zeros(max(len(points), 1))
    if len(points) > 1:
        step = points[1:] - points[:-1]  # np.diff(points, axis=0) without its per-call cost
        np.cumsum(np.hypot(step[:, 0], step[:, 1]), out=out[1:])
    return out


def _run_starts(ids: np.ndarray) -> np.ndarray:
    """Indices (R,) where the runs of equal consecutive ``ids`` start (the first is 0)."""
    change = np.empty(max(len(ids), 1), dtype=bool)
    change[0] = True
    np.not_equal(ids[1:], ids[:-1], out=change[1:len(ids)])
    return np.flatnonzero(change)


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D array, without its per-call overhead (called thousands of times
    per trip on small arrays)."""
    n = len(values)
    v = middle_sorted(values)
    return 0.5 * float(v[(n - 1) // 2] + v[n // 2])


def _unit_tangents(backbone: np.ndarray) -> np.ndarray:
    """Unit tangents (B, 2) of a polyline (B >= 2): central differences, one-sided at the ends
    (as ``np.gradient``)."""
    tan = np.empty_like(backbone, dtype=float)
    tan[1:-1] = 0.5 * (backbone[2:] - backbone[:-2])
    tan[0] = backbone[1] - backbone[0]
    tan[-1] = backbone[-1] - backbone[-2]
    norm = np.hypot(tan[:, 0], tan[:, 1])
    return tan / np.maximum(norm, 1e-12)[:, None]


class _Geometry(NamedTuple):
    """A backbone of B points with its arclength, unit tangents and KD-tree (``_geometry``)."""

    columns: np.ndarray  # (4, B) x, y, unit tangent x, y: contiguous rows (the cheapest to gather)
    arclength: np.ndarray  # (B,)
    tree: cKDTree | None  # None: built by ``_nearest`` when a query needs it


def _geometry(backbone: np.ndarray, with_tree: bool = False) -> _Geometry:
    """A backbone (B, 2) with its arclength and unit tangents, computed once per backbone (the
    path guide of a track is projected on twice); ``with_tree``: and its KD-tree (a backbone
    queried by many points, the guide; most others are cheaper to query pair by pair)."""
    return _Geometry(np.concatenate([backbone.T, _unit_tangents(backbone).T]), _arclength(backbone),
                     cKDTree(backbone) if with_tree else None)


#: point-backbone pairs up to which ``_nearest`` compares all pairs: a KD-tree costs two to three
#: times more below (its build and per-query overhead), the pairs' arrays leave the cache above
BRUTE_FORCE_MAX_PAIRS = 20_000


def _nearest_pairwise(points: np.ndarray, ref_x: np.ndarray, ref_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index ``(P,)`` of the nearest of the reference points (``ref_x``, ``ref_y``, (R,)) to each of
    ``points (P, 2)`` and the squared distance to it, from all pairs."""
    dx = points[:, 0, None] - ref_x[None, :]
    dy = points[:, 1, None] - ref_y[None, :]
    dx *= dx
    dy *= dy
    dx += dy
    i = dx.argmin(1)
    return i, dx[np.arange(len(points)), i]


def _nearest(points: np.ndarray, ref_x: np.ndarray, ref_y: np.ndarray, tree: cKDTree | None) -> np.ndarray:
    """Index ``(P,)`` of the nearest of the reference points (``ref_x``, ``ref_y``, (R,)) to each
    of ``points (P, 2)``: all pairs while there are at most ``BRUTE_FORCE_MAX_PAIRS``, else the
    KD-tree ``tree`` (built here when None)."""
    if len(points) * len(ref_x) <= BRUTE_FORCE_MAX_PAIRS:
        return _nearest_pairwise(points, ref_x, ref_y)[0]
    if tree is None:
        tree = cKDTree(np.column_stack([ref_x, ref_y]))
    return tree.query(points)[1]


def within_of_any(points: np.ndarray, others: np.ndarray, radius_m: float) -> np.ndarray:
    """``(P,)`` whether each of ``points (P, 2)`` lies within ``radius_m`` of one of ``others (Q, 2)``
    (at most; all pairs or a KD-tree, as ``_nearest``)."""
    if not len(others):
        return np.zeros(len(points), dtype=bool)
    if len(points) * len(others) <= BRUTE_FORCE_MAX_PAIRS:
        return _nearest_pairwise(points, others[:, 0], others[:, 1])[1] <= radius_m * radius_m
    return cKDTree(others).query(points, distance_upper_bound=radius_m + 1e-9)[0] <= radius_m


def _nearest_within(points: np.ndarray, ref: np.ndarray, bound_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Index ``(P,)`` of the nearest of ``ref (R, 2)`` to each of ``points (P, 2)`` and whether it
    lies closer than ``bound_m`` (strictly, as a KD-tree's ``distance_upper_bound``); the index
    means nothing where it does not. All pairs or a KD-tree, as ``_nearest``."""
    if len(points) * len(ref) <= BRUTE_FORCE_MAX_PAIRS:
        i, d2 = _nearest_pairwise(points, ref[:, 0], ref[:, 1])
        return i, d2 < bound_m * bound_m
    dist, i = cKDTree(ref).query(points, distance_upper_bound=bound_m)
    return i, np.isfinite(dist)


@functools.lru_cache(maxsize=16)
def _gaussian_kernel(sigma_bins: float, truncate: float = 4.0) -> np.ndarray:
    """The kernel of ``scipy.ndimage.gaussian_filter1d`` (same radius and normalisation)."""
    radius = int(truncate * sigma_bins + 0.5)
    x = np.arange(-radius, radius + 1, dtype=float)
    w = np.exp(-0.5 * (x / sigma_bins) ** 2)
    w /= w.sum()
    w.setflags(write=False)  # cached: shared by every caller
    return w


def _smooth_zero_padded(values: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``gaussian_filter1d(values, mode="constant")`` for a kernel from ``_gaussian_kernel``
    (one ``np.convolve``: a tenth of the call overhead on short arrays)."""
    r = len(kernel) // 2
    return np.convolve(values, kernel, mode="full")[r:r + len(values)]


def resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:
    s = _arclength(points)
    if s[-1] <= 0:
        return points[:1].copy()
    n = max(int(math.ceil(s[-1] / spacing_m)) + 1, 2)
    q = np.arange(n) * (float(s[-1]) / (n - 1))  # np.linspace(0, s[-1], n) without its per-call cost
    q[-1] = s[-1]
    return np.column_stack([np.interp(q, s, points[:, 0]), np.interp(q, s, points[:, 1])])


def _project(points: np.ndarray, geom: _Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Arclength s and signed lateral offset d (left positive) of points (P, 2) on a densely
    sampled backbone (``_geometry``): from its nearest point (KD-tree), along its tangent."""
    x, y, tan_x, tan_y = geom.columns
    i = _nearest(points, x, y, geom.tree)
    rel_x, rel_y = points[:, 0] - x[i], points[:, 1] - y[i]
    t_x, t_y = tan_x[i], tan_y[i]
    s = geom.arclength[i] + rel_x * t_x + rel_y * t_y
    d = t_x * rel_y - t_y * rel_x
    return s, d


def _binned_median(bins: np.ndarray, values: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-bin median (the upper middle value; NaN for an empty bin) and counts (n_bins,).

    Values sorted, then stably by bin: the order of ``np.lexsort((values, bins))`` up to ties
    of equal values, at about half its cost (numpy's stable sort of 16-bit keys is a radix
    sort; lexsort's indirect merge sort is slow on the large tracks)."""
    by_value = np.argsort(values)
    bin_of = bins[by_value]
    if n_bins <= _INT16_MAX:
        bin_of = bin_of.astype(np.int16)
    order = by_value[np.argsort(bin_of, kind="stable")]
    counts = np.bincount(bins, minlength=n_bins)
    starts = counts.cumsum() - counts
    med = np.full(n_bins, np.nan)
    ok = counts > 0
    med[ok] = values[order[starts[ok] + counts[ok] // 2]]
    return med, counts


def _extend_ends(line: np.ndarray, length_m: float, spacing_m: float, curvature_m: float = 10.0) -> np.ndarray:
    """The polyline prolonged at both ends by ``length_m`` along a circular arc with the
    curvature of its last ``curvature_m`` (a straight line where that is unknown)."""
    if len(line) < 3:
        return line
    s = _arclength(line)
    if s[-1] < 1e-6:
        return line
    q = np.arange(spacing_m, length_m + 1e-9, spacing_m)

    def arc(end: np.ndarray, before: np.ndarray, span: float, head_prev: float) -> np.ndarray:
        head = math.atan2(float(end[1] - before[1]), float(end[0] - before[0]))
        turn = head - head_prev
        kappa = math.atan2(math.sin(turn), math.cos(turn)) / max(span, 1e-6)
        kappa = min(max(kappa, -0.1), 0.1)  # radius at least 10 m
        th = head + kappa * q
        if abs(kappa) < 1e-6:
            return end + q[:, None] * np.array([math.cos(head), math.sin(head)])
        return end + np.column_stack([(np.sin(th) - math.sin(head)) / kappa, -(np.cos(th) - math.cos(head)) / kappa])

    def heading(i: int, j: int) -> float:
        return math.atan2(float(line[j, 1] - line[i, 1]), float(line[j, 0] - line[i, 0]))

    n = len(line)
    span = min(curvature_m, s[-1] / 2)
    # tail: heading over the last segment vs the heading span metres earlier
    i_span = max(int(np.searchsorted(s, s[-1] - span)) - 1, 0)
    tail = arc(line[-1], line[-2], s[-1] - s[i_span + 1] if i_span + 1 < n - 1 else span,
               heading(i_span, i_span + 1))
    # head: the same on the reversed line
    j_span = min(int(np.searchsorted(s, span)) + 1, n - 1)
    head = arc(line[0], line[1], s[j_span - 1] if j_span - 1 > 0 else span, heading(j_span, j_span - 1))
    return np.concatenate([head[::-1], line, tail])


def _walk_in(bbx: list[float], bby: list[float], step: int, start: int, span_m: float) -> int:
    """The index of the first point of a polyline (two lists of floats) at least ``span_m``
    from point ``start``, walking inward by ``step`` (-1 from the tail, +1 from the head); an
    end point where the line is shorter."""
    n = len(bbx)
    k = min(max(start + step, 0), n - 1)
    while 0 < k < n - 1 and math.hypot(bbx[start] - bbx[k], bby[start] - bby[k]) < span_m:
        k += step
    return k


def _end_tangent(bbx: list[float], bby: list[float], at_tail: bool, tangent_m: float, bends: bool = True
                 ) -> tuple[float, float, float, float, float] | None:
    """End point, unit tangent and curvature (x, y, tx, ty, kappa) at the tail (or head) of a
    polyline given as two lists of floats: the tangent over its last ``tangent_m``, the
    curvature (1/m, positive turning left in the direction of the tangent) from the heading
    change between that chord and the ``tangent_m`` before it (0 where the line is shorter, or
    without ``bends``: the chord's direction, no curvature); None where degenerate."""
    end, step = (len(bbx) - 1, -1) if at_tail else (0, 1)
    bx, by = bbx[end], bby[end]
    j = _walk_in(bbx, bby, step, end, tangent_m)
    tx, ty = bx - bbx[j], by - bby[j]
    tn = math.hypot(tx, ty)
    if tn < 1e-9:
        return None
    tx, ty = tx / tn, ty / tn
    if not bends:
        return bx, by, tx, ty, 0.0
    kappa = 0.0
    i = _walk_in(bbx, bby, step, j, tangent_m)
    px, py = bbx[j] - bbx[i], bby[j] - bby[i]
    pn = math.hypot(px, py)
    if pn >= tangent_m / 2:
        turn = math.atan2(px * ty - py * tx, px * tx + py * ty)  # from the chord before to the end chord
        kappa = min(max(turn / (0.5 * (tn + pn)), -_MAX_GROWTH_CURVATURE), _MAX_GROWTH_CURVATURE)
        # on an arc the tangent at the end is turned from the chord by half the chord's turning
        # (the chord spans a dash gap on a dashed line: metres)
        c, s = math.cos(0.5 * kappa * tn), math.sin(0.5 * kappa * tn)
        tx, ty = c * tx - s * ty, s * tx + c * ty
    return bx, by, tx, ty, kappa


def _tail_points(bbx: list[float], bby: list[float], at_tail: bool, span_m: float) -> np.ndarray:
    """The points of a backbone (two lists of floats) within ``span_m`` of its tail (or head)."""
    end, step = (len(bbx) - 1, -1) if at_tail else (0, 1)
    j = _walk_in(bbx, bby, step, end, span_m)
    lo, hi = (j, end) if at_tail else (end, j)
    return np.column_stack([bbx[lo:hi + 1], bby[lo:hi + 1]])


def _bend_continuation(tail_xy: np.ndarray, obs_xy: np.ndarray, beyond: np.ndarray, end_xy: np.ndarray,
                       max_gap_m: float) -> np.ndarray:
    """``beyond`` (indices of an observation's points past a backbone end) if they continue the
    backbone round a bend: one circle fits the backbone's last points ``tail_xy`` and them
    within ``_BEND_SHAPE_TOL_M`` (the observation bends with the line: a piece of another element
    crossing it, or of a parallel one, does not), turning no tighter than ``_BEND_MIN_RADIUS_M``,
    with the nearest of them within ``max_gap_m`` of the end ``end_xy``. Empty if not."""
    if len(beyond) < 2 or len(tail_xy) < 3:
        return beyond[:0]
    cand = obs_xy[beyond]
    if float(np.min(np.hypot(cand[:, 0] - end_xy[0], cand[:, 1] - end_xy[1]))) > max_gap_m:
        return beyond[:0]
    pts = np.vstack([tail_xy, cand])
    centre, r2 = kasa_circle(pts)
    if not np.isfinite(r2) or r2 <= _BEND_MIN_RADIUS_M ** 2:
        return beyond[:0]
    residual = np.abs(np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1]) - math.sqrt(r2))
    return beyond if float(residual.max()) <= _BEND_SHAPE_TOL_M else beyond[:0]


def kasa_circle(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) least-squares circle through ``pts (P, 2)``, fitted about their mean
    (x^2 + y^2 + D x + E y + F = 0): its centre and squared radius (not positive, or not finite,
    when the points are collinear)."""
    mu = pts.mean(0)
    q = pts - mu
    a = np.column_stack([q, np.ones(len(q))])
    (d, e, f), *_ = np.linalg.lstsq(a, -(q * q).sum(1), rcond=None)
    return mu - 0.5 * np.array([d, e]), float(0.25 * (d * d + e * e) - f)


def grow_backbone(points_w: np.ndarray, obs_ends: np.ndarray, min_step_m: float = 0.5, tangent_m: float = 4.0,
                  lateral_gate_m: float = 1.0, lateral_gate_slope: float = 0.15, max_gap_m: float = 15.0,
                  follow_bends: bool = False) -> np.ndarray:
    """An ordered polyline covering an element of any shape from its observations (each an
    ordered polyline, in time order): the first one, extended at either end by the points of
    later ones that lie beyond it along its end tangent (over the last ``tangent_m``) and near
    that tangent line. Observations are oriented like the previous one first.

    ``follow_bends`` (dashed lines: a guide line through a junction bends between its dashes,
    and the straight tangent misses the next dash by metres): the tangent line becomes the arc
    with the curvature of the last two ``tangent_m``, and an observation that is not near it
    still continues the backbone when one circle fits it and the backbone's last
    ``2 tangent_m`` (``_bend_continuation``), its nearest point within ``max_gap_m``."""
    polys = [points_w[a:b + 1] for a, b in obs_ends]
    ref = None
    bbx: list[float] = []  # the backbone as two lists of floats: grown at both ends, walked point by point
    bby: list[float] = []
    tangents: dict[bool, tuple[float, float, float, float, float] | None] = {}  # per end, until the backbone grows
    for p in polys:
        d = p[-1] - p[0]
        if ref is not None and float(d @ ref) < 0:
            p = p[::-1]
            d = -d
        if float(np.hypot(d[0], d[1])) > 0.5:
            ref = d
        if len(bbx) < 2:
            bbx, bby = p[:, 0].tolist(), p[:, 1].tolist()
            tangents.clear()
            continue
        px, py = p[:, 0], p[:, 1]
        (x_first, y_first), (x_last, y_last) = p[0].tolist(), p[-1].tolist()
        for at_tail in (True, False):
            if at_tail not in tangents:
                tangents[at_tail] = _end_tangent(bbx, bby, at_tail, tangent_m, follow_bends)
            tangent = tangents[at_tail]
            if tangent is None:
                continue
            bx, by, tx, ty, kappa = tangent
            # its end points first: most observations do not reach beyond this end
            if max((x_first - bx) * tx + (y_first - by) * ty, (x_last - bx) * tx + (y_last - by) * ty) <= min_step_m:
                continue
            proj = (px - bx) * tx + (py - by) * ty
            lat = np.abs((py - by) * tx - (px - bx) * ty - 0.5 * kappa * proj * proj)  # off the arc (parabola)
            beyond = np.flatnonzero((proj > min_step_m) & (lat <= lateral_gate_m + lateral_gate_slope * proj))
            if not len(beyond) and follow_bends:
                beyond = _bend_continuation(_tail_points(bbx, bby, at_tail, 2 * tangent_m), p,
                                            np.flatnonzero(proj > min_step_m), np.array([bx, by]), max_gap_m)
            if len(beyond):
                ext = beyond[np.argsort(proj[beyond])]
                if at_tail:
                    bbx.extend(px[ext].tolist())
                    bby.extend(py[ext].tolist())
                else:
                    bbx[:0] = px[ext[::-1]].tolist()
                    bby[:0] = py[ext[::-1]].tolist()
                tangents.clear()
    return np.column_stack([bbx, bby]) if bbx else points_w[:1]


def smooth_polyline(points: np.ndarray, spacing_m: float, sigma_m: float) -> np.ndarray:
    """Resampled at ``spacing_m`` and Gaussian-smoothed along arclength (ends kept in place)."""
    r = resample_polyline(points, spacing_m)
    if len(r) < 3 or sigma_m <= 0:
        return r
    out = gaussian_filter1d(r, sigma_m / spacing_m, axis=0, mode="nearest")
    out[0], out[-1] = r[0], r[-1]
    return out


def _principal_backbone(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """A straight backbone along the principal axis of the points, covering them."""
    mu = points.mean(0)
    _, _, vt = np.linalg.svd(points - mu, full_matrices=False)
    axis = vt[0]
    proj = (points - mu) @ axis
    q = np.arange(proj.min() - 1.0, proj.max() + 1.0 + spacing_m, spacing_m)
    return mu + q[:, None] * axis


def _cluster_sd(s: np.ndarray, d: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """Labels (P,) of the elements in a track's points in backbone coordinates (arclength s,
    lateral d): occupied cells (``SPLICE_BIN_M`` x ``SPLICE_CLUSTER_D_M``) joined across up to
    ``SPLICE_MAX_GAP_M`` along s (dash gaps, missed frames) and one cell across d. Two lines side
    by side (a track that took in a neighbour through a ramp or a ghost) come out apart."""
    sb = np.floor((s - s.min()) / params.SPLICE_BIN_M).astype(np.int64)
    db = np.floor((d - d.min()) / params.SPLICE_CLUSTER_D_M).astype(np.int64)
    grid = np.zeros((int(sb.max()) + 1, int(db.max()) + 1), dtype=bool)
    grid[sb, db] = True
    reach = max(int(params.SPLICE_MAX_GAP_M / params.SPLICE_BIN_M / 2), 1)
    # dilation by 2 reach + 1 cells along s (a running count: binary_dilation's cost is per call)
    n_s = grid.shape[0]
    csum = np.zeros((n_s + 1, grid.shape[1]), dtype=np.int32)
    np.cumsum(grid, axis=0, out=csum[1:])
    i = np.arange(n_s)
    grown = (csum[np.minimum(i + reach + 1, n_s)] - csum[np.maximum(i - reach, 0)]) > 0
    labels, _ = label(grown, structure=_EIGHT_CONNECTED)
    return labels[sb, db] - 1


def _binned_profile(s: np.ndarray, d: np.ndarray, bin_m: float) -> tuple[np.ndarray, int, np.ndarray]:
    """Arclength bins (P,) of width ``bin_m`` from the smallest s, their number and the per-bin
    median of d (the first step of ``_fit_profile``, shared with ``_mixture_sigma``)."""
    bins = np.floor((s - s.min()) / bin_m).astype(np.int64)
    n_bins = int(bins.max()) + 1
    med, _ = _binned_median(bins, d, n_bins)
    return bins, n_bins, med


def _fit_profile(s: np.ndarray, d: np.ndarray, obs_id: np.ndarray, geom: _Geometry, params: SingleTripParams,
                 binned: tuple[np.ndarray, int, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray] | None:
    """Robust lateral profile d(s) of one element: per-bin median with outlier rejection,
    Gaussian smoothing along s, ends from the observations. Returns (line (M, 2), inlier mask,
    s_lo, s_hi, fitted d at each point) or None. ``binned``: ``_binned_profile(s, d)`` when
    already computed."""
    bin_m = params.SPLICE_BIN_M
    s0 = s.min()
    bins, n_bins, med = binned if binned is not None else _binned_profile(s, d, bin_m)
    dev = np.abs(d - med[bins])
    sigma = max(1.4826 * _median(dev), 0.02)
    inl = dev <= params.SPLICE_OUTLIER_SIGMAS * sigma
    bins_inl = bins[inl]
    w = np.bincount(bins_inl, minlength=n_bins).astype(float)
    sum_d = np.bincount(bins_inl, weights=d[inl], minlength=n_bins)
    kernel = _gaussian_kernel(params.SPLICE_SMOOTH_SIGMA_M / bin_m)
    num = _smooth_zero_padded(sum_d, kernel)
    den = _smooth_zero_padded(w, kernel)
    good = den > 1e-6
    if not good.any():
        return None
    centers = s0 + (np.arange(n_bins) + 0.5) * bin_m
    d_s = np.interp(centers, centers[good], num[good] / den[good])
    s_lo, s_hi = _robust_ends(s[inl], obs_id[inl])
    if s_hi - s_lo < bin_m / 2:
        return None
    q = np.arange(s_lo, s_hi, params.SPLICE_OUTPUT_SPACING_M)
    q = np.append(q, s_hi) if len(q) == 0 or s_hi - q[-1] > 1e-3 else q
    s_b, (x, y, tan_x, tan_y) = geom.arclength, geom.columns
    dq = np.interp(q, centers, d_s)
    bx, by = np.interp(q, s_b, x), np.interp(q, s_b, y)
    tx, ty = np.interp(q, s_b, tan_x), np.interp(q, s_b, tan_y)
    nn = np.maximum(np.hypot(tx, ty), 1e-12)
    line = np.column_stack([bx - dq * ty / nn, by + dq * tx / nn])
    return line, inl, s_lo, s_hi, np.interp(s, centers, d_s)


@functools.lru_cache(maxsize=8)
def _guide_geometry(path_bytes: bytes, dtype: str, n: int, bin_m: float, extension_m: float) -> _Geometry | None:
    """The geometry of the guide of a splice: the vehicle path ``(n, 2)`` (given by its bytes, to
    be cached) resampled and prolonged at both ends; None when too short. Tracks seen over the
    same frames share their path (a quarter of them): the last few guides are kept."""
    path = np.frombuffer(path_bytes, dtype=dtype).reshape(n, 2)
    guide = _extend_ends(resample_polyline(path, bin_m), extension_m, bin_m)
    if len(guide) < 3:
        return None
    geom = _geometry(guide, with_tree=True)
    for shared in (geom.columns, geom.arclength):  # cached: shared by every caller
        shared.setflags(write=False)
    return geom


def splice_line(points_w: np.ndarray, obs_id: np.ndarray, obs_ends: np.ndarray, end_free: np.ndarray,
                guide_xy: np.ndarray | None, params: SingleTripParams,
                original: np.ndarray | None = None, follow_bends: bool = False) -> list[SplicedLine]:
    """Observations of one track -> one smoothed polyline per element found in it (usually one).

    ``points_w (P, 2)`` all observation points (world), ``obs_id (P,)`` their observation,
    ``obs_ends (n_obs, 2)`` indices of each observation's first and last point, ``end_free
    (n_obs, 2)`` whether those are element ends seen inside the BEV range (not cuts by the
    range): only those give along-track residuals; ``original (P,)`` marks the points as sent
    (not inserted by densification): only those give lateral residuals. ``guide_xy`` the vehicle path while the track
    was seen: the backbone when the element runs along it (curves, roundabouts), else the
    principal axis of the points, refined by a second pass on the first result.
    ``follow_bends``: a backbone grown from the observations follows the element round bends
    across gaps (``grow_backbone``): for dashed lines, whose gaps are the dash gaps; a continuous
    element that leaves the end tangent is a branch, not the same line.
    """
    bin_m = params.SPLICE_BIN_M
    if original is None:
        original = np.ones(len(points_w), dtype=bool)
    guide_geom = None
    if guide_xy is not None and len(guide_xy) >= 2:
        guide_xy = np.ascontiguousarray(guide_xy)
        guide_geom = _guide_geometry(guide_xy.tobytes(), guide_xy.dtype.str, len(guide_xy), bin_m,
                                     params.SPLICE_GUIDE_EXTENSION_M)
    if guide_geom is not None:
        # separate the elements of the track along the path; each element is then spliced on
        # the path if it runs along it, else on its own shape
        ends = unique_ids(obs_ends.ravel())  # the along/across test needs only the observation ends
        s_ends, _ = _project(points_w[ends], guide_geom)
        if _runs_along(s_ends, points_w[ends], obs_id[ends]) < params.SPLICE_ALONG_GUIDE_MIN:
            # the track runs across the path (a dashed line crossed in a junction): the gaps
            # between its pieces are along its own shape, not along the path
            return _splice_own_shape(points_w, np.arange(len(points_w)), obs_id, obs_ends, end_free, params,
                                     original, follow_bends)
        s, d = _project(points_w, guide_geom)
        labels = _cluster_sd(s, d, params)
        out = []
        groups: list[tuple[np.ndarray, tuple[np.ndarray, int, np.ndarray] | None]] = []  # points, their bins
        for lab in np.unique(labels):
            sel = np.flatnonzero(labels == lab)
            binned = _binned_profile(s[sel], d[sel], bin_m) if len(sel) > 10 else None
            if binned is not None and _mixture_sigma(d[sel], binned) > params.SPLICE_MIXTURE_SIGMA_M:
                sub = split_modes(s[sel], d[sel], params)
                groups.extend((sel[sub == k], None) for k in np.unique(sub[sub >= 0]))
            else:
                groups.append((sel, binned))
        for sel, binned in groups:
            if n_distinct(obs_id[sel]) < params.TRACK_MIN_FRAMES:
                continue
            if _runs_along(s[sel], points_w[sel], obs_id[sel]) >= params.SPLICE_ALONG_GUIDE_MIN:
                out.extend(_splice_on(points_w, sel, s[sel], d[sel], guide_geom, False, obs_id, obs_ends, end_free, params,
                                      original, binned))
            else:
                out.extend(_splice_own_shape(points_w, sel, obs_id, obs_ends, end_free, params, original, follow_bends))
        return out
    return _splice_own_shape(points_w, np.arange(len(points_w)), obs_id, obs_ends, end_free, params, original,
                             follow_bends)


def _mixture_sigma(d: np.ndarray, binned: tuple[np.ndarray, int, np.ndarray]) -> float:
    """Robust spread (m) of lateral offsets ``d`` around their per-bin median (``binned``, from
    ``_binned_profile``): large for a cluster that mixes elements (a Y where a connector leaves
    a lane)."""
    bins, _, med = binned
    return 1.4826 * _median(np.abs(d - med[bins]))


def split_modes(s: np.ndarray, d: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """Labels (P,) separating elements that share cells (a Y): per arclength bin the lateral
    offsets are split into modes at gaps wider than ``SPLICE_MODE_GAP_M``; modes are chained
    along arclength to the nearest chain within ``SPLICE_MODE_GATE_M`` (a 1-D tracker along s);
    a mode that finds no chain starts one. -1: points of modes too small to count."""
    bin_m = params.SPLICE_BIN_M
    bins = np.floor((s - s.min()) / bin_m).astype(np.int64)
    order = np.lexsort((d, bins))
    b_sorted, d_sorted = bins[order], d[order]
    first = np.ones(1, dtype=bool)
    new_bin = np.concatenate([first, b_sorted[1:] != b_sorted[:-1]])
    gap = np.concatenate([first, np.diff(d_sorted) > params.SPLICE_MODE_GAP_M])
    mode_start = np.flatnonzero(new_bin | gap)
    mode_end = np.append(mode_start[1:], len(order))
    mode_bin = b_sorted[mode_start]
    # within a bin d is sorted, so each mode is a sorted run: its median is its middle element(s)
    mode_d = 0.5 * (d_sorted[(mode_start + mode_end - 1) // 2] + d_sorted[(mode_start + mode_end) // 2])
    mode_n = mode_end - mode_start
    max_gap_bins = params.SPLICE_MAX_GAP_M / bin_m
    chains_d: list[float] = []
    chains_bin: list[int] = []
    mode_chain = np.full(len(mode_start), -1)
    # the chaining walks the modes one by one: on plain Python numbers (numpy scalars cost ten times more)
    for m, (size, at_bin, offset) in enumerate(zip(mode_n.tolist(), mode_bin.tolist(), mode_d.tolist(), strict=True)):
        if size < 2:
            continue
        best, best_dist = -1, params.SPLICE_MODE_GATE_M
        for c in range(len(chains_d)):
            if at_bin - chains_bin[c] > max_gap_bins or chains_bin[c] == at_bin:
                continue
            dist = abs(offset - chains_d[c])
            if dist < best_dist:
                best, best_dist = c, dist
        if best < 0:
            chains_d.append(offset)
            chains_bin.append(at_bin)
            best = len(chains_d) - 1
        else:
            chains_d[best] = offset
            chains_bin[best] = at_bin
        mode_chain[m] = best
    labels_sorted = np.repeat(mode_chain, mode_n)
    labels = np.empty(len(s), dtype=np.int64)
    labels[order] = labels_sorted
    return labels


def _runs_along(s: np.ndarray, points: np.ndarray, obs_id: np.ndarray) -> float:
    """Median over observations of |arclength span on the path| / chord: 1 along, 0 across."""
    order = (np.arange(len(obs_id)) if len(obs_id) < 2 or not bool((obs_id[1:] < obs_id[:-1]).any())
             else np.argsort(obs_id, kind="stable"))
    sorted_ids = obs_id[order]
    start = _run_starts(sorted_ids)
    end = np.append(start[1:], len(order)) - 1
    first, last = order[start], order[end]
    step = points[last] - points[first]
    chord = np.sqrt(step[:, 0] * step[:, 0] + step[:, 1] * step[:, 1])  # np.linalg.norm(step, axis=1)
    ok = chord > 2.0
    if not ok.any():
        return 1.0
    return _median(np.abs(s[last] - s[first])[ok] / chord[ok])


def _splice_own_shape(points_w: np.ndarray, sel: np.ndarray, obs_id: np.ndarray, obs_ends: np.ndarray,
                      end_free: np.ndarray, params: SingleTripParams, original: np.ndarray,
                      follow_bends: bool = False) -> list[SplicedLine]:
    """Splice the points ``sel`` on a backbone grown from their own observations (any shape),
    or their principal axis, refined by a second pass; clustered on it first."""
    bin_m = params.SPLICE_BIN_M
    pts = points_w[sel]
    ids = obs_id[sel]
    starts = _run_starts(ids)
    ends = np.append(starts[1:], len(ids)) - 1
    short = float((pts.max(0) - pts.min(0)).max()) < params.SPLICE_STRAIGHT_BELOW_M  # np.ptp
    grown = pts[:1] if short else grow_backbone(pts, np.column_stack([starts, ends]), max_gap_m=params.SPLICE_MAX_GAP_M,
                                                   follow_bends=follow_bends)
    if len(grown) >= 2 and _arclength(grown)[-1] > 2 * bin_m:
        backbone = smooth_polyline(grown, bin_m / 2, params.SPLICE_BACKBONE_SMOOTH_M)
    else:
        backbone = _principal_backbone(pts, bin_m / 2)
    if len(backbone) < 3:
        return []
    geom = _geometry(backbone)
    s, d = _project(pts, geom)
    labels = _cluster_sd(s, d, params)
    out = []
    for lab in np.unique(labels):
        sub = np.flatnonzero(labels == lab)
        if n_distinct(ids[sub]) < params.TRACK_MIN_FRAMES:
            continue
        out.extend(_splice_on(points_w, sel[sub], s[sub], d[sub], geom, True, obs_id, obs_ends, end_free, params,
                              original))
    return out


def _splice_on(points_w: np.ndarray, sel: np.ndarray, s_sel: np.ndarray, d_sel: np.ndarray,
               geom: _Geometry, refine: bool, obs_id: np.ndarray, obs_ends: np.ndarray, end_free: np.ndarray,
               params: SingleTripParams, original: np.ndarray,
               binned: tuple[np.ndarray, int, np.ndarray] | None = None) -> list[SplicedLine]:
    """One element (points ``sel`` with backbone coordinates) -> its SplicedLine (or none).
    ``binned``: ``_binned_profile(s_sel, d_sel)`` when already computed."""
    bin_m = params.SPLICE_BIN_M
    fit = _fit_profile(s_sel, d_sel, obs_id[sel], geom, params, binned)
    if fit is not None and refine and fit[3] - fit[2] >= 2 * bin_m:
        bb2 = resample_polyline(fit[0], bin_m / 2)
        if len(bb2) >= 3:
            geom2 = _geometry(bb2)
            s2, d2 = _project(points_w[sel], geom2)
            fit2 = _fit_profile(s2, d2, obs_id[sel], geom2, params)
            if fit2 is not None:
                fit, s_sel, d_sel = fit2, s2, d2
    if fit is None:
        return []
    line, inl, s_lo, s_hi, d_fit = fit
    # lateral residuals against the fitted profile; along-track: observation ends that are
    # element ends against the instance ends (both in backbone arclength)
    lat = (d_sel - d_fit)[inl & original[sel]]
    s_all = np.full(len(points_w), np.nan)
    s_all[sel[inl]] = s_sel[inl]
    s_first, s_last = s_all[obs_ends[:, 0]], s_all[obs_ends[:, 1]]
    lo_first = s_first <= s_last
    s_lo_obs = np.where(lo_first, s_first, s_last)
    s_hi_obs = np.where(lo_first, s_last, s_first)
    free_lo = np.where(lo_first, end_free[:, 0], end_free[:, 1])
    free_hi = np.where(lo_first, end_free[:, 1], end_free[:, 0])
    win = params.NOISE_END_WINDOW_M
    ok_lo = np.isfinite(s_lo_obs) & free_lo & (np.abs(s_lo_obs - s_lo) <= win)
    ok_hi = np.isfinite(s_hi_obs) & free_hi & (np.abs(s_hi_obs - s_hi) <= win)
    along_res = np.concatenate([s_lo_obs[ok_lo] - s_lo, s_hi_obs[ok_hi] - s_hi])
    obs = unique_ids(obs_id[sel[inl]])
    return [SplicedLine(line, lat, along_res, obs)]


def runs_along_observations(line_xy: np.ndarray, points_w: np.ndarray, obs_id: np.ndarray, obs: np.ndarray,
                            max_angle_rad: float, near_m: float, window_m: float) -> list[np.ndarray]:
    """The parts of the spliced ``line_xy`` that run along its own observations ``obs`` (values of
    ``obs_id``, the observation of each of the points ``points_w``); the whole line when all of
    it does.

    A splice is tangent to what it was spliced from. Where it crosses its observations it joined
    pieces of different elements: in a junction a dashed divider's dashes, extended along their
    chords to bridge the gaps, reach the dashes of a divider that crosses it, and the splice runs
    on from one to the other, or across from the end of one dash to the end of another.
    Observation segments within ``near_m`` of the line count as along it or across it (more than
    ``max_angle_rad`` to the line's direction where they pass it; segment by segment, so a curved
    observation of a curved element runs along, and the leg of an observation that leaves the
    line, a boundary turning a corner, is not near it). A vertex is cut when, within
    ``window_m`` of arclength either side, more observed length runs across than along; a stretch
    with no observation near it (the gap between two dashes) is kept. A part left with less than
    ``window_m`` of observed length along it (summed over the observations) is dropped: it only
    joined two cut places."""
    if len(line_xy) < 2 or len(points_w) < 2:
        return [line_xy]
    # the segments between consecutive points of one observation of ``obs``
    of_part = np.zeros(int(obs_id.max()) + 1, dtype=bool)
    of_part[obs] = True
    start = np.flatnonzero(of_part[obs_id[:-1]] & (obs_id[:-1] == obs_id[1:]))
    if len(start) == 0:
        return [line_xy]
    seg = points_w[start + 1] - points_w[start]
    seg_len = np.sqrt(seg[:, 0] * seg[:, 0] + seg[:, 1] * seg[:, 1])
    nearest, near = _nearest_within(points_w[start] + 0.5 * seg, line_xy, near_m)
    if not near.any():
        return [line_xy]
    seg, seg_len, nearest = seg[near], seg_len[near], nearest[near]
    at = np.minimum(nearest, len(line_xy) - 2)
    tangent = line_xy[at + 1] - line_xy[at]
    cos = np.abs((seg * tangent).sum(1)) / np.maximum(seg_len * np.hypot(tangent[:, 0], tangent[:, 1]), 1e-12)
    across = cos < np.cos(max_angle_rad)
    if not across.any():
        return [line_xy]
    # along and across length per vertex, summed over +-window_m of arclength
    arc = _arclength(line_xy)
    lo = np.searchsorted(arc, arc - window_m, side="left")
    hi = np.searchsorted(arc, arc + window_m, side="right")
    n = len(line_xy)
    cum_across = np.r_[0.0, np.cumsum(np.bincount(nearest, seg_len * across, n))]
    cum_along = np.r_[0.0, np.cumsum(np.bincount(nearest, seg_len * ~across, n))]
    bad = (cum_across[hi] - cum_across[lo]) > (cum_along[hi] - cum_along[lo])
    # the runs left; one with (almost) nothing observed along it joined two cut places
    edges = np.flatnonzero(np.diff(np.r_[0, (~bad).astype(np.int8), 0]))
    return [line_xy[a:b] for a, b in zip(edges[::2], edges[1::2], strict=True)
            if b - a >= 2 and cum_along[b] - cum_along[a] >= window_m]


def _robust_ends(s: np.ndarray, obs_id: np.ndarray, window_m: float = 1.5) -> tuple[float, float]:
    if len(s) == 0:
        return 0.0, 0.0
    if len(obs_id) > 1 and bool((obs_id[1:] < obs_id[:-1]).any()):
        order = np.argsort(obs_id, kind="stable")
        s, obs_id = s[order], obs_id[order]
    starts = _run_starts(obs_id)
    lo = np.minimum.reduceat(s, starts)  # per observation (runs of equal ids)
    hi = np.maximum.reduceat(s, starts)
    s_lo = _median(lo[lo <= lo.min() + window_m])
    s_hi = _median(hi[hi >= hi.max() - window_m])
    return s_lo, max(s_hi, s_lo)


def unique_ids(ids: np.ndarray) -> np.ndarray:
    """``np.unique(ids)``, without the sort when ``ids`` is already non-decreasing."""
    if len(ids) < 2:
        return np.unique(ids)
    if bool((ids[1:] < ids[:-1]).any()):
        return np.unique(ids)
    return ids[_run_starts(ids)]


def n_distinct(ids: np.ndarray) -> int:
    """``len(np.unique(ids))`` without the sort when ``ids`` is already non-decreasing."""
    if len(ids) < 2:
        return len(ids)
    step = ids[1:] != ids[:-1]
    if bool((ids[1:] < ids[:-1]).any()):
        return len(np.unique(ids))
    return 1 + int(np.count_nonzero(step))


def polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    nxt = np.arange(1, len(poly) + 1) % len(poly)  # np.roll(-1) as an index
    return 0.5 * float(np.dot(x, y[nxt]) - np.dot(y, x[nxt]))


def _edge_axes(polys: list[np.ndarray], inside: list[np.ndarray]) -> np.ndarray | None:
    """The axes (2, 2) of a rectangle from its observed edges: the length-weighted mean direction
    of the outline edges whose both ends lie inside the BEV range (the element's own sides, not
    the range's cut across it), modulo a right angle (a doubled-doubled angle average); None
    without such edges."""
    sum_sin = sum_cos = 0.0
    for poly, ins in zip(polys, inside, strict=True):
        nxt = np.roll(np.arange(len(poly)), -1)
        keep = ins & ins[nxt]
        if not keep.any():
            continue
        edge = poly[nxt[keep]] - poly[keep]
        length = np.hypot(edge[:, 0], edge[:, 1])
        angle4 = 4.0 * np.arctan2(edge[:, 1], edge[:, 0])
        sum_sin += float(np.dot(length, np.sin(angle4)))
        sum_cos += float(np.dot(length, np.cos(angle4)))
    if math.hypot(sum_sin, sum_cos) < 1e-9:
        return None
    theta = 0.25 * math.atan2(sum_sin, sum_cos)
    return np.array([[math.cos(theta), math.sin(theta)], [-math.sin(theta), math.cos(theta)]])


def _robust_rectangle(polys: list[np.ndarray], headings_rad: np.ndarray, q: float = 0.02,
                      inside: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An element never seen whole (a crosswalk wider than the BEV range): the rectangle spanning
    the q..1-q quantiles of all observed outline points along its axes. The axes are those of its
    observed sides (``_edge_axes``, ``inside`` (per outline, per vertex) marking the vertices
    inside the BEV range), else the principal axes of the points: the part of a crosswalk that the
    range lets through is a strip cut at the range's angle, whose principal axes can lie anywhere
    (Karlsruhe s3, docs/single-trip.md "Session 36"). Residuals: each observation's points beyond
    the rectangle, lateral/along the vehicle heading."""
    pts = np.concatenate(polys)
    mu = pts.mean(0)
    vt = _edge_axes(polys, inside) if inside is not None else None
    if vt is None:
        _, _, vt = np.linalg.svd(pts - mu, full_matrices=False)
    proj = (pts - mu) @ vt.T
    lo, hi = np.quantile(proj, q, axis=0), np.quantile(proj, 1 - q, axis=0)
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]) @ vt + mu
    if polygon_area(corners) < 0:
        corners = corners[::-1]
    over = np.maximum(proj - hi, 0.0) + np.minimum(proj - lo, 0.0)  # (P, 2) outside distance per axis
    h = np.repeat(headings_rad, [len(p) for p in polys])
    dev = over @ vt
    along = dev[:, 0] * np.cos(h) + dev[:, 1] * np.sin(h)
    lateral = -dev[:, 0] * np.sin(h) + dev[:, 1] * np.cos(h)
    return corners, lateral, along


def splice_polygon(polys: list[np.ndarray], whole: np.ndarray, headings_rad: np.ndarray,
                   inside: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observed outlines (world) -> one outline, lateral and along residuals (vehicle heading).

    ``whole`` (n_obs,) bool: the observation is not clipped by the BEV range; ``inside`` (per
    outline, per vertex): the vertex lies inside the range (for ``_robust_rectangle``)."""
    if not whole.any():
        return _robust_rectangle(polys, headings_rad, inside=inside)
    cand = [i for i in range(len(polys)) if whole[i]]
    # consistent winding (counter-clockwise)
    signed = [polygon_area(p) for p in polys]
    ccw = [p if area >= 0 else p[::-1] for p, area in zip(polys, signed, strict=True)]
    areas = np.array([abs(signed[i] if signed[i] >= 0 else polygon_area(ccw[i])) for i in cand])
    ref_i = cand[int(np.argsort(areas)[len(areas) // 2])]
    ref = ccw[ref_i]
    m = len(ref)
    roll = (np.arange(m)[:, None] + np.arange(m)[None, :]) % m  # row k: np.roll(p, -k) as an index
    stack, heads = [], []
    for i in cand:
        p = ccw[i]
        if len(p) != m:
            continue
        shifts = p[roll]
        diff = shifts - ref[None]
        err = np.sqrt(diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]).sum(1)  # np.linalg.norm(diff, axis=-1)
        stack.append(shifts[int(np.argmin(err))])
        heads.append(headings_rad[i])
    arr = np.stack(stack)  # (n, m, 2)
    fused = np.median(arr, axis=0)
    dev = arr - fused[None]
    h = np.asarray(heads)[:, None]
    along = dev[..., 0] * np.cos(h) + dev[..., 1] * np.sin(h)
    lateral = -dev[..., 0] * np.sin(h) + dev[..., 1] * np.cos(h)
    return fused, lateral.ravel(), along.ravel()
