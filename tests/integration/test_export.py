"""The Lanelet2 export over HTTP (``GET /v1/export/lanelet2``) on a map written through
``services.db.versions.write_tile_version``, and ``csr export`` on a simulated scenario."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import mercantile
import numpy as np
import orjson
import pytest
from shapely.geometry import LineString, Polygon

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


def _road(frame: LocalFrame) -> list[vs.VersionFeature]:
    """A 100 m road east: two lanes east, one west (centrelines), curbs, a dashed divider, a double
    centre line, a stop line and a crosswalk (as in tests/unit/test_lanelet2_export.py)."""

    def ll(xy) -> list[tuple[float, float]]:
        return [tuple(p) for p in frame.to_lonlat(np.asarray(xy, float)).tolist()]

    def straight(y, x0=0.0, x1=100.0):
        x = np.arange(x0, x1 + 1e-9, 5.0)
        return np.column_stack([x, np.full(len(x), y)])

    def f(fid, type_, xy, style=None):
        return vs.VersionFeature(fid, type_, style, {"support": 3}, LineString(ll(xy)))

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
            "zebra", "crosswalk", None, {}, Polygon(ll([[97, -1.75], [100, -1.75], [100, 8.75], [97, 8.75]]))
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
    assert out.read_bytes().startswith(b"<?xml")
    bad = subprocess.run(
        [*csr, "export", str(tmp_path / "missing.geojson"), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "csr export" in bad.stderr
