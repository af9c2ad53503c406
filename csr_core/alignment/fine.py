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
from csr_core.alignment.odometry_noise import chain_sigmas, trip_yaw_random_walk
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.types import ElementType, MapFeature, TripReconstruction

K_CANDIDATES = 4
MAX_POINTS_PER_DETECTION = 5
DASH_MIN_M, DASH_MAX_M = 1.0, 5.0  # a divider detection this long is one painted dash
RANGE_MARGIN_M = 1.0  # ends this close to the trip's perception range limit are cuts, not ends
DASH_CANDIDATES = 24
DASH_GATE_M = 2.0  # below half the shortest dash-gap period seen in practice (3 m + 6 m)


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
        moved = np.column_stack(
            [cos * pts[:, 0] - sin * pts[:, 1] + c[:, 0], sin * pts[:, 0] + cos * pts[:, 1] + c[:, 1]]
        )
        out.append((inst.type, moved, inst.type.is_polygon))
    return out


def build_segment_maps(
    elements_by_owner: Mapping[int, Sequence[tuple[ElementType, np.ndarray, bool]]],
) -> dict:
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
        a, b, o, f, l_ = (np.concatenate(x) for x in zip(*parts, strict=False))
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


@dataclass(frozen=True, slots=True)
class Detections:
    """Every detection of a trip with at least two vertices, flattened in upload order: the
    vertices ``points_xy_vehicle (V, 2)`` and, per detection, its first vertex ``start (D,)``,
    vertex ``count (D,)``, ``frame (D,)`` and ``type_code (D,)`` (index into ``ElementType``)."""

    points_xy_vehicle: np.ndarray
    start: np.ndarray
    count: np.ndarray
    frame: np.ndarray
    type_code: np.ndarray

    @property
    def last(self) -> np.ndarray:
        return self.start + self.count - 1


def detections(trip: TripReconstruction) -> Detections:
    """The trip's detections as flat arrays (one Python pass over the elements, numpy after)."""
    codes = {t: n for n, t in enumerate(ElementType)}
    pts, fr, ty = [], [], []
    for t, elems in enumerate(trip.trip.elements):
        for e in elems:
            if len(e.points_xy_vehicle) >= 2:
                pts.append(e.points_xy_vehicle)
                fr.append(t)
                ty.append(codes[e.type])
    if not pts:
        z = np.zeros(0, int)
        return Detections(np.zeros((0, 2)), z, z, z, z)
    count = np.fromiter((len(p) for p in pts), int, len(pts))
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    return Detections(np.concatenate(pts), start, count, np.asarray(fr), np.asarray(ty))


def frame_points(trip: TripReconstruction, dets: Detections | None = None) -> FramePoints:
    """All detections' vertices (at most about ``MAX_POINTS_PER_DETECTION`` each, evenly spread:
    every ``ceil(count / MAX)``-th vertex from the first)."""
    d = detections(trip) if dets is None else dets
    if len(d.count) == 0:
        return FramePoints(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int), np.zeros(0, int))
    det = np.repeat(np.arange(len(d.count)), d.count)
    step = -(-d.count // MAX_POINTS_PER_DETECTION)
    keep = (np.arange(len(det)) - d.start[det]) % step[det] == 0
    det = det[keep]
    return FramePoints(d.points_xy_vehicle[keep], d.frame[det], d.type_code[det], det)


@dataclass(frozen=True, slots=True)
class DashEnds:
    """Ends of the painted dashes of dashed dividers seen in each frame (vehicle frame): the
    along-road landmarks that spliced instances lose (a dashed divider splices into one line)."""

    points_xy_vehicle: np.ndarray  # (E, 2)
    frame: np.ndarray  # (E,)
    direction_vehicle: np.ndarray  # (E, 2) unit, from this end towards the other end of its dash

    def select(self, frames: np.ndarray) -> DashEnds:
        m = np.isin(self.frame, frames)
        return DashEnds(self.points_xy_vehicle[m], self.frame[m], self.direction_vehicle[m])


def dash_ends(
    trip: TripReconstruction, max_dash_m: float = DASH_MAX_M, dets: Detections | None = None
) -> DashEnds:
    """Both ends of every short divider detection (a dash), except ends at the edge of the
    perception range (cut by the range, not painted), which is read from the trip itself."""
    d = detections(trip) if dets is None else dets
    divider = d.type_code == list(ElementType).index(ElementType.LANE_DIVIDER)
    first, last = d.points_xy_vehicle[d.start[divider]], d.points_xy_vehicle[d.last[divider]]
    v = last - first
    length = np.hypot(v[:, 0], v[:, 1])
    dash = (length >= DASH_MIN_M) & (length <= max_dash_m)
    if not dash.any():
        return DashEnds(np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 2)))
    u = v[dash] / length[dash, None]
    P = np.stack([first[dash], last[dash]], axis=1).reshape(-1, 2)
    U = np.stack([u, -u], axis=1).reshape(-1, 2)
    F = np.repeat(d.frame[divider][dash], 2)
    ext = np.vstack([first, last])
    x_lo, x_hi = np.percentile(ext[:, 0], [0.5, 99.5])
    y_hi = np.percentile(np.abs(ext[:, 1]), 99.5)
    inside = (
        (P[:, 0] > x_lo + RANGE_MARGIN_M)
        & (P[:, 0] < x_hi - RANGE_MARGIN_M)
        & (np.abs(P[:, 1]) < y_hi - RANGE_MARGIN_M)
    )
    return DashEnds(P[inside], F[inside], U[inside])


@dataclass(frozen=True, slots=True)
class DashMap:
    """World dash ends of every trip; ``kind`` tells the two ends of a dash apart (the end
    pointing along (+1) or against (-1) the dash's canonical world direction)."""

    points_xy: np.ndarray  # (D, 2)
    owner: np.ndarray  # (D,)
    kind: np.ndarray  # (D,) +-1
    trees: dict


def _canonical(direction_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Direction of the dash with a sign fixed in the world (x >= 0 half-plane), and the kind."""
    flip = (direction_world[:, 0] < 0) | ((direction_world[:, 0] == 0) & (direction_world[:, 1] < 0))
    axis = np.where(flip[:, None], -direction_world, direction_world)
    return axis, np.where(
        flip, 1, -1
    )  # an end whose "towards the other end" points along +axis is the -1 end


def _rotate(poses_xyyaw: np.ndarray, v: np.ndarray) -> np.ndarray:
    c, s_ = np.cos(poses_xyyaw[:, 2]), np.sin(poses_xyyaw[:, 2])
    return np.column_stack([c * v[:, 0] - s_ * v[:, 1], s_ * v[:, 0] + c * v[:, 1]])


def build_dash_map(dashes: Sequence[DashEnds], poses: Sequence[np.ndarray]) -> DashMap:
    pts, own, kind = [np.zeros((0, 2))], [np.zeros(0, int)], [np.zeros(0, int)]
    for k, (d, p) in enumerate(zip(dashes, poses, strict=False)):
        if len(d.frame) == 0:
            continue
        pose = p[d.frame]
        pts.append(_to_world(pose, d.points_xy_vehicle))
        own.append(np.full(len(d.frame), k))
        kind.append(_canonical(_rotate(pose, d.direction_vehicle))[1])
    xy, owner, kinds = np.vstack(pts), np.concatenate(own), np.concatenate(kind)
    trees = {c: (np.flatnonzero(kinds == c), cKDTree(xy[kinds == c])) for c in (-1, 1) if np.any(kinds == c)}
    return DashMap(xy, owner, kinds, trees)


def associate_dash_ends(
    points_world: np.ndarray, direction_world: np.ndarray, dmap: DashMap, exclude_owner: int, gate_m: float
):
    """The same dash end as seen by the other trips (same kind, within ``gate_m``): foot (their
    mean, each trip weighted equally), along-dash unit normal (the residual direction), validity."""
    n = len(points_world)
    foot, normal, valid = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n, bool)
    if n == 0:
        return foot, normal, valid
    axis, kind = _canonical(direction_world)
    for c, (idx, tree) in dmap.trees.items():
        sel = np.flatnonzero(kind == c)
        if len(sel) == 0:
            continue
        k = min(DASH_CANDIDATES, len(idx))  # one dash end is seen in ~10 frames of each trip
        dist, cand = tree.query(points_world[sel], k=k)
        dist, cand = dist.reshape(len(sel), k), idx[cand.reshape(len(sel), k)]
        own = dmap.owner[cand]
        ok = (own != exclude_owner) & (dist <= gate_m)
        # the foot is the mean over the other trips (each trip weighted equally), not the nearest
        # copy: the nearest copy is biased towards trips that share this trip's error
        n_owners = int(dmap.owner.max()) + 1
        cell = np.arange(len(sel))[:, None] * n_owners + own  # (query, candidate's trip)
        per_trip = np.bincount(cell[ok], minlength=len(sel) * n_owners)[cell]
        w = np.where(ok, 1.0 / np.maximum(per_trip, 1), 0.0)
        wsum = w.sum(axis=1)
        pts = dmap.points_xy[cand]
        foot[sel] = (w[:, :, None] * pts).sum(axis=1) / np.maximum(wsum, 1e-12)[:, None]
        normal[sel] = axis[sel]
        valid[sel] = wsum > 0
    return foot, normal, valid


def associate_points(
    points_world: np.ndarray, types: np.ndarray, maps: Mapping, exclude_owner: int, gate_m: np.ndarray
):
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
        # (n, k) arrays per coordinate (no trailing axis of 2: reductions over it are slow)
        ax, ay = m.a[cand, 0], m.a[cand, 1]
        dx, dy = m.b[cand, 0] - ax, m.b[cand, 1] - ay
        rx, ry = q[:, 0, None] - ax, q[:, 1, None] - ay
        L2 = np.maximum(dx * dx + dy * dy, 1e-12)
        u = (rx * dx + ry * dy) / L2
        uc = np.clip(u, 0.0, 1.0)
        dist2 = (rx - uc * dx) ** 2 + (ry - uc * dy) ** 2
        bad = (m.owner[cand] == exclude_owner) | (m.open_start[cand] & (u < 0)) | (m.open_end[cand] & (u > 1))
        dist2[bad] = np.inf
        best = np.argmin(dist2, axis=1)
        rows = np.arange(len(sel))
        db = dist2[rows, best]
        dd = np.column_stack([dx[rows, best], dy[rows, best]])
        nrm = np.column_stack([-dd[:, 1], dd[:, 0]]) / np.sqrt(L2[rows, best])[:, None]
        f = np.column_stack([ax[rows, best], ay[rows, best]]) + uc[rows, best][:, None] * dd
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
    return np.column_stack(
        [
            c * points_xy[:, 0] - s_ * points_xy[:, 1] + poses_xyyaw[:, 0],
            s_ * points_xy[:, 0] + c * points_xy[:, 1] + poses_xyyaw[:, 1],
        ]
    )


def frame_registrations(
    fp: FramePoints,
    poses: np.ndarray,
    frames: np.ndarray,
    maps: Mapping,
    owner: int,
    noise: NoiseScales,
    params: AlignmentParams,
    dashes: DashEnds | None = None,
    dash_map: DashMap | None = None,
):
    """Per-frame body-frame correction ``xi (F, 3)``, information ``(F, 3, 3)`` and number of
    inlier points ``(F,)`` for the keyframes ``frames`` (ascending).

    Rows: perceived points against the other trips' lines (point to line, across the road),
    and dash ends against the other trips' dash ends (along the dash: the along-road constraint
    that lines cannot give)."""
    fp = fp.select(frames)
    F = len(frames)
    xi, info, n_in = np.zeros((F, 3)), np.zeros((F, 3, 3)), np.zeros(F, int)
    pv, ty, el = fp.points_xy_vehicle, fp.type_code, fp.element
    sigma = _point_sigmas(ty, pv, noise)
    gate = params.fine_gate_k * np.sqrt(sigma**2 + params.fine_coarse_sigma_m**2)
    pose = poses[fp.frame]
    # association once (nearest same-type segment of another trip); then fixed lines
    foot, normal, _, valid = associate_points(_to_world(pose, pv), ty, maps, owner, gate)
    frame_of = fp.frame
    if dashes is not None and dash_map is not None and len(dashes.frame):
        d = dashes.select(frames)
        dpose = poses[d.frame]
        f2, n2, v2 = associate_dash_ends(
            _to_world(dpose, d.points_xy_vehicle),
            _rotate(dpose, d.direction_vehicle),
            dash_map,
            owner,
            DASH_GATE_M,
        )
        pv = np.vstack([pv, d.points_xy_vehicle])
        foot, normal, valid = np.vstack([foot, f2]), np.vstack([normal, n2]), np.concatenate([valid, v2])
        sigma = np.concatenate([sigma, np.full(len(d.frame), params.fine_dash_sigma_m)])
        el = np.concatenate([el, (el.max() + 1 if len(el) else 0) + np.arange(len(d.frame))])
        frame_of = np.concatenate([frame_of, d.frame])
        pose = poses[frame_of]
    if len(pv) == 0:
        return xi, info, n_in
    slot = np.searchsorted(frames, frame_of)
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
        # points of one detection share its offset error: about 2 independent samples each
        used_per_element = np.bincount(el, weights=w, minlength=int(el.max()) + 1)
        wt = w * np.minimum(2.0 / np.maximum(used_per_element[el], 1.0), 1.0) / sigma**2
        H, g = np.empty((F, 3, 3)), np.empty((F, 3))
        for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):  # symmetric: the upper triangle
            H[:, i, j] = H[:, j, i] = np.bincount(slot, weights=J[:, i] * J[:, j] * wt, minlength=F)
        for i in range(3):
            g[:, i] = np.bincount(slot, weights=J[:, i] * (wt * r), minlength=F)
        n_pts = np.bincount(slot, weights=w, minlength=F)
        step = -np.linalg.solve(H + reg, g[:, :, None])[:, :, 0]
        ok = n_pts >= params.fine_min_points
        xi = np.where(ok[:, None], se2.compose(xi, step), 0.0)
        info = np.where(ok[:, None, None], H + reg, 0.0)
        n_in = np.where(ok, n_pts, 0).astype(int)
    return xi, info, n_in


def _keyframes(poses: np.ndarray, spacing_m: float) -> np.ndarray:
    s = arclength_m(poses[:, :2])
    bins = np.floor(s / spacing_m).astype(int)
    keep = np.concatenate([[True], bins[1:] != bins[:-1]])
    return np.flatnonzero(keep)


def refine_trip(
    trip: TripReconstruction,
    fp: FramePoints,
    poses: np.ndarray,
    maps: Mapping,
    owner: int,
    noise: NoiseScales,
    params: AlignmentParams,
    dashes: DashEnds | None = None,
    dash_map: DashMap | None = None,
) -> np.ndarray:
    """Frame-level pose graph of one trip: one ``Pose2`` per keyframe, chained at the *current*
    (coarse) relative poses, frame registrations as priors, a weak prior at the coarse pose.

    The chain holds the coarse solution's relative motion (already GNSS + odometry smoothed and
    calibrated, so its scale and yaw-rate bias are right) with the smoothed trajectory's
    relative accuracy (the heading random walk of the trip's odometry over the seconds between
    two keyframes, as e^sm: ``odometry_noise.chain_sigmas``): the fine stage estimates a
    *correction* that varies slowly along the trip and cannot add frame-to-frame noise. Raw
    odometry increments would re-introduce the odometry scale error that the single-trip stage
    removed. The keyframe corrections are spread to every frame linearly in travelled distance."""
    frames = _keyframes(poses, params.fine_keyframe_spacing_m)
    if frames[-1] != len(poses) - 1:
        frames = np.append(frames, len(poses) - 1)
    xi, info, n_in = frame_registrations(fp, poses, frames, maps, owner, noise, params, dashes, dash_map)
    kf = poses[frames]
    g, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for slot in range(len(frames)):
        init.insert(X(slot), gtsam.Pose2(*kf[slot]))
    rel = se2.between(kf[:-1], kf[1:])
    d = np.hypot(rel[:, 0], rel[:, 1])
    if params.fine_chain_from_odometry:  # the heading random walk over the seconds between keyframes
        sigmas = chain_sigmas(
            d,
            np.abs(np.diff(trip.trip.timestamps_s[frames])),
            trip_yaw_random_walk(trip, params),
            params.fine_chain_sigma_xy0_m,
        )
        sxy, syaw = sigmas[:, 0], sigmas[:, 2]
    else:
        sxy = params.fine_chain_sigma_floor_m + params.fine_chain_sigma_per_m * d
        syaw = params.fine_chain_sigma_yaw_floor_rad + params.fine_chain_sigma_yaw_per_m * d
    for slot in range(len(frames) - 1):
        g.add(
            gtsam.BetweenFactorPose2(
                X(slot),
                X(slot + 1),
                gtsam.Pose2(*rel[slot]),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([sxy[slot], sxy[slot], syaw[slot]])),
            )
        )
    weak = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([params.fine_prior_sigma_xy_m] * 2 + [params.fine_prior_sigma_yaw_rad])
    )
    for slot in range(len(frames)):
        g.add(gtsam.PriorFactorPose2(X(slot), gtsam.Pose2(*kf[slot]), weak))
        if n_in[slot] >= params.fine_min_points:
            H = params.fine_registration_weight * 0.5 * (info[slot] + info[slot].T)
            target = se2.compose(kf[slot], xi[slot])
            g.add(
                gtsam.PriorFactorPose2(
                    X(slot), gtsam.Pose2(*target), gtsam.noiseModel.Gaussian.Information(H)
                )
            )
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(20)
    res = gtsam.utilities.extractPose2(gtsam.LevenbergMarquardtOptimizer(g, init, lm).optimize())
    return spread_corrections(poses, frames, se2.compose(res, se2.inverse(kf)))


def spread_corrections(poses: np.ndarray, frames: np.ndarray, corrections_xyyaw: np.ndarray) -> np.ndarray:
    """Apply world-frame corrections ``c_k`` known at keyframes ``frames`` (ascending, first and
    last frame included) to every frame, interpolated linearly in travelled distance:
    ``x_t = c(s_t) o poses_t``. ``(N, 3)``."""
    s = arclength_m(poses[:, :2])
    sk = s[frames]
    if len(frames) == 1:
        c = np.repeat(corrections_xyyaw, len(poses), axis=0)
    else:
        c = np.column_stack(
            [
                np.interp(s, sk, corrections_xyyaw[:, 0]),
                np.interp(s, sk, corrections_xyyaw[:, 1]),
                np.interp(s, sk, np.unwrap(corrections_xyyaw[:, 2])),
            ]
        )
    return se2.compose(c, poses)


def refine_frames(
    trips: Sequence[TripReconstruction],
    fps: Sequence[FramePoints],
    poses: Mapping[str, np.ndarray],
    prior_features: Sequence[MapFeature],
    noise: NoiseScales,
    params: AlignmentParams,
    dash_sightings: Sequence[DashEnds] | None = None,
) -> dict[str, np.ndarray]:
    """Fine alignment of every trip (``fps``: each trip's :func:`frame_points`; ``dash_sightings``:
    each trip's :func:`dash_ends`, computed here when not given)."""
    current = {k: np.asarray(v, float).copy() for k, v in poses.items()}
    prior = [
        (
            f.type,
            resample_polyline(f.points_xy_world, params.element_resample_m, f.type.is_polygon),
            f.type.is_polygon,
        )
        for f in prior_features
    ]
    if len(trips) < 2 and not prior:
        return current
    dashes = None
    if len(trips) > 1 and params.fine_dashes:
        dashes = list(dash_sightings) if dash_sightings is not None else [dash_ends(t) for t in trips]
    for _ in range(params.fine_iterations):
        owners = {
            k: _aligned_instances(t, current[t.trip.key], params.element_resample_m)
            for k, t in enumerate(trips)
        }
        if prior:
            owners[-1] = prior
        maps = build_segment_maps(owners)
        dash_map = build_dash_map(dashes, [current[t.trip.key] for t in trips]) if dashes else None
        current = {
            t.trip.key: refine_trip(
                t,
                fps[k],
                current[t.trip.key],
                maps,
                k,
                noise,
                params,
                dashes[k] if dashes else None,
                dash_map,
            )
            for k, t in enumerate(trips)
        }
    return current


def frame_residuals(
    trips: Sequence[TripReconstruction],
    fps: Sequence[FramePoints],
    poses: Mapping[str, np.ndarray],
    prior_features: Sequence[MapFeature],
    noise: NoiseScales,
    params: AlignmentParams,
) -> dict[str, np.ndarray]:
    """Per-frame alignment residual: RMS point-to-line distance (metres) of the gated perceived
    points to the other trips' aligned elements and the prior map, evaluated on the fine
    keyframes (every ``fine_keyframe_spacing_m``) and held until the next; NaN where none."""
    owners = {
        k: _aligned_instances(t, poses[t.trip.key], params.element_resample_m) for k, t in enumerate(trips)
    }
    if prior_features:
        owners[-1] = [
            (
                f.type,
                resample_polyline(f.points_xy_world, params.element_resample_m, f.type.is_polygon),
                f.type.is_polygon,
            )
            for f in prior_features
        ]
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
        owner_kf = frames[
            np.clip(np.searchsorted(frames, np.arange(n), side="right") - 1, 0, len(frames) - 1)
        ]
        out[t.trip.key] = res_kf[owner_kf]
    return out
