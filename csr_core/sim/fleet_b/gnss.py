"""GNSS receiver model of fleet b: 10 Hz fixes with a status chain, per-status errors,
multipath bursts, outages, a receiver-style ``std_m`` and a Doppler course over ground.

It follows the usual error budget of a dual-frequency automotive receiver (Groves, *Principles
of GNSS, Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed., ch. 9 and 10;
Kaplan and Hegarty, *Understanding GPS/GNSS*, 3rd ed., ch. 11):

- Status: a discrete-time Markov chain at ``rate_hz`` over rtk_fixed / rtk_float / dgps / single,
  one step probability ``rate * dt`` per off-diagonal transition rate; vehicles without an RTK
  correction link (share ``1 - correction_share``) use the chain restricted to dgps / single.
- Error per axis: the current status's bias plus white noise. Each status has its own
  Ornstein-Uhlenbeck bias (a random walk with reversion: ``b_k = phi b_(k-1) + sqrt(1 - phi^2)
  sigma e_k``, ``phi = exp(-dt / tau)``), running the whole trip; a status change switches to the
  other solution's bias, so the fix jumps as a receiver's does when its solution changes.
- Multipath bursts: Poisson starts (more inside the world's canyon zones), a half-sine offset of
  exponential amplitude (capped) in a random direction; the receiver does not see them in
  ``std_m``, but a burst larger than ``multipath_unfix_m`` costs an RTK fix (rtk_fixed is
  reported as rtk_float while it lasts).
- Outages: Poisson starts, status ``none``.
- ``std_m``: the status's true 2-D RMS error times ``std_report_factor`` (below 1: optimistic, as
  float and single solutions typically are) times a per-fix log-normal jitter.
- Course over ground: from the receiver velocity (Doppler), the true velocity plus white noise
  ``velocity_sigma_mps`` per axis, so the course noise is ``velocity_sigma_mps / speed`` radians;
  absent below ``course_min_speed_mps`` and during outages.
- Latency: the fix and velocity are those of ``latency_s`` (per vehicle) before the stamp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from csr_core.sim.fleet_b.params import GnssParamsB
from csr_core.types import GnssStatus

_DEGRADED = (GnssStatus.DGPS, GnssStatus.SINGLE)


@dataclass(frozen=True, slots=True)
class ReceiverB:
    """One vehicle's receiver: whether it has an RTK correction link, and its latency."""

    has_corrections: bool
    latency_s: float

    @property
    def kind(self) -> str:
        return "rtk" if self.has_corrections else "sbas"


@dataclass(frozen=True, slots=True)
class GnssTrackB:
    """Per-frame receiver output (N frames), world frame."""

    status: np.ndarray  # (N,) GnssStatus codes, NONE during outages
    position_xy_world: np.ndarray  # (N, 2) the fix (meaningless where status is NONE)
    error_xy_m: np.ndarray  # (N, 2) fix minus true reference position
    std_m: np.ndarray  # (N,) reported std, NaN where status is NONE
    course_deg: np.ndarray  # (N,) grid course clockwise from north, NaN where absent
    multipath_m: np.ndarray  # (N,) size of the multipath offset in the fix (0 outside bursts)


def draw_receiver_b(params: GnssParamsB, rng: np.random.Generator) -> ReceiverB:
    has = bool(rng.random() < params.correction_share)
    return ReceiverB(has_corrections=has, latency_s=float(rng.uniform(*params.latency_s)))


def status_chain(
    n: int, params: GnssParamsB, allowed: tuple[int, ...], rng: np.random.Generator
) -> np.ndarray:
    """(n,) statuses of the discrete-time Markov chain restricted to ``allowed`` codes."""
    dt_s = 1.0 / params.rate_hz
    rates = np.array(params.transition_rate_per_s, dtype=float)[np.ix_(allowed, allowed)]
    np.fill_diagonal(rates, 0.0)
    leave_per_step = np.minimum(rates.sum(axis=1) * dt_s, 1.0)
    init = np.array(params.initial_probs, dtype=float)[list(allowed)]
    state = int(rng.choice(len(allowed), p=init / init.sum()))
    out = np.empty(n, dtype=np.int64)
    k = 0
    while k < n:
        p = leave_per_step[state]
        dwell = n - k if p <= 0.0 else int(rng.geometric(p))  # steps until the chain leaves
        out[k : k + dwell] = state
        k += dwell
        if p > 0.0:
            state = int(rng.choice(len(allowed), p=rates[state] / rates[state].sum()))
    return np.array(allowed, dtype=np.int64)[out]


def ou_unit(n: int, dt_s: float, tau_s: float, rng: np.random.Generator, size: int = 2) -> np.ndarray:
    """(n, size) stationary unit-variance Ornstein-Uhlenbeck samples at spacing ``dt_s``."""
    phi = float(np.exp(-dt_s / tau_s))
    e = rng.standard_normal((n, size))
    z0 = rng.standard_normal(size)
    return lfilter([np.sqrt(1.0 - phi * phi)], [1.0, -phi], e, axis=0, zi=(phi * z0)[None, :])[0]


def _in_zones(xy: np.ndarray, zones_xyr: np.ndarray) -> np.ndarray:
    if len(zones_xyr) == 0:
        return np.zeros(len(xy), dtype=bool)
    d = np.linalg.norm(xy[:, None, :] - zones_xyr[None, :, :2], axis=2)
    return (d < zones_xyr[None, :, 2]).any(axis=1)


def _events(rate_per_step: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices where Poisson events start, with a per-step probability."""
    return np.flatnonzero(rng.random(len(rate_per_step)) < rate_per_step)


def simulate_gnss_b(
    t_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    params: GnssParamsB,
    canyon_zones_xyr: np.ndarray,
    rng: np.random.Generator,
    receiver: ReceiverB,
) -> GnssTrackB:
    """Fixes for frames at ``t_s`` (N,) of the true trajectory ``poses_xyyaw_world`` (N, 3)."""
    n = len(t_s)
    dt_s = 1.0 / params.rate_hz
    true_xy = poses_xyyaw_world[:, :2]
    t_lag = np.maximum(t_s - receiver.latency_s, t_s[0])
    xy_lag = np.column_stack([np.interp(t_lag, t_s, true_xy[:, k]) for k in range(2)])
    vel = np.gradient(true_xy, t_s, axis=0) if n > 1 else np.zeros((n, 2))
    vel_lag = np.column_stack([np.interp(t_lag, t_s, vel[:, k]) for k in range(2)])

    allowed = tuple(range(4)) if receiver.has_corrections else tuple(int(s) for s in _DEGRADED)
    status = status_chain(n, params, allowed, rng)

    # multipath bursts: half-sine offsets, unseen by std_m; a large one costs an RTK fix
    in_zone = _in_zones(true_xy, canyon_zones_xyr)
    rate = params.multipath_rate_per_s * dt_s * np.where(in_zone, params.multipath_canyon_factor, 1.0)
    multipath = np.zeros((n, 2))
    for k0 in _events(rate, rng):
        amp = min(rng.exponential(params.multipath_mean_m), params.multipath_max_m)
        ang = rng.uniform(0.0, 2.0 * np.pi)
        dur = rng.uniform(*params.multipath_duration_s)
        k1 = min(n, k0 + max(1, int(round(dur / dt_s))))
        phase = (t_s[k0:k1] - t_s[k0]) / dur
        multipath[k0:k1] += amp * np.sin(np.pi * phase)[:, None] * np.array([np.cos(ang), np.sin(ang)])
        if amp > params.multipath_unfix_m:
            seg = status[k0:k1]
            seg[seg == GnssStatus.RTK_FIXED] = GnssStatus.RTK_FLOAT

    bias = np.zeros((n, 2))
    white = rng.standard_normal((n, 2))
    sigma_white = np.zeros(n)
    honest_2d = np.zeros(n)
    factor = np.zeros(n)
    for code, model in enumerate(params.status_errors):
        z = ou_unit(n, dt_s, model.bias_reversion_s, rng)
        here = status == code
        bias[here] = model.bias_sigma_m * z[here]
        sigma_white[here] = model.white_sigma_m
        honest_2d[here] = np.sqrt(2.0 * (model.bias_sigma_m**2 + model.white_sigma_m**2))
        factor[here] = model.std_report_factor
    error = bias + sigma_white[:, None] * white + multipath

    # outages
    for k0 in _events(np.full(n, params.outage_rate_per_s * dt_s), rng):
        dur = rng.uniform(*params.outage_duration_s)
        status[k0 : min(n, k0 + max(1, int(round(dur / dt_s))))] = GnssStatus.NONE

    std = factor * honest_2d * np.exp(params.std_report_jitter_log_sigma * rng.standard_normal(n))
    v_meas = vel_lag + params.velocity_sigma_mps * rng.standard_normal((n, 2))
    speed_meas = np.linalg.norm(v_meas, axis=1)
    course = np.mod(np.degrees(np.arctan2(v_meas[:, 0], v_meas[:, 1])), 360.0)
    none = status == GnssStatus.NONE
    course[(speed_meas < params.course_min_speed_mps) | none] = np.nan
    std[none] = np.nan
    position = xy_lag + error
    return GnssTrackB(status, position, position - true_xy, std, course, np.linalg.norm(multipath, axis=1))
