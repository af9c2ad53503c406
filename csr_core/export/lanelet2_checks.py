"""Lanelet2's validator checks (``lanelet2_validation``), run on a map loaded with the
``lanelet2`` package, and the routing figures of a map.

The PyPI wheel ships no ``lanelet2.validation``, so the checks are re-implemented here with the
names, thresholds and severities of Lanelet2's validators:

| check | severity | rule |
| --- | --- | --- |
| ``mapping.mandatory_tags`` | warning | lanelets and areas: ``type``, ``subtype``, ``location``; regulatory elements: ``type``, ``subtype``; line strings: ``type`` |
| ``mapping.bool_tags`` | warning | ``one_way``, ``participant:*``, ``lane_change``, ``dynamic``, ``fallback``, ``temporary`` read as a bool |
| ``mapping.duplicated_points`` | error | a line string or polygon holds one point twice in succession |
| ``mapping.points_too_close`` | warning | a point's nearest other point is closer than 0.05 m |
| ``mapping.curvature_too_big`` | warning | a lanelet bound's Menger curvature above 0.5 1/m at a vertex |
| ``routing_graph.routing_graph_is_valid`` | error | ``RoutingGraph.checkValidity()`` (German vehicle rules): relations mutual, no lanelet both adjacent and following, ... |

plus load errors of ``lanelet2.io.loadRobust`` (error; then the curvature and routing checks do
not run, as ``lanelet2`` cannot route on a lanelet whose bound did not load). ``nodes_within_1mm`` counts points whose
nearest other point is closer than 1 mm (stacked nodes).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

POINTS_TOO_CLOSE_M = 0.05  # lanelet2_validation PointsTooCloseChecker
STACKED_M = 0.001  # nodes closer than this are stacked (one node written twice)
MAX_CURVATURE_PER_M = 0.5  # lanelet2_validation CurvatureTooBigChecker
MANDATORY_TAGS = {
    "lanelet": ("type", "subtype", "location"),
    "area": ("type", "subtype", "location"),
    "regulatory_element": ("type", "subtype"),
    "line_string": ("type",),
}
BOOL_TAG_PREFIXES = ("one_way", "dynamic", "lane_change", "participant", "fallback", "temporary")
BOOL_VALUES = frozenset({"yes", "no", "true", "false", "1", "0"})


class Severity(enum.Enum):
    ERROR = "error"
    WARNING = "warning"


@dataclass(frozen=True, slots=True)
class Issue:
    severity: Severity
    check: str  # Lanelet2's validator name, e.g. ``mapping.points_too_close``
    primitive: str  # lanelet, area, regulatory_element, line_string, polygon, point, map
    primitive_id: int  # 0 where the issue names no primitive
    message: str

    def __str__(self) -> str:
        where = f"{self.primitive} {self.primitive_id}" if self.primitive_id else self.primitive
        return f"{self.severity.value}: {self.check}: {where}: {self.message}"


@dataclass(frozen=True, slots=True)
class Lanelet2Checks:
    """The issues of a map (all of them) and its counts."""

    issues: tuple[Issue, ...]
    lanelets: int
    road_lanelets: int
    crosswalk_lanelets: int
    areas: int
    regulatory_elements: int
    nodes_within_1mm: int

    @property
    def n_errors(self) -> int:
        return sum(1 for i in self.issues if i.severity == Severity.ERROR)

    @property
    def n_warnings(self) -> int:
        return sum(1 for i in self.issues if i.severity == Severity.WARNING)

    def counts_by_check(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for i in self.issues:
            out[i.check] = out.get(i.check, 0) + 1
        return dict(sorted(out.items()))

    def as_dict(self, max_issues: int = 20) -> dict[str, Any]:
        return {
            "errors": self.n_errors,
            "warnings": self.n_warnings,
            "by_check": self.counts_by_check(),
            "first": [str(i) for i in self.issues[:max_issues]],
            "lanelets": self.lanelets,
            "road_lanelets": self.road_lanelets,
            "crosswalk_lanelets": self.crosswalk_lanelets,
            "areas": self.areas,
            "regulatory_elements": self.regulatory_elements,
            "nodes_within_1mm": self.nodes_within_1mm,
        }


@dataclass(frozen=True, slots=True)
class RoutingFigures:
    """Routing over the road lanelets (German vehicle rules): the share of sampled ordered pairs
    (a, b), a != b, with a route from a to b, and the largest strongly connected component."""

    road_lanelets: int
    pairs_sampled: int
    routable_share: float
    largest_scc: int
    with_successor: int  # road lanelets with at least one following lanelet
    with_lane_change: int  # road lanelets with a left or right lane-change neighbour


def load_lanelet2(path: str | Path, origin_lat: float, origin_lon: float) -> tuple[Any, list[str]]:
    """(LaneletMap, load errors) with a LocalCartesian projector at the origin."""
    import lanelet2.io
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    lmap, errors = lanelet2.io.loadRobust(str(path), LocalCartesianProjector(Origin(origin_lat, origin_lon)))
    return lmap, list(errors)


def vehicle_routing_graph(lmap: Any) -> Any:
    import lanelet2.routing
    import lanelet2.traffic_rules as rules

    return lanelet2.routing.RoutingGraph(
        lmap, rules.create(rules.Locations.Germany, rules.Participants.Vehicle)
    )


def _attrs(prim: Any) -> dict[str, str]:
    return {str(k): str(v) for k, v in prim.attributes.items()}


def check_mandatory_tags(lmap: Any) -> list[Issue]:
    layers = (
        ("lanelet", lmap.laneletLayer),
        ("area", lmap.areaLayer),
        ("regulatory_element", lmap.regulatoryElementLayer),
        ("line_string", lmap.lineStringLayer),
    )
    out = []
    for kind, layer in layers:
        for prim in layer:
            attrs = _attrs(prim)
            for tag in MANDATORY_TAGS[kind]:
                if tag not in attrs:
                    out.append(
                        Issue(
                            Severity.WARNING,
                            "mapping.mandatory_tags",
                            kind,
                            prim.id,
                            f"should have a {tag} attribute",
                        )
                    )
    return out


def check_bool_tags(lmap: Any) -> list[Issue]:
    out = []
    for kind, layer in (
        ("line_string", lmap.lineStringLayer),
        ("lanelet", lmap.laneletLayer),
        ("area", lmap.areaLayer),
    ):
        for prim in layer:
            for k, v in _attrs(prim).items():
                if k.startswith(BOOL_TAG_PREFIXES) and v.lower() not in BOOL_VALUES:
                    out.append(
                        Issue(
                            Severity.WARNING,
                            "mapping.bool_tags",
                            kind,
                            prim.id,
                            f"attribute {k}: {v} is not a bool",
                        )
                    )
    return out


def _first_repeat(ids: list[int]) -> int | None:
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        if a == b:
            return a
    return None


def check_duplicated_points(lmap: Any) -> list[Issue]:
    out = []
    for kind, layer in (("line_string", lmap.lineStringLayer), ("polygon", lmap.polygonLayer)):
        for prim in layer:
            dup = _first_repeat([p.id for p in prim])
            if dup is not None:
                out.append(
                    Issue(
                        Severity.ERROR,
                        "mapping.duplicated_points",
                        kind,
                        prim.id,
                        f"contains the point {dup} multiple times in succession",
                    )
                )
    return out


def _nearest_other(lmap: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point ids (P,), their nearest other point's id (P,) and distance (P,), in the plane."""
    pts = list(lmap.pointLayer)
    if len(pts) < 2:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    ids = np.array([p.id for p in pts], int)
    xy = np.array([[p.x, p.y] for p in pts], float)
    dist, idx = cKDTree(xy).query(xy, k=2)
    return ids, ids[idx[:, 1]], dist[:, 1]


def check_points_too_close(lmap: Any) -> tuple[list[Issue], int]:
    """Issues, and the number of points stacked within ``STACKED_M`` of another."""
    ids, other, dist = _nearest_other(lmap)
    close = np.flatnonzero(dist < POINTS_TOO_CLOSE_M)
    issues = [
        Issue(
            Severity.WARNING,
            "mapping.points_too_close",
            "point",
            int(ids[k]),
            f"is {dist[k] * 1000:.1f} mm from point {int(other[k])}",
        )
        for k in close
    ]
    return issues, int(np.sum(dist < STACKED_M))


def menger_curvature(xy: np.ndarray) -> np.ndarray:
    """Curvature (1/m) of the circle through each three consecutive points of ``xy (N, 2)``:
    ``4 * area / (|ab| |bc| |ca|)`` (N - 2,), as Lanelet2's ``geometry::curvature2d``; infinite
    where two of the three points coincide."""
    a, b, c = xy[:-2], xy[1:-1], xy[2:]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    prod = np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - b, axis=1) * np.linalg.norm(c - a, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(prod < 1e-20, np.inf, 2.0 * area2 / prod)


def check_curvature(lmap: Any) -> list[Issue]:
    out = []
    for ll in lmap.laneletLayer:
        for bound in (ll.leftBound, ll.rightBound):
            if len(bound) < 3:
                continue
            xy = np.array([[p.x, p.y] for p in bound], float)
            for k in np.flatnonzero(np.abs(menger_curvature(xy)) > MAX_CURVATURE_PER_M):
                out.append(
                    Issue(
                        Severity.WARNING,
                        "mapping.curvature_too_big",
                        "lanelet",
                        ll.id,
                        f"curvature at point {bound[int(k) + 1].id} is bigger than {MAX_CURVATURE_PER_M}",
                    )
                )
    return out


def check_routing_graph(graph: Any) -> list[Issue]:
    return [
        Issue(Severity.ERROR, "routing_graph.routing_graph_is_valid", "map", 0, str(e))
        for e in graph.checkValidity(False)
    ]


def check_lanelet2_map(lmap: Any, load_errors: Sequence[str] = ()) -> Lanelet2Checks:
    """All checks on a loaded map (see the module doc)."""
    issues = [Issue(Severity.ERROR, "io.load", "map", 0, str(e)) for e in load_errors]
    issues += check_mandatory_tags(lmap)
    issues += check_bool_tags(lmap)
    issues += check_duplicated_points(lmap)
    close, stacked = check_points_too_close(lmap)
    issues += close
    if not load_errors:
        # geometry and routing need whole primitives: lanelet2 crashes on a lanelet whose bound
        # did not load
        issues += check_curvature(lmap)
        issues += check_routing_graph(vehicle_routing_graph(lmap))
    subtypes = [
        str(ll.attributes["subtype"]) if "subtype" in ll.attributes else "" for ll in lmap.laneletLayer
    ]
    return Lanelet2Checks(
        issues=tuple(sorted(issues, key=lambda i: (i.severity != Severity.ERROR, i.check))),
        lanelets=len(subtypes),
        road_lanelets=sum(1 for s in subtypes if s == "road"),
        crosswalk_lanelets=sum(1 for s in subtypes if s == "crosswalk"),
        areas=len(lmap.areaLayer),
        regulatory_elements=len(lmap.regulatoryElementLayer),
        nodes_within_1mm=stacked,
    )


def check_lanelet2_file(path: str | Path, origin_lat: float, origin_lon: float) -> Lanelet2Checks:
    lmap, errors = load_lanelet2(path, origin_lat, origin_lon)
    return check_lanelet2_map(lmap, errors)


def routing_figures(lmap: Any, n_sources: int | None = 40, seed: int = 0) -> RoutingFigures:
    """Routing figures of the road lanelets: per sampled source lanelet (``n_sources``, seeded;
    None: every road lanelet),
    ``reachableSet`` gives its routable targets; the share counts every other road lanelet as a
    target. The lane graph for the strongly connected components has Lanelet2's routable
    relations: following and lane changes (left/right)."""
    graph = vehicle_routing_graph(lmap)
    roads = [
        ll for ll in lmap.laneletLayer if "subtype" in ll.attributes and ll.attributes["subtype"] == "road"
    ]
    n = len(roads)
    g: nx.DiGraph = nx.DiGraph()
    g.add_nodes_from(ll.id for ll in roads)
    road_ids = {ll.id for ll in roads}
    with_succ = with_change = 0
    for ll in roads:
        following = [f.id for f in graph.following(ll, False) if f.id in road_ids]
        sideways = [x.id for x in (graph.left(ll), graph.right(ll)) if x is not None and x.id in road_ids]
        g.add_edges_from((ll.id, t) for t in following + sideways)
        with_succ += bool(following)
        with_change += bool(sideways)
    largest = max((len(c) for c in nx.strongly_connected_components(g)), default=0)
    if n < 2:
        return RoutingFigures(n, 0, 0.0, largest, with_succ, with_change)
    rng = np.random.default_rng(seed)
    sources = np.arange(n) if n_sources is None else rng.choice(n, size=min(n_sources, n), replace=False)
    routable = 0
    for k in sources:
        reach = {x.id for x in graph.reachableSet(roads[int(k)], math.inf, 0, True)}  # lane changes allowed
        routable += len((reach & road_ids) - {roads[int(k)].id})
    pairs = len(sources) * (n - 1)
    return RoutingFigures(n, pairs, routable / pairs, largest, with_succ, with_change)
