"""Worlds from Lanelet2 HD maps (OSM XML, WGS84 lat/lon on every node): Karlsruhe and Kashiwa-no-ha.

``load_lanelet2_world(path, options)`` reads any such file; the maps ship in ``csr_core/sim/data``
with their licences. World frame: local tmerc at the centre of the file's nodes (x east, y north,
metres).

Way tags -> truth elements:
- ``line_thin`` / ``line_thick``: lane dividers; subtype ``dashed`` -> dashed, ``solid`` -> solid,
  ``solid_solid`` / ``solid_dashed`` / ``dashed_solid`` -> double; no subtype -> unknown;
- ``curbstone``, ``road_border``, ``guard_rail``: road boundaries;
- ``stop_line``: stop lines;
- crosswalks: a lanelet whose two bounds are ``zebra_marking`` / ``pedestrian_marking`` gives the
  polygon between them; a ``zebra_marking`` not paired so is buffered to a 3 m deep polygon; with
  ``crosswalk_lanelets``, a lanelet of subtype ``crosswalk`` gives the polygon between its bounds;
- ``virtual``, untagged ways and everything else: nothing (no paint).
Lanelets of subtype ``road`` / ``highway`` give lanes: centreline = midline of the bounds
(both resampled by normalised arclength and averaged); the direction of travel is the one with
the left bound on the left, so left- and right-hand traffic need no option; bidirectional
lanelets give a lane each way. Successors where a lanelet's end meets another's start (bound end
points within 0.5 m); lane changes where two same-direction lanelets share a bound that is not
solid.

Derived, with ``derive_boundaries`` (maps that leave the kerb untagged): road boundaries are the
outline of the union of the road lanelets (see :mod:`csr_core.sim.drivable_area`), less the caps
where the mapped network is cut off and less the pieces along a ``line_thin`` / ``line_thick`` way
(there the bound is a painted edge line and the kerb beyond it is not mapped).

Maps:
- ``karlsruhe``: the Lanelet2 example map (BSD-3), surveyed streets of Karlsruhe; origin about
  49.0065 N, 8.4354 E; two GNSS urban-canyon zones over its mapped junction areas.
- ``kashiwanoha``: TIER IV's Kashiwa-no-ha map (Autoware flavour, Apache-2.0), one signalised
  crossing area of Kashiwa, Chiba, Japan, left-hand traffic; origin 35.9033 N, 139.9336 E.
  Its kerbs are untagged ways, so its boundaries are derived as above; its 4 crosswalks are
  lanelets of subtype ``crosswalk`` between untagged ways. Its ``speed_limit`` tag (10 km/h on
  every lanelet, a setting of the scenario simulator it comes from) is not used: lanes take
  40 km/h (11.1 m/s), a Japanese urban street's usual signed limit. Its lane graph keeps 69 of
  77 lanes on one strongly connected component; four lanes end where no lanelet starts (as
  mapped) and no lane start within 15 m heads back, so they stay dead ends without turnarounds.
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from csr_core.geo import LocalFrame
from csr_core.sim import drivable_area
from csr_core.sim import geometry as geo
from csr_core.sim.world import SUCCESSOR, World, WorldBuilder
from csr_core.types import DividerStyle, ElementType

log = logging.getLogger(__name__)

DATA_DIR = Path(__file__).resolve().parent / "data"
DEFAULT_OSM = DATA_DIR / "karlsruhe-lanelet2" / "mapping_example.osm"
KASHIWANOHA_OSM = DATA_DIR / "kashiwanoha-lanelet2" / "lanelet2_map.osm"
OSM_ENV = "CSR_LANELET2_OSM"
URBAN_SPEED_MPS = 13.9
HIGHWAY_SPEED_MPS = 27.8
KASHIWANOHA_SPEED_MPS = 11.1  # 40 km/h
JOIN_TOL_M = 0.5
CROSSWALK_DEPTH_M = 3.0

_DIVIDER_STYLE = {
    "dashed": DividerStyle.DASHED,
    "solid": DividerStyle.SOLID,
    "solid_solid": DividerStyle.DOUBLE,
    "solid_dashed": DividerStyle.DOUBLE,
    "dashed_solid": DividerStyle.DOUBLE,
}
_LINE_TYPES = ("line_thin", "line_thick")
_BOUNDARY_TYPES = ("curbstone", "road_border", "guard_rail")
_MARKING_TYPES = ("zebra_marking", "pedestrian_marking")


@dataclass(frozen=True, slots=True)
class Lanelet2Options:
    """How one Lanelet2 file becomes a world (speeds in m/s, distances in metres, zones in the
    world frame as ``(x, y, radius)``)."""

    name: str
    urban_speed_mps: float = URBAN_SPEED_MPS
    highway_speed_mps: float = HIGHWAY_SPEED_MPS
    crosswalk_lanelets: bool = False  # lanelets of subtype ``crosswalk`` give crosswalk polygons
    derive_boundaries: bool = False  # boundaries from the outline of the road lanelets
    hidden_link_max_gap_m: float = 0.0  # 0: no hidden links between mapped patches
    hidden_link_min_alignment: float = 0.97
    turnaround_max_gap_m: float = 15.0
    canyon_zones_xyr: tuple[tuple[float, float, float], ...] = ()


KARLSRUHE = Lanelet2Options(
    name="karlsruhe",
    hidden_link_max_gap_m=800.0,
    canyon_zones_xyr=((-1444.0, -144.0, 150.0), (-827.0, 332.0, 150.0)),  # two mapped junction areas
)
KASHIWANOHA = Lanelet2Options(
    name="kashiwanoha",
    urban_speed_mps=KASHIWANOHA_SPEED_MPS,
    crosswalk_lanelets=True,
    derive_boundaries=True,
)


@dataclass(frozen=True)
class _Way:
    way_id: str
    node_ids: tuple[str, ...]
    xy: np.ndarray  # (M, 2) world
    type: str
    subtype: str


@dataclass(frozen=True)
class _Lane:
    lane_id: int
    left_way: str
    right_way: str
    left_xy: np.ndarray  # (M, 2) world, in the direction of travel
    right_xy: np.ndarray  # (K, 2) world, in the direction of travel


def osm_path() -> Path:
    """The Karlsruhe file: ``$CSR_LANELET2_OSM`` if set, else the shipped copy."""
    return Path(os.environ.get(OSM_ENV, DEFAULT_OSM))


def _tags(element: ET.Element) -> dict[str, str]:
    return {t.get("k", ""): t.get("v", "") for t in element.findall("tag")}


def _oriented_bounds(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orient the right bound like the left, then both so that the left bound is on the left."""
    same = np.linalg.norm(left[0] - right[0]) + np.linalg.norm(left[-1] - right[-1])
    flipped = np.linalg.norm(left[0] - right[-1]) + np.linalg.norm(left[-1] - right[0])
    if flipped < same:
        right = right[::-1]
    return left, right


def _midline(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    n = max(int(np.ceil(max(geo.arclength_m(left)[-1], geo.arclength_m(right)[-1]))), 2)
    u = np.linspace(0.0, 1.0, n)
    sl, sr = geo.arclength_m(left), geo.arclength_m(right)
    pl = geo.interpolate_at(left, u * sl[-1])
    pr = geo.interpolate_at(right, u * sr[-1])
    return (pl + pr) / 2.0


def _read_ways(root: ET.Element) -> tuple[LocalFrame, dict[str, _Way]]:
    node_lonlat = {
        n.get("id", ""): (float(n.get("lon", "nan")), float(n.get("lat", "nan"))) for n in root.iter("node")
    }
    frame = LocalFrame.around(np.array(list(node_lonlat.values())))
    ids = list(node_lonlat)
    xy_all = frame.to_local(np.array([node_lonlat[i] for i in ids]))
    node_xy = {i: xy_all[k] for k, i in enumerate(ids)}
    ways: dict[str, _Way] = {}
    for w in root.iter("way"):
        refs = tuple(nd.get("ref", "") for nd in w.findall("nd"))
        refs = tuple(r for r in refs if r in node_xy)
        if len(refs) < 2:
            continue
        t = _tags(w)
        ways[w.get("id", "")] = _Way(
            w.get("id", ""),
            refs,
            np.array([node_xy[r] for r in refs]),
            t.get("type", ""),
            t.get("subtype", ""),
        )
    return frame, ways


def _crosswalk(builder: WorldBuilder, left: _Way, right: _Way) -> bool:
    lxy, rxy = _oriented_bounds(left.xy, right.xy)
    polygon = geo.dedupe(np.vstack([lxy, rxy[::-1]]), 0.05)
    if len(polygon) < 3:
        return False
    builder.add_element(ElementType.CROSSWALK, polygon)
    return True


def _add_lanes(
    builder: WorldBuilder, lanelets: list[tuple[_Way, _Way, dict[str, str]]], options: Lanelet2Options
) -> list[_Lane]:
    """One lane per lanelet and direction, the left bound on the left of travel."""
    lanes: list[_Lane] = []
    for left, right, t in lanelets:
        lxy, rxy = _oriented_bounds(left.xy, right.xy)
        centre = _midline(lxy, rxy)
        d = centre[-1] - centre[0]
        v = lxy.mean(axis=0) - centre.mean(axis=0)
        side = d[0] * v[1] - d[1] * v[0]
        if side < 0:
            lxy, rxy, centre = lxy[::-1], rxy[::-1], centre[::-1]
        width = float(
            np.median(
                np.linalg.norm(
                    geo.interpolate_at(lxy, np.linspace(0, geo.arclength_m(lxy)[-1], 5))
                    - geo.interpolate_at(rxy, np.linspace(0, geo.arclength_m(rxy)[-1], 5)),
                    axis=1,
                )
            )
        )
        speed = options.highway_speed_mps if t.get("subtype") == "highway" else options.urban_speed_mps
        road_type = "lanelet_" + t.get("subtype", "road")
        lid = builder.add_lane(centre, speed, width, road_type)
        lanes.append(_Lane(lid, left.way_id, right.way_id, lxy, rxy))
        if t.get("one_way", "yes") == "no":
            rid = builder.add_lane(centre[::-1], speed, width, road_type, with_element=False)
            lanes.append(_Lane(rid, right.way_id, left.way_id, rxy[::-1], lxy[::-1]))
    return lanes


def _connect(builder: WorldBuilder, lanes: list[_Lane], ways: dict[str, _Way]) -> None:
    """Successors (both bounds meet within ``JOIN_TOL_M``) and same-direction neighbours across a
    shared bound that is neither solid nor a kerb."""
    starts = np.array([(ln.left_xy[0] + ln.right_xy[0]) / 2 for ln in lanes])
    tree = cKDTree(starts)
    for ln in lanes:
        end = (ln.left_xy[-1] + ln.right_xy[-1]) / 2
        for k in sorted(tree.query_ball_point(end, r=2 * JOIN_TOL_M)):
            other = lanes[k]
            if other.lane_id == ln.lane_id:
                continue
            if (
                np.linalg.norm(other.left_xy[0] - ln.left_xy[-1]) < JOIN_TOL_M
                and np.linalg.norm(other.right_xy[0] - ln.right_xy[-1]) < JOIN_TOL_M
            ):
                builder.connect(ln.lane_id, other.lane_id)
    by_left: dict[str, list[_Lane]] = {}
    for ln in lanes:
        by_left.setdefault(ln.left_way, []).append(ln)
    for ln in lanes:
        for other in by_left.get(ln.right_way, []):
            same_direction = np.linalg.norm(other.left_xy[0] - ln.right_xy[0]) < JOIN_TOL_M
            shared = ways[ln.right_way]
            if (
                other.lane_id != ln.lane_id
                and same_direction
                and shared.subtype != "solid"
                and shared.type != "curbstone"
            ):
                builder.neighbours(ln.lane_id, other.lane_id)


def _derived_boundaries(builder: WorldBuilder, lanes: list[_Lane], ways: dict[str, _Way]) -> int:
    """Boundaries from the road lanelets' outline; returns how many were added."""
    successors = [(u, v) for u, v, kind in builder.graph.edges(data="kind") if kind == SUCCESSOR]
    has_in, has_out = {v for _, v in successors}, {u for u, _ in successors}
    polygons = [drivable_area.lanelet_polygon(ln.left_xy, ln.right_xy) for ln in lanes]
    caps = []
    for ln in lanes:
        if ln.lane_id not in has_in:
            caps.append(np.array([ln.left_xy[0], ln.right_xy[0]]))
        if ln.lane_id not in has_out:
            caps.append(np.array([ln.left_xy[-1], ln.right_xy[-1]]))
    painted = [w.xy for w in ways.values() if w.type in _LINE_TYPES]
    outlines = drivable_area.outline_boundaries(polygons, caps, painted)
    for line in outlines:
        builder.add_element(ElementType.ROAD_BOUNDARY, line)
    return len(outlines)


def load_lanelet2_world(path: str | Path, options: Lanelet2Options) -> World:
    """Parse a Lanelet2 OSM file into a :class:`World` (origin: centre of its nodes)."""
    root = ET.parse(path).getroot()
    frame, ways = _read_ways(root)

    builder = WorldBuilder()
    for way in ways.values():  # file order: deterministic
        if way.type in _LINE_TYPES:
            builder.add_element(
                ElementType.LANE_DIVIDER, way.xy, _DIVIDER_STYLE.get(way.subtype, DividerStyle.UNKNOWN)
            )
        elif way.type in _BOUNDARY_TYPES:
            builder.add_element(ElementType.ROAD_BOUNDARY, way.xy)
        elif way.type == "stop_line":
            builder.add_element(ElementType.STOP_LINE, way.xy)

    lanelets: list[tuple[_Way, _Way, dict[str, str]]] = []
    paired_markings: set[str] = set()
    for rel in root.iter("relation"):
        t = _tags(rel)
        if t.get("type") != "lanelet":
            continue
        members = {
            m.get("role", ""): m.get("ref", "") for m in rel.findall("member") if m.get("type") == "way"
        }
        left, right = ways.get(members.get("left", "")), ways.get(members.get("right", ""))
        if left is None or right is None:
            continue
        if left.type in _MARKING_TYPES and right.type in _MARKING_TYPES:
            if _crosswalk(builder, left, right):
                paired_markings.update((left.way_id, right.way_id))
            continue
        if options.crosswalk_lanelets and t.get("subtype") == "crosswalk":
            _crosswalk(builder, left, right)
            continue
        if t.get("subtype") in ("road", "highway"):
            lanelets.append((left, right, t))
    for way in ways.values():
        if way.type == "zebra_marking" and way.way_id not in paired_markings:
            line = geo.resample(way.xy, 0.5)
            half = CROSSWALK_DEPTH_M / 2.0
            builder.add_element(
                ElementType.CROSSWALK, np.vstack([geo.offset(line, half), geo.offset(line, -half)[::-1]])
            )

    lanes = _add_lanes(builder, lanelets, options)
    _connect(builder, lanes, ways)
    n_derived = _derived_boundaries(builder, lanes, ways) if options.derive_boundaries else 0
    n_links = (
        builder.add_hidden_links(
            max_gap_m=options.hidden_link_max_gap_m, min_alignment=options.hidden_link_min_alignment
        )
        if options.hidden_link_max_gap_m > 0
        else 0
    )
    n_turns = builder.add_turnarounds(max_gap_m=options.turnaround_max_gap_m)
    log.debug(
        "%s: %d derived boundaries, %d hidden links between mapped patches, %d turnarounds",
        options.name,
        n_derived,
        n_links,
        n_turns,
    )
    zones = np.array(options.canyon_zones_xyr, float).reshape(-1, 3)
    world = builder.build(options.name, frame.origin_lat, frame.origin_lon, zones)
    log.info("%s world: %s", options.name, world.summary())
    return world


def karlsruhe(path: str | Path | None = None) -> World:
    """The Lanelet2 example map of Karlsruhe (``$CSR_LANELET2_OSM`` or the shipped copy)."""
    return load_lanelet2_world(path or osm_path(), KARLSRUHE)


def kashiwanoha(path: str | Path | None = None) -> World:
    """TIER IV's Kashiwa-no-ha map: one signalised crossing area, left-hand traffic."""
    return load_lanelet2_world(path or KASHIWANOHA_OSM, KASHIWANOHA)
