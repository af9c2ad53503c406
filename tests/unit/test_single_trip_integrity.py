"""Never worse than the input, unflagged: the integrity test of a trip's poses against its GNSS,
the yaw-rate calibration's evidence count, and the repair of a runaway heading."""

import dataclasses

import numpy as np
import pytest

from csr_core.single_trip.integrity import TripVerdict, gnss_consistency, smooth_poses_checked
from csr_core.single_trip.params import DEFAULT
from csr_core.single_trip.pose_graph import calibrate_yaw_rate_bias, integrate_increments, smooth_poses
from csr_core.types import GnssStatus

pytestmark = pytest.mark.unit

DT_S = 0.1
RING_RADIUS_M = 20.0


def _loop_drive(
    laps: float = 18.0,
    approach_m: float = 40.0,
    standstill_s: float = 3.0,
    stops: tuple[tuple[float, float], ...] = ((150.0, 20.0), (320.0, 12.0), (470.0, 25.0)),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A trip like a delivery round: standing still, a straight approach, then laps of a ring
    of ``RING_RADIUS_M`` at 7 m/s, with stops (time s, wait s). Returns (t, true poses, increments)."""
    ring_m = 2 * np.pi * RING_RADIUS_M
    s_total = approach_m + laps * ring_m
    speed = 7.0
    t_move = np.arange(0.0, s_total / speed, DT_S)
    v = np.full(len(t_move), speed)
    # waits: insert frames at zero speed
    pieces_v = [np.zeros(int(standstill_s / DT_S))]
    last = 0
    for at_s, wait_s in stops:
        k = int(at_s / DT_S)
        pieces_v += [v[last:k], np.zeros(int(wait_s / DT_S))]
        last = k
    pieces_v.append(v[last:])
    speed_mps = np.concatenate(pieces_v)
    t = np.arange(len(speed_mps)) * DT_S
    s = np.r_[0.0, np.cumsum(speed_mps[:-1] * DT_S)]
    yaw = np.where(s < approach_m, 0.0, (s - approach_m) / RING_RADIUS_M)
    incr = np.column_stack([speed_mps * DT_S, np.zeros_like(t), np.r_[np.diff(yaw), 0.0]])[:-1]
    return t, integrate_increments(np.zeros(3), incr), incr


def _gnss(
    true_xy: np.ndarray,
    rng: np.random.Generator,
    bias_sigma_m: float = 0.85,
    tau_s: float = 60.0,
    white_m: float = 0.3,
) -> np.ndarray:
    """Fixes with a first-order Gauss-Markov bias per axis plus white noise."""
    n = len(true_xy)
    a = np.exp(-DT_S / tau_s)
    bias = np.zeros((n, 2))
    bias[0] = rng.normal(scale=bias_sigma_m, size=2)
    drive = rng.normal(scale=bias_sigma_m * np.sqrt(1 - a * a), size=(n, 2))
    for k in range(1, n):
        bias[k] = a * bias[k - 1] + drive[k]
    return true_xy + bias + rng.normal(scale=white_m, size=(n, 2))


def _course_deg(true: np.ndarray, speed_ok: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    heading = np.degrees(np.pi / 2 - true[:, 2]) % 360.0 + rng.normal(scale=2.0, size=len(true))
    return np.where(speed_ok, heading, np.nan)


def _loop_trip(seed: int, yaw_rate_bias_deg_s: float):
    rng = np.random.default_rng(seed)
    t, true, incr = _loop_drive()
    biased = incr.copy()
    biased[:, 2] += np.radians(yaw_rate_bias_deg_s) * DT_S + rng.normal(scale=2e-4, size=len(incr))
    odom = integrate_increments(np.zeros(3), biased)
    gnss = _gnss(true[:, :2], rng)
    moving = np.r_[np.linalg.norm(np.diff(true[:, :2], axis=0), axis=1) / DT_S, 0.0] > 3.0
    std = np.full(len(t), 1.0)
    status = np.full(len(t), int(GnssStatus.DGPS), np.uint8)
    return t, true, odom, gnss, status, std, _course_deg(true, moving, rng)


def _rmse(a_xy: np.ndarray, b_xy: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a_xy - b_xy) ** 2, axis=1))))


def _median_offset(poses_xyyaw: np.ndarray, gnss_xy: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(poses_xyyaw[:, :2] - gnss_xy, axis=1)))


def smoothed_plain(t, gnss, status, std, course, odom, params) -> np.ndarray:
    return smooth_poses(t, gnss, status, std, course, odom, params).poses_xyyaw_world


def test_multipath_jumps_the_smoother_rejects_do_not_mark_a_trip():
    """Jumps of 4-9 m for 6-10 s over a tenth of the trip (urban canyons): the smoother rejects
    them and the test, which reads the kept fixes per window and the median over all, passes."""
    t, true, odom, gnss, status, std, course = _loop_trip(15, 0.02)
    rng = np.random.default_rng(15)
    jumped = gnss.copy()
    for start_s in (60.0, 170.0, 300.0, 420.0):
        sel = (t >= start_s) & (t < start_s + rng.uniform(6.0, 10.0))
        angle = rng.uniform(0, 2 * np.pi)
        jumped[sel] += rng.uniform(4.0, 9.0) * np.array([np.cos(angle), np.sin(angle)])
    smoothed, quality = smooth_poses_checked(t, jumped, status, std, course, odom, DEFAULT)
    assert quality.verdict == TripVerdict.OK, quality.reason
    assert _rmse(smoothed.poses_xyyaw_world[:, :2], true[:, :2]) <= _rmse(jumped, true[:, :2])


def test_consistency_passes_the_truth_and_fails_a_turned_trajectory():
    t, true, _, gnss, _, std, _ = _loop_trip(3, 0.0)
    has_fix = np.ones(len(t), bool)
    ok = gnss_consistency(t, true, gnss, std, has_fix, DEFAULT)
    assert ok.passed and ok.worst_z < ok.z_limit
    # the same trajectory turned by 40 deg about its start: off by tens of metres
    c, s = np.cos(np.radians(40.0)), np.sin(np.radians(40.0))
    turned = true.copy()
    turned[:, :2] = true[:, :2] @ np.array([[c, s], [-s, c]])
    bad = gnss_consistency(t, turned, gnss, std, has_fix, DEFAULT)
    assert not bad.passed and bad.worst_z > 10.0


def test_consistency_locates_a_bad_stretch():
    t, true, _, gnss, _, std, _ = _loop_trip(4, 0.0)
    off = true.copy()
    bad = (t >= 200.0) & (t < 260.0)
    off[bad, 0] += 8.0
    check = gnss_consistency(t, off, gnss, std, np.ones(len(t), bool), DEFAULT)
    stretches = check.failing_stretches_s()
    assert len(stretches) == 1
    a, b = stretches[0]
    assert 190.0 <= a <= 201.0 and 255.0 <= b <= 270.0


def test_a_loop_gives_no_yaw_rate_estimate_however_many_overlapping_chords():
    """Laps of a ring shorter than the chord window: every long chord lies in the approach, so
    the calibration says "not estimated" and keeps the physical prior."""
    t, _, odom, gnss, status, std, _ = _loop_trip(5, 0.03)
    cal = calibrate_yaw_rate_bias(t, odom, gnss, std, np.ones(len(t), bool), DEFAULT)
    assert not cal.estimated
    assert cal.bias_rad_s == 0.0
    assert cal.sigma_rad_s == pytest.approx(DEFAULT.CAL_YAW_RATE_BIAS_PRIOR_RAD_S)


def test_a_long_open_drive_gives_an_estimate_with_its_uncertainty():
    rng = np.random.default_rng(6)
    t = np.arange(0.0, 400.0, DT_S)
    yaw = 0.8 * np.sin(t / 40.0)
    incr = np.column_stack([np.full(len(t), 1.2), np.zeros_like(t), np.r_[np.diff(yaw), 0.0]])[:-1]
    true = integrate_increments(np.zeros(3), incr)
    bias = np.radians(0.04)
    biased = incr.copy()
    biased[:, 2] += bias * DT_S
    odom = integrate_increments(np.zeros(3), biased)
    gnss = true[:, :2] + rng.normal(scale=0.3, size=(len(t), 2))
    cal = calibrate_yaw_rate_bias(t, odom, gnss, np.full(len(t), 0.3), np.ones(len(t), bool), DEFAULT)
    assert cal.estimated and cal.independent_chords >= 40
    assert cal.sigma_rad_s < 0.2 * DEFAULT.CAL_YAW_RATE_BIAS_PRIOR_RAD_S
    assert abs(cal.bias_rad_s - bias) < 3.0 * cal.sigma_rad_s + np.radians(0.002)


@pytest.mark.parametrize("seed", [11, 12])
def test_a_good_loop_trip_is_never_marked_and_beats_its_gnss(seed):
    t, true, odom, gnss, status, std, course = _loop_trip(seed, 0.02)
    smoothed, quality = smooth_poses_checked(t, gnss, status, std, course, odom, DEFAULT)
    assert quality.verdict == TripVerdict.OK, quality.reason
    assert _rmse(smoothed.poses_xyyaw_world[:, :2], true[:, :2]) <= _rmse(gnss, true[:, :2])


def test_a_planted_heading_runaway_is_caught_and_repaired():
    """A gyro bias ten times the prior on a looping trip (nothing to calibrate it from): the
    smoother alone runs away from the trip's own GNSS; the checked smoother says so and repairs
    it to better than the GNSS."""
    t, true, odom, gnss, status, std, course = _loop_trip(13, 0.4)
    plain = smooth_poses(t, gnss, status, std, course, odom, DEFAULT)
    raw_rmse = _rmse(gnss, true[:, :2])
    assert _rmse(plain.poses_xyyaw_world[:, :2], true[:, :2]) > 2.0 * raw_rmse
    smoothed, quality = smooth_poses_checked(t, gnss, status, std, course, odom, DEFAULT)
    assert quality.verdict in (TripVerdict.REPAIRED, TripVerdict.DEGRADED)
    assert quality.stretches_s and "sigma off the trip's GNSS" in quality.reason
    assert _rmse(smoothed.poses_xyyaw_world[:, :2], true[:, :2]) <= raw_rmse


def test_a_trip_the_repair_cannot_fix_is_marked_degraded_and_anchored_to_its_gnss():
    """With a repair that holds the odometry heading even stiffer than the first solve, the
    fallback must place the trip on its GNSS and mark it degraded."""
    t, true, odom, gnss, status, std, course = _loop_trip(14, 2.0)
    stiff = dataclasses.replace(DEFAULT, INTEGRITY_REPAIR_YAW_FACTOR=0.01, CAL_YAW_RATE_BIAS_PRIOR_RAD_S=1e-7)
    smoothed, quality = smooth_poses_checked(t, gnss, status, std, course, odom, stiff)
    assert quality.verdict == TripVerdict.DEGRADED and quality.degraded
    assert "the repair failed too" in quality.reason and quality.reason.endswith("kept")
    # of the three solves, the one kept is the least far from the trip's GNSS
    assert quality.median_offset_m <= _median_offset(
        smoothed_plain(t, gnss, status, std, course, odom, stiff), gnss
    )


def test_aligned_poses_within_the_gnss_error_model_are_kept_and_a_bad_shift_is_reverted():
    """Aligned poses at the truth are off the fixes by the GNSS bias (here 2.5 sigma, all along
    the trip): kept. Aligned poses moved 12 m by a wrong registration: the single-trip poses
    come back, with the reason."""
    from types import SimpleNamespace

    from csr_core.geo import LocalFrame
    from csr_core.single_trip.integrity import check_aligned_poses

    rng = np.random.default_rng(21)
    t, true, _, _, status, std, _ = _loop_trip(16, 0.0)
    frame = LocalFrame(48.0, 11.0)
    gnss = (
        true[:, :2] + np.array([1.77, -1.77]) + rng.normal(scale=0.1, size=(len(t), 2))
    )  # |bias| = 2.5 sigma
    trip = SimpleNamespace(
        fix_status=status,
        gnss_std_m=std,
        has_fix=np.ones(len(t), bool),
        timestamps_s=t,
        gnss_lonlat_deg=frame.to_lonlat(gnss),
    )
    single = true.copy()
    single[:, :2] = gnss  # the single-trip poses follow the fixes
    kept, reason = check_aligned_poses(trip, single, true, frame, DEFAULT)
    assert reason is None and kept is true
    wrong = true.copy()
    wrong[:, 0] += 12.0
    kept, reason = check_aligned_poses(trip, single, wrong, frame, DEFAULT)
    assert kept is single and reason is not None and "single-trip poses kept" in reason
