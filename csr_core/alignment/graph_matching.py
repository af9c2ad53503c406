"""Algorithm 1, Step 2a: element data association as multi-order graph matching (Eq. 4-6).

Coordinates: both sub-maps' elements in one local frame (world axes, origin at the circle
centre, initial poses), ``j`` optionally shifted by a pre-alignment vector.

- Eq. 5 node similarity: ``s = w exp(-d_p^2/2 sigma_p^2) + (1-w) exp(-d_o^2/2 sigma_o^2)``, with
  ``d_p`` the Chamfer distance (the smaller one-sided mean nearest distance, so a short piece
  lying on a long line is close) and ``d_o = 1 - overlap ratio`` (share of both elements'
  length inside their common extent along the line; the paper writes ``o_in/(o_in+o_out)``,
  which is a similarity: we use its complement as the distance). Different types: 0.
- Eq. 6 edge similarity: ``exp(-(e_kl - e_k'l')^2 / 2 sigma_e^2)``, ``e`` the element distance.
- Eq. 4 is solved by reweighted random walks (``rrwm``, see its note on pygmtools) on the affinity matrix
  ``K`` (node terms on the diagonal, edge terms off it; assignments with ``s < tau_s`` are
  removed from K, which enforces ``x = 0 <=> s < tau_s``), then Hungarian; the returned set is
  pruned greedily while the exact Eq. 4 objective improves.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.types import ElementType


def rrwm(
    K: np.ndarray,
    n1: int,
    n2: int,
    max_iter: int = 30,
    sk_iter: int = 6,
    alpha: float = 0.2,
    beta: float = 30.0,
) -> np.ndarray:
    """Reweighted random walks for graph matching (Cho et al. 2010), ``(n1, n2)`` soft assignment.

    The same iteration as ``pygmtools.rrwm`` (same K layout ``idx(i, a) = a * n1 + i``, same
    rescaling, alpha and beta) with a plain exp-domain Sinkhorn: pygmtools' numpy backend runs a
    log-domain Sinkhorn through ``scipy.special.logsumexp`` and costs ~130 ms per call whatever
    the size (measured, 30 x 20 Sinkhorn steps), which alone would exceed the speed budget;
    this one takes < 2 ms at n = 10 and agrees with it (tests/unit/test_alignment_matching.py).
    """
    d = K.sum(axis=1)
    K = K / (d.max() + d.min() * 1e-5 + 1e-12)
    v = np.full(n1 * n2, 1.0 / (n1 * n2))
    for _ in range(max_iter):
        v = K @ v
        last = v = v / max(v.sum(), 1e-300)
        s = v.reshape(n2, n1).T
        s = np.exp(beta * (s / max(s.max(), 1e-300) - 1.0))
        ax_full, ax_part = (1, 0) if n1 <= n2 else (0, 1)
        for _ in range(sk_iter):  # Sinkhorn: the smaller side sums to 1, the other to at most 1
            s /= np.maximum(np.add.reduce(s, axis=ax_full, keepdims=True), 1e-300)
            s /= np.maximum(np.add.reduce(s, axis=ax_part, keepdims=True), 1.0)
        v = alpha * s.T.reshape(-1) + (1 - alpha) * v
        v = v / v.sum()
        if np.linalg.norm(v - last) < 1e-5:
            break
    return v.reshape(n2, n1).T


@dataclass(frozen=True, slots=True)
class ElementSet:
    """Elements of one sub-map in the common local frame."""

    types: tuple[ElementType, ...]
    points: tuple[np.ndarray, ...]  # each (M, 2)

    def __len__(self) -> int:
        return len(self.types)

    def shifted(self, shift_xy: np.ndarray) -> ElementSet:
        return ElementSet(self.types, tuple(p + shift_xy for p in self.points))


def _concat(points: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    counts = np.array([len(p) for p in points])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.vstack(points), starts, counts


def chamfer_matrix(a: ElementSet, b: ElementSet) -> np.ndarray:
    """``(n_a, n_b)`` Chamfer distance d_p of Eq. 5: min of the two one-sided mean distances."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    pa, sa, ca = _concat(a.points)
    pb, sb, cb = _concat(b.points)
    D = cdist(pa, pb)
    a_to_b = np.add.reduceat(np.minimum.reduceat(D, sb, axis=1), sa, axis=0) / ca[:, None]
    b_to_a = np.add.reduceat(np.minimum.reduceat(D, sa, axis=0), sb, axis=1) / cb[None, :]
    return np.minimum(a_to_b, b_to_a)


def principal_directions(points: Sequence[np.ndarray]) -> np.ndarray:
    """``(n, 2)`` unit vectors of the largest spread of each point set, all at once: the top
    eigenvector of each 2 x 2 covariance in closed form, angle ``atan2(2 s_xy, s_xx - s_yy) / 2``
    (the first right singular vector of the centred points, up to sign; (1, 0) for one point)."""
    pts, starts, counts = _concat(points)
    mean = np.add.reduceat(pts, starts, axis=0) / counts[:, None]
    c = pts - np.repeat(mean, counts, axis=0)
    sxx, syy, sxy = (np.add.reduceat(v, starts) for v in (c[:, 0] ** 2, c[:, 1] ** 2, c[:, 0] * c[:, 1]))
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    return np.column_stack([np.cos(angle), np.sin(angle)])


def overlap_matrix(a: ElementSet, b: ElementSet) -> np.ndarray:
    """``(n_a, n_b)`` overlap ratio o_in/(o_in+o_out) along each ``a`` element's direction."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    pa, sa, ca = _concat(a.points)
    pb, sb, _ = _concat(b.points)
    direction = principal_directions(a.points)  # (n_a, 2)
    s_own = np.einsum("ij,ij->i", pa, np.repeat(direction, ca, axis=0))  # a's points on their own axis
    lo_k, hi_k = np.minimum.reduceat(s_own, sa)[:, None], np.maximum.reduceat(s_own, sa)[:, None]
    s_b = pb @ direction.T  # (N_b, n_a): b's points on every a axis
    lo_l, hi_l = np.minimum.reduceat(s_b, sb, axis=0).T, np.maximum.reduceat(s_b, sb, axis=0).T
    inter = np.maximum(0.0, np.minimum(hi_k, hi_l) - np.maximum(lo_k, lo_l))
    total = (hi_k - lo_k) + (hi_l - lo_l)
    ratio = np.where(total > 1e-9, 2.0 * inter / np.where(total > 1e-9, total, 1.0), 1.0)
    return np.where(same_type(a, b), ratio, 0.0)


def node_similarity(a: ElementSet, b: ElementSet, noise: NoiseScales, params: AlignmentParams) -> np.ndarray:
    """Eq. 5, ``(n_a, n_b)``; 0 between different element types."""
    d_p = chamfer_matrix(a, b)
    d_o = 1.0 - overlap_matrix(a, b)
    w = params.node_position_weight
    s = w * np.exp(-0.5 * (d_p / noise.sigma_p_m) ** 2) + (1 - w) * np.exp(-0.5 * (d_o / params.sigma_o) ** 2)
    return np.where(same_type(a, b), s, 0.0)


_CODES = {t: n for n, t in enumerate(ElementType)}


def same_type(a: ElementSet, b: ElementSet) -> np.ndarray:
    """``(n_a, n_b)`` bool. (Compare integer codes: ``np.asarray`` of str-enums truncates.)"""
    ca = np.array([_CODES[t] for t in a.types], int)
    cb = np.array([_CODES[t] for t in b.types], int)
    return ca[:, None] == cb[None, :]


def element_distances(a: ElementSet) -> np.ndarray:
    """``(n, n)`` distances e_kl between the elements of one sub-map (Eq. 6), symmetric."""
    D = chamfer_matrix(a, a)
    return 0.5 * (D + D.T)


def edge_similarity(e_a: np.ndarray, e_b: np.ndarray, sigma_e: float) -> np.ndarray:
    """Eq. 6 for all element pairs: ``[k, l, k', l'] = exp(-(e_kl - e_k'l')^2 / 2 sigma_e^2)``."""
    diff = e_a[:, :, None, None] - e_b[None, None, :, :]
    return np.exp(-0.5 * (diff / sigma_e) ** 2)


def eq4_objective(
    matches: Sequence[tuple[int, int]],
    s_node: np.ndarray,
    e_a: np.ndarray,
    e_b: np.ndarray,
    sigma_e: float,
    params: AlignmentParams,
) -> float:
    """Value of Eq. 4 for a set of matches ``(k, k')``."""
    n_m = len(matches)
    if n_m == 0:
        return 0.0
    k = np.array([m[0] for m in matches])
    kp = np.array([m[1] for m in matches])
    node = float(np.mean(s_node[k, kp]))
    edge = 0.0
    if n_m > 1:
        sim = np.exp(-0.5 * ((e_a[np.ix_(k, k)] - e_b[np.ix_(kp, kp)]) / sigma_e) ** 2)
        edge = float((sim.sum() - n_m) / (n_m * (n_m - 1)))
    return params.w_count * n_m + params.w_node * node + params.w_edge * edge


def rrwm_match(
    s_node: np.ndarray, e_a: np.ndarray, e_b: np.ndarray, sigma_e: float, params: AlignmentParams
) -> list[tuple[int, int]]:
    """Solve Eq. 4: RRWM on the affinity matrix, Hungarian, ``tau_s`` gate, greedy pruning."""
    valid = s_node >= params.tau_s
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    if len(rows) == 0:
        return []
    s = s_node[np.ix_(rows, cols)]
    v = valid[np.ix_(rows, cols)]
    n1, n2 = s.shape
    if n1 == 1 or n2 == 1:
        i, j = np.unravel_index(np.argmax(np.where(v, s, -1.0)), s.shape)
        matches = [(int(i), int(j))]
    else:
        ea, eb = e_a[np.ix_(rows, rows)], e_b[np.ix_(cols, cols)]
        # index convention of pygmtools: idx(i in G1, a in G2) = a * n1 + i
        E = np.exp(-0.5 * ((ea[None, :, None, :] - eb[:, None, :, None]) / sigma_e) ** 2)  # [a, i, b, j]
        E *= (1 - np.eye(n1))[None, :, None, :] * (1 - np.eye(n2))[:, None, :, None]
        mask = v.T.reshape(-1).astype(float)
        K = E.reshape(n1 * n2, n1 * n2) * (params.w_edge / max(min(n1, n2) - 1, 1))
        K *= mask[:, None] * mask[None, :]
        K[np.diag_indices_from(K)] = params.w_node * s.T.reshape(-1) * mask
        r_idx, c_idx = linear_sum_assignment(-rrwm(K, n1, n2, max_iter=params.rrwm_max_iter))  # Hungarian
        matches = [(int(i), int(j)) for i, j in zip(r_idx, c_idx, strict=False) if v[i, j]]
    matches = [(int(rows[i]), int(cols[j])) for i, j in matches]
    return _prune(matches, s_node, e_a, e_b, sigma_e, params)


def _prune(
    matches: list[tuple[int, int]],
    s_node: np.ndarray,
    e_a: np.ndarray,
    e_b: np.ndarray,
    sigma_e: float,
    params: AlignmentParams,
) -> list[tuple[int, int]]:
    """Greedy pruning: drop the match whose removal raises the Eq. 4 objective most, while one
    does. The objective without match ``q`` for all ``q`` at once, from the node terms and the
    edge-similarity matrix of the current set (``eq4_objective`` term by term)."""
    if len(matches) < 2:
        return matches
    k = np.array([m[0] for m in matches])
    kp = np.array([m[1] for m in matches])
    node = s_node[k, kp]
    sim = np.exp(-0.5 * ((e_a[np.ix_(k, k)] - e_b[np.ix_(kp, kp)]) / sigma_e) ** 2)
    np.fill_diagonal(sim, 0.0)
    keep = np.ones(len(matches), bool)
    best = eq4_objective(matches, s_node, e_a, e_b, sigma_e, params)
    while keep.sum() > 1:
        n = int(keep.sum()) - 1  # matches left after one more removal
        node_sum = float(node[keep].sum())
        edge_sum = float(sim[np.ix_(keep, keep)].sum())
        row = sim[:, keep].sum(axis=1)  # each match's edge terms with the kept ones
        edge = (edge_sum - 2.0 * row) / (n * (n - 1)) if n > 1 else np.zeros(len(matches))
        trials = params.w_count * n + params.w_node * (node_sum - node) / n + params.w_edge * edge
        trials = np.where(keep, trials, -np.inf)
        q = int(np.argmax(trials))
        if trials[q] <= best + 1e-9:
            break
        best = float(trials[q])
        keep[q] = False
    return [m for m, ok in zip(matches, keep, strict=True) if ok]


def boundary_prealignment(
    a: ElementSet, b: ElementSet, direction_xy: np.ndarray, max_shift_m: float
) -> np.ndarray:
    """Pre-alignment by the left and right road boundaries: the lateral shift (along the normal
    of ``direction``) bringing most of ``b``'s boundaries onto ``a``'s, as a ``(2,)`` vector;
    zero when no boundary pair supports a shift within ``max_shift_m``."""
    normal = np.array([-direction_xy[1], direction_xy[0]])

    def lateral(es: ElementSet) -> np.ndarray:
        out = []
        for t, p in zip(es.types, es.points, strict=False):
            if t == ElementType.ROAD_BOUNDARY:
                near = p[np.argsort(np.abs(p @ direction_xy))[:5]]  # near the cross-section
                out.append(float(np.mean(near @ normal)))
        return np.asarray(out)

    la, lb = lateral(a), lateral(b)
    if len(la) == 0 or len(lb) == 0:
        return np.zeros(2)
    cand = (la[:, None] - lb[None, :]).ravel()
    cand = cand[np.abs(cand) <= max_shift_m]
    if len(cand) == 0:
        return np.zeros(2)
    support = np.array([np.sum(np.min(np.abs(la[:, None] - (lb[None, :] + c)), axis=1) < 0.75) for c in cand])
    best = cand[support == support.max()]
    c = best[np.argmin(np.abs(best))]
    near = cand[np.abs(cand - c) < 0.75]
    return float(np.mean(near)) * normal
