"""Algorithm 1, Step 2b: sub-map relative pose by GNC and the matching confidence (Eq. 7).

GNC-TLS over point-to-line residuals, written in numpy. Why not gtsam: gtsam has no 2D
point-to-line (nor point-to-point with fixed points) factor for a ``Pose2``, and a
``CustomFactor`` per point is slow (LIBRARY-NOTES: 1,000 CustomFactors made LM take seconds),
while the problem here is 3 unknowns and a few hundred residuals. The loop is the standard
GNC-TLS of Yang et al. (2020) (the GNC of the paper's ref. [28]): the surrogate weights
``w = clip(c sqrt(mu (mu+1)) / |r| - mu, 0, 1)``, ``mu`` doubling per outer step, one
weighted Gauss-Newton step per outer step with correspondences refreshed (ICP style).

Residual of a source point ``p`` (sub-map ``j``) against the matched element of sub-map ``i``:
``r = n . (delta(p) - q)``, ``q`` the foot on the nearest segment, ``n`` its normal; points that
project beyond the target's ends are left out (clipped pieces differ in extent).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from csr_core import se2
from csr_core.alignment.geometry import point_to_segments
from csr_core.alignment.graph_matching import ElementSet, element_distances, node_similarity
from csr_core.alignment.landmarks import associate_landmarks, landmark_gate_m
from csr_core.alignment.params import AlignmentParams, NoiseScales

MAX_POINTS_PER_ELEMENT = 15
UNOBSERVED_SIGMA_XY_M, UNOBSERVED_SIGMA_YAW_RAD = 20.0, 0.5
GNC_MU_FACTOR = 4.0  # Yang et al. use 1.4; 4.0 needs a third of their outer steps, same results here
FAR_M = 1e6  # padding of the target polylines: farther than any point


@dataclass(frozen=True, slots=True)
class Registration:
    """``delta`` maps the source set onto the target (``target ~ delta o source``), in the
    common local frame; ``information_xyyaw`` is in the same frame (left perturbation)."""

    delta_xyyaw: np.ndarray  # (3,)
    information_xyyaw: np.ndarray  # (3, 3)
    element_inlier: np.ndarray  # (N_m,) bool per match
    residual_rms_m: float
    n_points: int
    # (3, 3) d delta / d initial pose: how much of the start pose (the GNSS relative pose) the
    # estimate keeps through the start-pose prior (I in a direction the elements do not observe)
    prior_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


@dataclass(frozen=True, slots=True)
class LandmarkSets:
    """Point landmarks (dash ends) of the target and the source in the common local frame:
    points ``(L, 2)``, unit directions towards the other end of their dash ``(L, 2)``, and
    sigma of each ``(L,)`` (metres, along the dash)."""

    target_xy: np.ndarray
    target_dir: np.ndarray
    target_sigma_m: np.ndarray
    source_xy: np.ndarray
    source_dir: np.ndarray
    source_sigma_m: np.ndarray
    gate_max_m: float


def _landmark_rows(delta: np.ndarray, lm: LandmarkSets, gate_m: float):
    """Rows of the landmarks at ``delta``: moved source points, foot (associated target
    landmark), normal (the target's dash direction: the residual is along the dash), validity
    and sigma of each residual."""
    moved = se2.transform_points(delta, lm.source_xy)
    c, s_ = np.cos(delta[2]), np.sin(delta[2])
    dirs = lm.source_dir @ np.array([[c, -s_], [s_, c]]).T
    idx, ok = associate_landmarks(moved, dirs, lm.target_xy, lm.target_dir, gate_m)
    sigma = np.sqrt(lm.source_sigma_m**2 + lm.target_sigma_m[idx] ** 2)
    return lm.source_xy, lm.target_xy[idx], lm.target_dir[idx], ok, sigma


def _nearest_on_polylines(
    points: np.ndarray, target_x: np.ndarray, target_y: np.ndarray, n_vertices: np.ndarray
):
    """For each point, its nearest segment on its own target polyline (row ``p`` of
    ``target_x, target_y (P, L)``, padded with ``FAR_M``, ``n_vertices (P,)`` each, ~1-2 m apart; the two
    segments around the nearest vertex are compared): foot, normal, and validity (False beyond
    the polyline's ends). Coordinates are kept in separate arrays (reductions over a trailing
    axis of 2 are slow)."""
    d2 = (points[:, 0, None] - target_x) ** 2 + (points[:, 1, None] - target_y) ** 2
    v = np.argmin(d2, axis=1)
    n = n_vertices
    P = len(points)
    seg = np.stack([np.clip(v - 1, 0, n - 2), np.clip(v, 0, n - 2)], axis=1).ravel()
    rows = np.repeat(np.arange(P), 2)
    seg_a = np.column_stack([target_x[rows, seg], target_y[rows, seg]])
    seg_b = np.column_stack([target_x[rows, seg + 1], target_y[rows, seg + 1]])
    foot, normal, u_raw, dist = point_to_segments(np.repeat(points, 2, axis=0), seg_a, seg_b)
    pick = np.argmin(dist.reshape(P, 2), axis=1)
    sel = np.arange(P) * 2 + pick
    best = seg[sel]
    valid = ~(((best == 0) & (u_raw[sel] < 0.0)) | ((best == n - 2) & (u_raw[sel] > 1.0)))
    return foot[sel], normal[sel], valid


def _subsample(points: np.ndarray, n_max: int) -> np.ndarray:
    if len(points) <= n_max:
        return points
    return points[np.linspace(0, len(points) - 1, n_max).round().astype(int)]


def register_elements(
    target: ElementSet,
    source: ElementSet,
    matches: Sequence[tuple[int, int]],
    point_sigma_m: float,
    params: AlignmentParams,
    closed_target: Sequence[bool] | None = None,
    initial_xyyaw: np.ndarray | None = None,
    landmarks: LandmarkSets | None = None,
) -> Registration | None:
    """GNC-TLS registration of ``source`` onto ``target`` over matched elements ``(k, k')``
    (``k`` in target, ``k'`` in source). None when fewer than ``min_matched_elements`` remain.

    ``landmarks`` (dash ends) add one row each, along the dash: associated every step to the
    nearest target end of the same kind within a gate kept below half the dash period (read
    from the target), TLS-weighted with the other rows in units of their own sigma."""
    if len(matches) < 1:
        return None
    closed_target = closed_target or [False] * len(target)
    # polygons (crosswalks, markings): their centroid, point to point (an outline matched point
    # to line slides onto the next parallel edge of a wide crosswalk); lines: vertices
    fixed_foot: list[np.ndarray] | np.ndarray  # the rows, then stacked
    fixed_normal: list[np.ndarray] | np.ndarray
    src, fixed_foot, fixed_normal = [], [], []
    for k, kp in matches:
        if closed_target[k]:
            c_src, c_tgt = source.points[kp].mean(axis=0), target.points[k].mean(axis=0)
            src.append(np.vstack([c_src, c_src]))
            fixed_foot.append(np.vstack([c_tgt, c_tgt]))
            fixed_normal.append(np.eye(2))
        else:
            p = _subsample(source.points[kp], MAX_POINTS_PER_ELEMENT)
            src.append(p)
            fixed_foot.append(np.full((len(p), 2), np.nan))
            fixed_normal.append(np.full((len(p), 2), np.nan))
    owner = np.concatenate([np.full(len(p), m) for m, p in enumerate(src)])
    lengths = np.array([2 if closed_target[k] else len(target.points[k]) for k, _ in matches])
    padded = np.full((len(matches), max(int(lengths.max()), 2), 2), FAR_M)  # never the nearest vertex
    for m, (k, _) in enumerate(matches):
        if not closed_target[k]:
            padded[m, : lengths[m]] = target.points[k]
        else:
            padded[m, :2] = 0.0
    src_pts = np.vstack(src)
    fixed_foot, fixed_normal = np.vstack(fixed_foot), np.vstack(fixed_normal)
    is_fixed = np.isfinite(fixed_foot[:, 0])
    delta = np.zeros(3) if initial_xyyaw is None else np.asarray(initial_xyyaw, float).copy()
    if is_fixed.any():  # start from the polygons' mean centroid offset (a unique basin)
        off = (fixed_foot[is_fixed] - se2.transform_points(delta, src_pts[is_fixed])).mean(axis=0)
        delta = se2.compose(np.array([off[0], off[1], 0.0]), delta)
    # a prior at the start pose keeps directions the elements do not observe (along a straight
    # road) where the initial pose put them instead of letting them drift
    delta0 = delta.copy()
    H_prior = np.diag(
        [1 / params.registration_prior_sigma_xy_m**2] * 2 + [1 / params.registration_prior_sigma_yaw_rad**2]
    )
    c_bar = params.gnc_inlier_k  # in units of each row's sigma
    n_line = len(src_pts)
    gate = (
        landmark_gate_m(landmarks.target_xy, landmarks.target_dir, landmarks.gate_max_m) if landmarks else 0.0
    )
    target_x, target_y, n_vertices = (
        padded[owner, :, 0],
        padded[owner, :, 1],
        lengths[owner],
    )  # per source point
    mu = None
    w = np.ones(n_line)
    for outer in range(params.gnc_max_outer + 1):
        moved = se2.transform_points(delta, src_pts)
        foot, normal, valid = _nearest_on_polylines(moved, target_x, target_y, n_vertices)
        foot[is_fixed], normal[is_fixed], valid[is_fixed] = fixed_foot[is_fixed], fixed_normal[is_fixed], True
        sig = np.full(n_line, point_sigma_m)
        if landmarks is not None:
            lp, lf, ln, lv, ls = _landmark_rows(delta, landmarks, gate)
            sig = np.concatenate([sig, ls])
            moved = np.vstack([moved, se2.transform_points(delta, lp)])
            foot, normal, valid = np.vstack([foot, lf]), np.vstack([normal, ln]), np.concatenate([valid, lv])
        r = np.einsum("ij,ij->i", normal, moved - foot)
        r2 = np.where(valid, (r / sig) ** 2, 0.0)
        if mu is None:
            r_max2 = float(r2[valid].max()) if valid.any() else 0.0
            mu = c_bar**2 / max(2 * r_max2 - c_bar**2, 1e-9) if r_max2 > c_bar**2 else 1e6
        # TLS surrogate weights
        lo, hi = mu / (mu + 1) * c_bar**2, (mu + 1) / mu * c_bar**2
        w = np.where(
            r2 <= lo,
            1.0,
            np.where(r2 >= hi, 0.0, c_bar * np.sqrt(mu * (mu + 1)) / np.sqrt(np.maximum(r2, 1e-12)) - mu),
        )
        w = np.clip(w, 0.0, 1.0) * valid
        J = np.column_stack([normal, normal[:, 0] * -moved[:, 1] + normal[:, 1] * moved[:, 0]])
        wj = J * (w / sig**2)[:, None]
        H = wj.T @ J + H_prior
        dev = np.r_[delta[:2] - delta0[:2], se2.wrap_angle(delta[2] - delta0[2])]
        g = wj.T @ r + H_prior @ dev
        step = -np.linalg.solve(H, g)
        sensitivity = np.linalg.solve(H, H_prior)  # of the solution on delta0, at this step's weights
        delta = se2.compose(step, delta)
        if outer == params.gnc_max_outer or (mu >= 1e2 and np.linalg.norm(step) < 1e-4):
            break
        mu = min(mu * GNC_MU_FACTOR, 1e6)
    inlier_pts = w[:n_line] > 0.5
    element_inlier = np.array(
        [np.sum(inlier_pts[owner == m]) >= max(2, 0.5 * np.sum(owner == m)) for m in range(len(matches))]
    )
    if element_inlier.sum() < params.min_matched_elements:
        return None
    sel = inlier_pts & element_inlier[owner]
    r_line = r[:n_line]
    rms = float(np.sqrt(np.mean(r_line[sel] ** 2))) if sel.any() else float("inf")
    J_all = np.column_stack([normal, normal[:, 0] * -moved[:, 1] + normal[:, 1] * moved[:, 0]])
    J = J_all[:n_line][sel]
    # points of one element share its perception error: count ~2 independent samples per element
    n_eff = 2.0 * element_inlier.sum()
    info = J.T @ J / point_sigma_m**2 * (n_eff / max(len(J), 1))
    if landmarks is not None:  # each landmark is its own (independent) sample
        lm_in = w[n_line:] > 0.5
        J_lm = J_all[n_line:][lm_in]
        info += (J_lm / sig[n_line:][lm_in, None] ** 2).T @ J_lm
    info += np.diag([1 / UNOBSERVED_SIGMA_XY_M**2] * 2 + [1 / UNOBSERVED_SIGMA_YAW_RAD**2])  # invertible only
    return Registration(delta, info, element_inlier, rms, int(sel.sum()), sensitivity)


def match_confidence(
    target: ElementSet,
    source_aligned: ElementSet,
    matches: Sequence[tuple[int, int]],
    noise: NoiseScales,
    params: AlignmentParams,
    target_distances: np.ndarray | None = None,
) -> np.ndarray:
    """Eq. 7 per match: ``c = w s_kk' + (1-w) mean_l' s_kl,k'l'`` after alignment
    (``target_distances``: ``element_distances(target)`` when already known)."""
    if not matches:
        return np.zeros(0)
    s = node_similarity(target, source_aligned, noise, params)
    k = np.array([m[0] for m in matches])
    kp = np.array([m[1] for m in matches])
    node = s[k, kp]
    if len(matches) > 1:
        e_t = element_distances(target) if target_distances is None else target_distances
        e_s = element_distances(source_aligned)
        pair = np.exp(-0.5 * ((e_t[np.ix_(k, k)] - e_s[np.ix_(kp, kp)]) / noise.sigma_e_m) ** 2)  # Eq. 6
        np.fill_diagonal(pair, 0.0)
        edge = pair.sum(axis=1) / (len(matches) - 1)
    else:
        edge = np.ones(1)
    w = params.node_position_weight
    return w * node + (1 - w) * edge
