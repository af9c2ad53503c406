"""HTTP conventions on both deployments: compressed answers by ``Accept-Encoding`` (br, zstd, gzip)
with an ETag and 304 per coding, through the tile fast path and the routes; ``HEAD`` on GET routes;
CORS headers on error answers; the GeoJSON ``bbox`` of the features returned, 7 decimals."""

from __future__ import annotations

import gzip
import itertools
from collections.abc import Iterator

import brotli
import httpx
import mercantile
import numpy as np
import pytest
import zstandard
from fastapi import FastAPI
from fastapi.testclient import TestClient
from shapely.geometry import LineString

from services.api.app import create_app
from services.db import versions as vs
from services.settings import Settings
from tests.integration.conftest import PgDatabases
from tests.integration.test_tiles import Tiled, decode, road, start_tiled

pytestmark = pytest.mark.integration

DECODE = {
    "br": brotli.decompress,
    "gzip": gzip.decompress,
    "zstd": lambda raw: zstandard.ZstdDecompressor().decompressobj().decompress(raw),
}


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def tiled(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    yield from start_tiled(
        request.param, tmp_path_factory.mktemp(f"http-{request.param}"), pg, shared_redis_url
    )


def busy_road(tile: mercantile.Tile, n_lines: int = 40) -> list[vs.VersionFeature]:
    """``n_lines`` wavy dividers across ``tile`` (a tile of several KB), seeded."""
    rng = np.random.default_rng(7)
    bounds = mercantile.bounds(tile)
    features = []
    for i in range(n_lines):
        fx = np.linspace(0.02, 0.98, 60)
        fy = (i + 0.5) / n_lines + 0.004 * np.sin(fx * 20 + i) + rng.normal(0, 0.0005, fx.size)
        lon = bounds.west + fx * (bounds.east - bounds.west)
        lat = bounds.north - fy * (bounds.north - bounds.south)
        features.append(
            vs.VersionFeature(
                f"t{tile.x}-l{i}",
                "lane_divider",
                "dashed" if i % 2 else "solid",
                {"support": int(i % 5) + 2},
                LineString(np.column_stack([lon, lat])),
            )
        )
    return features


def raw_get(http: httpx.Client, url: str, headers: dict[str, str]) -> tuple[httpx.Response, bytes]:
    """The answer and its body as sent (not decoded by httpx)."""
    with http.stream("GET", url, headers=headers) as response:
        return response, b"".join(response.iter_raw())


def test_tiles_are_sent_in_the_negotiated_coding_with_an_etag_per_coding(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = busy_road(tile)
    tiled.write(tile, features)
    base = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}"
    ids = {f.feature_id for f in features}
    # the fast path and FastAPI's route (an extra parameter) answer alike
    for url in (f"{base}.mvt", f"{base}.mvt?route=1", f"{base}.geojson"):
        with tiled.http() as http:
            plain, plain_body = raw_get(http, url, {"Accept-Encoding": "identity"})
            assert plain.status_code == 200 and "content-encoding" not in plain.headers, url
            assert plain.headers["content-length"] == str(len(plain_body)) and len(plain_body) > 4096
            assert "Accept-Encoding" in plain.headers["vary"]
            etag = plain.headers["etag"]
            if url.endswith(".mvt") or "mvt?" in url:
                assert set(decode(plain_body)) == ids
            etags = {etag}
            for coding, unpack in DECODE.items():
                answer, raw = raw_get(http, url, {"Accept-Encoding": f"{coding}, identity;q=0.5"})
                assert answer.status_code == 200 and answer.headers["content-encoding"] == coding, url
                assert answer.headers["content-length"] == str(len(raw)) and len(raw) < len(plain_body)
                assert unpack(raw) == plain_body, (url, coding)
                if ".mvt" in url:
                    assert set(decode(unpack(raw))) == ids
                tag = answer.headers["etag"]
                assert tag == f'{etag[:-1]}-{coding}"' and "Accept-Encoding" in answer.headers["vary"]
                etags.add(tag)
                # 304 for the coding's own tag; the same tag under another coding is a new 200
                cached = http.get(url, headers={"Accept-Encoding": coding, "If-None-Match": tag})
                assert cached.status_code == 304 and cached.headers["etag"] == tag, (url, coding)
                other = "gzip" if coding != "gzip" else "br"
                moved = http.get(url, headers={"Accept-Encoding": other, "If-None-Match": tag})
                assert moved.status_code == 200 and moved.headers["content-encoding"] == other
                assert moved.content == plain_body  # httpx decodes
            assert len(etags) == 1 + len(DECODE)
            assert (
                http.get(url, headers={"Accept-Encoding": "identity", "If-None-Match": etag}).status_code
                == 304
            )


def test_accept_encoding_weights_and_identity(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, busy_road(tile))
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    cases = {
        "gzip;q=0.4, br;q=0.8": "br",
        "gzip, br;q=0": "gzip",
        "br;q=0.5, identity": None,  # identity weighs more
        "x-gzip": "gzip",
        "*": "br",
        "*;q=0.5, gzip": "gzip",
        "compress, deflate": None,  # none on offer: identity
        "": None,
    }
    with tiled.http() as http:
        for header, coding in cases.items():
            answer = http.get(url, headers={"Accept-Encoding": header})
            assert answer.status_code == 200, header
            assert answer.headers.get("content-encoding") == coding, header
        refused = http.get(url, headers={"Accept-Encoding": "compress, identity;q=0"})
        assert refused.status_code == 406 and refused.json()["location"] == "header.accept-encoding"
        assert http.get(url, headers={"Accept-Encoding": "*;q=0"}).status_code == 406
        # identity refused: even a small body is compressed
        small = http.get("/v1/jobs/summary", headers={"Accept-Encoding": "gzip, identity;q=0"})
        assert small.status_code == 200 and small.headers["content-encoding"] == "gzip"
        # identity acceptable: a small body goes as it is
        small = http.get("/v1/jobs/summary", headers={"Accept-Encoding": "gzip"})
        assert len(small.content) < 1024 and "content-encoding" not in small.headers


def test_map_and_export_answers_are_compressed(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, busy_road(tile))
    b = mercantile.bounds(tile)
    bbox = f"{b.west},{b.south},{b.east},{b.north}"
    with tiled.http() as http:
        for url in (f"/v1/map?bbox={bbox}", f"/v1/export/lanelet2?bbox={bbox}"):
            plain, plain_body = raw_get(http, url, {"Accept-Encoding": "identity"})
            answer, raw = raw_get(http, url, {"Accept-Encoding": "br"})
            assert plain.status_code == answer.status_code == 200, (url, plain.text)
            assert answer.headers["content-encoding"] == "br" and brotli.decompress(raw) == plain_body
            assert len(raw) * 3 < len(plain_body), url


def test_head_answers_with_the_get_headers_and_no_body(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, busy_road(tile))
    b = mercantile.bounds(tile)
    base = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}"
    urls = [
        f"{base}.mvt",
        f"{base}.mvt?route=1",
        f"{base}.geojson",
        "/v1/tiles.json",
        "/v1/jobs/summary",
        f"/v1/map?bbox={b.west},{b.south},{b.east},{b.north}",
    ]
    same = ("etag", "content-length", "content-encoding", "content-type", "cache-control", "vary")
    with tiled.http() as http:
        for url, coding in itertools.product(urls, ("br", "identity")):
            get, get_body = raw_get(http, url, {"Accept-Encoding": coding})
            head = http.head(url, headers={"Accept-Encoding": coding})
            assert get.status_code == head.status_code == 200, (url, head.text)
            assert head.content == b"", url
            assert head.headers["content-length"] == str(len(get_body)), url
            for name in same:
                assert head.headers.get(name) == get.headers.get(name), (url, coding, name)
        # HEAD of a tile: 304 as the GET
        etag = http.get(f"{base}.mvt", headers={"Accept-Encoding": "gzip"}).headers["etag"]
        cached = http.head(f"{base}.mvt", headers={"Accept-Encoding": "gzip", "If-None-Match": etag})
        assert cached.status_code == 304 and cached.headers["etag"] == etag
        # a route without GET still answers 405
        assert http.head("/v1/process").status_code == 405


def test_error_answers_carry_cors_headers(tiled: Tiled):
    tile = tiled.fresh_tile()
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    origin = {"Origin": "https://viewer.example"}
    with (
        tiled.dep.client() as anonymous,
        tiled.dep.client("csr_not_a_key") as bad,
        tiled.http(tiled.vehicle) as vehicle,
    ):
        answers = {
            401: [anonymous.get(url, headers=origin), bad.get(url, headers=origin), bad.head(url)],
            403: [vehicle.get(url, headers=origin), vehicle.get("/v1/tiles.json", headers=origin)],
            404: [anonymous.get("/v1/nowhere", headers=origin)],
        }
    with tiled.http() as reader:
        answers[404].append(reader.get("/v1/trips/no-such-trip", headers=origin))
        answers[422] = [reader.get("/v1/tiles/23/0/0.mvt", headers=origin)]
    for status, responses in answers.items():
        for response in responses:
            assert response.status_code == status, response.text
            assert response.headers["access-control-allow-origin"] == "*", status
            assert "Retry-After" in response.headers["access-control-expose-headers"]
            if response.request.method == "GET":
                assert set(response.json()) == {"error", "location", "message"}


def test_an_unhandled_error_is_a_500_with_the_error_body_and_cors(tmp_path):
    app: FastAPI = create_app(Settings(data_dir=tmp_path))

    @app.get("/v1/broken")
    def broken() -> dict:
        raise RuntimeError("boom")

    with TestClient(app, raise_server_exceptions=False) as client:
        answer = client.get("/v1/broken")
    assert answer.status_code == 500
    assert answer.json() == {
        "error": "internal",
        "location": "server",
        "message": "internal server error (RuntimeError)",
    }
    assert answer.headers["access-control-allow-origin"] == "*"


def coordinates(geometry: dict) -> np.ndarray:
    """Every (lon, lat) of a GeoJSON geometry."""
    flat = list(geometry["coordinates"])
    while flat and isinstance(flat[0][0], list):
        flat = [c for part in flat for c in part]
    return np.asarray(flat, float)


def test_geojson_bbox_is_that_of_the_features_and_coordinates_have_7_decimals(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = road(tile)
    tiled.write(tile, features)
    b = mercantile.bounds(tile)
    # a box around the middle of the tile: the features reach past it
    west, south = b.west + 0.35 * (b.east - b.west), b.south + 0.3 * (b.north - b.south)
    query = (west, south, west + 0.2 * (b.east - b.west), south + 0.3 * (b.north - b.south))
    with tiled.http() as http:
        docs = {
            "map": http.get("/v1/map", params={"bbox": ",".join(map(str, query))}).json(),
            "tile": http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.geojson").json(),
            "version": http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/versions/1").json(),
        }
        empty = http.get("/v1/map", params={"bbox": "0.1,0.1,0.2,0.2"}).json()
    for name, doc in docs.items():
        assert {f["id"] for f in doc["features"]} == {f.feature_id for f in features}, name
        points = np.vstack([coordinates(f["geometry"]) for f in doc["features"]])
        tight = [*points.min(axis=0), *points.max(axis=0)]
        assert doc["bbox"] == tight, name
        written = np.vstack(
            [
                np.asarray(f.geometry.exterior.coords if f.type == "crosswalk" else f.geometry.coords)
                for f in features
            ]
        )
        # stored to 1e-8 degrees, sent to 1e-7
        assert np.abs(np.sort(points, axis=0) - np.sort(written, axis=0)).max() <= 0.55e-7, name
        assert np.array_equal(points, np.round(points, 7)), name
    assert docs["map"]["bbox"][0] < query[0] and docs["map"]["bbox"][2] > query[2]
    assert empty["features"] == [] and "bbox" not in empty
