"""Element tracking across frames (paper III-C, after Qiao et al.): per element type, each
tracked frame's detections are associated with the live tracks as an assignment problem
(``scipy.optimize.linear_sum_assignment``) whose cost combines a one-sided Chamfer distance
(detection -> track, with the track's end segments extended so that the next dash of a dashed
divider still matches), the pose uncertainty accumulated since the track was last seen (it
widens the gate) and lateral-order consistency (the offset of the element at the vehicle, in
the vehicle frame, must agree). Unassigned pieces collinear with a matched track join it (one
divider reported in pieces, dashes); the rest start tracks; tracks unseen for a while end.

Cost per frame: one batched (tracks x detections x points x segments) array per type.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from csr_core.single_trip.params import SingleTripParams
from csr_core.types import ElementType

_LATERAL_TYPES = (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE)
_BIG = 1e6


@dataclass
class Track:
    type: ElementType
    observations: list[tuple[int, int]] = field(default_factory=list)  # (frame, element index)
    frames: list[int] = field(default_factory=list)  # distinct frames, ascending
    ref_world: np.ndarray | None = None  # (K, 2) latest geometry, oriented
    last_travel_m: float = 0.0


def resample_polylines(polys: list[np.ndarray], k: int) -> np.ndarray:
    """Each polyline (M_i, 2) -> k points uniformly spaced in arclength: (P, k, 2)."""
    out = np.empty((len(polys), k, 2))
    u = np.linspace(0.0, 1.0, k)
    for i, p in enumerate(polys):
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        s = np.r_[0.0, np.cumsum(seg)]
        if s[-1] <= 0:
            out[i] = p[0]
            continue
        q = u * s[-1]
        out[i, :, 0] = np.interp(q, s, p[:, 0])
        out[i, :, 1] = np.interp(q, s, p[:, 1])
    return out


def orient_in_vehicle(points_xy_vehicle: np.ndarray) -> np.ndarray:
    """Orient a polyline so that its dominant vehicle-frame axis increases (x for lines along
    the road, y for lines across it), so that observations of one element agree."""
    d = points_xy_vehicle[-1] - points_xy_vehicle[0]
    axis = 0 if abs(d[0]) >= abs(d[1]) else 1
    return points_xy_vehicle[::-1] if d[axis] < 0 else points_xy_vehicle


def point_to_polyline_distance(points: np.ndarray, polys: np.ndarray, max_extrapolation_m: float,
                               cap_m: float) -> np.ndarray:
    """Truncated distance of points (D, P, 2) to polylines (T, K, 2) with their end segments
    extended by up to ``max_extrapolation_m``: (T, D, P). Beyond the extension: ``cap_m``."""
    a = polys[:, None, None, :-1, :]  # (T,1,1,S,2)
    ab = np.diff(polys, axis=1)[:, None, None, :, :]
    p = points[None, :, :, None, :]  # (1,D,P,1,2)
    len2 = np.maximum((ab * ab).sum(-1), 1e-12)
    t = ((p - a) * ab).sum(-1) / len2  # (T,D,P,S)
    n_seg = polys.shape[1] - 1
    lo = np.zeros(n_seg)
    hi = np.ones(n_seg)
    lo[0] = -np.inf
    hi[-1] = np.inf
    tc = np.clip(t, lo, hi)
    d = np.linalg.norm(p - (a + tc[..., None] * ab), axis=-1)
    seg_len = np.sqrt(len2)
    over = np.maximum(-tc, 0.0) * seg_len + np.maximum(tc - 1.0, 0.0) * seg_len
    d = np.where(over > max_extrapolation_m, cap_m, d)
    return np.minimum(d, cap_m).min(axis=-1)


def lateral_at_vehicle(polys_vehicle: np.ndarray) -> np.ndarray:
    """Signed lateral offset (P,) at x = 0 of polylines (P, K, 2) in the vehicle frame, by
    interpolation, or extrapolation along the nearest end segment."""
    x, y = polys_vehicle[..., 0], polys_vehicle[..., 1]
    out = np.empty(len(polys_vehicle))
    for i in range(len(polys_vehicle)):
        xi, yi = x[i], y[i]
        order = np.argsort(xi)
        xs, ys = xi[order], yi[order]
        if xs[-1] - xs[0] < 1e-6:
            out[i] = ys.mean()
        elif xs[0] <= 0.0 <= xs[-1]:
            out[i] = np.interp(0.0, xs, ys)
        elif xs[0] > 0.0:
            out[i] = ys[0] - xs[0] * (ys[1] - ys[0]) / max(xs[1] - xs[0], 1e-6)
        else:
            out[i] = ys[-1] - xs[-1] * (ys[-1] - ys[-2]) / max(xs[-1] - xs[-2], 1e-6)
    return out


def _near(refs: np.ndarray, dets: np.ndarray, margin_m: float) -> np.ndarray:
    """(T, D) bool: bounding boxes of tracks and detections within ``margin_m``."""
    rlo, rhi = refs.min(1), refs.max(1)
    dlo, dhi = dets.min(1), dets.max(1)
    gap = np.maximum(dlo[None] - rhi[:, None], rlo[:, None] - dhi[None])  # (T,D,2)
    return (gap <= margin_m).all(-1)


def _union_resampled(polys_vehicle: list[np.ndarray], k: int) -> np.ndarray:
    """Pieces of one element (vehicle frame) joined along their dominant axis, resampled (k, 2)."""
    pts = np.concatenate(polys_vehicle)
    ext = pts.max(0) - pts.min(0)
    pts = pts[np.argsort(pts[:, 0 if ext[0] >= ext[1] else 1], kind="stable")]
    return resample_polylines([pts], k)[0]


def group_collinear(polys: np.ndarray, gate_m: float, max_extrapolation_m: float, cap_m: float) -> list[list[int]]:
    """Groups (connected components) of polylines (D, k, 2) lying on each other's extension:
    mean distance of one's points to the other's (extended) polyline under ``gate_m``."""
    n = len(polys)
    if n == 1:
        return [[0]]
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    near = _near(polys, polys, max_extrapolation_m)
    np.fill_diagonal(near, False)
    rows = np.flatnonzero(near.any(1))
    if len(rows):
        m = point_to_polyline_distance(polys, polys[rows], max_extrapolation_m, cap_m).mean(-1)  # (R, D)
        full = np.full((n, n), np.inf)
        full[rows] = m
        full = np.minimum(full, full.T)
        ii, jj = np.nonzero(np.triu(full <= gate_m, 1) & near)
        for i, j in zip(ii, jj, strict=True):
            parent[find(int(i))] = find(int(j))
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return list(groups.values())


def track_elements(frames: np.ndarray, poses_xyyaw: np.ndarray, travel_m: np.ndarray,
                   elements_vehicle: list[list[tuple[ElementType, np.ndarray]]],
                   params: SingleTripParams) -> list[Track]:
    """Track detections over the tracked ``frames`` (F,).

    ``elements_vehicle[f]`` lists (type, oriented points_xy_vehicle (M, 2)) of frame ``frames[f]``
    in upload order of that frame; observations refer to (frame, index in that list).
    ``poses_xyyaw`` (N, 3) smoothed world_T_vehicle, ``travel_m`` (N,) path length.
    Returns every track (finished or not), in creation order.
    """
    k = params.TRACK_RESAMPLE_POINTS
    cap = params.TRACK_DISTANCE_CAP_M
    tracks: list[Track] = []
    live: dict[ElementType, list[int]] = {}
    for f, frame in enumerate(frames):
        elems = elements_vehicle[f]
        if not elems:
            continue
        pose = poses_xyyaw[frame]
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rot = np.array([[c, -s], [s, c]])
        by_type: dict[ElementType, list[int]] = {}
        for j, (etype, _) in enumerate(elems):
            by_type.setdefault(etype, []).append(j)
        for etype, pieces in by_type.items():
            # pieces of one element in this frame (dashes, a divider split where its style
            # changes) form one detection: group pieces collinear within the merge gate
            pieces_v = resample_polylines([elems[j][1] for j in pieces], k)  # (D,k,2) vehicle
            groups = group_collinear(pieces_v, params.TRACK_MERGE_GATE_M, params.TRACK_MAX_EXTRAPOLATION_M, cap)
            idx = [[pieces[g] for g in grp] for grp in groups]
            dets_v = np.stack([pieces_v[grp[0]] if len(grp) == 1 else
                               _union_resampled([elems[j][1] for j in members], k)
                               for grp, members in zip(groups, idx, strict=True)])
            dets_w = dets_v @ rot.T + pose[:2]
            live_ids = [t for t in live.get(etype, [])
                        if travel_m[frame] - tracks[t].last_travel_m <= params.TRACK_MAX_MISSED_M]
            assigned: dict[int, list[int]] = {}
            unassigned = list(range(len(idx)))
            if live_ids:
                refs = np.stack([tracks[t].ref_world for t in live_ids])  # (T,k,2)
                near = _near(refs, dets_w, params.TRACK_MAX_EXTRAPOLATION_M + cap)
                chamfer = np.full((len(live_ids), len(idx)), _BIG)
                rows_n, cols_n = np.flatnonzero(near.any(1)), np.flatnonzero(near.any(0))
                if len(rows_n) and len(cols_n):
                    dist = point_to_polyline_distance(dets_w[cols_n], refs[rows_n],
                                                      params.TRACK_MAX_EXTRAPOLATION_M, cap)
                    chamfer[np.ix_(rows_n, cols_n)] = dist.mean(axis=-1)
                # pose uncertainty since the track was last seen widens the gate (odometry drift
                # over that travel, lateral error of the yaw drift at half the BEV depth)
                gap = np.array([travel_m[frame] - tracks[t].last_travel_m for t in live_ids])
                sig_rel = params.ODOM_SIGMA_XY_PER_M * gap + params.ODOM_SIGMA_YAW_PER_M * gap * 15.0
                gate = np.sqrt(params.TRACK_GATE_M**2 + (params.TRACK_GATE_SIGMAS * sig_rel) ** 2)
                cost = chamfer.copy()
                if etype in _LATERAL_TYPES and len(rows_n) and len(cols_n):
                    refs_v = (refs[rows_n] - pose[:2]) @ rot
                    along = np.abs(refs_v[:, -1, 0] - refs_v[:, 0, 0]) >= np.abs(refs_v[:, -1, 1] - refs_v[:, 0, 1])
                    y_t = lateral_at_vehicle(refs_v)
                    y_d = lateral_at_vehicle(dets_v[cols_n])
                    dy = np.minimum(np.abs(y_t[:, None] - y_d[None, :]), cap)
                    cost[np.ix_(rows_n, cols_n)] += params.TRACK_LATERAL_WEIGHT * np.where(along[:, None], dy, 0.0)
                cost = np.where(chamfer <= gate[:, None], cost, _BIG)
                rows, cols = linear_sum_assignment(cost)
                for r, cidx in zip(rows, cols, strict=True):
                    if cost[r, cidx] < _BIG:
                        assigned.setdefault(live_ids[r], []).append(int(cidx))
                taken = {d for v in assigned.values() for d in v}
                unassigned = [d for d in range(len(idx)) if d not in taken]
                # groups collinear with a matched track (missed grouping) join it
                still = []
                for d in unassigned:
                    r = int(np.argmin(chamfer[:, d]))
                    if chamfer[r, d] <= params.TRACK_MERGE_GATE_M and live_ids[r] in assigned:
                        assigned[live_ids[r]].append(d)
                    else:
                        still.append(d)
                unassigned = still
            for t, ds in assigned.items():
                tr = tracks[t]
                for d in ds:
                    tr.observations.extend((f, j) for j in idx[d])
                tr.frames.append(f)
                tr.last_travel_m = float(travel_m[frame])
                if len(ds) == 1:
                    tr.ref_world = dets_w[ds[0]]
                else:
                    members = [j for d in ds for j in idx[d]]
                    tr.ref_world = _union_resampled([elems[j][1] for j in members], k) @ rot.T + pose[:2]
            for d in unassigned:
                tr = Track(type=etype, observations=[(f, j) for j in idx[d]], frames=[f], ref_world=dets_w[d],
                           last_travel_m=float(travel_m[frame]))
                tracks.append(tr)
                live_ids.append(len(tracks) - 1)
            live[etype] = live_ids
    return tracks
