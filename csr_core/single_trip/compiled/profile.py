"""A splice's lateral profile along its backbone (compiled): the clustering of a track's points into
elements, per-bin medians, the robust fit, its ends and residuals.

Part of the splicing stage's compiled steps (``csr_core.single_trip.compiled``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: 1.4826 x the median absolute deviation: the sigma of a normal distribution
MAD_TO_SIGMA = 1.4826
#: the window of ``robust_ends`` (m): observation ends this close to the extreme one are pooled
ROBUST_END_WINDOW_M = 1.5


@njit(cache=True)
def median(values: np.ndarray) -> float:  # pragma: no cover - compiled
    """The median of ``values`` (mean of the two middle values for an even count)."""
    v = np.sort(values)
    n = len(v)
    return 0.5 * (v[(n - 1) // 2] + v[n // 2])


@njit(cache=True)
def cluster_sd(
    s: np.ndarray, d: np.ndarray, bin_m: float, cell_d_m: float, reach_bins: int
) -> np.ndarray:  # pragma: no cover
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
def binned_profile(
    s: np.ndarray, d: np.ndarray, bin_m: float
) -> tuple[np.ndarray, int, np.ndarray]:  # pragma: no cover
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
def robust_ends(
    s: np.ndarray, obs_id: np.ndarray, window_m: float
) -> tuple[float, float]:  # pragma: no cover
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
    lo, hi = lo[: k + 1], hi[: k + 1]
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
def fit_profile(
    s: np.ndarray,
    d: np.ndarray,
    obs_id: np.ndarray,
    bins: np.ndarray,
    n_bins: int,
    med: np.ndarray,
    outlier_sigmas: float,
    bin_m: float,
    kernel: np.ndarray,
    spacing_m: float,
    columns: np.ndarray,
    arclength: np.ndarray,
):  # pragma: no cover - compiled
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
def splice_residuals(
    n_points: int,
    sel: np.ndarray,
    inl: np.ndarray,
    s_sel: np.ndarray,
    d_sel: np.ndarray,
    d_fit: np.ndarray,
    original: np.ndarray,
    obs_id: np.ndarray,
    obs_ends: np.ndarray,
    end_free: np.ndarray,
    s_lo: float,
    s_hi: float,
    end_window_m: float,
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
        chord = math.sqrt(
            (points[last, 0] - points[first, 0]) ** 2 + (points[last, 1] - points[first, 1]) ** 2
        )
        if chord > 2.0:
            ratios[m] = abs(s[last] - s[first]) / chord
            m += 1
        j = k + 1
    if m == 0:
        return 1.0
    return median(ratios[:m])
