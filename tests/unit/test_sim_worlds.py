"""Simulator worlds: truth maps and lane graphs."""

import networkx as nx
import numpy as np
import pytest

from csr_core.sim import WORLD_NAMES, load_world
from csr_core.sim.world import SUCCESSOR
from csr_core.types import ElementType

pytestmark = pytest.mark.unit

PROCEDURAL = ("urban", "highway", "rural", "roundabout")
REAL_MAPS = ("karlsruhe", "kashiwanoha", "carcarana", "a9")  # shipped in csr_core/sim/data


def _successor_graph(world) -> nx.DiGraph:
    g = world.lane_graph
    return g.edge_subgraph([(u, v) for u, v, d in g.edges(data=True) if d["kind"] == SUCCESSOR])


def _load(name):
    # the real maps ship in csr_core/sim/data; missing, the test fails
    return load_world(name)


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_world_builds_with_truth_and_a_connected_lane_graph(name):
    world = _load(name)
    g = world.lane_graph
    assert g.number_of_nodes() >= 8
    counts = world.summary()["elements"]
    for t in ("lane_divider", "road_boundary", "centerline"):
        assert counts[t] > 0, t
    for e in world.elements:
        assert e.points_xy_world.shape[1] == 2 and len(e.points_xy_world) >= 2
        assert np.isfinite(e.points_xy_world).all()
        assert (e.style is not None) == (e.type == ElementType.LANE_DIVIDER)
        if e.type.is_polygon:
            assert len(e.points_xy_world) >= 3
            assert not np.allclose(e.points_xy_world[0], e.points_xy_world[-1])
    # routes never get stuck: lanes lie on cycles (procedural worlds: all of them)
    on_cycles = sum(len(c) for c in nx.strongly_connected_components(g) if len(c) >= 4)
    assert on_cycles >= (0.3 if name in REAL_MAPS else 1.0) * g.number_of_nodes()
    # same-direction neighbours exist where there are multi-lane roads
    kinds = {d["kind"] for _, _, d in g.edges(data=True)}
    if name in ("urban", "highway", "karlsruhe"):
        assert {"left", "right"} <= kinds
    assert -90 < world.origin_lat < 90 and -180 < world.origin_lon < 180


def test_urban_has_intersections_with_stop_lines_and_crosswalks():
    world = load_world("urban")
    counts = world.summary()["elements"]
    assert counts["stop_line"] >= 20 and counts["crosswalk"] >= 20
    succ = _successor_graph(world)
    assert max(d for _, d in succ.out_degree()) >= 3  # straight, left, right


def test_highway_has_a_split_and_a_merge():
    succ = _successor_graph(load_world("highway"))
    visible = {n for n, d in load_world("highway").lane_graph.nodes(data=True) if d["visible"]}
    assert any(succ.out_degree(n) >= 2 for n in visible if n in succ)
    assert any(succ.in_degree(n) >= 2 for n in visible if n in succ)


def test_roundabout_ring_is_a_cycle():
    world = load_world("roundabout")
    ring = [n for n, d in world.lane_graph.nodes(data=True) if d["road_type"] == "roundabout"]
    sub = _successor_graph(world).subgraph(ring)
    cycles = list(nx.simple_cycles(sub))
    assert cycles and max(len(c) for c in cycles) >= 8


def test_rural_is_a_curvy_loop_with_no_overtaking_zones():
    world = load_world("rural")
    styles = {e.style.value for e in world.elements_of(ElementType.LANE_DIVIDER)}
    assert {"dashed", "solid"} <= styles
    assert nx.number_strongly_connected_components(world.lane_graph) == 2  # one cycle per direction
    assert world.road_length_km() > 8.0  # both directions


def test_karlsruhe_counts_match_the_lanelet2_file():
    world = _load("karlsruhe")
    s = world.summary()
    assert s["elements"]["stop_line"] == 28
    assert 8 <= s["elements"]["crosswalk"] <= 30
    assert s["elements"]["lane_divider"] > 150
    assert s["elements"]["road_boundary"] > 400
    assert 4.0 < s["element_km"]["centerline"] < 6.5  # "about 5 km of road lanelets"
    assert abs(world.origin_lat - 49.0064) < 0.01 and abs(world.origin_lon - 8.43) < 0.02
