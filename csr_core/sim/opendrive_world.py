"""Simulator worlds from OpenDRIVE maps; ``newmarket``: a suburban network of Newmarket, Ontario.

The map (``data/newmarket/od_newmarket.xodr``, ASAM OpenDRIVE 1.4, MIT, OSM-derived: see the
folder's ``SOURCES.txt``) has 533 roads (99 streets and 434 junction connecting roads) and 68
junctions; its geoReference header is wrong for Ontario, so its coordinates are read as local
metres. The world shifts them so that the centre of the reference lines' bounding box is the
origin and places that origin at 44.0500 N, 79.4600 W (central Newmarket); x east, y north, metres.

File -> truth elements (per lane section, sampled every ``SAMPLE_STEP_M`` along ``s``):
- centrelines: the midline of each driving lane's inner and outer edges, in the direction of
  travel (right-hand traffic: lanes with negative ids follow the reference line, positive ids run
  against it); junction connecting roads included;
- lane dividers: the edge between two adjacent roadway lanes (the reference line when both sides
  have lanes) whose ``roadMark`` (that of the lane nearer the reference line) is painted:
  ``solid`` -> solid, ``broken`` -> dashed, the two-line types -> double, other paint -> unknown;
  ``none`` -> nothing. Road marks change along ``s`` where their ``sOffset`` says;
- road boundaries: on each side of a street, the outer edge of its outermost roadway lane
  (driving, shoulder, border, parking, biking, ...: the inner edge of a sidewalk); a side without
  lanes (a one-way street) has its boundary on the reference line. The outer edge's own road mark
  adds no divider on top of the boundary. Junction connecting roads give no dividers and no
  boundaries (their edges overlap across the junction area; the file paints none there);
- stop lines and crosswalks: none. The file has no objects and no signals, and none are derived.

Lane graph: a node per driving lane and lane section; successors from lane links between
sections, road links (road to road, with their lane links) and junction connections (incoming
lane -> connecting lane, then the connecting road's own link to the outgoing road). A link whose
two lanes both end (or both start) at the touching ends is dropped (counted in the log). A lane
end left unlinked is joined to lane starts within ``GAP_JOIN_TOL_M`` heading the same way (within
45 degrees). Dead ends get hidden U-turn connectors to the opposite lane (``add_turnarounds``),
so that routes continue; in this file they are the six connecting roads whose incoming road
(ids 2 and 8) lies outside the map, and one street cut at the map's edge.

Where the file's geometry is inconsistent, the world keeps what is written and says so:
- 39 ``planView`` records end short of the next record's start (by up to 64 m, always straight
  ahead: near-zero-curvature arcs written with too small a length). The lane lines are sampled
  by ``s`` and so bridge each gap with a straight segment; this adds 0.67 lane-km to the 31.62
  lane-km that the written road lengths give;
- 33 junction connecting roads (0.05 - 5 m long) miss the road they link to by more than
  ``GAP_JOIN_TOL_M`` (up to 8.6 m); their lanes are rebuilt as cubic Bezier curves from the
  incoming lane's end to the outgoing lane's start.

Speeds: 50 km/h everywhere (Ontario's default limit in built-up areas); the file's speed records
(2.7 - 5.4 "mph") are not plausible limits and are not used.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from csr_core.sim import geometry as geo
from csr_core.sim.opendrive import (
    ContactPoint,
    Lane,
    LaneSection,
    OpenDrive,
    Road,
    lane_edges_t,
    parse_opendrive,
    points_at_t,
    reference_pose,
)
from csr_core.sim.world import SUCCESSOR, World, WorldBuilder
from csr_core.types import DividerStyle, ElementType

log = logging.getLogger(__name__)

DATA_DIR = Path(__file__).resolve().parent / "data" / "newmarket"
NEWMARKET_XODR = DATA_DIR / "od_newmarket.xodr"
NEWMARKET_ORIGIN_LATLON = (44.0500, -79.4600)  # central Newmarket, Ontario
URBAN_SPEED_MPS = 13.9  # 50 km/h
SAMPLE_STEP_M = 0.5
GAP_JOIN_TOL_M = 1.0
TURNAROUND_MAX_GAP_M = 15.0

DRIVING_LANE_TYPES = frozenset({"driving", "entry", "exit", "onRamp", "offRamp", "connectingRamp"})
ROADWAY_LANE_TYPES = DRIVING_LANE_TYPES | {"shoulder", "border", "parking", "stop", "restricted", "biking"}
_MARK_STYLE = {
    "solid": DividerStyle.SOLID,
    "broken": DividerStyle.DASHED,
    "solid solid": DividerStyle.DOUBLE,
    "solid broken": DividerStyle.DOUBLE,
    "broken solid": DividerStyle.DOUBLE,
    "broken broken": DividerStyle.DOUBLE,
}
_NO_PAINT = ("none", "grass", "curb", "edge")


@dataclass(frozen=True, slots=True)
class LaneEnd:
    """One end of a lane: ``at_s_end`` is True for the end at the section's larger ``s``."""

    road_id: str
    section: int
    lane_id: int
    at_s_end: bool

    @property
    def exits(self) -> bool:
        """Traffic leaves the lane here (right-hand traffic: negative ids run along ``s``)."""
        return self.at_s_end == (self.lane_id < 0)


LaneKey = tuple[str, int, int]  # road id, lane section index, lane id


@dataclass(frozen=True, slots=True)
class _LaneGeometry:
    centerline_xy: np.ndarray  # (M, 2) world, direction of travel
    width_m: float
    road_type: str


def _rebuild_short_connectors(
    lanes: dict[LaneKey, _LaneGeometry], links: set[tuple[LaneKey, LaneKey]]
) -> int:
    """Replace the centreline of each junction lane whose start misses its predecessor's end, or
    whose end misses its successor's start, by more than ``GAP_JOIN_TOL_M`` with a cubic Bezier
    from that predecessor's end to that successor's start (one of each; tangents matched).
    Returns how many were rebuilt."""
    preds: dict[LaneKey, list[LaneKey]] = {}
    succs: dict[LaneKey, list[LaneKey]] = {}
    for u, v in links:
        succs.setdefault(u, []).append(v)
        preds.setdefault(v, []).append(u)
    rebuilt = 0
    for key in sorted(lanes):
        lane = lanes[key]
        p, s = preds.get(key, []), succs.get(key, [])
        if lane.road_type != "urban_junction" or len(p) != 1 or len(s) != 1:
            continue
        c_in, c_out, c = lanes[p[0]].centerline_xy, lanes[s[0]].centerline_xy, lane.centerline_xy
        misses = max(np.linalg.norm(c[0] - c_in[-1]), np.linalg.norm(c[-1] - c_out[0])) > GAP_JOIN_TOL_M
        if not misses or np.linalg.norm(c_out[0] - c_in[-1]) < 1.0:
            continue
        path = geo.bezier_cubic(c_in[-1], geo.tangents(c_in)[-1], c_out[0], geo.tangents(c_out)[0], 0.5)
        lanes[key] = _LaneGeometry(path, lane.width_m, lane.road_type)
        rebuilt += 1
    return rebuilt


def _section_s(road: Road, index: int) -> np.ndarray:
    s0, s1 = road.sections[index].s_m, road.section_end_m(index)
    n = max(int(np.ceil((s1 - s0) / SAMPLE_STEP_M)) + 1, 2)
    return np.linspace(s0, s1, n)


def _mark_pieces(lane: Lane, section: LaneSection, s: np.ndarray) -> list[tuple[slice, str]]:
    """Index ranges of ``s`` and the road-mark type in force there (consecutive pieces share a point)."""
    if not lane.road_marks:
        return [(slice(0, len(s)), "none")]
    starts = np.array([m.s_offset_m for m in lane.road_marks]) + section.s_m
    k = np.clip(np.searchsorted(starts, s + 1e-9, side="right") - 1, 0, len(starts) - 1)
    pieces = []
    lo = 0
    for i in range(1, len(s) + 1):
        if i == len(s) or k[i] != k[lo]:
            pieces.append((slice(lo, min(i + 1, len(s))), lane.road_marks[int(k[lo])].type))
            lo = i
    return pieces


def _add_section_paint(builder: WorldBuilder, road: Road, index: int, shift_xy: np.ndarray) -> None:
    """Dividers and boundaries of one lane section of a street (world frame)."""
    section = road.sections[index]
    s = _section_s(road, index)
    edges = lane_edges_t(road, index, s)
    roadway = {ln.lane_id: ln for ln in section.lanes if ln.lane_id != 0 and ln.type in ROADWAY_LANE_TYPES}
    if not any(ln.type in DRIVING_LANE_TYPES for ln in roadway.values()):
        return
    left = sorted(i for i in roadway if i > 0)
    right = sorted((i for i in roadway if i < 0), reverse=True)

    def line(t: np.ndarray) -> np.ndarray:
        return points_at_t(road, s, t) - shift_xy

    # boundaries: outer edge of the outermost roadway lane on each side, else the reference line
    for side in (left, right):
        t = edges[side[-1]][1] if side else edges[0][0]
        builder.add_element(ElementType.ROAD_BOUNDARY, line(t))
    # dividers: the reference line when both sides have lanes, then every inner edge between lanes
    inner_edges: list[Lane] = []
    centre = section.lane(0)
    if left and right and centre is not None:
        inner_edges.append(centre)
    inner_edges += [roadway[i] for i in left[:-1]] + [roadway[i] for i in right[:-1]]
    for lane in inner_edges:
        t = edges[lane.lane_id][1]
        xy = line(t)
        for piece, mark in _mark_pieces(lane, section, s):
            if mark in _NO_PAINT:
                continue
            builder.add_element(
                ElementType.LANE_DIVIDER, xy[piece], _MARK_STYLE.get(mark, DividerStyle.UNKNOWN)
            )


def _junction_end(incoming: Road, junction_id: str, near_xy: np.ndarray) -> bool:
    """Whether ``incoming`` touches the junction at its ``s`` end (else at its start)."""
    at_end = (
        incoming.successor is not None
        and incoming.successor.element_type == "junction"
        and incoming.successor.element_id == junction_id
    )
    at_start = (
        incoming.predecessor is not None
        and incoming.predecessor.element_type == "junction"
        and incoming.predecessor.element_id == junction_id
    )
    if at_end != at_start:
        return at_end
    ends, _ = reference_pose(incoming, np.array([0.0, incoming.length_m]))
    return bool(np.linalg.norm(ends[1] - near_xy) < np.linalg.norm(ends[0] - near_xy))


def _touching_ends(od: OpenDrive) -> set[tuple[LaneEnd, LaneEnd]]:
    """Pairs of lane ends the file links (lane links across sections, road links, junctions)."""
    pairs: set[tuple[LaneEnd, LaneEnd]] = set()

    def add(a: LaneEnd, b: LaneEnd) -> None:
        pairs.add(
            (a, b) if (a.road_id, a.section, a.lane_id) <= (b.road_id, b.section, b.lane_id) else (b, a)
        )

    def section_at(road: Road, cp: ContactPoint | None) -> tuple[int, bool]:
        return (len(road.sections) - 1, True) if cp == ContactPoint.END else (0, False)

    for road in od.roads.values():
        last = len(road.sections) - 1
        for k, section in enumerate(road.sections):
            for lane in section.lanes:
                if lane.lane_id == 0:
                    continue
                if lane.successor_id is not None and k < last:
                    add(
                        LaneEnd(road.road_id, k, lane.lane_id, True),
                        LaneEnd(road.road_id, k + 1, lane.successor_id, False),
                    )
                for link, here_end, linked_id in (
                    (road.successor, True, lane.successor_id),
                    (road.predecessor, False, lane.predecessor_id),
                ):
                    if (k != last if here_end else k != 0) or linked_id is None or link is None:
                        continue
                    if link.element_type != "road" or link.element_id not in od.roads:
                        continue
                    other = od.roads[link.element_id]
                    sec, at_end = section_at(other, link.contact_point)
                    add(
                        LaneEnd(road.road_id, k, lane.lane_id, here_end),
                        LaneEnd(other.road_id, sec, linked_id, at_end),
                    )
    for junction in od.junctions.values():
        for conn in junction.connections:
            incoming, connecting = od.roads.get(conn.incoming_road), od.roads.get(conn.connecting_road)
            if incoming is None or connecting is None:
                continue
            c_sec, c_end = section_at(connecting, conn.contact_point)
            c_xy, _ = reference_pose(connecting, np.array([connecting.length_m if c_end else 0.0]))
            i_end = _junction_end(incoming, junction.junction_id, c_xy[0])
            i_sec = len(incoming.sections) - 1 if i_end else 0
            for from_id, to_id in conn.lane_links:
                add(
                    LaneEnd(incoming.road_id, i_sec, from_id, i_end),
                    LaneEnd(connecting.road_id, c_sec, to_id, c_end),
                )
    return pairs


def opendrive_world(
    name: str, source: str | Path, origin_lat: float, origin_lon: float, speed_mps: float = URBAN_SPEED_MPS
) -> World:
    """Build a :class:`World` from an OpenDRIVE file (see the module docstring for the mapping)."""
    od = parse_opendrive(source)
    roads = sorted(
        od.roads.values(),
        key=lambda r: (r.in_junction, int(r.road_id) if r.road_id.isdigit() else 0, r.road_id),
    )
    # world frame: the file frame shifted to the centre of the reference lines' bounding box
    ref_xy = np.vstack([reference_pose(r, np.linspace(0.0, r.length_m, 5))[0] for r in roads])
    shift_xy = (ref_xy.min(axis=0) + ref_xy.max(axis=0)) / 2.0

    builder = WorldBuilder()
    for road in roads:
        if not road.in_junction:
            for k in range(len(road.sections)):
                _add_section_paint(builder, road, k, shift_xy)

    lanes: dict[LaneKey, _LaneGeometry] = {}
    for road in roads:
        road_type = "urban_junction" if road.in_junction else "opendrive_street"
        for k, section in enumerate(road.sections):
            s = _section_s(road, k)
            edges = lane_edges_t(road, k, s)
            for lane in section.lanes:
                if lane.lane_id == 0 or lane.type not in DRIVING_LANE_TYPES:
                    continue
                inner, outer = edges[lane.lane_id]
                centre = geo.dedupe(points_at_t(road, s, (inner + outer) / 2.0) - shift_xy, 1e-3)
                if len(centre) < 2:
                    continue
                width = float(np.mean(np.abs(outer - inner)))
                lanes[(road.road_id, k, lane.lane_id)] = _LaneGeometry(
                    centre[::-1] if lane.lane_id > 0 else centre, width, road_type
                )

    links: set[tuple[LaneKey, LaneKey]] = set()
    n_inconsistent = 0
    for a, b in _touching_ends(od):
        ka, kb = (a.road_id, a.section, a.lane_id), (b.road_id, b.section, b.lane_id)
        if ka not in lanes or kb not in lanes:
            continue
        if a.exits == b.exits:
            n_inconsistent += 1
            continue
        links.add((ka, kb) if a.exits else (kb, ka))
    n_rebuilt = _rebuild_short_connectors(lanes, links)

    lane_nodes: dict[LaneKey, int] = {}
    for key, lane_geom in lanes.items():
        lane_nodes[key] = builder.add_lane(
            lane_geom.centerline_xy, speed_mps, lane_geom.width_m, lane_geom.road_type
        )
    for u, v in sorted(links):
        builder.connect(lane_nodes[u], lane_nodes[v])
    n_gaps = _join_unlinked_ends(builder)
    n_turns = builder.add_turnarounds(max_gap_m=TURNAROUND_MAX_GAP_M)
    log.debug(
        "%s: %d lane links, %d inconsistent links dropped, %d connectors rebuilt, %d gaps joined, %d turnarounds",
        name,
        len(links),
        n_inconsistent,
        n_rebuilt,
        n_gaps,
        n_turns,
    )
    world = builder.build(name, origin_lat, origin_lon)
    log.info("%s world: %s", name, world.summary())
    return world


def _join_unlinked_ends(builder: WorldBuilder) -> int:
    """Join each lane end without a successor to the lane starts within ``GAP_JOIN_TOL_M`` that
    head the same way (within 45 degrees), then each lane start without a predecessor to such lane
    ends; returns how many successor edges were added."""
    g = builder.graph
    min_cos = float(np.cos(np.pi / 4))

    def has(n: int, out: bool) -> bool:
        edges = g.out_edges(n, data=True) if out else g.in_edges(n, data=True)
        return any(d["kind"] == SUCCESSOR for _, _, d in edges)

    nodes = sorted(g.nodes)
    first_xy = np.array([g.nodes[n]["centerline_xy"][0] for n in nodes])
    last_xy = np.array([g.nodes[n]["centerline_xy"][-1] for n in nodes])
    first_t = np.array([geo.tangents(g.nodes[n]["centerline_xy"])[0] for n in nodes])
    last_t = np.array([geo.tangents(g.nodes[n]["centerline_xy"])[-1] for n in nodes])
    start_tree, end_tree = cKDTree(first_xy), cKDTree(last_xy)
    before = g.number_of_edges()
    for i, n in enumerate(nodes):
        if not has(n, out=True):
            for k in sorted(start_tree.query_ball_point(last_xy[i], r=GAP_JOIN_TOL_M)):
                if nodes[k] != n and float(first_t[k] @ last_t[i]) > min_cos:
                    builder.connect(n, nodes[k])
    for i, n in enumerate(nodes):
        if not has(n, out=False):
            for k in sorted(end_tree.query_ball_point(first_xy[i], r=GAP_JOIN_TOL_M)):
                if nodes[k] != n and float(last_t[k] @ first_t[i]) > min_cos:
                    builder.connect(nodes[k], n)
    return g.number_of_edges() - before


def newmarket(path: str | Path | None = None) -> World:
    """The Newmarket, Ontario world from the vendored OpenDRIVE map."""
    return opendrive_world("newmarket", path or NEWMARKET_XODR, *NEWMARKET_ORIGIN_LATLON)
