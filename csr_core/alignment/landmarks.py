"""Point landmarks for along-road registration: the painted ends of dashed dividers.

Lines constrain a registration only across the road; on a straight road with dashed dividers
the dash ends are what fixes the along-road offset between two trips. Spliced instances join a
dashed divider into one line and lose them, so they are rebuilt here from the per-frame
detections (:func:`csr_core.alignment.fine.dash_ends`): each detected dash end is moved to the
world by the trip's smoothed pose, and the ~10 sightings of one painted end (one every frame
while it is in view) are merged into one landmark (same end of the dash: direction towards the
dash's other end agrees; closer than ``MERGE_RADIUS_M``). A landmark seen once is dropped
(a false or cut detection).

Landmarks enter the sub-map registration (:func:`csr_core.alignment.registration.register_elements`)
as rows along the dash direction (point to point, projected on the dash): their sigma comes
from the single-trip along-track noise estimate of dividers (``ElementNoise.along_sigma_m``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from csr_core.alignment.fine import DashEnds, dash_ends
from csr_core.types import TripReconstruction

MERGE_RADIUS_M = 0.75  # sightings of one dash end; same-kind ends of one line are >= a dash period apart
MIN_SIGHTINGS = 2
SAME_END_COS = 0.7
SAME_LINE_M = 0.5  # two ends of one painted line are this close across it  # two sightings (or two trips' landmarks) are the same end if directions agree this well


@dataclass(frozen=True, slots=True)
class Landmarks:
    """Dash-end landmarks of one trip (world frame of its smoothed poses)."""

    points_xy: np.ndarray  # (L, 2)
    direction_xy: np.ndarray  # (L, 2) unit, from this end towards the other end of its dash
    first_frame: np.ndarray  # (L,) first and last frame it was seen in
    last_frame: np.ndarray  # (L,)
    count: np.ndarray  # (L,) sightings merged

    @staticmethod
    def empty() -> Landmarks:
        return Landmarks(
            np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int), np.zeros(0, int)
        )

    def __len__(self) -> int:
        return len(self.points_xy)


def trip_landmarks(trip: TripReconstruction, sightings: DashEnds | None = None) -> Landmarks:
    """Merge the per-frame dash-end sightings of a trip (``dash_ends(trip)`` unless given) into landmarks."""
    d = dash_ends(trip) if sightings is None else sightings
    if len(d.frame) < MIN_SIGHTINGS:
        return Landmarks.empty()
    pose = trip.poses_xyyaw_world[d.frame]
    pts = _to_world(pose, d.points_xy_vehicle)
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    u = np.column_stack(
        [
            c * d.direction_vehicle[:, 0] - s * d.direction_vehicle[:, 1],
            s * d.direction_vehicle[:, 0] + c * d.direction_vehicle[:, 1],
        ]
    )
    pairs = cKDTree(pts).query_pairs(MERGE_RADIUS_M, output_type="ndarray")
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        pairs = pairs[u[a, 0] * u[b, 0] + u[a, 1] * u[b, 1] > SAME_END_COS]
    n = len(pts)
    adj = sparse.coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1]))
        if len(pairs)
        else (np.zeros(0), (np.zeros(0, int), np.zeros(0, int))),
        shape=(n, n),
    )
    _, label = connected_components(adj, directed=False)
    count = np.bincount(label)
    keep = np.flatnonzero(count >= MIN_SIGHTINGS)
    if len(keep) == 0:
        return Landmarks.empty()
    m = len(count)
    mean = np.column_stack([np.bincount(label, pts[:, k], m) for k in range(2)]) / count[:, None]
    dirs: np.ndarray = np.column_stack([np.bincount(label, u[:, k], m) for k in range(2)])
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1), 1e-12)[:, None]
    first = np.full(m, np.iinfo(np.int64).max)
    last = np.full(m, -1)
    np.minimum.at(first, label, d.frame)
    np.maximum.at(last, label, d.frame)
    return Landmarks(mean[keep], dirs[keep], first[keep], last[keep], count[keep])


def _to_world(poses_xyyaw: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(poses_xyyaw[:, 2]), np.sin(poses_xyyaw[:, 2])
    return np.column_stack(
        [
            c * points_xy[:, 0] - s * points_xy[:, 1] + poses_xyyaw[:, 0],
            s * points_xy[:, 0] + c * points_xy[:, 1] + poses_xyyaw[:, 1],
        ]
    )


def associate_landmarks(
    src_xy: np.ndarray, src_dir: np.ndarray, tgt_xy: np.ndarray, tgt_dir: np.ndarray, gate_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest target landmark of the same end kind (directions agree) within ``gate_m`` for
    every source landmark: ``(index into target, valid)``, both ``(Ls,)``."""
    if len(src_xy) == 0 or len(tgt_xy) == 0:
        return np.zeros(len(src_xy), int), np.zeros(len(src_xy), bool)
    d2 = ((src_xy[:, None, :] - tgt_xy[None, :, :]) ** 2).sum(-1)
    d2[src_dir @ tgt_dir.T <= SAME_END_COS] = np.inf
    best = np.argmin(d2, axis=1)
    return best, d2[np.arange(len(src_xy)), best] <= gate_m**2


def landmark_gate_m(tgt_xy: np.ndarray, tgt_dir: np.ndarray, default_m: float) -> float:
    """Association gate: below half the spacing of same-kind ends in the target (the dash
    period, read from the data), so a landmark cannot snap to the next dash; ``default_m``
    when the target has no two ends of one kind."""
    if len(tgt_xy) < 2:
        return default_m
    diff = tgt_xy[:, None, :] - tgt_xy[None, :, :]
    d2 = (diff**2).sum(-1)
    across = np.abs(diff[..., 0] * tgt_dir[:, None, 1] - diff[..., 1] * tgt_dir[:, None, 0])
    # same kind, on the same painted line (ends of a parallel divider are not the period)
    same = (tgt_dir @ tgt_dir.T > SAME_END_COS) & (across < SAME_LINE_M) & ~np.eye(len(tgt_xy), dtype=bool)
    d2[~same] = np.inf
    nn = np.sqrt(d2.min(axis=1))
    nn = nn[np.isfinite(nn)]
    if len(nn) == 0:
        return default_m
    return float(min(0.4 * np.median(nn), default_m))
