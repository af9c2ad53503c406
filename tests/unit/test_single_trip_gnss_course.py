"""Eq. 2's course factors (csr_core/single_trip/gnss_course.py): every fix's course, its sigma
measured on the trip."""

import dataclasses

import numpy as np
import pytest

from csr_core import metrics, se2
from csr_core.single_trip.gnss_course import course_noise
from csr_core.single_trip.params import DEFAULT
from csr_core.single_trip.pose_graph import _heading_yaw, integrate_increments, smooth_poses
from csr_core.types import GnssStatus

pytestmark = pytest.mark.unit


def _speeds(n: int, rng: np.random.Generator) -> np.ndarray:
    """5-20 m/s, changing slowly."""
    return 12.5 + 7.5 * np.sin(np.arange(n) / 400.0 + rng.uniform(0, 6))


def test_the_course_sigma_is_measured_per_speed_band():
    """Course noise of a velocity's direction: 0.17 m/s over the speed (the simulator's 1 degree
    at 10 m/s). The measured per-fix sigma follows it across the trip's speeds, from the course
    against an odometry yaw that drifts with a gyro's bias and random walk."""
    rng = np.random.default_rng(5)
    n = 3000
    t = np.arange(n) * 0.1
    speed = _speeds(n, rng)
    true_yaw = np.cumsum(0.02 * rng.standard_normal(n)) * 0.1
    odom_yaw = true_yaw + 0.4 + np.radians(0.05) * t + np.cumsum(2e-4 * rng.standard_normal(n))
    sigma_true = 0.17 / speed
    heading = se2.wrap_angle(true_yaw + sigma_true * rng.standard_normal(n))
    noise = course_noise(heading, odom_yaw, speed, t, DEFAULT)
    assert noise is not None
    assert noise.neighbour_correlation < 0.15
    ratio = noise.sigma_rad / sigma_true[noise.frames]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.15)
    slow, fast = speed[noise.frames] < 8.0, speed[noise.frames] > 17.0
    assert np.median(noise.sigma_rad[slow]) > 1.7 * np.median(noise.sigma_rad[fast])


def test_a_course_repeated_over_frames_is_not_counted_as_new_measurements():
    """A 1 Hz course logged at 10 Hz (the same value over ten frames): consecutive changes are
    mostly zero, which alone would claim a tiny sigma. The 1 s changes show the real spread and
    the repeats are counted about once: the factors' combined weight per second is near one
    course's, not ten."""
    rng = np.random.default_rng(8)
    n = 3000
    t = np.arange(n) * 0.1
    speed = np.full(n, 12.0)
    per_epoch = np.radians(1.0) * rng.standard_normal(n // 10)
    heading = np.repeat(per_epoch, 10) + 0.3
    noise = course_noise(heading, np.zeros(n), speed, t, DEFAULT)
    assert noise is not None
    assert noise.neighbour_correlation > 0.8
    weight_per_second = 10.0 / np.median(noise.sigma_rad) ** 2
    assert weight_per_second < 2.0 / np.radians(1.0) ** 2


def test_too_few_courses_fall_back_to_the_node_priors():
    n = 40
    heading = np.full(n, 0.1)
    assert course_noise(heading, np.zeros(n), np.full(n, 10.0), np.arange(n) * 0.1, DEFAULT) is None


def _weaving_trip(seed: int):
    """A 150 s drive at 10-14 m/s, 10 Hz, weaving gently; odometry with the simulator's gyro
    noise (0.0002 rad per 0.1 s: its yaw wanders a few tenths of a degree a minute); GNSS of a
    DGPS receiver (Gauss-Markov bias 0.5 m, 60 s, plus 0.08 m white) and its course (1 degree
    at 10 m/s, white)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 150.0, 0.1)
    n = len(t)
    speed = 12.0 + 2.0 * np.sin(t / 20.0)
    yaw_rate = 0.05 * np.sin(t / 9.0)
    incr = np.column_stack([speed[:-1] * 0.1, np.zeros(n - 1), yaw_rate[:-1] * 0.1])
    true = integrate_increments(np.zeros(3), incr)
    noisy = incr + np.column_stack(
        [
            0.002 * np.sqrt(incr[:, 0]) * rng.standard_normal(n - 1),
            np.zeros(n - 1),
            0.0002 * rng.standard_normal(n - 1),
        ]
    )
    odom = integrate_increments(np.array([3.0, -2.0, 0.4]), noisy)
    phi = np.exp(-0.1 / 60.0)
    bias = np.zeros((n, 2))
    bias[0] = 0.5 * rng.standard_normal(2)
    for k in range(1, n):
        bias[k] = phi * bias[k - 1] + 0.5 * np.sqrt(1 - phi**2) * rng.standard_normal(2)
    gnss = true[:, :2] + bias + 0.08 * rng.standard_normal((n, 2))
    status = np.full(n, int(GnssStatus.DGPS), np.uint8)
    heading_deg = np.degrees(
        np.pi / 2 - (true[:, 2] + np.radians(1.0) * 10.0 / speed * rng.standard_normal(n))
    )
    return t, true, odom, gnss, status, np.full(n, 0.5), np.mod(heading_deg, 360.0)


def test_every_fix_s_course_holds_the_trajectory_s_shape_against_the_gnss_bias() -> None:
    """The trajectory's sideways shape over tens of seconds is its yaw, which the gyro holds
    only for seconds and the wandering position bias cannot tell. Every course, weighed by its
    measured noise, holds it: the trip-aligned error (the single-trip measure) over four trips is
    lower than with one course per node at the fixed 3 degrees."""
    models = {
        "per_fix": dataclasses.replace(DEFAULT, GNSS_HEADING_PER_FIX=True),
        "per_node": dataclasses.replace(DEFAULT, GNSS_HEADING_PER_FIX=False),
    }
    errors: dict[str, list[np.ndarray]] = {k: [] for k in models}
    for seed in range(4):
        t, true, odom, gnss, status, std, heading = _weaving_trip(seed)
        for name, params in models.items():
            est = smooth_poses(t, gnss, status, std, heading, odom, params).poses_xyyaw_world[:, :2]
            aligned = metrics.apply_se2(metrics.umeyama_se2(est, true[:, :2]), est)
            errors[name].append(metrics.position_errors(aligned, true[:, :2]))
    rms = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in errors.items()}
    assert rms["per_fix"] < 0.85 * rms["per_node"], rms


def test_a_frame_without_a_new_fix_has_no_course():
    """A frame whose fix is a held repeat (status none to the stages) repeats its epoch's course
    too: it is not a new measurement; nor is a course below the minimum speed."""
    heading_deg = np.array([10.0, 10.0, 10.0, 20.0, 30.0])
    status = np.array([GnssStatus.DGPS, GnssStatus.NONE, GnssStatus.NONE, GnssStatus.DGPS, GnssStatus.DGPS])
    speed = np.array([10.0, 10.0, 10.0, 10.0, 1.0])
    yaw = _heading_yaw(heading_deg, status, speed, DEFAULT)
    assert np.isfinite(yaw).tolist() == [True, False, False, True, False]
    assert yaw[0] == pytest.approx(np.radians(80.0))
