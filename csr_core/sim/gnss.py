"""GNSS receiver model (parameters: ``profiles.GnssParams``).

- Receivers: per vehicle, RTK-capable (share ``rtk_receiver_share``: all statuses, fixes
  time-tagged at the epoch) or consumer (statuses dgps / single, fixes stamped on arrival).
- Fix status: a semi-Markov chain over the receiver's statuses (exponential dwell times, next
  status from the transition matrix restricted to them).
- Position error per axis (east, north): ``sigma_b(status) * z_t + white``, ``z`` a unit
  first-order Gauss-Markov process with time constant ``tau(status)``.
- Latency (consumer receivers): the fix reports the true position ``latency`` seconds earlier
  (per vehicle, plus a small per-fix time-tag jitter), which shows as an along-track lag, as in
  the real u-blox log (comma2k19: 82 ms, 1.4 m behind at 17 m/s).
- ``std_m``: the status' honest per-axis std ``sqrt(sigma_b^2 + sigma_w^2)`` times a slowly
  varying log-normal factor; it does not include the latency lag nor canyon jumps (real receivers do not know them).
- Course heading: direction of true motion plus noise that grows at low speed; absent when slow.
- Urban canyons (``hard``): inside ``World.canyon_zones_xyr`` the status is at best `single`,
  multipath jumps of several metres last seconds, and outages report status `none`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csr_core.sim.profiles import GnssParams
from csr_core.types import GnssStatus

MIN_STD_M = 0.005


@dataclass(frozen=True)
class GnssTrack:
    """Simulated receiver output per frame (world frame metres)."""

    position_xy_world: np.ndarray  # (N, 2); meaningless where status is NONE
    status: np.ndarray  # (N,) uint8 GnssStatus codes
    std_m: np.ndarray  # (N,)
    heading_deg: np.ndarray  # (N,) NaN where absent
    error_xy_m: np.ndarray  # (N, 2) reported minus true (diagnostics)


CONSUMER_STATUSES = (GnssStatus.DGPS, GnssStatus.SINGLE)


@dataclass(frozen=True)
class Receiver:
    """One vehicle's GNSS receiver: which statuses it reaches and how its fixes are time-tagged."""

    kind: str  # "rtk" or "consumer"
    latency_s: float
    jitter_s: float
    statuses: tuple[int, ...]  # reachable status codes


def draw_receiver(params: GnssParams, rng: np.random.Generator) -> Receiver:
    """An RTK receiver (share ``rtk_receiver_share``) or a consumer one with a latency."""
    if rng.random() < params.rtk_receiver_share:
        return Receiver("rtk", 0.0, 0.0, (0, 1, 2, 3))
    latency = params.latency_mean_s
    if params.latency_sigma_s > 0:
        latency = max(float(rng.normal(params.latency_mean_s, params.latency_sigma_s)), 0.0)
    return Receiver("consumer", latency, params.latency_jitter_s, tuple(int(s) for s in CONSUMER_STATUSES))


def status_sequence(
    params: GnssParams,
    n_frames: int,
    dt_s: float,
    rng: np.random.Generator,
    statuses: tuple[int, ...] = (0, 1, 2, 3),
) -> np.ndarray:
    """Per-frame status codes (0..3) from the semi-Markov chain restricted to ``statuses``."""
    out = np.empty(n_frames, np.uint8)
    allowed = np.isin(np.arange(4), statuses).astype(float)
    trans = np.asarray(params.transition_probs, float) * allowed
    init = np.asarray(params.initial_probs, float) * allowed
    init = init / init.sum() if init.sum() > 0 else allowed / allowed.sum()
    state = int(rng.choice(4, p=init))
    i = 0
    while i < n_frames:
        dwell = rng.exponential(params.status_models[state].mean_dwell_s)
        n = max(int(round(dwell / dt_s)), 1)
        out[i : i + n] = state
        i += n
        row = trans[state]
        state = int(rng.choice(4, p=row / row.sum())) if row.sum() > 0 else state
    return out


def gauss_markov_unit(n: int, dt_s: float, tau_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``(n, 2)`` unit-variance first-order Gauss-Markov process with per-step ``tau_s (n,)``."""
    phi = np.exp(-dt_s / np.asarray(tau_s, float))
    q = np.sqrt(1.0 - phi**2)
    eps = rng.standard_normal((n, 2))
    z = np.empty((n, 2))
    z[0] = eps[0]
    for k in range(1, n):
        z[k] = phi[k] * z[k - 1] + q[k] * eps[k]
    return z


def _in_zones(points_xy: np.ndarray, zones_xyr: np.ndarray) -> np.ndarray:
    if len(zones_xyr) == 0:
        return np.zeros(len(points_xy), bool)
    d = np.linalg.norm(points_xy[:, None, :] - zones_xyr[None, :, :2], axis=2)
    return (d < zones_xyr[None, :, 2]).any(axis=1)


def _events(
    mask: np.ndarray,
    rate_per_s: float,
    duration_s: tuple[float, float],
    dt_s: float,
    rng: np.random.Generator,
) -> list[tuple[int, int]]:
    """Start/stop frame pairs of events that start (Poisson) at frames where ``mask`` holds."""
    if rate_per_s <= 0:
        return []
    starts = np.flatnonzero(mask & (rng.random(len(mask)) < rate_per_s * dt_s))
    out, busy_until = [], -1
    for i in starts.tolist():
        if i < busy_until:
            continue
        n = int(round(rng.uniform(*duration_s) / dt_s))
        out.append((i, min(i + n, len(mask))))
        busy_until = i + n
    return out


def simulate_gnss(
    timestamps_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    speed_mps: np.ndarray,
    params: GnssParams,
    canyon_zones_xyr: np.ndarray,
    rng: np.random.Generator,
    receiver: Receiver | None = None,
) -> GnssTrack:
    """Receiver output for a true trajectory ``poses_xyyaw_world (N, 3)`` at ``timestamps_s (N,)``.

    ``receiver``: the vehicle's receiver (None: draw one from the parameters)."""
    n = len(timestamps_s)
    dt = float(np.median(np.diff(timestamps_s))) if n > 1 else 0.1
    if receiver is None:
        receiver = draw_receiver(params, rng)
    status = status_sequence(params, n, dt, rng, receiver.statuses)
    models = params.status_models
    sigma_b = np.array([models[k].bias_sigma_m for k in range(4)])[status]
    sigma_w = np.array([models[k].white_sigma_m for k in range(4)])[status]
    tau = np.array([models[k].bias_tau_s for k in range(4)])[status]
    true_xy = poses_xyyaw_world[:, :2]
    t_fix = timestamps_s - receiver.latency_s
    if receiver.jitter_s > 0:
        t_fix = t_fix + receiver.jitter_s * rng.standard_normal(n)
    lagged_xy = np.column_stack([np.interp(t_fix, timestamps_s, true_xy[:, k]) for k in range(2)])
    z = gauss_markov_unit(n, dt, tau, rng)
    white = rng.standard_normal((n, 2))
    in_zone = _in_zones(true_xy, canyon_zones_xyr)
    if params.canyon_degrade_to_single:
        status = np.where(in_zone, np.maximum(status, GnssStatus.SINGLE), status).astype(np.uint8)
        sigma_b = np.where(in_zone, models[3].bias_sigma_m, sigma_b)
        sigma_w = np.where(in_zone, models[3].white_sigma_m, sigma_w)
    error = sigma_b[:, None] * z + sigma_w[:, None] * white
    for i0, i1 in _events(in_zone, params.canyon_jump_rate_per_s, params.canyon_jump_duration_s, dt, rng):
        a, m = rng.uniform(0, 2 * np.pi), rng.uniform(*params.canyon_jump_m)
        ramp = np.minimum(1.0, np.arange(i1 - i0) / 3.0)[:, None]  # multipath builds up within ~0.3 s
        error[i0:i1] += ramp * m * np.array([np.cos(a), np.sin(a)])
    for i0, i1 in _events(in_zone, params.canyon_outage_rate_per_s, params.canyon_outage_duration_s, dt, rng):
        status[i0:i1] = GnssStatus.NONE
    position = lagged_xy + error
    honest = np.sqrt(sigma_b**2 + sigma_w**2)
    # the receiver's own estimate wanders slowly around the honest value (not white per fix)
    log_factor = (
        params.std_report_log_sigma * gauss_markov_unit(n, dt, np.full(n, params.std_report_tau_s), rng)[:, 0]
    )
    std = np.maximum(honest * np.exp(log_factor), MIN_STD_M)
    # course over ground from the true motion (at the lagged time) with speed-dependent noise
    v_xy = np.gradient(lagged_xy, timestamps_s, axis=0) if n > 1 else np.zeros((n, 2))
    course_deg = np.mod(np.degrees(np.arctan2(v_xy[:, 0], v_xy[:, 1])), 360.0)
    noise_deg = params.heading_sigma_deg_at_10mps * 10.0 / np.maximum(speed_mps, 1.0) * rng.standard_normal(n)
    heading = np.mod(course_deg + noise_deg, 360.0)
    heading = np.where(
        (speed_mps >= params.heading_min_speed_mps) & (status != GnssStatus.NONE), heading, np.nan
    )
    heading = np.where(heading >= 359.9995, 0.0, heading)  # stays < 360 after rounding
    std = np.where(status == GnssStatus.NONE, np.nan, std)
    return GnssTrack(position, status.astype(np.uint8), std, heading, position - true_xy)
