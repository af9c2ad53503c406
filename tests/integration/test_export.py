"""The Lanelet2 export over HTTP (``GET /v1/export/lanelet2``) on a map written through
``services.db.versions.write_tile_version``, and ``csr export`` on a simulated scenario."""

from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import mercantile
import numpy as np
import orjson
import pytest
from shapely.geometry import LineString, Point, Polygon

from csr_core.export import validate_lanelet2_osm
from csr_core.geo import LocalFrame
from services.db import versions as vs
from tests.integration.conftest import PgDatabases
from tests.integration.test_tiles import Tiled, start_tiled

pytestmark = pytest.mark.integration

TILE = mercantile.tile(8.46, 49.02, 16)  # north-east of the tiles test_tiles.py uses


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def tiled(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    yield from start_tiled(
        request.param, tmp_path_factory.mktemp(f"export-{request.param}"), pg, shared_redis_url
    )


def _road(frame: LocalFrame, prefix: str = "", dy: float = 0.0) -> list[vs.VersionFeature]:
    """A 100 m road east: two lanes east, one west (centrelines), curbs, a dashed divider, a double
    centre line, a stop line and a crosswalk (as in tests/unit/test_lanelet2_export.py); ids with
    ``prefix``, ``dy`` metres north."""

    def ll(xy) -> list[tuple[float, float]]:
        return [tuple(p) for p in frame.to_lonlat(np.asarray(xy, float) + [0.0, dy]).tolist()]

    def straight(y, x0=0.0, x1=100.0):
        x = np.arange(x0, x1 + 1e-9, 5.0)
        return np.column_stack([x, np.full(len(x), y)])

    def f(fid, type_, xy, style=None):
        return vs.VersionFeature(
            prefix + fid, type_, style, {"support_trips": 3, "uncertainty_m": 0.1}, LineString(ll(xy))
        )

    return [
        f("e0", "centerline", straight(0.0)),
        f("e1", "centerline", straight(3.5)),
        f("w0", "centerline", straight(7.0)[::-1]),
        f("curb_s", "road_boundary", straight(-1.75)),
        f("curb_n", "road_boundary", straight(8.75)),
        f("dash", "lane_divider", straight(1.75), "dashed"),
        f("centre", "lane_divider", straight(5.25), "double"),
        f("stop", "stop_line", [[95.0, -1.5], [95.0, 5.0]]),
        vs.VersionFeature(
            prefix + "zebra",
            "crosswalk",
            None,
            {},
            Polygon(ll([[97, -1.75], [100, -1.75], [100, 8.75], [97, 8.75]])),
        ),
    ]


def test_lanelet2_export_of_the_live_map(tiled: Tiled):
    b = mercantile.bounds(TILE)
    frame = LocalFrame(origin_lat=(b.south + b.north) / 2, origin_lon=(b.west + b.east) / 2)
    tiled.write(TILE, _road(frame))
    bbox = f"{b.west},{b.south},{b.east},{b.north}"
    with tiled.http() as http:
        r = http.get("/v1/export/lanelet2", params={"bbox": bbox})
        assert r.status_code == 200, r.text
        assert r.headers["content-type"].startswith("application/xml")
        assert "attachment" in r.headers["content-disposition"] and ".osm" in r.headers["content-disposition"]
        report = orjson.loads(r.headers["x-lanelet2-report"])
        assert (report["lanelets"], report["crosswalks"], report["stop_lines"]) == (3, 1, 1)
        assert report["runs_skipped"] == {}
        v = validate_lanelet2_osm(r.content)
        assert v.ok, v.problems
        assert v.n_lanelets == 4
        # an empty box: a valid, empty file
        far = mercantile.bounds(mercantile.Tile(TILE.x + 40, TILE.y, 16))
        r = http.get("/v1/export/lanelet2", params={"bbox": f"{far.west},{far.south},{far.east},{far.north}"})
        assert r.status_code == 200 and orjson.loads(r.headers["x-lanelet2-report"])["lanelets"] == 0
        assert validate_lanelet2_osm(r.content).ok
        r = http.get("/v1/export/lanelet2", params={"bbox": "1,2,3"})
        assert r.status_code == 422 and r.json()["location"] == "query.bbox"
    with tiled.http(tiled.vehicle) as http:
        assert http.get("/v1/export/lanelet2", params={"bbox": bbox}).status_code == 403
    with tiled.dep.client(None) as http:
        assert http.get("/v1/export/lanelet2", params={"bbox": bbox}).status_code == 401


def test_csr_export_command_on_a_simulated_scenario(tmp_path: Path):
    csr = [str(Path(sys.executable).parent / "csr")]
    scen = tmp_path / "urban"
    subprocess.run(
        [*csr, "simulate", "--world", "urban", "--trips", "1", "--seed", "1", "--out", str(scen)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    out = tmp_path / "urban.osm"
    done = subprocess.run(
        [*csr, "export", "--scenario-dir", str(scen), "--out", str(out), "--validate", "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    report = orjson.loads(done.stdout)
    assert report["input"].endswith("truth/map.geojson")
    assert report["lanelets"] > 400 and report["runs_skipped"] == {}
    assert report["validation"]["problems"] == 0
    checks = report["lanelet2"]  # Lanelet2's validator checks on the written file
    assert (checks["errors"], checks["nodes_within_1mm"]) == (0, 0), checks["first"]
    assert checks["regulatory_elements"] >= report["stop_lines"] > 0
    assert checks["routing"]["routable_share"] > 0.5
    assert out.read_bytes().startswith(b"<?xml")
    bad = subprocess.run(
        [*csr, "export", str(tmp_path / "missing.geojson"), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "csr export" in bad.stderr


def _osm_lines(xml: bytes) -> tuple[dict[str, set[str]], dict[str, int], list[str]]:
    """Feature id -> the OSM ways carrying it; relation tag counts; every element id."""
    root = ET.fromstring(xml)
    ways: dict[str, set[str]] = {}
    kinds: dict[str, int] = {}
    for w in root.findall("way"):
        tags = {t.get("k", ""): t.get("v", "") for t in w.findall("tag")}
        if "csr:feature_id" in tags:
            ways.setdefault(tags["csr:feature_id"], set()).add(w.get("id", ""))
    centrelines: set[str] = set()
    for r in root.findall("relation"):
        tags = {t.get("k", ""): t.get("v", "") for t in r.findall("tag")}
        kinds[tags.get("subtype", "")] = kinds.get(tags.get("subtype", ""), 0) + 1
        if "csr:centerline_id" in tags:
            centrelines.add(tags["csr:centerline_id"])
    ways["<centrelines>"] = centrelines
    ids = [el.get("id", "") for el in root if el.tag in ("node", "way", "relation")]
    return ways, kinds, ids


def test_pinned_version_export_has_the_lines_of_that_version(tiled: Tiled):
    """Version 1 of a tile, then version 2 without the westbound lane and its centre line: the
    export pinned at version 1 carries exactly the lines GET /v1/map?version=1 gives (ids and
    places), the live export those of version 2."""
    tile = tiled.fresh_tile()
    b = mercantile.bounds(tile)
    frame = LocalFrame(origin_lat=(b.south + b.north) / 2, origin_lon=(b.west + b.east) / 2)
    first = tiled.write(tile, _road(frame))
    second_features = [f for f in _road(frame) if f.feature_id not in ("w0", "curb_n")]
    tiled.write(tile, second_features)
    bbox = f"{b.west},{b.south},{b.east},{b.north}"
    with tiled.http() as http:
        for pinned, expected_ids in ((first.id, {f.feature_id for f in _road(frame)}), (None, None)):
            params: dict[str, str | int] = {"bbox": bbox, **({"version": pinned} if pinned else {})}
            geo = http.get("/v1/map", params=params).json()
            r = http.get("/v1/export/lanelet2", params=params)
            assert r.status_code == 200, r.text
            assert r.headers["x-map-version"] == str(geo["map_version"])
            lines, _, ids = _osm_lines(r.content)
            assert len(ids) == len(set(ids))
            geo_lines = {
                f["id"]: f
                for f in geo["features"]
                if f["properties"]["type"] not in ("centerline", "crosswalk")
            }
            geo_centres = {f["id"] for f in geo["features"] if f["properties"]["type"] == "centerline"}
            assert set(lines) - {"<centrelines>", "zebra"} == set(geo_lines)
            assert lines["<centrelines>"] == geo_centres
            if expected_ids is not None:
                assert set(geo_lines) | geo_centres | {"zebra"} == expected_ids
            else:
                assert "w0" not in geo_centres and "curb_n" not in geo_lines
            # each line's nodes lie on the version's line
            root = ET.fromstring(r.content)
            nodes = {
                n.get("id"): (float(n.get("lon", "")), float(n.get("lat", ""))) for n in root.findall("node")
            }
            for w in root.findall("way"):
                fid = next((t.get("v") for t in w.findall("tag") if t.get("k") == "csr:feature_id"), None)
                if fid not in geo_lines:
                    continue
                line = LineString(frame.to_local(np.array(geo_lines[fid]["geometry"]["coordinates"])))
                xy = frame.to_local(np.array([nodes[nd.get("ref")] for nd in w.findall("nd")]))
                assert max(line.distance(Point(p)) for p in xy) < 0.06, fid  # nodes merge within 5 cm
                version_tag = next(t.get("v", "") for t in w.findall("tag") if t.get("k") == "csr:version")
                assert int(version_tag) <= geo["map_version"]
    assert first.id < tiled.map_version()


def test_export_across_tiles_writes_each_feature_once(tiled: Tiled):
    """Two tiles, each with a road, and one divider written into both tiles' versions: one file
    over both, ids unique, the shared divider once, the lanelets of both roads."""
    west = tiled.fresh_tile()
    east = mercantile.Tile(west.x + 1, west.y, west.z)
    bw, be = mercantile.bounds(west), mercantile.bounds(east)
    frame_w = LocalFrame(origin_lat=(bw.south + bw.north) / 2, origin_lon=(bw.west + bw.east) / 2)
    frame_e = LocalFrame(origin_lat=(be.south + be.north) / 2, origin_lon=(be.west + be.east) / 2)
    shared = next(f for f in _road(frame_w, "w-") if f.feature_id == "w-dash")
    tiled.write(west, _road(frame_w, "w-"))
    tiled.write(east, [*_road(frame_e, "e-"), shared])
    bbox = f"{bw.west},{min(bw.south, be.south)},{be.east},{max(bw.north, be.north)}"
    with tiled.http() as http:
        r = http.get("/v1/export/lanelet2", params={"bbox": bbox})
    assert r.status_code == 200, r.text
    lines, kinds, ids = _osm_lines(r.content)
    assert len(ids) == len(set(ids))
    assert len(lines["w-dash"]) == 1  # one way, though two tile versions hold the feature
    assert kinds["road"] == 6 and kinds["crosswalk"] == 2 and kinds["traffic_sign"] == 2
    report = orjson.loads(r.headers["x-lanelet2-report"])
    assert report["regulatory_elements"] == 2 and report["stop_lines_governing"] == 2
    assert validate_lanelet2_osm(r.content).ok
