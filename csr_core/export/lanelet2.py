"""Lanelet2 export: lanelets from the lane graph, bounded by the map's dividers and boundaries.

``build_lanelet2_map`` reads like its recipe:

1. lanes: the lane graph of the centrelines (``csr_core.topology.lane_graph``), its dead ends
   linked to the open starts ahead (``junction_bridges``: connector centrelines across junctions,
   shared ends across tile seams), each lane sampled every ``SAMPLE_STEP_M`` along its
   direction of travel;
2. bound candidates: every lane divider and road boundary, sampled densely;
3. sides: per lane sample, the nearest candidate beside it on each side (parallel within
   ``BOUND_MAX_ANGLE_RAD``, ``BOUND_MIN_OFFSET_M``..``BOUND_MAX_OFFSET_M`` away);
4. runs: a lane is cut where its (left, right) pair changes (runs shorter than ``MIN_RUN_M``
   fold into a neighbour); each run becomes one lanelet with one way per bound;
5. nodes: the point where a run ends on a candidate is a *station* of that candidate, shared
   by every run ending there (within ``STATION_SNAP_M``), so neighbouring lanes bounded by one
   divider get the very same way; the run ends of lanes joined in the lane graph are merged
   (union-find, refused beyond ``JOIN_M``), so a successor's bounds start at the nodes where
   its predecessor's end and routing sees the link;
6. gaps: a side without paint gets a ``type=virtual`` bound between its merged end points
   (as Lanelet2 maps draw junction interiors); a run with no paint on either side and no
   painted neighbour at any end, an implausible width or a bound on the wrong side is skipped
   and counted by reason in the report.

Stop lines become ``stop_line`` ways, crosswalks ``subtype=crosswalk`` lanelets bounded by
the long sides of their minimum rotated rectangle, road markings closed ``area=yes`` ways.
No regulatory elements: the map knows where a stop line is, not whether a sign or a light
governs it. Coordinates: the world plane of ``frame`` (metres) in, lon/lat out.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from csr_core.errors import CsrError
from csr_core.export.junction_bridges import BRIDGE_ID_PREFIX, BridgeParams, bridge_lane_graph
from csr_core.geo import LocalFrame
from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology.fusion import arclength
from csr_core.topology.lane_graph import build_lane_graph
from csr_core.topology.params import TopologyParams
from csr_core.types import DividerStyle, ElementType, MapFeature

log = logging.getLogger(__name__)

LEFT, RIGHT = 0, 1
NO_BOUND = -1
PRIO_PAINT, PRIO_ESTIMATED, PRIO_DEFAULT = 0, 1, 2  # how a point's position is known, best first
TWO_WAY = "two-way"  # a run written as the other direction of a one_way=no lanelet
DUPLICATE = "duplicate of another lane"  # a run with the very bounds of a lanelet already written

# lane_divider style -> Lanelet2 line_thin subtype (unknown: solid, the conservative reading)
DIVIDER_SUBTYPE = {
    DividerStyle.SOLID: "solid",
    DividerStyle.DASHED: "dashed",
    DividerStyle.DOUBLE: "solid_solid",
    DividerStyle.UNKNOWN: "solid",
}


class ExportError(CsrError):
    """The export cannot be produced (no features, a degenerate input)."""


@dataclass(frozen=True, slots=True)
class Lanelet2Params:
    location: str = "urban"  # Lanelet2 ``location`` of road lanelets (urban / nonurban)
    SAMPLE_STEP_M: float = 1.0  # lane samples
    CANDIDATE_STEP_M: float = 0.5  # bound candidate samples
    BOUND_MIN_OFFSET_M: float = 0.5  # a bound lies at least this far beside the centreline
    BOUND_MAX_OFFSET_M: float = 4.0  # ... and at most this (half a wide lane plus a shoulder)
    BOUND_MAX_ANGLE_RAD: float = math.radians(30.0)  # bound tangent vs lane tangent
    MIN_RUN_M: float = 3.0  # shorter stretches of one (left, right) pair fold into a neighbour
    STATION_SNAP_M: float = 0.75  # run ends on one candidate closer than this share a node
    JOIN_M: float = 1.0  # painted end points of linked lanes farther apart across the lane are not
    # merged (along it: up to the lane graph's CONNECT_M)
    ESTIMATE_REACH_M: float = 15.0  # a measured offset this close along the lane estimates a gap
    DEFAULT_HALF_WIDTH_M: float = 1.75  # half lane width where nothing was measured
    MIN_WIDTH_M: float = 1.5  # plausible lanelet width at its ends
    MAX_WIDTH_M: float = 8.0
    VIRTUAL_STEP_M: float = 2.0  # vertex spacing of virtual bounds
    STOP_LINE_REACH_M: float = 3.0  # a lanelet ending this close to a stop line (or crossing it) stops there
    STOP_LINE_MIN_ANGLE_RAD: float = math.radians(
        45.0
    )  # ... if its lane meets the line at least this steeply
    NODE_MERGE_M: float = 0.05  # nodes closer than this are one (Lanelet2's points_too_close limit)
    # lane graph: short centrelines are lanes here (junction pieces of a real map), not fragments
    topology: TopologyParams = field(default_factory=lambda: TopologyParams(LANE_MIN_LENGTH_M=1.5))
    # connector centrelines from dead ends to open starts (None: the lane graph as the map gives it)
    bridges: BridgeParams | None = field(default_factory=BridgeParams)


DEFAULT = Lanelet2Params()


@dataclass(frozen=True, slots=True)
class OsmWay:
    way_id: int
    node_ids: tuple[int, ...]
    tags: tuple[tuple[str, str], ...]


@dataclass(frozen=True, slots=True)
class OsmRelation:
    relation_id: int
    members: tuple[tuple[str, int, str], ...]  # (member type, ref, role)
    tags: tuple[tuple[str, str], ...]


@dataclass(frozen=True, slots=True)
class ExportReport:
    """What was written and what was left out, with reasons (counts)."""

    lanes: int  # lane graph nodes
    lanelets: int  # road lanelets written
    lanelets_with_virtual_bound: int
    two_way_lanelets: int  # one_way=no: two lanes of opposite direction with the same bounds
    lanes_skipped: int  # lanes none of whose runs could be written
    runs_skipped: dict[str, int]  # reason -> runs (would-be lanelets) not written
    successor_links: int  # lane graph successor edges between written lanelets
    successor_links_joined: int  # ... whose bounds share the end/start nodes
    bridges: int  # connector centrelines added from dead ends to open starts (junction_bridges)
    seams: int  # dead ends linked to an open start within the seam tolerance (junction_bridges)
    bridge_runs_skipped: int  # runs of bridges among runs_skipped (no plausible bounds in the junction)
    centerlines_not_lanes: int  # centreline features too short to be lanes
    crosswalks: int
    stop_lines: int
    stop_lines_governing: int  # stop lines whose regulatory element a lanelet references
    regulatory_elements: int
    nodes_merged: int  # nodes closer than NODE_MERGE_M to another, written as one
    road_markings: int
    lines_unused: int  # dividers/boundaries bounding no lanelet, written as plain ways
    nodes: int
    ways: int

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__slots__}  # type: ignore[attr-defined]


@dataclass(frozen=True, slots=True)
class Lanelet2Map:
    """Nodes (``lonlat_deg (N, 2)``, ``xy_world (N, 2)`` in ``frame``; node ``k`` has id
    ``node_ids[k]``), ways and relations with ids unique across all three."""

    frame: LocalFrame
    node_ids: np.ndarray  # (N,) int
    lonlat_deg: np.ndarray  # (N, 2)
    xy_world: np.ndarray  # (N, 2)
    sigma_m: np.ndarray  # (N,) 1-sigma position uncertainty of the element a node lies on (NaN: unknown)
    ways: tuple[OsmWay, ...]
    relations: tuple[OsmRelation, ...]
    report: ExportReport
    sigma_abs_m: np.ndarray | None = (
        None  # (N,) the element's absolute 1 sigma, ``sigma_abs_m`` (NaN: unknown)
    )


# --- points with union-find ------------------------------------------------------------------


class _Points:
    """Candidate nodes. Union merges points that must be one node; a set's position is the
    mean of its best-known members (paint before estimated before default)."""

    def __init__(self) -> None:
        self.xy: list[np.ndarray] = []
        self.prio: list[int] = []
        self.parent: list[int] = []
        self.anchor: list[np.ndarray | None] = []  # per root: a painted member's position
        # (relative, absolute) 1-sigma position uncertainty of the source element (NaN: unknown)
        self.sigma_m: list[tuple[float, float]] = []

    def add(self, xy: np.ndarray, prio: int, sigma_m: tuple[float, float] = (math.nan, math.nan)) -> int:
        self.xy.append(np.asarray(xy, float))
        self.prio.append(prio)
        self.sigma_m.append(sigma_m)
        self.parent.append(len(self.parent))
        self.anchor.append(self.xy[-1] if prio == PRIO_PAINT else None)
        return len(self.parent) - 1

    def find(self, i: int) -> int:
        root = i
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[i] != root:
            self.parent[i], i = root, self.parent[i]
        return root

    def union(self, a: int, b: int, join_m: float, along_m: float, dir_xy: np.ndarray) -> bool:
        """Merge the sets of ``a`` and ``b``, unless both hold paint whose positions differ by
        more than ``join_m`` across ``dir_xy`` (the lane direction) or ``along_m`` along it:
        lanes linked over a short longitudinal gap join, lanes side by side do not."""
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return True
        pa, pb = self.anchor[ra], self.anchor[rb]
        if pa is not None and pb is not None:
            d = pb - pa
            if abs(float(dir_xy[0] * d[1] - dir_xy[1] * d[0])) > join_m or abs(float(dir_xy @ d)) > along_m:
                return False
        self.parent[rb] = ra
        if pa is None:
            self.anchor[ra] = pb
        return True

    def resolve(self) -> tuple[np.ndarray, np.ndarray]:
        """Per point: its root, and per root the resolved position ``(P, 2)`` and best priority."""
        roots = np.array([self.find(i) for i in range(len(self.parent))], int)
        xy = np.array(self.xy).reshape(-1, 2)
        prio = np.array(self.prio, int)
        best = np.full(len(roots), 99)
        np.minimum.at(best, roots, prio)
        keep = prio == best[roots]
        pos = np.zeros_like(xy)
        count = np.zeros(len(roots))
        np.add.at(pos, roots[keep], xy[keep])
        np.add.at(count, roots[keep], 1.0)
        pos[count > 0] /= count[count > 0, None]
        sig = np.array(self.sigma_m, float).reshape(-1, 2)
        self.root_sigma_m = np.full((len(roots), 2), np.nan)
        for c in range(2):  # the mean of the best-known members' sigmas, relative and absolute
            known = keep & np.isfinite(sig[:, c])
            sig_sum, sig_n = np.zeros(len(roots)), np.zeros(len(roots))
            np.add.at(sig_sum, roots[known], sig[known, c])
            np.add.at(sig_n, roots[known], 1.0)
            self.root_sigma_m[:, c] = np.where(sig_n > 0, sig_sum / np.maximum(sig_n, 1.0), np.nan)
        self.best_prio = best
        return roots, pos


# --- bound candidates ------------------------------------------------------------------------


@dataclass
class _Candidate:
    feature: MapFeature
    xy: np.ndarray  # (M, 2) vertices
    s_vertex: np.ndarray  # (M,)
    line: shapely.LineString
    stations: list[tuple[float, int]] = field(default_factory=list)  # (s, point index)
    vertex_points: dict[int, int] = field(default_factory=dict)  # vertex index -> point index
    used: bool = False

    @property
    def tags(self) -> tuple[tuple[str, str], ...]:
        f = self.feature
        if f.type == ElementType.ROAD_BOUNDARY:
            tags = [("type", "road_border")]
        else:
            style = f.style or DividerStyle.UNKNOWN
            tags = [("type", "line_thin"), ("subtype", DIVIDER_SUBTYPE[style])]
            if style == DividerStyle.UNKNOWN:
                tags.append(("csr:style", "unknown"))
        if f.feature_id:
            tags.append(("csr:feature_id", f.feature_id))
        return (*tags, *provenance_tags(f.properties))

    @property
    def sigma_m(self) -> tuple[float, float]:
        return feature_sigmas_m(self.feature.properties)

    def station(self, points: _Points, xy: np.ndarray, snap_m: float) -> tuple[int, float]:
        """The node where ``xy`` projects onto this line (an existing one within ``snap_m``)."""
        s = float(self.line.project(shapely.Point(float(xy[0]), float(xy[1]))))
        for s_known, idx in self.stations:
            if abs(s_known - s) <= snap_m:
                return idx, s_known
        foot = self.line.interpolate(s)
        idx = points.add(np.array([foot.x, foot.y]), PRIO_PAINT, self.sigma_m)
        self.stations.append((s, idx))
        return idx, s

    def vertex_point(self, points: _Points, k: int) -> int:
        if k not in self.vertex_points:
            self.vertex_points[k] = points.add(self.xy[k], PRIO_PAINT, self.sigma_m)
        return self.vertex_points[k]

    def between(self, points: _Points, s_a: float, s_b: float, margin_m: float = 0.3) -> list[int]:
        """Vertex points strictly between arclengths ``s_a`` and ``s_b``, in that order."""
        lo, hi = min(s_a, s_b) + margin_m, max(s_a, s_b) - margin_m
        ks = [k for k in np.flatnonzero((self.s_vertex > lo) & (self.s_vertex < hi)).tolist()]
        if s_b < s_a:
            ks.reverse()
        return [self.vertex_point(points, k) for k in ks]


def feature_sigma_m(properties: dict) -> float:
    """The element's 1-sigma position uncertainty (metres; the fused map's ``uncertainty_m``),
    NaN where the map gives none (a truth map)."""
    try:
        return float(properties.get("uncertainty_m", math.nan))
    except (TypeError, ValueError):
        return math.nan


def feature_sigmas_m(properties: dict) -> tuple[float, float]:
    """The element's relative (``uncertainty_m``) and absolute (``sigma_abs_m``) 1 sigma, metres;
    NaN where the map gives none."""
    try:
        absolute = float(properties.get("sigma_abs_m", math.nan))
    except (TypeError, ValueError):
        absolute = math.nan
    return feature_sigma_m(properties), absolute


def provenance_tags(properties: dict) -> tuple[tuple[str, str], ...]:
    """``csr:trips`` (trips that saw the element: ``support_trips``) and ``csr:version`` (the map
    version that made it: ``map_version``, else ``tile_version``), where the map gives them."""
    tags = []
    trips = properties.get("support_trips")
    if isinstance(trips, int | float) and not isinstance(trips, bool):
        tags.append(("csr:trips", str(int(trips))))
    version = properties.get("map_version", properties.get("tile_version"))
    if isinstance(version, int) and not isinstance(version, bool):
        tags.append(("csr:version", str(version)))
    return tuple(tags)


def _candidates(features: Sequence[MapFeature]) -> list[_Candidate]:
    out = []
    for f in features:
        if f.type not in (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY):
            continue
        xy = np.asarray(f.points_xy_world, float)
        if len(xy) >= 2:
            xy = xy[np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-3]]
        if len(xy) < 2 or arclength(xy)[-1] < 0.5:
            continue
        out.append(_Candidate(f, xy, arclength(xy), shapely.LineString(xy)))
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class _CandidateIndex:
    """All candidates sampled every ``CANDIDATE_STEP_M``: points, owner, unit tangents, KD-tree."""

    xy: np.ndarray  # (D, 2)
    owner: np.ndarray  # (D,)
    tan: np.ndarray  # (D, 2)
    tree: cKDTree | None

    @classmethod
    def of(cls, cands: list[_Candidate], step_m: float) -> _CandidateIndex:
        if not cands:
            return cls(np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 2)), None)
        dense = [resample_polyline(c.xy, step_m) for c in cands]
        xy = np.concatenate(dense)
        owner = np.repeat(np.arange(len(cands)), [len(d) for d in dense])
        tan = _unit(np.concatenate([np.gradient(d, axis=0) for d in dense]))
        return cls(xy, owner, tan, cKDTree(xy))


def _side_labels(
    p_xy: np.ndarray, t_xy: np.ndarray, index: _CandidateIndex, params: Lanelet2Params
) -> tuple[np.ndarray, np.ndarray]:
    """Per lane sample and side (K, 2): the nearest candidate beside it (or NO_BOUND) and its
    signed lateral offset (left positive; NaN where none)."""
    k_n = len(p_xy)
    label = np.full((k_n, 2), NO_BOUND)
    offset = np.full((k_n, 2), np.nan)
    if index.tree is None:
        return label, offset
    hits = index.tree.query_ball_point(p_xy, params.BOUND_MAX_OFFSET_M + params.CANDIDATE_STEP_M)
    k = np.repeat(np.arange(k_n), [len(h) for h in hits])
    if not len(k):
        return label, offset
    h = np.concatenate([np.asarray(x, int) for x in hits])
    n_xy = np.column_stack([-t_xy[:, 1], t_xy[:, 0]])
    rel = index.xy[h] - p_xy[k]
    lat = (n_xy[k] * rel).sum(1)
    along = (t_xy[k] * rel).sum(1)
    ok = (
        (np.abs(along) <= params.CANDIDATE_STEP_M)
        & (np.abs(lat) >= params.BOUND_MIN_OFFSET_M)
        & (np.abs(lat) <= params.BOUND_MAX_OFFSET_M)
        & (np.abs((t_xy[k] * index.tan[h]).sum(1)) >= math.cos(params.BOUND_MAX_ANGLE_RAD))
    )
    k, h, lat = k[ok], h[ok], lat[ok]
    for side, sel in ((LEFT, lat > 0), (RIGHT, lat < 0)):
        ks, hs, ls = k[sel], h[sel], lat[sel]
        order = np.lexsort((np.abs(ls), ks))
        ks, hs, ls = ks[order], hs[order], ls[order]
        first = np.r_[True, ks[1:] != ks[:-1]] if len(ks) else np.zeros(0, bool)
        label[ks[first], side] = index.owner[hs[first]]
        offset[ks[first], side] = ls[first]
    return label, offset


def _fold_short_runs(codes: np.ndarray, s: np.ndarray, min_len_m: float) -> np.ndarray:
    """Relabel runs of equal codes shorter than ``min_len_m`` (arclength ``s``) with the code
    of their longer neighbouring run, shortest first, until none is left."""
    codes = codes.copy()
    while True:
        change = np.flatnonzero(codes[1:] != codes[:-1]) + 1
        if not len(change):
            return codes
        starts, ends = np.r_[0, change], np.r_[change, len(codes)]
        length = s[np.minimum(ends, len(s) - 1)] - s[starts]
        i = int(np.argmin(length))
        if length[i] >= min_len_m:
            return codes
        before = length[i - 1] if i > 0 else -1.0
        after = length[i + 1] if i + 1 < len(starts) else -1.0
        j = i - 1 if before >= after else i + 1
        codes[starts[i] : ends[i]] = codes[starts[j]]


# --- the export ------------------------------------------------------------------------------


@dataclass
class _Run:
    lane: str
    i0: int
    i1: int  # sample indices, inclusive; consecutive runs share the cut sample
    bound: tuple[int, int]  # candidate index per side or NO_BOUND
    ends: list[list[int]] = field(default_factory=lambda: [[-1, -1], [-1, -1]])  # [side][start, end]
    s_ends: list[list[float]] = field(default_factory=lambda: [[0.0, 0.0], [0.0, 0.0]])
    lead: list[int] = field(default_factory=lambda: [-1, -1])  # per side: own start point after a forced one
    skip: str = ""

    def force_start(self, side: int, point: int) -> None:
        """Start this side's bound at ``point`` (the predecessor's end), then go to its own start."""
        self.lead[side] = self.ends[side][0]
        self.ends[side][0] = point


def _estimate_offset(
    side: int, i: int, s: np.ndarray, offset: np.ndarray, params: Lanelet2Params
) -> tuple[float, int]:
    """Offset of ``side`` at sample ``i`` where no bound was found there: the nearest measured
    one within reach on that side, else the other side's mirrored, else the default."""
    sign = 1.0 if side == LEFT else -1.0
    for sd, mirror in ((side, 1.0), (1 - side, -1.0)):
        known = np.flatnonzero(np.isfinite(offset[:, sd]))
        if len(known):
            j = known[np.argmin(np.abs(s[known] - s[i]))]
            if abs(s[j] - s[i]) <= params.ESTIMATE_REACH_M:
                return mirror * float(offset[j, sd]), PRIO_ESTIMATED
    return sign * params.DEFAULT_HALF_WIDTH_M, PRIO_DEFAULT


def _join_tolerances_m(props_a: dict, props_b: dict, params: Lanelet2Params) -> tuple[float, float]:
    """(across, along): how far apart the painted end points of two linked lanes may be and still
    become one node: ``JOIN_M`` / ``CONNECT_M``, or ``SEAM_SIGMAS`` combined 1-sigma
    uncertainties of the two lanes where that is more (ends at a tile seam or a version boundary)."""
    sig = [feature_sigma_m(p) for p in (props_a, props_b)]
    k = params.bridges.SEAM_SIGMAS if params.bridges is not None else 0.0
    seam_m = k * math.hypot(*(x if math.isfinite(x) else 0.0 for x in sig))
    return max(params.JOIN_M, seam_m), max(params.topology.CONNECT_M, seam_m)


def build_lanelet2_map(
    features: Sequence[MapFeature], frame: LocalFrame, params: Lanelet2Params = DEFAULT
) -> Lanelet2Map:
    """Lanelets of the map ``features`` (world plane of ``frame``, metres), see the module doc."""
    lane_graph = build_lane_graph(features, params.topology)
    n_bridges = n_seams = 0
    if params.bridges is not None:
        features, lane_graph, n_bridges, n_seams = bridge_lane_graph(
            features, lane_graph, params.topology, params.bridges
        )
    g = lane_graph.graph
    cands = _candidates(features)
    index = _CandidateIndex.of(cands, params.CANDIDATE_STEP_M)
    points = _Points()
    n_centerlines = sum(1 for f in features if f.type == ElementType.CENTERLINE)
    fids = {a["feature_id"] for _, a in g.nodes(data=True)}
    centre_props = {f.feature_id: f.properties for f in features if f.type == ElementType.CENTERLINE}

    # 1-4. lane samples, sides, runs
    samples: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    runs: dict[str, list[_Run]] = {}
    for lane in g.nodes:
        p = resample_polyline(np.asarray(g.nodes[lane]["points_xy_world"], float), params.SAMPLE_STEP_M)
        if len(p) < 2:
            continue
        t = _unit(np.gradient(p, axis=0))
        s = arclength(p)
        label, offset = _side_labels(p, t, index, params)
        for side in (LEFT, RIGHT):
            label[:, side] = _fold_short_runs(label[:, side], s, params.MIN_RUN_M)
        pair = _fold_short_runs(
            (label[:, LEFT] + 1) * (len(cands) + 1) + label[:, RIGHT] + 1, s, params.MIN_RUN_M
        )
        label = np.column_stack([pair // (len(cands) + 1) - 1, pair % (len(cands) + 1) - 1])
        cut = np.flatnonzero(pair[1:] != pair[:-1]) + 1
        bounds = np.r_[0, cut, len(p) - 1]
        lane_runs = [
            _Run(lane, int(a), int(b), (int(label[a, LEFT]), int(label[a, RIGHT])))
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)
            if b > a
        ]
        samples[lane] = (p, t, s)
        lane_sigma_m = feature_sigmas_m(centre_props.get(g.nodes[lane]["feature_id"], {}))
        # 5. end points: stations on painted sides, estimates elsewhere; runs of a lane joined
        n_xy = np.column_stack([-t[:, 1], t[:, 0]])
        for r in lane_runs:
            for side in (LEFT, RIGHT):
                for e, i in enumerate((r.i0, r.i1)):
                    c = r.bound[side]
                    if c != NO_BOUND:
                        idx, s_c = cands[c].station(points, p[i], params.STATION_SNAP_M)
                        r.s_ends[side][e] = s_c
                    else:
                        o, prio = _estimate_offset(side, i, s, offset, params)
                        idx = points.add(p[i] + o * n_xy[i], prio, lane_sigma_m)
                    r.ends[side][e] = idx
        for prev, nxt in zip(lane_runs[:-1], lane_runs[1:], strict=False):
            for side in (LEFT, RIGHT):
                if not points.union(
                    prev.ends[side][1], nxt.ends[side][0], params.JOIN_M, params.JOIN_M, t[prev.i1]
                ):
                    nxt.force_start(side, prev.ends[side][1])  # the bound steps sideways (paint changes)
        runs[lane] = lane_runs

    # 5. lanes joined in the lane graph share their end / start points
    succ_edges = [
        (u, v) for u, v, kind in g.edges(data="kind") if kind == "successor" and u in runs and v in runs
    ]
    for u, v in succ_edges:
        join_m, along_m = _join_tolerances_m(
            centre_props.get(g.nodes[u]["feature_id"], {}),
            centre_props.get(g.nodes[v]["feature_id"], {}),
            params,
        )
        for side in (LEFT, RIGHT):
            a, b = runs[u][-1].ends[side][1], runs[v][0].ends[side][0]
            if points.union(a, b, join_m, along_m, samples[u][1][-1]):
                continue
            if len(lane_graph.predecessors(v)) == 1 and runs[v][0].lead[side] < 0:
                runs[v][0].force_start(side, a)
            else:
                log.debug(
                    "lanes %s -> %s: %s end points %s and %s too far apart to join",
                    u,
                    v,
                    ("left", "right")[side],
                    np.round(points.xy[a], 2),
                    np.round(points.xy[b], 2),
                )
    roots, pos = points.resolve()

    # 6. skip what cannot be a lanelet
    for lane, lane_runs in runs.items():
        p, t, _ = samples[lane]
        n_xy = np.column_stack([-t[:, 1], t[:, 0]])
        for r in lane_runs:
            end_prio = [points.best_prio[roots[r.ends[sd][e]]] for sd in (LEFT, RIGHT) for e in (0, 1)]
            if r.bound == (NO_BOUND, NO_BOUND) and min(end_prio) == PRIO_DEFAULT:
                r.skip = "no bounds found"
                continue
            for e, i in enumerate((r.i0, r.i1)):
                left, right = pos[roots[r.ends[LEFT][e]]], pos[roots[r.ends[RIGHT][e]]]
                width = float(np.linalg.norm(left - right))
                if not params.MIN_WIDTH_M <= width <= params.MAX_WIDTH_M:
                    r.skip = "implausible width"
                elif float(n_xy[i] @ (left - p[i])) <= 0.0 or float(n_xy[i] @ (right - p[i])) >= 0.0:
                    r.skip = "bound on the wrong side"
            if r.skip:
                continue
            for side in (LEFT, RIGHT):
                c = r.bound[side]
                if c != NO_BOUND and abs(r.s_ends[side][1] - r.s_ends[side][0]) < 0.5:
                    r.bound = (NO_BOUND, r.bound[1]) if side == LEFT else (r.bound[0], NO_BOUND)

    # 7. ways and lanelets
    builder = _OsmBuilder(points, roots, pos)
    n_virtual = n_two_way = 0
    approaches: list[tuple[int, np.ndarray]] = []  # (lanelet relation, its lane samples (K, 2))
    for lane, lane_runs in runs.items():
        p, t, s = samples[lane]
        n_xy = np.column_stack([-t[:, 1], t[:, 0]])
        lane_props = centre_props.get(g.nodes[lane]["feature_id"], {})
        for r in lane_runs:
            if r.skip:
                continue
            bound_ways: list[int | None] = []
            has_virtual = False
            for side in (LEFT, RIGHT):
                a, b = r.ends[side]
                c = r.bound[side]
                if c != NO_BOUND:
                    cand = cands[c]
                    cand.used = True
                    lead = [r.lead[side]] if r.lead[side] >= 0 else []
                    chain = [a, *lead, *cand.between(points, r.s_ends[side][0], r.s_ends[side][1]), b]
                    bound_ways.append(builder.way(chain, cand.tags))
                else:
                    o_a = float(n_xy[r.i0] @ (pos[roots[a]] - p[r.i0]))
                    o_b = float(n_xy[r.i1] @ (pos[roots[b]] - p[r.i1]))
                    step = max(int(round(params.VIRTUAL_STEP_M / params.SAMPLE_STEP_M)), 1)
                    inner = list(range(r.i0 + step, r.i1 - step // 2, step))
                    w = (s[inner] - s[r.i0]) / max(s[r.i1] - s[r.i0], 1e-9)
                    mid = [
                        points.add(
                            p[i] + ((1 - wi) * o_a + wi * o_b) * n_xy[i],
                            PRIO_ESTIMATED,
                            feature_sigmas_m(lane_props),
                        )
                        for i, wi in zip(inner, w, strict=True)
                    ]
                    bound_ways.append(builder.way([a, *mid, b], (("type", "virtual"),)))
                    has_virtual = True
            left_way, right_way = bound_ways
            if left_way is None or right_way is None:
                r.skip = "degenerate bound"
                continue
            if not builder.simple_outline(left_way, right_way):
                r.skip = "bounds cross"
                continue
            status, rel = builder.lanelet(
                left_way,
                right_way,
                (
                    ("type", "lanelet"),
                    ("subtype", "road"),
                    ("location", params.location),
                    ("one_way", "yes"),
                    ("csr:lane", lane),
                    ("csr:centerline_id", g.nodes[lane]["feature_id"]),
                    *provenance_tags(lane_props),
                ),
            )
            if status == "":
                n_virtual += has_virtual
                approaches.append((rel, p[r.i0 : r.i1 + 1]))
            else:
                r.skip = status
                n_two_way += status == TWO_WAY

    # crosswalks, stop lines, road markings, unused lines
    n_cross = n_stop = n_mark = n_stop_attached = 0
    for f in features:
        tags_id = (("csr:feature_id", f.feature_id),) if f.feature_id else ()
        tags_id = (*tags_id, *provenance_tags(f.properties))
        sigma_m = feature_sigmas_m(f.properties)
        xy = np.asarray(f.points_xy_world, float)
        if f.type == ElementType.CROSSWALK and len(xy) >= 3:
            sides = _crosswalk_sides(xy)
            if sides is None:
                continue
            cw = [
                builder.way(
                    [points.add(q, PRIO_PAINT, sigma_m) for q in side], (("type", "zebra_marking"), *tags_id)
                )
                for side in sides
            ]
            if cw[0] is not None and cw[1] is not None:
                builder.lanelet(
                    cw[0],
                    cw[1],
                    (
                        ("type", "lanelet"),
                        ("subtype", "crosswalk"),
                        ("location", params.location),
                        ("one_way", "no"),
                        ("participant:pedestrian", "yes"),
                        *tags_id,
                    ),
                )
                n_cross += 1
        elif f.type == ElementType.STOP_LINE and len(xy) >= 2:
            way = builder.way(
                [points.add(q, PRIO_PAINT, sigma_m) for q in xy], (("type", "stop_line"), *tags_id)
            )
            if way is not None:
                n_stop += 1
                yielding = _lanelets_at_stop_line(xy, approaches, params)
                builder.regulatory_element(
                    (
                        ("type", "regulatory_element"),
                        ("subtype", "traffic_sign"),
                        ("sign_type", "stop_line"),
                        *tags_id,
                    ),
                    (("way", way, "ref_line"),),
                    lanelets=yielding,
                )
                n_stop_attached += bool(yielding)
        elif f.type == ElementType.ROAD_MARKING and len(xy) >= 3:
            ids = [points.add(q, PRIO_PAINT, sigma_m) for q in xy]
            if builder.way([*ids, ids[0]], (("type", "road_marking"), ("area", "yes"), *tags_id)) is not None:
                n_mark += 1
    n_unused = 0
    for cand in cands:
        if not cand.used:
            builder.way([cand.vertex_point(points, k) for k in range(len(cand.xy))], cand.tags)
            n_unused += 1

    # report
    written = {r.lane: r for lane_runs in runs.values() for r in lane_runs if r.skip in ("", TWO_WAY)}
    skipped = Counter(r.skip for lane_runs in runs.values() for r in lane_runs if r.skip not in ("", TWO_WAY))
    lanes_skipped = sum(1 for lane in g.nodes if lane not in written)
    joined = n_links = 0
    for u, v in succ_edges:
        ru, rv = runs[u][-1], runs[v][0]
        if ru.skip not in ("", TWO_WAY) or rv.skip not in ("", TWO_WAY):
            continue
        n_links += 1
        joined += all(roots[ru.ends[sd][1]] == roots[rv.ends[sd][0]] for sd in (LEFT, RIGHT))
    node_ids, xy_world, node_sigma_m, ways, relations, n_merged = builder.finish(params.NODE_MERGE_M)
    report = ExportReport(
        lanes=g.number_of_nodes(),
        lanelets=sum(1 for lane_runs in runs.values() for r in lane_runs if not r.skip),
        lanelets_with_virtual_bound=int(n_virtual),
        two_way_lanelets=n_two_way,
        lanes_skipped=lanes_skipped,
        runs_skipped=dict(sorted(skipped.items())),
        successor_links=n_links,
        successor_links_joined=int(joined),
        bridges=n_bridges,
        seams=n_seams,
        bridge_runs_skipped=sum(
            1
            for lane_runs in runs.values()
            for r in lane_runs
            if r.skip not in ("", TWO_WAY) and g.nodes[r.lane]["feature_id"].startswith(BRIDGE_ID_PREFIX)
        ),
        centerlines_not_lanes=n_centerlines - len(fids),
        crosswalks=n_cross,
        stop_lines=n_stop,
        stop_lines_governing=n_stop_attached,
        regulatory_elements=sum(1 for r in relations if ("type", "regulatory_element") in r.tags),
        nodes_merged=n_merged,
        road_markings=n_mark,
        lines_unused=n_unused,
        nodes=len(node_ids),
        ways=len(ways),
    )
    log.info("lanelet2 export: %s", report.as_dict())
    return Lanelet2Map(
        frame,
        node_ids,
        frame.to_lonlat(xy_world) if len(xy_world) else np.zeros((0, 2)),
        xy_world,
        node_sigma_m[:, 0],
        ways,
        relations,
        report,
        node_sigma_m[:, 1],
    )


def _lanelets_at_stop_line(
    stop_xy: np.ndarray, approaches: Sequence[tuple[int, np.ndarray]], params: Lanelet2Params
) -> list[int]:
    """Road lanelets (relation indices) a stop line governs: their lane ends within
    ``STOP_LINE_REACH_M`` of it, or crosses it, at an angle above ``STOP_LINE_MIN_ANGLE_RAD``."""
    line = shapely.LineString(stop_xy)
    d_stop = stop_xy[-1] - stop_xy[0]
    d_stop = d_stop / max(float(np.linalg.norm(d_stop)), 1e-9)
    out = []
    for rel, lane_xy in approaches:
        if len(lane_xy) < 2:
            continue
        end = shapely.Point(float(lane_xy[-1, 0]), float(lane_xy[-1, 1]))
        lane_line = shapely.LineString(lane_xy)
        if line.distance(end) > params.STOP_LINE_REACH_M and not line.intersects(lane_line):
            continue
        k = int(np.argmin(np.linalg.norm(lane_xy - np.asarray(line.centroid.coords[0]), axis=1)))
        k = min(k, len(lane_xy) - 2)
        t = lane_xy[k + 1] - lane_xy[k]
        t = t / max(float(np.linalg.norm(t)), 1e-9)
        if abs(float(t @ d_stop)) <= math.cos(params.STOP_LINE_MIN_ANGLE_RAD):
            out.append(rel)
    return out


def _crosswalk_sides(outline_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The two long sides (2, 2) of the minimum rotated rectangle of a polygon, same direction:
    a pedestrian walks between them."""
    rect = shapely.Polygon(outline_xy).minimum_rotated_rectangle
    if rect.geom_type != "Polygon" or rect.area < 0.5:
        return None
    c = np.asarray(rect.exterior.coords)[:4]
    if np.linalg.norm(c[1] - c[0]) >= np.linalg.norm(c[2] - c[1]):
        return c[[0, 1]], c[[3, 2]]
    return c[[1, 2]], c[[0, 3]]


class _OsmBuilder:
    """Ways (deduplicated: one way per node sequence, either direction) and relations (lanelets,
    regulatory elements) over the resolved points; nodes closer than ``merge_m`` become one and
    ids are assigned in ``finish``."""

    def __init__(self, points: _Points, roots: np.ndarray, pos: np.ndarray) -> None:
        self.points, self.roots, self.pos = points, roots, pos
        self.ways: list[tuple[tuple[int, ...], tuple[tuple[str, str], ...]]] = []
        self.by_nodes: dict[tuple[int, ...], int] = {}
        # members: (member type "way" / "relation", way or relation index, role)
        self.relations: list[tuple[list[tuple[str, int, str]], tuple[tuple[str, str], ...]]] = []
        self.by_bounds: dict[tuple[int, int], int] = {}

    def _root(self, i: int) -> int:
        if i >= len(self.roots):  # added after resolve: its own root and position
            return i
        return int(self.roots[i])

    def _xy(self, n: int) -> np.ndarray:
        return self.pos[n] if n < len(self.pos) else self.points.xy[n]

    def _sigma_m(self, n: int) -> np.ndarray:
        """(2,) the node's relative and absolute 1 sigma."""
        return np.asarray(self.points.root_sigma_m[n] if n < len(self.pos) else self.points.sigma_m[n], float)

    def way(self, chain: Sequence[int], tags: tuple[tuple[str, str], ...]) -> int | None:
        nodes: list[int] = []
        for i in chain:
            r = self._root(i)
            if not nodes or nodes[-1] != r:
                nodes.append(r)
        if len(set(nodes)) < 2:
            return None
        key = tuple(nodes)
        for k in (key, key[::-1]):
            if k in self.by_nodes:
                return self.by_nodes[k]
        self.ways.append((key, tags))
        self.by_nodes[key] = len(self.ways) - 1
        return len(self.ways) - 1

    def xy_of(self, way: int) -> np.ndarray:
        return np.array([self._xy(n) for n in self.ways[way][0]])

    def simple_outline(self, left: int, right: int) -> bool:
        """Left and right bound enclose a simple polygon (a stored way may run either way)."""
        a, b = self.xy_of(left), self.xy_of(right)
        if np.linalg.norm(a[0] - b[-1]) + np.linalg.norm(a[-1] - b[0]) < np.linalg.norm(
            a[0] - b[0]
        ) + np.linalg.norm(a[-1] - b[-1]):
            b = b[::-1]
        return bool(shapely.Polygon(np.vstack([a, b[::-1]])).is_valid)

    def lanelet(self, left: int, right: int, tags: tuple[tuple[str, str], ...]) -> tuple[str, int]:
        """Add a lanelet: ``("", index)``; ``(TWO_WAY, other)`` if it is the other direction of one
        already added (same ways, sides swapped: a two-way lane), which then becomes
        ``one_way=no``; ``(DUPLICATE, other)`` if one with the same two bounds exists (two
        centrelines of one lane)."""
        if (left, right) in self.by_bounds:
            return DUPLICATE, self.by_bounds[(left, right)]
        other = self.by_bounds.get((right, left))
        if other is not None:
            members, old = self.relations[other]
            self.relations[other] = (members, tuple((k, "no" if k == "one_way" else v) for k, v in old))
            return TWO_WAY, other
        self.by_bounds[(left, right)] = len(self.relations)
        self.relations.append(([("way", left, "left"), ("way", right, "right")], tags))
        return "", len(self.relations) - 1

    def regulatory_element(
        self,
        tags: tuple[tuple[str, str], ...],
        members: tuple[tuple[str, int, str], ...],
        lanelets: Sequence[int] = (),
    ) -> int:
        """Add a regulatory element; each of ``lanelets`` (relation indices) references it."""
        self.relations.append((list(members), tags))
        k = len(self.relations) - 1
        for ll in lanelets:
            self.relations[ll][0].append(("relation", k, "regulatory_element"))
        return k

    def _merge_close(self, used: list[int], merge_m: float) -> dict[int, int]:
        """Point -> the point standing for it: points closer than ``merge_m`` (transitively) are
        one, at their mean position (written back to ``pos`` / ``points.xy``)."""
        if len(used) < 2 or merge_m <= 0:
            return {n: n for n in used}
        xy = np.array([self._xy(n) for n in used])
        pairs = cKDTree(xy).query_pairs(merge_m, output_type="ndarray")
        if not len(pairs):
            return {n: n for n in used}
        adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(used), len(used)))
        _, comp = connected_components(adj, directed=False)
        first: dict[int, int] = {}
        for k, c in enumerate(comp.tolist()):
            first.setdefault(c, used[k])
        for c in np.unique(comp[pairs[:, 0]]).tolist():
            members = np.flatnonzero(comp == c)
            rep, mean = first[c], xy[members].mean(axis=0)
            if rep < len(self.pos):
                self.pos[rep] = mean
            else:
                self.points.xy[rep] = mean
        return {n: first[c] for n, c in zip(used, comp.tolist(), strict=True)}

    def finish(
        self, merge_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[OsmWay, ...], tuple[OsmRelation, ...], int]:
        """(node ids, node xy (N, 2), node sigmas (N, 2): relative and absolute, ways, relations,
        nodes merged). A way
        shorter than ``merge_m`` disappears, and with it a lanelet it bounds or a regulatory
        element with no member left."""
        used = sorted({n for nodes, _ in self.ways for n in nodes})
        merged = self._merge_close(used, merge_m)
        way_nodes: list[tuple[int, ...] | None] = []
        for nodes, _ in self.ways:
            chain: list[int] = []
            for n in nodes:
                m = merged[n]
                if not chain or chain[-1] != m:
                    chain.append(m)
            way_nodes.append(tuple(chain) if len(set(chain)) >= 2 else None)
        kept = sorted({n for seq in way_nodes if seq is not None for n in seq})
        xy = np.array([self._xy(n) for n in kept]).reshape(-1, 2)
        sigma = np.array([self._sigma_m(n) for n in kept], float).reshape(-1, 2)
        node_id = {n: k + 1 for k, n in enumerate(kept)}
        way_id: dict[int, int] = {}
        ways: list[OsmWay] = []
        for w, (seq, (_, tags)) in enumerate(zip(way_nodes, self.ways, strict=True)):
            if seq is not None:
                way_id[w] = len(kept) + 1 + len(ways)
                ways.append(OsmWay(way_id[w], tuple(node_id[n] for n in seq), tags))
        # relations: a lanelet without both bounds goes, then members referring to gone relations
        alive = [
            all(ref in way_id for t, ref, _ in members if t == "way")
            and any(t == "way" for t, _, _ in members)
            for members, _ in self.relations
        ]
        rel_base = len(kept) + 1 + len(ways)
        rel_id: dict[int, int] = {}
        for k, ok in enumerate(alive):
            if ok:
                rel_id[k] = rel_base + len(rel_id)
        relations = tuple(
            OsmRelation(
                rel_id[k],
                tuple(
                    (t, way_id[ref] if t == "way" else rel_id[ref], role)
                    for t, ref, role in members
                    if (t == "way" and ref in way_id) or (t == "relation" and ref in rel_id)
                ),
                tags,
            )
            for k, (members, tags) in enumerate(self.relations)
            if k in rel_id
        )
        return np.arange(1, len(kept) + 1), xy, sigma, tuple(ways), relations, len(used) - len(kept)
