"""Wheel-speed and gyro dead reckoning of fleet b, integrated at ``integration_rate_hz``
(100 Hz) and sampled at the frames.

It follows the standard 2-D odometry mechanisation of a land vehicle (Groves, 2nd ed., ch. 6.3
and 16.2; Titterton and Weston, *Strapdown Inertial Navigation Technology*, ch. 8 for the gyro
errors):

- Distance: wheel-encoder ticks of ``wheel_tick_m`` counted on the true travel times
  ``1 + e0 + k v``: ``e0`` the vehicle's rolling-radius error, ``k`` per m/s the radius growth and
  slip with speed (both per vehicle, shared by its trips). The tick count quantises distance.
- Yaw rate: the true rate times ``1 + gyro scale error`` (per vehicle) plus a bias that starts at
  ``N(0, gyro_bias_init_sigma_rad_s)`` and follows a random walk of
  ``gyro_bias_rw_rad_s_per_sqrt_s`` (rate random walk), plus white noise ``gyro_white_rad_s`` per
  sample. At standstill (no wheel tick within ``standstill_window_s``) the heading is held, as a
  zero-velocity update does.
- Integration: heading by the measured rate, position by the tick distance along the mid-step
  heading; the odometry frame starts at a random pose (only differences are meaningful), yaw
  wrapped to (-pi, pi].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from csr_core.sim.fleet_b.params import OdometryParamsB


@dataclass(frozen=True, slots=True)
class OdometerB:
    """One vehicle's wheel and gyro traits, shared by its trips."""

    scale_error: float  # e0
    scale_per_mps: float  # k, per m/s
    gyro_scale_error: float


def draw_odometer_b(params: OdometryParamsB, rng: np.random.Generator) -> OdometerB:
    return OdometerB(
        scale_error=float(rng.normal(0.0, params.scale_error_sigma)),
        scale_per_mps=float(rng.normal(params.scale_per_mps_mean, params.scale_per_mps_sigma)),
        gyro_scale_error=float(rng.normal(0.0, params.gyro_scale_sigma)),
    )


def fine_truth(
    t_s: np.ndarray, poses_xyyaw_world: np.ndarray, rate_hz: float
) -> tuple[np.ndarray, np.ndarray]:
    """The true trajectory at ``rate_hz``: times (F,) and poses (F, 3), yaw unwrapped; frame k is
    sample ``k * n_sub`` with ``n_sub = round(rate_hz * frame spacing)``."""
    n_sub = max(1, int(round(rate_hz * float(np.median(np.diff(t_s))))))
    u = np.arange((len(t_s) - 1) * n_sub + 1) / n_sub
    t_fine = np.interp(u, np.arange(len(t_s)), t_s)
    yaw = np.unwrap(poses_xyyaw_world[:, 2])
    cols = [
        PchipInterpolator(t_s, c)(t_fine) for c in (poses_xyyaw_world[:, 0], poses_xyyaw_world[:, 1], yaw)
    ]
    return t_fine, np.column_stack(cols)


def simulate_odometry_b(
    t_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    params: OdometryParamsB,
    rng: np.random.Generator,
    odometer: OdometerB,
) -> tuple[np.ndarray, dict[str, float]]:
    """Odometry poses (N, 3) at the frames ``t_s`` and the trip's drawn traits."""
    t_fine, fine = fine_truth(t_s, poses_xyyaw_world, params.integration_rate_hz)
    n_sub = (len(t_fine) - 1) // max(len(t_s) - 1, 1)
    dt = np.diff(t_fine)
    d_true = np.linalg.norm(np.diff(fine[:, :2], axis=0), axis=1)
    v = d_true / np.maximum(dt, 1e-9)
    wheel = d_true * (1.0 + odometer.scale_error + odometer.scale_per_mps * v)
    ticks = np.floor(np.concatenate([[0.0], np.cumsum(wheel)]) / params.wheel_tick_m)
    d_meas = np.diff(ticks) * params.wheel_tick_m

    omega = np.diff(fine[:, 2]) / np.maximum(dt, 1e-9)
    b0 = rng.normal(0.0, params.gyro_bias_init_sigma_rad_s)
    steps = params.gyro_bias_rw_rad_s_per_sqrt_s * np.sqrt(dt) * rng.standard_normal(len(dt))
    bias = b0 + np.concatenate([[0.0], np.cumsum(steps[:-1])])
    omega_meas = omega * (1.0 + odometer.gyro_scale_error) + bias
    omega_meas += params.gyro_white_rad_s * rng.standard_normal(len(dt))
    # standstill: no wheel tick within +-standstill_window_s (one tick gap at 1 m/s is 0.02 s)
    half = max(1, int(round(params.standstill_window_s * params.integration_rate_hz)))
    ticking = np.convolve((d_meas > 0.0).astype(float), np.ones(2 * half + 1), mode="same") > 0.0
    dyaw = np.where(ticking, omega_meas * dt, 0.0)

    x0, y0 = rng.uniform(-params.start_pose_span_m, params.start_pose_span_m, 2)
    yaw0 = rng.uniform(-np.pi, np.pi)
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(dyaw)])
    mid = yaw[:-1] + 0.5 * dyaw
    x = x0 + np.concatenate([[0.0], np.cumsum(d_meas * np.cos(mid))])
    y = y0 + np.concatenate([[0.0], np.cumsum(d_meas * np.sin(mid))])
    pick = np.arange(len(t_s)) * n_sub
    odom = np.column_stack([x[pick], y[pick], np.angle(np.exp(1j * yaw[pick]))])
    info = {
        "scale_error": odometer.scale_error,
        "scale_per_mps": odometer.scale_per_mps,
        "gyro_scale_error": odometer.gyro_scale_error,
        "gyro_bias_start_deg_s": float(np.degrees(bias[0])) if len(bias) else 0.0,
        "gyro_bias_end_deg_s": float(np.degrees(bias[-1])) if len(bias) else 0.0,
    }
    return odom, info
