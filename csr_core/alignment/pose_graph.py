"""Incremental pose graph optimisation over sub-map poses (Eq. 9-12, Fig. 8), with gtsam.

Variables ``S(i)``: ``world_T_submap`` of every sub-map (trip sub-maps and pre-built-map patches).
Factors (Eq. 9/10):
- ``e^g``  ``PriorFactorPose2(S(i), g_i)``, g_i the smoothed anchor pose, information
  ``Omega_g = mean_t(M_table(s_t) (1 + omega d_go_t)) Omega_g^base`` (Eq. 11, with the
  deviation term scaled by the status weight so that ``omega`` means the same for every status
  -- the paper adds it; with an inverse-variance M_table an additive term would vanish for RTK
  and dominate for single fixes; ``omega < 0``: a GNSS step that disagrees with odometry lowers
  the weight, to 0 at ``1/|omega|`` metres; the mean is floored at ``gnss_min_weight``).
  The GNSS error is mostly a bias with minutes of correlation time, so the priors of one trip's
  sub-maps are not independent: with ``gnss_bias_tau_s > 0`` each prior holds ``B(i)^-1 S(i)``
  at ``g_i`` with only the independent share of its variance, and the trip's biases ``B(i)`` form a
  Gauss-Markov chain (:func:`add_gnss_bias_chain`). A trip's GNSS offset is then one unknown,
  learnt where the trip overlaps others and carried along the stretches it drives alone,
  instead of each sub-map being pulled back to its own fixes. What another alignment (a
  neighbouring tile's) learnt of that offset comes in as priors on the chain (bias messages,
  :mod:`csr_core.alignment.bias_messages`);
- ``e^pre`` the pre-built map: each patch is a variable held by a ``PriorFactorPose2`` at its
  stored pose with the map's own sigma, and a sub-map registered to it gets a between factor,
  so the map moves only as far as its weight allows (a fixed map is the limit sigma -> 0);
- ``e^reg`` ``BetweenFactorPose2(S(i), S(j), T_reg)``, information ``alpha c_ij Omega_reg^base``
  (Eq. 12) where ``Omega_reg^base`` is the registration's own point-to-line information (so a
  straight road constrains across, hardly along), divided by the pair's variance factor
  (:func:`registration_variance_factors`: the redundancy of the pairs of its circle and its own
  residual against the batch's typical one);
- ``e^sm`` consecutive (overlapping) sub-maps of one trip share frames: their relative pose is
  held at the smoothed one (with the single-trip GNSS bias state, the white-noise solve's before
  it: ``submap_chain_from_white_solve``, docs/alignment.md; e^g stays at the bias
  state's anchors) with the sigmas the trip's odometry gives over the seconds and metres between
  them (:mod:`csr_core.alignment.odometry_noise`: its heading's random walk, read from the trip's
  own yaw increments, and the lateral error that makes), its translation scaled
  by ``1 + k``, ``k`` the trip's odometry scale correction (a variable ``K(trip)`` with a prior
  of ``odom_scale_sigma``): the single-trip calibration sets the scale from the trip's own GNSS,
  0.04 % off (RMS; 0.6 m over a 1.5 km trip); registrations to other trips refine it.
Registrations are not trusted blindly: GNC-TLS (gtsam ``GncLMOptimizer``, all other factors
known inliers) rejects those that contradict the rest (cycles through several trips), warm
started from a Huber LM solution (GNC restarts from its initial values; LIBRARY-NOTES).

Incremental: a new batch is optimised against the pre-built map through its patches (the old
solution marginalised into priors), so the cost depends on the new trips and the map patches
they touch, never on how many trips built the map.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import cast

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, K, S

from csr_core import se2
from csr_core.alignment.association import PairMatch
from csr_core.alignment.bias_messages import GnssBiasMessage, add_bias_messages
from csr_core.alignment.geometry import arclength_m
from csr_core.alignment.odometry_noise import chain_sigmas, trip_yaw_random_walk
from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.submaps import Submap
from csr_core.types import TripReconstruction

log = logging.getLogger(__name__)

EARTH_RADIUS_M = 6_378_137.0


@dataclass(frozen=True, slots=True)
class PoseGraphResult:
    poses_xyyaw: dict[int, np.ndarray]  # sub-map id -> optimised world_T_submap
    registration_inlier: np.ndarray  # (P,) per accepted PairMatch
    gnss_weight: dict[int, float]  # Eq. 11 weight per trip sub-map
    # own-GNSS gain per trip sub-map: (2, 2) d(optimised position) / d(common shift of its trip's
    # GNSS priors), world axes (see :func:`own_gnss_gain`); identity = held by nothing but its GNSS
    own_gnss_gain: dict[int, np.ndarray] = field(default_factory=dict)
    # per trip index: the relative correction k of its odometry distance scale (``odom_scale_sigma``)
    odom_scale_correction: dict[int, float] = field(default_factory=dict)


def gnss_odometry_deviation_m(trip: TripReconstruction) -> np.ndarray:
    """``d_go^t`` of Eq. 11: |GNSS step - odometry step| between consecutive frames (metres,
    ``(N,)``, 0 at the first frame). The GNSS step uses a local equirectangular scale, exact
    enough for metre-scale steps."""
    t = trip.trip
    lon, lat = np.radians(t.gnss_lonlat_deg[:, 0]), np.radians(t.gnss_lonlat_deg[:, 1])
    dx = np.diff(lon) * np.cos(lat[:-1]) * EARTH_RADIUS_M
    dy = np.diff(lat) * EARTH_RADIUS_M
    g_step = np.hypot(dx, dy)
    o_step = np.linalg.norm(np.diff(t.odom_xyyaw[:, :2], axis=0), axis=1)
    d = np.abs(g_step - o_step)
    fix = t.has_fix
    d[~(fix[1:] & fix[:-1])] = 0.0
    return np.concatenate([[0.0], d])


def gnss_weight(
    trip: TripReconstruction, lo: int, hi: int, deviation: np.ndarray, params: AlignmentParams
) -> float:
    """Eq. 11's scalar factor over frames ``lo..hi``."""
    status = trip.trip.gnss_status[lo : hi + 1].astype(int)
    table = np.array([params.gnss_status_weights.get(int(s), 0.0) for s in range(5)])
    w = table[np.clip(status, 0, 4)] * np.maximum(
        1.0 + params.gnss_deviation_weight_per_m * deviation[lo : hi + 1], 0.0
    )
    w = np.where(status == 4, 0.0, w)
    return float(max(float(np.mean(w)), params.gnss_min_weight))


def _clip_information(info: np.ndarray, max_eig: float) -> np.ndarray:
    info = 0.5 * (info + info.T)
    vals, vecs = np.linalg.eigh(info)
    vals = np.clip(vals, 1e-9, max_eig)
    return (vecs * vals) @ vecs.T


def registration_variance_factors(matches: Sequence[PairMatch], params: AlignmentParams) -> np.ndarray:
    """Per pair, the factor by which Eq. 12's ``alpha c_ij Omega_reg^base`` is divided (a
    variance factor, >= 1; 1 for a pair a human added, whose weight is given).

    ``Omega_reg^base`` is one registration's point-to-line information, computed as if the pair
    were the only measurement of its two sub-maps and its residuals were as the noise model
    says. Neither holds:

    - **redundancy of its circle** (``reg_circle_redundancy``): the ``m_c`` accepted pairs of
      a circle with ``n_c`` sub-maps measure only ``n_c - 1`` independent relative poses; each
      sub-map's element errors enter every pair it is in (Fig. 4 pairs each sub-map with its next
      ``max_partners_per_submap`` in the circle, for Step 4's cycles). Independent factors would
      count them ``m_c / (n_c - 1)`` times, so each pair's information is divided by that;
    - **its own residual** (``reg_residual_variance``): the a-posteriori variance factor of
      least squares, ``(rms / rms_0)^2`` when above 1, ``rms_0`` the median RMS residual of the
      batch's accepted pairs (the residual of a correct registration, from the data rather than
      the noise model, whose point sigma is about twice it). A pair that fits worse than the
      batch's typical pair is held looser in proportion, instead of as tight as its geometry
      alone would say.
    """
    n = len(matches)
    factor = np.ones(n)
    if n == 0:
        return factor
    if params.reg_circle_redundancy:
        nodes: dict[int, set[int]] = {}
        edges: dict[int, int] = {}
        for m in matches:
            nodes.setdefault(m.circle_id, set()).update((m.i, m.j))
            edges[m.circle_id] = edges.get(m.circle_id, 0) + 1
        factor *= np.array([edges[m.circle_id] / max(len(nodes[m.circle_id]) - 1, 1) for m in matches])
    human = np.array([m.human for m in matches], bool)
    if params.reg_residual_variance:
        rms = np.array([m.residual_rms_m for m in matches], float)
        automatic = ~human & np.isfinite(rms)
        if automatic.any():
            rms_0 = float(np.median(rms[automatic]))
            if rms_0 > 0:
                factor[automatic] *= np.maximum(1.0, (rms[automatic] / rms_0) ** 2)
    factor[human] = 1.0
    return factor


def build_factor_graph(
    trips: Sequence[TripReconstruction],
    submaps: Sequence[Submap],
    matches: Sequence[PairMatch],
    params: AlignmentParams,
    with_scale: bool = False,
    bias_messages: Mapping[str, Sequence[GnssBiasMessage]] | None = None,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int], list[int], dict[int, float]]:
    """Eq. 9 as a factor graph; returns graph, initial values, the indices of the registration
    factors and of the known-inlier factors, and the Eq. 11 weights. ``with_scale``: each trip's
    e^sm factors scale with its odometry scale correction ``K(trip)`` (prior
    ``odom_scale_sigma``), those priors added last. ``bias_messages`` (by trip key): other
    alignments' estimates of a trip's GNSS bias, priors on its bias chain
    (:func:`csr_core.alignment.bias_messages.add_bias_messages`, known inliers)."""
    g, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    known, reg_idx, weights = [], [], {}
    deviations = {k: gnss_odometry_deviation_m(t) for k, t in enumerate(trips)}
    for s in submaps:
        init.insert(S(s.submap_id), gtsam.Pose2(*s.world_T_submap))
        if s.is_prior:  # e^pre: the pre-built map holds with its own weight
            sig = np.array([params.prior_map_sigma_xy_m] * 2 + [params.prior_map_sigma_yaw_rad])
        else:  # e^g with Eq. 11
            w = gnss_weight(
                trips[s.trip_index], s.first_frame, s.last_frame, deviations[s.trip_index], params
            )
            weights[s.submap_id] = w
            sig = np.array([params.gnss_sigma_base_xy_m] * 2 + [params.gnss_sigma_base_yaw_rad]) / np.sqrt(w)
        known.append(g.size())
        if s.is_prior or params.gnss_bias_tau_s <= 0:
            g.add(
                gtsam.PriorFactorPose2(
                    S(s.submap_id),
                    gtsam.Pose2(*s.gnss_prior_pose(params.gnss_prior_from_white_solve)),
                    gtsam.noiseModel.Diagonal.Sigmas(sig),
                )
            )
        else:  # e^g through the trip's bias: B^-1 S = g (B a pure shift), the independent share only
            independent = sig * np.array([np.sqrt(1.0 - params.gnss_bias_share)] * 2 + [1.0])
            init.insert(B(s.submap_id), gtsam.Pose2())
            g.add(
                gtsam.BetweenFactorPose2(
                    B(s.submap_id),
                    S(s.submap_id),
                    gtsam.Pose2(*s.gnss_prior_pose(params.gnss_prior_from_white_solve)),
                    gtsam.noiseModel.Diagonal.Sigmas(independent),
                )
            )
    # e^sm: overlapping sub-maps of one trip keep their smoothed relative pose
    chain_white = params.submap_chain_from_white_solve
    by_trip: dict[int, list[Submap]] = {}
    for s in submaps:
        if not s.is_prior:
            by_trip.setdefault(s.trip_index, []).append(s)
    for k, group in by_trip.items():
        group.sort(key=lambda s: s.anchor_frame)
        if params.gnss_bias_tau_s > 0:
            known.extend(add_gnss_bias_chain(g, trips[k], group, weights, params))
            if bias_messages and trips[k].trip.key in bias_messages:
                known.extend(
                    add_bias_messages(g, trips[k], group, weights, bias_messages[trips[k].trip.key], params)
                )
        travel = arclength_m(trips[k].poses_xyyaw_world[:, :2])
        t = trips[k].trip.timestamps_s
        yaw_rw = trip_yaw_random_walk(trips[k], params)
        for a, b in zip(group[:-1], group[1:], strict=False):
            rel = se2.between(a.gnss_prior_pose(chain_white), b.gnss_prior_pose(chain_white))
            d = float(travel[b.anchor_frame] - travel[a.anchor_frame])  # travelled, not straight-line
            if params.submap_chain_from_odometry:
                sigmas = chain_sigmas(
                    d,
                    abs(float(t[b.anchor_frame] - t[a.anchor_frame])),
                    yaw_rw,
                    params.submap_chain_sigma_xy0_m,
                )
                if not with_scale and params.odom_scale_sigma > 0:
                    # the graph without K(trip) (GNC's, which decides the inliers) holds the scale
                    # at the smoothed one: its unknown correction belongs in the translation's
                    # sigma, or a trip whose scale is off rejects the registrations that say so
                    sigmas[:2] = np.hypot(sigmas[:2], params.odom_scale_sigma * d)
            else:
                sxy = params.submap_chain_sigma_xy_m + params.submap_chain_sigma_per_m * d
                sigmas = np.array([sxy, sxy, params.submap_chain_sigma_yaw_rad * (1.0 + d / 50.0)])
            known.append(g.size())
            noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            if with_scale:
                g.add(scaled_chain_factor(S(a.submap_id), S(b.submap_id), K(k), rel, noise))
            else:
                g.add(gtsam.BetweenFactorPose2(S(a.submap_id), S(b.submap_id), gtsam.Pose2(*rel), noise))
    # e^reg (and e^pre against map patches) with Eq. 12 weights
    max_eig = 1.0 / params.reg_sigma_floor_xy_m**2
    for m, variance_factor in zip(matches, registration_variance_factors(matches, params), strict=True):
        si, sj = submaps[m.i], submaps[m.j]
        T = m.relative_pose(si.world_T_submap, sj.world_T_submap)
        info = params.reg_alpha * m.confidence * m.information_body_j(sj.world_T_submap) / variance_factor
        if m.human:  # a pair a human added: a known inlier, its weight as given (corrections)
            known.append(g.size())
        else:
            info = _clip_information(info, max_eig)
        reg_idx.append(g.size())
        g.add(
            gtsam.BetweenFactorPose2(
                S(m.i), S(m.j), gtsam.Pose2(*T), gtsam.noiseModel.Gaussian.Information(info)
            )
        )
    if with_scale:  # last, so that the other factors keep their indices
        for k, group in by_trip.items():
            if len(group) > 1:
                init.insert(K(k), np.zeros(1))
                known.append(g.size())
                g.add(
                    gtsam.PriorFactorVector(
                        K(k), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, params.odom_scale_sigma)
                    )
                )
    return g, init, reg_idx, known, weights


def scaled_chain_factor(
    key_a: int, key_b: int, key_scale: int, rel_xyyaw: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """e^sm with the trip's odometry scale correction ``k``: the translation from sub-map a to b,
    in a's frame, is ``(1 + k)`` times the smoothed one; the rotation is the smoothed one.
    Residual ``(R_a^T (t_b - t_a) - (1 + k) rel_t, theta_b - theta_a - rel_theta)`` with analytic
    Jacobians (gtsam's right perturbation of Pose2). A Python factor: gtsam has no between
    factor with a scale variable."""
    rel_t = np.asarray(rel_xyyaw[:2], float)
    rel_yaw = float(rel_xyyaw[2])
    d_scale = np.array([[-rel_t[0]], [-rel_t[1]], [0.0]])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        a, b = values.atPose2(key_a), values.atPose2(key_b)
        k = float(values.atVector(key_scale)[0])
        ca, sa = np.cos(a.theta()), np.sin(a.theta())
        dx, dy = b.x() - a.x(), b.y() - a.y()
        r0, r1 = ca * dx + sa * dy, -sa * dx + ca * dy
        phi = b.theta() - a.theta()
        e = np.array([r0 - (1.0 + k) * rel_t[0], r1 - (1.0 + k) * rel_t[1], se2.wrap_angle(phi - rel_yaw)])
        if jacobians is not None:
            c, s_ = np.cos(phi), np.sin(phi)
            jacobians[0] = np.array([[-1.0, 0.0, r1], [0.0, -1.0, -r0], [0.0, 0.0, -1.0]])
            jacobians[1] = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
            jacobians[2] = d_scale
        return e

    return gtsam.CustomFactor(noise, gtsam.KeyVector([key_a, key_b, key_scale]), error)


#: the bias has no heading: its yaw is held at zero
_BIAS_YAW_SIGMA_RAD = 1e-4


def add_gnss_bias_chain(
    g: gtsam.NonlinearFactorGraph,
    trip: TripReconstruction,
    group: Sequence[Submap],
    weights: Mapping[int, float],
    params: AlignmentParams,
) -> list[int]:
    """The GNSS bias of one trip's sub-maps (in anchor order) as a Gauss-Markov chain; returns the
    indices of the factors added.

    The bias at sub-map ``i`` has std ``sigma_i = sqrt(rho) sigma_base / sqrt(w_i)`` (Eq. 11's
    weight, ``rho`` = ``gnss_bias_share``); the first bias gets that prior, each next one a
    between factor with the variance of the difference of a first-order Gauss-Markov process
    scaled by ``sigma``: ``sigma_a^2 + sigma_b^2 - 2 phi sigma_a sigma_b``, ``phi = exp(-dt /
    tau)``. A status change (``sigma`` jumps) frees the bias by itself; fixes minutes apart are
    independent again."""
    t = trip.trip.timestamps_s
    sigma = {
        s.submap_id: np.sqrt(params.gnss_bias_share)
        * params.gnss_sigma_base_xy_m
        / np.sqrt(weights[s.submap_id])
        for s in group
    }
    added = []
    first = group[0].submap_id
    added.append(g.size())
    g.add(
        gtsam.PriorFactorPose2(
            B(first),
            gtsam.Pose2(),
            gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma[first], sigma[first], _BIAS_YAW_SIGMA_RAD])),
        )
    )
    for a, b in zip(group[:-1], group[1:], strict=False):
        phi = np.exp(-abs(float(t[b.anchor_frame] - t[a.anchor_frame])) / params.gnss_bias_tau_s)
        sa, sb = sigma[a.submap_id], sigma[b.submap_id]
        step = np.sqrt(max(sa**2 + sb**2 - 2.0 * phi * sa * sb, 1e-8))
        added.append(g.size())
        g.add(
            gtsam.BetweenFactorPose2(
                B(a.submap_id),
                B(b.submap_id),
                gtsam.Pose2(),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([step, step, _BIAS_YAW_SIGMA_RAD])),
            )
        )
    return added


def _huber_copy(
    g: gtsam.NonlinearFactorGraph, reg_idx: Sequence[int], values: gtsam.Values
) -> gtsam.NonlinearFactorGraph:
    """The graph with each registration factor under a Huber loss (warm start for GNC)."""
    h = gtsam.NonlinearFactorGraph()
    regs = set(reg_idx)
    for n in range(g.size()):
        f = g.at(n)
        if n in regs:
            reg = cast(gtsam.BetweenFactorPose2, f)  # registration factors are BetweenFactorPose2
            f = gtsam.BetweenFactorPose2(
                f.keys()[0],
                f.keys()[1],
                reg.measured(),
                gtsam.noiseModel.Robust.Create(
                    gtsam.noiseModel.mEstimator.Huber.Create(1.345), reg.noiseModel()
                ),
            )
        h.add(f)
    return h


def _without(
    graph: gtsam.NonlinearFactorGraph, reg_idx: Sequence[int], inlier: np.ndarray
) -> gtsam.NonlinearFactorGraph:
    """The graph without the registration factors that are not ``inlier``."""
    rejected = {reg_idx[int(n)] for n in np.flatnonzero(~inlier)}
    keep = gtsam.NonlinearFactorGraph()
    for n in range(graph.size()):
        if n not in rejected:
            keep.add(graph.at(n))
    return keep


def optimize_submap_poses(
    trips: Sequence[TripReconstruction],
    submaps: Sequence[Submap],
    matches: Sequence[PairMatch],
    params: AlignmentParams,
    bias_messages: Mapping[str, Sequence[GnssBiasMessage]] | None = None,
) -> PoseGraphResult:
    g, init, reg_idx, known, weights = build_factor_graph(
        trips, submaps, matches, params, bias_messages=bias_messages
    )
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(100)
    warm = gtsam.LevenbergMarquardtOptimizer(_huber_copy(g, reg_idx, init), init, lm).optimize()
    inlier = np.ones(len(matches), bool)
    if params.pose_graph_gnc and len(reg_idx) > 0:
        gp = gtsam.GncLMParams(lm)
        gp.setLossType(gtsam.GncLossType.TLS)
        gp.setKnownInliers(known)
        opt = gtsam.GncLMOptimizer(g, warm, gp)
        opt.setInlierCostThresholdsAtProbability(0.999)
        result = opt.optimize()
        w = np.asarray(opt.getWeights())
        inlier = w[np.asarray(reg_idx)] > 0.5
        if not inlier.all():
            log.debug("pose graph GNC rejected %d of %d registrations", int((~inlier).sum()), len(inlier))
            result = gtsam.LevenbergMarquardtOptimizer(_without(g, reg_idx, inlier), result, lm).optimize()
    else:
        result = warm
    scale_correction: dict[int, float] = {}
    if params.odom_scale_sigma > 0:
        # each trip's odometry scale, on the inliers GNC kept (gtsam's GNC clones its factors,
        # which a Python factor cannot do, so it decides with the scale fixed)
        gs, init_s, _, _, _ = build_factor_graph(
            trips, submaps, matches, params, with_scale=True, bias_messages=bias_messages
        )
        start = gtsam.Values(result)
        for key in init_s.keys():
            if not start.exists(key):
                start.insert(key, init_s.atVector(key))
        result = gauss_newton(_without(gs, reg_idx, inlier), start)
        scale_correction = {
            k: float(result.atVector(K(k))[0]) for k in range(len(trips)) if result.exists(K(k))
        }
    # a dense (3 x sub-maps)^2 solve: only when it decides something (``mark_unobservable``)
    gains = own_gnss_gain(g, result, submaps, matches, reg_idx, inlier) if params.mark_unobservable else {}
    poses = {
        s.submap_id: np.array(
            [
                result.atPose2(S(s.submap_id)).x(),
                result.atPose2(S(s.submap_id)).y(),
                result.atPose2(S(s.submap_id)).theta(),
            ]
        )
        for s in submaps
    }
    return PoseGraphResult(poses, inlier, weights, gains, scale_correction)


def gauss_newton(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    max_iterations: int = 20,
    relative_tolerance: float = 1e-6,
) -> gtsam.Values:
    """Gauss-Newton by hand, for a graph with Python factors (``scaled_chain_factor``): gtsam's
    LM spends seconds per iteration on such a graph (measured: 3 iterations in 11 s for 2,400
    sub-maps, ``linearize`` alone 0.07 s; LIBRARY-NOTES saw the same), while a plain linearize,
    solve, retract loop takes a fraction of a second. A step that raises the error is halved
    (at most 5 times); the loop ends when the error falls by less than ``relative_tolerance``."""
    error = graph.error(values)
    for _ in range(max_iterations):
        delta = graph.linearize(values).optimize()
        for _halving in range(6):
            candidate = values.retract(delta)
            new_error = graph.error(candidate)
            if new_error <= error:
                break
            delta = delta.scale(0.5)
        else:
            return values  # no step lowers the error: at the minimum to numerical precision
        values, done = candidate, error - new_error <= relative_tolerance * max(error, 1e-12)
        error = new_error
        if done:
            break
    return values


def own_gnss_gain(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    submaps: Sequence[Submap],
    matches: Sequence[PairMatch],
    reg_idx: Sequence[int],
    inlier: np.ndarray,
) -> dict[int, np.ndarray]:
    """How much of a trip's own GNSS error stays in its optimised sub-map positions.

    The GNSS error of a trip is dominated by a slowly varying bias (per axis, minutes of
    correlation time): close to a common offset ``u`` (world, metres) of all its fixes. It
    enters the graph twice: every ``e^g`` prior of the trip moves by ``u``, and every
    registration of one of its sub-maps keeps the share ``L u`` of it that its start-pose prior
    kept (``PairMatch.prior_sensitivity``: a registration repeats the GNSS relative pose in the
    directions its elements do not observe). To first order the solution moves by
    ``dx = H^-1 sum_f A_f^T R_f xi_f(u)`` (``H`` the Gauss-Newton information of the inlier
    factors at ``values``, ``A_f`` the whitened Jacobian, ``R_f`` the square-root information,
    ``xi_f`` the factor's measurement perturbation). Returned per trip sub-map: the ``(2, 2)``
    world gain ``G_s`` with ``dx_s = G_s u``. ``G = I`` where nothing but the trip's own GNSS
    holds the sub-map (along a straight road without landmarks), ``G ~ 1/n`` where registrations
    to ``n`` trips of equal weight do. ``graph`` is ``build_factor_graph``'s (priors first, one
    per sub-map in ``submaps`` order; ``reg_idx`` the registration factors, ``inlier`` kept).
    """
    n = len(submaps)
    if n == 0:
        return {}
    ordering = gtsam.Ordering()
    keys = [S(s.submap_id) for s in submaps] + [
        B(s.submap_id) for s in submaps if values.exists(B(s.submap_id))
    ]
    for key in keys:  # sub-map poses first, then the GNSS biases (when modelled)
        ordering.push_back(key)
    column = {key: 3 * m for m, key in enumerate(keys)}
    trips = sorted({int(s.trip_index) for s in submaps if not s.is_prior})
    pose = np.array(
        [
            [
                values.atPose2(S(s.submap_id)).x(),
                values.atPose2(S(s.submap_id)).y(),
                values.atPose2(S(s.submap_id)).theta(),
            ]
            for s in submaps
        ]
    )
    world_to_body = lambda m: _rot(-pose[m, 2])  # noqa: E731
    rhs_by_trip = np.zeros((3 * len(keys), 2 * len(trips)))

    def add(factor_index: int, col: int, xi: np.ndarray) -> None:
        """RHS of a measurement perturbation ``xi (3, 2)`` (columns: unit east, north shift)."""
        f = cast(gtsam.NoiseModelFactor, graph.at(factor_index))  # priors and between factors
        A, _ = f.linearize(values).jacobian()  # whitened, columns in f.keys() order
        rhs = (
            A.T @ f.noiseModel().whiten(xi)
            if xi.ndim == 1
            else A.T @ np.column_stack([f.noiseModel().whiten(xi[:, c]) for c in range(xi.shape[1])])
        )
        for b, key in enumerate(f.keys()):
            rhs_by_trip[column[key] : column[key] + 3, col : col + 2] += rhs[3 * b : 3 * b + 3]

    for m, s in enumerate(submaps):  # e^g: the trip's priors move with u (body frame of s)
        if not s.is_prior:
            add(m, 2 * trips.index(int(s.trip_index)), np.vstack([world_to_body(m), np.zeros((1, 2))]))
    for match, idx, ok in zip(matches, reg_idx, inlier, strict=True):
        L = np.asarray(match.prior_sensitivity)
        if not ok or not L.any():
            continue
        jm = match.j  # sub-map ids are their index in ``submaps``
        v = L[:, :2]  # (3, 2): local left perturbation of delta per unit world shift of j's trip
        arm = pose[jm, :2] - np.asarray(match.centre_xy_world)
        v_at_j = v[:2] + np.outer(np.array([-arm[1], arm[0]]), v[2])  # translation of j's anchor
        xi = np.vstack([world_to_body(jm) @ v_at_j, v[2:3]])  # right perturbation of i_T_j
        for sub, sign in ((submaps[match.j], 1.0), (submaps[match.i], -1.0)):
            if not sub.is_prior:
                add(idx, 2 * trips.index(int(sub.trip_index)), sign * xi)
    H, _ = _without(graph, reg_idx, inlier).linearize(values).hessian(ordering)
    X = np.linalg.solve(H + 1e-12 * np.eye(3 * len(keys)), rhs_by_trip)
    return {
        s.submap_id: _rot(pose[m, 2]) @ X[3 * m : 3 * m + 2, 2 * trips.index(int(s.trip_index)) :][:, :2]
        for m, s in enumerate(submaps)
        if not s.is_prior
    }


def _rot(yaw: float) -> np.ndarray:
    c, s_ = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s_], [s_, c]])


def frame_poses_from_submaps(
    trip: TripReconstruction, trip_submaps: Sequence[Submap], poses: Mapping[int, np.ndarray]
) -> np.ndarray:
    """Distribute the sub-map solution to every frame: each sub-map carries its frames rigidly
    (``x_t = x_i (g_i^-1 g_t)``); between two anchors the two proposals are blended linearly in
    travelled distance. ``(N, 3)``; the smoothed poses when the trip has no sub-map."""
    smoothed = trip.poses_xyyaw_world
    if not trip_submaps:
        return smoothed.copy()
    group = sorted(trip_submaps, key=lambda s: s.anchor_frame)
    anchors = np.array([s.anchor_frame for s in group])
    s_travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(smoothed[:, :2], axis=0), axis=1))])
    corrections = [se2.compose(poses[s.submap_id], se2.inverse(s.world_T_submap)) for s in group]
    proposals = np.stack([se2.compose(c[None, :], smoothed) for c in corrections])  # (G, N, 3)
    n = len(smoothed)
    hi = (
        np.clip(np.searchsorted(anchors, np.arange(n), side="right"), 1, len(group) - 1)
        if len(group) > 1
        else None
    )
    if hi is None:
        return proposals[0]
    lo = hi - 1
    s_lo, s_hi = s_travel[anchors[lo]], s_travel[anchors[hi]]
    w = np.clip((s_travel - s_lo) / np.maximum(s_hi - s_lo, 1e-9), 0.0, 1.0)
    idx = np.arange(n)
    a, b = proposals[lo, idx], proposals[hi, idx]
    out = a + w[:, None] * (b - a)
    out[:, 2] = se2.wrap_angle(a[:, 2] + w * se2.wrap_angle(b[:, 2] - a[:, 2]))
    return out
