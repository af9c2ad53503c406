"""Parameters of fleet b, the second fleet model: GNSS, odometry, perception and its traffic.

Units are in the names. ``docs/simulator.md`` (section "Fleet b") says where each model
differs from fleet a; the module docstrings of ``gnss``, ``odometry`` and ``perception`` say
what each model follows. ``scenario.json`` of a fleet-b scenario stores all of these values.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from csr_core.sim.profiles import TrafficParams

STATUS_NAMES_B = ("rtk_fixed", "rtk_float", "dgps", "single")


@dataclass(frozen=True, slots=True)
class StatusErrorB:
    """Position error of one fix status, per axis (east, north): an Ornstein-Uhlenbeck bias (a
    random walk pulled back to zero with time constant ``bias_reversion_s``, stationary std
    ``bias_sigma_m``) plus white noise ``white_sigma_m``. ``std_report_factor`` is the ratio of the
    reported ``std_m`` to the true horizontal (2-D RMS) error: below 1 the receiver is optimistic."""

    bias_sigma_m: float
    bias_reversion_s: float
    white_sigma_m: float
    std_report_factor: float


@dataclass(frozen=True, slots=True)
class GnssParamsB:
    rate_hz: float = 10.0
    # status: a discrete-time Markov chain at rate_hz over STATUS_NAMES_B with these transition
    # rates (per second, row = from, column = to; the diagonal is ignored)
    transition_rate_per_s: tuple[tuple[float, ...], ...] = (
        (0.0, 0.010, 0.004, 0.002),
        (0.030, 0.0, 0.008, 0.004),
        (0.006, 0.012, 0.0, 0.010),
        (0.002, 0.004, 0.015, 0.0),
    )
    initial_probs: tuple[float, ...] = (0.35, 0.20, 0.25, 0.20)
    status_errors: tuple[StatusErrorB, ...] = (
        StatusErrorB(bias_sigma_m=0.03, bias_reversion_s=45.0, white_sigma_m=0.015, std_report_factor=1.0),
        StatusErrorB(bias_sigma_m=0.35, bias_reversion_s=20.0, white_sigma_m=0.08, std_report_factor=0.5),
        StatusErrorB(bias_sigma_m=0.70, bias_reversion_s=40.0, white_sigma_m=0.20, std_report_factor=1.3),
        StatusErrorB(bias_sigma_m=1.20, bias_reversion_s=150.0, white_sigma_m=0.30, std_report_factor=0.7),
    )
    correction_share: float = 0.5  # vehicles with an RTK correction link; the others: dgps / single only
    std_report_jitter_log_sigma: float = 0.10  # per-fix log-normal jitter of the reported std_m
    # multipath bursts: Poisson starts, a half-sine offset in a random direction, not in std_m
    multipath_rate_per_s: float = 0.004
    multipath_canyon_factor: float = 10.0  # rate multiplier inside the world's canyon zones
    multipath_mean_m: float = 2.5  # burst amplitude ~ exponential with this mean ...
    multipath_max_m: float = 8.0  # ... capped here
    multipath_unfix_m: float = 1.0  # a larger burst turns rtk_fixed into rtk_float while it lasts
    multipath_duration_s: tuple[float, float] = (1.0, 6.0)
    # short outages (bridges, tunnels): status none, no std_m nor course
    outage_rate_per_s: float = 0.001
    outage_duration_s: tuple[float, float] = (1.0, 8.0)
    # course over ground from the receiver velocity (Doppler): white velocity noise per axis,
    # so the course noise is velocity_sigma_mps / speed radians; no course below the speed
    velocity_sigma_mps: float = 0.05
    course_min_speed_mps: float = 1.5
    latency_s: tuple[float, float] = (0.0, 0.12)  # per vehicle (uniform): fix = position this long before


@dataclass(frozen=True, slots=True)
class OdometryParamsB:
    integration_rate_hz: float = 100.0  # wheel ticks and gyro integrated at this rate, sampled per frame
    wheel_tick_m: float = 0.02  # distance per encoder tick (~2 m tyre circumference / 96 ticks)
    scale_error_sigma: float = 0.006  # per vehicle: wheel distance x (1 + e0 + k v), e0 ~ N(0, this)
    scale_per_mps_mean: float = 2.0e-4  # k ~ N(mean, sigma) per vehicle: tyre growth and slip with speed
    scale_per_mps_sigma: float = 5.0e-5
    gyro_bias_init_sigma_rad_s: float = 8.7e-4  # 0.05 deg/s at the start of a trip
    gyro_bias_rw_rad_s_per_sqrt_s: float = 1.0e-5  # random walk of the bias (rate random walk)
    gyro_white_rad_s: float = 8.7e-4  # white noise per 100 Hz sample (0.3 deg/sqrt(h) ARW ~ 0.05 deg/s)
    gyro_scale_sigma: float = 0.003  # per vehicle yaw-rate scale factor error
    standstill_window_s: float = 0.5  # no wheel tick within +- this: standstill, heading held
    start_pose_span_m: float = 5000.0  # the odometry frame starts at a random pose (+-this, any yaw)


@dataclass(frozen=True, slots=True)
class OccluderParamsB:
    """Other traffic as moving boxes along the ego path: a lead vehicle, one on each side, one
    oncoming; each present for exponential on/off periods."""

    lead_gap_m: tuple[float, float] = (8.0, 35.0)
    side_gap_m: tuple[float, float] = (-15.0, 20.0)
    side_offset_m: float = 3.4  # lateral offset of side / oncoming vehicles
    oncoming_start_gap_m: float = 60.0
    oncoming_speed_mps: float = 10.0
    mean_present_s: float = 20.0
    mean_absent_s: float = 20.0
    car_size_m: tuple[float, float] = (4.6, 1.9)
    truck_size_m: tuple[float, float] = (12.0, 2.55)
    truck_share: float = 0.15
    gap_reversion_s: float = 15.0  # the gaps wander (Ornstein-Uhlenbeck) inside their ranges


@dataclass(frozen=True, slots=True)
class PerceptionParamsB:
    range_x_m: tuple[float, float] = (-30.0, 30.0)  # MapTR's nuScenes range: 60 m x 30 m
    range_y_m: tuple[float, float] = (-15.0, 15.0)
    sample_step_m: float = 0.5  # truth sampling: visibility, clipping and occlusion resolution
    points_per_instance: int = 20  # line instances resampled to this many points (MapTR) ...
    min_point_spacing_m: float = 1.5  # ... or fewer on short instances (a 3 m dash has 3 points)
    min_piece_m: float = 1.0
    # noise sigma(r) = base + quad * r^2, r = distance from the vehicle
    point_sigma_base_m: float = 0.03
    point_sigma_quad_per_m2: float = 1.2e-4
    offset_sigma_base_m: float = 0.03  # per instance and frame, normal to the line
    offset_sigma_quad_per_m2: float = 8.0e-5
    track_bias_sigma_m: float = 0.05  # per track (until its id changes), normal to the line
    centerline_noise_factor: float = 1.5  # centrelines are inferred, not painted
    extrinsic_yaw_sigma_rad: float = 0.0026  # per vehicle camera-rig yaw misalignment (0.15 deg)
    extrinsic_xy_sigma_m: float = 0.05  # per vehicle rig translation error
    # detection: p_miss(r, occluded share) = base + range * (r / r_max)^2 + occlusion * share
    miss_prob_base: float = 0.02
    miss_prob_range: float = 0.20
    miss_prob_occlusion: float = 0.6
    small_element_miss_prob: float = 0.08  # added for stop lines and crosswalks
    false_positive_rate_per_frame: float = 0.08  # Poisson mean of spurious instances per frame
    false_positive_length_m: tuple[float, float] = (2.0, 15.0)
    # tracker: ids kept while seen; a new id after a gap longer than this or at a switch
    track_lost_frames: int = 5
    track_switch_prob: float = 0.004  # per track and frame
    # dashed dividers: painted dashes (phase from the element id, the same in every trip);
    # beyond the merge range the detector reports a dashed run as one instance
    dash_length_m: float = 3.0
    dash_gap_m: float = 9.0
    dash_merge_range_m: float = 20.0
    style_confusion_prob: float = 0.05  # solid <-> dashed, more likely at range (x r / r_max)
    # score: logistic in (score_logit_base - score_logit_range * r / r_max - occlusion) + noise
    score_logit_base: float = 3.0
    score_logit_range: float = 1.5
    score_logit_sigma: float = 0.5
    spurious_score_beta: tuple[float, float] = (2.0, 4.0)
    occluders: OccluderParamsB = field(default_factory=OccluderParamsB)


def traffic_b() -> TrafficParams:
    """Fleet b drives the same routes generator with more red-light stops and some loops."""
    return dataclasses.replace(TrafficParams(), red_light_prob=0.7, loop_route_share=0.25)


@dataclass(frozen=True, slots=True)
class FleetBParams:
    name: str = "fleet-b"
    gnss: GnssParamsB = field(default_factory=GnssParamsB)
    odometry: OdometryParamsB = field(default_factory=OdometryParamsB)
    perception: PerceptionParamsB = field(default_factory=PerceptionParamsB)
    traffic: TrafficParams = field(default_factory=traffic_b)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
