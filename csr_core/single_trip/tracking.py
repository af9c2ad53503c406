"""Element tracking across frames (paper III-C, after Qiao et al.), batched over the trip.

Every detection ("piece") of the tracked frames is resampled to ``k`` points and put in the
world frame with its smoothed pose, all at once. Two kinds of links are then scored in one
vectorised pass each:

- within a frame, pieces of one type lying on each other's extension (a dashed divider seen
  as separate dashes, a divider split where its style changes) are one detection;
- between a frame and the next tracked frames (up to ``TRACK_MAX_SKIP_FRAMES`` later, so a
  missed detection does not end the track), a piece and a later one are linked when each is
  the other's best choice (mutual best: a one-to-one assignment, so tracks stay chains and do
  not branch into every lane at a junction). The cost
  combines a one-sided Chamfer distance (later piece -> earlier piece, end segments extended
  so that the next dash still matches), the pose uncertainty accumulated over the travel
  between the frames (it widens the gate) and lateral-order consistency (the offsets of both
  pieces at the vehicle, in the later frame's vehicle frame, must agree).

Tracks are the connected components of those links. Costs are pairwise arrays over candidate
pairs (bounding boxes within reach), so a 1 km trip costs tens of milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from csr_core.single_trip.compiled import observations
from csr_core.single_trip.params import SingleTripParams
from csr_core.types import ElementType

TYPE_CODES = {t: i for i, t in enumerate(ElementType)}
_BOUND_SLACK_M = 1e-6  # _chamfer_lower_bound: rounding allowance (the bound holds exactly in reals)
_POLYGON_CODES = np.array([t.is_polygon for t in ElementType])
#: lines perceived whole where seen: one piece continues another only end to end, one piece per end
#: (a dashed divider's dashes are chained by dash_chaining)
_CONTINUOUS_CODES = np.array([t in (ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE) for t in ElementType])
_LATERAL_CODES = np.array(
    [t in (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE) for t in ElementType]
)


@dataclass(frozen=True, slots=True)
class Pieces:
    """All detections of the tracked frames, flattened (Q pieces)."""

    frame: np.ndarray  # (Q,) index into the tracked-frame list
    element: np.ndarray  # (Q,) index of the element in its upload frame
    type_code: np.ndarray  # (Q,) TYPE_CODES
    points_v: np.ndarray  # (Q, k, 2) resampled, vehicle frame
    points_w: np.ndarray  # (Q, k, 2) resampled, world frame
    # the detections as sent (vehicle frame), concatenated: piece q is raw_points_v[raw_offsets[q]:raw_offsets[q + 1]]
    raw_points_v: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    raw_offsets: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))


@dataclass(frozen=True, slots=True)
class Track:
    type: ElementType
    pieces: np.ndarray  # (m,) indices into Pieces, by frame
    frames: np.ndarray  # (f,) distinct tracked-frame indices, ascending


def resample_flat(points: np.ndarray, offsets: np.ndarray, k: int) -> np.ndarray:
    """Polylines given as concatenated ``points (P, 2)`` with ``offsets (Q+1,)`` -> (Q, k, 2),
    each resampled to k points uniformly in arclength. Vectorised over all polylines."""
    q = len(offsets) - 1
    counts = np.diff(offsets)
    piece = np.repeat(np.arange(q), counts)
    step = np.zeros(len(points))
    d = points[1:] - points[:-1]
    np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1], out=step[1:])  # np.linalg.norm(d, axis=1)
    step[offsets[:-1]] = 0.0  # no step across pieces
    s = np.cumsum(step)
    s_local = s - s[offsets[:-1]][piece]
    length = s_local[offsets[1:] - 1]
    big = float(length.max()) + 1.0 if q else 1.0
    key = piece * big + s_local
    target = np.linspace(0.0, 1.0, k)[None, :] * length[:, None]  # (Q,k)
    tkey = np.arange(q)[:, None] * big + target
    right = np.searchsorted(key, tkey.ravel(), side="left").reshape(q, k)
    right = np.clip(right, offsets[:-1, None] + 1, offsets[1:, None] - 1)
    left = right - 1
    span = np.maximum(s_local[right] - s_local[left], 1e-12)
    w = np.clip((target - s_local[left]) / span, 0.0, 1.0)[..., None]
    return points[left] * (1.0 - w) + points[right] * w


def pair_distance(
    points: np.ndarray, polys: np.ndarray, max_extrapolation_m: float, cap_m: float
) -> np.ndarray:
    """Truncated distance of each point of ``points (M, P, 2)`` to the matching polyline of
    ``polys (M, K, 2)``, the polyline extended at both ends along its chord (first to last
    point: a noisy end segment of a short dash would swing) by up to ``max_extrapolation_m``;
    farther: ``cap_m``. Returns (M, P). Compiled (``observations.pair_distance``)."""
    return observations.pair_distance(
        np.ascontiguousarray(points, dtype=float),
        np.ascontiguousarray(polys, dtype=float),
        float(max_extrapolation_m),
        float(cap_m),
    )


def lateral_at_vehicle(polys_vehicle: np.ndarray) -> np.ndarray:
    """Signed lateral offset (M,) at x = 0 of polylines (M, K, 2) (vehicle frame, roughly along
    x), interpolated or extrapolated along the end segment nearest to x = 0."""
    x, y = polys_vehicle[..., 0], polys_vehicle[..., 1]
    flip = x[:, -1] < x[:, 0]
    x = np.where(flip[:, None], x[:, ::-1], x)
    y = np.where(flip[:, None], y[:, ::-1], y)
    k = x.shape[1]
    i = np.clip((x < 0.0).sum(1), 1, k - 1)
    rows = np.arange(len(x))
    x0, x1, y0, y1 = x[rows, i - 1], x[rows, i], y[rows, i - 1], y[rows, i]
    dx = x1 - x0
    return np.where(
        np.abs(dx) > 1e-6, y0 + (0.0 - x0) * (y1 - y0) / np.where(np.abs(dx) > 1e-6, dx, 1.0), 0.5 * (y0 + y1)
    )


def _pairs_between(
    keys_sorted: np.ndarray, a_keys: np.ndarray, order_a: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """All (a, b) with b's key equal to ``a_keys[a]`` (b indexes the sorted array)."""
    lo = np.searchsorted(keys_sorted, a_keys, side="left")
    hi = np.searchsorted(keys_sorted, a_keys, side="right")
    c = hi - lo
    a = np.repeat(order_a, c)
    base = np.repeat(lo - np.r_[0, np.cumsum(c)[:-1]], c)
    b = base + np.arange(int(c.sum()))
    return a, b


@dataclass(frozen=True, slots=True)
class _Shapes:
    """Per-piece quantities of the pair pre-tests, computed once per trip. Coordinates are kept
    as separate contiguous (Q,) arrays: the pre-tests gather them for ~10^5 pairs, and 1-D
    gathers are the cheapest."""

    lo_x: np.ndarray  # (Q,) bounding box
    lo_y: np.ndarray
    hi_x: np.ndarray
    hi_y: np.ndarray
    start_x: np.ndarray  # (Q,) first point
    start_y: np.ndarray
    u_x: np.ndarray  # (Q,) unit chord
    u_y: np.ndarray
    length: np.ndarray  # (Q,) chord length
    mid_x: np.ndarray  # (Q,) middle point
    mid_y: np.ndarray
    sag: np.ndarray  # (Q,) largest distance of a point to the chord line

    @staticmethod
    def of(pw: np.ndarray) -> _Shapes:
        chord = pw[:, -1] - pw[:, 0]
        length = np.maximum(np.linalg.norm(chord, axis=1), 1e-9)
        u = chord / length[:, None]
        rel = pw - pw[:, :1]
        sag = np.abs(rel[..., 0] * u[:, None, 1] - rel[..., 1] * u[:, None, 0]).max(1)
        lo, hi, mid = pw.min(1), pw.max(1), pw[:, pw.shape[1] // 2]

        def col(a: np.ndarray, k: int) -> np.ndarray:
            return np.ascontiguousarray(a[:, k])

        return _Shapes(
            col(lo, 0),
            col(lo, 1),
            col(hi, 0),
            col(hi, 1),
            col(pw[:, 0], 0),
            col(pw[:, 0], 1),
            col(u, 0),
            col(u, 1),
            length,
            col(mid, 0),
            col(mid, 1),
            sag,
        )


def _bbox_near(sh: _Shapes, a: np.ndarray, b: np.ndarray, margin_m: float) -> np.ndarray:
    """Indices of the pairs (a, b) whose bounding boxes are within ``margin_m`` of each other
    along x and y (y tested only on the pairs that pass along x)."""
    idx = np.flatnonzero((sh.lo_x[b] - sh.hi_x[a] <= margin_m) & (sh.lo_x[a] - sh.hi_x[b] <= margin_m))
    a, b = a[idx], b[idx]
    return idx[(sh.lo_y[b] - sh.hi_y[a] <= margin_m) & (sh.lo_y[a] - sh.hi_y[b] <= margin_m)]


def _coarse_near(
    sh: _Shapes, a: np.ndarray, b: np.ndarray, ext_m: float, gate_m: float, min_cos: float
) -> np.ndarray:
    """Cheap pre-test of pairs: bounding boxes within reach; chords nearly parallel (pieces
    shorter than 2 m exempt); the middle point of one within ``gate_m`` plus both pieces'
    sagitta (curvature) of the other's chord line. Returns a mask (n_pairs,)."""
    keep = np.zeros(len(a), dtype=bool)
    near = _bbox_near(sh, a, b, ext_m)
    a, b = a[near], b[near]
    ua_x, ua_y, ub_x, ub_y = sh.u_x[a], sh.u_y[a], sh.u_x[b], sh.u_y[b]
    lat1 = np.abs((sh.mid_x[b] - sh.start_x[a]) * ua_y - (sh.mid_y[b] - sh.start_y[a]) * ua_x)
    lat2 = np.abs((sh.mid_x[a] - sh.start_x[b]) * ub_y - (sh.mid_y[a] - sh.start_y[b]) * ub_x)
    cos = np.abs(ua_x * ub_x + ua_y * ub_y)
    sag_a, sag_b = sh.sag[a], sh.sag[b]
    short = (sh.length[a] < 2.0) | (sh.length[b] < 2.0)
    ok = (np.minimum(lat1, lat2) <= gate_m + sag_a + sag_b) & (
        (cos >= min_cos) | short | (sag_a + sag_b > 1.0)
    )
    keep[near[ok]] = True
    return keep


def _chamfer_lower_bound(points: np.ndarray, sh: _Shapes, poly: np.ndarray, cap_m: float) -> np.ndarray:
    """A lower bound (M,) of ``pair_distance(points, pw[poly], ., cap_m).mean(1)`` for
    ``points (M, P, 2)`` and the pieces ``poly (M,)``: a piece, and its extensions along its
    chord, lie within its sagitta of its chord line, so a point is at least its offset from that
    line minus the sagitta from them. About a tenth of the cost of the distances: pairs whose
    bound is beyond the gate are dropped before them."""
    px, py = points[..., 0], points[..., 1]
    ux, uy = sh.u_x[poly, None], sh.u_y[poly, None]
    offset = np.abs((px - sh.start_x[poly, None]) * uy - (py - sh.start_y[poly, None]) * ux)
    return np.minimum(np.maximum(offset - sh.sag[poly, None], 0.0), cap_m).mean(1)


def collect_pieces(frames: np.ndarray, poses_xyyaw: np.ndarray, elements, k: int) -> Pieces:
    """Flatten the detections of the tracked ``frames`` (indices into the upload) into Pieces."""
    per_frame = [elements[frame] for frame in frames]
    flat = [e for frame_elements in per_frame for e in frame_elements]
    pts = [e.points_xy_vehicle for e in flat]
    if not pts:
        z = np.zeros(0, dtype=np.int64)
        return Pieces(z, z, z, np.zeros((0, k, 2)), np.zeros((0, k, 2)))
    counts = np.fromiter(map(len, pts), dtype=np.int64, count=len(pts))
    offsets = np.r_[0, np.cumsum(counts)]
    raw = np.ascontiguousarray(np.concatenate(pts), dtype=float)
    pv = resample_flat(raw, offsets, k)
    n_per_frame = np.fromiter(map(len, per_frame), dtype=np.int64, count=len(per_frame))
    f_arr = np.repeat(np.arange(len(per_frame), dtype=np.int64), n_per_frame)
    e_idx = np.arange(len(flat), dtype=np.int64) - np.repeat(
        np.cumsum(n_per_frame) - n_per_frame, n_per_frame
    )
    codes = np.fromiter((TYPE_CODES[e.type] for e in flat), dtype=np.int64, count=len(flat))
    pose = poses_xyyaw[frames[f_arr]]
    c, s = np.cos(pose[:, 2])[:, None], np.sin(pose[:, 2])[:, None]
    pw = np.stack(
        [
            c * pv[..., 0] - s * pv[..., 1] + pose[:, None, 0],
            s * pv[..., 0] + c * pv[..., 1] + pose[:, None, 1],
        ],
        axis=-1,
    )
    return Pieces(f_arr, e_idx, codes, pv, pw, raw, offsets.astype(np.int64))


def track_elements(
    frames: np.ndarray, poses_xyyaw: np.ndarray, travel_m: np.ndarray, elements, params: SingleTripParams
) -> tuple[Pieces, list[Track]]:
    """Track the detections of the tracked ``frames`` (F,) through the trip.

    ``poses_xyyaw`` (N, 3) smoothed world_T_vehicle, ``travel_m`` (N,) path length, ``elements``
    the trip's per-frame PerceivedElement tuples. Returns the pieces and the tracks (connected
    components of the links), each with its pieces and distinct tracked frames.
    """
    k = params.TRACK_RESAMPLE_POINTS
    cap = params.TRACK_DISTANCE_CAP_M
    ext = params.TRACK_MAX_EXTRAPOLATION_M
    pc = collect_pieces(frames, poses_xyyaw, elements, k)
    q = len(pc.frame)
    if q == 0:
        return pc, []
    n_types = len(TYPE_CODES)
    key = pc.frame * n_types + pc.type_code  # pieces are in (frame, upload) order
    order = np.argsort(key, kind="stable")
    keys_sorted = key[order]
    rows, cols = [], []

    # 1. pieces of one element within a frame: collinear within the merge gate (lines only: a
    # polygon is detected whole or clipped, never in pieces; two crosswalks side by side are two)
    a, b_sorted = _pairs_between(keys_sorted, key, np.arange(q))
    b = order[b_sorted]
    m = (a < b) & ~_POLYGON_CODES[pc.type_code[a]]
    a, b = a[m], b[m]
    shapes = _Shapes.of(pc.points_w)
    m = _coarse_near(
        shapes,
        a,
        b,
        ext,
        params.TRACK_MERGE_GATE_M + params.TRACK_COARSE_MARGIN_M,
        np.cos(params.TRACK_MAX_ANGLE_RAD),
    )
    a, b = a[m], b[m]
    if len(a):
        # min(d_ab, d_ba) within the gate: each distance only where its lower bound is within
        # the gate, d_ba only where d_ab is not
        gate = params.TRACK_MERGE_GATE_M
        m = np.zeros(len(a), dtype=bool)
        i_ab = np.flatnonzero(_chamfer_lower_bound(pc.points_w[b], shapes, a, cap) <= gate + _BOUND_SLACK_M)
        d_ab = pair_distance(pc.points_w[b[i_ab]], pc.points_w[a[i_ab]], ext, cap).mean(1)
        m[i_ab] = d_ab <= gate
        rest = np.flatnonzero(~m)
        rest = rest[_chamfer_lower_bound(pc.points_w[a[rest]], shapes, b[rest], cap) <= gate + _BOUND_SLACK_M]
        d_ba = pair_distance(pc.points_w[a[rest]], pc.points_w[b[rest]], ext, cap).mean(1)
        m[rest] = d_ba <= gate
        if params.TRACK_MERGE_ONE_PER_END:
            cost = np.full(len(a), np.inf)
            cost[i_ab] = d_ab
            cost[rest] = np.minimum(cost[rest], d_ba)
            m &= one_continuation_per_end(pc.points_w, a, b, cost, ~_CONTINUOUS_CODES[pc.type_code[a]] | ~m)
        rows.append(a[m])
        cols.append(b[m])

    # 2. links to the next tracked frames: best successor and best predecessor within the gate
    pa, pb, pcost = [], [], []
    for skip in range(1, params.TRACK_MAX_SKIP_FRAMES + 1):
        a, b_sorted = _pairs_between(keys_sorted, key + skip * n_types, np.arange(q))
        b = order[b_sorted]
        if len(a) == 0:
            continue
        m = _coarse_near(
            shapes,
            a,
            b,
            ext,
            params.TRACK_GATE_M + params.TRACK_COARSE_MARGIN_M,
            np.cos(params.TRACK_MAX_ANGLE_RAD),
        )
        a, b = a[m], b[m]
        if len(a) == 0:
            continue
        # pose uncertainty over the travel between the frames widens the gate
        gap_m = np.abs(travel_m[frames[pc.frame[b]]] - travel_m[frames[pc.frame[a]]])
        sig_rel = params.ODOM_SIGMA_XY_PER_M * gap_m + params.ODOM_SIGMA_YAW_PER_M * gap_m * 15.0
        gate = np.sqrt(params.TRACK_GATE_M**2 + (params.TRACK_GATE_SIGMAS * sig_rel) ** 2)
        near = _chamfer_lower_bound(pc.points_w[b], shapes, a, cap) <= gate + _BOUND_SLACK_M
        a, b, gate = a[near], b[near], gate[near]
        chamfer = pair_distance(pc.points_w[b], pc.points_w[a], ext, cap).mean(1)
        poly = _POLYGON_CODES[pc.type_code[a]]
        if poly.any():  # an outline is not extended along its chord (a side): a neighbour is not it
            chamfer[poly] = pair_distance(pc.points_w[b[poly]], pc.points_w[a[poly]], 0.0, cap).mean(1)
        ok = chamfer <= gate
        a, b, chamfer = a[ok], b[ok], chamfer[ok]
        # lateral order: offsets at the vehicle of both pieces, in the later frame's vehicle frame
        lat = _LATERAL_CODES[pc.type_code[a]]
        cost = chamfer.copy()
        if lat.any():
            pose_b = poses_xyyaw[frames[pc.frame[b[lat]]]]
            rel = pc.points_w[a[lat]] - pose_b[:, None, :2]
            c, s = np.cos(pose_b[:, 2])[:, None], np.sin(pose_b[:, 2])[:, None]
            a_in_b = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]], -1)
            along = np.abs(a_in_b[:, -1, 0] - a_in_b[:, 0, 0]) >= np.abs(a_in_b[:, -1, 1] - a_in_b[:, 0, 1])
            dy = np.abs(lateral_at_vehicle(a_in_b) - lateral_at_vehicle(pc.points_v[b[lat]]))
            cost[lat] += params.TRACK_LATERAL_WEIGHT * np.where(along, np.minimum(dy, cap), 0.0)
        pa.append(a)
        pb.append(b)
        pcost.append(cost)
    # mutual best per skip, nearest frames first; a later skip only for pieces still unlinked
    has_succ = np.zeros(q, dtype=bool)
    has_pred = np.zeros(q, dtype=bool)
    for a, b, cost in zip(pa, pb, pcost, strict=True):
        free = ~has_succ[a] & ~has_pred[b]
        a, b, cost = a[free], b[free], cost[free]
        if len(a) == 0:
            continue
        best_succ = np.full(q, np.inf)
        np.minimum.at(best_succ, a, cost)
        best_pred = np.full(q, np.inf)
        np.minimum.at(best_pred, b, cost)
        keep = (cost <= best_succ[a]) & (cost <= best_pred[b])
        rows.append(a[keep])
        cols.append(b[keep])
        has_succ[a[keep]] = True
        has_pred[b[keep]] = True

    r = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, dtype=np.int64)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(q, q))
    n_comp, labels = connected_components(graph, directed=False)
    by_label = np.argsort(labels, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(labels, minlength=n_comp))]
    # distinct frames of every track at once: a track's pieces are in frame order
    frame_of = pc.frame[by_label]
    first_of_frame = np.ones(q, dtype=bool)
    first_of_frame[1:] = frame_of[1:] != frame_of[:-1]
    first_of_frame[bounds[:-1]] = True
    distinct_frames = frame_of[first_of_frame]
    frame_bounds = np.r_[0, np.cumsum(first_of_frame)][bounds]
    types = list(ElementType)
    track_types = pc.type_code[by_label[bounds[:-1]]].tolist()
    tracks = []
    for i in range(n_comp):
        tracks.append(
            Track(
                type=types[track_types[i]],
                pieces=by_label[bounds[i] : bounds[i + 1]],
                frames=distinct_frames[frame_bounds[i] : frame_bounds[i + 1]],
            )
        )
    return pc, tracks


def one_continuation_per_end(
    points_w: np.ndarray, a: np.ndarray, b: np.ndarray, cost: np.ndarray, exempt: np.ndarray
) -> np.ndarray:
    """Which of the within-frame merges of pieces ``a`` and ``b`` (indices into ``points_w (Q, k,
    2)``, with their Chamfer ``cost``) to keep: the pieces must continue each other, lying on
    opposite sides of the joint of their nearest ends, and each must be the other's cheapest
    continuation at that end (cost plus the gap between the ends). Merges marked ``exempt`` are
    kept as they are and take no part.

    Where a lane ends, its connectors (left, straight, right) start: all of them lie on its
    extension, and a test of each pair alone makes one detection of all of them, whose track
    then takes in every connector of the junction (Karlsruhe s1: one centreline track of 67
    tracked frames held 608 detections and came out as 89 instances). One continuation per end
    keeps the lane with its straightest connector; the others start tracks of their own, as the
    links between frames already do (mutual best)."""
    keep = exempt.copy()
    sel = np.flatnonzero(~exempt)
    if len(sel) == 0:
        return keep
    ia, ib = a[sel], b[sel]
    ends_a = points_w[ia][:, [0, -1]]  # (n, end, xy)
    ends_b = points_w[ib][:, [0, -1]]
    gap = ends_a[:, :, None, :] - ends_b[:, None, :, :]
    gap = np.sqrt((gap * gap).sum(-1)).reshape(len(sel), 4)  # (first, first), (first, last), ...
    joint = gap.argmin(1)
    end_a, end_b = joint // 2, joint % 2
    r = np.arange(len(sel))
    into_a = ends_a[r, 1 - end_a] - ends_a[r, end_a]  # from the joint into each piece
    into_b = ends_b[r, 1 - end_b] - ends_b[r, end_b]
    total = np.where((into_a * into_b).sum(1) < 0, cost[sel] + gap[r, joint], np.inf)
    node_a, node_b = 2 * ia + end_a, 2 * ib + end_b  # (piece, end)
    best = np.full(2 * len(points_w), np.inf)
    np.minimum.at(best, node_a, total)
    np.minimum.at(best, node_b, total)
    keep[sel] = np.isfinite(total) & (total <= best[node_a]) & (total <= best[node_b])
    return keep


def component_labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Labels ``(n,)`` of the connected components of the undirected graph on ``n`` nodes with
    edges ``a[i]-b[i]``, numbered in the order of each component's smallest node, as scipy's
    ``connected_components`` numbers them. Union-find on plain ints: for the few dozen
    observations of one track a quarter of the cost of building a sparse matrix for scipy."""
    parent = list(range(n))

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for u, v in zip(np.asarray(a).tolist(), np.asarray(b).tolist(), strict=True):
        ru, rv = root(u), root(v)
        if ru != rv:
            parent[max(ru, rv)] = min(ru, rv)
    numbers: dict[int, int] = {}
    return np.array([numbers.setdefault(root(x), len(numbers)) for x in range(n)], dtype=np.int32)


def regroup_observations(
    points_w: np.ndarray,
    frame: np.ndarray,
    gate_m: float,
    max_angle_rad: float,
    max_skip_frames: int,
    max_extrapolation_m: float,
) -> np.ndarray:
    """Labels (m,) splitting a track's observations ``points_w (m, k, 2)`` (tracked frame
    ``frame (m,)``) into elements by a stricter, symmetric test than the tracker's: two
    observations at most ``max_skip_frames`` apart are one element when each one's mean distance
    to the other (end segments extended along the chord) is within ``gate_m`` and their chords
    are nearly parallel. Used on a track whose splice mixes elements (connectors crossing or
    branching in a junction, chained by the one-sided tracking cost)."""
    m = len(points_w)
    a, b = np.triu_indices(m, 1)
    near = np.abs(frame[a] - frame[b]) <= max_skip_frames
    a, b = a[near], b[near]
    if len(a) == 0:
        return np.arange(m)
    chord = points_w[:, -1] - points_w[:, 0]
    length = np.maximum(np.hypot(chord[:, 0], chord[:, 1]), 1e-9)
    u = chord / length[:, None]
    parallel = (np.abs((u[a] * u[b]).sum(1)) >= np.cos(max_angle_rad)) | (
        np.minimum(length[a], length[b]) < 2.0
    )
    a, b = a[parallel], b[parallel]
    # both mean distances within the gate: d_ba only where d_ab is
    d_ab = pair_distance(points_w[b], points_w[a], max_extrapolation_m, 3.0 * gate_m).mean(1)
    ok = np.flatnonzero(d_ab <= gate_m)
    d_ba = pair_distance(points_w[a[ok]], points_w[b[ok]], max_extrapolation_m, 3.0 * gate_m).mean(1)
    ok = ok[d_ba <= gate_m]
    return component_labels(m, a[ok], b[ok])
