"""Worlds from CommonRoad scenarios (XML, format 2018b and 2020a; local metric coordinates): the
Carcarana street grid and a section of the A9 motorway.

``load_commonroad_world(path, options)`` reads the lanelet network of any such file; the maps ship
in ``csr_core/sim/data`` with their licences. The file is read with ElementTree: the
``commonroad-io`` package pins ``protobuf==3.20.x`` in every release, which cannot be installed
beside ``mapbox-vector-tile`` (``protobuf>=6.31``). World frame: local tmerc at
``(options.origin_lat, options.origin_lon)``, x east, y north, metres; the file's x / y axes are
taken as east / north and the centre of the lanelets' bounding box is placed at the origin.

From the map (when the file has them):
- lanes: one per drivable lanelet (every type but crosswalk, sidewalk, bicycle lane, parking),
  centreline = midpoint of the left and right bound vertices (CommonRoad bounds have equal vertex
  counts), in the direction of travel; width = median distance between the bounds;
- lane graph: ``successor`` elements; lane changes across ``adjacentLeft`` / ``adjacentRight`` of
  the same driving direction unless the shared bound's marking is solid;
- speed: the lanelet's ``speedLimit`` (2018b) or the lowest maximum-speed sign it refers to
  (sign id ``274`` or ``R15`` with a value in m/s), else ``options.default_speed_mps``;
- lane dividers from ``lineMarking`` (dashed / broad_dashed -> dashed, solid / broad_solid ->
  solid), stop lines from ``stopLine`` (its two points, or the lanelet's end when it has none),
  crosswalks from lanelets of type crosswalk (the polygon between their bounds).

Derived, where the file has no such element (neither shipped file has line markings, stop lines
or crosswalks):
- divider styles: a bound between two adjacent lanelets whose ``lineMarking`` is missing or
  ``unknown`` is a divider, dashed between lanelets of the same direction; between opposite
  directions dashed when each direction has one lane there, double when either side has a
  same-direction neighbour (the procedural urban world's convention); lanelets inside an
  intersection (the ``successors*`` / ``outgoing*`` of its incomings) get no dividers and the
  road type ``urban_junction`` (routes do not start there);
- road boundaries: the outline of the union of the drivable lanelets, less the caps where the
  network is cut off (see :mod:`csr_core.sim.drivable_area`).
No stop lines or crosswalks are derived: the files have none.

Maps (placements are chosen; the files have no projection):
- ``carcarana``: Carcarana, Santa Fe, Argentina (OSM-derived, CommonRoad Scenario Factory;
  BSD-3, map data (c) OpenStreetMap contributors, ODbL): the box centre at the file's city
  location, 32.85679 S, 61.15331 W; lanes at 40 km/h (its signs and the default).
- ``a9``: 2.3 km of the A9 motorway, Germany (source BMW; BSD-3), placed nominally at
  48.2500 N, 11.6400 E (north of Munich) with the file's axes kept; lanes at the file's
  27.78 m/s; dead ends joined by hidden turnarounds across the median.
"""

from __future__ import annotations

import dataclasses
import logging
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csr_core.sim import drivable_area
from csr_core.sim.world import World, WorldBuilder
from csr_core.types import DividerStyle, ElementType

log = logging.getLogger(__name__)

DATA_DIR = Path(__file__).resolve().parent / "data"
CARCARANA_XML = DATA_DIR / "carcarana-commonroad" / "ARG_Carcarana-4_5_T-1.xml"
A9_XML = DATA_DIR / "a9-commonroad" / "DEU_A9-3_1_T-1.xml"
URBAN_SPEED_MPS = 11.1  # 40 km/h
HIGHWAY_SPEED_MPS = 27.8

_NOT_DRIVABLE = frozenset({"crosswalk", "sidewalk", "bicycleLane", "parking"})
_MARKING_STYLE = {
    "dashed": DividerStyle.DASHED,
    "broad_dashed": DividerStyle.DASHED,
    "solid": DividerStyle.SOLID,
    "broad_solid": DividerStyle.SOLID,
}
_MAX_SPEED_SIGNS = frozenset({"274", "R15"})
_INTERSECTION_LANE_TAGS = (
    "successorsRight",
    "successorsLeft",
    "successorsStraight",
    "outgoingRight",
    "outgoingLeft",
    "outgoingStraight",
)


@dataclass(frozen=True, slots=True)
class CommonRoadOptions:
    """How one CommonRoad file becomes a world (degrees, m/s, metres)."""

    name: str
    origin_lat: float
    origin_lon: float
    default_speed_mps: float
    road_type: str
    turnaround_max_gap_m: float = 15.0


CARCARANA = CommonRoadOptions(
    name="carcarana",
    origin_lat=-32.85679,
    origin_lon=-61.15331,
    default_speed_mps=URBAN_SPEED_MPS,
    road_type="commonroad_urban",
)
A9 = CommonRoadOptions(
    name="a9",
    origin_lat=48.2500,
    origin_lon=11.6400,
    default_speed_mps=HIGHWAY_SPEED_MPS,
    road_type="commonroad_highway",
    turnaround_max_gap_m=80.0,
)


@dataclass(frozen=True)
class _Lanelet:
    lanelet_id: str
    left_xy: np.ndarray  # (M, 2) file frame, direction of travel
    right_xy: np.ndarray  # (M, 2)
    left_marking: str
    right_marking: str
    predecessors: tuple[str, ...]
    successors: tuple[str, ...]
    adj_left: str | None
    adj_left_same: bool
    adj_right: str | None
    adj_right_same: bool
    types: frozenset[str]
    speed_mps: float | None
    sign_refs: tuple[str, ...]
    stop_line_xy: np.ndarray | None  # (2, 2)

    @property
    def drivable(self) -> bool:
        return not (self.types & _NOT_DRIVABLE)


def _points(element: ET.Element | None) -> np.ndarray:
    if element is None:
        return np.zeros((0, 2))
    return np.array(
        [[float(p.findtext("x", "nan")), float(p.findtext("y", "nan"))] for p in element.findall("point")]
    ).reshape(-1, 2)


def _adjacent(element: ET.Element, tag: str) -> tuple[str | None, bool]:
    adj = element.find(tag)
    if adj is None:
        return None, False
    return adj.get("ref"), adj.get("drivingDir", "same") == "same"


def _parse_lanelet(el: ET.Element) -> _Lanelet:
    left, right = el.find("leftBound"), el.find("rightBound")
    adj_left, adj_left_same = _adjacent(el, "adjacentLeft")
    adj_right, adj_right_same = _adjacent(el, "adjacentRight")
    speed = el.findtext("speedLimit")
    stop = el.find("stopLine")
    stop_xy = None
    if stop is not None:
        stop_xy = _points(stop)
        if len(stop_xy) < 2:
            stop_xy = np.array([_points(left)[-1], _points(right)[-1]])
    return _Lanelet(
        lanelet_id=el.get("id", ""),
        left_xy=_points(left),
        right_xy=_points(right),
        left_marking=(left.findtext("lineMarking") or "unknown") if left is not None else "unknown",
        right_marking=(right.findtext("lineMarking") or "unknown") if right is not None else "unknown",
        predecessors=tuple(p.get("ref", "") for p in el.findall("predecessor")),
        successors=tuple(s.get("ref", "") for s in el.findall("successor")),
        adj_left=adj_left,
        adj_left_same=adj_left_same,
        adj_right=adj_right,
        adj_right_same=adj_right_same,
        types=frozenset((t.text or "").strip() for t in el.findall("laneletType")),
        speed_mps=float(speed) if speed else None,
        sign_refs=tuple(r.get("ref", "") for r in el.findall("trafficSignRef")),
        stop_line_xy=stop_xy,
    )


def _max_speed_signs(root: ET.Element) -> dict[str, float]:
    """Sign id -> the lowest maximum speed (m/s) among its elements."""
    out: dict[str, float] = {}
    for sign in root.iter("trafficSign"):
        for element in sign.findall("trafficSignElement"):
            value = element.findtext("additionalValue")
            if (element.findtext("trafficSignID") or "").strip() in _MAX_SPEED_SIGNS and value:
                out[sign.get("id", "")] = min(out.get(sign.get("id", ""), np.inf), float(value))
    return out


def _intersection_lanelets(root: ET.Element) -> set[str]:
    return {
        ref.get("ref", "")
        for intersection in root.iter("intersection")
        for tag in _INTERSECTION_LANE_TAGS
        for ref in intersection.iter(tag)
    }


def _divider_style(a: _Lanelet, b: _Lanelet, marking: str, same_direction: bool) -> DividerStyle | None:
    """The style of the bound between adjacent lanelets ``a`` and ``b`` (None: no paint)."""
    if marking in _MARKING_STYLE:
        return _MARKING_STYLE[marking]
    if marking == "no_marking":
        return None
    if same_direction:
        return DividerStyle.DASHED

    def multi_lane(ll: _Lanelet) -> bool:
        return (ll.adj_left is not None and ll.adj_left_same) or (
            ll.adj_right is not None and ll.adj_right_same
        )

    return DividerStyle.DOUBLE if multi_lane(a) or multi_lane(b) else DividerStyle.DASHED


def load_commonroad_world(path: str | Path, options: CommonRoadOptions) -> World:
    """Parse a CommonRoad file's lanelet network into a :class:`World`."""
    root = ET.parse(path).getroot()
    raw = [_parse_lanelet(el) for el in root.iter("lanelet")]
    raw = [ll for ll in raw if len(ll.left_xy) >= 2 and len(ll.left_xy) == len(ll.right_xy)]
    all_xy = np.vstack([np.vstack([ll.left_xy, ll.right_xy]) for ll in raw])
    centre = (all_xy.min(axis=0) + all_xy.max(axis=0)) / 2.0
    lanelets = {
        ll.lanelet_id: dataclasses.replace(
            ll,
            left_xy=ll.left_xy - centre,
            right_xy=ll.right_xy - centre,
            stop_line_xy=None if ll.stop_line_xy is None else ll.stop_line_xy - centre,
        )
        for ll in raw
    }
    signs = _max_speed_signs(root)
    in_intersection = _intersection_lanelets(root)
    drivable = {k: ll for k, ll in lanelets.items() if ll.drivable}

    builder = WorldBuilder()
    lane_of: dict[str, int] = {}
    for lid, ll in drivable.items():  # file order: deterministic
        speeds = [signs[r] for r in ll.sign_refs if r in signs]
        speed = ll.speed_mps or (min(speeds) if speeds else options.default_speed_mps)
        width = float(np.median(np.linalg.norm(ll.left_xy - ll.right_xy, axis=1)))
        road_type = "urban_junction" if lid in in_intersection else options.road_type
        lane_of[lid] = builder.add_lane((ll.left_xy + ll.right_xy) / 2.0, speed, width, road_type)

    # dividers: once per adjacent pair, outside intersections
    done: set[frozenset[str]] = set()
    for lid, ll in drivable.items():
        for adj, same, marking, bound in (
            (ll.adj_left, ll.adj_left_same, ll.left_marking, ll.left_xy),
            (ll.adj_right, ll.adj_right_same, ll.right_marking, ll.right_xy),
        ):
            if adj is None or adj not in drivable or frozenset((lid, adj)) in done:
                continue
            done.add(frozenset((lid, adj)))
            if lid in in_intersection or adj in in_intersection:
                continue
            style = _divider_style(ll, drivable[adj], marking, same)
            if style is not None:
                builder.add_element(ElementType.LANE_DIVIDER, bound, style)
        for adj, marking, bound in (
            (ll.adj_left, ll.left_marking, ll.left_xy),
            (ll.adj_right, ll.right_marking, ll.right_xy),
        ):
            if adj is None and marking in _MARKING_STYLE:  # painted edge line
                builder.add_element(ElementType.LANE_DIVIDER, bound, _MARKING_STYLE[marking])

    # boundaries: outline of the drivable area, less the cut-off ends of the network
    caps = []
    for ll in drivable.values():
        if not any(p in drivable for p in ll.predecessors):
            caps.append(np.array([ll.left_xy[0], ll.right_xy[0]]))
        if not any(s in drivable for s in ll.successors):
            caps.append(np.array([ll.left_xy[-1], ll.right_xy[-1]]))
    polygons = [drivable_area.lanelet_polygon(ll.left_xy, ll.right_xy) for ll in drivable.values()]
    for line in drivable_area.outline_boundaries(polygons, caps):
        builder.add_element(ElementType.ROAD_BOUNDARY, line)

    for ll in lanelets.values():
        if ll.stop_line_xy is not None:
            builder.add_element(ElementType.STOP_LINE, ll.stop_line_xy)
        if "crosswalk" in ll.types:
            builder.add_element(ElementType.CROSSWALK, np.vstack([ll.left_xy, ll.right_xy[::-1]]))

    # lane graph
    for lid, ll in drivable.items():
        for s in ll.successors:
            if s in lane_of:
                builder.connect(lane_of[lid], lane_of[s])
        if ll.adj_left in lane_of and ll.adj_left_same and ll.left_marking not in ("solid", "broad_solid"):
            builder.neighbours(lane_of[ll.adj_left], lane_of[lid])
        if ll.adj_right in lane_of and ll.adj_right_same and ll.right_marking not in ("solid", "broad_solid"):
            builder.neighbours(lane_of[lid], lane_of[ll.adj_right])
    n_turns = builder.add_turnarounds(max_gap_m=options.turnaround_max_gap_m)
    log.debug("%s: %d turnarounds", options.name, n_turns)
    world = builder.build(options.name, options.origin_lat, options.origin_lon)
    log.info("%s world: %s", options.name, world.summary())
    return world


def carcarana(path: str | Path | None = None) -> World:
    """The Carcarana street grid (CommonRoad 2020a), centred at the file's city location."""
    return load_commonroad_world(path or CARCARANA_XML, CARCARANA)


def a9(path: str | Path | None = None) -> World:
    """2.3 km of the A9 motorway (CommonRoad 2018b), placed nominally north of Munich."""
    return load_commonroad_world(path or A9_XML, A9)
