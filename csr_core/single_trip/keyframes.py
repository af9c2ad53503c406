"""Keyframes by distance and time (paper III-C: "extract keyframes based on movement distance
and period for subsequent steps to reduce calculations")."""

from __future__ import annotations

import numpy as np


def select_keyframes(
    poses_xyyaw: np.ndarray, timestamps_s: np.ndarray, distance_m: float, period_s: float
) -> np.ndarray:
    """Indices (K,) ascending: the first and last frame, and each frame at least ``distance_m`` of
    travel or ``period_s`` after the previous keyframe. Travel is summed along the path, so a
    vehicle driving back and forth still gets keyframes."""
    n = len(timestamps_s)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    step = np.r_[0.0, np.linalg.norm(np.diff(poses_xyyaw[:, :2], axis=0), axis=1)]
    travel = np.cumsum(step)
    return every_travel_or_time(travel, np.asarray(timestamps_s, float), distance_m, period_s, keep_last=True)


def every_travel_or_time(
    travel_m: np.ndarray, timestamps_s: np.ndarray, distance_m: float, period_s: float, keep_last: bool
) -> np.ndarray:
    n = len(travel_m)
    out = [0]
    last_d, last_t = travel_m[0], timestamps_s[0]
    # jump with searchsorted: next frame past the distance or the period, whichever comes first
    i = 0
    while True:
        j_d = int(np.searchsorted(travel_m, last_d + distance_m, side="left"))
        j_t = int(np.searchsorted(timestamps_s, last_t + period_s, side="left"))
        j = max(min(j_d, j_t), i + 1)
        if j >= n:
            break
        out.append(j)
        i, last_d, last_t = j, travel_m[j], timestamps_s[j]
    if keep_last and out[-1] != n - 1:
        out.append(n - 1)
    return np.asarray(out, dtype=np.int64)


def select_tracking_frames(
    poses_xyyaw: np.ndarray,
    timestamps_s: np.ndarray,
    step_m: float,
    step_s: float,
    perceived: np.ndarray | None = None,
) -> np.ndarray:
    """Frames fed to element tracking: one every ``step_m`` of travel or ``step_s`` of time,
    chosen among the frames that report elements (``perceived (N,)`` bool; all if ``None``), so
    that an upload with the elements of keyframes only (docs/upload-binary.md) is tracked on
    its keyframes. Travel is summed along every pose."""
    step = np.r_[0.0, np.linalg.norm(np.diff(poses_xyyaw[:, :2], axis=0), axis=1)]
    candidates = np.arange(len(step)) if perceived is None else np.flatnonzero(perceived)
    if len(candidates) == 0:
        return candidates.astype(np.int64)
    chosen = every_travel_or_time(
        np.cumsum(step)[candidates],
        np.asarray(timestamps_s, float)[candidates],
        step_m,
        step_s,
        keep_last=False,
    )
    return candidates[chosen].astype(np.int64)
