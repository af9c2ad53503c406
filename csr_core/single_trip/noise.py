"""Noise of each element type from single-trip residuals (paper III-D: the thresholds of Eq. 3
and the sigmas of Eq. 5-6 are "established based on the noise estimation result of each element
obtained through the single-trip reconstruction step")."""

from __future__ import annotations

import numpy as np

from csr_core.single_trip.params import SingleTripParams
from csr_core.types import ElementNoise, ElementType

_SORT_BELOW = 256  # middle_sorted: np.sort below this length, np.partition above


def middle_sorted(values: np.ndarray) -> np.ndarray:
    """``values`` (1-D) with at least its middle element(s) ``(n - 1) // 2`` and ``n // 2`` in
    sorted place: ``np.sort`` for short arrays, a partition around the middle for long ones
    (linear time: five times faster on a few thousand residuals)."""
    n = len(values)
    if n <= _SORT_BELOW:
        return np.sort(values)
    return np.partition(values, ((n - 1) // 2, n // 2))


def robust_sigma(residuals: np.ndarray) -> float:
    """1.4826 x median absolute deviation from the median: the Gaussian sigma, robust to outliers."""
    r = middle_sorted(np.asarray(residuals, float).ravel())
    n = len(r)
    if n == 0:
        return float("nan")
    lo, hi = (n - 1) // 2, n // 2  # medians of sorted arrays (np.median's per-call cost, thousands of calls)
    dev = middle_sorted(np.abs(r - 0.5 * (r[lo] + r[hi])))
    return float(1.4826 * 0.5 * (dev[lo] + dev[hi]))


def estimate_noise(
    lateral: dict[ElementType, list[np.ndarray]],
    along: dict[ElementType, list[np.ndarray]],
    params: SingleTripParams,
) -> dict[ElementType, ElementNoise]:
    """Per type: lateral sigma (normal to the element) and along-track sigma (element ends for
    lines, outline vertices along the heading for polygons), robust. Types with fewer than
    ``NOISE_MIN_SAMPLES`` residuals keep the prior (``n_samples`` says how many there were);
    along-track falls back to the lateral sigma's prior ratio when ends were never seen."""
    out: dict[ElementType, ElementNoise] = {}
    for etype in ElementType:
        lat = np.concatenate(lateral.get(etype, [])) if lateral.get(etype) else np.zeros(0)
        alo = np.concatenate(along.get(etype, [])) if along.get(etype) else np.zeros(0)
        lat_sigma = (
            robust_sigma(lat) if len(lat) >= params.NOISE_MIN_SAMPLES else params.NOISE_PRIOR_LATERAL_M
        )
        if len(alo) >= params.NOISE_MIN_SAMPLES:
            along_sigma = robust_sigma(alo)
        else:
            along_sigma = max(params.NOISE_PRIOR_ALONG_M, lat_sigma)
        out[etype] = ElementNoise(
            lateral_sigma_m=max(lat_sigma, 1e-3),
            along_sigma_m=max(along_sigma, 1e-3),
            n_samples=int(len(lat)),
        )
    return out
