"""Lanelet2's validator checks (csr_core.export.lanelet2_checks): each check fails on a crafted
bad file and passes on its repaired twin; the export of a road passes them all; a solid divider
forbids the lane change a dashed one allows (Lanelet2's routing graph)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from csr_core.export import LonLatFeature, export_lanelet2
from csr_core.export.lanelet2_checks import (
    Lanelet2Checks,
    Severity,
    check_lanelet2_file,
    load_lanelet2,
    menger_curvature,
    vehicle_routing_graph,
)
from csr_core.geo import LocalFrame
from csr_core.types import DividerStyle, ElementType

pytestmark = pytest.mark.unit

FRAME = LocalFrame(48.1374, 11.5755)
ROAD = (("type", "lanelet"), ("subtype", "road"), ("location", "urban"), ("one_way", "yes"))


def _osm(
    nodes: dict[int, tuple[float, float]],
    ways: dict[int, list[int]],
    lanelets: dict[int, tuple[int, int, tuple[tuple[str, str], ...]]],
    way_tags: dict[int, tuple[tuple[str, str], ...]] | None = None,
) -> bytes:
    """An OSM file: nodes in metres of FRAME, ways (default tags ``type=line_thin solid``),
    lanelets (left way, right way, tags)."""
    out = ["<?xml version='1.0' encoding='UTF-8'?>", "<osm version='0.6'>"]
    for nid, xy in nodes.items():
        lon, lat = FRAME.to_lonlat(np.array([xy], float))[0]
        out.append(f"<node id='{nid}' lat='{lat:.10f}' lon='{lon:.10f}'/>")
    for wid, refs in ways.items():
        tags = (way_tags or {}).get(wid, (("type", "line_thin"), ("subtype", "solid")))
        out.append(
            f"<way id='{wid}'>"
            + "".join(f"<nd ref='{r}'/>" for r in refs)
            + "".join(f"<tag k='{k}' v='{v}'/>" for k, v in tags)
            + "</way>"
        )
    for rid, (left, right, tags) in lanelets.items():
        out.append(
            f"<relation id='{rid}'><member type='way' ref='{left}' role='left'/>"
            f"<member type='way' ref='{right}' role='right'/>"
            + "".join(f"<tag k='{k}' v='{v}'/>" for k, v in tags)
            + "</relation>"
        )
    out.append("</osm>")
    return "\n".join(out).encode()


def _check(xml: bytes, tmp_path: Path) -> Lanelet2Checks:
    path = tmp_path / "map.osm"
    path.write_bytes(xml)
    return check_lanelet2_file(path, FRAME.origin_lat, FRAME.origin_lon)


def _lane(y_left: float = 3.5, length: float = 20.0) -> tuple[dict, dict]:
    """One lanelet along +x between y = 0 (right) and ``y_left``, three vertices per bound."""
    nodes = {
        1: (0, y_left),
        2: (length / 2, y_left),
        3: (length, y_left),
        4: (0, 0),
        5: (length / 2, 0),
        6: (length, 0),
    }
    return nodes, {10: [1, 2, 3], 11: [4, 5, 6]}


def _checks_of(c: Lanelet2Checks, name: str) -> list:
    return [i for i in c.issues if i.check == name]


def test_a_clean_lanelet_has_no_issue(tmp_path):
    nodes, ways = _lane()
    c = _check(_osm(nodes, ways, {20: (10, 11, ROAD)}), tmp_path)
    assert c.issues == () and (c.lanelets, c.road_lanelets, c.nodes_within_1mm) == (1, 1, 0)


def test_mandatory_tags(tmp_path):
    nodes, ways = _lane()
    crosswalk = (("type", "lanelet"), ("subtype", "crosswalk"), ("one_way", "no"))  # no location
    c = _check(_osm(nodes, ways, {20: (10, 11, crosswalk)}, {10: (("subtype", "solid"),)}), tmp_path)
    found = {(i.primitive, i.primitive_id, i.message) for i in _checks_of(c, "mapping.mandatory_tags")}
    assert found == {
        ("lanelet", 20, "should have a location attribute"),
        ("line_string", 10, "should have a type attribute"),
    }
    assert c.n_errors == 0 and c.n_warnings == 2  # Lanelet2 rates them warnings


def test_bool_tags(tmp_path):
    nodes, ways = _lane()
    tags = (*ROAD[:3], ("one_way", "maybe"))
    c = _check(_osm(nodes, ways, {20: (10, 11, tags)}), tmp_path)
    assert [i.primitive_id for i in _checks_of(c, "mapping.bool_tags")] == [20]


def test_duplicated_points(tmp_path):
    nodes, ways = _lane()
    ways[10] = [1, 2, 2, 3]
    c = _check(_osm(nodes, ways, {20: (10, 11, ROAD)}), tmp_path)
    dup = _checks_of(c, "mapping.duplicated_points")
    assert [(i.severity, i.primitive_id) for i in dup] == [(Severity.ERROR, 10)]


def test_points_too_close_and_stacked(tmp_path):
    nodes, ways = _lane()
    nodes[7] = (10.0, 3.53)  # 3 cm from node 2: too close, not stacked
    nodes[8] = (20.0, 0.0005)  # 0.5 mm from node 6: stacked
    ways[12] = [7, 8]
    c = _check(_osm(nodes, ways, {20: (10, 11, ROAD)}), tmp_path)
    assert {i.primitive_id for i in _checks_of(c, "mapping.points_too_close")} == {2, 7, 6, 8}
    assert c.nodes_within_1mm == 2


def test_curvature(tmp_path):
    nodes, ways = _lane()
    nodes[2] = (10.0, 4.5)  # a 1 m kink over 10 m: curvature 0.02 1/m, fine
    assert not _checks_of(
        _check(_osm(nodes, ways, {20: (10, 11, ROAD)}), tmp_path), "mapping.curvature_too_big"
    )
    nodes[2], nodes[13] = (1.0, 4.5), (2.0, 3.5)  # a 1 m tooth: the circle through it has radius 1 m
    ways[10] = [1, 2, 13, 3]
    c = _check(_osm(nodes, ways, {20: (10, 11, ROAD)}), tmp_path)
    assert [i.primitive_id for i in _checks_of(c, "mapping.curvature_too_big")] == [20]
    # Menger curvature, known answers: three points on a circle of radius 2; a straight line
    a = np.array([0.0, 1.0, 2.0])
    on_circle = np.column_stack([2 * np.cos(a), 2 * np.sin(a)])
    np.testing.assert_allclose(np.abs(menger_curvature(on_circle)), 0.5)
    np.testing.assert_allclose(menger_curvature(np.array([[0, 0], [1, 0], [3, 0]], float)), 0.0)


def test_routing_graph_relation_not_mutual(tmp_path):
    """Two lanelets with the very same bounds beside a third: the third's left neighbour is
    ambiguous, which RoutingGraph.checkValidity() reports (the exporter skips such a duplicate)."""
    nodes, ways = _lane()
    nodes.update({7: (0, -3.5), 8: (10, -3.5), 9: (20, -3.5)})
    ways[12] = [7, 8, 9]
    dashed = {11: (("type", "line_thin"), ("subtype", "dashed"))}
    good = {20: (10, 11, ROAD), 22: (11, 12, ROAD)}
    assert _check(_osm(nodes, ways, good, dashed), tmp_path).n_errors == 0
    c = _check(_osm(nodes, ways, {**good, 21: (10, 11, ROAD)}, dashed), tmp_path)
    routing = _checks_of(c, "routing_graph.routing_graph_is_valid")
    assert routing and all(i.severity == Severity.ERROR for i in routing)


def test_load_errors_are_errors(tmp_path):
    nodes, ways = _lane()
    c = _check(_osm(nodes, ways, {20: (10, 99, ROAD)}), tmp_path)  # way 99 does not exist
    errors = [i for i in c.issues if i.severity == Severity.ERROR]
    assert errors and {i.check for i in errors} == {"io.load"}
    assert any("99" in i.message for i in errors)


# --- the exporter's output ----------------------------------------------------------------------


def _line(
    type_: ElementType, xy, style: DividerStyle | None = None, fid: str = "", props=None
) -> LonLatFeature:
    return LonLatFeature(type_, FRAME.to_lonlat(np.asarray(xy, float)), style, fid, dict(props or {}))


def _straight(y: float, x0: float = 0.0, x1: float = 60.0) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, 5.0)
    return np.column_stack([x, np.full(len(x), y)])


def _two_lanes(divider: DividerStyle) -> list[LonLatFeature]:
    """Two lanes east (y = 0, 3.5) between curbs, ``divider`` between them; the curb's end points
    lie 2 cm from the divider's (nodes that the export writes as one)."""
    cl = ElementType.CENTERLINE
    return [
        _line(cl, _straight(0.0), fid="right"),
        _line(cl, _straight(3.5), fid="left"),
        _line(ElementType.ROAD_BOUNDARY, _straight(-1.75), fid="curb_s"),
        _line(ElementType.LANE_DIVIDER, _straight(1.75), divider, fid="divider"),
        _line(ElementType.ROAD_BOUNDARY, _straight(5.25), fid="curb_n"),
        _line(ElementType.STOP_LINE, [[59.0, -1.75], [59.0, 1.77]], fid="stop"),
    ]


def _export_and_load(features: list[LonLatFeature], tmp_path: Path):
    xml, m = export_lanelet2(features)
    path = tmp_path / "export.osm"
    path.write_bytes(xml)
    lmap, errors = load_lanelet2(path, m.frame.origin_lat, m.frame.origin_lon)
    assert errors == []
    return lmap, check_lanelet2_file(path, m.frame.origin_lat, m.frame.origin_lon), m


def _by_centerline(lmap) -> dict:
    return {
        ll.attributes["csr:centerline_id"]: ll
        for ll in lmap.laneletLayer
        if "csr:centerline_id" in ll.attributes
    }


def test_a_dashed_divider_allows_the_lane_change_a_solid_one_forbids(tmp_path):
    for style, allowed in ((DividerStyle.DASHED, True), (DividerStyle.SOLID, False)):
        lmap, checks, _ = _export_and_load(_two_lanes(style), tmp_path)
        assert checks.n_errors == 0 and checks.nodes_within_1mm == 0, checks.issues
        graph = vehicle_routing_graph(lmap)
        lanes = _by_centerline(lmap)
        assert (graph.left(lanes["right"]) is not None) is allowed, style
        assert (graph.right(lanes["left"]) is not None) is allowed, style
        assert (graph.getRoute(lanes["right"], lanes["left"]) is not None) is allowed, style


def test_export_merges_nodes_closer_than_lanelet2_allows(tmp_path):
    feats = _two_lanes(DividerStyle.DASHED)
    # a second stop line 1 cm beside the first's end: its end node and the first's become one
    feats.append(_line(ElementType.STOP_LINE, [[59.01, 1.77], [59.0, 5.25]], fid="stop2"))
    _, checks, m = _export_and_load(feats, tmp_path)
    assert m.report.nodes_merged >= 1
    assert not _checks_of(checks, "mapping.points_too_close") and checks.nodes_within_1mm == 0


def test_export_skips_a_second_centreline_of_the_same_lane(tmp_path):
    feats = _two_lanes(DividerStyle.DASHED)
    feats.append(_line(ElementType.CENTERLINE, _straight(0.1), fid="right_again"))
    _, checks, m = _export_and_load(feats, tmp_path)
    assert m.report.runs_skipped == {"duplicate of another lane": 1}
    assert checks.n_errors == 0, checks.issues


def test_routing_figures_known_answers(tmp_path):
    """Two lanelets side by side: across a dashed divider each reaches the other (every pair
    routable, one component of two); across a solid one neither (no pair, components of one)."""
    from csr_core.export.lanelet2_checks import routing_figures

    for style, share, scc, change in ((DividerStyle.DASHED, 1.0, 2, 2), (DividerStyle.SOLID, 0.0, 1, 0)):
        lmap, _, _ = _export_and_load(_two_lanes(style), tmp_path)
        r = routing_figures(lmap)
        assert (r.road_lanelets, r.pairs_sampled) == (2, 2)
        assert routing_figures(lmap, n_sources=1).pairs_sampled == 1  # one source, one other lanelet
        assert routing_figures(lmap, n_sources=None) == r  # every lanelet a source
        assert (r.routable_share, r.largest_scc, r.with_lane_change, r.with_successor) == (
            share,
            scc,
            change,
            0,
        )
