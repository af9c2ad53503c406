"""Real-map worlds on the shipped files: what each loader makes of its map (element counts per
type, measured on the files in ``csr_core/sim/data``), lane graph connectivity, routes of the
requested length, and a short simulated trip whose uploads are valid against the schema."""

import gzip
import json
import pathlib
import tomllib

import jsonschema
import networkx as nx
import numpy as np
import orjson
import pytest

import csr_core
from csr_core.sim import commonroad_world, gnss_calibration, lanelet2_world, load_world, simulate_scenario
from csr_core.sim.profiles import get_profile
from csr_core.sim.routes import random_route
from csr_core.sim.world import LEFT, SUCCESSOR
from csr_core.types import DividerStyle, ElementType
from csr_core.upload import decode_trip, validate_upload_json

pytestmark = pytest.mark.unit

ROOT = pathlib.Path(__file__).resolve().parents[2]
PACKAGE = pathlib.Path(csr_core.__file__).resolve().parent
SCHEMA = PACKAGE / "schemas" / "trip-upload.schema.json"
NEW_MAPS = ("kashiwanoha", "carcarana", "a9")

# measured on the shipped files: element counts per type
COUNTS = {
    "kashiwanoha": {"centerline": 77, "lane_divider": 29, "road_boundary": 9, "stop_line": 2, "crosswalk": 4},
    "carcarana": {"centerline": 368, "lane_divider": 57, "road_boundary": 38, "stop_line": 0, "crosswalk": 0},
    "a9": {"centerline": 32, "lane_divider": 24, "road_boundary": 4, "stop_line": 0, "crosswalk": 0},
}


def _successor_graph(world) -> nx.DiGraph:
    g = world.lane_graph
    return g.edge_subgraph([(u, v) for u, v, d in g.edges(data=True) if d["kind"] == SUCCESSOR])


def test_shipped_data_lives_inside_the_package_with_licences():
    paths = [
        lanelet2_world.DEFAULT_OSM,
        lanelet2_world.KASHIWANOHA_OSM,
        commonroad_world.CARCARANA_XML,
        commonroad_world.A9_XML,
        gnss_calibration.DEFAULT_SEGMENT / "global_pose" / "frame_positions",
    ]
    for path in paths:
        assert path.is_file(), path
        assert path.resolve().is_relative_to(PACKAGE / "sim" / "data"), path  # never ../shared
    for folder in sorted((PACKAGE / "sim" / "data").iterdir()):
        if folder.is_dir():
            assert (folder / "LICENSE").is_file() and (folder / "SOURCES.txt").is_file(), folder
    assert "OpenStreetMap" in (commonroad_world.CARCARANA_XML.parent / "SOURCES.txt").read_text()
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "sim/data/**/*" in package_data["csr_core"]


@pytest.mark.parametrize("name", NEW_MAPS)
def test_element_counts_per_type_match_the_shipped_file(name):
    world = load_world(name)
    counts = world.summary()["elements"]
    assert {k: counts[k] for k in COUNTS[name]} == COUNTS[name]
    assert counts["road_marking"] == 0
    for e in world.elements:
        assert np.isfinite(e.points_xy_world).all() and len(e.points_xy_world) >= 2
        assert (e.style is not None) == (e.type == ElementType.LANE_DIVIDER)


def test_kashiwanoha_lanelets_crosswalks_and_styles():
    world = load_world("kashiwanoha")
    assert abs(world.origin_lat - 35.9033) < 1e-3 and abs(world.origin_lon - 139.9336) < 1e-3
    assert world.road_length_km() == pytest.approx(1.65, abs=0.01)  # "~1.65 km of lanelets"
    styles = [e.style for e in world.elements_of(ElementType.LANE_DIVIDER)]
    assert styles.count(DividerStyle.SOLID) == 26 and styles.count(DividerStyle.DASHED) == 3
    for cw in world.elements_of(ElementType.CROSSWALK):
        extent = cw.points_xy_world.max(axis=0) - cw.points_xy_world.min(axis=0)
        assert 2.0 < extent.min() and extent.max() < 20.0


def test_kashiwanoha_directions_agree_with_the_lanelet2_library():
    """Left-hand traffic needs no option: each lane runs the way the lanelet2 library's
    centreline does (its left bound on its left)."""
    import lanelet2
    from lanelet2.io import Origin
    from lanelet2.projection import UtmProjector

    from csr_core.geo import LocalFrame

    world = load_world("kashiwanoha")
    proj = UtmProjector(Origin(world.origin_lat, world.origin_lon))
    lanelet_map, _ = lanelet2.io.loadRobust(str(lanelet2_world.KASHIWANOHA_OSM), proj)
    frame = LocalFrame(world.origin_lat, world.origin_lon)
    lanes = [d["centerline_xy"] for _, d in world.lane_graph.nodes(data=True) if d["visible"]]
    starts, ends = np.array([c[0] for c in lanes]), np.array([c[-1] for c in lanes])
    n_road = 0
    for ll in lanelet_map.laneletLayer:
        if ll.attributes["subtype"] != "road":
            continue
        n_road += 1
        c = ll.centerline
        gps = [proj.reverse(lanelet2.core.BasicPoint3d(p.x, p.y, 0.0)) for p in (c[0], c[len(c) - 1])]
        a, b = frame.to_local(np.array([[g.lon, g.lat] for g in gps]))
        assert np.min(np.linalg.norm(starts - a, axis=1) + np.linalg.norm(ends - b, axis=1)) < 1.0
    assert n_road == 77


def test_kashiwanoha_lane_graph():
    g = load_world("kashiwanoha").lane_graph
    assert g.number_of_nodes() == 77  # no hidden connectors: no dead end has a lane start behind it
    assert max(len(c) for c in nx.strongly_connected_components(g)) == 69
    assert sum(1 for _, _, k in g.edges(data="kind") if k == LEFT) == 3


def test_carcarana_grid_is_one_strongly_connected_network():
    world = load_world("carcarana")
    g = world.lane_graph
    assert (world.origin_lat, world.origin_lon) == (-32.85679, -61.15331)
    assert world.road_length_km() == pytest.approx(15.74, abs=0.01)  # "15.7 km of lanelets"
    assert nx.is_strongly_connected(g) and g.number_of_nodes() == 368 + 22  # 22 hidden turnarounds
    road_types = [d["road_type"] for _, d in g.nodes(data=True)]
    assert road_types.count("urban_junction") == 254  # lanelets inside the 24 intersections
    succ = _successor_graph(world)
    assert max(d for _, d in succ.out_degree()) >= 3  # straight, left, right
    # derived dividers: one per pair of opposite lanelets outside intersections, dashed
    assert {e.style for e in world.elements_of(ElementType.LANE_DIVIDER)} == {DividerStyle.DASHED}


def test_a9_is_a_multi_lane_carriageway_with_a_split():
    world = load_world("a9")
    g = world.lane_graph
    assert (world.origin_lat, world.origin_lon) == (48.25, 11.64)
    assert world.road_length_km() == pytest.approx(10.95, abs=0.01)  # "11 km of lanelets"
    assert sum(1 for _, _, k in g.edges(data="kind") if k == LEFT) == 24
    succ = _successor_graph(world)
    assert any(succ.out_degree(n) >= 2 for n in succ)  # a lane split
    assert max(len(c) for c in nx.strongly_connected_components(g)) == 6


@pytest.mark.parametrize(
    ("name", "length_m"), [("kashiwanoha", 1000.0), ("carcarana", 1500.0), ("a9", 1500.0)]
)
def test_routes_of_the_requested_length_are_drivable(name, length_m):
    world = load_world(name)
    traffic = get_profile("standard").traffic
    for seed in range(3):
        route = random_route(world, np.random.default_rng(seed), length_m, traffic)
        steps = np.linalg.norm(np.diff(route.path_xy, axis=0), axis=1)
        assert steps.sum() >= length_m - 1.0
        assert steps.max() < 1.0  # continuous


@pytest.mark.parametrize("name", NEW_MAPS)
def test_a_short_trip_gives_uploads_valid_against_the_schema(name, tmp_path):
    out = tmp_path / name
    simulate_scenario(name, 1, "standard", 5, out, trip_length_m=200.0)
    validator = jsonschema.Draft202012Validator(
        json.loads(SCHEMA.read_text()), format_checker=jsonschema.FormatChecker()
    )
    trips = sorted((out / "trips").glob("*.json.gz"))
    assert len(trips) == 1
    body = gzip.decompress(trips[0].read_bytes())
    validator.validate(orjson.loads(body))
    trip = decode_trip(validate_upload_json(body))
    assert trip.n_frames > 100
    assert sum(len(f) for f in trip.elements) > 0
    kinds = {
        f["properties"]["type"] for f in json.loads((out / "truth" / "map.geojson").read_text())["features"]
    }
    assert {k for k, n in COUNTS[name].items() if n} <= kinds


def test_outline_boundaries_known_answer():
    """Two opposite 50 m lanelets side by side: the outline's two long sides are the boundaries;
    the caps at both ends are cut off, and so is a side named as painted."""
    from csr_core.sim.drivable_area import lanelet_polygon, outline_boundaries

    x = np.linspace(0.0, 50.0, 11)
    centre, north, south = (np.column_stack([x, np.full_like(x, y)]) for y in (0.0, 3.5, -3.5))
    polygons = [lanelet_polygon(north, centre), lanelet_polygon(centre[::-1], south[::-1])]
    caps = [np.array([[0.0, -3.5], [0.0, 3.5]]), np.array([[50.0, -3.5], [50.0, 3.5]])]
    lines = outline_boundaries(polygons, caps)
    assert len(lines) == 2
    for line in lines:
        assert np.allclose(np.abs(line[:, 1]), 3.5, atol=0.06)
        assert np.ptp(line[:, 0]) == pytest.approx(50.0 - 2 * 0.3, abs=0.1)  # caps cut with 0.3 m tolerance
    assert len(outline_boundaries(polygons, caps, [north])) == 1
