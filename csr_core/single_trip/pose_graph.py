"""Single-trip pose smoothing (paper Eq. 2): odometry between-factors + robust GNSS priors.

    X_hat = argmin_X  sum_t ||e_o(x_t, x_t+1, o_t,t+1)||^2_{Omega_o} + rho(||e_g(x_t, g_t)||^2_{Omega_g})

Built-in gtsam factors only (Python custom factors are 30-100x slower):
``BetweenFactorPose2`` for odometry increments (sigma grows with the distance travelled),
``PoseTranslationPrior2D`` for GNSS positions (sigma from the receiver's ``std_m``, else from the
status table), ``PoseRotationPrior2D`` for the GNSS course when the vehicle moves (one per node;
or, off by default, every fix's with its sigma measured on the trip: ``gnss_course``). Frames
without a fix get no GNSS factor: odometry alone bridges them. Two LM stages with the fixes as
white noise (inflated by their correlation time): Huber from a robust rigid fit of the odometry
to GNSS (convex, so the warm start is safe), then Cauchy from the Huber solution, which leaves
GNSS jumps (tunnels, urban canyons) with almost no weight. A last solve on the fixes kept (``GNSS_BIAS_STATE``, on) holds the GNSS error as a
Gauss-Markov bias state (``gnss_bias``), so that its slow wander does not bend the trip.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from csr_core import se2
from csr_core.errors import ReconstructionError
from csr_core.single_trip.gnss_bias import build_bias_graph, run_sigmas_m, white_sigmas_m
from csr_core.single_trip.gnss_course import CourseNoise, course_noise
from csr_core.single_trip.keyframes import every_travel_or_time
from csr_core.single_trip.params import SingleTripParams
from csr_core.types import GnssStatus

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SmoothedPoses:
    poses_xyyaw_world: np.ndarray  # (N, 3) world_T_vehicle
    sigma_xy_m: np.ndarray  # (N,) approximate marginal horizontal sigma
    gnss_sigma_m: np.ndarray  # (N,) sigma used per GNSS factor (inf: no factor)
    gnss_inlier: np.ndarray  # (N,) bool, fix kept by the robust kernel
    world_T_odom_fit: np.ndarray  # (3,) the rigid initial fit, for diagnostics
    odom_scale: float = 1.0  # estimated odometry distance scale (applied)
    odom_yaw_rate_bias_rad_s: float = 0.0  # estimated yaw-rate bias (removed)
    gnss_latency_s: float = 0.0  # estimated GNSS latency (compensated)
    # with ``GNSS_BIAS_STATE``: the poses of the white-noise solve before the bias state (the
    # alignment's e^sm chain takes a trip's relative poses from them); None without it
    white_poses_xyyaw_world: np.ndarray | None = None

    @classmethod
    def given(cls, poses_xyyaw_world: np.ndarray) -> SmoothedPoses:
        """``poses_xyyaw_world (N, 3)`` taken as they are, in place of the smoothing (the true
        poses, to measure the element stages alone): no sigma, every fix an inlier."""
        n = len(poses_xyyaw_world)
        return cls(
            np.array(poses_xyyaw_world, dtype=float), np.zeros(n), np.zeros(n), np.ones(n, bool), np.zeros(3)
        )


def gnss_sigmas_m(
    status: np.ndarray, std_m: np.ndarray, params: SingleTripParams, floor_m: float | None = None
) -> np.ndarray:
    """Per-frame GNSS sigma (N,): the receiver's ``std_m`` when given, else the status table,
    at least ``floor_m`` (default ``GNSS_SIGMA_FLOOR_M``); ``inf`` where there is no fix."""
    table = np.asarray(params.GNSS_SIGMA_BY_STATUS_M, float)
    status = np.asarray(status, int)
    sigma = np.where(np.isfinite(std_m) & (std_m > 0), std_m, table[np.clip(status, 0, len(table) - 1)])
    sigma = np.maximum(sigma, params.GNSS_SIGMA_FLOOR_M if floor_m is None else floor_m)
    sigma[status == GnssStatus.NONE] = np.inf
    return sigma


def robust_rigid_fit(
    odom_xy: np.ndarray, world_xy: np.ndarray, sigma_m: np.ndarray, iterations: int = 8
) -> np.ndarray:
    """world_T_odom ``(3,)`` minimising a Huber-weighted 2D Umeyama (no scale) over pairs (M, 2)."""
    w = 1.0 / np.square(sigma_m)
    pose = np.zeros(3)
    for _ in range(iterations):
        sw = w.sum()
        mu_o = (w[:, None] * odom_xy).sum(0) / sw
        mu_w = (w[:, None] * world_xy).sum(0) / sw
        a, b = odom_xy - mu_o, world_xy - mu_w
        cross = (w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])).sum()
        dot = (w * (a * b).sum(1)).sum()
        yaw = np.arctan2(cross, dot)
        c, s = np.cos(yaw), np.sin(yaw)
        t = mu_w - np.array([c * mu_o[0] - s * mu_o[1], s * mu_o[0] + c * mu_o[1]])
        pose = np.array([t[0], t[1], yaw])
        r = np.linalg.norm(se2.transform_points(pose, odom_xy) - world_xy, axis=1) / sigma_m
        k = 1.5 * max(np.median(r), 1.0)
        w = np.where(r <= k, 1.0, k / np.maximum(r, 1e-12)) / np.square(sigma_m)
    return pose


def _odometry_speed_mps(odom_xyyaw: np.ndarray, timestamps_s: np.ndarray) -> np.ndarray:
    """(N,) speed from the odometry: the larger of the steps into and out of each frame."""
    n = len(timestamps_s)
    speed = np.zeros(n)
    if n > 1:
        v = np.linalg.norm(np.diff(odom_xyyaw[:, :2], axis=0), axis=1) / np.maximum(
            np.diff(timestamps_s), 1e-6
        )
        speed[:-1] = v
        speed[1:] = np.maximum(speed[1:], v) if n > 2 else v
    return speed


def _heading_yaw(
    heading_deg: np.ndarray, status: np.ndarray, speed_mps: np.ndarray, params: SingleTripParams
) -> np.ndarray:
    """GNSS course as yaw (rad), NaN where absent, where the frame has no new fix (status none:
    a held frame repeats its epoch's course) or the vehicle is too slow for a course."""
    yaw = np.where(np.isfinite(heading_deg), se2.heading_deg_to_yaw_rad(np.nan_to_num(heading_deg)), np.nan)
    yaw[(speed_mps < params.GNSS_HEADING_MIN_SPEED_MPS) | (np.asarray(status) == GnssStatus.NONE)] = np.nan
    return yaw


def _optimize(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, params: SingleTripParams
) -> gtsam.Values:
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(params.LM_MAX_ITERATIONS)
    lm.setRelativeErrorTol(params.LM_RELATIVE_ERROR_TOL)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, lm).optimize()


def _marginal_sigma_xy(gnss_var: np.ndarray, step_var: np.ndarray) -> np.ndarray:
    """Closed-form marginal position sigma (N,): a scalar random-walk Kalman smoother (RTS) with
    per-frame GNSS variance ``gnss_var`` (inf: none) and odometry variance ``step_var`` (N-1,)
    between frames. Cheap stand-in for ``gtsam.Marginals`` (same model, isotropic, linear)."""
    n = len(gnss_var)
    big = 1e8
    # plain floats in the recursions (a numpy scalar per step costs ten times more)
    gnss_info = np.where(
        np.isfinite(gnss_var), 1.0 / np.where(np.isfinite(gnss_var), gnss_var, 1.0), 0.0
    ).tolist()
    steps = np.asarray(step_var, float).tolist()
    pf = [0.0] * n
    p = big
    for t in range(n):
        p = 1.0 / (1.0 / p + gnss_info[t])
        pf[t] = p
        if t < n - 1:
            p = p + steps[t]
    ps = pf.copy()
    for t in range(n - 2, -1, -1):
        pred = pf[t] + steps[t]
        g = pf[t] / pred
        ps[t] = pf[t] + g * g * (ps[t + 1] - pred)
    return np.sqrt(np.clip(np.asarray(ps), 0.0, big))


def integrate_increments(first_xyyaw: np.ndarray, incr_xyyaw: np.ndarray) -> np.ndarray:
    """Poses (N, 3) from a first pose and N-1 body-frame increments (vectorised: cumulative yaw,
    then rotated steps summed)."""
    yaw = first_xyyaw[2] + np.r_[0.0, np.cumsum(incr_xyyaw[:, 2])]
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    dx = c * incr_xyyaw[:, 0] - s * incr_xyyaw[:, 1]
    dy = s * incr_xyyaw[:, 0] + c * incr_xyyaw[:, 1]
    x = first_xyyaw[0] + np.r_[0.0, np.cumsum(dx)]
    y = first_xyyaw[1] + np.r_[0.0, np.cumsum(dy)]
    return np.column_stack([x, y, se2.wrap_angle(yaw)])


def interpolate_poses(timestamps_s: np.ndarray, poses_xyyaw: np.ndarray, at_s: np.ndarray) -> np.ndarray:
    """Poses (M, 3) at times ``at_s`` by linear interpolation (yaw unwrapped), clamped at the ends."""
    yaw = np.unwrap(poses_xyyaw[:, 2])
    return np.column_stack(
        [
            np.interp(at_s, timestamps_s, poses_xyyaw[:, 0]),
            np.interp(at_s, timestamps_s, poses_xyyaw[:, 1]),
            se2.wrap_angle(np.interp(at_s, timestamps_s, yaw)),
        ]
    )


def estimate_latency_s(
    timestamps_s: np.ndarray,
    odom_xyyaw: np.ndarray,
    gnss_xy_world: np.ndarray,
    inlier: np.ndarray,
    window_s: float,
    max_s: float,
    step_s: float = 0.01,
    robust_z: float = 3.0,
) -> tuple[float, float]:
    """GNSS latency L (s) and odometry distance scale: the fix stamped t is the position at t - L.

    For each candidate L, the odometry at t - L is fitted to the fixes in windows of
    ``window_s``, each window with its own rotation and translation (the slowly varying GNSS
    bias and the odometry heading drift drop out) and one scale shared by all windows (closed
    form); L minimises the summed residual, refined by a parabola. Where speed and heading do
    not change within a window, L has no effect there and is not seen. The windows are summed as a
    generalised least squares, each weighted by its own residual variance
    (:func:`_window_weights`), so a window with a multipath excursion does not set the scale.

    L is kept only where it explains the data: a drop of the cost against L = 0 of more than 3
    sigma of a chi-square(1) on the residual variance, and L more than ``robust_z`` standard
    deviations from 0 with the windows as independent clusters (:func:`_window_robust_sd_s`): the
    chi-square test counts every fix as independent, and passed a spurious 5-13 ms on 15 of 40
    simulated trips whose receivers time-tag at the epoch."""
    idx = np.flatnonzero(inlier)
    if len(idx) < 50:
        return 0.0, 1.0
    t = timestamps_s[idx]
    wid = np.floor((t - t[0]) / window_s).astype(np.int64)
    n_w = int(wid.max()) + 1
    cnt = np.maximum(np.bincount(wid, minlength=n_w), 1).astype(float)
    g = gnss_xy_world[idx]
    mg = np.column_stack([np.bincount(wid, g[:, k], n_w) / cnt for k in range(2)])
    b = g - mg[wid]
    bb = np.bincount(wid, (b * b).sum(1), n_w)
    grid = np.arange(0.0, max_s + 1e-9, step_s)  # a fix cannot come from the future
    h_w = np.empty((len(grid), n_w))  # per window: |sum a x b| (rotation-aligned cross-moment)
    aa_w = np.empty((len(grid), n_w))
    ox, oy = odom_xyyaw[:, 0], odom_xyyaw[:, 1]
    for i, lat in enumerate(grid):
        o = np.column_stack([np.interp(t - lat, timestamps_s, ox), np.interp(t - lat, timestamps_s, oy)])
        mo = np.column_stack([np.bincount(wid, o[:, k], n_w) / cnt for k in range(2)])
        a = o - mo[wid]
        cross = np.bincount(wid, a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], n_w)
        dot = np.bincount(wid, (a * b).sum(1), n_w)
        aa_w[i] = np.bincount(wid, (a * a).sum(1), n_w)
        h_w[i] = np.hypot(cross, dot)
    # generalised least squares over the windows: each window's sums weighted by the inverse of
    # its own residual variance, so a window with a multipath jump (or worse fixes) does not set
    # the shared scale. The weights are read at the unweighted minimum, then at the weighted one,
    # twice.
    bb_g, h_g, aa_g = bb, h_w, aa_w
    scale, cost = _shared_scale_and_cost(bb_g, h_g, aa_g)
    lat, k = _refined_argmin(cost, grid, step_s)
    for _ in range(2):
        weight = _window_weights(bb, h_w[k], aa_w[k], cnt)
        bb_g, h_g, aa_g = bb * weight, h_w * weight, aa_w * weight
        scale, cost = _shared_scale_and_cost(bb_g, h_g, aa_g)
        lat, k = _refined_argmin(cost, grid, step_s)
    # the two tests of the docstring (chi-square(1) at 3 sigma, then windows as clusters)
    dof = max(2 * len(idx) - 4 * n_w - 2, 1)
    if cost[0] - cost[k] <= 9.0 * cost[k] / dof or (
        n_w >= 2 and lat <= robust_z * _window_robust_sd_s(lat, k, bb_g, h_g, aa_g, grid, step_s)
    ):
        return 0.0, float(scale[0])
    return lat, float(scale[k])


def _shared_scale_and_cost(
    bb_w: np.ndarray, h_w: np.ndarray, aa_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per latency candidate (rows of ``h_w`` and ``aa_w``): the scale shared by all windows and
    the summed residual at it (closed form)."""
    scale = h_w.sum(1) / np.maximum(aa_w.sum(1), 1e-12)
    return scale, bb_w.sum() - h_w.sum(1) * scale


def _window_weights(bb_w: np.ndarray, h_w: np.ndarray, aa_w: np.ndarray, count_w: np.ndarray) -> np.ndarray:
    """Inverse residual variance (1/m^2) of each window fitted on its own (rotation, translation and
    scale: 4 parameters), normalised to a mean of 1; at least 1 cm of residual."""
    resid = np.maximum(bb_w - h_w**2 / np.maximum(aa_w, 1e-12), 0.0) / np.maximum(2.0 * count_w - 4.0, 1.0)
    w = 1.0 / np.maximum(resid, 1e-4)
    return w / w.mean()


def _refined_argmin(cost: np.ndarray, grid: np.ndarray, step_s: float) -> tuple[float, int]:
    """The grid minimum of ``cost`` refined by a parabola through it and its neighbours, and its index."""
    k = int(np.argmin(cost))
    lat = float(grid[k])
    if 0 < k < len(grid) - 1:
        c0, c1, c2 = cost[k - 1], cost[k], cost[k + 1]
        den = c0 - 2 * c1 + c2
        if den > 0:
            lat = float(grid[k] + 0.5 * step_s * (c0 - c2) / den)
    return lat, k


def _window_robust_sd_s(
    lat: float, k: int, bb_w: np.ndarray, h_w: np.ndarray, aa_w: np.ndarray, grid: np.ndarray, step_s: float
) -> float:
    """Standard deviation (s) of the latency estimate ``lat`` (grid index ``k``) with the windows as
    independent clusters (the sandwich, or cluster-robust, variance: sum of squared per-window
    scores over the squared summed curvature, times ``n / (n - 1)``). Each window's cost at the
    shared scale is ``bb - 2 s h(L) + s^2 aa(L)``; scores and curvatures are finite differences on
    the grid. Within a window the GNSS error is correlated over seconds, so the fixes are not
    independent (the chi-square test's assumption), but windows ``window_s`` apart nearly are."""
    n_w = len(bb_w)
    kk = min(max(k, 1), len(grid) - 2)
    scale = h_w[kk].sum() / max(aa_w[kk].sum(), 1e-12)
    cost_w = bb_w[None, :] - 2.0 * scale * h_w[kk - 1 : kk + 2] + scale**2 * aa_w[kk - 1 : kk + 2]
    curvature_w = (cost_w[2] - 2.0 * cost_w[1] + cost_w[0]) / step_s**2
    score_w = (cost_w[2] - cost_w[0]) / (2.0 * step_s) + curvature_w * (lat - grid[kk])
    return float(np.sqrt(n_w / (n_w - 1) * np.sum(np.square(score_w))) / max(abs(curvature_w.sum()), 1e-12))


@dataclass(frozen=True, slots=True)
class YawRateBias:
    """The odometry yaw-rate bias of one trip (rad/s): the posterior of the chord estimate
    (:func:`estimate_yaw_rate_bias`) under the physical prior ``N(0, CAL_YAW_RATE_BIAS_PRIOR_RAD_S)``.
    ``independent_chords`` is the number of non-overlapping chords behind it; ``estimated`` is
    False when there were too few, and the bias is then the prior's (0, prior sigma)."""

    bias_rad_s: float
    sigma_rad_s: float
    independent_chords: int
    estimated: bool


def calibrate_yaw_rate_bias(
    timestamps_s: np.ndarray,
    odom_xyyaw: np.ndarray,
    gnss_xy_world: np.ndarray,
    gnss_sigma_m: np.ndarray,
    inlier: np.ndarray,
    params: SingleTripParams,
) -> YawRateBias:
    """The trip's odometry yaw-rate bias with its uncertainty: the chord estimate combined with
    the physical prior (a product of Gaussians: the estimate is shrunk towards 0 by how little
    the chords say). Not estimated (the prior alone) for a trip shorter than
    ``CAL_MIN_DURATION_S`` or ``2 CAL_WINDOW_M``, or with fewer than ``CAL_MIN_INDEPENDENT_CHORDS``
    non-overlapping chords: a trip that laps a loop shorter than the chord window has no
    evidence of a slow heading drift, however many overlapping chords its first seconds give."""
    prior = params.CAL_YAW_RATE_BIAS_PRIOR_RAD_S
    travel = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(odom_xyyaw[:, :2], axis=0), axis=1))]
    if timestamps_s[-1] - timestamps_s[0] < params.CAL_MIN_DURATION_S or travel[-1] < 2 * params.CAL_WINDOW_M:
        return YawRateBias(0.0, prior, 0, False)
    bias, sigma, n_chords = estimate_yaw_rate_bias(
        timestamps_s, odom_xyyaw, gnss_xy_world, gnss_sigma_m, inlier, params.CAL_WINDOW_M
    )
    if n_chords < params.CAL_MIN_INDEPENDENT_CHORDS or not np.isfinite(sigma):
        return YawRateBias(0.0, prior, n_chords, False)
    info = 1.0 / prior**2 + 1.0 / sigma**2
    return YawRateBias(float(bias / sigma**2 / info), float(np.sqrt(1.0 / info)), n_chords, True)


def _independent_chords(
    travel_m: np.ndarray, idx: np.ndarray, window_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b) of fix indices ``window_m`` of travel apart that share no stretch: each chord
    starts where the previous one ended, so no two measure the same piece of road."""
    starts, ends = [], []
    travel_idx = travel_m[idx]
    k = 0
    while k < len(idx):
        j = int(np.searchsorted(travel_idx, travel_idx[k] + window_m))
        if j >= len(idx):
            break
        starts.append(idx[k])
        ends.append(idx[j])
        k = j
    return np.asarray(starts, int), np.asarray(ends, int)


def estimate_yaw_rate_bias(
    timestamps_s: np.ndarray,
    odom_xyyaw: np.ndarray,
    gnss_xy_world: np.ndarray,
    gnss_sigma_m: np.ndarray,
    inlier: np.ndarray,
    window_m: float,
) -> tuple[float, float, int]:
    """Constant odometry yaw-rate bias (rad/s) from chords, with its standard deviation and the
    number of chords behind it: over pairs of GNSS inlier fixes ``window_m`` of travel apart
    that share no stretch (:func:`_independent_chords`), the odometry chord is the true chord
    turned by the odometry heading error of the stretch, ``c + b t`` (``t`` the time at
    mid-travel); the angle between the odometry and GNSS chords, fitted linearly in ``t``
    (weighted by chord length over GNSS sigma, 3-sigma trimming), gives ``b``. Its sigma is the
    fit's, from the robust spread of the residuals, with the chords as independent pieces of
    evidence (overlapping chords would repeat the same GNSS errors and count them many times).
    Chords shorter than half the window (a loop, a turn back) say nothing of the heading and
    are left out. ``(0, inf, n)`` when fewer than three chords remain."""
    travel = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(odom_xyyaw[:, :2], axis=0), axis=1))]
    idx = np.flatnonzero(inlier)
    if len(idx) < 10:
        return 0.0, np.inf, 0
    a, b = _independent_chords(travel, idx, window_m)
    d_odo = odom_xyyaw[b, :2] - odom_xyyaw[a, :2]
    d_gnss = gnss_xy_world[b] - gnss_xy_world[a]
    length = np.linalg.norm(d_odo, axis=1)
    good = length > 0.5 * window_m
    n = int(good.sum())
    if n < 3:
        return 0.0, np.inf, n
    a, b, d_odo, d_gnss, length = a[good], b[good], d_odo[good], d_gnss[good], length[good]
    angle = np.arctan2(d_odo[:, 1], d_odo[:, 0]) - np.arctan2(d_gnss[:, 1], d_gnss[:, 0])
    w = np.square(length) / (np.square(gnss_sigma_m[a]) + np.square(gnss_sigma_m[b]))
    mean = np.angle(np.sum(w * np.exp(1j * angle)))
    angle = np.asarray(se2.wrap_angle(angle - mean))
    t_mid = np.interp(0.5 * (travel[a] + travel[b]), travel, timestamps_s)
    t_mid = t_mid - np.average(t_mid, weights=w)
    keep = np.ones(len(angle), bool)
    coef, slope_sigma = np.zeros(2), np.inf
    for _ in range(3):
        if keep.sum() < 3:
            return 0.0, np.inf, int(keep.sum())
        sw = np.sqrt(w[keep])
        A = np.column_stack([np.ones(keep.sum()), t_mid[keep]]) * sw[:, None]
        coef, *_ = np.linalg.lstsq(A, angle[keep] * sw, rcond=None)
        r = angle - coef[0] - coef[1] * t_mid
        # residual scale of a unit-weight chord (robust), then the slope's sigma from the normal matrix
        unit = max(1.4826 * float(np.median(np.abs(r[keep] * sw))), 1e-9)
        dof_scale = np.sqrt(keep.sum() / max(keep.sum() - 2, 1))
        cov = np.linalg.pinv(A.T @ A) * (unit * dof_scale) ** 2
        slope_sigma = float(np.sqrt(max(cov[1, 1], 0.0)))
        new_keep = np.abs(r * np.sqrt(w)) <= 3.0 * unit
        if (new_keep == keep).all():
            break
        keep = new_keep
    return float(coef[1]), slope_sigma, int(keep.sum())


def smooth_poses(
    timestamps_s: np.ndarray,
    gnss_xy_world: np.ndarray,
    gnss_status: np.ndarray,
    gnss_std_m: np.ndarray,
    gnss_heading_deg: np.ndarray,
    odom_xyyaw: np.ndarray,
    params: SingleTripParams,
) -> SmoothedPoses:
    """Eq. 2 for one trip. Arrays (N,...) in upload order; returns world_T_vehicle per frame.

    Recipe: robust rigid fit (warm start) -> Huber LM -> reject GNSS jumps -> calibrate the
    odometry (scale, yaw-rate bias) against the kept fixes -> Cauchy LM with rejection rounds ->
    optionally the kept fixes with a Gauss-Markov bias state (``GNSS_BIAS_STATE``).
    """
    n = len(timestamps_s)
    timestamps_s = np.asarray(timestamps_s, float)
    sigma = gnss_sigmas_m(gnss_status, gnss_std_m, params)
    has_fix = np.isfinite(sigma) & np.all(np.isfinite(gnss_xy_world), axis=1)
    sigma[~has_fix] = np.inf
    fix_idx = np.flatnonzero(has_fix)
    # GNSS errors are correlated over GNSS_CORRELATION_S: the fixes inside that time carry about
    # one fix's information, so each factor's sigma is inflated by sqrt(fixes per correlation time)
    if len(fix_idx) > 1:
        rate_hz = 1.0 / max(float(np.median(np.diff(timestamps_s[fix_idx]))), 1e-3)
        inflation = np.sqrt(max(1.0, rate_hz * params.GNSS_CORRELATION_S))
    else:
        inflation = 1.0
    if len(fix_idx) == 0:
        raise ReconstructionError("trip has no GNSS fix: it cannot be placed in the world")
    if n < 2:
        raise ReconstructionError("trip has fewer than two frames")

    # warm start: odometry rigidly fitted to GNSS (robust); fixes too close together need the course
    spread = np.ptp(odom_xyyaw[fix_idx, :2], axis=0).max() if len(fix_idx) > 1 else 0.0
    speed = _odometry_speed_mps(odom_xyyaw, timestamps_s)
    heading_yaw = _heading_yaw(gnss_heading_deg, gnss_status, speed, params)
    course = (
        course_noise(heading_yaw, odom_xyyaw[:, 2], speed, timestamps_s, params)
        if params.GNSS_HEADING_PER_FIX
        else None
    )
    if spread > 3.0 * np.median(sigma[fix_idx]) + 1.0:
        world_T_odom = robust_rigid_fit(odom_xyyaw[fix_idx, :2], gnss_xy_world[fix_idx], sigma[fix_idx])
    else:
        with_course = np.flatnonzero(np.isfinite(heading_yaw) & has_fix)
        if len(with_course) == 0:
            raise ReconstructionError("trip GNSS fixes span too little distance to fix its orientation")
        i = with_course[0]
        world_T_odom = np.array([0.0, 0.0, float(se2.wrap_angle(heading_yaw[i] - odom_xyyaw[i, 2]))])
        rot_xy = se2.transform_points(world_T_odom, odom_xyyaw[fix_idx, :2])
        world_T_odom[:2] = np.median(gnss_xy_world[fix_idx] - rot_xy, axis=0)

    # graph nodes: every POSE_NODE_SPACING_M of travel (or POSE_NODE_PERIOD_S); frames in
    # between follow the odometry. Chosen once, on the uploaded odometry.
    dist0 = np.linalg.norm(np.diff(odom_xyyaw[:, :2], axis=0), axis=1)
    nodes = every_travel_or_time(
        np.r_[0.0, np.cumsum(dist0)],
        timestamps_s,
        params.POSE_NODE_SPACING_M,
        params.POSE_NODE_PERIOD_S,
        keep_last=True,
    )
    graph = _NodeGraph(
        nodes,
        timestamps_s,
        odom_xyyaw,
        gnss_xy_world,
        sigma,
        heading_yaw,
        course,
        params,
        factor_inflation=inflation,
        yaw_rate_bias_sigma_rad_s=params.CAL_YAW_RATE_BIAS_PRIOR_RAD_S,
    )
    node_poses = se2.compose(world_T_odom[None, :], odom_xyyaw[nodes])

    # stage 1: Huber from the rigid fit (convex in position: safe from a rough start)
    node_poses = graph.solve("huber", fix_idx, node_poses)
    inlier, _ = graph.reject(node_poses, has_fix, has_fix)
    # odometry calibration against the kept fixes: yaw-rate bias from GNSS/odometry chords, then
    # GNSS latency and odometry scale jointly from windowed fits; the graph on the result
    scale, latency, yaw_bias = 1.0, 0.0, 0.0
    yaw_cal = YawRateBias(0.0, params.CAL_YAW_RATE_BIAS_PRIOR_RAD_S, 0, False)
    if params.CAL_ENABLED:
        yaw_cal = calibrate_yaw_rate_bias(timestamps_s, odom_xyyaw, gnss_xy_world, sigma, inlier, params)
        yaw_bias = yaw_cal.bias_rad_s
        incr = se2.between(odom_xyyaw[:-1], odom_xyyaw[1:])
        incr[:, 2] -= yaw_bias * np.diff(timestamps_s)
        corrected = integrate_increments(odom_xyyaw[0], incr)
        if timestamps_s[-1] - timestamps_s[0] >= params.CAL_MIN_DURATION_S:
            latency, scale = estimate_latency_s(
                timestamps_s,
                corrected,
                gnss_xy_world,
                inlier,
                params.GNSS_LATENCY_WINDOW_S,
                params.GNSS_LATENCY_MAX_S,
                robust_z=params.GNSS_LATENCY_ROBUST_Z,
            )
            if not params.GNSS_LATENCY_ESTIMATE:
                latency = 0.0
            scale = float(np.clip(scale, 1.0 - params.CAL_MAX_SCALE_ERROR, 1.0 + params.CAL_MAX_SCALE_ERROR))
            incr[:, :2] *= scale
            corrected = integrate_increments(odom_xyyaw[0], incr)
        graph = _NodeGraph(
            nodes,
            timestamps_s,
            corrected,
            gnss_xy_world,
            sigma,
            heading_yaw,
            course,
            params,
            latency,
            factor_inflation=inflation,
            yaw_rate_bias_sigma_rad_s=yaw_cal.sigma_rad_s,
        )
    # stage 2: hard rejection of GNSS jumps at a data-scaled threshold, Cauchy on the rest,
    # warm-started; repeated while the inlier set changes (GNC-like, with a warm start)
    node_poses = graph.solve("cauchy", np.flatnonzero(inlier), node_poses)
    for _ in range(params.GNSS_REJECTION_ROUNDS):
        inlier, changed = graph.reject(node_poses, has_fix, inlier)
        if not changed:
            break
        node_poses = graph.solve("cauchy", np.flatnonzero(inlier), node_poses)
    white_poses = None
    if params.GNSS_BIAS_STATE:
        white_poses = graph.frame_poses(node_poses)
        # the bias's own sigma is the receiver's, unfloored: an RTK fix's 2 cm, not the white
        # stages' 5 cm floor (which would let the odometry move a fixed spell by that much)
        bias_sigma = run_sigmas_m(
            gnss_status, gnss_sigmas_m(gnss_status, gnss_std_m, params, floor_m=params.GNSS_WHITE_SIGMA_MIN_M)
        )
        node_poses = graph.solve_with_bias(node_poses, timestamps_s, gnss_status, bias_sigma, inlier)
    poses = graph.frame_poses(node_poses)

    gnss_var = np.where(inlier, np.square(sigma * inflation), np.inf)
    sigma_xy = _marginal_sigma_xy(gnss_var, graph.step_var)
    log.debug(
        "pose graph: %d frames, %d nodes, %d fixes, %d rejected, scale %.4f, yaw bias %.4f deg/s",
        n,
        len(nodes),
        len(fix_idx),
        int((~inlier[fix_idx]).sum()),
        scale,
        np.degrees(yaw_bias),
    )
    log.debug("gnss latency %.3f s", latency)
    return SmoothedPoses(poses, sigma_xy, sigma, inlier, world_T_odom, scale, yaw_bias, latency, white_poses)


class _NodeGraph:
    """The Eq. 2 graph on node frames. Each frame's GNSS fix is attached to its node through
    the odometry lever node_T_frame (``PoseTranslationPrior2D`` takes no lever arm, so the fix
    is moved by it, with the node's current yaw); frames in between follow the odometry."""

    def __init__(
        self,
        nodes: np.ndarray,
        timestamps_s: np.ndarray,
        odom_xyyaw: np.ndarray,
        gnss_xy_world: np.ndarray,
        sigma: np.ndarray,
        heading_yaw: np.ndarray,
        course: CourseNoise | None,
        params: SingleTripParams,
        gnss_latency_s: float = 0.0,
        factor_inflation: float = 1.0,
        yaw_rate_bias_sigma_rad_s: float = 0.0,
    ) -> None:
        n = len(timestamps_s)
        self.params = params
        self.odom = odom_xyyaw
        self.nodes = nodes
        self.gnss_xy = gnss_xy_world
        self.sigma = sigma  # per fix, as reported: the outlier test
        self.factor_sigma = sigma * factor_inflation  # in the graph (correlated fixes)
        incr = se2.between(odom_xyyaw[:-1], odom_xyyaw[1:])
        dist = np.linalg.norm(incr[:, :2], axis=1)
        dt = np.diff(timestamps_s)
        sig_xy = params.ODOM_SIGMA_XY_FLOOR_M + params.ODOM_SIGMA_XY_PER_M * dist
        # the gyro's own drift and what is left of its bias after the calibration (its posterior sigma)
        yaw_per_s = float(np.hypot(params.ODOM_SIGMA_YAW_PER_S, yaw_rate_bias_sigma_rad_s))
        sig_yaw = params.ODOM_SIGMA_YAW_FLOOR_RAD + params.ODOM_SIGMA_YAW_PER_M * dist + yaw_per_s * dt
        # lateral drift of the yaw uncertainty adds to the translation random walk (marginals)
        self.step_var = np.square(sig_xy) + np.square(sig_yaw * dist * 10.0)
        self.travel = np.r_[0.0, np.cumsum(dist)]
        self.node_of = np.searchsorted(nodes, np.arange(n), side="right") - 1
        self.node_T_frame = se2.between(odom_xyyaw[nodes[self.node_of]], odom_xyyaw)
        # a fix stamped t measured the position at t - latency: its lever goes to that instant
        self.node_T_fix = (
            self.node_T_frame
            if gnss_latency_s == 0.0
            else se2.between(
                odom_xyyaw[nodes[self.node_of]],
                interpolate_poses(timestamps_s, odom_xyyaw, timestamps_s - gnss_latency_s),
            )
        )
        self.node_incr = se2.between(odom_xyyaw[nodes[:-1]], odom_xyyaw[nodes[1:]])
        cum_xy = np.r_[0.0, np.cumsum(np.square(sig_xy))]
        cum_yaw = np.r_[0.0, np.cumsum(np.square(sig_yaw))]
        self.node_sig_xy = np.sqrt(cum_xy[nodes[1:]] - cum_xy[nodes[:-1]])
        self.node_sig_yaw = np.sqrt(cum_yaw[nodes[1:]] - cum_yaw[nodes[:-1]])
        self.node_heading = heading_yaw[nodes]
        self.heading_yaw = heading_yaw
        self.course = course
        self._fixed: tuple[gtsam.NonlinearFactorGraph, gtsam.NonlinearFactorGraph] | None = None
        self._gnss_models: dict[str, dict[float, gtsam.noiseModel.Base]] = {}

    def _fixed_factors(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.NonlinearFactorGraph]:
        """The odometry between-factors and the GNSS course priors: the same in every solve,
        so built once (the factors are shared by the graphs of all solves)."""
        if self._fixed is None:
            p = self.params
            odometry = gtsam.NonlinearFactorGraph()
            for k in range(len(self.nodes) - 1):
                model = gtsam.noiseModel.Diagonal.Sigmas(
                    np.array([self.node_sig_xy[k], self.node_sig_xy[k], self.node_sig_yaw[k]])
                )
                odometry.add(gtsam.BetweenFactorPose2(k, k + 1, gtsam.Pose2(*self.node_incr[k]), model))
            course = gtsam.NonlinearFactorGraph()
            head_est = gtsam.noiseModel.mEstimator.Cauchy.Create(p.GNSS_HEADING_CAUCHY_C_SIGMAS)
            if self.course is not None:
                # every fix's course on its node, the odometry's yaw from the node to the
                # instant the course refers to taken off (gnss_course.py)
                frames = self.course.frames
                measured = self.heading_yaw[frames] - self.node_T_fix[frames, 2]
                for node, yaw, sig in zip(
                    self.node_of[frames].tolist(),
                    measured.tolist(),
                    self.course.sigma_rad.tolist(),
                    strict=True,
                ):
                    one = gtsam.noiseModel.Robust.Create(head_est, gtsam.noiseModel.Isotropic.Sigma(1, sig))
                    course.add(gtsam.PoseRotationPrior2D(node, gtsam.Rot2(yaw), one))
            else:
                head_model = gtsam.noiseModel.Robust.Create(
                    head_est, gtsam.noiseModel.Isotropic.Sigma(1, p.GNSS_HEADING_SIGMA_RAD)
                )
                for node in np.flatnonzero(np.isfinite(self.node_heading)).tolist():
                    course.add(
                        gtsam.PoseRotationPrior2D(
                            node, gtsam.Rot2(float(self.node_heading[node])), head_model
                        )
                    )
            self._fixed = (odometry, course)
        return self._fixed

    def _gnss_model(self, kernel: str, sigma: float) -> gtsam.noiseModel.Base:
        """The robust (``kernel``: Huber or Cauchy) isotropic GNSS noise model of ``sigma``."""
        p = self.params
        est: gtsam.noiseModel.mEstimator.Base = (
            gtsam.noiseModel.mEstimator.Huber.Create(p.GNSS_HUBER_K_SIGMAS)
            if kernel == "huber"
            else gtsam.noiseModel.mEstimator.Cauchy.Create(p.GNSS_CAUCHY_C_SIGMAS)
        )
        return gtsam.noiseModel.Robust.Create(est, gtsam.noiseModel.Isotropic.Sigma(2, sigma))

    def fix_at_node(self, gnss_idx: np.ndarray, node_poses: np.ndarray) -> np.ndarray:
        """(M, 2) each fix moved to its node by the odometry lever, with the node's current yaw."""
        yaw = node_poses[self.node_of[gnss_idx], 2]
        c, s = np.cos(yaw), np.sin(yaw)
        lever = self.node_T_fix[gnss_idx]
        return self.gnss_xy[gnss_idx] - np.column_stack(
            [c * lever[:, 0] - s * lever[:, 1], s * lever[:, 0] + c * lever[:, 1]]
        )

    def build(self, kernel: str, gnss_idx: np.ndarray, node_poses: np.ndarray) -> gtsam.NonlinearFactorGraph:
        odometry, course = self._fixed_factors()
        g = gtsam.NonlinearFactorGraph()
        g.push_back(odometry)
        z = self.fix_at_node(gnss_idx, node_poses)
        models = self._gnss_models.setdefault(
            kernel, {}
        )  # one noise model per distinct sigma, kept across solves
        for zi, node, sig in zip(
            z, self.node_of[gnss_idx].tolist(), self.factor_sigma[gnss_idx].tolist(), strict=True
        ):
            robust = models.get(sig)
            if robust is None:
                robust = models[sig] = self._gnss_model(kernel, sig)
            g.add(gtsam.PoseTranslationPrior2D(node, zi, robust))
        g.push_back(course)
        return g

    def solve(self, kernel: str, gnss_idx: np.ndarray, node_poses: np.ndarray) -> np.ndarray:
        values = gtsam.Values()
        for k, pose in enumerate(node_poses.tolist()):  # plain floats: a third faster into gtsam
            values.insert(k, gtsam.Pose2(*pose))
        values = _optimize(self.build(kernel, gnss_idx, node_poses), values, self.params)
        return gtsam.utilities.extractPose2(values)

    def solve_with_bias(
        self,
        node_poses: np.ndarray,
        timestamps_s: np.ndarray,
        status: np.ndarray,
        bias_sigma: np.ndarray,
        inlier: np.ndarray,
    ) -> np.ndarray:
        """The kept fixes again, with the GNSS error as a Gauss-Markov bias state (gnss_bias.py);
        ``bias_sigma (N,)`` the bias's stationary sigma per frame."""
        idx = np.flatnonzero(inlier)
        run = np.r_[0, np.cumsum(np.diff(np.asarray(status, int)) != 0)]
        white = white_sigmas_m(
            timestamps_s, status, self.fix_positions(node_poses), self.gnss_xy, inlier, self.params
        )
        odometry, course = self._fixed_factors()
        graph, values = build_bias_graph(
            odometry,
            course,
            node_poses,
            timestamps_s[self.nodes],
            run[self.nodes],
            self.node_of[idx],
            self.fix_at_node(idx, node_poses),
            bias_sigma[idx],
            white[idx],
            self.params,
        )
        result = _optimize(graph, values, self.params)
        return np.array(
            [[p.x(), p.y(), p.theta()] for p in (result.atPose2(k) for k in range(len(node_poses)))]
        )

    def frame_poses(self, node_poses: np.ndarray) -> np.ndarray:
        """Every frame from its node by odometry; the small misclosure to the next node is
        spread linearly along the travel in between."""
        nodes, node_of, travel = self.nodes, self.node_of, self.travel
        out = se2.compose(node_poses[node_of], self.node_T_frame)
        if len(nodes) < 2:
            return out
        pred_next = se2.compose(node_poses[:-1], self.node_incr)
        mis = node_poses[1:] - pred_next
        mis[:, 2] = se2.wrap_angle(mis[:, 2])
        seg = np.minimum(node_of, len(nodes) - 2)
        span = np.maximum(travel[nodes[seg + 1]] - travel[nodes[seg]], 1e-9)
        alpha = np.clip((travel - travel[nodes[seg]]) / span, 0.0, 1.0)
        alpha[node_of == len(nodes) - 1] = 0.0
        out = out + alpha[:, None] * mis[seg]
        out[:, 2] = se2.wrap_angle(out[:, 2])
        return out

    def fix_positions(self, node_poses: np.ndarray) -> np.ndarray:
        """(N, 2) world positions of the instants the fixes refer to (frame time - latency)."""
        return se2.compose(node_poses[self.node_of], self.node_T_fix)[:, :2]

    def reject(
        self, node_poses: np.ndarray, has_fix: np.ndarray, inlier: np.ndarray
    ) -> tuple[np.ndarray, bool]:
        """GNSS fixes kept: normalised residual norm under ``GNSS_OUTLIER_SIGMAS`` x the trip's
        scale (median normalised residual over the Rayleigh median 1.1774)."""
        p = self.params
        pos = self.fix_positions(node_poses)
        fix_idx = np.flatnonzero(has_fix)
        r = np.full(len(has_fix), np.inf)
        r[fix_idx] = np.linalg.norm(pos[fix_idx] - self.gnss_xy[fix_idx], axis=1) / self.sigma[fix_idx]
        scale = max(float(np.median(r[inlier])) / 1.1774, p.GNSS_SCALE_MIN)
        new = has_fix & (r <= p.GNSS_OUTLIER_SIGMAS * scale)
        if new.sum() < max(2, int(p.GNSS_MIN_INLIER_SHARE * len(fix_idx))):
            return inlier, False
        return new, bool(np.any(new != inlier))
