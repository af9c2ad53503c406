"""A backbone grown from a track's own observations (compiled): the first one, extended at either end
by the points of later ones beyond it along its end tangent, or round a bend
(``splicing.grow_backbone``).

Part of the splicing stage's compiled steps (``csr_core.single_trip.compiled``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: ``grow_backbone`` follows bends of at least 10 m radius (as ``splicing._extend_ends``)
MAX_GROWTH_CURVATURE = 0.1
#: no marking turns tighter than a car's turning circle
BEND_MIN_RADIUS_M = 6.0
#: an observation continuing a bend lies on its circle this close
BEND_SHAPE_TOL_M = 0.5


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
def _end_tangent(
    xs: np.ndarray, ys: np.ndarray, at_tail: bool, tangent_m: float, bends: bool
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
def _bend_continues(
    tail_xy: np.ndarray, cand: np.ndarray, end_x: float, end_y: float, max_gap_m: float
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
    if not np.isfinite(r2) or r2 <= BEND_MIN_RADIUS_M**2:
        return False
    r = math.sqrt(r2)
    worst = 0.0
    for k in range(pts.shape[0]):
        worst = max(worst, abs(math.hypot(pts[k, 0] - centre[0], pts[k, 1] - centre[1]) - r))
    return worst <= BEND_SHAPE_TOL_M


@njit(cache=True)
def grow_backbone(
    points_w: np.ndarray,
    obs_ends: np.ndarray,
    min_step_m: float,
    tangent_m: float,
    lateral_gate_m: float,
    lateral_gate_slope: float,
    max_gap_m: float,
    follow_bends: bool,
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
        p = points_w[a : b + 1]
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
                ok, bx, by, tx, ty, kappa = _end_tangent(
                    xs[head:tail], ys[head:tail], at_tail, tangent_m, follow_bends
                )
                tangents[end, 0] = 1.0 if ok else 0.0
                tangents[end, 1], tangents[end, 2], tangents[end, 3], tangents[end, 4], tangents[end, 5] = (
                    bx,
                    by,
                    tx,
                    ty,
                    kappa,
                )
                known[end] = True
            if tangents[end, 0] == 0.0:
                continue
            bx, by, tx, ty, kappa = (
                tangents[end, 1],
                tangents[end, 2],
                tangents[end, 3],
                tangents[end, 4],
                tangents[end, 5],
            )
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
                j = _walk_in(
                    xs[head:tail],
                    ys[head:tail],
                    -1 if at_tail else 1,
                    tail - head - 1 if at_tail else 0,
                    2 * tangent_m,
                )
                lo, hi = (head + j, tail - 1) if at_tail else (head, head + j)
                tail_xy = np.empty((hi - lo + 1, 2))
                tail_xy[:, 0] = xs[lo : hi + 1]
                tail_xy[:, 1] = ys[lo : hi + 1]
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
