"""How far one trip's smoothed shape can be trusted between two of its sub-maps (Eq. 9's e^sm).

Two overlapping sub-maps of one trip are tied by their smoothed relative pose. Over the seconds
between two sub-map anchors GNSS cannot correct the shape, so the relative pose is as good as the
odometry: its heading drifts as a random walk (the gyro's white noise integrated, the *angle
random walk* ``q`` in rad/sqrt(s)), and that heading error bends the path sideways.

``q`` is read from each trip's own odometry (:func:`yaw_random_walk_rad_per_sqrt_s`): a car's yaw
rate changes smoothly, so from one 0.1 s increment to the next the yaw increments differ by
little but the gyro's white noise, which the second difference of the increments keeps (``6
sigma^2`` for white noise with ``sigma`` per increment) and a robust spread measures without the
moments where the yaw rate really changes. Measured against the simulator's truth on the five
worlds (standard seed 1): 0.00065-0.00093 rad/sqrt(s) for its 0.00063, so the estimate errs on
the loose side where roads bend often (Karlsruhe); the first difference read 0.00076-0.00121.

Over ``dt`` seconds and ``d`` metres (:func:`chain_sigmas`):

    sigma_yaw = q sqrt(dt)                        (a random walk's spread)
    sigma_xy  = sigma_xy0 + d sigma_yaw / sqrt(3) (the lateral error of a path whose heading is
                                                   that random walk, end to end; used on both axes)

The smoothed trajectory's relative error measured against truth follows this on every world and
both profiles (docs/alignment.md, "Session 24": 0.73 / 1.0 / 1.4 mrad over 1.5 / 3 / 6 s
whatever the speed), where the distance-based model before it (``0.002 (1 + d / 50)`` rad) was
three to four times too loose on rural and highway roads and matched only slow urban traffic.
"""

from __future__ import annotations

import numpy as np

from csr_core import se2
from csr_core.single_trip.noise import robust_sigma

#: fewer odometry increments than this give no estimate (the caller falls back to its default)
MIN_INCREMENTS = 20


def yaw_random_walk_rad_per_sqrt_s(timestamps_s: np.ndarray, odom_xyyaw: np.ndarray) -> float | None:
    """The angle random walk of a trip's odometry heading (rad/sqrt(s)), from the robust spread
    (1.4826 MAD) of the second difference of its yaw increments; None for too short a trip."""
    t = np.asarray(timestamps_s, float)
    odom = np.asarray(odom_xyyaw, float)
    if len(t) < MIN_INCREMENTS + 3:
        return None
    increments = se2.wrap_angle(np.diff(odom[:, 2]))
    dt = np.diff(t)
    step_s = float(np.median(dt))
    if not np.isfinite(step_s) or step_s <= 0:
        return None
    return robust_sigma(np.diff(increments, 2)) / np.sqrt(6.0) / np.sqrt(step_s)


def chain_sigmas(distance_m: float, duration_s: float, yaw_rw_rad_per_sqrt_s: float,
                 sigma_xy0_m: float) -> np.ndarray:
    """``(sigma_x, sigma_y, sigma_yaw)`` of e^sm between two anchors ``distance_m`` of travel and
    ``duration_s`` apart (module docstring)."""
    sigma_yaw = yaw_rw_rad_per_sqrt_s * np.sqrt(max(float(duration_s), 0.1))
    sigma_xy = sigma_xy0_m + float(distance_m) * sigma_yaw / np.sqrt(3.0)
    return np.array([sigma_xy, sigma_xy, sigma_yaw])
