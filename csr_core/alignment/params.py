"""Parameters of multi-trip alignment (paper section III-D), one frozen object.

Thresholds and similarity widths are *multiples of noise sigmas* (see :func:`noise_scales`):
the sigmas come from ``TripReconstruction.noise`` (single-trip residuals), so a noisier
perception widens every gate by itself; the multiples here are the only knobs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from csr_core.types import ElementNoise, ElementType, GnssStatus, TripReconstruction

#: Typical horizontal accuracy per fix status (metres, per axis), as published for automotive
#: receivers (RTK fixed a few cm, float decimetres, DGPS sub-metre, single metre-level).
TYPICAL_GNSS_SIGMA_M: dict[int, float] = {
    int(GnssStatus.RTK_FIXED): 0.05,
    int(GnssStatus.RTK_FLOAT): 0.3,
    int(GnssStatus.DGPS): 0.7,
    int(GnssStatus.SINGLE): 1.5,
}
#: Eq. 11's M_table: weight of a fix by receiver status, the inverse variance relative to
#: ``gnss_sigma_base_xy_m`` (1 m), so that the absolute position is the information-weighted
#: mean of the trips' fixes; no fix weighs nothing.
DEFAULT_GNSS_STATUS_WEIGHTS: dict[int, float] = {
    s: (1.0 / v) ** 2 for s, v in TYPICAL_GNSS_SIGMA_M.items()
} | {int(GnssStatus.NONE): 0.0}

#: used when a trip reports no noise for a type (metres)
FALLBACK_LATERAL_SIGMA_M = 0.15


@dataclass(frozen=True, slots=True)
class AlignmentParams:
    # --- ablation switches (paper Table I) ---------------------------------------------------
    coarse: bool = True
    fine: bool = True

    # --- sub-map splitting (Fig. 4) ----------------------------------------------------------
    submap_radius_m: float = 25.0  # circle radius; sub-map elements are clipped to it
    # inter-trip frame edges: frames of two trips closer than this ... (None: the shortest lateral
    # reach of the trips' perception, ``submaps.frame_graph_distance_m``: two frames that far
    # apart share half of their views; 15 m for the +-15 m of the contract's example sensor
    # setup). A fixed 6 m was rejected: the two carriageways of a divided road (7.75 m and
    # more apart) never paired, and each kept the GNSS mean of its own trips (docs/alignment.md,
    # "Tried and rejected").
    frame_graph_distance_m: float | None = None
    frame_graph_angle_rad: float = np.radians(30.0)  # ... and heading difference below this
    pair_opposite_directions: bool = True  # headings compared modulo pi (two-way roads)
    keyframe_spacing_m: float = 2.0  # node spacing of the frame graph
    min_submap_path_m: float = 10.0  # a trip must drive this far inside a circle to get a sub-map
    max_partners_per_submap: int = 2  # P_sub-sub pairs: each sub-map with its next k in the circle
    element_resample_m: float = 2.0
    min_element_length_m: float = 3.0

    # --- Eq. 3 global topology (multiples of sigmas) -----------------------------------------
    topo_lane_count_tol: int = 1
    topo_road_width_k: float = 4.0  # x sqrt(2) * boundary lateral sigma
    topo_split_merge_tol: int = 3
    # tau_sm also at least z x sqrt(N_sm^i + N_sm^j): element ends are counted events, and two
    # counts of one place differ by their Poisson noise (docs/alignment.md)
    topo_split_merge_z: float = 2.0
    topo_road_centre_k: float = 3.0  # x sqrt(sigma_pose_i^2 + sigma_pose_j^2 + boundary^2)
    topo_road_centre_floor_m: float = 2.0
    voting_half_window: int = 2  # sliding window of 2w+1 neighbouring pairs of the same two trips
    voting_min_fraction: float = 0.5

    # --- Eq. 4-7 graph matching -------------------------------------------------------------
    w_count: float = 0.15  # omega_1 (per match)
    w_node: float = 1.0  # omega_2
    w_edge: float = 1.0  # omega_3
    node_position_weight: float = 0.7  # omega of Eq. 5 / Eq. 7
    sigma_p_k: float = 2.5  # sigma_p = k * sqrt(2 lat^2 + boundary^2)  (after pre-alignment)
    sigma_p_floor_m: float = 0.4
    sigma_o: float = 0.5  # overlap similarity width (d_o = 1 - overlap ratio)
    sigma_e_k: float = 3.0  # sigma_e = k * sqrt(2) * lateral sigma
    sigma_e_floor_m: float = 0.25
    tau_s: float = 0.3  # x_kk' = 0 iff s_kk' < tau_s
    rrwm_max_iter: int = 10
    max_elements_per_submap: int = 28  # keeps the (n1 n2)^2 affinity matrix small
    max_prealign_shift_m: float = 6.0

    # --- registration (GNC-TLS) -------------------------------------------------------------
    gnc_inlier_k: float = 3.0  # TLS threshold = k * point sigma
    gnc_max_outer: int = 25
    min_matched_elements: int = 2
    registration_prior_sigma_xy_m: float = 1.5  # pull to the start pose (GNSS-relative error scale)
    registration_prior_sigma_yaw_rad: float = 0.03
    max_registration_rms_k: float = 3.0
    landmarks: bool = True  # dash ends as along-road landmarks in the sub-map registration
    landmark_gate_max_m: float = 3.0  # association gate (also kept below 0.4 x the dash period)
    degenerate_sigma_xy_m: float = 5.0  # regulariser on unobservable directions
    degenerate_sigma_yaw_rad: float = 0.2

    # --- Step 3 / Step 4 consistency ---------------------------------------------------------
    clique_consistency_m: float = 0.6  # |delta_p - delta_q| for the same two trips ...
    clique_drift_m_per_m: float = 0.01  # ... plus this per metre between the two places
    clique_window_m: float = 250.0  # pairs further apart are not compared

    # --- Eq. 9-12 pose graph ----------------------------------------------------------------
    gnss_status_weights: Mapping[int, float] = field(
        default_factory=lambda: dict(DEFAULT_GNSS_STATUS_WEIGHTS)
    )
    gnss_deviation_weight_per_m: float = (
        -2.0
    )  # omega of Eq. 11 (a GNSS/odometry disagreement lowers the weight)
    gnss_sigma_base_xy_m: float = 1.0  # Omega_g^base
    gnss_sigma_base_yaw_rad: float = 0.05
    gnss_min_weight: float = 0.02
    # GNSS error as a slowly varying bias (Eq. 9's e^g with a per-trip bias chain): a fix's error
    # is mostly a bias with minutes of correlation time (the real u-blox log: nearly constant over
    # 60 s; docs/gnss-model.md), so the fixes of one trip are not independent from one sub-map to
    # the next. ``gnss_bias_tau_s`` is that correlation time (0: independent priors per sub-map,
    # the paper's literal e^g); ``gnss_bias_share`` the share of a sub-map prior's variance that
    # is that bias. The rest stays independent per sub-map: the smoothed anchor also carries the
    # single-trip shape error, latency jitter and multipath. 0.5 and 0.9 give the same standard
    # ATE; 0.9 made 17 of 100 hard-profile trips exceed 0.5 m against 13 (docs/alignment.md).
    gnss_bias_tau_s: float = 300.0
    gnss_bias_share: float = 0.5
    # With the single-trip GNSS bias state a trip carries two trajectories: the bias state's (its
    # poses, the frame of its sub-maps' contents) and the white-noise solve before it
    # (``TripReconstruction.white_poses_xyyaw_world``). e^g holds each sub-map at the first (the
    # bias state's absolute positions are the better ones); the e^sm chain holds consecutive
    # sub-maps at the second's relative pose (with the bias state's, the dense fleets lost:
    # docs/alignment.md, where all four combinations are measured).
    gnss_prior_from_white_solve: bool = False
    submap_chain_from_white_solve: bool = True
    reg_alpha: float = 1.0  # alpha of Eq. 12
    # Eq. 12's information divided by the pair's variance factor (pose_graph.registration_variance_factors):
    # the redundancy of the accepted pairs of its circle, m_c / (n_c - 1), and its residual RMS
    # against the batch's median, squared, when above 1 (docs/alignment.md)
    reg_circle_redundancy: bool = True
    reg_residual_variance: bool = True
    reg_sigma_floor_xy_m: float = 0.03
    # e^sm: consistency of one trip's overlapping sub-maps. From the trip's odometry
    # (``submap_chain_from_odometry``, :mod:`csr_core.alignment.odometry_noise`): the heading's
    # random walk over the seconds between the anchors, the lateral error it makes over the metres
    # between them, plus ``submap_chain_sigma_xy0_m``; the random walk is read from each trip's
    # own odometry (``submap_chain_yaw_rw_default`` for a trip too short to say, never below
    # ``submap_chain_yaw_rw_min``). docs/alignment.md.
    submap_chain_from_odometry: bool = True
    submap_chain_sigma_xy0_m: float = 0.005
    submap_chain_yaw_rw_default: float = 0.001  # rad/sqrt(s)
    submap_chain_yaw_rw_min: float = 0.0001  # rad/sqrt(s), a good automotive gyro
    # The model before (``submap_chain_from_odometry=False``): sigma = xy + per_m * travelled. The
    # smoothed trajectory's relative error once its scale is estimated (below), measured against
    # truth (docs/alignment.md): 0.013-0.027 m per axis over 25 m, 0.025-0.059 m over
    # 50 m (urban the largest, standard and hard alike); this model covers the urban figures.
    # Yaw: measured 0.0008-0.0020 rad RMS over 25-50 m; the model gives 0.003-0.004 rad there
    # (times 1 + d / 50 m), still above the urban figure.
    submap_chain_sigma_xy_m: float = 0.01
    submap_chain_sigma_per_m: float = 0.001
    submap_chain_sigma_yaw_rad: float = 0.002
    # per-trip odometry distance scale left after the single-trip calibration (relative, 1-sigma):
    # a variable of each trip in the graph, scaling its e^sm translations (0: not estimated). The
    # calibration against the trip's own GNSS is off by 0.04 % RMS (measured), so this prior is
    # loose; 0.003 and 0.01 gave the same ATE.
    odom_scale_sigma: float = 0.003
    prior_map_sigma_xy_m: float = 0.10  # how firmly a pre-built map holds
    prior_map_sigma_yaw_rad: float = 0.005
    pose_graph_gnc: bool = True
    # a trip whose predicted own-GNSS error (``observability``: what no registration to another
    # trip holds, times the receiver's reported std and the latency disagreement) exceeds this
    # RMS over its overlapping sub-maps is marked failed: the accuracy alignment must deliver
    # (the target: every aligned trip under 0.5 m ATE), not a fitted value
    max_own_gnss_error_m: float = 0.5
    # off by default: measured (docs/alignment.md) it marks a 0.36 m trip on standard
    # rural seed 1 and misses 0.7-1.0 m trips on hard rural. The prediction
    # (``diagnostics["own_gnss_error_m"]``) is computed only when this is on: its gain is a dense
    # solve over all sub-maps
    mark_unobservable: bool = False

    # --- fine alignment (frame level) -------------------------------------------------------
    fine_keyframe_spacing_m: float = 2.0
    fine_gate_k: float = 4.0  # association gate = k * single-frame lateral sigma (+ coarse sigma)
    fine_coarse_sigma_m: float = 0.15  # expected error left by coarse alignment
    # chain between keyframes at the coarse relative pose: the relative accuracy of the
    # smoothed trajectory, from the trip's own odometry as e^sm's (``odometry_noise.chain_sigmas``
    # with ``odometry_noise.trip_yaw_random_walk``; ``fine_chain_sigma_xy0_m`` per step). False:
    # the distance model before it (``fine_chain_sigma_*``: 0.6 mrad per 2 m step, two to three
    # times the measured heading drift of rural and highway trips)
    fine_chain_from_odometry: bool = True
    fine_chain_sigma_xy0_m: float = 0.002
    fine_chain_sigma_per_m: float = 0.002
    fine_chain_sigma_floor_m: float = 0.002
    fine_chain_sigma_yaw_per_m: float = 0.0002
    fine_chain_sigma_yaw_floor_rad: float = 0.0002
    fine_registration_weight: float = (
        0.2  # keyframe spacing / ~10 m over which a frame's perception errors stay correlated
    )
    fine_prior_sigma_xy_m: float = 0.5  # keeps along-track where perception is degenerate
    fine_prior_sigma_yaw_rad: float = 0.02
    fine_min_points: int = 6
    fine_dashes: bool = True  # dash ends as along-road landmarks
    fine_dash_sigma_m: float = 0.15  # a painted dash end, single frame, along the dash
    fine_iterations: int = 2


DEFAULT = AlignmentParams()


@dataclass(frozen=True, slots=True)
class NoiseScales:
    """Per-type lateral sigma (metres) pooled over trips, and the derived Eq. 5/6 widths."""

    lateral_sigma_m: dict[ElementType, float]
    boundary_sigma_m: float
    sigma_p_m: float
    sigma_e_m: float
    dash_end_sigma_m: float = 0.5  # one sighting of a dash end, along the dash (divider along sigma)

    def lateral(self, element_type: ElementType) -> float:
        return self.lateral_sigma_m.get(element_type, FALLBACK_LATERAL_SIGMA_M)


def pooled_noise(noises: Sequence[Mapping[ElementType, ElementNoise]]) -> dict[ElementType, float]:
    """Root-mean-square lateral sigma per element type over trips."""
    out: dict[ElementType, float] = {}
    for t in ElementType:
        vals = [n[t].lateral_sigma_m for n in noises if t in n and np.isfinite(n[t].lateral_sigma_m)]
        out[t] = float(np.sqrt(np.mean(np.square(vals)))) if vals else FALLBACK_LATERAL_SIGMA_M
    return out


def noise_scales(trips: Sequence[TripReconstruction], params: AlignmentParams) -> NoiseScales:
    """Derive the Eq. 5/6 widths from the single-trip noise estimates."""
    lat = pooled_noise([t.noise for t in trips])
    bdr = lat[ElementType.ROAD_BOUNDARY]
    lines = [lat[t] for t in (ElementType.LANE_DIVIDER, ElementType.CENTERLINE, ElementType.ROAD_BOUNDARY)]
    typical = float(np.sqrt(np.mean(np.square(lines))))
    sigma_p = params.sigma_p_k * float(np.sqrt(2 * typical**2 + bdr**2)) + params.sigma_p_floor_m
    sigma_e = max(params.sigma_e_k * np.sqrt(2.0) * typical, params.sigma_e_floor_m)
    along = [
        t.noise[ElementType.LANE_DIVIDER].along_sigma_m
        for t in trips
        if ElementType.LANE_DIVIDER in t.noise
        and np.isfinite(t.noise[ElementType.LANE_DIVIDER].along_sigma_m)
    ]
    dash = float(np.sqrt(np.mean(np.square(along)))) if along else 0.5
    return NoiseScales(lat, bdr, sigma_p, float(sigma_e), dash)
