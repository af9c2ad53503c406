"""Tile arithmetic, the Python MVT encoder (known answers, clipping, y axis, collapse), ETags,
bbox parsing, change detection: no database."""

from __future__ import annotations

import hashlib

import mapbox_vector_tile
import mercantile
import numpy as np
import pytest
from shapely.geometry import LineString, Polygon, shape

from services.api.errors import ApiError
from services.db.versions import MapFeature, VersionFeature, as_stored, change_type, geometry_changed
from services.tiles import mvt
from services.tiles.http import parse_bbox
from services.tiles.mercator import buffered_bounds_lonlat, lonlat_to_m, tile_bounds_m, valid_tile
from services.tiles.render import TileCache, etag_matches, make_etag

pytestmark = pytest.mark.unit

TILE = mercantile.tile(8.40, 49.01, 16)


def at(fx: float, fy: float, tile: mercantile.Tile = TILE) -> tuple[float, float]:
    b = mercantile.xy_bounds(tile)
    return mercantile.lnglat(b.left + fx * (b.right - b.left), b.top - fy * (b.top - b.bottom))


def feature(fid: str, geometry, type_: str = "lane_divider", style: str | None = None, **props) -> MapFeature:
    return MapFeature(VersionFeature(fid, type_, style, props, geometry), 1, 16, TILE.x, TILE.y, 1)


def decoded(body: bytes) -> dict[str, dict]:
    layer = mapbox_vector_tile.decode(body, default_options={"y_coord_down": True})["road"]
    return {f["properties"]["id"]: f for f in layer["features"]}


def test_tile_bounds_match_mercantile():
    for z, x, y in ((0, 0, 0), (16, TILE.x, TILE.y), (22, 2**21 + 5, 2**21 - 7)):
        np.testing.assert_allclose(tile_bounds_m(z, x, y), tuple(mercantile.xy_bounds(x, y, z)), atol=1e-6)
    np.testing.assert_allclose(lonlat_to_m(np.array([[8.4, 49.01]]))[0], mercantile.xy(8.4, 49.01), atol=1e-6)
    w, s, e, n = buffered_bounds_lonlat(16, TILE.x, TILE.y, buffer_frac=0.0)
    np.testing.assert_allclose((w, s, e, n), tuple(mercantile.bounds(TILE)), atol=1e-9)
    assert valid_tile(22, 0, 2**22 - 1) and not valid_tile(23, 0, 0) and not valid_tile(2, 4, 0)


def test_known_answer_line_y_down_and_properties():
    line = LineString([at(0.25, 0.25), at(0.75, 0.5)])
    body = mvt.encode_python(
        [feature("a", line, style="dashed", support=3, sigma_m=0.25, ok=True, nested={"x": 1}, none=None)],
        z=16,
        x=TILE.x,
        y=TILE.y,
    )
    got = decoded(body)["a"]
    assert got["geometry"] == {"type": "LineString", "coordinates": [[1024, 1024], [3072, 2048]]}
    assert got["properties"] == {
        "id": "a",
        "type": "lane_divider",
        "style": "dashed",
        "support": 3,
        "sigma_m": 0.25,
        "ok": True,
    }
    assert got["id"] == int(hashlib.md5(b"a").hexdigest()[:12], 16) < 2**48


def test_clipped_to_the_buffer_and_children_tiles():
    line = LineString([at(-1.0, 0.5), at(2.0, 0.5)])  # crosses the tile and both neighbours
    got = decoded(mvt.encode_python([feature("a", line)], z=16, x=TILE.x, y=TILE.y))["a"]
    assert got["geometry"]["coordinates"] == [[-256, 2048], [4096 + 256, 2048]]
    child = mercantile.children(TILE)[0]  # north-west: the line runs along its south edge
    got = decoded(mvt.encode_python([feature("a", line)], z=17, x=child.x, y=child.y))["a"]
    assert got["geometry"]["coordinates"] == [[-256, 4096], [4096 + 256, 4096]]


def test_polygon_round_trip_and_winding():
    square = Polygon([at(0.25, 0.25), at(0.5, 0.25), at(0.5, 0.5), at(0.25, 0.5)])
    got = decoded(mvt.encode_python([feature("p", square, "crosswalk")], z=16, x=TILE.x, y=TILE.y))["p"]
    assert got["geometry"]["type"] == "Polygon"
    assert shape(got["geometry"]).equals(Polygon([(1024, 1024), (2048, 1024), (2048, 2048), (1024, 2048)]))


def test_empty_and_collapsed_tiles_are_none():
    assert mvt.encode_python([], z=16, x=TILE.x, y=TILE.y) is None
    short = LineString([at(0.5, 0.5), at(0.50001, 0.5)])  # far under a pixel at zoom 10
    parent = mercantile.parent(TILE, zoom=10)
    assert mvt.encode_python([feature("a", short)], z=10, x=parent.x, y=parent.y) is None
    outside = LineString([at(3.0, 0.5), at(4.0, 0.5)])
    assert mvt.encode_python([feature("a", outside)], z=16, x=TILE.x, y=TILE.y) is None


def test_etags_and_if_none_match():
    a = make_etag("mvt", 16, 1, 2, [(16, 1, 2, 3, 40)], "python")
    assert a.startswith('"') and a.endswith('"') and len(a) == 34
    assert a == make_etag("mvt", 16, 1, 2, [(16, 1, 2, 3, 40)], "python")
    others = [
        make_etag("mvt", 16, 1, 2, [(16, 1, 2, 4, 41)], "python"),
        make_etag("geojson", 16, 1, 2, [(16, 1, 2, 3, 40)], "python"),
        make_etag("mvt", 16, 1, 2, [(16, 1, 2, 3, 40)], "postgis"),
        make_etag("mvt", 16, 1, 2, [], "python"),
    ]
    assert a not in others
    assert etag_matches(a, a) and etag_matches(f'"x", W/{a}', a) and etag_matches("*", a)
    assert not etag_matches('"x"', a)


def test_tile_cache_evicts_least_recently_used():
    cache = TileCache(max_bytes=100, max_entries=3)
    for i in range(3):
        cache.put(f"e{i}", bytes(10))
    assert cache.get("e0") == (True, bytes(10))
    cache.put("e3", None)  # e1 is the least recently used
    assert cache.get("e1") == (False, None) and cache.get("e3") == (True, None)
    cache.put("big", bytes(60))  # over a quarter of the budget: not kept
    assert cache.get("big") == (False, None)


@pytest.mark.parametrize(
    "raw", ["1,2,3", "a,b,c,d", "0,0,inf,1", "2,0,1,1", "0,1,1,0", "0,0,1,1", "-200,0,1,1"]
)
def test_bad_bboxes(raw: str):
    with pytest.raises(ApiError) as err:
        parse_bbox(raw)
    assert err.value.status == 422 and err.value.location == "query.bbox"


def test_good_bbox():
    assert parse_bbox("8.39,49.0,8.41,49.02") == (8.39, 49.0, 8.41, 49.02)


def test_change_types():
    base = VersionFeature("f", "lane_divider", "solid", {}, LineString([(8.4, 49.01), (8.401, 49.01)]))
    nudged = VersionFeature(
        "f", "lane_divider", "solid", {"support": 9}, LineString([(8.4, 49.01 + 2e-9), (8.401, 49.01)])
    )  # 0.2 mm, new properties
    moved = VersionFeature(
        "f", "lane_divider", "solid", {}, LineString([(8.4, 49.01 + 5e-8), (8.401, 49.01)])
    )
    restyled = VersionFeature("f", "lane_divider", "dashed", {}, base.geometry)
    assert change_type(None, base) == "added"
    assert change_type(base, as_stored(nudged)) == "unchanged"
    assert change_type(base, moved) == "modified"  # 5.6 mm
    assert change_type(base, restyled) == "modified"
    assert geometry_changed(base.geometry, Polygon([(8.4, 49.01), (8.401, 49.01), (8.401, 49.011)]))
