"""Absolute (GNSS-frame) 1-sigma of a map element and the per-tile accuracy certificate.

``uncertainty_m`` (fusion) is the spread of the aligned observations of an element: the error
left *after* the trips are brought onto each other. What no alignment removes is where the
fleet as a whole puts the element: the alignment holds the map to the trips' GNSS fixes as their
information-weighted mean (``alignment.params.DEFAULT_GNSS_STATUS_WEIGHTS``), and each trip's
fixes near the element share that trip's slowly varying GNSS bias (a Gauss-Markov process,
stationary sigma ``s_i`` per axis; docs/gnss-model.md). Passes of different trips have
independent biases, so the map's absolute lateral error at the element is

    sigma_abs^2 = uncertainty_m^2 + 1 / sum_i (1 / s_i^2)                             (1)

which is ``uncertainty_m^2 + s^2 / n`` for ``n`` trips of one sigma ``s``. ``s_i`` is the trip's
own error model: the median of its fixes' reported ``std_m`` (per axis, the honest
``sqrt(bias^2 + white^2)`` of the receiver), else the single-trip status table
``SingleTripParams.GNSS_SIGMA_BY_STATUS_M``, floored at ``GNSS_SIGMA_FLOOR_M``
(:func:`trip_bias_sigma_m`, stored in the trip's diagnostics as ``gnss_bias_sigma_m``).

The certificate of a tile (:func:`tile_certificate`) is the length-weighted RMS of
``sigma_abs_m`` and of ``uncertainty_m`` over its elements, the trips behind it, and how many
more passes the 1/sqrt(n) model of Eq. 1 needs until the RMS absolute error reaches a target.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from csr_core.single_trip.gnss_bias import (
    TRIP_BIAS_LENGTH_KEY,
    TRIP_BIAS_SIGMA_KEY,
    UNKNOWN_TRIP_BIAS_SIGMA_M,
    trip_bias_sigma_m,
)
from csr_core.types import MapFeature

__all__ = [
    "SIGMA_ABS_PROPERTY",
    "TRIP_BIAS_LENGTH_KEY",
    "TRIP_BIAS_SIGMA_KEY",
    "TripBias",
    "UNKNOWN_TRIP_BIAS_SIGMA_M",
    "TileCertificate",
    "absolute_sigma_m",
    "tied_trips",
    "trip_biases",
    "passes_needed",
    "tile_certificate",
    "trip_bias_sigma_m",
    "with_absolute_uncertainty",
]

#: the property name of Eq. 1's result on a feature (metres, lateral 1 sigma)
SIGMA_ABS_PROPERTY = "sigma_abs_m"


@dataclass(frozen=True, slots=True)
class TileCertificate:
    """What a tile's map promises: RMS expected errors (metres, lateral 1 sigma) weighted by
    element length, the trips behind the tile and the median passes per element, and the passes
    still needed for ``expected_absolute_error_m`` to reach ``target_m`` (0 when it does; None
    when no number of passes does, because the relative part alone exceeds the target)."""

    expected_absolute_error_m: float
    expected_relative_error_m: float
    n_features: int
    trips: int
    passes_median: float
    target_m: float
    passes_needed: int | None

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "expected_absolute_error_m": round(self.expected_absolute_error_m, 4),
            "expected_relative_error_m": round(self.expected_relative_error_m, 4),
            "n_features": self.n_features,
            "trips": self.trips,
            "passes_median": self.passes_median,
            "target_m": self.target_m,
            "passes_needed": self.passes_needed,
        }


def absolute_sigma_m(uncertainty_m: float, trip_bias_sigmas_m: Sequence[float]) -> float:
    """Eq. 1: the element's absolute lateral 1 sigma (metres) from its relative ``uncertainty_m``
    and the bias sigma of each independent trip behind it. Never below ``uncertainty_m``; with no
    trip, the unknown trip's sigma."""
    s = np.asarray(trip_bias_sigmas_m, float)
    if len(s) and not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError(f"trip bias sigmas must be positive and finite, got {s.tolist()}")
    bias_var = 1.0 / float(np.sum(1.0 / s**2)) if len(s) else UNKNOWN_TRIP_BIAS_SIGMA_M**2
    u = float(uncertainty_m) if math.isfinite(uncertainty_m) and uncertainty_m > 0 else 0.0
    return math.sqrt(u * u + bias_var)


@dataclass(frozen=True, slots=True)
class TripBias:
    """A trip's GNSS bias: ``sigma_m`` its stationary 1 sigma per axis, ``length_m`` the distance it
    drives in one correlation time (``single_trip.gnss_bias``; from its reconstruction's diagnostics)."""

    sigma_m: float
    length_m: float


def tied_trips(
    points_xy: np.ndarray,
    own_trips: Sequence[str],
    trip_paths_xy: Mapping[str, np.ndarray],
    biases: Mapping[str, TripBias],
) -> list[str]:
    """The trips whose bias the element's absolute position averages: its own (``own_trips``) and
    every trip whose path (``trip_paths_xy``: (P, >=2), x y first) passes within that trip's
    ``length_m`` of one of the element's ``points_xy (M, 2)``: the alignment ties such a trip to
    the others where they overlap, and its bias there is the one it has near the element."""
    out = set(own_trips)
    pts = np.asarray(points_xy, float).reshape(-1, 2)
    for trip, path in trip_paths_xy.items():
        if trip in out or trip not in biases or not len(path) or not len(pts):
            continue
        reach = biases[trip].length_m
        xy = np.asarray(path, float)[:, :2]
        lo, hi = pts.min(axis=0) - reach, pts.max(axis=0) + reach
        near = xy[np.all((xy >= lo) & (xy <= hi), axis=1)]
        if len(near) and cKDTree(near).query(pts, distance_upper_bound=reach)[0].min() <= reach:
            out.add(trip)
    return sorted(out)


def with_absolute_uncertainty(
    features: Sequence[MapFeature],
    biases: Mapping[str, TripBias],
    trip_paths_xy: Mapping[str, np.ndarray] | None = None,
) -> list[MapFeature]:
    """``features`` with ``properties["sigma_abs_m"]`` (Eq. 1) from their ``uncertainty_m`` and
    the bias sigmas of their :func:`tied_trips` (their own ``trips`` when no paths are given); a
    trip missing from ``biases`` counts with :data:`UNKNOWN_TRIP_BIAS_SIGMA_M`."""
    out = []
    for f in features:
        own = [str(t) for t in f.properties.get("trips") or ()]
        trips = tied_trips(f.points_xy_world, own, trip_paths_xy, biases) if trip_paths_xy else own
        sigmas = [biases[t].sigma_m if t in biases else UNKNOWN_TRIP_BIAS_SIGMA_M for t in trips]
        u = f.properties.get("uncertainty_m")
        sigma = absolute_sigma_m(float(u) if isinstance(u, int | float) else 0.0, sigmas)
        out.append(replace(f, properties={**f.properties, SIGMA_ABS_PROPERTY: round(sigma, 4)}))
    return out


def trip_biases(diagnostics_by_trip: Mapping[str, Mapping[str, object]]) -> dict[str, TripBias]:
    """The :class:`TripBias` of each trip whose reconstruction diagnostics hold one."""
    out = {}
    for trip, diag in diagnostics_by_trip.items():
        sigma, length = diag.get(TRIP_BIAS_SIGMA_KEY), diag.get(TRIP_BIAS_LENGTH_KEY, 0.0)
        if isinstance(sigma, int | float) and sigma > 0 and isinstance(length, int | float):
            out[trip] = TripBias(float(sigma), max(float(length), 0.0))
    return out


def passes_needed(sigma_abs_m: float, uncertainty_m: float, passes: float, target_m: float) -> int | None:
    """Passes to add so that Eq. 1 with equal trips reaches ``target_m``: the bias part
    ``b^2 = sigma_abs^2 - u^2`` falls as ``n / (n + k)``; the smallest integer ``k >= 0`` with
    ``u^2 + b^2 n / (n + k) <= target^2``. None when ``u >= target`` (no pass removes it)."""
    if sigma_abs_m <= target_m:
        return 0
    if uncertainty_m >= target_m:
        return None
    bias_var = sigma_abs_m**2 - uncertainty_m**2
    n = max(float(passes), 1.0)
    total = bias_var * n / (target_m**2 - uncertainty_m**2)
    return max(math.ceil(total - n - 1e-9), 0)


def tile_certificate(
    lengths_m: Sequence[float] | np.ndarray,
    sigma_abs_m: Sequence[float] | np.ndarray,
    uncertainty_m: Sequence[float] | np.ndarray,
    passes: Sequence[int] | np.ndarray,
    trips: int,
    target_m: float,
) -> TileCertificate:
    """The certificate of a tile's elements: ``lengths_m`` (K,) their lengths in metres (a
    polygon's outline), ``sigma_abs_m`` / ``uncertainty_m`` (K,) their Eq. 1 and relative sigmas,
    ``passes`` (K,) their support trips, ``trips`` the distinct trips behind the tile. An empty
    tile certifies nothing: zero errors, zero trips, ``passes_needed`` None."""
    if target_m <= 0:
        raise ValueError(f"target_m must be positive, got {target_m}")
    w = np.asarray(lengths_m, float)
    sa = np.asarray(sigma_abs_m, float)
    u = np.asarray(uncertainty_m, float)
    if not (w.shape == sa.shape == u.shape == (len(passes),)):
        raise ValueError("lengths_m, sigma_abs_m, uncertainty_m and passes must have one entry per element")
    if not len(w):
        return TileCertificate(0.0, 0.0, 0, trips, 0.0, target_m, None)
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    w = w if w.sum() > 0 else np.ones_like(w)
    abs_rms = float(np.sqrt(np.sum(w * sa**2) / w.sum()))
    rel_rms = float(np.sqrt(np.sum(w * u**2) / w.sum()))
    n = float(np.median(np.asarray(passes, float)))
    return TileCertificate(
        expected_absolute_error_m=abs_rms,
        expected_relative_error_m=rel_rms,
        n_features=len(w),
        trips=trips,
        passes_median=n,
        target_m=target_m,
        passes_needed=passes_needed(abs_rms, rel_rms, n, target_m),
    )
