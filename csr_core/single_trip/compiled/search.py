"""Exact nearest-point and within-radius searches over reference points sorted once along their wider
axis (compiled): a backbone's, a track's or a path's points lie along a line, so each query looks at
a few dozen of them, not all.

Part of the splicing stage's compiled steps (``csr_core.single_trip.compiled``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def sort_along_wider_axis(
    ref_x: np.ndarray, ref_y: np.ndarray
) -> tuple[bool, np.ndarray, np.ndarray]:  # pragma: no cover
    """Reference points (R >= 1) sorted along their wider axis, for ``nearest_in_sorted``: (the
    axis is x, the order, the sorted coordinates along it)."""
    wide_x = ref_x.max() - ref_x.min() >= ref_y.max() - ref_y.min()
    key = ref_x if wide_x else ref_y
    order = np.argsort(key, kind="mergesort")
    return wide_x, order, key[order]


@njit(cache=True)
def nearest_in_sorted(
    points: np.ndarray,
    ref_x: np.ndarray,
    ref_y: np.ndarray,
    wide_x: bool,
    order: np.ndarray,
    sorted_key: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
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
        for step in (1, -1):  # up the sorted order from the query's place, then down
            j = start if step == 1 else start - 1
            while 0 <= j < n_ref:
                gap = sorted_key[j] - q
                if gap * gap > best_d2:
                    break
                i = order[j]
                dx, dy = px - ref_x[i], py - ref_y[i]
                d2 = dx * dx + dy * dy
                if d2 < best_d2 or (d2 == best_d2 and i < best):
                    best, best_d2 = i, d2
                j += step
        nearest[k] = best
        dist2[k] = best_d2
    return nearest, dist2


@njit(cache=True)
def nearest_index(
    points: np.ndarray, ref_x: np.ndarray, ref_y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Index (P,) of the nearest of the reference points (``ref_x``, ``ref_y``, (R,), R >= 1) to
    each of ``points (P, 2)`` (the first of equals, as ``argmin`` over all pairs) and the squared
    distance to it. Exact: the references sorted along their wider axis, each search walks out
    from the query's place in that order until the gap along the axis alone exceeds the best
    distance (a backbone's points lie along a line: a few dozen pairs per query, not all R)."""
    wide_x, order, sorted_key = sort_along_wider_axis(ref_x, ref_y)
    return nearest_in_sorted(points, ref_x, ref_y, wide_x, order, sorted_key)


@njit(cache=True)
def within_radius(
    points: np.ndarray,
    ref_x: np.ndarray,
    ref_y: np.ndarray,
    wide_x: bool,
    order: np.ndarray,
    sorted_key: np.ndarray,
    radius_m: float,
) -> np.ndarray:  # pragma: no cover - compiled
    """(P,) whether each of ``points (P, 2)`` lies within ``radius_m`` (at most) of one of the
    reference points, sorted by ``sort_along_wider_axis``: those within the radius along the axis
    are tested until one is within it."""
    out = np.zeros(points.shape[0], dtype=np.bool_)
    for k in range(points.shape[0]):
        px, py = points[k, 0], points[k, 1]
        q = px if wide_x else py
        for j in range(
            np.searchsorted(sorted_key, q - radius_m), np.searchsorted(sorted_key, q + radius_m, side="right")
        ):
            i = order[j]
            if math.sqrt((ref_x[i] - px) ** 2 + (ref_y[i] - py) ** 2) <= radius_m:
                out[k] = True
                break
    return out


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
        return within_radius(
            np.ascontiguousarray(points, dtype=float),
            self.x,
            self.y,
            self.wide_x,
            self.order,
            self.sorted_key,
            float(radius_m),
        )


@njit(cache=True)
def seen_within(
    points: np.ndarray,
    observed: np.ndarray,
    step: np.ndarray,
    step_len: np.ndarray,
    step_m: float,
    gate_m: float,
    wide_x: bool,
    order: np.ndarray,
    sorted_key: np.ndarray,
) -> np.ndarray:  # pragma: no cover
    """(M,) whether each of ``points (M, 2)`` has an observed point within ``gate_m``: one of
    ``observed (N >= 1, 2)`` as given or, with ``step_m`` > 0, one of the points that densify each
    ``step (N, 2)`` (to the next point of its polyline, of length ``step_len``; zero after a
    polyline's last point) to at most ``step_m`` (``paint_breaks.ObservedPoints``). ``wide_x``,
    ``order``, ``sorted_key``: ``observed`` sorted by ``sort_along_wider_axis``."""
    seen = within_radius(
        points,
        np.ascontiguousarray(observed[:, 0]),
        np.ascontiguousarray(observed[:, 1]),
        wide_x,
        order,
        sorted_key,
        gate_m,
    )  # the points as given
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
            if (
                step_len[i] == 0.0
                or math.hypot(observed[i, 0] - vx, observed[i, 1] - vy) > gate_m + step_len[i]
            ):
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
