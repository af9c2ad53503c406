"""The tests a splice passes (compiled): whether it runs along its own observations, and which tracked
frames had it in range.

Part of the splicing stage's compiled steps (``csr_core.single_trip.compiled``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from csr_core.single_trip.compiled.polyline import arclength
from csr_core.single_trip.compiled.search import nearest_index


@njit(cache=True)
def runs_along_observations(
    line_xy: np.ndarray,
    points_w: np.ndarray,
    obs_id: np.ndarray,
    obs: np.ndarray,
    cos_max: float,
    near_m: float,
    window_m: float,
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
    nearest, dist2 = nearest_index(
        mid[:n_seg], np.ascontiguousarray(line_xy[:, 0]), np.ascontiguousarray(line_xy[:, 1])
    )
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
def frames_near(
    samples: np.ndarray, poses_xyyaw: np.ndarray, frames: np.ndarray, reach_m: float, corner_m: float
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
def frames_in_range(
    samples: np.ndarray, poses_xyyaw: np.ndarray, box: np.ndarray
) -> np.ndarray:  # pragma: no cover
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
