"""Fine alignment (frame level): the coarse flow with single-frame perception as the primitive.

For each trip, against the map of every *other* trip (their spliced instances moved with their
current aligned poses) and the pre-built map:
1. association: each perceived point of a frame (vehicle frame -> world by the current pose)
   to the nearest same-type map segment of another trip, gated at ``fine_gate_k`` sigmas
   (sigma from the single-trip noise and the error left by coarse alignment) -- the coarse
   stage already resolved the lane-level ambiguity, so the nearest element is the match and
   no graph matching is needed here (this is the simplification against the paper);
2. registration: per frame, a robust (TLS-weighted, iterated) point-to-line Gauss-Newton
   system in the frame's body tangent space, vectorised over all frames: mean ``xi_t`` and
   information ``H_t`` (degenerate along a straight road, as it should be);
3. per-trip pose graph (gtsam, LM): one ``Pose2`` per frame, odometry ``BetweenFactorPose2``
   between consecutive frames, ``PriorFactorPose2`` from each frame registration, and a weak
   prior at the coarse pose (holds what perception cannot see);
repeated ``fine_iterations`` times (Jacobi style: all trips against the previous round's map).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X
from scipy.spatial import cKDTree

from csr_core import se2
from csr_core.alignment.geometry import arclength_m, resample_polyline
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.types import ElementType, MapFeature, TripReconstruction

K_CANDIDATES = 4
MAX_POINTS_PER_DETECTION = 5


@dataclass(frozen=True, slots=True)
class SegmentMap:
    """All map segments of one element type, with the trip that produced each (-1: prior map)."""

    a: np.ndarray  # (S, 2)
    b: np.ndarray  # (S, 2)
    owner: np.ndarray  # (S,)
    open_start: np.ndarray  # (S,) bool: first segment of an open polyline
    open_end: np.ndarray  # (S,) bool: last segment of an open polyline
    tree: cKDTree


def _aligned_instances(trip: TripReconstruction, poses: np.ndarray, spacing_m: float):
    """The trip's instances moved with its aligned poses (each point by its nearest frame's
    correction ``x_t g_t^-1``)."""
    smoothed = trip.poses_xyyaw_world
    corr = se2.compose(poses, se2.inverse(smoothed))  # (N, 3)
    tree = cKDTree(smoothed[:, :2])
    out = []
    for inst in trip.instances:
        pts = resample_polyline(inst.points_xy_world, spacing_m, inst.type.is_polygon)
        _, idx = tree.query(pts)
        c = corr[idx]
        cos, sin = np.cos(c[:, 2]), np.sin(c[:, 2])
        moved = np.column_stack([cos * pts[:, 0] - sin * pts[:, 1] + c[:, 0], sin * pts[:, 0] + cos * pts[:, 1] + c[:, 1]])
        out.append((inst.type, moved, inst.type.is_polygon))
    return out


def build_segment_maps(elements_by_owner: Mapping[int, Sequence[tuple[ElementType, np.ndarray, bool]]]) -> dict:
    acc: dict[ElementType, list] = {}
    for owner, elems in elements_by_owner.items():
        for etype, pts, closed in elems:
            if len(pts) < 2:
                continue
            a, b = (pts, np.roll(pts, -1, axis=0)) if closed and len(pts) > 2 else (pts[:-1], pts[1:])
            n = len(a)
            first = np.zeros(n, bool)
            last = np.zeros(n, bool)
            if not closed:
                first[0], last[-1] = True, True
            acc.setdefault(etype, []).append((a, b, np.full(n, owner), first, last))
    out = {}
    for etype, parts in acc.items():
        a, b, o, f, l_ = (np.concatenate(x) for x in zip(*parts))
        out[etype] = SegmentMap(a, b, o, f, l_, cKDTree(0.5 * (a + b)))
    return out


@dataclass(frozen=True, slots=True)
class FramePoints:
    """Perceived points of every frame of a trip, flattened (vehicle frame)."""

    points_xy_vehicle: np.ndarray  # (P, 2)
    frame: np.ndarray  # (P,)
    type_code: np.ndarray  # (P,) index into list(ElementType)
    element: np.ndarray  # (P,) running detection id

    def select(self, frames: np.ndarray) -> FramePoints:
        m = np.isin(self.frame, frames)
        return FramePoints(self.points_xy_vehicle[m], self.frame[m], self.type_code[m], self.element[m])


def frame_points(trip: TripReconstruction) -> FramePoints:
    """All detections' vertices (at most about ``MAX_POINTS_PER_DETECTION`` each, evenly spread)."""
    codes = {t: n for n, t in enumerate(ElementType)}
    pts, fr, ty = [], [], []
    for t, elems in enumerate(trip.trip.elements):
        for e in elems:
            p = e.points_xy_vehicle
            if len(p) < 2:
                continue
            if len(p) > MAX_POINTS_PER_DETECTION:
                p = p[:: -(-len(p) // MAX_POINTS_PER_DETECTION)]
            pts.append(p)
            fr.append(t)
            ty.append(codes[e.type])
    if not pts:
        return FramePoints(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int), np.zeros(0, int))
    counts = np.fromiter((len(p) for p in pts), int, len(pts))
    return FramePoints(np.vstack(pts), np.repeat(np.asarray(fr), counts), np.repeat(np.asarray(ty), counts),
                       np.repeat(np.arange(len(pts)), counts))


def associate_points(points_world: np.ndarray, types: np.ndarray, maps: Mapping, exclude_owner: int,
                     gate_m: np.ndarray):
    """Nearest same-type segment of another owner (among the ``K_CANDIDATES`` nearest segment
    midpoints): foot, unit normal, signed residual and validity (gated, not beyond an end)."""
    P = len(points_world)
    foot, normal = np.zeros((P, 2)), np.zeros((P, 2))
    resid, valid = np.zeros(P), np.zeros(P, bool)
    all_types = list(ElementType)
    for code in np.unique(types):
        m = maps.get(all_types[code])
        if m is None:
            continue
        sel = np.flatnonzero(types == code)
        q = points_world[sel]
        k = min(K_CANDIDATES, len(m.a))
        _, cand = m.tree.query(q, k=k)
        cand = cand.reshape(len(sel), k)
        a, d = m.a[cand], m.b[cand] - m.a[cand]  # (n, k, 2)
        rel = q[:, None, :] - a
        L2 = np.maximum((d * d).sum(-1), 1e-12)
        u = (rel * d).sum(-1) / L2
        uc = np.clip(u, 0.0, 1.0)
        dist2 = ((rel - uc[..., None] * d) ** 2).sum(-1)
        bad = (m.owner[cand] == exclude_owner) | (m.open_start[cand] & (u < 0)) | (m.open_end[cand] & (u > 1))
        dist2[bad] = np.inf
        best = np.argmin(dist2, axis=1)
        rows = np.arange(len(sel))
        db = dist2[rows, best]
        dd = d[rows, best]
        nrm = np.column_stack([-dd[:, 1], dd[:, 0]]) / np.sqrt(L2[rows, best])[:, None]
        f = a[rows, best] + uc[rows, best][:, None] * dd
        foot[sel], normal[sel] = f, nrm
        resid[sel] = np.einsum("ij,ij->i", nrm, q - f)
        valid[sel] = np.isfinite(db) & (db <= gate_m[sel] ** 2)
    return foot, normal, resid, valid


def _point_sigmas(types: np.ndarray, points_vehicle: np.ndarray, noise: NoiseScales) -> np.ndarray:
    lat = np.array([noise.lateral(t) for t in ElementType])
    # single-frame detections get worse with range (about +1 cm per 3 m)
    return lat[types] + 0.003 * np.linalg.norm(points_vehicle, axis=1)


def _to_world(poses_xyyaw: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    c, s_ = np.cos(poses_xyyaw[:, 2]), np.sin(poses_xyyaw[:, 2])
    return np.column_stack([c * points_xy[:, 0] - s_ * points_xy[:, 1] + poses_xyyaw[:, 0],
                            s_ * points_xy[:, 0] + c * points_xy[:, 1] + poses_xyyaw[:, 1]])


def frame_registrations(fp: FramePoints, poses: np.ndarray, frames: np.ndarray, maps: Mapping,
                        owner: int, noise: NoiseScales, params: AlignmentParams):
    """Per-frame body-frame correction ``xi (F, 3)``, information ``(F, 3, 3)`` and number of
    inlier points ``(F,)`` for the keyframes ``frames`` (ascending)."""
    fp = fp.select(frames)
    pv, ty, el = fp.points_xy_vehicle, fp.type_code, fp.element
    F = len(frames)
    xi, info, n_in = np.zeros((F, 3)), np.zeros((F, 3, 3)), np.zeros(F, int)
    if len(pv) == 0:
        return xi, info, n_in
    slot = np.searchsorted(frames, fp.frame)
    sigma = _point_sigmas(ty, pv, noise)
    gate = params.fine_gate_k * np.sqrt(sigma**2 + params.fine_coarse_sigma_m**2)
    pose = poses[fp.frame]
    # association once (nearest same-type segment of another trip); then fixed lines
    foot, normal, _, valid = associate_points(_to_world(pose, pv), ty, maps, owner, gate)
    reg = np.diag([1 / params.degenerate_sigma_xy_m**2] * 2 + [1 / params.degenerate_sigma_yaw_rad**2])
    w = valid.astype(float)
    for it in range(4):
        cur = se2.compose(pose, xi[slot])
        r = np.einsum("ij,ij->i", normal, _to_world(cur, pv) - foot)
        if it > 0:  # truncated least squares at 3 sigma on the current residuals
            w = valid * (np.abs(r) <= 3.0 * sigma)
        cc, ss = np.cos(cur[:, 2]), np.sin(cur[:, 2])
        # Jacobian wrt the body-frame increment: d(pw)/d(v, w) = R [I, perp(pv)]
        nb = np.column_stack([cc * normal[:, 0] + ss * normal[:, 1], -ss * normal[:, 0] + cc * normal[:, 1]])
        J = np.column_stack([nb, nb[:, 0] * -pv[:, 1] + nb[:, 1] * pv[:, 0]])
        wt = w / sigma**2
        H = np.zeros((F, 3, 3))
        g = np.zeros((F, 3))
        np.add.at(H, slot, J[:, :, None] * J[:, None, :] * wt[:, None, None])
        np.add.at(g, slot, J * (wt * r)[:, None])
        # points of one detection share its offset error: about 2 independent samples each
        n_pts = np.bincount(slot, weights=w, minlength=F)
        n_elem = _elements_per_frame(slot, el, w > 0, F)
        scale = np.where(n_pts > 0, np.minimum(2.0 * n_elem / np.maximum(n_pts, 1), 1.0), 0.0)
        H *= scale[:, None, None]
        g *= scale[:, None]
        step = -np.linalg.solve(H + reg, g[:, :, None])[:, :, 0]
        ok = n_pts >= params.fine_min_points
        xi = np.where(ok[:, None], se2.compose(xi, step), 0.0)
        info = np.where(ok[:, None, None], H + reg, 0.0)
        n_in = np.where(ok, n_pts, 0).astype(int)
    return xi, info, n_in


def _elements_per_frame(slot: np.ndarray, element: np.ndarray, used: np.ndarray, n_frames: int) -> np.ndarray:
    if not used.any():
        return np.zeros(n_frames)
    _, first = np.unique(element[used], return_index=True)
    return np.bincount(slot[used][first], minlength=n_frames).astype(float)


def _keyframes(poses: np.ndarray, spacing_m: float) -> np.ndarray:
    s = arclength_m(poses[:, :2])
    bins = np.floor(s / spacing_m).astype(int)
    keep = np.concatenate([[True], bins[1:] != bins[:-1]])
    return np.flatnonzero(keep)


def refine_trip(trip: TripReconstruction, fp: FramePoints, poses: np.ndarray, maps: Mapping, owner: int,
                noise: NoiseScales, params: AlignmentParams) -> np.ndarray:
    """Frame-level pose graph of one trip (odometry chain + frame registrations + coarse prior)."""
    frames = _keyframes(poses, params.fine_keyframe_spacing_m)
    xi, info, n_in = frame_registrations(fp, poses, frames, maps, owner, noise, params)
    g, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    n = len(poses)
    for t in range(n):
        init.insert(X(t), gtsam.Pose2(*poses[t]))
    odom = trip.trip.odom_xyyaw
    rel = se2.between(odom[:-1], odom[1:])
    d = np.hypot(rel[:, 0], rel[:, 1])
    sxy = params.fine_odom_sigma_floor_m + params.fine_odom_sigma_per_m * d
    syaw = 1e-4 + params.fine_odom_sigma_yaw_per_m * d
    for t in range(n - 1):
        g.add(gtsam.BetweenFactorPose2(X(t), X(t + 1), gtsam.Pose2(*rel[t]),
                                       gtsam.noiseModel.Diagonal.Sigmas(np.array([sxy[t], sxy[t], syaw[t]]))))
    weak = gtsam.noiseModel.Diagonal.Sigmas(np.array([params.fine_prior_sigma_xy_m] * 2 + [params.fine_prior_sigma_yaw_rad]))
    for slot, t in enumerate(frames):
        g.add(gtsam.PriorFactorPose2(X(t), gtsam.Pose2(*poses[t]), weak))
        if n_in[slot] >= params.fine_min_points:
            H = 0.5 * (info[slot] + info[slot].T)
            target = se2.compose(poses[t], xi[slot])
            g.add(gtsam.PriorFactorPose2(X(t), gtsam.Pose2(*target), gtsam.noiseModel.Gaussian.Information(H)))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(20)
    res = gtsam.LevenbergMarquardtOptimizer(g, init, lm).optimize()
    return gtsam.utilities.extractPose2(res)


def refine_frames(trips: Sequence[TripReconstruction], fps: Sequence[FramePoints], poses: Mapping[str, np.ndarray],
                  prior_features: Sequence[MapFeature], noise: NoiseScales, params: AlignmentParams) -> dict[str, np.ndarray]:
    """Fine alignment of every trip (``fps``: each trip's :func:`frame_points`)."""
    current = {k: np.asarray(v, float).copy() for k, v in poses.items()}
    prior = [(f.type, resample_polyline(f.points_xy_world, params.element_resample_m, f.type.is_polygon),
              f.type.is_polygon) for f in prior_features]
    if len(trips) < 2 and not prior:
        return current
    for _ in range(params.fine_iterations):
        owners = {k: _aligned_instances(t, current[t.trip.key], params.element_resample_m) for k, t in enumerate(trips)}
        if prior:
            owners[-1] = prior
        maps = build_segment_maps(owners)
        current = {t.trip.key: refine_trip(t, fps[k], current[t.trip.key], maps, k, noise, params)
                   for k, t in enumerate(trips)}
    return current


def frame_residuals(trips: Sequence[TripReconstruction], fps: Sequence[FramePoints], poses: Mapping[str, np.ndarray],
                    prior_features: Sequence[MapFeature], noise: NoiseScales, params: AlignmentParams) -> dict[str, np.ndarray]:
    """Per-frame alignment residual: RMS point-to-line distance (metres) of the gated perceived
    points to the other trips' aligned elements and the prior map, evaluated on the fine
    keyframes (every ``fine_keyframe_spacing_m``) and held until the next; NaN where none."""
    owners = {k: _aligned_instances(t, poses[t.trip.key], params.element_resample_m) for k, t in enumerate(trips)}
    if prior_features:
        owners[-1] = [(f.type, resample_polyline(f.points_xy_world, params.element_resample_m, f.type.is_polygon),
                       f.type.is_polygon) for f in prior_features]
    maps = build_segment_maps(owners)
    out = {}
    for k, t in enumerate(trips):
        n = t.trip.n_frames
        frames = _keyframes(poses[t.trip.key], params.fine_keyframe_spacing_m)
        fp = fps[k].select(frames)
        res_kf = np.full(n, np.nan)
        if len(fp.frame):
            pw = _to_world(poses[t.trip.key][fp.frame], fp.points_xy_vehicle)
            sigma = _point_sigmas(fp.type_code, fp.points_xy_vehicle, noise)
            gate = params.fine_gate_k * np.sqrt(sigma**2 + params.fine_coarse_sigma_m**2)
            _, _, r, valid = associate_points(pw, fp.type_code, maps, k, gate)
            sq = np.bincount(fp.frame[valid], weights=r[valid] ** 2, minlength=n)
            cnt = np.bincount(fp.frame[valid], minlength=n)
            res_kf = np.where(cnt > 0, np.sqrt(sq / np.maximum(cnt, 1)), np.nan)
        # every frame takes the residual of its keyframe (the last one at or before it)
        owner_kf = frames[np.clip(np.searchsorted(frames, np.arange(n), side="right") - 1, 0, len(frames) - 1)]
        out[t.trip.key] = res_kf[owner_kf]
    return out
