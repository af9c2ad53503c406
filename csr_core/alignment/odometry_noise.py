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

The same model ties the fine stage's keyframes (every ``fine_keyframe_spacing_m``, a tenth of a
second to a second apart; ``fine.refine_trip``), with ``sigma_xy0`` the step-length noise of
wheel odometry over one such step (0.1 % of 2 m).

The smoothed trajectory's relative error measured against truth follows this on every world and
both profiles (docs/alignment.md: 0.73 / 1.0 / 1.4 mrad over 1.5 / 3 / 6 s
whatever the speed), where the distance-based model before it (``0.002 (1 + d / 50)`` rad) was
three to four times too loose on rural and highway roads and matched only slow urban traffic.
"""

from __future__ import annotations

import numpy as np

from csr_core import se2
from csr_core.alignment.params import AlignmentParams
from csr_core.single_trip.noise import robust_sigma
from csr_core.types import TripReconstruction

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


def chain_sigmas(
    distance_m: float | np.ndarray,
    duration_s: float | np.ndarray,
    yaw_rw_rad_per_sqrt_s: float,
    sigma_xy0_m: float,
) -> np.ndarray:
    """``(sigma_x, sigma_y, sigma_yaw)`` of a link ``distance_m`` of travel and ``duration_s``
    apart (module docstring): ``(3,)`` for one link, ``(n, 3)`` for arrays of ``n``. No link is
    shorter in time than one 0.1 s odometry increment."""
    sigma_yaw = yaw_rw_rad_per_sqrt_s * np.sqrt(np.maximum(np.asarray(duration_s, float), 0.1))
    sigma_xy = sigma_xy0_m + np.asarray(distance_m, float) * sigma_yaw / np.sqrt(3.0)
    return np.stack([sigma_xy, sigma_xy, sigma_yaw], axis=-1)


def trip_yaw_random_walk(trip: TripReconstruction, params: AlignmentParams) -> float:
    """The angle random walk (rad/sqrt(s)) that the chains (e^sm, the fine keyframes) assume for
    ``trip``: read from its odometry (:func:`yaw_random_walk_rad_per_sqrt_s`), the default for a
    trip too short to say, at least ``submap_chain_yaw_rw_min``."""
    q = yaw_random_walk_rad_per_sqrt_s(trip.trip.timestamps_s, trip.trip.odom_xyyaw)
    return max(params.submap_chain_yaw_rw_default if q is None else q, params.submap_chain_yaw_rw_min)
