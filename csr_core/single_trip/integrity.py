"""Never worse than the input, unflagged: a trip's poses tested against its own GNSS.

A correct trajectory sits within the GNSS error model of the trip's own fixes: over a window
shorter than the GNSS bias's correlation time, the median offset from the fixes to the poses
is that window's GNSS error, whose per-axis standard deviation the receiver reports
(``std_m``; the status table without it). So the window's normalised squared offset
``|median(fix - pose)|^2 / sigma^2`` follows a chi-square with 2 degrees of freedom, and a
runaway heading, a wrong odometry calibration or a registration that moved the trip by more
than its GNSS allows puts it far in the tail. The test (:func:`gnss_consistency`) flags a
window above the chi-square quantile of a false-alarm rate shared by all of the trip's
windows (Bonferroni). The median makes a window robust to the GNSS jumps the smoother rightly
rejected (multipath, a minority of its fixes).

:func:`smooth_poses_checked` is Eq. 2 with that test after it: a trip that fails is repaired
(solved again without the odometry's yaw-rate calibration, with the odometry heading held
loosely so that the GNSS course and positions set it, and no fix rejected beyond a tenth of
them), tested again, and if it still fails, placed by a GNSS-anchored solve (the odometry
only smoothing between fixes) and marked ``degraded`` with the failing stretches.

Tried and rejected: an RMSE-to-GNSS ratio per trip (one bad minute hides in a long trip); the
inlier fixes only (a runaway rejects the good fixes it drifted from).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from csr_core.single_trip.params import SingleTripParams
from csr_core.single_trip.pose_graph import SmoothedPoses, gnss_sigmas_m, interpolate_poses, smooth_poses

log = logging.getLogger(__name__)


class TripVerdict(StrEnum):
    """What the integrity test concluded of a trip's poses."""

    OK = "ok"  # passed at the first solve
    REPAIRED = "repaired"  # failed, passed after the repair solve
    DEGRADED = "degraded"  # failed after the repair: GNSS-anchored poses, held back from the map


@dataclass(frozen=True, slots=True)
class GnssConsistency:
    """The windowed test of a trip's poses against its fixes.

    ``window_start_s`` / ``window_end_s`` (W,) the windows with enough fixes, ``window_z`` (W,)
    their normalised offset ``|median(fix - pose)| / sigma``; ``z_limit`` the threshold (the
    chi-square(2) quantile of ``false_alarm / W``, square-rooted); ``rmse_to_gnss_m`` the
    poses' RMS distance to all fixes, which must stay within ``rmse_factor`` times what the GNSS
    error model gives (``expected_rmse_m``): a correct trajectory is closer to the truth than
    the fixes are, so its distance to them is about theirs to the truth."""

    window_start_s: np.ndarray
    window_end_s: np.ndarray
    window_z: np.ndarray
    z_limit: float
    rmse_to_gnss_m: float
    expected_rmse_m: float = math.inf  # the GNSS error model's RMS distance, sqrt(mean(2 sigma^2))
    rmse_factor: float = math.inf

    @property
    def passed(self) -> bool:
        return self.windows_passed and self.rmse_passed

    @property
    def windows_passed(self) -> bool:
        return not bool(np.any(self.window_z > self.z_limit))

    @property
    def rmse_passed(self) -> bool:
        return self.rmse_to_gnss_m <= self.rmse_factor * self.expected_rmse_m

    @property
    def worst_z(self) -> float:
        return float(self.window_z.max()) if len(self.window_z) else 0.0

    def failing_stretches_s(self) -> list[tuple[float, float]]:
        """Consecutive failing windows merged: (start, end) times in seconds."""
        out: list[tuple[float, float]] = []
        for a, b, z in zip(self.window_start_s.tolist(), self.window_end_s.tolist(), self.window_z.tolist(),
                           strict=True):
            if z <= self.z_limit:
                continue
            if out and a <= out[-1][1] + 1.0:  # the next window (its first fix a frame later)
                out[-1] = (out[-1][0], b)
            else:
                out.append((a, b))
        return out


@dataclass(frozen=True, slots=True)
class TripQuality:
    """The integrity verdict of one trip (``report.json``'s ``degraded``, ``GET /v1/trips/{id}``'s
    ``quality``): the verdict, the reason when not ``ok``, the failing stretches (seconds from
    the trip's first frame) of the first solve, and the figures of the poses kept."""

    verdict: TripVerdict
    reason: str
    stretches_s: tuple[tuple[float, float], ...]
    worst_z: float
    z_limit: float
    rmse_to_gnss_m: float
    gnss_rmse_expected_m: float

    def as_dict(self) -> dict:
        return {"verdict": self.verdict.value, "reason": self.reason,
                "stretches_s": [[round(a, 1), round(b, 1)] for a, b in self.stretches_s],
                "worst_z": round(self.worst_z, 2), "z_limit": round(self.z_limit, 2),
                "rmse_to_gnss_m": round(self.rmse_to_gnss_m, 3),
                "gnss_rmse_expected_m": round(self.gnss_rmse_expected_m, 3)}

    @property
    def degraded(self) -> bool:
        return self.verdict == TripVerdict.DEGRADED


def gnss_consistency(timestamps_s: np.ndarray, poses_xyyaw_world: np.ndarray, gnss_xy_world: np.ndarray,
                     gnss_sigma_m: np.ndarray, has_fix: np.ndarray, window_s: float, false_alarm: float,
                     gnss_latency_s: float = 0.0, min_fixes: int = 5,
                     rmse_factor: float = math.inf) -> GnssConsistency:
    """The windowed test of the module docstring. Arrays (N, ...) per frame; ``gnss_sigma_m``
    the per-axis 1-sigma of each fix (inf: none); a fix stamped t is compared with the pose at
    ``t - gnss_latency_s``. ``rmse_factor`` (inf: not tested) bounds the whole trip's RMS
    distance to its fixes against the error model's. Windows of ``window_s`` with fewer than ``min_fixes`` fixes are not
    tested."""
    timestamps_s = np.asarray(timestamps_s, float)
    fix = np.flatnonzero(has_fix & np.isfinite(gnss_sigma_m))
    empty = np.zeros(0)
    if len(fix) == 0:
        return GnssConsistency(empty, empty, empty, math.inf, 0.0)
    at = timestamps_s[fix] - gnss_latency_s
    pose_xy = interpolate_poses(timestamps_s, poses_xyyaw_world, at)[:, :2] if gnss_latency_s else \
        poses_xyyaw_world[fix, :2]
    offset = gnss_xy_world[fix] - pose_xy
    rmse = float(np.sqrt(np.mean(np.sum(offset**2, axis=1))))
    expected = float(np.sqrt(np.mean(2.0 * np.square(gnss_sigma_m[fix]))))
    wid = np.floor((timestamps_s[fix] - timestamps_s[0]) / window_s).astype(np.int64)
    starts, ends, zs = [], [], []
    for w in np.unique(wid).tolist():
        sel = wid == w
        if sel.sum() < min_fixes:
            continue
        med = np.median(offset[sel], axis=0)
        sigma = float(np.median(gnss_sigma_m[fix[sel]]))
        zs.append(float(np.hypot(*med)) / max(sigma, 1e-3))
        starts.append(float(timestamps_s[fix[sel]][0] - timestamps_s[0]))
        ends.append(float(timestamps_s[fix[sel]][-1] - timestamps_s[0]))
    n_w = max(len(zs), 1)
    # chi-square(2) survival is exp(-x/2): the per-window quantile of false_alarm / n_w
    z_limit = math.sqrt(2.0 * math.log(n_w / false_alarm))
    return GnssConsistency(np.asarray(starts), np.asarray(ends), np.asarray(zs), z_limit, rmse, expected,
                           rmse_factor)


def _describe(stretches_s: list[tuple[float, float]]) -> str:
    """A short text of failing stretches: the first three, and how many seconds in all."""
    head = ", ".join(f"{a:.0f}-{b:.0f} s" for a, b in stretches_s[:3])
    total = sum(b - a for a, b in stretches_s)
    more = f" and {len(stretches_s) - 3} more" if len(stretches_s) > 3 else ""
    return f"{head}{more} ({total:.0f} s in all)"


def _why(check: GnssConsistency) -> str:
    """Why ``check`` failed, in words."""
    parts = []
    if not check.windows_passed:
        parts.append(f"poses {check.worst_z:.1f} sigma off the trip's GNSS (limit {check.z_limit:.1f}) at "
                     + _describe(check.failing_stretches_s()))
    if not check.rmse_passed:
        parts.append(f"poses {check.rmse_to_gnss_m:.2f} m RMS from the trip's GNSS, more than "
                     f"{check.rmse_factor:g} x the {check.expected_rmse_m:.2f} m its error model gives")
    return "; ".join(parts)


def smooth_poses_checked(timestamps_s: np.ndarray, gnss_xy_world: np.ndarray, gnss_status: np.ndarray,
                         gnss_std_m: np.ndarray, gnss_heading_deg: np.ndarray, odom_xyyaw: np.ndarray,
                         params: SingleTripParams) -> tuple[SmoothedPoses, TripQuality]:
    """Eq. 2 (:func:`smooth_poses`) with the integrity test, the repair and the GNSS-anchored
    fallback of the module docstring. Returns the poses kept and their verdict."""
    args = (timestamps_s, gnss_xy_world, gnss_status, gnss_std_m, gnss_heading_deg, odom_xyyaw)
    sigma = gnss_sigmas_m(gnss_status, gnss_std_m, params)
    has_fix = np.isfinite(sigma) & np.all(np.isfinite(gnss_xy_world), axis=1)

    def check(smoothed: SmoothedPoses) -> GnssConsistency:
        return gnss_consistency(timestamps_s, smoothed.poses_xyyaw_world, gnss_xy_world, sigma, has_fix,
                                params.INTEGRITY_WINDOW_S, params.INTEGRITY_FALSE_ALARM,
                                smoothed.gnss_latency_s, rmse_factor=params.INTEGRITY_RMSE_FACTOR)

    def quality(verdict: TripVerdict, reason: str, first: GnssConsistency, kept: GnssConsistency) -> TripQuality:
        return TripQuality(verdict, reason, tuple(first.failing_stretches_s()), kept.worst_z, kept.z_limit,
                           kept.rmse_to_gnss_m, kept.expected_rmse_m)

    smoothed = smooth_poses(*args, params)
    first = check(smoothed)
    if first.passed or not params.INTEGRITY_CHECK:
        return smoothed, quality(TripVerdict.OK, "", first, first)
    why = _why(first)
    log.info("trip poses off their GNSS (%s): repairing", why)
    # repair: no odometry yaw calibration, the heading loosely held (the GNSS course and the
    # positions set it), hardly any fix rejected
    repair_params = replace(params, CAL_ENABLED=False, GNSS_MIN_INLIER_SHARE=0.9,
                            ODOM_SIGMA_YAW_PER_S=params.ODOM_SIGMA_YAW_PER_S * params.INTEGRITY_REPAIR_YAW_FACTOR)
    repaired = smooth_poses(*args, repair_params)
    second = check(repaired)
    if second.passed:
        return repaired, quality(TripVerdict.REPAIRED, why + "; repaired by a re-solve without the odometry "
                                 "yaw calibration", first, second)
    # fallback: GNSS-anchored (odometry only smooths between fixes), marked degraded
    anchored_params = replace(repair_params, GNSS_BIAS_STATE=False, GNSS_CORRELATION_S=0.0,
                              ODOM_SIGMA_YAW_PER_S=params.ODOM_SIGMA_YAW_PER_S * params.INTEGRITY_ANCHOR_YAW_FACTOR,
                              ODOM_SIGMA_XY_PER_M=params.ODOM_SIGMA_XY_PER_M * params.INTEGRITY_ANCHOR_YAW_FACTOR)
    anchored = smooth_poses(*args, anchored_params)
    kept = check(anchored)
    log.warning("trip degraded: %s; GNSS-anchored poses kept (worst %.1f sigma)", why, kept.worst_z)
    return anchored, quality(TripVerdict.DEGRADED, why + "; the repair failed too: GNSS-anchored poses",
                             first, kept)
