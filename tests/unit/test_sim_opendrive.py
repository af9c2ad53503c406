"""The OpenDRIVE reader (known answers on hand-written roads) and the newmarket world built from it."""

import gzip
import json
import pathlib

import jsonschema
import networkx as nx
import numpy as np
import orjson
import pytest
from scipy.integrate import cumulative_trapezoid
from scipy.special import fresnel

from csr_core.sim import geometry as geo
from csr_core.sim import load_world, simulate_scenario
from csr_core.sim.opendrive import (
    GeometryKind,
    OpenDriveError,
    lane_edges_t,
    parse_opendrive,
    points_at_t,
    reference_pose,
)
from csr_core.sim.opendrive_world import NEWMARKET_XODR, opendrive_world
from csr_core.sim.world import SUCCESSOR
from csr_core.types import DividerStyle, ElementType
from csr_core.upload import validate_upload_json

pytestmark = pytest.mark.unit

# the vendored contract schema (test_contract_schema checks it equals the contract's)
SCHEMA = pathlib.Path(__file__).resolve().parents[2] / "csr_core" / "schemas" / "trip-upload.schema.json"


def _road(geometry: str, length: float, lanes: str = "", road_id: str = "1", extra: str = "") -> str:
    lanes = lanes or (
        '<laneSection s="0"><center><lane id="0" type="none"/></center>'
        '<right><lane id="-1" type="driving"><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></right>'
        "</laneSection>"
    )
    return (
        f'<road id="{road_id}" junction="-1" length="{length}">{extra}<planView>{geometry}</planView>'
        f"<lanes>{lanes}</lanes></road>"
    )


def _doc(*roads: str, junctions: str = "") -> str:
    return f'<?xml version="1.0"?><OpenDRIVE><header revMajor="1" revMinor="4"/>{"".join(roads)}{junctions}</OpenDRIVE>'


def _single(geometry: str, length: float, lanes: str = ""):
    return parse_opendrive(_doc(_road(geometry, length, lanes))).roads["1"]


# --- reference lines --------------------------------------------------------------------------


def test_line_runs_along_its_heading():
    hdg = np.pi / 6
    road = _single(f'<geometry s="0" x="1" y="2" hdg="{hdg}" length="10"><line/></geometry>', 10)
    xy, h = reference_pose(road, np.array([0.0, 4.0, 10.0]))
    np.testing.assert_allclose(xy[2], [1 + 10 * np.cos(hdg), 2 + 10 * np.sin(hdg)], atol=1e-12)
    np.testing.assert_allclose(xy[1], [1 + 4 * np.cos(hdg), 2 + 4 * np.sin(hdg)], atol=1e-12)
    np.testing.assert_allclose(h, hdg)


def test_quarter_arc_of_radius_10_ends_at_10_10_heading_north():
    length = (np.pi / 2) * 10.0
    road = _single(
        f'<geometry s="0" x="0" y="0" hdg="0" length="{length}"><arc curvature="0.1"/></geometry>', length
    )
    xy, h = reference_pose(road, np.linspace(0.0, length, 50))
    np.testing.assert_allclose(xy[-1], [10.0, 10.0], atol=1e-9)
    np.testing.assert_allclose(h[-1], np.pi / 2, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(xy - [0.0, 10.0], axis=1), 10.0, atol=1e-9)  # on the circle


def test_spiral_from_zero_curvature_ends_where_fresnel_says():
    length, k_end = 40.0, 0.05
    road = _single(
        f'<geometry s="0" x="0" y="0" hdg="0" length="{length}"><spiral curvStart="0" curvEnd="{k_end}"/></geometry>',
        length,
    )
    xy, h = reference_pose(road, np.array([length]))
    a = np.sqrt(np.pi * length / k_end)  # scale of the standard clothoid with curvature rate k_end / length
    s_frac, c_frac = fresnel(length / a)
    np.testing.assert_allclose(xy[0], [a * c_frac, a * s_frac], atol=1e-9)
    np.testing.assert_allclose(h[0], k_end * length / 2.0, atol=1e-12)


def test_spiral_between_two_curvatures_matches_numerical_integration():
    length, k0, k1, hdg = 30.0, 0.02, -0.03, 0.7
    road = _single(
        f'<geometry s="0" x="5" y="-3" hdg="{hdg}" length="{length}"><spiral curvStart="{k0}" curvEnd="{k1}"/></geometry>',
        length,
    )
    s = np.linspace(0.0, length, 20001)
    theta = hdg + k0 * s + (k1 - k0) / length * s**2 / 2.0
    expected = np.column_stack(
        [
            5 + cumulative_trapezoid(np.cos(theta), s, initial=0),
            -3 + cumulative_trapezoid(np.sin(theta), s, initial=0),
        ]
    )
    xy, h = reference_pose(road, s[::1000])
    np.testing.assert_allclose(xy, expected[::1000], atol=1e-6)
    np.testing.assert_allclose(h, theta[::1000], atol=1e-12)


def test_poly3_and_param_poly3_straight_lines():
    road = _single(
        '<geometry s="0" x="0" y="0" hdg="0" length="10"><poly3 a="0" b="0" c="0" d="0"/></geometry>', 10
    )
    np.testing.assert_allclose(reference_pose(road, np.array([10.0]))[0][0], [10.0, 0.0], atol=1e-6)
    # u = 6 p, v = 8 p over normalized p: a straight line of length 10 along atan2(8, 6), rotated by hdg
    road = _single(
        '<geometry s="0" x="1" y="1" hdg="0.5" length="10">'
        '<paramPoly3 aU="0" bU="6" cU="0" dU="0" aV="0" bV="8" cV="0" dV="0" pRange="normalized"/></geometry>',
        10,
    )
    xy, h = reference_pose(road, np.array([5.0, 10.0]))
    direction = 0.5 + np.arctan2(8, 6)
    np.testing.assert_allclose(xy[1], [1 + 10 * np.cos(direction), 1 + 10 * np.sin(direction)], atol=1e-6)
    np.testing.assert_allclose(xy[0], [1 + 5 * np.cos(direction), 1 + 5 * np.sin(direction)], atol=1e-6)
    np.testing.assert_allclose(h, direction, atol=1e-9)


def test_poly3_with_curvature_keeps_its_written_length():
    road = _single(
        '<geometry s="0" x="0" y="0" hdg="0" length="20"><poly3 a="0" b="0" c="0.01" d="0"/></geometry>', 20
    )
    xy, _ = reference_pose(road, np.linspace(0.0, 20.0, 2001))
    np.testing.assert_allclose(geo.arclength_m(xy)[-1], 20.0, atol=1e-3)
    np.testing.assert_allclose(xy[:, 1], 0.01 * xy[:, 0] ** 2, atol=1e-4)  # on v = c u^2


# --- lanes ------------------------------------------------------------------------------------


def test_lane_width_cubic_in_ds_from_the_section_start_and_lane_offset():
    lanes = (
        '<laneOffset s="0" a="0.5" b="0" c="0" d="0"/>'
        '<laneSection s="0"><center><lane id="0" type="none"/></center>'
        '<right><lane id="-1" type="driving"><width sOffset="0" a="3" b="0" c="0" d="0"/></lane></right></laneSection>'
        '<laneSection s="5"><center><lane id="0" type="none"/></center>'
        '<left><lane id="1" type="driving"><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></left>'
        '<right><lane id="-1" type="driving">'
        '<width sOffset="0" a="3" b="0.1" c="-0.002" d="0.00001"/><width sOffset="20" a="4" b="0" c="0" d="0"/>'
        '</lane><lane id="-2" type="driving"><width sOffset="0" a="2" b="0" c="0" d="0"/></lane></right></laneSection>'
    )
    road = _single('<geometry s="0" x="0" y="0" hdg="0" length="40"><line/></geometry>', 40, lanes)
    assert [sec.s_m for sec in road.sections] == [0.0, 5.0]
    edges = lane_edges_t(road, 1, np.array([15.0, 30.0]))
    width_15 = 3 + 0.1 * 10 - 0.002 * 100 + 0.00001 * 1000  # ds = 10 from the section start
    np.testing.assert_allclose(edges[-1][0], [0.5, 0.5])
    np.testing.assert_allclose(edges[-1][1], [0.5 - width_15, 0.5 - 4.0])
    np.testing.assert_allclose(edges[-2][1], [0.5 - width_15 - 2.0, 0.5 - 6.0])
    np.testing.assert_allclose(edges[1][1], [4.0, 4.0])
    np.testing.assert_allclose(
        points_at_t(road, np.array([15.0]), edges[-1][1][:1]), [[15.0, 0.5 - width_15]]
    )


def test_malformed_documents_raise():
    with pytest.raises(OpenDriveError):
        parse_opendrive("<OpenDRIVE><road")
    with pytest.raises(OpenDriveError):
        parse_opendrive("<Map/>")
    with pytest.raises(OpenDriveError):
        parse_opendrive(
            _doc(_road('<geometry s="0" x="0" y="0" hdg="0" length="5"><clothoid/></geometry>', 5))
        )


# --- links and junctions ----------------------------------------------------------------------

_TWO_WAY = (
    '<laneSection s="0"><center><lane id="0" type="none"><roadMark sOffset="0" type="broken"/></lane></center>'
    '<left><lane id="1" type="driving"><link>{left_link}</link><width sOffset="0" a="4" b="0" c="0" d="0"/>'
    '<roadMark sOffset="0" type="solid"/></lane></left>'
    '<right><lane id="-1" type="driving"><link>{right_link}</link><width sOffset="0" a="4" b="0" c="0" d="0"/>'
    '<roadMark sOffset="0" type="solid"/></lane></right></laneSection>'
)
_ONE_LANE = (
    '<laneSection s="0"><center><lane id="0" type="none"/></center><right><lane id="-1" type="driving">'
    '<link><predecessor id="{pred}"/><successor id="{succ}"/></link>'
    '<width sOffset="0" a="4" b="0" c="0" d="0"/><roadMark sOffset="0" type="none"/></lane></right></laneSection>'
)


def _two_roads_and_a_junction() -> str:
    """Road A (x 0..50) and road B (x 60..110) along +x, one lane each way, joined by junction 7:
    connector 10 (A's lane -1 -> B's lane -1, eastbound) and 11 (B's lane 1 -> A's lane 1, westbound)."""
    a = _road(
        '<geometry s="0" x="0" y="0" hdg="0" length="50"><line/></geometry>',
        50,
        _TWO_WAY.format(left_link="", right_link=""),
        "1",
        '<link><successor elementType="junction" elementId="7"/></link>',
    )
    b = _road(
        '<geometry s="0" x="60" y="0" hdg="0" length="50"><line/></geometry>',
        50,
        _TWO_WAY.format(left_link="", right_link=""),
        "2",
        '<link><predecessor elementType="junction" elementId="7"/></link>',
    )
    east = _road(
        '<geometry s="0" x="50" y="0" hdg="0" length="10"><line/></geometry>',
        10,
        _ONE_LANE.format(pred=-1, succ=-1),
        "10",
        '<link><predecessor elementType="road" elementId="1" contactPoint="end"/>'
        '<successor elementType="road" elementId="2" contactPoint="start"/></link>',
    ).replace('junction="-1"', 'junction="7"')
    west = _road(
        f'<geometry s="0" x="60" y="0" hdg="{np.pi}" length="10"><line/></geometry>',
        10,
        _ONE_LANE.format(pred=1, succ=1),
        "11",
        '<link><predecessor elementType="road" elementId="2" contactPoint="start"/>'
        '<successor elementType="road" elementId="1" contactPoint="end"/></link>',
    ).replace('junction="-1"', 'junction="7"')
    junction = (
        '<junction id="7" name="j"><connection id="0" incomingRoad="1" connectingRoad="10" contactPoint="start">'
        '<laneLink from="-1" to="-1"/></connection><connection id="1" incomingRoad="2" connectingRoad="11" '
        'contactPoint="start"><laneLink from="1" to="-1"/></connection></junction>'
    )
    return _doc(a, b, east, west, junctions=junction)


def test_junction_connections_give_successors_in_both_travel_directions():
    od = parse_opendrive(_two_roads_and_a_junction())
    assert od.junctions["7"].connections[1].lane_links == ((1, -1),)
    world = opendrive_world("toy", _two_roads_and_a_junction(), 44.0, -79.0)
    g = world.lane_graph
    visible = [n for n, d in g.nodes(data=True) if d["visible"]]
    assert len(visible) == 6
    start = {n: tuple(np.round(g.nodes[n]["centerline_xy"][0], 6)) for n in visible}
    by_start = {v: k for k, v in start.items()}
    # world frame: the file shifted by the bounding-box centre (55, 0); lanes 2 m off the reference
    a_east, a_west = by_start[(-55.0, -2.0)], by_start[(-5.0, 2.0)]
    b_east, b_west = by_start[(5.0, -2.0)], by_start[(55.0, 2.0)]
    east, west = by_start[(-5.0, -2.0)], by_start[(5.0, 2.0)]
    succ = {(u, v) for u, v, d in g.edges(data=True) if d["kind"] == SUCCESSOR}
    assert {(a_east, east), (east, b_east), (b_west, west), (west, a_west)} <= succ
    assert g.nodes[east]["road_type"] == "urban_junction"
    # dead ends at x = 0 and x = 110 turn around, so every lane lies on one cycle
    assert nx.number_strongly_connected_components(g) == 1
    dividers = world.elements_of(ElementType.LANE_DIVIDER)
    assert len(dividers) == 2 and {d.style for d in dividers} == {DividerStyle.DASHED}
    assert len(world.elements_of(ElementType.ROAD_BOUNDARY)) == 4  # none inside the junction


# --- the shipped map --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def newmarket_od():
    return parse_opendrive(NEWMARKET_XODR)


def test_newmarket_file_counts(newmarket_od):
    od = newmarket_od
    assert len(od.roads) == 533 and len(od.junctions) == 68
    assert sum(r.in_junction for r in od.roads.values()) == 434
    assert sum(len(j.connections) for j in od.junctions.values()) == 434
    kinds = [g.kind for r in od.roads.values() for g in r.geometries]
    assert (kinds.count(GeometryKind.LINE), kinds.count(GeometryKind.ARC)) == (549, 756)
    assert sum(r.n_objects + r.n_signals for r in od.roads.values()) == 0
    lane_km = (
        sum(
            r.length_m * sum(ln.type == "driving" for sec in r.sections for ln in sec.lanes)
            for r in od.roads.values()
        )
        / 1000.0
    )
    assert lane_km == pytest.approx(31.62, abs=0.02)  # the written road lengths times their driving lanes


def test_newmarket_world_elements_and_lane_graph():
    world = load_world("newmarket")
    s = world.summary()
    assert s["elements"] == {
        "lane_divider": 97,
        "road_boundary": 198,
        "centerline": 630,
        "stop_line": 0,
        "crosswalk": 0,
        "road_marking": 0,
    }
    # measured centrelines: the written 31.62 lane-km, plus the straight bridges over the file's
    # geometry gaps (0.67) and the rebuilt junction connectors
    assert world.road_length_km() == pytest.approx(32.56, abs=0.1)
    styles = {e.style for e in world.elements_of(ElementType.LANE_DIVIDER)}
    assert styles == {DividerStyle.DASHED}
    g = world.lane_graph
    visible = [n for n, d in g.nodes(data=True) if d["visible"]]
    assert len(visible) == 630
    biggest = max(nx.strongly_connected_components(g), key=len)
    lane_m = {n: float(geo.arclength_m(g.nodes[n]["centerline_xy"])[-1]) for n in visible}
    assert sum(lane_m[n] for n in visible if n in biggest) >= 0.98 * sum(lane_m.values())
    for u, v, d in g.edges(data=True):
        if d["kind"] == SUCCESSOR:  # lanes join end to start
            assert np.linalg.norm(g.nodes[u]["centerline_xy"][-1] - g.nodes[v]["centerline_xy"][0]) < 1.0
    xy = np.vstack([e.points_xy_world for e in world.elements])
    assert np.all(np.abs(xy) < 800.0)  # about 1.1 x 1.5 km around the origin
    assert world.origin_lat == pytest.approx(44.05) and world.origin_lon == pytest.approx(-79.46)


def test_a_short_trip_on_newmarket_validates_against_the_upload_schema(tmp_path):
    out = tmp_path / "newmarket"
    simulate_scenario("newmarket", 1, "standard", 3, out, trip_length_m=250.0)
    schema = json.loads(SCHEMA.read_text())
    validator = jsonschema.Draft202012Validator(schema, format_checker=jsonschema.FormatChecker())
    paths = sorted((out / "trips").glob("*.json.gz"))
    assert len(paths) == 1
    body = gzip.decompress(paths[0].read_bytes())
    validate_upload_json(body)
    doc = orjson.loads(body)
    validator.validate(doc)
    assert abs(doc["frames"][0]["gnss"]["lat"] - 44.05) < 0.01
