"""The Karlsruhe world from the Lanelet2 example HD map (OSM XML, BSD-3; ``shared/realdata``).

Way tags -> truth elements:
- ``line_thin`` / ``line_thick``: lane dividers; subtype ``dashed`` -> dashed, ``solid`` -> solid,
  ``solid_solid`` / ``solid_dashed`` / ``dashed_solid`` -> double; no subtype -> unknown;
- ``curbstone``, ``road_border``, ``guard_rail``: road boundaries;
- ``stop_line``: stop lines;
- crosswalks: a lanelet whose two bounds are ``zebra_marking`` / ``pedestrian_marking`` gives the
  polygon between them; a ``zebra_marking`` not paired so is buffered to a 3 m deep polygon;
- ``virtual`` and everything else: nothing (no paint).
Lanelets of subtype ``road`` / ``highway`` give lanes: centreline = midline of the bounds
(both resampled by normalised arclength and averaged); bidirectional lanelets give a lane each
way. Successors where a lanelet's end meets another's start (bound end points within 0.5 m);
lane changes where two same-direction lanelets share a bound that is not solid.
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
from csr_core.sim import geometry as geo
from csr_core.sim.world import World, WorldBuilder
from csr_core.types import DividerStyle, ElementType

log = logging.getLogger(__name__)

DEFAULT_OSM = Path(__file__).resolve().parents[3] / "shared" / "realdata" / "lanelet2" / "mapping_example.osm"
OSM_ENV = "CSR_LANELET2_OSM"
URBAN_SPEED_MPS = 13.9
HIGHWAY_SPEED_MPS = 27.8
JOIN_TOL_M = 0.5
CROSSWALK_DEPTH_M = 3.0

_DIVIDER_STYLE = {
    "dashed": DividerStyle.DASHED,
    "solid": DividerStyle.SOLID,
    "solid_solid": DividerStyle.DOUBLE,
    "solid_dashed": DividerStyle.DOUBLE,
    "dashed_solid": DividerStyle.DOUBLE,
}
_BOUNDARY_TYPES = ("curbstone", "road_border", "guard_rail")
_MARKING_TYPES = ("zebra_marking", "pedestrian_marking")


@dataclass(frozen=True)
class _Way:
    way_id: str
    node_ids: tuple[str, ...]
    xy: np.ndarray  # (M, 2) world
    type: str
    subtype: str


def osm_path() -> Path:
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


def karlsruhe(path: str | Path | None = None) -> World:
    """Parse the Lanelet2 example map into a :class:`World` (origin: centre of its nodes)."""
    root = ET.parse(path or osm_path()).getroot()
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

    builder = WorldBuilder()
    for way in ways.values():  # file order: deterministic
        if way.type in ("line_thin", "line_thick"):
            builder.add_element(
                ElementType.LANE_DIVIDER, way.xy, _DIVIDER_STYLE.get(way.subtype, DividerStyle.UNKNOWN)
            )
        elif way.type in _BOUNDARY_TYPES:
            builder.add_element(ElementType.ROAD_BOUNDARY, way.xy)
        elif way.type == "stop_line":
            builder.add_element(ElementType.STOP_LINE, way.xy)

    lanelets = []
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
            lxy, rxy = _oriented_bounds(left.xy, right.xy)
            polygon = geo.dedupe(np.vstack([lxy, rxy[::-1]]), 0.05)
            if len(polygon) >= 3:
                builder.add_element(ElementType.CROSSWALK, polygon)
                paired_markings.update((left.way_id, right.way_id))
            continue
        if t.get("subtype") in ("road", "highway"):
            lanelets.append((rel.get("id"), left, right, t))
    for way in ways.values():
        if way.type == "zebra_marking" and way.way_id not in paired_markings:
            line = geo.resample(way.xy, 0.5)
            half = CROSSWALK_DEPTH_M / 2.0
            builder.add_element(
                ElementType.CROSSWALK, np.vstack([geo.offset(line, half), geo.offset(line, -half)[::-1]])
            )

    # lanes: one per lanelet and direction
    lanes = []  # (lane id, left way, right way, left_xy, right_xy, reversed)
    for _, left, right, t in lanelets:
        lxy, rxy = _oriented_bounds(left.xy, right.xy)
        centre = _midline(lxy, rxy)
        # the left bound must be on the left of the travel direction
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
        speed = HIGHWAY_SPEED_MPS if t.get("subtype") == "highway" else URBAN_SPEED_MPS
        lid = builder.add_lane(centre, speed, width, "lanelet_" + t.get("subtype", "road"))
        lanes.append((lid, left.way_id, right.way_id, lxy, rxy))
        if t.get("one_way", "yes") == "no":
            rid = builder.add_lane(
                centre[::-1], speed, width, "lanelet_" + t.get("subtype", "road"), with_element=False
            )
            lanes.append((rid, right.way_id, left.way_id, rxy[::-1], lxy[::-1]))

    # successors: end of one lane meets the start of another (both bounds)
    starts = np.array([(lx[0] + rx[0]) / 2 for _, _, _, lx, rx in lanes])
    tree = cKDTree(starts)
    for lid, _, _, lx, rx in lanes:
        end = (lx[-1] + rx[-1]) / 2
        for k in sorted(tree.query_ball_point(end, r=2 * JOIN_TOL_M)):
            oid, _, _, olx, orx = lanes[k]
            if oid == lid:
                continue
            if np.linalg.norm(olx[0] - lx[-1]) < JOIN_TOL_M and np.linalg.norm(orx[0] - rx[-1]) < JOIN_TOL_M:
                builder.connect(lid, oid)
    # neighbours: a shared, non-solid bound between two lanes of the same direction
    by_left: dict[str, list[tuple[int, np.ndarray]]] = {}
    for lid, lw, _, lx, _ in lanes:
        by_left.setdefault(lw, []).append((lid, lx))
    for lid, _, rw, _, rx in lanes:
        for oid, olx in by_left.get(rw, []):
            same_direction = np.linalg.norm(olx[0] - rx[0]) < JOIN_TOL_M
            if oid != lid and same_direction and ways[rw].subtype != "solid" and ways[rw].type != "curbstone":
                builder.neighbours(lid, oid)
    n_links = builder.add_hidden_links(max_gap_m=800.0, min_alignment=0.97)
    n_turns = builder.add_turnarounds(max_gap_m=15.0)
    log.debug("karlsruhe: %d hidden links between mapped patches, %d turnarounds", n_links, n_turns)
    zones = np.array([[-1444.0, -144.0, 150.0], [-827.0, 332.0, 150.0]])  # two mapped junction areas
    world = builder.build("karlsruhe", frame.origin_lat, frame.origin_lon, zones)
    log.info("karlsruhe world: %s", world.summary())
    return world
