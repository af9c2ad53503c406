"""Sub-map splitting and matching pairs (paper Fig. 4).

1. Frame graph: nodes are frames (subsampled every ``keyframe_spacing_m`` of smoothed travel);
   edges join consecutive nodes of a trip and nodes of different trips closer than
   :func:`frame_graph_distance_m` (unless set, the trips' lateral perception reach: two frames
   that far apart share half of their views) whose headings differ by less than ``frame_graph_angle_rad``
   (modulo pi when ``pair_opposite_directions``: on a two-way road both directions see the same
   dividers and boundaries).
2. Circles: an uncovered node is a centre; the nodes within ``submap_radius_m`` that the graph
   reaches without leaving the disk are its members, and are covered.
3. Sub-maps: per circle, each trip's contiguous run of member nodes is one sub-map, anchored at
   the run's node nearest the centre (``world_T_submap`` = that frame's smoothed pose); its
   elements are the trip's instances seen during the run, clipped to the disk, in the sub-map
   frame.
4. Pairs: sub-maps of different trips in one circle form P_sub-sub (each with its next
   ``max_partners_per_submap`` in trip order, so every circle holds cycles for Step 4); a
   circle that overlaps the pre-built map forms P_sub-pre with its patch of that map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order
from scipy.spatial import cKDTree

from csr_core import se2
from csr_core.alignment.geometry import arclength_m, resample_polyline
from csr_core.alignment.landmarks import Landmarks, trip_landmarks
from csr_core.alignment.params import AlignmentParams
from csr_core.single_trip import bev_range_m
from csr_core.types import ElementType, MapFeature, TripReconstruction

DUPLICATE_M = 0.75  # pieces of a pre-built map closer than this are one element


@dataclass(frozen=True, slots=True)
class SubmapElement:
    """One element of a sub-map, in the sub-map (anchor) frame, resampled every ~1 m."""

    type: ElementType
    points_xy_submap: np.ndarray  # (M, 2)
    instance_index: int  # index into the trip's instances (prior map: into its features)
    closed: bool = False


def gnss_prior_poses_xyyaw(trip: TripReconstruction, white_solve: bool) -> np.ndarray:
    """A trip's poses as Eq. 9's e^g or the e^sm chain takes them (``(N, 3)``): its white-noise solve
    when ``white_solve`` and it has one, else its smoothed poses (``Submap.gnss_prior_pose`` per anchor)."""
    if white_solve and trip.white_poses_xyyaw_world is not None:
        return trip.white_poses_xyyaw_world
    return trip.poses_xyyaw_world


@dataclass(frozen=True, slots=True)
class Submap:
    """One trip's data inside one circle. ``trip_index == -1`` marks a pre-built-map patch."""

    submap_id: int
    circle_id: int
    trip_index: int
    trip_key: str
    anchor_frame: int
    first_frame: int
    last_frame: int
    world_T_submap: np.ndarray  # (3,) initial (smoothed) pose of the anchor
    elements: tuple[SubmapElement, ...]
    # dash-end landmarks seen in this run, sub-map frame (see ``landmarks``); empty for map patches
    landmarks_xy_submap: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    landmark_dirs_submap: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    landmark_counts: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    # the anchor's pose in the trip's white-noise solve (``TripReconstruction.white_poses_xyyaw_world``,
    # with the single-trip GNSS bias state), for the alignment's e^g and e^sm (``gnss_prior_pose``)
    white_world_T_submap: np.ndarray | None = None

    @property
    def is_prior(self) -> bool:
        return self.trip_index < 0

    def gnss_prior_pose(self, white_solve: bool) -> np.ndarray:
        """The anchor pose Eq. 9's e^g or the e^sm chain holds this sub-map to: the white-noise
        solve's when ``white_solve`` and the trip has one, else ``world_T_submap``."""
        return (
            self.white_world_T_submap
            if white_solve and self.white_world_T_submap is not None
            else self.world_T_submap
        )

    def landmarks_world(self, world_T_submap: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Landmark points and unit directions in the world (at ``world_T_submap``)."""
        pose = self.world_T_submap if world_T_submap is None else world_T_submap
        c, s_ = np.cos(pose[2]), np.sin(pose[2])
        rot = np.array([[c, -s_], [s_, c]])
        return se2.transform_points(pose, self.landmarks_xy_submap), self.landmark_dirs_submap @ rot.T

    def element_points_world(self, world_T_submap: np.ndarray | None = None) -> list[np.ndarray]:
        pose = self.world_T_submap if world_T_submap is None else world_T_submap
        return [se2.transform_points(pose, e.points_xy_submap) for e in self.elements]


@dataclass(frozen=True, slots=True)
class Circle:
    circle_id: int
    centre_xy_world: np.ndarray  # (2,)
    heading_rad: float  # heading of the centre node (reference direction for Eq. 3 cross-sections)
    radius_m: float


@dataclass(frozen=True, slots=True)
class FrameGraph:
    positions_xy: np.ndarray  # (V, 2)
    yaw_rad: np.ndarray  # (V,)
    trip_index: np.ndarray  # (V,)
    frame_index: np.ndarray  # (V,)
    adjacency: sparse.csr_matrix  # (V, V)


def _distance_subsample(poses_xyyaw: np.ndarray, spacing_m: float) -> np.ndarray:
    s = arclength_m(poses_xyyaw[:, :2])
    bins = np.floor(s / spacing_m).astype(int)
    keep = np.concatenate([[True], bins[1:] != bins[:-1]])
    keep[-1] = True
    return np.flatnonzero(keep)


def frame_graph_distance_m(trips: Sequence[TripReconstruction], params: AlignmentParams) -> float:
    """Largest distance (metres) between frames of two trips joined in the frame graph:
    ``params.frame_graph_distance_m`` when set, else the shortest lateral reach of the trips'
    perception (the farther side of ``sensor_setup.bev_range_m``, else of where the trip's
    detections lie). With a range of +-R, two frames R apart see a common strip at least R wide,
    half of each one's view, so the sub-maps of the two carriageways of a divided road, or of the
    two directions of a wide road, are paired."""
    if params.frame_graph_distance_m is not None:
        return float(params.frame_graph_distance_m)
    reach = [max(-y_min, y_max) for (_, _, y_min, y_max) in (bev_range_m(t.trip) for t in trips)]
    return float(min(reach))


def build_frame_graph(trips: Sequence[TripReconstruction], params: AlignmentParams) -> FrameGraph:
    pos, yaw, tix, fix = [], [], [], []
    for k, tr in enumerate(trips):
        idx = _distance_subsample(tr.poses_xyyaw_world, params.keyframe_spacing_m)
        pos.append(tr.poses_xyyaw_world[idx, :2])
        yaw.append(tr.poses_xyyaw_world[idx, 2])
        tix.append(np.full(len(idx), k))
        fix.append(idx)
    P, Y, T, F = np.vstack(pos), np.concatenate(yaw), np.concatenate(tix), np.concatenate(fix)
    # consecutive frames of a trip
    same = T[1:] == T[:-1]
    rows = [np.flatnonzero(same)]
    cols = [np.flatnonzero(same) + 1]
    # frames of different trips within distance and angle
    pairs = cKDTree(P).query_pairs(frame_graph_distance_m(trips, params), output_type="ndarray")
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        dyaw = np.abs(se2.wrap_angle(Y[a] - Y[b]))
        if params.pair_opposite_directions:
            dyaw = np.minimum(dyaw, np.pi - dyaw)
        ok = (T[a] != T[b]) & (dyaw < params.frame_graph_angle_rad)
        rows.append(a[ok])
        cols.append(b[ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    n = len(P)
    adj = sparse.coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n)).tocsr()
    return FrameGraph(P, Y, T, F, (adj + adj.T).tocsr())


def split_circles(graph: FrameGraph, params: AlignmentParams) -> tuple[list[Circle], list[np.ndarray]]:
    """Greedy circles over the frame graph; returns circles and their member node indices."""
    tree = cKDTree(graph.positions_xy)
    covered = np.zeros(len(graph.positions_xy), bool)
    circles: list[Circle] = []
    members: list[np.ndarray] = []
    R = params.submap_radius_m
    for v in range(len(graph.positions_xy)):
        if covered[v]:
            continue
        ball = np.asarray(tree.query_ball_point(graph.positions_xy[v], R), int)
        sub = graph.adjacency[ball][:, ball]
        local = int(np.flatnonzero(ball == v)[0])
        order = breadth_first_order(sub, local, directed=False, return_predecessors=False)
        mem = np.sort(ball[order])
        covered[mem] = True
        circles.append(Circle(len(circles), graph.positions_xy[v].copy(), float(graph.yaw_rad[v]), R))
        members.append(mem)
    return circles, members


def _prepared_instances(trip: TripReconstruction, params: AlignmentParams) -> list[tuple[np.ndarray, bool]]:
    out = []
    for inst in trip.instances:
        closed = inst.type.is_polygon
        out.append((resample_polyline(inst.points_xy_world, params.element_resample_m, closed), closed))
    return out


def element_bounds(prepared: Sequence[tuple[np.ndarray, bool]]) -> np.ndarray:
    """``(K, 4)`` bounding boxes ``(x_lo, y_lo, x_hi, y_hi)`` of prepared elements; an element of
    fewer than two points gets an empty box (``lo = +inf``, ``hi = -inf``) that no disk meets."""
    bounds = np.tile([np.inf, np.inf, -np.inf, -np.inf], (len(prepared), 1))
    for i, (pts, _) in enumerate(prepared):
        if len(pts) >= 2:
            bounds[i] = np.r_[pts.min(axis=0), pts.max(axis=0)]
    return bounds


def clip_elements_to_disk(
    prepared: Sequence[tuple[np.ndarray, bool]],
    types: Sequence[ElementType],
    centre_xy: np.ndarray,
    radius_m: float,
    min_length_m: float,
    bounds: np.ndarray | None = None,
) -> list[tuple[int, np.ndarray, bool]]:
    """Pieces of (resampled) elements inside a disk: ``(element index, points, closed)``.
    ``bounds``: :func:`element_bounds` of ``prepared`` (computed here when not given)."""
    bounds = element_bounds(prepared) if bounds is None else bounds
    # cheap reject by bounding box
    near = ~(
        np.any(bounds[:, :2] > centre_xy + radius_m, axis=1)
        | np.any(bounds[:, 2:] < centre_xy - radius_m, axis=1)
    )
    out = []
    for i in map(int, np.flatnonzero(near)):
        (pts, closed), etype = prepared[i], types[i]
        inside = np.linalg.norm(pts - centre_xy, axis=1) <= radius_m
        if not inside.any():
            continue
        if closed:
            if np.linalg.norm(pts.mean(axis=0) - centre_xy) <= radius_m:
                out.append((i, pts, True))
            continue
        edges = np.flatnonzero(np.diff(inside.astype(int))) + 1
        for run in np.split(np.arange(len(pts)), edges):
            if not inside[run[0]] or len(run) < 2:
                continue
            piece = pts[run]
            min_len = min_length_m if etype != ElementType.STOP_LINE else 1.0
            if arclength_m(piece)[-1] >= min_len:
                out.append((i, piece, False))
    return out


def _limit(elements: list[SubmapElement], n_max: int) -> tuple[SubmapElement, ...]:
    if len(elements) <= n_max:
        return tuple(elements)
    d = [float(np.min(np.linalg.norm(e.points_xy_submap, axis=1))) for e in elements]
    keep = sorted(np.argsort(d)[:n_max])
    return tuple(elements[i] for i in keep)


def split_submaps(
    trips: Sequence[TripReconstruction],
    params: AlignmentParams,
    dash_sightings: Sequence | None = None,
) -> tuple[list[Circle], list[Submap]]:
    """Fig. 4: circles over the frame graph and one sub-map per trip (run) per circle."""
    graph = build_frame_graph(trips, params)
    circles, members = split_circles(graph, params)
    prepared = [_prepared_instances(t, params) for t in trips]
    bounds = [element_bounds(p) for p in prepared]
    types = [[inst.type for inst in t.instances] for t in trips]
    marks = [
        trip_landmarks(t, dash_sightings[k] if dash_sightings else None)
        if params.landmarks
        else Landmarks.empty()
        for k, t in enumerate(trips)
    ]
    submaps: list[Submap] = []
    for circle, mem in zip(circles, members, strict=False):
        for k in np.unique(graph.trip_index[mem]):
            nodes = mem[graph.trip_index[mem] == k]
            runs = np.split(nodes, np.flatnonzero(np.diff(nodes) > 1) + 1)
            tr = trips[int(k)]
            for run in runs:
                frames = graph.frame_index[run]
                if (
                    arclength_m(tr.poses_xyyaw_world[frames[0] : frames[-1] + 1, :2])[-1]
                    < params.min_submap_path_m
                ):
                    continue
                near = run[
                    np.argmin(np.linalg.norm(graph.positions_xy[run] - circle.centre_xy_world, axis=1))
                ]
                anchor = int(graph.frame_index[near])
                pose = tr.poses_xyyaw_world[anchor].copy()
                lo, hi = int(frames[0]), int(frames[-1])
                inv = se2.inverse(pose)
                elems = []
                for i, pts, closed in clip_elements_to_disk(
                    prepared[k],
                    types[k],
                    circle.centre_xy_world,
                    circle.radius_m,
                    params.min_element_length_m,
                    bounds[k],
                ):
                    inst = tr.instances[i]
                    if inst.last_frame > inst.first_frame and (inst.last_frame < lo or inst.first_frame > hi):
                        continue  # not seen while in this circle
                    elems.append(SubmapElement(inst.type, se2.transform_points(inv, pts), i, closed))
                lm = marks[k]
                sel = (
                    (np.linalg.norm(lm.points_xy - circle.centre_xy_world, axis=1) <= circle.radius_m)
                    & (lm.last_frame >= lo)
                    & (lm.first_frame <= hi)
                )
                c, s_ = np.cos(pose[2]), np.sin(pose[2])
                submaps.append(
                    Submap(
                        len(submaps),
                        circle.circle_id,
                        int(k),
                        tr.trip.key,
                        anchor,
                        lo,
                        hi,
                        pose,
                        _limit(elems, params.max_elements_per_submap),
                        se2.transform_points(inv, lm.points_xy[sel]),
                        lm.direction_xy[sel] @ np.array([[c, -s_], [s_, c]]),
                        lm.count[sel],
                        white_world_T_submap=(
                            None
                            if tr.white_poses_xyyaw_world is None
                            else tr.white_poses_xyyaw_world[anchor].copy()
                        ),
                    )
                )
    return circles, submaps


def reduce_prior_map(
    features: Sequence[MapFeature],
    trips: Sequence[TripReconstruction],
    params: AlignmentParams,
    duplicate_m: float = DUPLICATE_M,
) -> tuple[MapFeature, ...]:
    """The part of a pre-built map the new trips can touch, with duplicates removed: features
    outside the trips' bounding box (plus a circle radius and a GNSS margin) are dropped, and
    the parts of a feature lying within ``duplicate_m`` of a longer kept feature of the same
    type are cut away. A map handed over unfused (every earlier trip's aligned instances) then
    matches like a fused one, and the cost of aligning a trip hardly grows with the number of
    trips that built the map."""
    xy = np.vstack([t.poses_xyyaw_world[:, :2] for t in trips])
    margin = params.submap_radius_m + 2 * params.max_prealign_shift_m
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    cand = []
    for f in features:
        pts = resample_polyline(f.points_xy_world, params.element_resample_m, f.type.is_polygon)
        if len(pts) and not (np.any(pts.max(axis=0) < lo) or np.any(pts.min(axis=0) > hi)):
            cand.append((f, pts))
    cand.sort(key=lambda fp: -arclength_m(fp[1])[-1] if len(fp[1]) > 1 else 0.0)
    kept: list[MapFeature] = []
    trees: dict[ElementType, list] = {}
    for f, pts in cand:
        covered = np.zeros(len(pts), bool)
        for tree in trees.get(f.type, []):
            covered |= tree.query(pts, distance_upper_bound=duplicate_m)[0] < duplicate_m
        if f.type.is_polygon:
            if covered.mean() > 0.5:
                continue
            runs = [pts]
        else:
            runs = [
                pts[r]
                for r in np.split(np.arange(len(pts)), np.flatnonzero(np.diff(covered.astype(int))) + 1)
                if not covered[r[0]]
                and len(r) >= 2
                and arclength_m(pts[r])[-1] >= params.min_element_length_m
            ]
        for r in runs:
            kept.append(MapFeature(f.type, r, f.style, f.feature_id, f.properties))
            trees.setdefault(f.type, []).append(cKDTree(r))
    return tuple(kept)


def prior_patches(
    circles: Sequence[Circle], features: Sequence[MapFeature], params: AlignmentParams, first_id: int
) -> list[Submap]:
    """The pre-built map's elements inside each circle, as a sub-map anchored at the circle
    centre (``trip_index = -1``); circles with fewer than two map elements get none."""
    prepared = [
        (
            resample_polyline(f.points_xy_world, params.element_resample_m, f.type.is_polygon),
            f.type.is_polygon,
        )
        for f in features
    ]
    types = [f.type for f in features]
    bounds = element_bounds(prepared)
    out: list[Submap] = []
    for c in circles:
        pose = np.array([c.centre_xy_world[0], c.centre_xy_world[1], c.heading_rad])
        inv = se2.inverse(pose)
        elems = [
            SubmapElement(types[i], se2.transform_points(inv, pts), i, closed)
            for i, pts, closed in clip_elements_to_disk(
                prepared, types, c.centre_xy_world, c.radius_m, params.min_element_length_m, bounds
            )
        ]
        if len(elems) >= 2:
            out.append(
                Submap(
                    first_id + len(out),
                    c.circle_id,
                    -1,
                    "<prior>",
                    -1,
                    -1,
                    -1,
                    pose,
                    _limit(elems, params.max_elements_per_submap),
                )
            )
    return out


def submap_pairs(submaps: Sequence[Submap], params: AlignmentParams) -> list[tuple[int, int]]:
    """P_sub-sub and P_sub-pre: ``(i, j)`` sub-map ids, ``i`` the reference (prior patch first)."""
    by_circle: dict[int, list[Submap]] = {}
    for s in submaps:
        by_circle.setdefault(s.circle_id, []).append(s)
    pairs = []
    for group in by_circle.values():
        group.sort(key=lambda s: (s.trip_index, s.anchor_frame))
        prior = [s for s in group if s.is_prior]
        trips_ = [s for s in group if not s.is_prior]
        for p in prior:
            pairs += [(p.submap_id, s.submap_id) for s in trips_]
        for a, s in enumerate(trips_):
            partners = [t for t in trips_[a + 1 :] if t.trip_index != s.trip_index][
                : params.max_partners_per_submap
            ]
            pairs += [(s.submap_id, t.submap_id) for t in partners]
    return pairs
