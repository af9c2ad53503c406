"""Eq. 2's GNSS course factors: every fix's course, weighed by the noise the trip's own data shows.

A receiver's course over ground is the direction of its Doppler velocity, not of its position
fixes, so its error is not the position's slowly wandering bias: the comma2k19 u-blox's course is
0.31 degrees (1 sigma) off the reference with no measurable bias and no autocorrelation at 10 Hz
(lags 1-50 fixes inside the white-noise band; 1 s and 2 s block means 1.1x what white noise
gives; docs/single-trip.md). Averaged over the fixes of a few seconds it holds the
yaw far better than the gyro's random walk, and the yaw over tens of seconds is the trajectory's
sideways shape: what the position bias cannot be told apart from.

With ``GNSS_HEADING_PER_FIX`` (on; off, the graph takes one course per node, every 5 m or 1 s, at a
fixed 3 degrees: docs/single-trip.md) every fix with a course is a
``PoseRotationPrior2D`` on
its node (the odometry's yaw from the node to the instant the course refers to taken off), with a
sigma measured on the trip:

- the course minus the odometry's yaw changes between consecutive fixes only by the course
  noise (the odometry's yaw drifts by about a hundredth of it in 0.1 s), so the robust spread of
  those changes is the per-fix sigma; measured per speed band (quartiles of the trip's speeds),
  since a velocity's direction is noisier the slower the vehicle;
- noise correlated from fix to fix would make consecutive changes small and the sigma too
  small, and averaging would not reduce it like white noise. So the spread is also measured
  over ``COURSE_DECORRELATION_S`` (1 s) of fixes; the larger of the two is the sigma, and their
  ratio gives the correlation ``rho`` between neighbouring fixes, which inflates each factor's
  sigma by ``sqrt((1 + rho) / (1 - rho))`` (the variance of the mean of AR(1) noise). White
  noise (the simulator's, the u-blox's) gives ``rho`` near 0; a course repeated over several
  frames (a 1 Hz receiver logged at 10 Hz) a large inflation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csr_core import se2
from csr_core.single_trip.noise import robust_sigma
from csr_core.single_trip.params import SingleTripParams

SPEED_BANDS = 4  # quartiles of the trip's speeds with a course
MAX_NEIGHBOUR_CORRELATION = 0.95


@dataclass(frozen=True, slots=True)
class CourseNoise:
    """The trip's course noise: frames with a course and each one's factor sigma (rad)."""

    frames: np.ndarray  # (M,) frame indices with a course
    sigma_rad: np.ndarray  # (M,) factor sigma per course (inflation included)
    neighbour_correlation: float  # rho between consecutive fixes (0: white)


def _change_sigmas(
    residual_rad: np.ndarray, frames: np.ndarray, lag: int, bands: np.ndarray, min_pairs: int
) -> tuple[float, np.ndarray]:
    """The per-fix sigma from the changes of ``residual`` between fixes ``lag`` frames apart (both
    with a course): robust spread / sqrt(2), over all pairs and per speed band (``bands`` of
    ``frames``, 0..SPEED_BANDS-1); NaN where there are fewer than ``min_pairs``."""
    has = np.zeros(int(frames.max()) + lag + 1, bool)
    has[frames] = True
    paired = has[frames + lag]
    first = frames[paired]
    change = np.asarray(se2.wrap_angle(residual_rad[first + lag] - residual_rad[first]))
    band = bands[paired]
    per_band = np.array(
        [
            robust_sigma(change[band == b]) if np.sum(band == b) >= min_pairs else np.nan
            for b in range(SPEED_BANDS)
        ]
    ) / np.sqrt(2.0)
    pooled = robust_sigma(change) / np.sqrt(2.0) if len(change) >= min_pairs else float("nan")
    return pooled, per_band


def course_noise(
    heading_yaw_rad: np.ndarray,
    odom_yaw_rad: np.ndarray,
    speed_mps: np.ndarray,
    timestamps_s: np.ndarray,
    params: SingleTripParams,
) -> CourseNoise | None:
    """The per-fix course sigmas of one trip (module docstring); ``heading_yaw_rad (N,)`` NaN
    where there is no course. None when the trip has too few consecutive courses to measure them
    (the graph then falls back to one course per node at ``GNSS_HEADING_SIGMA_RAD``)."""
    frames = np.flatnonzero(np.isfinite(heading_yaw_rad))
    min_pairs = params.NOISE_MIN_SAMPLES
    if len(frames) < 2 * min_pairs:
        return None
    dt = float(np.median(np.diff(timestamps_s[frames])))
    lag = max(1, int(round(params.COURSE_DECORRELATION_S / max(dt, 1e-3))))
    residual = np.full(len(heading_yaw_rad), np.nan)
    residual[frames] = se2.wrap_angle(heading_yaw_rad[frames] - odom_yaw_rad[frames])
    edges = np.quantile(speed_mps[frames], np.linspace(0.0, 1.0, SPEED_BANDS + 1)[1:-1])
    bands = np.searchsorted(edges, speed_mps[frames])
    next_fix, next_fix_bands = _change_sigmas(residual, frames, 1, bands, min_pairs)
    decorrelated, decorrelated_bands = _change_sigmas(residual, frames, lag, bands, min_pairs)
    if not (np.isfinite(next_fix) and np.isfinite(decorrelated)) or decorrelated <= 0.0:
        return None
    rho = float(np.clip(1.0 - (next_fix / decorrelated) ** 2, 0.0, MAX_NEIGHBOUR_CORRELATION))
    inflation = np.sqrt((1.0 + rho) / (1.0 - rho))
    per_band = np.fmax(next_fix_bands, decorrelated_bands)
    per_band = np.where(np.isfinite(per_band), per_band, max(next_fix, decorrelated))
    sigma = np.maximum(per_band[bands], params.GNSS_COURSE_SIGMA_FLOOR_RAD) * inflation
    return CourseNoise(frames, sigma, rho)
