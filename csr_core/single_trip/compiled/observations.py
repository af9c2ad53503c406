"""A track's detections as the splice and the tracker take them (compiled): gathered, densified and
moved into the world, and the pairwise distance of detections.

Part of the splicing stage's compiled steps (``csr_core.single_trip.compiled``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def track_observations(
    raw_points_v: np.ndarray,
    raw_offsets: np.ndarray,
    pieces: np.ndarray,
    cos_yaw: np.ndarray,
    sin_yaw: np.ndarray,
    pose_x: np.ndarray,
    pose_y: np.ndarray,
    max_step_m: float,
):  # pragma: no cover
    """A track's observations as its splice takes them: the detections ``pieces`` (m,) (rows of
    ``raw_offsets`` into ``raw_points_v``, vehicle frame, as sent) with points inserted so that no
    step exceeds ``max_step_m`` (each step cut into ceil(length / ``max_step_m``) equal parts; none
    when it is 0: polygons, whose vertices are corners), and moved into the world by each one's pose (``cos_yaw``, ``sin_yaw``, ``pose_x``, ``pose_y``, (m,)).
    Returns (points_v (N, 2), offsets (m+1,), original (N,): as sent, points_w (N, 2), obs_id (N,))."""
    m = len(pieces)
    counts = np.zeros(m, dtype=np.int64)
    for o in range(m):
        a, b = raw_offsets[pieces[o]], raw_offsets[pieces[o] + 1]
        total = 1 if b > a else 0
        for i in range(a, b - 1):
            k = 1
            if max_step_m > 0:
                seg = math.sqrt(
                    (raw_points_v[i + 1, 0] - raw_points_v[i, 0]) ** 2
                    + (raw_points_v[i + 1, 1] - raw_points_v[i, 1]) ** 2
                )
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
def pair_distance(
    points: np.ndarray, polys: np.ndarray, max_extrapolation_m: float, cap_m: float
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
