"""``GET /v1/tiles/{z}/{x}/{y}/certificate`` and TileJSON's ``certificate`` on both deployments
(embedded SQLite, PostGIS): the length-weighted RMS of the elements' ``sigma_abs_m`` and
``uncertainty_m`` over the tile, the trips behind it and the passes still needed; errors and
roles as on the neighbouring tile routes. Versions are written through
``services.db.versions.write_tile_version`` (what the merge job calls)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import mercantile
import pytest
from pyproj import Geod
from shapely.geometry import LineString

from csr_core.topology.absolute_uncertainty import passes_needed
from services.db import versions as vs
from tests.integration.conftest import PgDatabases
from tests.integration.test_tiles import Tiled, frac, start_tiled

pytestmark = pytest.mark.integration

TARGET_M = 0.10  # the setting's default


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def tiled(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    yield from start_tiled(
        request.param, tmp_path_factory.mktemp(f"certificate-{request.param}"), pg, shared_redis_url
    )


def lines(tile: mercantile.Tile) -> list[vs.VersionFeature]:
    """A long well-seen divider and a short poorly seen boundary, inside ``tile``."""

    def line(*pts):
        return LineString([frac(tile, fx, fy) for fx, fy in pts])

    return [
        vs.VersionFeature(
            f"16-{tile.x}-{tile.y}-d1",
            "lane_divider",
            "dashed",
            {"support_trips": 9, "uncertainty_m": 0.03, "sigma_abs_m": 0.12},
            line((0.1, 0.5), (0.9, 0.5)),
        ),
        vs.VersionFeature(
            f"16-{tile.x}-{tile.y}-b1",
            "road_boundary",
            None,
            {"support_trips": 3, "uncertainty_m": 0.05, "sigma_abs_m": 0.30},
            line((0.2, 0.6), (0.4, 0.6)),
        ),
    ]


def expected(features: list[vs.VersionFeature]) -> tuple[float, float]:
    geod = Geod(ellps="WGS84")
    w = [geod.geometry_length(f.geometry) for f in features]
    rms = [
        math.sqrt(sum(wi * f.properties[key] ** 2 for wi, f in zip(w, features, strict=True)) / sum(w))
        for key in ("sigma_abs_m", "uncertainty_m")
    ]
    return rms[0], rms[1]


def test_certificate_of_a_tile(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = lines(tile)
    tiled.write(tile, features, trips=["trip-a", "trip-b"])
    tiled.write(tile, features, trips=["trip-c"])
    abs_m, rel_m = expected(features)
    with tiled.http() as http:
        answer = http.get(f"/v1/tiles/16/{tile.x}/{tile.y}/certificate")
        assert answer.status_code == 200, answer.text
        cert = answer.json()
    assert cert["tile"] == f"16/{tile.x}/{tile.y}" and cert["map_version"] is None
    assert cert["expected_absolute_error_m"] == pytest.approx(abs_m, abs=1e-4)
    assert cert["expected_relative_error_m"] == pytest.approx(rel_m, abs=1e-4)
    assert cert["n_features"] == 2 and cert["trips"] == 3 and cert["passes_median"] == 6.0
    assert cert["target_m"] == TARGET_M
    assert cert["passes_needed"] == passes_needed(abs_m, rel_m, 6.0, TARGET_M) and cert["passes_needed"] > 0
    assert answer.headers["cache-control"].startswith("private")


def test_certificate_of_a_parent_tile_and_of_an_empty_one(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = lines(tile)
    tiled.write(tile, features, trips=["trip-p"])
    parent = mercantile.parent(tile, zoom=12)
    with tiled.http() as http:
        cert = http.get(f"/v1/tiles/12/{parent.x}/{parent.y}/certificate").raise_for_status().json()
        assert cert["n_features"] >= 2 and cert["trips"] >= 1
        far = http.get("/v1/tiles/16/0/0/certificate").raise_for_status().json()
    assert far["n_features"] == 0 and far["trips"] == 0 and far["passes_needed"] is None
    assert far["expected_absolute_error_m"] == 0.0


def test_certificate_pinned_to_a_map_version(tiled: Tiled):
    tile = tiled.fresh_tile()
    features = lines(tile)
    tiled.write(tile, features, trips=["trip-v1"])
    pinned = tiled.map_version()
    better = [
        vs.VersionFeature(f.feature_id, f.type, f.style, {**f.properties, "sigma_abs_m": 0.05}, f.geometry)
        for f in features
    ]
    tiled.write(tile, better, trips=["trip-v2"])
    with tiled.http() as http:
        then = http.get(f"/v1/tiles/16/{tile.x}/{tile.y}/certificate", params={"v": pinned}).json()
        now = http.get(f"/v1/tiles/16/{tile.x}/{tile.y}/certificate").json()
    assert then["map_version"] == pinned and then["trips"] == 1
    assert then["expected_absolute_error_m"] == pytest.approx(expected(features)[0], abs=1e-4)
    assert now["trips"] == 2 and now["expected_absolute_error_m"] == pytest.approx(0.05, abs=1e-4)
    assert now["passes_needed"] == 0


def test_bad_requests_name_what_is_wrong(tiled: Tiled):
    with tiled.http() as http:
        bad = http.get("/v1/tiles/16/70000/0/certificate")
        assert bad.status_code == 422
        assert bad.json()["location"] == "path.x" and "70000" in bad.json()["message"]
        future = http.get("/v1/tiles/16/0/0/certificate", params={"v": 10**9})
        assert future.status_code == 404 and future.json()["location"] == "query.v"
        assert set(future.json()) >= {"error", "location", "message"}
    with tiled.dep.client() as anonymous:
        assert anonymous.get("/v1/tiles/16/0/0/certificate").status_code == 401
    with tiled.http(tiled.vehicle) as vehicle:
        assert vehicle.get("/v1/tiles/16/0/0/certificate").status_code == 403


def test_tilejson_summarises_the_live_tiles(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, lines(tile), trips=["trip-j"])
    with tiled.http() as http:
        doc = http.get("/v1/tiles.json").raise_for_status().json()
        per_tile = http.get(f"/v1/tiles/16/{tile.x}/{tile.y}/certificate").json()
    summary = doc["certificate"]
    assert summary["n_features"] >= per_tile["n_features"] and summary["trips"] >= per_tile["trips"]
    assert summary["target_m"] == TARGET_M
    assert 0 < summary["expected_relative_error_m"] < summary["expected_absolute_error_m"]
    assert doc["certificate_tiles"] == [f"{tiled.dep.base_url}/v1/tiles/{{z}}/{{x}}/{{y}}/certificate"]
    assert "sigma_abs_m" in doc["vector_layers"][0]["fields"]
