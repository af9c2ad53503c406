"""Is a trip held by the other trips, or only by its own GNSS? (failure marking)

The pose graph ties a trip to the others through its registrations; what they do not observe
(along a straight road without dash ends, stop lines or crosswalks; a stretch where no
registration survived) only the trip's own GNSS priors hold. There the trip keeps its own GNSS
error, which on the hard profile is metres (single fixes: a bias of ~0.6 m per axis that lasts
minutes, plus the receiver latency along the track): such a trip can sit on the wrong lane or
road with nothing to tell.

``own_gnss_error_m`` predicts that error from the pose graph and the data's own noise figures:
per trip sub-map, the gain ``G_s`` of the optimised position on a common offset of the trip's
fixes (``pose_graph.own_gnss_gain``; a GNSS bias is such an offset) times the GNSS error scale
the receiver reports there (``gnss_std_m`` per axis, the status' typical accuracy where it
reports none): ``e_s = sigma_s ||G_s||_F``, the expected 2D position error the trip's own GNSS
leaves at that sub-map (``sqrt(2) sigma`` when nothing else holds it, ``~sigma sqrt(2)/n``
when n trips of equal weight do). A trip whose RMS ``e_s`` over its sub-maps that share a
circle with another trip or the map exceeds ``AlignmentParams.max_own_gnss_error_m`` (the
accuracy the alignment must deliver) is marked failed: its position there is its GNSS fix, not
an alignment.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from csr_core.alignment.params import TYPICAL_GNSS_SIGMA_M
from csr_core.alignment.submaps import Submap
from csr_core.types import TripReconstruction

UNOBSERVABLE = "unobservable"


@dataclass(frozen=True, slots=True)
class OwnGnssError:
    """Per trip: predicted 2D error left by its own GNSS, RMS over its overlapping sub-maps
    (metres), the worst sub-map's, and how many sub-maps went in."""

    rms_m: float
    max_m: float
    n_submaps: int


def gnss_sigma_m(trip: TripReconstruction, lo: int, hi: int) -> float:
    """Per-axis GNSS error scale over frames ``lo..hi``: the median reported ``std_m`` of the
    fixes, or the status' typical accuracy where the receiver reports none; NaN without a fix."""
    t = trip.trip
    fix = t.has_fix[lo : hi + 1]
    if not fix.any():
        return float("nan")
    std = t.gnss_std_m[lo : hi + 1][fix]
    typical = np.array([TYPICAL_GNSS_SIGMA_M.get(int(s), np.nan) for s in t.gnss_status[lo : hi + 1][fix]])
    return float(np.nanmedian(np.where(np.isfinite(std) & (std > 0), std, typical)))


def latency_offsets_s(trips: Sequence[TripReconstruction]) -> np.ndarray:
    """Per trip: its GNSS latency estimate (single-trip stage) minus the median of the other
    trips of the same vehicle (the latency is the receiver's: one value per vehicle); 0 where
    the trip or fewer than 2 other trips of its vehicle have an estimate (no majority)."""
    lat = np.array([float(t.diagnostics.get("gnss_latency_s", np.nan)) for t in trips])
    vehicle = [t.trip.vehicle_id for t in trips]
    out = np.zeros(len(trips))
    for k in range(len(trips)):
        others = [
            lat[m] for m in range(len(trips)) if m != k and vehicle[m] == vehicle[k] and np.isfinite(lat[m])
        ]
        if np.isfinite(lat[k]) and len(others) >= 2:
            out[k] = lat[k] - float(np.median(others))
    return out


def _speed_mps(trip: TripReconstruction, lo: int, hi: int) -> float:
    xy, t = trip.poses_xyyaw_world[lo : hi + 1, :2], trip.trip.timestamps_s[lo : hi + 1]
    dt = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() / dt) if dt > 0 else 0.0


def own_gnss_error_m(
    trips: Sequence[TripReconstruction],
    submaps: Sequence[Submap],
    gains: Mapping[int, np.ndarray],
    paired: set[int],
) -> dict[int, OwnGnssError]:
    """``OwnGnssError`` per trip index, over its sub-maps in ``paired`` (ids of sub-maps that
    share a circle with another trip or the map: elsewhere there is nothing to align with).

    Per sub-map ``e_s^2 = sigma_s^2 ||G_s||_F^2 + |G_s o_s|^2``: the reported GNSS error scale
    through the gain, plus the along-track offset ``o_s`` (heading x speed x latency offset,
    :func:`latency_offsets_s`) by which the trip's latency estimate disagrees with its
    vehicle's other trips (the receiver's ``std_m`` does not include the latency lag)."""
    dlat = latency_offsets_s(trips)
    per_trip: dict[int, list[float]] = {}
    for s in submaps:
        if s.is_prior or s.submap_id not in paired or s.submap_id not in gains:
            continue
        trip = trips[s.trip_index]
        sigma = gnss_sigma_m(trip, s.first_frame, s.last_frame)
        if np.isfinite(sigma):
            G = gains[s.submap_id]
            yaw = s.world_T_submap[2]
            lag = (
                np.array([np.cos(yaw), np.sin(yaw)])
                * _speed_mps(trip, s.first_frame, s.last_frame)
                * dlat[s.trip_index]
            )
            e2 = sigma**2 * float(np.sum(G**2)) + float(np.sum((G @ lag) ** 2))
            per_trip.setdefault(s.trip_index, []).append(float(np.sqrt(e2)))
    return {
        k: OwnGnssError(float(np.sqrt(np.mean(np.square(e)))), float(np.max(e)), len(e))
        for k, e in per_trip.items()
    }


def unobservable_reason(err: OwnGnssError, bound_m: float) -> str:
    return (
        f"{UNOBSERVABLE}: the trip's position is held by its own GNSS, not by other trips "
        f"(predicted own-GNSS error {err.rms_m:.2f} m RMS over {err.n_submaps} overlapping sub-maps, "
        f"worst {err.max_m:.2f} m; bound {bound_m:.2f} m)"
    )
