"""Raw GNSS poses of a trip in a world plane: the starting point of both baselines.

- Position: the GNSS fix projected into the world plane; frames without a fix (status
  ``none``) are bridged by odometry from the fixes on both sides of the outage, blended
  linearly in time so the bridge meets both ends (one side only at the start or end).
- Yaw: the GNSS course ``heading_deg`` where the receiver gives one; elsewhere the odometry yaw
  plus the trip's odometry-to-world yaw offset (circular mean of ``heading - odom yaw`` over the
  frames with a heading, or, with no heading at all, of ``course between fixes - odom course``).
"""

from __future__ import annotations

import numpy as np

from csr_core.errors import ReconstructionError
from csr_core.geo import LocalFrame
from csr_core.se2 import between, compose, heading_deg_to_yaw_rad, wrap_angle
from csr_core.types import Trip

MIN_COURSE_STEP_M = 2.0  # fixes closer than this give no usable course


def _circular_mean(angles_rad: np.ndarray) -> float:
    return float(np.arctan2(np.sin(angles_rad).mean(), np.cos(angles_rad).mean()))


def odom_to_world_yaw_offset(trip: Trip, fixes_xy_world: np.ndarray, grid_heading_deg: np.ndarray) -> float:
    """Yaw offset ``world yaw - odom yaw`` of a trip (radians); ``grid_heading_deg`` the GNSS course
    clockwise from the plane's grid north (``LocalFrame.grid_heading_deg``)."""
    has_heading = trip.has_fix & np.isfinite(grid_heading_deg)
    if has_heading.any():
        yaw = heading_deg_to_yaw_rad(grid_heading_deg[has_heading])
        return _circular_mean(np.asarray(wrap_angle(yaw - trip.odom_xyyaw[has_heading, 2])))
    idx = np.flatnonzero(trip.has_fix)
    if len(idx) >= 2:
        d_world = np.diff(fixes_xy_world[idx], axis=0)
        d_odom = np.diff(trip.odom_xyyaw[idx, :2], axis=0)
        ok = (np.linalg.norm(d_world, axis=1) > MIN_COURSE_STEP_M) & (
            np.linalg.norm(d_odom, axis=1) > MIN_COURSE_STEP_M
        )
        if ok.any():
            diff = np.arctan2(d_world[ok, 1], d_world[ok, 0]) - np.arctan2(d_odom[ok, 1], d_odom[ok, 0])
            return _circular_mean(np.asarray(wrap_angle(diff)))
    return 0.0


def gnss_poses_xyyaw(trip: Trip, frame: LocalFrame) -> np.ndarray:
    """``(N, 3)`` world_T_vehicle poses from raw GNSS (+ odometry across outages).

    Raises :class:`ReconstructionError` when the trip has no GNSS fix at all.
    """
    fix = trip.has_fix
    if not fix.any():
        raise ReconstructionError(f"{trip.key}: no GNSS fix in the whole trip")
    xy = frame.to_local(trip.gnss_lonlat_deg)
    grid_heading = frame.grid_heading_deg(trip.gnss_heading_deg, trip.gnss_lonlat_deg)
    offset = odom_to_world_yaw_offset(trip, xy, grid_heading)
    yaw = np.asarray(wrap_angle(trip.odom_xyyaw[:, 2] + offset))
    has_heading = fix & np.isfinite(grid_heading)
    yaw[has_heading] = heading_deg_to_yaw_rad(grid_heading[has_heading])
    poses = np.column_stack([xy, yaw])
    if fix.all():
        return poses
    # Bridge outages: frames between fix a (before) and fix b (after).
    fixed_idx = np.flatnonzero(fix)
    missing = np.flatnonzero(~fix)
    prev_fix = np.searchsorted(fixed_idx, missing) - 1  # index into fixed_idx, -1 = none before
    for i, p in zip(missing, prev_fix, strict=False):
        a = fixed_idx[p] if p >= 0 else None
        b = fixed_idx[p + 1] if p + 1 < len(fixed_idx) else None
        preds, weights = [], []
        if a is not None:
            preds.append(compose(poses[a], between(trip.odom_xyyaw[a], trip.odom_xyyaw[i])))
            weights.append(1.0 if b is None else (b - i) / (b - a))
        if b is not None:
            preds.append(compose(poses[b], between(trip.odom_xyyaw[b], trip.odom_xyyaw[i])))
            weights.append(1.0 if a is None else (i - a) / (b - a))
        w = np.asarray(weights) / np.sum(weights)
        p_xy = sum(wk * pk[:2] for wk, pk in zip(w, preds, strict=False))
        p_yaw = np.arctan2(
            sum(wk * np.sin(pk[2]) for wk, pk in zip(w, preds, strict=False)),
            sum(wk * np.cos(pk[2]) for wk, pk in zip(w, preds, strict=False)),
        )
        poses[i] = [p_xy[0], p_xy[1], p_yaw]
    return poses
