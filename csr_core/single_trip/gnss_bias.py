"""Eq. 2's last solve with the GNSS error as a state: a Gauss-Markov bias per graph node.

A receiver's error is mostly a slowly wandering bias (multipath, atmosphere, orbit) plus a
little white noise per fix. Treated as white, the bias bends the trajectory: the smoother
follows whatever the bias does over tens of seconds (the trip's within-trip drift, what the single-trip
rigid-offset figure measures). Here each node ``k`` gets a bias ``b_k`` and each fix measures
``p_k + lever + b_k`` with the white sigma only; consecutive biases are tied by the first-order
Gauss-Markov step,

    b_{k+1} / s_{k+1} = exp(-dt / tau) b_k / s_k + w,   w ~ N(0, 1 - exp(-2 dt / tau)),

``s`` the stationary sigma of the fix's status run (the median of the receiver's ``std_m`` over
the run, else the status table), ``tau`` ``GNSS_BIAS_TAU_S``, and a new bias where the run changes. The odometry then carries the shape over the bias's correlation time and
the fixes still hold the trip where the bias has wandered (the chain is no stiffer than the
receiver's own sigma allows).

:func:`trip_bias_sigma_m` gives the stationary sigma of the trip as a whole (the median of its
fixes' ``s``): the part of the trip's error that no alignment removes, which the map's
absolute uncertainty (``topology.absolute_uncertainty``) is made of.

Built-in factors only (LIBRARY-NOTES: Python custom factors are 30-100x slower): a bias is a
``Pose2`` whose rotation is held at 0, a fix is ``BetweenFactorPose2(b_k, x_k)`` measuring the
fix position with the node's current yaw (so SE(2)'s log map does not mix the rotation into the
translation residual) and a free rotation; the chain is linear (``add_gauss_markov_chain``).
The fixes and the odometry are those the white-noise stages kept and calibrated
(``pose_graph.smooth_poses``); this stage only re-weighs them.

On (``GNSS_BIAS_STATE``). With these poses in the alignment's e^sm chain the single trip gained
but the alignment lost (docs/single-trip.md), so the white solve before this one is kept with the
trip for that chain; ``python -m csr_core.alignment.compare_single_trip`` measures a change like this
one through the alignment.
"""

from __future__ import annotations

import gtsam
import numpy as np

from csr_core.single_trip.params import SingleTripParams
from csr_core.types import GnssStatus

FREE_ROTATION_SIGMA_RAD = 1e3  # a fix says nothing about the yaw
BIAS_YAW_SIGMA_RAD = 1e-6  # a bias is a translation: its rotation is held at 0
#: a trip with no readable error model: the status table's single-point sigma (metres, per axis)
UNKNOWN_TRIP_BIAS_SIGMA_M = SingleTripParams().GNSS_SIGMA_BY_STATUS_M[int(GnssStatus.SINGLE)]
#: the diagnostics keys of :func:`trip_bias_sigma_m` and :func:`bias_correlation_length_m`
TRIP_BIAS_SIGMA_KEY = "gnss_bias_sigma_m"
TRIP_BIAS_LENGTH_KEY = "gnss_bias_length_m"


def trip_bias_sigma_m(
    gnss_status: np.ndarray, gnss_std_m: np.ndarray, params: SingleTripParams = SingleTripParams()
) -> float:
    """A trip's per-axis GNSS bias sigma (metres): the median over its fixes (status not
    ``none``) of the reported ``std_m``, or the status table's sigma where the receiver gave none,
    floored at ``GNSS_SIGMA_FLOOR_M``. A trip without a fix: :data:`UNKNOWN_TRIP_BIAS_SIGMA_M`.
    ``gnss_status`` (N,) uint8 codes, ``gnss_std_m`` (N,)."""
    status = np.asarray(gnss_status, np.int64)
    std = np.asarray(gnss_std_m, float)
    if status.shape != std.shape:
        raise ValueError(f"gnss_status {status.shape} and gnss_std_m {std.shape} differ in shape")
    fix = status != int(GnssStatus.NONE)
    if not fix.any():
        return UNKNOWN_TRIP_BIAS_SIGMA_M
    table = np.asarray(params.GNSS_SIGMA_BY_STATUS_M, float)[status[fix]]
    reported = std[fix]
    sigma = np.where(np.isfinite(reported) & (reported > 0), reported, table)
    return float(max(np.median(sigma), params.GNSS_SIGMA_FLOOR_M))


def bias_correlation_length_m(
    timestamps_s: np.ndarray, positions_xy: np.ndarray, params: SingleTripParams = SingleTripParams()
) -> float:
    """How far the trip drives in one bias correlation time ``GNSS_BIAS_TAU_S`` at its median
    speed (metres): along this distance the trip's bias, and so the correction its alignment
    to other trips makes, is shared. ``timestamps_s (N,)``, ``positions_xy (N, 2)``; 0 for fewer
    than two frames."""
    t = np.asarray(timestamps_s, float)
    xy = np.asarray(positions_xy, float)
    if xy.shape != (len(t), 2):
        raise ValueError(f"positions_xy {xy.shape} must be ({len(t)}, 2)")
    dt = np.diff(t)
    ok = dt > 0
    if not ok.any():
        return 0.0
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1)[ok] / dt[ok]
    return float(np.median(speed) * params.GNSS_BIAS_TAU_S)


def _bias_key(k: int) -> int:
    return gtsam.symbol("b", k)


def white_sigma_m(
    timestamps_s: np.ndarray,
    fix_xy_model: np.ndarray,
    gnss_xy: np.ndarray,
    kept: np.ndarray,
    params: SingleTripParams,
) -> float | None:
    """Per-axis white noise of the ``kept`` fixes, from the trip itself: the change of ``gnss -
    model`` between consecutive kept fixes (a bias hardly moves in one fix interval, so what
    changes is the white part, twice). Robust (MAD) over both axes; at least
    ``GNSS_WHITE_SIGMA_MIN_M``. None with fewer than ``NOISE_MIN_SAMPLES`` consecutive pairs."""
    idx = np.flatnonzero(kept)
    if len(idx) < 3:
        return None
    dt = np.diff(timestamps_s[idx])
    consecutive = (np.diff(idx) == 1) | (dt <= 1.5 * float(np.median(dt)))
    d = np.diff(gnss_xy[idx] - fix_xy_model[idx], axis=0)[consecutive]
    if len(d) < params.NOISE_MIN_SAMPLES:
        return None
    mad = float(np.median(np.abs(d - np.median(d, axis=0))))
    return max(1.4826 * mad / np.sqrt(2.0), params.GNSS_WHITE_SIGMA_MIN_M)


def white_sigmas_m(
    timestamps_s: np.ndarray,
    status: np.ndarray,
    fix_xy_model: np.ndarray,
    gnss_xy: np.ndarray,
    kept: np.ndarray,
    params: SingleTripParams,
) -> np.ndarray:
    """White sigma per fix (N,): measured per fix status (an RTK-fixed spell's centimetres are
    not a single-point fix's decimetres); a status with too few fixes takes the trip's pooled
    value, a trip with too few the sigma floor."""
    pooled = white_sigma_m(timestamps_s, fix_xy_model, gnss_xy, kept, params)
    out = np.full(len(kept), params.GNSS_SIGMA_FLOOR_M if pooled is None else pooled)
    for code in np.unique(np.asarray(status)[kept]).tolist():
        mine = kept & (np.asarray(status) == code)
        own = white_sigma_m(timestamps_s, fix_xy_model, gnss_xy, mine, params)
        if own is not None:
            out[mine] = own
    return out


def run_sigmas_m(status: np.ndarray, sigma_m: np.ndarray) -> np.ndarray:
    """Stationary bias sigma per fix (N,): the median of the reported sigmas over each run of one
    fix status. A receiver's ``std_m`` wobbles from fix to fix; its bias does not rescale with
    that wobble (a Gauss-Markov chain in units of a sigma that wobbles would force it to)."""
    out = np.asarray(sigma_m, float).copy()
    change = np.flatnonzero(np.diff(np.asarray(status, int)) != 0) + 1
    for lo, hi in zip(np.r_[0, change].tolist(), np.r_[change, len(out)].tolist(), strict=True):
        finite = np.isfinite(out[lo:hi])
        if finite.any():
            out[lo:hi] = np.where(finite, np.median(out[lo:hi][finite]), out[lo:hi])
    return out


def median_per_node(node_of_fix: np.ndarray, values: np.ndarray, n_nodes: int) -> np.ndarray:
    """``(n_nodes, ...)`` the median of ``values`` (M, ...) over each node's fixes; NaN for a node
    without a fix. All nodes at once: each column sorted by node, then by value; a node's median
    is the middle of its run (the mean of the two middles for an even count, as ``np.median``)."""
    values = np.asarray(values, float)
    out = np.full((n_nodes, *values.shape[1:]), np.nan)
    if len(node_of_fix) == 0:
        return out
    columns = values.reshape(len(values), -1)
    by_node = np.sort(node_of_fix)
    first = np.flatnonzero(np.r_[True, by_node[1:] != by_node[:-1]])
    counts = np.diff(np.r_[first, len(by_node)])
    lo, hi = first + (counts - 1) // 2, first + counts // 2
    medians = np.empty((len(first), columns.shape[1]))
    for j in range(columns.shape[1]):
        ranked = columns[np.lexsort((columns[:, j], node_of_fix)), j]
        medians[:, j] = 0.5 * (ranked[lo] + ranked[hi])
    out.reshape(n_nodes, -1)[by_node[first]] = medians
    return out


def fill_from_nearest(per_node: np.ndarray) -> np.ndarray:
    """Nodes without a value (outages) take the nearest node's: the bias keeps wandering at its
    own rate there, and starts from where it was."""
    have = np.flatnonzero(np.isfinite(per_node).all(axis=tuple(range(1, per_node.ndim))))
    if len(have) == 0:
        return per_node
    k = np.arange(len(per_node))
    pos = np.clip(np.searchsorted(have, k), 0, len(have) - 1)
    after, before = have[pos], have[np.maximum(pos - 1, 0)]
    return per_node[np.where(np.abs(before - k) < np.abs(after - k), before, after)]


def add_gauss_markov_chain(
    g: gtsam.NonlinearFactorGraph,
    node_time_s: np.ndarray,
    node_sigma_m: np.ndarray,
    node_run: np.ndarray,
    bias_xy_lin: np.ndarray,
    tau_s: float,
) -> None:
    """The first-order Gauss-Markov prior of the biases: ``b_0 ~ N(0, s_0^2)`` and, in units of
    each node's stationary sigma, ``b_{k+1} / s_{k+1} = phi b_k / s_k + w``, ``phi = exp(-dt /
    tau)``, ``w ~ N(0, 1 - phi^2)``; ``phi = 0`` where ``node_run`` changes (a new fix status, or
    the fixes back after an outage: the receiver's error is a new one, independent of the last).
    The step is linear but not a difference (the mean reversion holds the bias's level over a trip
    longer than tau), so it is a ``JacobianFactor`` in a
    ``LinearContainerFactor``, linearised at ``bias_xy_lin``: a bias keeps its yaw at 0, where
    ``Pose2``'s local coordinates are the plain translation difference and the factor is exact."""
    s0 = float(node_sigma_m[0])
    g.add(
        gtsam.PriorFactorPose2(
            _bias_key(0),
            gtsam.Pose2(0.0, 0.0, 0.0),
            gtsam.noiseModel.Diagonal.Sigmas(np.array([s0, s0, BIAS_YAW_SIGMA_RAD])),
        )
    )
    lin = gtsam.Values()
    for k, (x, y) in enumerate(bias_xy_lin.tolist()):
        lin.insert(_bias_key(k), gtsam.Pose2(x, y, 0.0))
    phi = np.where(np.diff(node_run) == 0, np.exp(-np.diff(node_time_s) / tau_s), 0.0)
    a_all = phi / node_sigma_m[:-1]
    b_all = 1.0 / node_sigma_m[1:]
    rhs_all = np.zeros((len(phi), 3))
    rhs_all[:, :2] = -(a_all[:, None] * bias_xy_lin[:-1] - b_all[:, None] * bias_xy_lin[1:])
    for k, (a, b) in enumerate(zip(a_all.tolist(), b_all.tolist(), strict=True)):
        a_k = np.array([[a, 0.0, 0.0], [0.0, a, 0.0], [0.0, 0.0, 0.0]])
        a_next = np.array([[-b, 0.0, 0.0], [0.0, -b, 0.0], [0.0, 0.0, 1.0]])  # row 3: the next yaw at 0
        rhs = rhs_all[k]
        step = float(np.sqrt(max(1.0 - phi[k] ** 2, 1e-12)))
        model = gtsam.noiseModel.Diagonal.Sigmas(np.array([step, step, BIAS_YAW_SIGMA_RAD]))
        jac = gtsam.JacobianFactor(_bias_key(k), a_k, _bias_key(k + 1), a_next, rhs, model)
        g.add(gtsam.LinearContainerFactor(jac, lin))


def build_bias_graph(
    odometry: gtsam.NonlinearFactorGraph,
    course: gtsam.NonlinearFactorGraph,
    node_poses: np.ndarray,
    node_time_s: np.ndarray,
    node_run: np.ndarray,
    node_of_fix: np.ndarray,
    fix_xy_at_node: np.ndarray,
    fix_sigma_m: np.ndarray,
    white_m: np.ndarray,
    params: SingleTripParams,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph ``odometry + course + fixes with a bias chain`` and its initial values (node
    poses under keys ``0..n-1``, biases under ``b``).

    ``fix_xy_at_node (M, 2)``: each kept fix moved to its node by the odometry lever (what the fix
    says the node's position is, bias included); ``node_of_fix (M,)``; ``fix_sigma_m (M,)`` its
    stationary sigma, ``white_m (M,)`` its white sigma; ``node_run (n_nodes,)`` the fix-status run
    each node is in. Warm start: the given node poses, each bias at its node's median residual,
    so that the fixes start near their white sigma (Cauchy from a good start)."""
    n = len(node_poses)
    sig_node = fill_from_nearest(median_per_node(node_of_fix, fix_sigma_m, n))
    b0 = fill_from_nearest(median_per_node(node_of_fix, node_poses[node_of_fix, :2] - fix_xy_at_node, n))

    g = gtsam.NonlinearFactorGraph()
    g.push_back(odometry)
    g.push_back(course)
    values = gtsam.Values()
    for k, pose in enumerate(node_poses.tolist()):
        values.insert(k, gtsam.Pose2(*pose))
        values.insert(_bias_key(k), gtsam.Pose2(float(b0[k, 0]), float(b0[k, 1]), 0.0))
    add_gauss_markov_chain(g, node_time_s, sig_node, node_run, b0, params.GNSS_BIAS_TAU_S)
    est = gtsam.noiseModel.mEstimator.Cauchy.Create(params.GNSS_CAUCHY_C_SIGMAS)
    models: dict[float, gtsam.noiseModel.Base] = {}  # one per distinct white sigma (one per status)
    # b^-1 x = (p - b, yaw): measured (z, the node's yaw now), so the log map's rotation is ~0
    for node, z, w in zip(
        node_of_fix.tolist(), fix_xy_at_node.tolist(), np.asarray(white_m).tolist(), strict=True
    ):
        model = models.get(w)
        if model is None:
            model = models[w] = gtsam.noiseModel.Robust.Create(
                est, gtsam.noiseModel.Diagonal.Sigmas(np.array([w, w, FREE_ROTATION_SIGMA_RAD]))
            )
        g.add(
            gtsam.BetweenFactorPose2(
                _bias_key(node), node, gtsam.Pose2(z[0], z[1], float(node_poses[node, 2])), model
            )
        )
    return g, values
