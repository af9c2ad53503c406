"""Polyline helpers for building worlds and routes (world frame, metres)."""

from __future__ import annotations

import numpy as np


def arclength_m(points_xy: np.ndarray) -> np.ndarray:
    """Cumulative arclength ``(M,)`` of a polyline ``(M, 2)``, starting at 0."""
    points_xy = np.asarray(points_xy, float)
    if len(points_xy) < 2:
        return np.zeros(len(points_xy))
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points_xy, axis=0), axis=1))])


def dedupe(points_xy: np.ndarray, min_step_m: float = 1e-6) -> np.ndarray:
    """Drop consecutive points closer than ``min_step_m``."""
    points_xy = np.asarray(points_xy, float)
    if len(points_xy) < 2:
        return points_xy
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points_xy, axis=0), axis=1) > min_step_m])
    return points_xy[keep]


def resample(points_xy: np.ndarray, step_m: float) -> np.ndarray:
    """Resample a polyline ``(M, 2)`` at (about) ``step_m`` spacing, keeping both ends."""
    points_xy = dedupe(points_xy)
    s = arclength_m(points_xy)
    if len(points_xy) < 2 or s[-1] <= 0:
        return points_xy.copy()
    n = max(int(np.ceil(s[-1] / step_m)), 1)
    s_new = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(s_new, s, points_xy[:, 0]), np.interp(s_new, s, points_xy[:, 1])])


def interpolate_at(points_xy: np.ndarray, s_m: np.ndarray | list[float]) -> np.ndarray:
    """Points ``(K, 2)`` at arclengths ``s_m (K,)`` along the polyline (clamped)."""
    points_xy = np.asarray(points_xy, float)
    s = arclength_m(points_xy)
    return np.column_stack([np.interp(s_m, s, points_xy[:, 0]), np.interp(s_m, s, points_xy[:, 1])])


def tangents(points_xy: np.ndarray) -> np.ndarray:
    """Unit tangents ``(M, 2)`` (central differences)."""
    points_xy = np.asarray(points_xy, float)
    d = np.gradient(points_xy, axis=0)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(n, 1e-12)


def headings_rad(points_xy: np.ndarray) -> np.ndarray:
    t = tangents(points_xy)
    return np.arctan2(t[:, 1], t[:, 0])


def offset(points_xy: np.ndarray, offset_left_m: float | np.ndarray) -> np.ndarray:
    """Offset a (dense) polyline to its left by ``offset_left_m`` (negative: right)."""
    t = tangents(points_xy)
    normal_left = np.column_stack([-t[:, 1], t[:, 0]])
    return np.asarray(points_xy, float) + normal_left * np.asarray(offset_left_m, float).reshape(-1, 1)


def curvature_1pm(points_xy: np.ndarray) -> np.ndarray:
    """Signed curvature ``(M,)`` in 1/m (left turn positive) of a densely resampled polyline."""
    yaw = np.unwrap(headings_rad(points_xy))
    s = arclength_m(points_xy)
    if len(s) < 3:
        return np.zeros(len(s))
    return np.gradient(yaw, s)


def bezier_cubic(
    p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray, step_m: float = 1.0
) -> np.ndarray:
    """Cubic Bezier from ``p0`` leaving along unit tangent ``t0`` to ``p1`` arriving along ``t1``.

    The handle length is a third of the chord (gentle, near-circular for 90 deg turns).
    """
    p0, t0, p1, t1 = (np.asarray(a, float) for a in (p0, t0, p1, t1))
    chord = float(np.linalg.norm(p1 - p0))
    h = chord * 0.39
    c0, c1 = p0 + t0 * h, p1 - t1 * h
    n = max(int(np.ceil(chord / step_m)) * 2, 8)
    u = np.linspace(0.0, 1.0, n)[:, None]
    pts = (1 - u) ** 3 * p0 + 3 * (1 - u) ** 2 * u * c0 + 3 * (1 - u) * u**2 * c1 + u**3 * p1
    return resample(pts, step_m)


def bezier_quadratic(p0: np.ndarray, control: np.ndarray, p1: np.ndarray, step_m: float = 0.5) -> np.ndarray:
    p0, control, p1 = (np.asarray(a, float) for a in (p0, control, p1))
    u = np.linspace(0.0, 1.0, 40)[:, None]
    pts = (1 - u) ** 2 * p0 + 2 * (1 - u) * u * control + u**2 * p1
    return resample(pts, step_m)


def arc(
    center_xy: np.ndarray, radius_m: float, start_rad: float, end_rad: float, step_m: float = 1.0
) -> np.ndarray:
    """Circular arc from ``start_rad`` to ``end_rad`` (CCW if end > start)."""
    n = max(int(np.ceil(abs(end_rad - start_rad) * radius_m / step_m)), 2) + 1
    a = np.linspace(start_rad, end_rad, n)
    return np.asarray(center_xy, float) + radius_m * np.column_stack([np.cos(a), np.sin(a)])


def line_intersection(p0: np.ndarray, d0: np.ndarray, p1: np.ndarray, d1: np.ndarray) -> np.ndarray | None:
    """Intersection of lines ``p0 + a d0`` and ``p1 + b d1``; None if (nearly) parallel."""
    m = np.column_stack([d0, -d1])
    if abs(np.linalg.det(m)) < 1e-6:
        return None
    a, _ = np.linalg.solve(m, np.asarray(p1, float) - np.asarray(p0, float))
    return np.asarray(p0, float) + a * np.asarray(d0, float)


def cut(points_xy: np.ndarray, s_from_m: float, s_to_m: float, step_m: float = 0.5) -> np.ndarray:
    """The part of a polyline between two arclengths, resampled at ``step_m``."""
    s = arclength_m(points_xy)
    s_from_m, s_to_m = max(s_from_m, 0.0), min(s_to_m, s[-1])
    n = max(int(np.ceil((s_to_m - s_from_m) / step_m)), 1)
    return interpolate_at(points_xy, np.linspace(s_from_m, s_to_m, n + 1))


def chaikin(points_xy: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Corner-cutting smoothing that keeps the end points."""
    p = np.asarray(points_xy, float)
    for _ in range(iterations):
        if len(p) < 3:
            return p
        q = 0.75 * p[:-1] + 0.25 * p[1:]
        r = 0.25 * p[:-1] + 0.75 * p[1:]
        mid = np.empty((2 * (len(p) - 1), 2))
        mid[0::2], mid[1::2] = q, r
        p = np.vstack([p[:1], mid[1:-1], p[-1:]])
    return p
