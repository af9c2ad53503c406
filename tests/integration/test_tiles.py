"""The read side over HTTP on both deployments (embedded SQLite, PostGIS): ``GET /v1/map``,
``/v1/tiles/{z}/{x}/{y}.mvt`` (decoded with mapbox_vector_tile) and ``.geojson``, TileJSON, ETag /
304, 204, CORS, version-pinned URLs, roles. Versions are written by hand through
``services.db.versions.write_tile_version`` (what the merge job calls) into a deployment of this
module's own (so no other test's tiles mix in)."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import httpx
import mapbox_vector_tile
import mercantile
import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Polygon, shape
from sqlalchemy.orm import Session, sessionmaker

from services.db import versions as vs
from services.db.engine import make_engine, make_session_factory
from services.tiles import fastpath, render
from tests.integration.conftest import Deployment, PgDatabases, make_deployment

pytestmark = pytest.mark.integration

LON, LAT = 8.40, 49.01  # Karlsruhe
BASE = mercantile.tile(LON, LAT, 16)


@dataclass
class Tiled:
    """A running deployment, a session factory on its database, and keys."""

    dep: Deployment
    sessions: sessionmaker[Session]
    reader: str
    vehicle: str
    _next: Iterator[int]

    @property
    def postgres(self) -> bool:
        return self.dep.db_url.startswith("postgresql")

    def fresh_tile(self) -> mercantile.Tile:
        """A zoom-16 tile no other test of the module uses (east of Karlsruhe, 3 tiles apart)."""
        return mercantile.Tile(BASE.x + 3 * next(self._next), BASE.y, 16)

    def http(self, key: str | None = None) -> httpx.Client:
        return self.dep.client(key or self.reader)

    def write(self, tile: mercantile.Tile, features: Sequence[vs.VersionFeature], **kw) -> vs.TileVersion:
        args: dict[str, Any] = dict(
            reason="merge",
            job_id="job-test",
            trips=["trip-a"],
            corrections=[],
            quality={"ok": True},
            origin_lat=LAT,
            origin_lon=LON,
            state=b"state",
            publish=True,
        )
        args.update(kw)
        if "expected_latest" not in args:
            with self.sessions() as session:
                head = vs.tile_head(session, z=tile.z, x=tile.x, y=tile.y)
                args["expected_latest"] = head.latest_version if head else None
        with self.sessions.begin() as session:
            version = vs.write_tile_version(session, z=tile.z, x=tile.x, y=tile.y, features=features, **args)
            session.expunge(version)
        return version

    def map_version(self) -> int:
        with self.sessions() as session:
            return vs.current_map_version(session)


def start_tiled(kind: str, tmp, pg: PgDatabases, redis_url: str) -> Iterator[Tiled]:
    dep = make_deployment(kind, tmp, pg, redis_url)
    try:
        dep.start_server()
        engine = make_engine(dep.db_url)
        with dep.admin() as http:
            reader = http.post("/v1/keys", json={"role": "reader"}).raise_for_status().json()["key"]
            vehicle = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-t"}).json()["key"]
        yield Tiled(dep, make_session_factory(engine), reader, vehicle, itertools.count(1))
        engine.dispose()
    finally:
        dep.stop()


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def tiled(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    """This module's own deployment of each kind (API only: no jobs run here)."""
    yield from start_tiled(
        request.param, tmp_path_factory.mktemp(f"tiles-{request.param}"), pg, shared_redis_url
    )


def frac(tile: mercantile.Tile, fx: float, fy: float) -> tuple[float, float]:
    """lon, lat of the point at fractions (fx from west, fy from north) of the tile (in mercator)."""
    b = mercantile.xy_bounds(tile)
    return mercantile.lnglat(b.left + fx * (b.right - b.left), b.top - fy * (b.top - b.bottom))


def road(tile: mercantile.Tile, *, shift: float = 0.0) -> list[vs.VersionFeature]:
    """Three lines and a crosswalk polygon inside ``tile`` (``shift``: fraction of the tile north)."""

    def line(*pts):
        return LineString([frac(tile, fx, fy - shift) for fx, fy in pts])

    return [
        vs.VersionFeature(
            f"t{tile.x}-b1",
            "road_boundary",
            None,
            {"support": 4, "sigma_m": 0.2, "flags": ["low_support", "gap"]},
            line((0.1, 0.40), (0.5, 0.41), (0.9, 0.40)),
        ),
        vs.VersionFeature(
            f"t{tile.x}-d1",
            "lane_divider",
            "dashed",
            {"support": 3, "flags": {"seam": 1}},
            line((0.1, 0.50), (0.9, 0.50)),
        ),
        vs.VersionFeature(
            f"t{tile.x}-c1", "centerline", None, {"support": 3}, line((0.1, 0.55), (0.9, 0.55))
        ),
        vs.VersionFeature(
            f"t{tile.x}-x1",
            "crosswalk",
            None,
            {"support": 5, "painted": True},
            Polygon(
                [frac(tile, fx, fy - shift) for fx, fy in ((0.3, 0.3), (0.4, 0.3), (0.4, 0.6), (0.3, 0.6))]
            ),
        ),
    ]


def eventually(call, done, *, within_s: float = fastpath.LIVE_TTL_S + 2.0):
    """``call()`` until ``done(answer)``, for at most ``within_s``: a write made by another process
    reaches the server's cached ETags and keys at once on SQLite, by NOTIFY on PostgreSQL, and
    at the latest after the caches' time-to-live (``services.tiles.fastpath``)."""
    deadline = time.monotonic() + within_s
    while True:
        answer = call()
        if done(answer) or time.monotonic() > deadline:
            return answer
        time.sleep(0.05)


def decode(body: bytes) -> dict[str, dict]:
    layers = mapbox_vector_tile.decode(body, default_options={"y_coord_down": True})
    assert set(layers) == {"road"}
    assert layers["road"]["extent"] == 4096
    return {f["properties"]["id"]: f for f in layers["road"]["features"]}


def tile_units(tile: mercantile.Tile, lonlat: Sequence[float]) -> np.ndarray:
    b = mercantile.xy_bounds(tile)
    x, y = mercantile.xy(*lonlat)
    return np.array([(x - b.left) / (b.right - b.left) * 4096, (b.top - y) / (b.top - b.bottom) * 4096])


# --- MVT ------------------------------------------------------------------------------------------


def test_mvt_decodes_to_the_written_features(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = road(tile)
    tiled.write(tile, features)
    with tiled.http() as http:
        response = http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/vnd.mapbox-vector-tile"
    decoded = decode(response.content)
    assert set(decoded) == {f.feature_id for f in features}
    for f in features:
        got = decoded[f.feature_id]
        expected_type = "Polygon" if f.type == "crosswalk" else "LineString"
        assert got["geometry"]["type"] == expected_type
        assert got["properties"]["type"] == f.type
        assert got["properties"].get("style") == f.style
        assert got["properties"]["support"] == f.properties["support"]
        if isinstance(f.properties.get("flags"), list):  # the validator's flags: their JSON text
            assert got["properties"]["flags"] == '["low_support", "gap"]'
        else:
            assert "flags" not in got["properties"]  # other nested values stay out of the tile
        assert got["id"] == int(__import__("hashlib").md5(f.feature_id.encode()).hexdigest()[:12], 16)
        coords = got["geometry"]["coordinates"]
        ring = coords[0] if expected_type == "Polygon" else coords
        exterior = f.geometry.exterior.coords if expected_type == "Polygon" else f.geometry.coords
        expected = np.array([tile_units(tile, p) for p in exterior])
        # the same vertices, to the tile grid (the polygon ring may start elsewhere / turn the other way)
        got_xy = np.asarray(ring, float)
        dist = np.abs(got_xy[:, None, :] - expected[None, :, :]).max(axis=2).min(axis=1)
        assert dist.max() <= 0.5 + 1e-9, (f.feature_id, got_xy, expected)
    assert decoded[f"t{tile.x}-x1"]["properties"]["painted"] is True


def test_postgis_and_python_encoders_give_the_same_tiles(tiled: Tiled):
    """The SQL tile (ST_AsMVT) and the Python tile of the same versions decode to the same
    features, at the pipeline zoom, a parent and a child (clipped at the buffer)."""
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    child = mercantile.children(tile)[0]  # north-west quarter: the lines cross its edges
    tiles = (tile, mercantile.parent(tile), child, mercantile.children(child)[3])
    pairs = []
    with tiled.sessions() as session:  # closed before the HTTP calls (SQLite: one writer at a time)
        for t in tiles:
            versions = render.tile_versions_for(session, z=t.z, x=t.x, y=t.y, map_version=None)
            python = render.encode_tile(session, z=t.z, x=t.x, y=t.y, versions=versions, backend="python")
            sql = None
            if tiled.postgres:
                sql = render.encode_tile(session, z=t.z, x=t.x, y=t.y, versions=versions, backend="postgis")
            pairs.append((t, python, sql))
    checked = 0
    for t, python, sql in pairs:
        with tiled.http() as http:  # the server's tile: PostGIS on PostgreSQL, Python on SQLite
            served = http.get(f"/v1/tiles/{t.z}/{t.x}/{t.y}.mvt").content
        assert python is not None, t
        for other in (served, sql) if sql is not None else (served,):
            a, b = decode(python), decode(other)
            assert set(a) == set(b) and a, t
            for fid in a:
                assert a[fid]["properties"] == b[fid]["properties"]
                assert a[fid]["id"] == b[fid]["id"]
                ga, gb = shape(a[fid]["geometry"]), shape(b[fid]["geometry"])
                assert ga.geom_type == gb.geom_type
                assert shapely.hausdorff_distance(ga, gb) <= 1.5, (t, fid, ga.wkt, gb.wkt)
                checked += 1
        if sql is not None:
            assert served == sql
    assert checked >= 10


def test_empty_tile_is_204_and_bad_coordinates_are_422(tiled: Tiled):
    with tiled.http() as http:
        empty = http.get("/v1/tiles/16/0/0.mvt")
        assert empty.status_code == 204 and empty.content == b""
        assert empty.headers["etag"].startswith('"')
        assert http.get("/v1/tiles/16/0/0.geojson").status_code == 204
        for path, location in (
            ("/v1/tiles/23/0/0.mvt", "path.z"),
            ("/v1/tiles/3/8/0.mvt", "path.x"),
            ("/v1/tiles/3/0/-1.mvt", "path.y"),
        ):
            bad = http.get(path)
            assert bad.status_code == 422, path
            assert bad.json()["location"] == location


def test_etag_304_cors_and_a_new_version_changes_the_etag(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    with tiled.http() as http:
        first = http.get(url)
        etag = first.headers["etag"]
        assert first.status_code == 200 and etag.startswith('"') and not etag.startswith("W/")
        assert first.headers["cache-control"] == "private, max-age=30"  # keyed data: no shared cache
        assert first.headers["access-control-allow-origin"] == "*"
        assert "ETag" in first.headers["access-control-expose-headers"]
        again = http.get(url)
        assert again.headers["etag"] == etag and again.content == first.content
        cached = http.get(url, headers={"If-None-Match": etag})
        assert cached.status_code == 304 and cached.content == b""
        assert cached.headers["etag"] == etag and cached.headers["access-control-allow-origin"] == "*"
        assert http.get(url, headers={"If-None-Match": '"other", ' + etag}).status_code == 304
        preflight = http.options(
            url, headers={"Origin": "https://viewer.example", "Access-Control-Request-Method": "GET"}
        )
        assert preflight.status_code == 204
        assert "Authorization" in preflight.headers["access-control-allow-headers"]

        tiled.write(tile, road(tile, shift=0.05))  # by another process than the server
        changed = eventually(
            lambda: http.get(url, headers={"If-None-Match": etag}), lambda r: r.status_code == 200
        )
        assert changed.status_code == 200 and changed.headers["etag"] != etag
        assert changed.content != first.content
        # the parent tile contains this one: its ETag follows too; a far tile's does not
        parent = mercantile.parent(tile)
        assert http.get(f"/v1/tiles/{parent.z}/{parent.x}/{parent.y}.mvt").status_code == 200


def test_pinned_tiles_are_immutable(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    pinned_version = tiled.map_version()
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    with tiled.http() as http:
        before = http.get(url, params={"v": pinned_version})
        assert before.status_code == 200
        assert before.headers["cache-control"] == "private, max-age=31536000, immutable"
        assert before.headers["x-map-version"] == str(pinned_version)
        tiled.write(tile, road(tile, shift=0.1))
        after = http.get(url, params={"v": pinned_version})
        assert after.content == before.content and after.headers["etag"] == before.headers["etag"]
        live = http.get(url)
        assert live.content != before.content
        assert http.get(url, params={"v": tiled.map_version()}).content == live.content
        future = http.get(url, params={"v": tiled.map_version() + 1})
        assert future.status_code == 404 and future.json()["location"] == "query.v"
        # before the tile had any version: an empty tile, cacheable forever too
        old = http.get(url, params={"v": 0})
        assert old.status_code == 204 and "immutable" in old.headers["cache-control"]


def test_geojson_tile_has_the_same_features(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = road(tile)
    tiled.write(tile, features)
    with tiled.http() as http:
        gj = http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.geojson")
        mvt = http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt")
    assert gj.status_code == 200 and gj.headers["content-type"] == "application/geo+json"
    doc = gj.json()
    assert doc["type"] == "FeatureCollection"
    assert {f["id"] for f in doc["features"]} == set(decode(mvt.content))
    by_id = {f["id"]: f for f in doc["features"]}
    for f in features:
        got = by_id[f.feature_id]
        assert got["properties"]["type"] == f.type
        assert shape(got["geometry"]).equals_exact(f.geometry, 1e-7)


# --- /v1/map ---------------------------------------------------------------------------------------


def test_map_bbox_and_version_pinning(tiled: Tiled):
    tile = tiled.fresh_tile()
    v1 = road(tile)
    tiled.write(tile, v1)
    version_1 = tiled.map_version()
    tiled.write(tile, road(tile, shift=0.02)[:3])  # moved north, crosswalk removed
    w, s, e, n = mercantile.bounds(tile)
    bbox = f"{w},{s},{e},{n}"
    with tiled.http() as http:
        live = http.get("/v1/map", params={"bbox": bbox})
        old = http.get("/v1/map", params={"bbox": bbox, "version": version_1})
        corner = http.get("/v1/map", params={"bbox": f"{w},{s},{w + (e - w) * 0.05},{s + (n - s) * 0.05}"})
    assert live.status_code == 200 and live.headers["content-type"] == "application/geo+json"
    live_doc, old_doc = live.json(), old.json()
    assert live_doc["type"] == "FeatureCollection" and live_doc["map_version"] == tiled.map_version()
    assert {f["id"] for f in live_doc["features"]} == {f.feature_id for f in v1[:3]}
    assert {f["id"] for f in old_doc["features"]} == {f.feature_id for f in v1}
    assert "immutable" in old.headers["cache-control"]
    types = {f["properties"]["type"]: f["geometry"]["type"] for f in old_doc["features"]}
    assert types == {
        "road_boundary": "LineString",
        "lane_divider": "LineString",
        "centerline": "LineString",
        "crosswalk": "Polygon",
    }
    for f in old_doc["features"]:
        assert f["properties"]["id"] == f["id"] and f["properties"]["support"] >= 3
        assert f["properties"]["tile"] == f"{tile.z}/{tile.x}/{tile.y}"
    old_by_id = {f["id"]: f for f in old_doc["features"]}
    boundary = f"t{tile.x}-b1"
    assert shape(old_by_id[boundary]["geometry"]).equals_exact(v1[0].geometry, 1e-7)
    assert old_by_id[f"t{tile.x}-d1"]["properties"]["style"] == "dashed"
    assert corner.json()["features"] == []  # nothing in the south-west corner of the tile


@pytest.mark.parametrize(
    "bbox,why",
    [
        ("8.4,49.0,8.41", "3 numbers"),
        ("8.4,49.0,8.41,x", "not a number"),
        ("8.4,49.0,nan,49.1", "non-finite"),
        ("8.41,49.0,8.40,49.1", "minlon < maxlon"),
        ("8.4,49.1,8.41,49.0", "minlat < maxlat"),
        ("7.0,48.0,9.0,50.0", "over the limit"),
        ("-181,0,1,1", "-180"),
    ],
)
def test_map_rejects_bad_bboxes(tiled: Tiled, bbox: str, why: str):
    with tiled.http() as http:
        response = http.get("/v1/map", params={"bbox": bbox})
    assert response.status_code == 422
    body = response.json()
    assert body["error"] == "invalid_request" and body["location"] == "query.bbox"
    assert body["message"].startswith("bbox:") and why in body["message"]


def test_map_version_in_the_future_is_404(tiled: Tiled):
    with tiled.http() as http:
        response = http.get(
            "/v1/map", params={"bbox": "8.39,49.0,8.41,49.02", "version": tiled.map_version() + 5}
        )
    assert response.status_code == 404 and response.json()["location"] == "query.version"


# --- TileJSON ----------------------------------------------------------------------------------------


def test_tilejson(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    with tiled.http() as http:
        doc = http.get("/v1/tiles.json").raise_for_status().json()
        current = tiled.map_version()
        assert doc["tilejson"] == "3.0.0" and doc["scheme"] == "xyz"
        assert doc["map_version"] == current
        assert doc["tiles"] == [f"{tiled.dep.base_url}/v1/tiles/{{z}}/{{x}}/{{y}}.mvt?v={current}"]
        assert (doc["minzoom"], doc["maxzoom"]) == (0, 22)
        w, s, e, n = mercantile.bounds(tile)
        west, south, east, north = doc["bounds"]
        assert west <= w and south <= s and east >= e and north >= n and east - west < 1.0
        (layer,) = doc["vector_layers"]
        assert layer["id"] == "road" and {"id", "type", "style", "support"} <= set(layer["fields"])
        # how the viewer shows each validator flag kind
        levels = doc["flag_levels"]
        assert levels["trips_disagree"] == levels["implausible_lane_width"] == "severe"
        assert levels["low_support"] == levels["degraded_support"] == "warning"
        assert levels["gap"] == levels["outlier_trip"] == "info"
        # the template works
        url = doc["tiles"][0].format(z=tile.z, x=tile.x, y=tile.y).removeprefix(tiled.dep.base_url)
        assert http.get(url).status_code == 200


# --- roles -----------------------------------------------------------------------------------------


READS = [
    "/v1/tiles/16/0/0.mvt",
    "/v1/tiles/16/0/0.geojson",
    "/v1/tiles.json",
    "/v1/map?bbox=8.39,49.0,8.41,49.02",
    f"/v1/tiles/16/{BASE.x}/{BASE.y}/versions",
    "/v1/changes?since=0",
    "/v1/features/none",
]


@pytest.mark.parametrize("path", READS)
def test_reads_need_a_reader_key(tiled: Tiled, path: str):
    with tiled.dep.client() as anonymous:
        assert anonymous.get(path).status_code == 401
    with tiled.http(tiled.vehicle) as vehicle:
        assert vehicle.get(path).status_code == 403
    with tiled.http() as reader:
        assert reader.get(path).status_code in (200, 204, 404)
