"""Polylines (compiled): arclength, resampling, the unit tangents of a backbone and the projection of
points onto it.

Part of the splicing stage's compiled steps (``csr_core.single_trip.compiled``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from csr_core.single_trip.compiled.search import nearest_index


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
def project(
    points: np.ndarray, columns: np.ndarray, arclength: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Arclength s and signed lateral offset d (left positive) of ``points (P, 2)`` on a densely
    sampled backbone (``columns (4, B)``: x, y, unit tangent x, y; its ``arclength (B,)``): from
    its nearest point (``nearest_index``), along its tangent."""
    return project_at(points, nearest_index(points, columns[0], columns[1])[0], columns, arclength)


@njit(cache=True)
def project_at(
    points: np.ndarray, nearest: np.ndarray, columns: np.ndarray, arclength: np.ndarray
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
