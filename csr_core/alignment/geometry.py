"""Small polyline helpers shared by the alignment stages (metres, (M, 2) arrays)."""

from __future__ import annotations

import numpy as np


def arclength_m(points_xy: np.ndarray) -> np.ndarray:
    """Cumulative length ``(M,)`` along a polyline ``(M, 2)``."""
    if len(points_xy) < 2:
        return np.zeros(len(points_xy))
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points_xy, axis=0), axis=1))])


def resample_polyline(points_xy: np.ndarray, spacing_m: float, closed: bool = False) -> np.ndarray:
    """Points every ``spacing_m`` along a polyline (closed: along its outline), ends kept."""
    pts = np.asarray(points_xy, float)
    if closed and len(pts) > 2:
        pts = np.vstack([pts, pts[:1]])
    s = arclength_m(pts)
    if len(pts) < 2 or s[-1] < 1e-9:
        return pts[:1].copy()
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    pts, s = pts[keep], s[keep]
    n = max(int(np.ceil(s[-1] / spacing_m)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])])


def point_to_segments(points_xy: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray):
    """For each point and ITS segment (row-aligned ``(P, 2)`` arrays): foot point, unit normal,
    clamped parameter ``u`` in [0, 1] and distance. Zero-length segments get normal (0, 0)."""
    d = seg_b - seg_a
    L2 = np.einsum("ij,ij->i", d, d)
    u_raw = np.einsum("ij,ij->i", points_xy - seg_a, d) / np.maximum(L2, 1e-12)
    u = np.clip(u_raw, 0.0, 1.0)
    foot = seg_a + u[:, None] * d
    L = np.sqrt(np.maximum(L2, 1e-12))
    normal = np.column_stack([-d[:, 1], d[:, 0]]) / L[:, None]
    normal[L2 < 1e-12] = 0.0
    return foot, normal, u_raw, np.linalg.norm(points_xy - foot, axis=1)


def line_crossing(points_xy: np.ndarray, origin_xy: np.ndarray, direction_xy: np.ndarray) -> float:
    """Signed coordinate along ``normal = rot90(direction)`` where a polyline crosses the line
    through ``origin`` perpendicular to ``direction`` (NaN when it does not cross)."""
    rel = points_xy - origin_xy
    along = rel @ direction_xy
    lateral = rel @ np.array([-direction_xy[1], direction_xy[0]])
    sign = np.sign(along)
    idx = np.flatnonzero(sign[:-1] * sign[1:] <= 0)
    if len(idx) == 0:
        return float("nan")
    best = float("nan")
    for i in idx:  # pick the crossing closest to the origin
        a0, a1 = along[i], along[i + 1]
        w = 0.5 if abs(a1 - a0) < 1e-12 else a0 / (a0 - a1)
        y = lateral[i] + w * (lateral[i + 1] - lateral[i])
        if not np.isfinite(best) or abs(y) < abs(best):
            best = float(y)
    return best
