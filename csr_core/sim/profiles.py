"""Every simulator model parameter, in one place: profiles ``standard``, ``hard`` and ``noiseless``.

Units are in the names. ``docs/simulator.md`` describes the models; this module is the source
of the numbers (``scenario.json`` stores the whole profile). The GNSS ``single`` status and
the receiver latency are calibrated on the comma2k19 u-blox log (see ``gnss_calibration``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

STATUS_NAMES = ("rtk_fixed", "rtk_float", "dgps", "single")


@dataclass(frozen=True, slots=True)
class GnssStatusModel:
    """Error model of one fix status: a first-order Gauss-Markov bias (per axis, east and north)
    plus white noise; ``std_m`` is reported as ``sqrt(bias^2 + white^2)`` times a log-normal factor."""

    bias_sigma_m: float  # stationary std of the GM bias, per axis
    bias_tau_s: float  # GM correlation time
    white_sigma_m: float  # per-axis white noise per fix
    mean_dwell_s: float  # mean time the receiver stays in this status (exponential)


@dataclass(frozen=True, slots=True)
class GnssParams:
    rate_hz: float = 10.0
    # status process: a semi-Markov chain over STATUS_NAMES (dwell ~ exponential, next status by row)
    initial_probs: tuple[float, ...] = (0.10, 0.20, 0.30, 0.40)
    transition_probs: tuple[tuple[float, ...], ...] = (
        (0.00, 0.70, 0.20, 0.10),
        (0.40, 0.00, 0.40, 0.20),
        (0.10, 0.30, 0.00, 0.60),
        (0.05, 0.15, 0.80, 0.00),
    )
    status_models: tuple[GnssStatusModel, ...] = (
        GnssStatusModel(bias_sigma_m=0.02, bias_tau_s=30.0, white_sigma_m=0.01, mean_dwell_s=60.0),
        GnssStatusModel(bias_sigma_m=0.20, bias_tau_s=30.0, white_sigma_m=0.04, mean_dwell_s=40.0),
        GnssStatusModel(bias_sigma_m=0.50, bias_tau_s=60.0, white_sigma_m=0.08, mean_dwell_s=90.0),
        GnssStatusModel(bias_sigma_m=0.60, bias_tau_s=600.0, white_sigma_m=0.04, mean_dwell_s=120.0),
    )
    # receivers: a share of the fleet has RTK-capable receivers whose fixes are time-tagged at the
    # measurement epoch (all statuses, no latency); the others are consumer receivers (statuses
    # dgps / single) whose fixes are stamped on arrival, like the comma2k19 u-blox
    rtk_receiver_share: float = 0.3
    latency_mean_s: float = 0.08  # consumer: fix = position this long before its stamp (comma2k19: 0.082 s)
    latency_sigma_s: float = 0.02  # consumer: spread of the latency between vehicles
    latency_jitter_s: float = 0.01  # consumer: per-fix time-tag jitter (along-track noise = speed * jitter)
    std_report_log_sigma: float = 0.15  # reported std_m = honest std * exp(this * z), z unit Gauss-Markov
    std_report_tau_s: float = 10.0  # correlation time of that factor
    heading_sigma_deg_at_10mps: float = 1.0  # course noise, scales with 10 / speed
    heading_min_speed_mps: float = 1.0  # no course below this speed
    # urban canyons (``World.canyon_zones_xyr``); zero rates disable them
    canyon_outage_rate_per_s: float = 0.0  # outage (status none) starts per second inside a zone
    canyon_outage_duration_s: tuple[float, float] = (3.0, 20.0)
    canyon_jump_rate_per_s: float = 0.0  # multipath jump starts per second inside a zone
    canyon_jump_duration_s: tuple[float, float] = (2.0, 10.0)
    canyon_jump_m: tuple[float, float] = (3.0, 10.0)  # jump size range (uniform), random direction
    canyon_degrade_to_single: bool = False  # fixes inside zones are at best `single`


@dataclass(frozen=True, slots=True)
class OdometryParams:
    """Dead reckoning from wheel speed and yaw rate: per-trip scale error and yaw-rate bias."""

    scale_error_sigma: float = 0.005  # per-vehicle (1 + e) on distance, e ~ N(0, this), clipped to 3 sigma
    yaw_rate_bias_sigma_deg_s: float = 0.03  # per-trip constant yaw-rate bias
    step_sigma_m_per_sqrt_m: float = 0.002  # white noise on each increment, per sqrt(metre travelled)
    yaw_step_sigma_rad: float = 0.0002  # white noise on each 0.1 s yaw increment
    scale_error_trip_sigma: float = 0.001  # per-trip part of the scale error, added to the vehicle's


@dataclass(frozen=True, slots=True)
class PerceptionParams:
    """MapTR-like BEV vector perception in the vehicle frame (x forward, y left)."""

    range_x_m: tuple[float, float] = (-15.0, 30.0)
    range_y_m: tuple[float, float] = (-15.0, 15.0)
    point_spacing_m: float = 2.0  # output vertex spacing along lines
    dense_step_m: float = 1.0  # internal truth sampling (clipping resolution at the range edge)
    min_visible_m: float = 1.0  # shorter visible pieces are not reported
    # noise: sigma = base + slope * distance from the vehicle (metres); boundaries are noisier
    line_white_base_m: float = 0.03
    line_white_per_m: float = 0.003
    line_offset_base_m: float = 0.05  # per-element, per-frame offset (correlated along the element)
    line_offset_per_m: float = 0.004
    offset_temporal_share: float = 0.7  # share of that offset's variance varying slowly with travel
    offset_wavelength_m: tuple[float, float] = (15.0, 60.0)  # its wavelength range (per track, uniform)
    track_bias_sigma_m: float = 0.04  # per-element offset drawn once per trip (same in every frame)
    frame_yaw_sigma_deg: float = 0.1  # per-frame BEV rotation (extrinsic jitter), common to all elements
    frame_scale_sigma: float = 0.003  # per-frame longitudinal scale error (ground-plane pitch)
    boundary_noise_factor: float = 2.0  # road_boundary sigmas = line sigmas * this
    polygon_noise_factor: float = 1.5  # crosswalk corner sigmas = line sigmas * this
    # detections
    miss_prob_base: float = 0.03
    miss_prob_at_range_end: float = 0.12  # extra miss probability at 30 m
    small_miss_prob: float = 0.10  # stop lines and crosswalks
    false_positive_rate_per_frame: float = 0.05  # Poisson mean of spurious short lines per frame
    false_positive_length_m: tuple[float, float] = (3.0, 12.0)
    ghost_rate_per_frame: float = 0.004  # ghost events start (per frame)
    ghost_frames: tuple[int, int] = (3, 10)
    ghost_shift_m: float = 3.5  # one lane width
    style_error_prob: float = 0.03  # divider style reported as `unknown`
    score_mean: float = 0.88
    score_drop_at_range_end: float = 0.15
    score_sigma: float = 0.04
    spurious_score: tuple[float, float] = (0.25, 0.6)
    # painted dashes of dashed dividers (phase fixed on the truth polyline, hence in the world)
    dash_length_m: float = 3.0
    dash_gap_m: float = 6.0


@dataclass(frozen=True, slots=True)
class TrafficParams:
    """How the fleet drives: routes, lane changes, speeds."""

    frame_rate_hz: float = 10.0
    lane_change_prob: float = 0.35  # per lane piece that has a neighbour and room
    lane_change_duration_s: float = 4.0
    red_light_prob: float = 0.35  # stop at a signalised stop line
    red_light_wait_s: tuple[float, float] = (5.0, 40.0)
    max_lateral_accel_mps2: float = 2.0
    max_accel_mps2: float = 1.5
    max_decel_mps2: float = 2.5
    driver_speed_factor: tuple[float, float] = (0.85, 1.05)  # per trip, times the legal speed
    lane_wander_sigma_m: float = 0.15  # slow lateral wander of the driver inside the lane
    n_vehicles: int = 0  # 0: about one vehicle per 3 trips
    # looping routes (``routes.looping_route``): a short approach, then laps of the shortest loop
    # of the lane graph through it (a delivery round, a search for parking), with stops anywhere
    loop_route_share: float = 0.0  # share of trips that loop; 0 draws nothing (other routes unchanged)
    loop_approach_m: tuple[float, float] = (20.0, 60.0)
    loop_stops_per_km: float = 3.0  # Poisson mean of stops (red lights, queues) per km of loop
    start_standstill_s: tuple[float, float] = (2.0, 6.0)  # a looping trip starts at rest this long


@dataclass(frozen=True, slots=True)
class Profile:
    name: str
    gnss: GnssParams = field(default_factory=GnssParams)
    odometry: OdometryParams = field(default_factory=OdometryParams)
    perception: PerceptionParams = field(default_factory=PerceptionParams)
    traffic: TrafficParams = field(default_factory=TrafficParams)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def standard() -> Profile:
    return Profile(name="standard")


def hard() -> Profile:
    """Mostly `single` fixes, urban canyons with multi-metre jumps and outages, worse perception."""
    gnss = dataclasses.replace(
        GnssParams(),
        initial_probs=(0.02, 0.08, 0.30, 0.60),
        rtk_receiver_share=0.1,
        transition_probs=(
            (0.00, 0.40, 0.30, 0.30),
            (0.15, 0.00, 0.35, 0.50),
            (0.03, 0.12, 0.00, 0.85),
            (0.02, 0.08, 0.90, 0.00),
        ),
        canyon_outage_rate_per_s=0.02,
        canyon_jump_rate_per_s=0.05,
        canyon_degrade_to_single=True,
    )
    odometry = dataclasses.replace(OdometryParams(), scale_error_sigma=0.008, yaw_rate_bias_sigma_deg_s=0.05)
    perception = dataclasses.replace(
        PerceptionParams(),
        track_bias_sigma_m=0.08,
        frame_yaw_sigma_deg=0.2,
        frame_scale_sigma=0.006,
        line_white_base_m=0.05,
        line_offset_base_m=0.08,
        miss_prob_base=0.08,
        miss_prob_at_range_end=0.2,
        false_positive_rate_per_frame=0.15,
        ghost_rate_per_frame=0.012,
        style_error_prob=0.08,
    )
    return Profile(name="hard", gnss=gnss, odometry=odometry, perception=perception)


def noiseless() -> Profile:
    """No sensor error at all (for tests and debugging): exact GNSS, odometry and perception."""
    exact = GnssStatusModel(bias_sigma_m=0.0, bias_tau_s=30.0, white_sigma_m=0.0, mean_dwell_s=1e9)
    gnss = dataclasses.replace(
        GnssParams(),
        initial_probs=(1.0, 0.0, 0.0, 0.0),
        rtk_receiver_share=1.0,
        status_models=(exact,) * 4,
        latency_mean_s=0.0,
        latency_sigma_s=0.0,
        latency_jitter_s=0.0,
        std_report_log_sigma=0.0,
        heading_sigma_deg_at_10mps=0.0,
    )
    odometry = OdometryParams(0.0, 0.0, 0.0, 0.0, 0.0)
    perception = dataclasses.replace(
        PerceptionParams(),
        line_white_base_m=0.0,
        line_white_per_m=0.0,
        line_offset_base_m=0.0,
        line_offset_per_m=0.0,
        track_bias_sigma_m=0.0,
        frame_yaw_sigma_deg=0.0,
        frame_scale_sigma=0.0,
        miss_prob_base=0.0,
        miss_prob_at_range_end=0.0,
        small_miss_prob=0.0,
        false_positive_rate_per_frame=0.0,
        ghost_rate_per_frame=0.0,
        style_error_prob=0.0,
        score_sigma=0.0,
    )
    return Profile(name="noiseless", gnss=gnss, odometry=odometry, perception=perception)


def loops() -> Profile:
    """The standard sensors on looping routes: every trip laps a short loop after a short
    approach, with long stops and a standstill at the start (``TrafficParams.loop_*``)."""
    return Profile(name="loops", traffic=dataclasses.replace(TrafficParams(), loop_route_share=1.0))


PROFILES = {"standard": standard, "hard": hard, "noiseless": noiseless, "loops": loops}


def get_profile(name: str) -> Profile:
    try:
        return PROFILES[name]()
    except KeyError:
        from csr_core.sim.world import SimulationError

        raise SimulationError(f"unknown profile {name!r}; known: {sorted(PROFILES)}") from None


def _flatten(prefix: str, value) -> list[tuple[str, object]]:
    if dataclasses.is_dataclass(value):
        out = []
        for f in dataclasses.fields(value):
            out += _flatten(f"{prefix}.{f.name}" if prefix else f.name, getattr(value, f.name))
        return out
    if isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
        out = []
        for name, item in zip(STATUS_NAMES, value, strict=True):
            out += _flatten(f"{prefix}[{name}]", item)
        return out
    return [(prefix, value)]


def parameter_table_markdown(names: tuple[str, ...] = ("standard", "hard", "noiseless")) -> str:
    """Every parameter with its value in each profile, as a markdown table (for docs/simulator.md)."""
    columns = [dict(_flatten("", get_profile(n))) for n in names]
    lines = ["| parameter | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
    for key in columns[0]:
        if key == "name":
            continue
        cells = [str(c[key]).replace("|", "/") for c in columns]
        lines.append(f"| `{key}` | " + " | ".join(cells) + " |")
    return "\n".join(lines)
