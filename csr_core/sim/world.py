"""A simulated world: the true road map (what perception can see) and a lane graph for routing.

World frame: local tmerc at ``(origin_lat, origin_lon)``, x east, y north, metres.

Lane graph (``networkx.DiGraph``): one node per lane piece (int id) with attributes
``centerline_xy (M, 2)`` in the direction of travel, ``speed_mps`` (legal speed),
``width_m``, ``road_type`` and ``visible`` (False for hidden turnaround connectors that
exist only so routes can continue; they have no truth elements). Edges carry
``kind``: ``"successor"`` (end of u meets start of v), ``"left"`` / ``"right"`` (v is the
neighbouring lane a vehicle may change into, same direction).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import networkx as nx
import numpy as np

from csr_core.errors import CsrError
from csr_core.sim import geometry as geo
from csr_core.types import DividerStyle, ElementType

log = logging.getLogger(__name__)

SUCCESSOR = "successor"
LEFT = "left"
RIGHT = "right"


class SimulationError(CsrError, ValueError):
    """The simulator cannot do what was asked (unknown world or profile, no drivable route)."""


@dataclass(frozen=True, slots=True)
class TruthElement:
    """One true road element, world frame; polygons are outlines, first point not repeated."""

    element_id: int
    type: ElementType
    points_xy_world: np.ndarray  # (M, 2)
    style: DividerStyle | None = None


@dataclass(frozen=True)
class World:
    """Truth map + lane graph + (for the ``hard`` profile) GNSS urban-canyon zones."""

    name: str
    origin_lat: float
    origin_lon: float
    elements: tuple[TruthElement, ...]
    lane_graph: nx.DiGraph
    canyon_zones_xyr: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (Z, 3) x, y, radius m

    def elements_of(self, element_type: ElementType) -> list[TruthElement]:
        return [e for e in self.elements if e.type == element_type]

    def road_length_km(self) -> float:
        """Total length of the visible lanes' centrelines (lane km, every lane and direction)."""
        total = 0.0
        for _, data in self.lane_graph.nodes(data=True):
            if data["visible"]:
                total += float(geo.arclength_m(data["centerline_xy"])[-1])
        return total / 1000.0

    def summary(self) -> dict:
        counts = {t.value: 0 for t in ElementType}
        length_m = {t.value: 0.0 for t in ElementType}
        for e in self.elements:
            counts[e.type.value] += 1
            length_m[e.type.value] += float(geo.arclength_m(e.points_xy_world)[-1])
        return {
            "world": self.name,
            "lane_nodes": self.lane_graph.number_of_nodes(),
            "lane_edges": self.lane_graph.number_of_edges(),
            "lane_km": round(self.road_length_km(), 2),
            "elements": counts,
            "element_km": {k: round(v / 1000.0, 2) for k, v in length_m.items() if v > 0},
        }


class WorldBuilder:
    """Accumulates elements and lanes with deterministic ids (insertion order)."""

    def __init__(self) -> None:
        self.elements: list[TruthElement] = []
        self.graph = nx.DiGraph()

    def add_element(
        self, element_type: ElementType, points_xy: np.ndarray, style: DividerStyle | None = None
    ) -> None:
        points_xy = geo.dedupe(np.asarray(points_xy, float), 0.05)
        if len(points_xy) < 2:
            return
        if element_type == ElementType.LANE_DIVIDER and style is None:
            style = DividerStyle.UNKNOWN
        self.elements.append(TruthElement(len(self.elements), element_type, points_xy, style))

    def add_lane(
        self,
        centerline_xy: np.ndarray,
        speed_mps: float,
        width_m: float,
        road_type: str,
        visible: bool = True,
        with_element: bool = True,
    ) -> int:
        """Add a lane node (and its centreline truth element when visible); return its id."""
        lane_id = self.graph.number_of_nodes()
        centerline_xy = geo.resample(centerline_xy, 1.0)
        self.graph.add_node(
            lane_id,
            centerline_xy=centerline_xy,
            speed_mps=float(speed_mps),
            width_m=float(width_m),
            road_type=road_type,
            visible=visible,
        )
        if visible and with_element:
            self.add_element(ElementType.CENTERLINE, centerline_xy)
        return lane_id

    def connect(self, u: int, v: int, kind: str = SUCCESSOR) -> None:
        self.graph.add_edge(u, v, kind=kind)

    def neighbours(self, left_lane: int, right_lane: int) -> None:
        """Two same-direction adjacent lanes: lane changes both ways."""
        self.graph.add_edge(left_lane, right_lane, kind=RIGHT)
        self.graph.add_edge(right_lane, left_lane, kind=LEFT)

    def _dead_ends_and_sources(self) -> tuple[list[int], list[int]]:
        g = self.graph
        ends = [
            n
            for n in sorted(g.nodes)
            if not any(d["kind"] == SUCCESSOR for _, _, d in g.out_edges(n, data=True))
        ]
        starts = [
            n
            for n in sorted(g.nodes)
            if not any(d["kind"] == SUCCESSOR for _, _, d in g.in_edges(n, data=True))
        ]
        return ends, starts

    def _nearest_start(
        self,
        p_end: np.ndarray,
        starts: list[int],
        max_gap_m: float,
        accept: Callable[[np.ndarray, float, np.ndarray], bool],
    ) -> tuple[int | None, float]:
        """The lane start nearest to ``p_end`` (closer than ``max_gap_m``) that ``accept(gap_xy,
        distance_m, start_tangent)`` admits, and its distance; ``(None, max_gap_m)`` if none."""
        best, best_d = None, max_gap_m
        for s in starts:
            cs = self.graph.nodes[s]["centerline_xy"]
            gap = cs[0] - p_end
            d = float(np.linalg.norm(gap))
            if d < best_d and accept(gap, d, geo.tangents(cs)[0]):
                best, best_d = s, d
        return best, best_d

    def add_hidden_links(self, max_gap_m: float, min_alignment: float = 0.8, speed_mps: float = 13.9) -> int:
        """Join dead ends to lane starts further along the same direction (an unmapped stretch of
        road between mapped patches) with hidden connectors; returns how many were added."""
        g = self.graph
        ends, starts = self._dead_ends_and_sources()
        added = 0
        for e in ends:
            c = g.nodes[e]["centerline_xy"]
            p_end, t_end = c[-1], geo.tangents(c)[-1]

            def ahead(gap: np.ndarray, d: float, t_start: np.ndarray, t_end: np.ndarray = t_end) -> bool:
                if d < 5.0:
                    return False
                u = gap / d
                return float(np.dot(u, t_end)) > min_alignment and float(np.dot(u, t_start)) > min_alignment

            best, best_d = self._nearest_start(p_end, starts, max_gap_m, ahead)
            if best is None:
                continue
            cs = g.nodes[best]["centerline_xy"]
            link = geo.bezier_cubic(p_end, t_end, cs[0], geo.tangents(cs)[0], 1.0)
            lid = self.add_lane(link, speed_mps, g.nodes[e]["width_m"], "link", visible=False)
            self.connect(e, lid)
            self.connect(lid, best)
            added += 1
        return added

    def add_turnarounds(self, max_gap_m: float = 40.0) -> int:
        """Join each dead end to the nearest lane start heading back (hidden U-turn connector)."""
        g = self.graph
        ends, starts = self._dead_ends_and_sources()
        added = 0
        for e in ends:
            c = g.nodes[e]["centerline_xy"]
            p_end, t_end = c[-1], geo.tangents(c)[-1]
            best, best_d = self._nearest_start(
                p_end,
                starts,
                max_gap_m,
                cast(
                    Callable[[np.ndarray, float, np.ndarray], bool],
                    lambda _gap, _d, t_start, t_end=t_end: float(np.dot(t_start, t_end)) < -0.5,
                ),
            )
            if best is None:
                continue
            cs = g.nodes[best]["centerline_xy"]
            radius = max(best_d / 2.0, 6.0)
            # push the U-turn out beyond the dead end so it is a proper loop, not a kink
            mid = np.array([p_end + t_end * radius * 1.2, cs[0] + t_end * radius * 1.2])
            loop = geo.resample(
                np.vstack([p_end, geo.chaikin(np.vstack([p_end, mid, cs[0]]), 4)[1:-1], cs[0]]), 1.0
            )
            lid = self.add_lane(loop, 4.0, g.nodes[e]["width_m"], "turnaround", visible=False)
            self.connect(e, lid)
            self.connect(lid, best)
            added += 1
        return added

    def build(
        self, name: str, origin_lat: float, origin_lon: float, canyon_zones_xyr: np.ndarray | None = None
    ) -> World:
        world = World(
            name=name,
            origin_lat=origin_lat,
            origin_lon=origin_lon,
            elements=tuple(self.elements),
            lane_graph=self.graph,
            canyon_zones_xyr=np.zeros((0, 3))
            if canyon_zones_xyr is None
            else np.asarray(canyon_zones_xyr, float),
        )
        log.debug("built world %s: %s", name, world.summary())
        return world
