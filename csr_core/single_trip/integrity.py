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
from typing import Any

import numpy as np

from csr_core.geo import LocalFrame
from csr_core.single_trip.params import SingleTripParams
from csr_core.single_trip.pose_graph import SmoothedPoses, gnss_sigmas_m, interpolate_poses, smooth_poses

log = logging.getLogger(__name__)

RAYLEIGH_MEDIAN = 1.1774  # median of |e| for a 2-D error of unit sigma per axis


class TripVerdict(StrEnum):
    """What the integrity test concluded of a trip's poses."""

    OK = "ok"  # passed at the first solve
    REPAIRED = "repaired"  # failed, passed after the repair solve
    DEGRADED = "degraded"  # failed after the repair: GNSS-anchored poses, held back from the map


@dataclass(frozen=True, slots=True)
class GnssConsistency:
    """The test of a trip's poses against its fixes, three parts:

    - windows: ``window_start_s`` / ``window_end_s`` (W,) the windows with enough kept fixes,
      ``window_z`` (W,) their normalised offset ``|median(fix - pose)| / sigma`` over the fixes
      the smoother kept; ``z_limit`` the chi-square(2) quantile of ``false_alarm / W``,
      square-rooted;
    - the whole trip: ``median_offset_m``, the median distance from the poses to all fixes,
      within ``median_factor`` times the Rayleigh median of the error model
      (``expected_median_m = 1.1774 median(sigma)``): a correct trajectory is closer to the truth
      than the fixes are, so its distance to them is about theirs to the truth; the median is
      blind to the minority of multipath jumps;
    - the smoother's own rejections: ``rejected_share`` of the fixes at most ``rejected_limit``
      (a large rejected share is a model failure: the fixes left out are what it drifted from).
    ``rmse_to_gnss_m`` is the RMS distance to all fixes, for the record."""

    window_start_s: np.ndarray
    window_end_s: np.ndarray
    window_z: np.ndarray
    z_limit: float
    median_offset_m: float
    expected_median_m: float
    median_factor: float
    rejected_share: float
    rejected_limit: float
    rmse_to_gnss_m: float

    @property
    def passed(self) -> bool:
        return self.windows_passed and self.median_passed and self.rejected_passed

    @property
    def windows_passed(self) -> bool:
        return not bool(np.any(self.window_z > self.z_limit))

    @property
    def median_passed(self) -> bool:
        return self.median_offset_m <= self.median_factor * self.expected_median_m

    @property
    def rejected_passed(self) -> bool:
        return self.rejected_share <= self.rejected_limit

    @property
    def worst_z(self) -> float:
        return float(self.window_z.max()) if len(self.window_z) else 0.0

    def failing_stretches_s(self) -> list[tuple[float, float]]:
        """Consecutive failing windows merged: (start, end) times in seconds."""
        out: list[tuple[float, float]] = []
        for a, b, z in zip(
            self.window_start_s.tolist(), self.window_end_s.tolist(), self.window_z.tolist(), strict=True
        ):
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
    the trip's first frame) of the first solve, and the test's figures on the poses kept."""

    verdict: TripVerdict
    reason: str
    stretches_s: tuple[tuple[float, float], ...]
    worst_z: float
    z_limit: float
    median_offset_m: float
    expected_median_m: float
    rejected_share: float
    rmse_to_gnss_m: float

    def as_dict(self) -> dict:
        return {
            "verdict": self.verdict.value,
            "reason": self.reason,
            "stretches_s": [[round(a, 1), round(b, 1)] for a, b in self.stretches_s],
            "worst_z": round(self.worst_z, 2),
            "z_limit": round(self.z_limit, 2),
            "median_offset_m": round(self.median_offset_m, 3),
            "gnss_median_expected_m": round(self.expected_median_m, 3),
            "rejected_share": round(self.rejected_share, 3),
            "rmse_to_gnss_m": round(self.rmse_to_gnss_m, 3),
        }

    @property
    def degraded(self) -> bool:
        return self.verdict == TripVerdict.DEGRADED


def gnss_consistency(
    timestamps_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    gnss_xy_world: np.ndarray,
    gnss_sigma_m: np.ndarray,
    has_fix: np.ndarray,
    params: SingleTripParams,
    gnss_latency_s: float = 0.0,
    inlier: np.ndarray | None = None,
    min_fixes: int = 5,
) -> GnssConsistency:
    """The test of :class:`GnssConsistency`. Arrays (N, ...) per frame; ``gnss_sigma_m`` the
    per-axis 1-sigma of each fix (inf: none); a fix stamped t is compared with the pose at
    ``t - gnss_latency_s``; ``inlier`` the fixes the smoother kept (None: all, and no rejection
    test). Windows of ``INTEGRITY_WINDOW_S`` with fewer than ``min_fixes`` kept fixes are not
    tested."""
    timestamps_s = np.asarray(timestamps_s, float)
    usable = has_fix & np.isfinite(gnss_sigma_m)
    fix = np.flatnonzero(usable)
    empty = np.zeros(0)
    if len(fix) == 0:
        return GnssConsistency(empty, empty, empty, math.inf, 0.0, 0.0, math.inf, 0.0, 1.0, 0.0)
    at = timestamps_s[fix] - gnss_latency_s
    pose_xy = (
        interpolate_poses(timestamps_s, poses_xyyaw_world, at)[:, :2]
        if gnss_latency_s
        else poses_xyyaw_world[fix, :2]
    )
    offset = gnss_xy_world[fix] - pose_xy
    dist = np.linalg.norm(offset, axis=1)
    kept = np.ones(len(fix), bool) if inlier is None else np.asarray(inlier, bool)[fix]
    rejected = 0.0 if inlier is None else float(1.0 - kept.mean())
    # the windows read every fix but those of a GNSS jump the smoother rightly rejected
    tested = kept | ~_jumps(offset, kept)
    wid = np.floor((timestamps_s[fix] - timestamps_s[0]) / params.INTEGRITY_WINDOW_S).astype(np.int64)
    starts, ends, zs = [], [], []
    for w in np.unique(wid[tested]).tolist():
        sel = (wid == w) & tested
        if sel.sum() < min_fixes:
            continue
        med = np.median(offset[sel], axis=0)
        sigma = float(np.median(gnss_sigma_m[fix[sel]]))
        zs.append(float(np.hypot(*med)) / max(sigma, 1e-3))
        starts.append(float(timestamps_s[fix[sel]][0] - timestamps_s[0]))
        ends.append(float(timestamps_s[fix[sel]][-1] - timestamps_s[0]))
    n_w = max(len(zs), 1)
    # chi-square(2) survival is exp(-x/2): the per-window quantile of the shared false-alarm rate
    z_limit = math.sqrt(2.0 * math.log(n_w / params.INTEGRITY_FALSE_ALARM))
    return GnssConsistency(
        np.asarray(starts),
        np.asarray(ends),
        np.asarray(zs),
        z_limit,
        median_offset_m=float(np.median(dist)),
        expected_median_m=RAYLEIGH_MEDIAN * float(np.median(gnss_sigma_m[fix])),
        median_factor=params.INTEGRITY_MEDIAN_FACTOR,
        rejected_share=rejected,
        rejected_limit=params.INTEGRITY_MAX_REJECTED_SHARE,
        rmse_to_gnss_m=float(np.sqrt(np.mean(dist**2))),
    )


def _jumps(offset_xy: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """(M,) bool: the rejected fixes that belong to a GNSS jump. ``offset_xy`` (M, 2) fix minus
    pose of consecutive fixes, ``kept`` the smoother's inliers. A run of rejected fixes is a jump
    when its offset steps at its start or its end by more than the fixes' own epoch-to-epoch
    scatter allows (6 robust sigmas of the offset's increments, at least 1 m): multipath moves
    the fix in one epoch while the vehicle does not; a trajectory that drifts away from good
    fixes moves the offset smoothly, and its rejected fixes stay in the test."""
    m = len(kept)
    out = np.zeros(m, bool)
    if m < 3 or kept.all():
        return out
    step = np.linalg.norm(np.diff(offset_xy, axis=0), axis=1)  # (M-1,) offset change per epoch
    limit = max(6.0 * 1.4826 * float(np.median(step)), 1.0)
    edges = np.flatnonzero(np.diff(np.r_[0, (~kept).astype(np.int8), 0]))
    for a, b in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):  # rejected run [a, b)
        steps_in = step[a - 1] if a > 0 else 0.0
        steps_out = step[b - 1] if b < m else 0.0
        if max(steps_in, steps_out) > limit:
            out[a:b] = True
    return out


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
        parts.append(
            f"poses {check.worst_z:.1f} sigma off the trip's GNSS (limit {check.z_limit:.1f}) at "
            + _describe(check.failing_stretches_s())
        )
    if not check.median_passed:
        parts.append(
            f"poses a median {check.median_offset_m:.2f} m from the trip's GNSS, more than "
            f"{check.median_factor:g} x the {check.expected_median_m:.2f} m its error model gives"
        )
    if not check.rejected_passed:
        parts.append(
            f"{100 * check.rejected_share:.0f} % of the fixes rejected by the smoother (limit "
            f"{100 * check.rejected_limit:.0f} %)"
        )
    return "; ".join(parts)


def test_sigmas_m(status: np.ndarray, std_m: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """Per-fix sigma of the integrity test (N,): the reported ``std_m`` (the status table without
    it), never below the status table's typical figure: a receiver that reports ten times too
    small a sigma must not make every trip fail the test (the smoother's own robust scale
    absorbs such a receiver; the test has no such scale)."""
    sigma = gnss_sigmas_m(status, std_m, params)
    table = np.asarray(params.GNSS_SIGMA_BY_STATUS_M, float)
    return np.maximum(sigma, table[np.clip(np.asarray(status, int), 0, len(table) - 1)])


def _badness(check: GnssConsistency) -> float:
    """How far ``check`` is past its worst limit (below 1: passed)."""
    return max(
        check.worst_z / check.z_limit,
        check.median_offset_m / max(check.median_factor * check.expected_median_m, 1e-9),
        check.rejected_share / max(check.rejected_limit, 1e-9),
    )


def smooth_poses_checked(
    timestamps_s: np.ndarray,
    gnss_xy_world: np.ndarray,
    gnss_status: np.ndarray,
    gnss_std_m: np.ndarray,
    gnss_heading_deg: np.ndarray,
    odom_xyyaw: np.ndarray,
    params: SingleTripParams,
) -> tuple[SmoothedPoses, TripQuality]:
    """Eq. 2 (:func:`smooth_poses`) with the integrity test, the repair and the GNSS-anchored
    fallback of the module docstring. Returns the poses kept and their verdict; of three
    solves that all fail, the one least past its limits is kept."""
    args = (timestamps_s, gnss_xy_world, gnss_status, gnss_std_m, gnss_heading_deg, odom_xyyaw)
    sigma = test_sigmas_m(gnss_status, gnss_std_m, params)
    has_fix = np.isfinite(sigma) & np.all(np.isfinite(gnss_xy_world), axis=1)

    def check(smoothed: SmoothedPoses) -> GnssConsistency:
        return gnss_consistency(
            timestamps_s,
            smoothed.poses_xyyaw_world,
            gnss_xy_world,
            sigma,
            has_fix,
            params,
            smoothed.gnss_latency_s,
            inlier=smoothed.gnss_inlier,
        )

    def quality(
        verdict: TripVerdict, reason: str, first: GnssConsistency, kept: GnssConsistency
    ) -> TripQuality:
        return TripQuality(
            verdict,
            reason,
            tuple(first.failing_stretches_s()),
            kept.worst_z,
            kept.z_limit,
            kept.median_offset_m,
            kept.expected_median_m,
            kept.rejected_share,
            kept.rmse_to_gnss_m,
        )

    smoothed = smooth_poses(*args, params)
    first = check(smoothed)
    if first.passed or not params.INTEGRITY_CHECK:
        return smoothed, quality(TripVerdict.OK, "", first, first)
    why = _why(first)
    log.info("trip poses off their GNSS (%s): repairing", why)
    # repair: no odometry yaw calibration, the heading and the distance loosely held (the GNSS
    # course and positions set them), hardly any fix rejected
    repair_params = replace(
        params,
        CAL_ENABLED=False,
        GNSS_MIN_INLIER_SHARE=0.9,
        ODOM_SIGMA_YAW_PER_S=params.ODOM_SIGMA_YAW_PER_S * params.INTEGRITY_REPAIR_YAW_FACTOR,
        ODOM_SIGMA_XY_PER_M=params.ODOM_SIGMA_XY_PER_M * params.INTEGRITY_REPAIR_XY_FACTOR,
    )
    repaired = smooth_poses(*args, repair_params)
    second = check(repaired)
    if second.passed:
        return repaired, quality(
            TripVerdict.REPAIRED,
            why + "; repaired by a re-solve without the odometry yaw calibration",
            first,
            second,
        )
    # fallback: GNSS-anchored (odometry only smooths between fixes), marked degraded
    anchored_params = replace(
        repair_params,
        GNSS_BIAS_STATE=False,
        GNSS_CORRELATION_S=0.0,
        ODOM_SIGMA_YAW_PER_S=params.ODOM_SIGMA_YAW_PER_S * params.INTEGRITY_ANCHOR_YAW_FACTOR,
        ODOM_SIGMA_XY_PER_M=params.ODOM_SIGMA_XY_PER_M * params.INTEGRITY_ANCHOR_YAW_FACTOR,
    )
    anchored = smooth_poses(*args, anchored_params)
    third = check(anchored)
    candidates = [
        (smoothed, first, "the first solve's poses"),
        (repaired, second, "the repair's poses"),
        (anchored, third, "GNSS-anchored poses"),
    ]
    poses, kept, which = min(candidates, key=lambda c: _badness(c[1]))
    log.warning("trip degraded: %s; the repair failed too: %s kept", why, which)
    return poses, quality(TripVerdict.DEGRADED, f"{why}; the repair failed too: {which} kept", first, kept)


def check_aligned_poses(
    trip: Any,
    single_poses_xyyaw: np.ndarray,
    aligned_poses_xyyaw: np.ndarray,
    frame: LocalFrame,
    params: SingleTripParams,
    gnss_latency_s: float = 0.0,
    gnss_inlier: np.ndarray | None = None,
) -> tuple[np.ndarray, str | None]:
    """The same test on a trip's aligned poses (both arrays (N, 3) in ``frame``; ``gnss_inlier``
    the fixes the smoother kept): when they fail it and its single-trip poses do better, the
    alignment moved the trip by more than its GNSS error model allows; the single-trip poses are
    returned with the reason. Otherwise the aligned poses and None. The smoother's rejections
    are not judged again here."""
    if not params.INTEGRITY_CHECK:
        return aligned_poses_xyyaw, None
    sigma = test_sigmas_m(trip.fix_status, trip.gnss_std_m, params)
    has_fix = np.isfinite(sigma) & np.asarray(trip.has_fix, bool)
    gnss_xy = frame.to_local(trip.gnss_lonlat_deg)
    # aligned poses sit near the truth, so their offsets are the fixes' whole error, bias
    # included (the single-trip poses follow the bias): the whole-trip median is bounded like
    # one window, at the error model's tail, and the smoother's rejections are not judged again
    lenient = replace(
        params,
        INTEGRITY_MAX_REJECTED_SHARE=1.0,
        INTEGRITY_MEDIAN_FACTOR=params.INTEGRITY_ALIGNED_MEDIAN_FACTOR,
    )

    def check(poses: np.ndarray) -> GnssConsistency:
        return gnss_consistency(
            trip.timestamps_s, poses, gnss_xy, sigma, has_fix, lenient, gnss_latency_s, inlier=gnss_inlier
        )

    aligned = check(aligned_poses_xyyaw)
    if aligned.passed:
        return aligned_poses_xyyaw, None
    if _badness(check(single_poses_xyyaw)) >= _badness(aligned):
        return aligned_poses_xyyaw, None
    return single_poses_xyyaw, f"aligned {_why(aligned)}; single-trip poses kept"
