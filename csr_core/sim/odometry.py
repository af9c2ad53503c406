"""Wheel/IMU dead reckoning (parameters: ``profiles.OdometryParams``).

The true increments ``vehicle_{k}_T_vehicle_{k+1}`` get a distance scale error ``(1 + e)``
(per vehicle plus a small per-trip part), a per-trip yaw-rate bias ``b`` (``b * dt`` added to each yaw increment) and small
white noise, and are integrated from ``(0, 0, 0)`` in the trip's own odometry frame.
"""

from __future__ import annotations

import numpy as np

from csr_core import se2
from csr_core.sim.profiles import OdometryParams


def draw_scale_error(sigma: float, rng: np.random.Generator) -> float:
    """``e ~ N(0, sigma)`` clipped to 3 sigma (0 when sigma is 0)."""
    return float(np.clip(rng.normal(0.0, sigma), -3 * sigma, 3 * sigma)) if sigma > 0 else 0.0


def simulate_odometry(
    timestamps_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    params: OdometryParams,
    rng: np.random.Generator,
    vehicle_scale_error: float | None = None,
) -> tuple[np.ndarray, dict]:
    """``odom_xyyaw (N, 3)`` (metres, radians; odom frame) and the drawn per-trip errors.

    The distance scale error is the vehicle's (``vehicle_scale_error``, e.g. its tyre radius;
    None draws one with ``scale_error_sigma``) plus a per-trip part (load, tyre pressure)."""
    n = len(timestamps_s)
    if vehicle_scale_error is None:
        vehicle_scale_error = draw_scale_error(params.scale_error_sigma, rng)
    scale_error = vehicle_scale_error + draw_scale_error(params.scale_error_trip_sigma, rng)
    yaw_bias_rad_s = (
        float(np.radians(rng.normal(0.0, params.yaw_rate_bias_sigma_deg_s)))
        if params.yaw_rate_bias_sigma_deg_s > 0
        else 0.0
    )
    inc = se2.between(poses_xyyaw_world[:-1], poses_xyyaw_world[1:])  # (N-1, 3) vehicle-frame increments
    dist = np.linalg.norm(inc[:, :2], axis=1)
    dt = np.diff(timestamps_s)
    noise_xy = params.step_sigma_m_per_sqrt_m * np.sqrt(dist)[:, None] * rng.standard_normal((n - 1, 2))
    noise_yaw = params.yaw_step_sigma_rad * rng.standard_normal(n - 1)
    inc_xy = inc[:, :2] * (1.0 + scale_error) + noise_xy
    inc_yaw = inc[:, 2] + yaw_bias_rad_s * dt + noise_yaw
    # integrate: yaw_k = sum of earlier yaw increments; positions rotate each increment by yaw_k
    yaw = np.concatenate([[0.0], np.cumsum(inc_yaw)])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    step_world = np.column_stack([c * inc_xy[:, 0] - s * inc_xy[:, 1], s * inc_xy[:, 0] + c * inc_xy[:, 1]])
    xy = np.vstack([[0.0, 0.0], np.cumsum(step_world, axis=0)])
    odom = np.column_stack([xy, se2.wrap_angle(yaw)])
    return odom, {"scale_error": scale_error, "yaw_rate_bias_deg_s": float(np.degrees(yaw_bias_rad_s))}
