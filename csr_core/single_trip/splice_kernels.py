"""Compiled steps of the splicing stage (numba).

A trip has about 300 tracks, and in numpy each track's splice is 300-500 small array calls of a
few microseconds each, none of them more than a fifth of the time (docs/single-trip.md, sessions
38 and 40): the cost is the number of calls, not any one of them. Compiling one leaf saved 3 %
(session 40); these kernels compile whole steps (a projection with its nearest-point search, a
clustering with its labelling, a profile fit with its medians, ends and resampling), each one call.

Each kernel computes what the numpy code it replaced computed, in the same order, so that the
splices are the same to rounding (``tests/unit/test_splice_kernels.py`` checks them against
plain numpy and scipy). Compiled on first use and cached on disk (``cache=True``: beside this
file, or numba's user cache directory where that is read-only).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: 1.4826 x the median absolute deviation: the sigma of a normal distribution
MAD_TO_SIGMA = 1.4826
#: the window of ``robust_ends`` (m): observation ends this close to the extreme one are pooled
ROBUST_END_WINDOW_M = 1.5
#: ``grow_backbone`` follows bends of at least 10 m radius (as ``splicing._extend_ends``)
MAX_GROWTH_CURVATURE = 0.1
#: no marking turns tighter than a car's turning circle
BEND_MIN_RADIUS_M = 6.0
#: an observation continuing a bend lies on its circle this close
BEND_SHAPE_TOL_M = 0.5


@njit(cache=True)
def median(values: np.ndarray) -> float:  # pragma: no cover - compiled
    """The median of ``values`` (mean of the two middle values for an even count)."""
    v = np.sort(values)
    n = len(v)
    return 0.5 * (v[(n - 1) // 2] + v[n // 2])


@njit(cache=True)
def sort_along_wider_axis(ref_x: np.ndarray, ref_y: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:  # pragma: no cover
    """Reference points (R >= 1) sorted along their wider axis, for ``nearest_in_sorted``: (the
    axis is x, the order, the sorted coordinates along it)."""
    wide_x = ref_x.max() - ref_x.min() >= ref_y.max() - ref_y.min()
    key = ref_x if wide_x else ref_y
    order = np.argsort(key, kind="mergesort")
    return wide_x, order, key[order]


@njit(cache=True)
def nearest_in_sorted(points: np.ndarray, ref_x: np.ndarray, ref_y: np.ndarray, wide_x: bool, order: np.ndarray,
                      sorted_key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``nearest_index`` on references already sorted (``sort_along_wider_axis``)."""
    n_ref = len(ref_x)
    n = points.shape[0]
    nearest = np.empty(n, dtype=np.int64)
    dist2 = np.empty(n)
    for k in range(n):
        px, py = points[k, 0], points[k, 1]
        q = px if wide_x else py
        start = np.searchsorted(sorted_key, q)
        best, best_d2 = n_ref, np.inf
        j = start
        while j < n_ref:
            gap = sorted_key[j] - q
            if gap * gap > best_d2:
                break
            i = order[j]
            dx, dy = px - ref_x[i], py - ref_y[i]
            d2 = dx * dx + dy * dy
            if d2 < best_d2 or (d2 == best_d2 and i < best):
                best, best_d2 = i, d2
            j += 1
        j = start - 1
        while j >= 0:
            gap = q - sorted_key[j]
            if gap * gap > best_d2:
                break
            i = order[j]
            dx, dy = px - ref_x[i], py - ref_y[i]
            d2 = dx * dx + dy * dy
            if d2 < best_d2 or (d2 == best_d2 and i < best):
                best, best_d2 = i, d2
            j -= 1
        nearest[k] = best
        dist2[k] = best_d2
    return nearest, dist2


@njit(cache=True)
def nearest_index(points: np.ndarray, ref_x: np.ndarray, ref_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Index (P,) of the nearest of the reference points (``ref_x``, ``ref_y``, (R,), R >= 1) to
    each of ``points (P, 2)`` (the first of equals, as ``argmin`` over all pairs) and the squared
    distance to it. Exact: the references sorted along their wider axis, each search walks out
    from the query's place in that order until the gap along the axis alone exceeds the best
    distance (a backbone's points lie along a line: a few dozen pairs per query, not all R)."""
    wide_x, order, sorted_key = sort_along_wider_axis(ref_x, ref_y)
    return nearest_in_sorted(points, ref_x, ref_y, wide_x, order, sorted_key)


@njit(cache=True)
def project(points: np.ndarray, columns: np.ndarray, arclength: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Arclength s and signed lateral offset d (left positive) of ``points (P, 2)`` on a densely
    sampled backbone (``columns (4, B)``: x, y, unit tangent x, y; its ``arclength (B,)``): from
    its nearest point (``nearest_index``), along its tangent."""
    return project_at(points, nearest_index(points, columns[0], columns[1])[0], columns, arclength)


@njit(cache=True)
def project_at(points: np.ndarray, nearest: np.ndarray, columns: np.ndarray, arclength: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``project`` with the nearest backbone point of each point given (a KD-tree's answer)."""
    n = points.shape[0]
    s = np.empty(n)
    d = np.empty(n)
    for k in range(n):
        i = nearest[k]
        rel_x, rel_y = points[k, 0] - columns[0, i], points[k, 1] - columns[1, i]
        s[k] = arclength[i] + rel_x * columns[2, i] + rel_y * columns[3, i]
        d[k] = columns[2, i] * rel_y - columns[3, i] * rel_x
    return s, d


@njit(cache=True)
def cluster_sd(s: np.ndarray, d: np.ndarray, bin_m: float, cell_d_m: float, reach_bins: int) -> np.ndarray:  # pragma: no cover
    """Labels (P,) of the occupied cells (``bin_m`` along s x ``cell_d_m`` across) grown by
    ``reach_bins`` cells either way along s and joined where they touch by a side or a corner,
    numbered in raster order from 0 (as ``scipy.ndimage.label`` numbers them, less one)."""
    n = len(s)
    s_min, d_min = s.min(), d.min()
    sb = np.empty(n, dtype=np.int64)
    db = np.empty(n, dtype=np.int64)
    n_s = n_d = 0
    for i in range(n):
        sb[i] = int(math.floor((s[i] - s_min) / bin_m))
        db[i] = int(math.floor((d[i] - d_min) / cell_d_m))
        n_s = max(n_s, sb[i] + 1)
        n_d = max(n_d, db[i] + 1)
    occupied = np.zeros((n_s + 1, n_d), dtype=np.int32)  # running count along s
    for i in range(n):
        occupied[sb[i] + 1, db[i]] = 1
    for a in range(1, n_s + 1):
        for b in range(n_d):
            occupied[a, b] += occupied[a - 1, b]
    grown = np.zeros((n_s, n_d), dtype=np.bool_)
    for a in range(n_s):
        lo, hi = max(a - reach_bins, 0), min(a + reach_bins + 1, n_s)
        for b in range(n_d):
            grown[a, b] = occupied[hi, b] - occupied[lo, b] > 0
    labels = np.full((n_s, n_d), -1, dtype=np.int64)
    stack = np.empty(n_s * n_d, dtype=np.int64)
    n_labels = 0
    for a in range(n_s):
        for b in range(n_d):
            if not grown[a, b] or labels[a, b] >= 0:
                continue
            labels[a, b] = n_labels
            top = 0
            stack[0] = a * n_d + b
            top = 1
            while top:
                top -= 1
                ca, cb = stack[top] // n_d, stack[top] % n_d
                for na in range(max(ca - 1, 0), min(ca + 2, n_s)):
                    for nb in range(max(cb - 1, 0), min(cb + 2, n_d)):
                        if grown[na, nb] and labels[na, nb] < 0:
                            labels[na, nb] = n_labels
                            stack[top] = na * n_d + nb
                            top += 1
            n_labels += 1
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        out[i] = labels[sb[i], db[i]]
    return out


@njit(cache=True)
def binned_profile(s: np.ndarray, d: np.ndarray, bin_m: float) -> tuple[np.ndarray, int, np.ndarray]:  # pragma: no cover
    """Arclength bins (P,) of width ``bin_m`` from the smallest s, their number, and the per-bin
    upper-middle value of d (NaN for an empty bin)."""
    s0 = s.min()
    n = len(s)
    bins = np.empty(n, dtype=np.int64)
    n_bins = 0
    for i in range(n):
        b = int(math.floor((s[i] - s0) / bin_m))
        bins[i] = b
        n_bins = max(n_bins, b + 1)
    counts = np.zeros(n_bins, dtype=np.int64)
    for i in range(n):
        counts[bins[i]] += 1
    fill = np.empty(n_bins, dtype=np.int64)  # a counting sort by bin of the values in ascending order
    total = 0
    for b in range(n_bins):
        fill[b] = total
        total += counts[b]
    starts = fill.copy()
    grouped = np.empty(n)
    for i in np.argsort(d):
        b = bins[i]
        grouped[fill[b]] = d[i]
        fill[b] += 1
    med = np.full(n_bins, np.nan)
    for b in range(n_bins):
        if counts[b] > 0:
            med[b] = grouped[starts[b] + counts[b] // 2]
    return bins, n_bins, med


@njit(cache=True)
def mixture_sigma(d: np.ndarray, bins: np.ndarray, med: np.ndarray) -> float:  # pragma: no cover - compiled
    """Robust spread of ``d`` around its per-bin medians (``binned_profile``)."""
    dev = np.empty(len(d))
    for i in range(len(d)):
        dev[i] = abs(d[i] - med[bins[i]])
    return MAD_TO_SIGMA * median(dev)


@njit(cache=True)
def robust_ends(s: np.ndarray, obs_id: np.ndarray, window_m: float) -> tuple[float, float]:  # pragma: no cover
    """The median of the observations' lowest arclengths within ``window_m`` of the lowest one,
    and the same for the highest (``obs_id`` in any order)."""
    n = len(s)
    if n == 0:
        return 0.0, 0.0
    order = np.argsort(obs_id, kind="mergesort")
    lo = np.empty(n)
    hi = np.empty(n)
    k = -1
    prev = 0
    for j in range(n):
        i = order[j]
        if j == 0 or obs_id[i] != prev:
            k += 1
            lo[k] = s[i]
            hi[k] = s[i]
            prev = obs_id[i]
        else:
            lo[k] = min(lo[k], s[i])
            hi[k] = max(hi[k], s[i])
    lo, hi = lo[:k + 1], hi[:k + 1]
    s_lo = median(lo[lo <= lo.min() + window_m])
    s_hi = median(hi[hi >= hi.max() - window_m])
    return s_lo, max(s_hi, s_lo)


@njit(cache=True)
def _smooth_zero_padded(values: np.ndarray, kernel: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """A zero-padded convolution with a centred ``kernel`` (odd length), cut to ``values``' length:
    ``np.convolve(values, kernel)[r:r + len(values)]`` (numba's ``np.convolve`` costs ten times this
    loop on a few dozen bins)."""
    n, n_k = len(values), len(kernel)
    r = n_k // 2
    out = np.zeros(n)
    for i in range(n):
        m = i + r  # the index in the full convolution
        for j in range(max(0, m - n + 1), min(n_k, m + 1)):
            out[i] += values[m - j] * kernel[j]
    return out


@njit(cache=True)
def fit_profile(s: np.ndarray, d: np.ndarray, obs_id: np.ndarray, bins: np.ndarray, n_bins: int, med: np.ndarray,
                outlier_sigmas: float, bin_m: float, kernel: np.ndarray, spacing_m: float,
                columns: np.ndarray, arclength: np.ndarray):  # pragma: no cover - compiled
    """The robust lateral profile of one element (``splicing._fit_profile``) from the bins of
    ``binned_profile``: points further than ``outlier_sigmas`` robust sigmas from their bin's
    median left out, the rest averaged per bin and smoothed along s by ``kernel``, the ends from
    the observations (``robust_ends``), resampled every ``spacing_m`` on the backbone
    (``columns``, ``arclength`` as for ``project``). Returns (ok, line (M, 2), inlier mask, s_lo,
    s_hi, fitted d at each point)."""
    n = len(s)
    s0 = s.min()
    dev = np.empty(n)
    for i in range(n):
        dev[i] = abs(d[i] - med[bins[i]])
    sigma = max(MAD_TO_SIGMA * median(dev), 0.02)
    inl = dev <= outlier_sigmas * sigma
    w = np.zeros(n_bins)
    sum_d = np.zeros(n_bins)
    for i in range(n):
        if inl[i]:
            w[bins[i]] += 1.0
            sum_d[bins[i]] += d[i]
    num = _smooth_zero_padded(sum_d, kernel)
    den = _smooth_zero_padded(w, kernel)
    good = den > 1e-6
    no_line = np.empty((0, 2))
    if not good.any():
        return False, no_line, inl, 0.0, 0.0, np.empty(0)
    centers = s0 + (np.arange(n_bins) + 0.5) * bin_m
    d_s = np.interp(centers, centers[good], num[good] / den[good])
    s_lo, s_hi = robust_ends(s[inl], obs_id[inl], ROBUST_END_WINDOW_M)
    if s_hi - s_lo < bin_m / 2:
        return False, no_line, inl, s_lo, s_hi, np.empty(0)
    q = np.arange(s_lo, s_hi, spacing_m)
    if len(q) == 0 or s_hi - q[-1] > 1e-3:
        q = np.append(q, s_hi)
    dq = np.interp(q, centers, d_s)
    bx, by = np.interp(q, arclength, columns[0]), np.interp(q, arclength, columns[1])
    tx, ty = np.interp(q, arclength, columns[2]), np.interp(q, arclength, columns[3])
    line = np.empty((len(q), 2))
    for k in range(len(q)):
        nn = max(math.hypot(tx[k], ty[k]), 1e-12)
        line[k, 0] = bx[k] - dq[k] * ty[k] / nn
        line[k, 1] = by[k] + dq[k] * tx[k] / nn
    return True, line, inl, s_lo, s_hi, np.interp(s, centers, d_s)


@njit(cache=True)
def arclength(points: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Cumulative length (P,) along a polyline (P, 2), from 0 (``[0.]`` for no points)."""
    out = np.zeros(max(points.shape[0], 1))
    for k in range(1, points.shape[0]):
        out[k] = out[k - 1] + math.hypot(points[k, 0] - points[k - 1, 0], points[k, 1] - points[k - 1, 1])
    return out


@njit(cache=True)
def resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:  # pragma: no cover - compiled
    """The polyline (P >= 1, 2) resampled at equal steps of at most ``spacing_m``, ends kept (its
    first point alone when it has no length)."""
    s = arclength(points)
    total = s[-1]
    if total <= 0:
        return points[:1].copy()
    n = max(int(math.ceil(total / spacing_m)) + 1, 2)
    q = np.arange(n) * (total / (n - 1))
    q[-1] = total
    out = np.empty((n, 2))
    out[:, 0] = np.interp(q, s, points[:, 0])
    out[:, 1] = np.interp(q, s, points[:, 1])
    return out


@njit(cache=True)
def geometry_columns(backbone: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """A backbone (B >= 2, 2) as ``columns (4, B)`` (x, y and the unit tangent: central
    differences, one-sided at the ends, as ``np.gradient``) and its arclength (B,)."""
    n = backbone.shape[0]
    columns = np.empty((4, n))
    for k in range(n):
        columns[0, k] = backbone[k, 0]
        columns[1, k] = backbone[k, 1]
        a, b = max(k - 1, 0), min(k + 1, n - 1)
        scale = 0.5 if 0 < k < n - 1 else 1.0
        tx = scale * (backbone[b, 0] - backbone[a, 0])
        ty = scale * (backbone[b, 1] - backbone[a, 1])
        norm = max(math.hypot(tx, ty), 1e-12)
        columns[2, k] = tx / norm
        columns[3, k] = ty / norm
    return columns, arclength(backbone)


@njit(cache=True)
def runs_along_observations(line_xy: np.ndarray, points_w: np.ndarray, obs_id: np.ndarray, obs: np.ndarray,
                            cos_max: float, near_m: float, window_m: float
                            ) -> tuple[bool, np.ndarray]:  # pragma: no cover - compiled
    """The cut of ``splicing.runs_along_observations`` (see there): the segments between
    consecutive points of one observation of ``obs`` (values of ``obs_id``), those whose midpoint
    lies within ``near_m`` of the line (nearer than: strictly) counted at the nearest line
    vertex as along or across it (more than the angle of ``cos_max``). Returns (whole, runs
    (K, 2) of vertex indices [a, b) kept); ``whole``: no segment runs across, the line is kept as
    it is."""
    n = line_xy.shape[0]
    of_part = np.zeros(obs_id.max() + 1, dtype=np.bool_)
    for o in obs:
        of_part[o] = True
    n_pts = points_w.shape[0]
    mid = np.empty((n_pts, 2))
    seg = np.empty((n_pts, 2))
    n_seg = 0
    for i in range(n_pts - 1):
        if of_part[obs_id[i]] and obs_id[i] == obs_id[i + 1]:
            seg[n_seg, 0] = points_w[i + 1, 0] - points_w[i, 0]
            seg[n_seg, 1] = points_w[i + 1, 1] - points_w[i, 1]
            mid[n_seg, 0] = points_w[i, 0] + 0.5 * seg[n_seg, 0]
            mid[n_seg, 1] = points_w[i, 1] + 0.5 * seg[n_seg, 1]
            n_seg += 1
    if n_seg == 0:
        return True, np.empty((0, 2), dtype=np.int64)
    nearest, dist2 = nearest_index(mid[:n_seg], np.ascontiguousarray(line_xy[:, 0]), np.ascontiguousarray(line_xy[:, 1]))
    along_len = np.zeros(n)
    across_len = np.zeros(n)
    any_near = any_across = False
    for k in range(n_seg):
        if not dist2[k] < near_m * near_m:
            continue
        any_near = True
        at = min(nearest[k], n - 2)
        tx, ty = line_xy[at + 1, 0] - line_xy[at, 0], line_xy[at + 1, 1] - line_xy[at, 1]
        seg_len = math.sqrt(seg[k, 0] * seg[k, 0] + seg[k, 1] * seg[k, 1])
        cos = abs(seg[k, 0] * tx + seg[k, 1] * ty) / max(seg_len * math.hypot(tx, ty), 1e-12)
        if cos < cos_max:
            across_len[nearest[k]] += seg_len
            any_across = True
        else:
            along_len[nearest[k]] += seg_len
    if not any_near or not any_across:
        return True, np.empty((0, 2), dtype=np.int64)
    cum_across = np.zeros(n + 1)
    cum_along = np.zeros(n + 1)
    for k in range(n):
        cum_across[k + 1] = cum_across[k] + across_len[k]
        cum_along[k + 1] = cum_along[k] + along_len[k]
    arc = arclength(line_xy)
    lo = np.searchsorted(arc, arc - window_m, side="left")
    hi = np.searchsorted(arc, arc + window_m, side="right")
    runs = np.empty((n, 2), dtype=np.int64)
    n_runs = 0
    k = 0
    while k < n:
        if cum_across[hi[k]] - cum_across[lo[k]] > cum_along[hi[k]] - cum_along[lo[k]]:  # cut
            k += 1
            continue
        a = k
        while k < n and not (cum_across[hi[k]] - cum_across[lo[k]] > cum_along[hi[k]] - cum_along[lo[k]]):
            k += 1
        if k - a >= 2 and cum_along[k] - cum_along[a] >= window_m:
            runs[n_runs, 0] = a
            runs[n_runs, 1] = k
            n_runs += 1
    return False, runs[:n_runs]


@njit(cache=True)
def frames_in_range(samples: np.ndarray, poses_xyyaw: np.ndarray, box: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(F,) whether any of ``samples (S, 2)`` (world) lies inside ``box`` (x0, x1, y0, y1, the
    vehicle frame) of each pose ``(F, 3)``."""
    out = np.zeros(poses_xyyaw.shape[0], dtype=np.bool_)
    for f in range(poses_xyyaw.shape[0]):
        c, s = math.cos(poses_xyyaw[f, 2]), math.sin(poses_xyyaw[f, 2])
        for k in range(samples.shape[0]):
            rel_x, rel_y = samples[k, 0] - poses_xyyaw[f, 0], samples[k, 1] - poses_xyyaw[f, 1]
            xv = c * rel_x + s * rel_y
            yv = -s * rel_x + c * rel_y
            if box[0] <= xv <= box[1] and box[2] <= yv <= box[3]:
                out[f] = True
                break
    return out


@njit(cache=True)
def frames_near(samples: np.ndarray, poses_xyyaw: np.ndarray, frames: np.ndarray, reach_m: float, corner_m: float
                ) -> np.ndarray:  # pragma: no cover - compiled
    """Indices into ``frames`` of the frames whose vehicle lies within ``reach_m`` of the bounding
    box of ``samples (S, 2)`` on both axes and within ``corner_m`` (at most) of one of them."""
    x_lo, y_lo = samples[:, 0].min() - reach_m, samples[:, 1].min() - reach_m
    x_hi, y_hi = samples[:, 0].max() + reach_m, samples[:, 1].max() + reach_m
    r2 = corner_m * corner_m
    out = np.empty(len(frames), dtype=np.int64)
    n = 0
    for j in range(len(frames)):
        px, py = poses_xyyaw[frames[j], 0], poses_xyyaw[frames[j], 1]
        if not (x_lo <= px <= x_hi and y_lo <= py <= y_hi):
            continue
        for k in range(samples.shape[0]):
            dx, dy = px - samples[k, 0], py - samples[k, 1]
            if dx * dx + dy * dy <= r2:
                out[n] = j
                n += 1
                break
    return out[:n]


@njit(cache=True)
def runs_along(s: np.ndarray, points: np.ndarray, obs_id: np.ndarray) -> float:  # pragma: no cover - compiled
    """Median over observations (runs of equal ``obs_id`` after a stable sort) with a chord of
    more than 2 m of |arclength span| / chord, from each one's first and last point: 1 along the
    backbone, 0 across; 1 when no observation has such a chord."""
    n = len(obs_id)
    order = np.argsort(obs_id, kind="mergesort")
    ratios = np.empty(n)
    m = 0
    j = 0
    while j < n:
        first = order[j]
        k = j
        while k + 1 < n and obs_id[order[k + 1]] == obs_id[first]:
            k += 1
        last = order[k]
        chord = math.sqrt((points[last, 0] - points[first, 0]) ** 2 + (points[last, 1] - points[first, 1]) ** 2)
        if chord > 2.0:
            ratios[m] = abs(s[last] - s[first]) / chord
            m += 1
        j = k + 1
    if m == 0:
        return 1.0
    return median(ratios[:m])


@njit(cache=True)
def splice_residuals(n_points: int, sel: np.ndarray, inl: np.ndarray, s_sel: np.ndarray, d_sel: np.ndarray,
                     d_fit: np.ndarray, original: np.ndarray, obs_id: np.ndarray, obs_ends: np.ndarray,
                     end_free: np.ndarray, s_lo: float, s_hi: float, end_window_m: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The residuals of one splice (``splicing._splice_on``): lateral, of the inlier points as sent
    (``original``) against the fitted profile; along-track, of the observation ends that are element
    ends (``end_free``, per observation: first, last point) within ``end_window_m`` of the
    instance's ends ``s_lo``, ``s_hi`` (low ends first, then high ends, each in observation order);
    and the observations (sorted ids) with an inlier point."""
    n = len(sel)
    lat = np.empty(n)
    n_lat = 0
    s_all = np.full(n_points, np.nan)
    seen = np.zeros(obs_ends.shape[0], dtype=np.bool_)
    for k in range(n):
        if inl[k]:
            s_all[sel[k]] = s_sel[k]
            seen[obs_id[sel[k]]] = True
            if original[sel[k]]:
                lat[n_lat] = d_sel[k] - d_fit[k]
                n_lat += 1
    n_obs = obs_ends.shape[0]
    lo_res = np.empty(n_obs)
    hi_res = np.empty(n_obs)
    n_lo = n_hi = 0
    for o in range(n_obs):
        s_first, s_last = s_all[obs_ends[o, 0]], s_all[obs_ends[o, 1]]
        lo_first = s_first <= s_last
        s_lo_obs, s_hi_obs = (s_first, s_last) if lo_first else (s_last, s_first)
        free_lo, free_hi = (end_free[o, 0], end_free[o, 1]) if lo_first else (end_free[o, 1], end_free[o, 0])
        if np.isfinite(s_lo_obs) and free_lo and abs(s_lo_obs - s_lo) <= end_window_m:
            lo_res[n_lo] = s_lo_obs - s_lo
            n_lo += 1
        if np.isfinite(s_hi_obs) and free_hi and abs(s_hi_obs - s_hi) <= end_window_m:
            hi_res[n_hi] = s_hi_obs - s_hi
            n_hi += 1
    along = np.concatenate((lo_res[:n_lo], hi_res[:n_hi]))
    return lat[:n_lat], along, np.flatnonzero(seen)


@njit(cache=True)
def pair_distance(points: np.ndarray, polys: np.ndarray, max_extrapolation_m: float, cap_m: float
                  ) -> np.ndarray:  # pragma: no cover - compiled
    """Truncated distance (M, P) of each point of ``points (M, P, 2)`` to the matching polyline of
    ``polys (M, K, 2)`` (``tracking.pair_distance``): to its segments, or to its extension along
    its chord within ``max_extrapolation_m`` of either end; at most ``cap_m``."""
    m_pairs, n_points, k = points.shape[0], points.shape[1], polys.shape[1]
    out = np.empty((m_pairs, n_points))
    for m in range(m_pairs):
        cx, cy = polys[m, k - 1, 0] - polys[m, 0, 0], polys[m, k - 1, 1] - polys[m, 0, 1]
        length = max(math.hypot(cx, cy), 1e-9)
        ux, uy = cx / length, cy / length
        for p in range(n_points):
            px, py = points[m, p, 0], points[m, p, 1]
            best = np.inf
            for s in range(k - 1):
                bx, by = polys[m, s + 1, 0] - polys[m, s, 0], polys[m, s + 1, 1] - polys[m, s, 1]
                inv_len2 = 1.0 / max(bx * bx + by * by, 1e-12)
                rx, ry = px - polys[m, s, 0], py - polys[m, s, 1]
                t = min(max((rx * bx + ry * by) * inv_len2, 0.0), 1.0)
                dx, dy = rx - t * bx, ry - t * by
                best = min(best, dx * dx + dy * dy)
            d = math.sqrt(best)
            r0x, r0y = px - polys[m, 0, 0], py - polys[m, 0, 1]
            along0 = r0x * ux + r0y * uy
            if -max_extrapolation_m <= along0 < 0:
                d = min(d, abs(r0x * uy - r0y * ux))
            r1x, r1y = px - polys[m, k - 1, 0], py - polys[m, k - 1, 1]
            along1 = r1x * ux + r1y * uy
            if 0 < along1 <= max_extrapolation_m:
                d = min(d, abs(r1x * uy - r1y * ux))
            out[m, p] = min(d, cap_m)
    return out


@njit(cache=True)
def _walk_in(xs: np.ndarray, ys: np.ndarray, step: int, start: int, span_m: float) -> int:  # pragma: no cover
    """The index of the first point of a polyline at least ``span_m`` from point ``start``, walking
    inward by ``step`` (-1 from the tail, +1 from the head); an end point where it is shorter."""
    n = len(xs)
    k = min(max(start + step, 0), n - 1)
    while 0 < k < n - 1 and math.hypot(xs[start] - xs[k], ys[start] - ys[k]) < span_m:
        k += step
    return k


@njit(cache=True)
def _end_tangent(xs: np.ndarray, ys: np.ndarray, at_tail: bool, tangent_m: float, bends: bool
                 ) -> tuple[bool, float, float, float, float, float]:  # pragma: no cover - compiled
    """(ok, x, y, tx, ty, kappa) at the tail (or head) of a polyline: ``splicing``'s end tangent
    over the last ``tangent_m`` and, with ``bends``, the curvature from the chord before it."""
    n = len(xs)
    end, step = (n - 1, -1) if at_tail else (0, 1)
    bx, by = xs[end], ys[end]
    j = _walk_in(xs, ys, step, end, tangent_m)
    tx, ty = bx - xs[j], by - ys[j]
    tn = math.hypot(tx, ty)
    if tn < 1e-9:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    tx, ty = tx / tn, ty / tn
    if not bends:
        return True, bx, by, tx, ty, 0.0
    kappa = 0.0
    i = _walk_in(xs, ys, step, j, tangent_m)
    px, py = xs[j] - xs[i], ys[j] - ys[i]
    pn = math.hypot(px, py)
    if pn >= tangent_m / 2:
        turn = math.atan2(px * ty - py * tx, px * tx + py * ty)
        kappa = min(max(turn / (0.5 * (tn + pn)), -MAX_GROWTH_CURVATURE), MAX_GROWTH_CURVATURE)
        c, s = math.cos(0.5 * kappa * tn), math.sin(0.5 * kappa * tn)
        tx, ty = c * tx - s * ty, s * tx + c * ty
    return True, bx, by, tx, ty, kappa


@njit(cache=True)
def kasa_circle(pts: np.ndarray) -> tuple[np.ndarray, float]:  # pragma: no cover - compiled
    """Algebraic (Kasa) least-squares circle through ``pts (P, 2)``, fitted about their mean: its
    centre and squared radius (not positive, or not finite, when the points are collinear)."""
    n = pts.shape[0]
    mu_x, mu_y = pts[:, 0].mean(), pts[:, 1].mean()
    a = np.empty((n, 3))
    rhs = np.empty(n)
    for k in range(n):
        qx, qy = pts[k, 0] - mu_x, pts[k, 1] - mu_y
        a[k, 0], a[k, 1], a[k, 2] = qx, qy, 1.0
        rhs[k] = -(qx * qx + qy * qy)
    sol = np.linalg.lstsq(a, rhs, rcond=2.220446049250313e-16 * max(n, 3))[0]  # numpy's rcond=None
    d, e, f = sol[0], sol[1], sol[2]
    centre = np.array([mu_x - 0.5 * d, mu_y - 0.5 * e])
    return centre, 0.25 * (d * d + e * e) - f


@njit(cache=True)
def _bend_continues(tail_xy: np.ndarray, cand: np.ndarray, end_x: float, end_y: float, max_gap_m: float
                    ) -> bool:  # pragma: no cover - compiled
    """Whether the points ``cand`` past a backbone end continue it round a bend: one circle fits
    the backbone's last points ``tail_xy`` and them within ``BEND_SHAPE_TOL_M``, no tighter than
    ``BEND_MIN_RADIUS_M``, the nearest of them within ``max_gap_m`` of the end."""
    if cand.shape[0] < 2 or tail_xy.shape[0] < 3:
        return False
    gap = np.inf
    for k in range(cand.shape[0]):
        gap = min(gap, math.hypot(cand[k, 0] - end_x, cand[k, 1] - end_y))
    if gap > max_gap_m:
        return False
    pts = np.concatenate((tail_xy, cand))
    centre, r2 = kasa_circle(pts)
    if not np.isfinite(r2) or r2 <= BEND_MIN_RADIUS_M ** 2:
        return False
    r = math.sqrt(r2)
    worst = 0.0
    for k in range(pts.shape[0]):
        worst = max(worst, abs(math.hypot(pts[k, 0] - centre[0], pts[k, 1] - centre[1]) - r))
    return worst <= BEND_SHAPE_TOL_M


@njit(cache=True)
def grow_backbone(points_w: np.ndarray, obs_ends: np.ndarray, min_step_m: float, tangent_m: float,
                  lateral_gate_m: float, lateral_gate_slope: float, max_gap_m: float, follow_bends: bool
                  ) -> np.ndarray:  # pragma: no cover - compiled
    """``splicing.grow_backbone`` (see there): the first observation, extended at either end by the
    points of later ones beyond it along its end tangent (or arc, ``follow_bends``) and near it."""
    total = points_w.shape[0]
    n_obs = obs_ends.shape[0]
    cap = 4 * total + 4  # the backbone [head, tail) grows both ways from the middle
    xs = np.empty(cap)
    ys = np.empty(cap)
    head = tail = 2 * total + 2
    ref_x = ref_y = 0.0
    has_ref = False
    known = np.zeros(2, dtype=np.bool_)  # per end (0 tail, 1 head): tangent computed since the last growth
    tangents = np.zeros((2, 6))  # ok, x, y, tx, ty, kappa
    for o in range(n_obs):
        a, b = obs_ends[o, 0], obs_ends[o, 1]
        p = points_w[a:b + 1]
        dx, dy = p[-1, 0] - p[0, 0], p[-1, 1] - p[0, 1]
        if has_ref and dx * ref_x + dy * ref_y < 0:
            p = p[::-1]
            dx, dy = -dx, -dy
        if math.hypot(dx, dy) > 0.5:
            ref_x, ref_y, has_ref = dx, dy, True
        if tail - head < 2:
            head = 2 * total + 2
            tail = head + p.shape[0]
            xs[head:tail] = p[:, 0]
            ys[head:tail] = p[:, 1]
            known[:] = False
            continue
        for end in range(2):
            at_tail = end == 0
            if not known[end]:
                ok, bx, by, tx, ty, kappa = _end_tangent(xs[head:tail], ys[head:tail], at_tail, tangent_m, follow_bends)
                tangents[end, 0] = 1.0 if ok else 0.0
                tangents[end, 1], tangents[end, 2], tangents[end, 3], tangents[end, 4], tangents[end, 5] = bx, by, tx, ty, kappa
                known[end] = True
            if tangents[end, 0] == 0.0:
                continue
            bx, by, tx, ty, kappa = tangents[end, 1], tangents[end, 2], tangents[end, 3], tangents[end, 4], tangents[end, 5]
            first = (p[0, 0] - bx) * tx + (p[0, 1] - by) * ty
            last = (p[-1, 0] - bx) * tx + (p[-1, 1] - by) * ty
            if max(first, last) <= min_step_m:  # most observations do not reach beyond this end
                continue
            m = p.shape[0]
            proj = np.empty(m)
            beyond = np.empty(m, dtype=np.int64)
            past = np.empty(m, dtype=np.int64)
            n_beyond = n_past = 0
            for k in range(m):
                pr = (p[k, 0] - bx) * tx + (p[k, 1] - by) * ty
                proj[k] = pr
                if pr > min_step_m:
                    past[n_past] = k
                    n_past += 1
                    lat = abs((p[k, 1] - by) * tx - (p[k, 0] - bx) * ty - 0.5 * kappa * pr * pr)
                    if lat <= lateral_gate_m + lateral_gate_slope * pr:
                        beyond[n_beyond] = k
                        n_beyond += 1
            chosen = beyond[:n_beyond]
            if n_beyond == 0 and follow_bends:
                j = _walk_in(xs[head:tail], ys[head:tail], -1 if at_tail else 1, tail - head - 1 if at_tail else 0,
                             2 * tangent_m)
                lo, hi = (head + j, tail - 1) if at_tail else (head, head + j)
                tail_xy = np.empty((hi - lo + 1, 2))
                tail_xy[:, 0] = xs[lo:hi + 1]
                tail_xy[:, 1] = ys[lo:hi + 1]
                if _bend_continues(tail_xy, p[past[:n_past]], bx, by, max_gap_m):
                    chosen = past[:n_past]
            if len(chosen) == 0:
                continue
            ext = chosen[np.argsort(proj[chosen], kind="mergesort")]
            if at_tail:
                for k in range(len(ext)):
                    xs[tail + k] = p[ext[k], 0]
                    ys[tail + k] = p[ext[k], 1]
                tail += len(ext)
            else:
                for k in range(len(ext)):
                    xs[head - 1 - k] = p[ext[k], 0]
                    ys[head - 1 - k] = p[ext[k], 1]
                head -= len(ext)
            known[:] = False
    if tail == head:
        return points_w[:1].copy()
    out = np.empty((tail - head, 2))
    out[:, 0] = xs[head:tail]
    out[:, 1] = ys[head:tail]
    return out


@njit(cache=True)
def track_observations(raw_points_v: np.ndarray, raw_offsets: np.ndarray, pieces: np.ndarray, cos_yaw: np.ndarray,
                       sin_yaw: np.ndarray, pose_x: np.ndarray, pose_y: np.ndarray, max_step_m: float):  # pragma: no cover
    """A track's observations as its splice takes them: the detections ``pieces`` (m,) (rows of
    ``raw_offsets`` into ``raw_points_v``, vehicle frame, as sent) with points inserted so that no
    step exceeds ``max_step_m`` (none when it is 0: polygons; as ``tracking.densify_flat``), and
    moved into the world by each one's pose (``cos_yaw``, ``sin_yaw``, ``pose_x``, ``pose_y``, (m,)).
    Returns (points_v (N, 2), offsets (m+1,), original (N,): as sent, points_w (N, 2), obs_id (N,))."""
    m = len(pieces)
    counts = np.zeros(m, dtype=np.int64)
    for o in range(m):
        a, b = raw_offsets[pieces[o]], raw_offsets[pieces[o] + 1]
        total = 1 if b > a else 0
        for i in range(a, b - 1):
            k = 1
            if max_step_m > 0:
                seg = math.sqrt((raw_points_v[i + 1, 0] - raw_points_v[i, 0]) ** 2
                                + (raw_points_v[i + 1, 1] - raw_points_v[i, 1]) ** 2)
                k = max(int(math.ceil(seg / max_step_m)), 1)
            total += k
        counts[o] = total
    offsets = np.zeros(m + 1, dtype=np.int64)
    for o in range(m):
        offsets[o + 1] = offsets[o] + counts[o]
    n = offsets[m]
    points_v = np.empty((n, 2))
    points_w = np.empty((n, 2))
    original = np.zeros(n, dtype=np.bool_)
    obs_id = np.empty(n, dtype=np.int64)
    for o in range(m):
        a, b = raw_offsets[pieces[o]], raw_offsets[pieces[o] + 1]
        w = offsets[o]
        for i in range(a, b):
            x0, y0 = raw_points_v[i, 0], raw_points_v[i, 1]
            k = 1
            step_x = step_y = 0.0
            if i < b - 1:
                step_x, step_y = raw_points_v[i + 1, 0] - x0, raw_points_v[i + 1, 1] - y0
                if max_step_m > 0:
                    k = max(int(math.ceil(math.sqrt(step_x * step_x + step_y * step_y) / max_step_m)), 1)
            for j in range(k):
                frac = j / k
                points_v[w, 0] = x0 + frac * step_x
                points_v[w, 1] = y0 + frac * step_y
                original[w] = j == 0
                obs_id[w] = o
                w += 1
        c, s, px, py = cos_yaw[o], sin_yaw[o], pose_x[o], pose_y[o]
        for w in range(offsets[o], offsets[o + 1]):
            x, y = points_v[w, 0], points_v[w, 1]
            points_w[w, 0] = c * x - s * y + px
            points_w[w, 1] = s * x + c * y + py
    return points_v, offsets, original, points_w, obs_id


@njit(cache=True)
def seen_within(points: np.ndarray, observed: np.ndarray, step: np.ndarray, step_len: np.ndarray, step_m: float,
                gate_m: float, wide_x: bool, order: np.ndarray, sorted_key: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(M,) whether each of ``points (M, 2)`` has an observed point within ``gate_m``: one of
    ``observed (N >= 1, 2)`` as given or, with ``step_m`` > 0, one of the points that densify each
    ``step (N, 2)`` (to the next point of its polyline, of length ``step_len``; zero after a
    polyline's last point) to at most ``step_m`` (``paint_breaks.ObservedPoints``). ``wide_x``,
    ``order``, ``sorted_key``: ``observed`` sorted by ``sort_along_wider_axis``."""
    obs_x, obs_y = observed[:, 0], observed[:, 1]
    seen = np.zeros(points.shape[0], dtype=np.bool_)
    for k in range(points.shape[0]):  # the points as given: those within the gate along the axis
        vx, vy = points[k, 0], points[k, 1]
        q = vx if wide_x else vy
        for j in range(np.searchsorted(sorted_key, q - gate_m), np.searchsorted(sorted_key, q + gate_m, side="right")):
            i = order[j]
            if math.sqrt((obs_x[i] - vx) ** 2 + (obs_y[i] - vy) ** 2) <= gate_m:
                seen[k] = True
                break
    if step_m <= 0:
        return seen
    gate2 = gate_m * gate_m
    reach = gate_m + step_len.max()  # a step with a point within the gate starts within this
    for k in range(points.shape[0]):
        if seen[k]:
            continue
        vx, vy = points[k, 0], points[k, 1]
        q = vx if wide_x else vy
        lo = np.searchsorted(sorted_key, q - reach)
        hi = np.searchsorted(sorted_key, q + reach, side="right")
        for j in range(lo, hi):
            i = order[j]
            if step_len[i] == 0.0 or math.hypot(observed[i, 0] - vx, observed[i, 1] - vy) > gate_m + step_len[i]:
                continue  # no point of this step comes within the gate
            n = max(int(math.ceil(step_len[i] / step_m)), 1)
            for m in range(n):
                frac = m / n
                dx = observed[i, 0] + frac * step[i, 0] - vx
                dy = observed[i, 1] + frac * step[i, 1] - vy
                if dx * dx + dy * dy <= gate2:
                    seen[k] = True
                    break
            if seen[k]:
                break
    return seen


class SortedPoints:
    """Reference points (R >= 1, 2) sorted once along their wider axis, asked again and again which
    query points lie within a radius of one of them (``within_radius``): a trip's path, asked for
    each instance."""

    def __init__(self, points: np.ndarray) -> None:
        self.x = np.ascontiguousarray(points[:, 0], dtype=float)
        self.y = np.ascontiguousarray(points[:, 1], dtype=float)
        self.wide_x, self.order, self.sorted_key = sort_along_wider_axis(self.x, self.y)

    def within(self, points: np.ndarray, radius_m: float) -> np.ndarray:
        """(P,) whether each of ``points (P, 2)`` lies within ``radius_m`` (at most) of one of them."""
        return within_radius(np.ascontiguousarray(points, dtype=float), self.x, self.y, self.wide_x, self.order,
                             self.sorted_key, float(radius_m))


@njit(cache=True)
def within_radius(points: np.ndarray, ref_x: np.ndarray, ref_y: np.ndarray, wide_x: bool, order: np.ndarray,
                  sorted_key: np.ndarray, radius_m: float) -> np.ndarray:  # pragma: no cover - compiled
    """(P,) whether each of ``points (P, 2)`` lies within ``radius_m`` (at most) of one of the
    reference points, sorted by ``sort_along_wider_axis``: those within the radius along the axis
    are tested until one is within it."""
    out = np.zeros(points.shape[0], dtype=np.bool_)
    for k in range(points.shape[0]):
        px, py = points[k, 0], points[k, 1]
        q = px if wide_x else py
        for j in range(np.searchsorted(sorted_key, q - radius_m), np.searchsorted(sorted_key, q + radius_m, side="right")):
            i = order[j]
            if math.sqrt((ref_x[i] - px) ** 2 + (ref_y[i] - py) ** 2) <= radius_m:
                out[k] = True
                break
    return out
