"""e^sm's sigmas from a trip's own odometry (csr_core/alignment/odometry_noise.py)."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.alignment.odometry_noise import chain_sigmas, yaw_random_walk_rad_per_sqrt_s

pytestmark = pytest.mark.unit


def _odometry(yaw_rw_rad_per_sqrt_s: float, seed: int, n: int = 3000, rate_hz: float = 10.0):
    """A drive at 12 m/s: straight, a 60 m-radius bend entered and left over two seconds each,
    straight again; the yaw increments carry white noise of the given angle random walk."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt
    yaw_rate = np.interp(t, [0, 80, 82, 150, 152, 300], [0, 0, 0.2, 0.2, 0, 0])
    increments = yaw_rate[:-1] * dt + yaw_rw_rad_per_sqrt_s * np.sqrt(dt) * rng.standard_normal(n - 1)
    yaw = np.concatenate([[0.0], np.cumsum(increments)])
    xy = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * 12.0 * dt, axis=0)
    return t, np.column_stack([xy, yaw])


@pytest.mark.parametrize("yaw_rw", [0.0003, 0.001, 0.003])
def test_the_angle_random_walk_of_a_trip_is_read_from_its_yaw_increments(yaw_rw):
    estimates = [yaw_random_walk_rad_per_sqrt_s(*_odometry(yaw_rw, seed)) for seed in range(5)]
    assert all(e is not None for e in estimates)
    # the bend's entry and exit (a changing yaw rate) must not count as noise
    assert np.median(estimates) == pytest.approx(yaw_rw, rel=0.12)


def test_the_estimate_does_not_depend_on_the_frame_rate():
    at_10 = yaw_random_walk_rad_per_sqrt_s(*_odometry(0.001, 1, rate_hz=10.0))
    at_5 = yaw_random_walk_rad_per_sqrt_s(*_odometry(0.001, 1, n=1500, rate_hz=5.0))
    assert at_10 == pytest.approx(at_5, rel=0.15)


def test_a_trip_too_short_to_say_gives_no_estimate():
    t, odom = _odometry(0.001, 0, n=15)
    assert yaw_random_walk_rad_per_sqrt_s(t, odom) is None


def test_a_noiseless_straight_drive_reads_zero():
    t, odom = _odometry(0.0, 0, n=200)
    assert yaw_random_walk_rad_per_sqrt_s(t, odom) == pytest.approx(0.0, abs=1e-9)


def test_chain_sigmas_grow_as_a_heading_random_walk():
    slow = chain_sigmas(distance_m=20.0, duration_s=4.0, yaw_rw_rad_per_sqrt_s=0.001, sigma_xy0_m=0.005)
    fast = chain_sigmas(distance_m=20.0, duration_s=1.0, yaw_rw_rad_per_sqrt_s=0.001, sigma_xy0_m=0.005)
    # the heading's spread grows with the square root of the time between the anchors
    assert slow[2] == pytest.approx(2.0 * fast[2])
    assert slow[2] == pytest.approx(0.002)
    # the lateral error: distance times the heading's spread over sqrt(3), plus the floor
    assert slow[0] == pytest.approx(0.005 + 20.0 * 0.002 / np.sqrt(3.0))
    assert slow[0] == slow[1]


def test_chain_sigmas_of_many_links_are_those_of_each_link():
    d, dt = np.array([2.0, 2.0, 30.0]), np.array([0.05, 0.4, 1.5])
    many = chain_sigmas(d, dt, yaw_rw_rad_per_sqrt_s=0.0007, sigma_xy0_m=0.002)
    assert many.shape == (3, 3)
    for k in range(3):
        np.testing.assert_allclose(many[k], chain_sigmas(float(d[k]), float(dt[k]), 0.0007, 0.002))
    assert many[0, 2] == pytest.approx(0.0007 * np.sqrt(0.1))  # no link shorter than one 0.1 s increment
