"""Splicing a track's observations into one trip-level instance (paper III-C).

Lines: the observations (world frame) are ordered along a backbone grown from the first
observation by the parts of later ones beyond its ends; every point is then projected on the
backbone (arclength s, signed lateral offset d), the lateral profile d(s) is estimated per
arclength bin by a median with outlier rejection (ghost points, mis-assignments), smoothed by
a Gaussian kernel along s, and turned back into a polyline; twice, the second time on the
first result. Gaps up to ``SPLICE_MAX_GAP_M`` (dashes, missed frames) are spanned, so a dashed
divider stays one instance; longer gaps split the instance. A Gaussian kernel along arclength
stands in for Qiao et al.'s Catmull-Rom fit: same role (a smooth curve through denoised
control points), closed form and vectorised.

Polygons (crosswalk, road marking): observations clipped by the BEV range are left out when
whole ones exist; the vertices of the others are brought into the order of the median-area
one and averaged by a per-vertex median.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

from csr_core.single_trip.params import SingleTripParams


@dataclass(frozen=True, slots=True)
class SplicedLine:
    points_xy_world: np.ndarray  # (M, 2)
    lateral_residuals_m: np.ndarray  # (R,) of inlier observation points
    along_residuals_m: np.ndarray  # (A,) of observed element ends (not BEV cuts)
    obs_inlier_share: np.ndarray  # (n_obs,) share of each observation's points kept


def _arclength(points: np.ndarray) -> np.ndarray:
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]


def resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:
    s = _arclength(points)
    if s[-1] <= 0:
        return points[:1].copy()
    q = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / spacing_m)) + 1, 2))
    return np.column_stack([np.interp(q, s, points[:, 0]), np.interp(q, s, points[:, 1])])


def orient_observations(polys: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Flip observations whose end-to-end direction opposes the previous one's (world frame).
    Returns the oriented polylines and which were flipped (n_obs,)."""
    out = []
    flipped = np.zeros(len(polys), dtype=bool)
    ref = None
    for i, p in enumerate(polys):
        d = p[-1] - p[0]
        if ref is not None and float(d @ ref) < 0:
            p = p[::-1]
            d = -d
            flipped[i] = True
        if np.linalg.norm(d) > 0.5:
            ref = d
        out.append(p)
    return out, flipped


def grow_backbone(polys: list[np.ndarray], min_step_m: float = 0.5) -> np.ndarray:
    """An ordered polyline covering all observations: the first one, extended at either end
    by the points of later observations that lie beyond it along its end tangents."""
    bb = polys[0]
    for p in polys[1:]:
        if len(bb) < 2:
            bb = p
            continue
        for end in (1, 0):
            if end:
                a, b = bb[-2], bb[-1]
            else:
                a, b = bb[1], bb[0]
            t = b - a
            tn = np.linalg.norm(t)
            if tn < 1e-9:
                continue
            t = t / tn
            proj = (p - b) @ t
            beyond = proj > min_step_m
            if beyond.any():
                ext = p[beyond][np.argsort(proj[beyond])]
                bb = np.vstack([bb, ext]) if end else np.vstack([ext[::-1], bb])
    return bb


def _project(points: np.ndarray, backbone: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arclength s and signed lateral offset d (left positive) of points (P, 2) on a densely
    sampled backbone (B, 2)."""
    s_b = _arclength(backbone)
    tan = np.gradient(backbone, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    _, i = cKDTree(backbone).query(points)
    rel = points - backbone[i]
    s = s_b[i] + (rel * tan[i]).sum(1)
    d = tan[i, 0] * rel[:, 1] - tan[i, 1] * rel[:, 0]
    return s, d


def _binned_median(bins: np.ndarray, values: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((values, bins))
    counts = np.bincount(bins, minlength=n_bins)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    med = np.full(n_bins, np.nan)
    ok = counts > 0
    med[ok] = values[order][starts[ok] + counts[ok] // 2]
    return med, counts


def splice_line(polys: list[np.ndarray], end_free: np.ndarray, params: SingleTripParams) -> list[SplicedLine]:
    """Observations (world, each (M_i, 2)) of one track -> one smoothed polyline per span
    without a gap longer than ``SPLICE_MAX_GAP_M`` (usually one).

    ``end_free`` (n_obs, 2) bool: the observation's first/last point is an element end seen
    inside the BEV range (not a cut by the range); only those give along-track residuals.
    """
    polys, flipped = orient_observations(polys)
    end_free = np.where(flipped[:, None], end_free[:, ::-1], end_free)
    pts = np.concatenate(polys)
    obs_id = np.repeat(np.arange(len(polys)), [len(p) for p in polys])
    backbone = resample_polyline(grow_backbone(polys), params.SPLICE_BIN_M / 2)
    if len(backbone) < 3:
        return []
    bin_m = params.SPLICE_BIN_M
    result = None
    for _ in range(params.SPLICE_ITERATIONS):
        s, d = _project(pts, backbone)
        s0 = s.min()
        bins = np.floor((s - s0) / bin_m).astype(np.int64)
        n_bins = int(bins.max()) + 1
        med, counts = _binned_median(bins, d, n_bins)
        dev = np.abs(d - med[bins])
        sigma = max(1.4826 * float(np.median(dev)), 0.02)
        inl = dev <= params.SPLICE_OUTLIER_SIGMAS * sigma
        w = np.bincount(bins[inl], minlength=n_bins).astype(float)
        sum_d = np.bincount(bins[inl], weights=d[inl], minlength=n_bins)
        sm = params.SPLICE_SMOOTH_SIGMA_M / bin_m
        num = gaussian_filter1d(sum_d, sm, mode="nearest")
        den = gaussian_filter1d(w, sm, mode="nearest")
        supported = w > 0
        centers = s0 + (np.arange(n_bins) + 0.5) * bin_m
        # split at gaps longer than the limit
        idx = np.flatnonzero(supported)
        if len(idx) == 0:
            return []
        cuts = np.flatnonzero(np.diff(idx) * bin_m > params.SPLICE_MAX_GAP_M)
        spans = np.split(idx, cuts + 1)
        d_s = np.where(den > 1e-6, num / np.maximum(den, 1e-12), np.nan)
        good = np.isfinite(d_s)
        d_s = np.interp(centers, centers[good], d_s[good])
        s_b = _arclength(backbone)
        tan = np.gradient(backbone, axis=0)
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
        normal = np.column_stack([-tan[:, 1], tan[:, 0]])
        result = []
        for span in spans:
            in_span = inl & (bins >= span[0]) & (bins <= span[-1])
            # ends: median of the observation ends that cluster at the extreme
            s_lo, s_hi = _robust_ends(s[in_span], obs_id[in_span])
            q = np.arange(s_lo, s_hi, params.SPLICE_OUTPUT_SPACING_M)
            q = np.r_[q, s_hi] if len(q) == 0 or s_hi - q[-1] > 1e-3 else q
            if len(q) < 2:
                q = np.array([s_lo, s_hi])
            dq = np.interp(q, centers, d_s)
            bx = np.interp(q, s_b, backbone[:, 0])
            by = np.interp(q, s_b, backbone[:, 1])
            nx = np.interp(q, s_b, normal[:, 0])
            ny = np.interp(q, s_b, normal[:, 1])
            nn = np.maximum(np.hypot(nx, ny), 1e-12)
            line = np.column_stack([bx + dq * nx / nn, by + dq * ny / nn])
            result.append((line, in_span, s_lo, s_hi))
        if len(result) == 1 and result[0][3] - result[0][2] >= 2 * bin_m:
            backbone = resample_polyline(result[0][0], bin_m / 2)
    assert result is not None
    out = []
    for line, in_span, s_lo, s_hi in result:
        if s_hi - s_lo < bin_m / 2:
            continue
        s_f, d_f = _project(pts[in_span], resample_polyline(line, bin_m / 4))
        lat = d_f
        s_line_end = _arclength(line)[-1]
        along = _along_residuals(s_f, obs_id[in_span], end_free, s_line_end)
        share = np.bincount(obs_id[in_span], minlength=len(polys)) / np.maximum(
            np.bincount(obs_id, minlength=len(polys)), 1)
        out.append(SplicedLine(line, lat, along, share))
    return out


def _robust_ends(s: np.ndarray, obs_id: np.ndarray, window_m: float = 1.5) -> tuple[float, float]:
    if len(s) == 0:
        return 0.0, 0.0
    n = int(obs_id.max()) + 1
    lo = np.full(n, np.inf)
    hi = np.full(n, -np.inf)
    np.minimum.at(lo, obs_id, s)
    np.maximum.at(hi, obs_id, s)
    lo, hi = lo[np.isfinite(lo)], hi[np.isfinite(hi)]
    s_lo = float(np.median(lo[lo <= lo.min() + window_m]))
    s_hi = float(np.median(hi[hi >= hi.max() - window_m]))
    return s_lo, max(s_hi, s_lo)


def _along_residuals(s: np.ndarray, obs_id: np.ndarray, end_free: np.ndarray, s_end: float,
                     window_m: float = 3.0) -> np.ndarray:
    """Along-track residuals: observed element ends (not BEV cuts) against the instance ends."""
    if len(s) == 0:
        return np.zeros(0)
    n = len(end_free)
    lo = np.full(n, np.inf)
    hi = np.full(n, -np.inf)
    np.minimum.at(lo, obs_id, s)
    np.maximum.at(hi, obs_id, s)
    res = []
    ok = np.isfinite(lo) & end_free[:, 0] & (np.abs(lo) <= window_m)
    res.append(lo[ok])
    ok = np.isfinite(hi) & end_free[:, 1] & (np.abs(hi - s_end) <= window_m)
    res.append(hi[ok] - s_end)
    return np.concatenate(res)


def polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def splice_polygon(polys: list[np.ndarray], whole: np.ndarray, headings_rad: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observed outlines (world) -> one outline, lateral and along residuals (vehicle heading).

    ``whole`` (n_obs,) bool: the observation is not clipped by the BEV range."""
    cand = [i for i in range(len(polys)) if whole[i]] or list(range(len(polys)))
    # consistent winding (counter-clockwise)
    ccw = [p if polygon_area(p) >= 0 else p[::-1] for p in polys]
    areas = np.array([abs(polygon_area(ccw[i])) for i in cand])
    ref_i = cand[int(np.argsort(areas)[len(areas) // 2])]
    ref = ccw[ref_i]
    m = len(ref)
    stack, heads = [], []
    for i in cand:
        p = ccw[i]
        if len(p) != m:
            continue
        shifts = np.stack([np.roll(p, -k, axis=0) for k in range(m)])
        err = np.linalg.norm(shifts - ref[None], axis=-1).sum(1)
        stack.append(shifts[int(np.argmin(err))])
        heads.append(headings_rad[i])
    arr = np.stack(stack)  # (n, m, 2)
    fused = np.median(arr, axis=0)
    dev = arr - fused[None]
    h = np.asarray(heads)[:, None]
    along = dev[..., 0] * np.cos(h) + dev[..., 1] * np.sin(h)
    lateral = -dev[..., 0] * np.sin(h) + dev[..., 1] * np.cos(h)
    return fused, lateral.ravel(), along.ravel()
