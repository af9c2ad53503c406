"""Tile serving on both deployments: rendered tiles stored with their version (``tile_renders``),
a tile's identity limited to the versions that reach it, the ASGI fast path answering exactly as
the FastAPI route, and keys revoked while their tiles are cached."""

from __future__ import annotations

from collections.abc import Iterator

import mercantile
import pytest
from shapely.geometry import LineString

from services.db import versions as vs
from services.tiles import fastpath
from tests.integration.conftest import PgDatabases
from tests.integration.test_tiles import Tiled, decode, eventually, frac, road, start_tiled

pytestmark = pytest.mark.integration

# What the fast path and the route must both send alike (plus the body and the status).
SAME_HEADERS = (
    "etag",
    "cache-control",
    "content-type",
    "content-length",
    "x-map-version",
    "access-control-allow-origin",
    "access-control-expose-headers",
)


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def tiled(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    yield from start_tiled(
        request.param, tmp_path_factory.mktemp(f"serving-{request.param}"), pg, shared_redis_url
    )


def stored(tiled: Tiled, etag: str) -> list:
    return tiled.dep.rows("SELECT kind, z, x, y, body FROM tile_renders WHERE etag = :e", e=etag)


def crossing_line(tile: mercantile.Tile, fid: str) -> vs.VersionFeature:
    """A line from the middle of ``tile`` to 30% into its west neighbour."""
    return vs.VersionFeature(
        fid, "lane_divider", None, {"support": 2}, LineString([frac(tile, 0.5, 0.5), frac(tile, -0.3, 0.5)])
    )


def test_a_published_version_comes_with_its_rendered_tiles(tiled: Tiled):
    tile = tiled.fresh_tile()
    west = mercantile.Tile(tile.x - 1, tile.y, tile.z)
    tiled.write(tile, [*road(tile), crossing_line(tile, f"t{tile.x}-w")])
    # committed with the version: before any read, the tile and the neighbour it reaches are stored
    renders = {
        (x, y): body
        for x, y, body in tiled.dep.rows(
            "SELECT x, y, body FROM tile_renders WHERE z = 16 AND kind = 'mvt' AND y = :y AND x BETWEEN :a AND :b",
            y=tile.y,
            a=west.x,
            b=tile.x,
        )
    }
    assert set(renders) == {(west.x, west.y), (tile.x, tile.y)}
    with tiled.http() as http:
        http.headers["Accept-Encoding"] = "identity"  # renders are stored under the identity ETag
        for t in (tile, west):
            served = http.get(f"/v1/tiles/{t.z}/{t.x}/{t.y}.mvt")
            assert served.status_code == 200
            rows = stored(tiled, served.headers["etag"])
            assert len(rows) == 1 and bytes(rows[0].body) == served.content == bytes(renders[(t.x, t.y)])
        assert set(decode(http.get(f"/v1/tiles/16/{west.x}/{west.y}.mvt").content)) == {f"t{tile.x}-w"}
        # another zoom is rendered at its first read, and kept
        parent = mercantile.parent(tile)
        first = http.get(f"/v1/tiles/{parent.z}/{parent.x}/{parent.y}.mvt")
        assert (
            first.status_code == 200 and bytes(stored(tiled, first.headers["etag"])[0].body) == first.content
        )
        gj = http.get(f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.geojson")
        assert stored(tiled, gj.headers["etag"])[0].kind == "geojson"


def test_a_candidate_renders_nothing_and_changes_nothing(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    count = "SELECT count(*) FROM tile_renders WHERE z = 16 AND x = :x AND y = :y"
    with tiled.http() as http:
        before = http.get(url)
        n_before = tiled.dep.rows(count, x=tile.x, y=tile.y)[0][0]
        tiled.write(tile, road(tile, shift=0.1), publish=False)
        assert tiled.dep.rows(count, x=tile.x, y=tile.y)[0][0] == n_before
        after = http.get(url)
    assert after.headers["etag"] == before.headers["etag"] and after.content == before.content


def test_only_versions_that_reach_a_tile_change_it(tiled: Tiled):
    """A tile's ETag follows the neighbours whose features reach into it, not the others."""
    tile = tiled.fresh_tile()
    east = mercantile.Tile(tile.x + 1, tile.y, tile.z)
    south = mercantile.Tile(tile.x, tile.y + 1, tile.z)
    tiled.write(tile, road(tile))
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    with tiled.http() as http:
        first = http.get(url)
        # features of the southern neighbour that stay inside it: the tile is the same
        tiled.write(south, road(south))
        same = eventually(
            lambda: http.get(url), lambda r: r.headers["etag"] != first.headers["etag"], within_s=2.0
        )
        assert same.headers["etag"] == first.headers["etag"] and same.content == first.content
        # a line of the eastern neighbour crossing into the tile: the tile shows it
        tiled.write(east, [crossing_line(east, f"t{east.x}-w")])
        changed = eventually(lambda: http.get(url), lambda r: r.headers["etag"] != first.headers["etag"])
        assert changed.headers["etag"] != first.headers["etag"]
        assert set(decode(changed.content)) == {f.feature_id for f in road(tile)} | {f"t{east.x}-w"}
        # and the line going away again
        tiled.write(east, road(east))
        gone = eventually(lambda: http.get(url), lambda r: r.headers["etag"] != changed.headers["etag"])
        assert set(decode(gone.content)) == {f.feature_id for f in road(tile)}


def test_the_fast_path_answers_as_the_route(tiled: Tiled):
    """An extra query parameter sends the request through FastAPI's route: same answer."""
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    pinned = tiled.map_version()
    base = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}"
    with tiled.http() as http:
        etag = http.get(base + ".mvt").headers["etag"]
        cases = [
            (base + ".mvt", {}, {}),
            (base + ".geojson", {}, {}),
            (base + ".mvt", {"v": pinned}, {}),
            (base + ".mvt", {}, {"If-None-Match": etag}),
            (base + ".mvt", {"v": pinned}, {"If-None-Match": f'"x", W/{etag}'}),
            ("/v1/tiles/16/0/0.mvt", {}, {}),
            ("/v1/tiles/16/0/0.mvt", {"v": 0}, {}),
        ]
        for path, params, headers in cases:
            fast = http.get(path, params=params, headers=headers)
            fast_again = http.get(path, params=params, headers=headers)  # from the caches
            route = http.get(path, params={**params, "route": "1"}, headers=headers)
            assert fast.status_code in (200, 204, 304), (path, params, fast.text)
            for answer in (fast_again, route):
                assert (answer.status_code, answer.content) == (fast.status_code, fast.content), (
                    path,
                    params,
                )
                for name in SAME_HEADERS:
                    assert answer.headers.get(name) == fast.headers.get(name), (path, params, name)


def test_a_revoked_key_stops_reading_tiles_at_once(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    with tiled.dep.admin() as admin:
        created = admin.post("/v1/keys", json={"role": "reader"}).json()
        with tiled.http(created["key"]) as reader:
            assert reader.get(url).status_code == 200
            assert reader.get(url).status_code == 200  # the key is cached now
            assert admin.delete(f"/v1/keys/{created['id']}").status_code == 204
            gone = reader.get(url)
            assert gone.status_code == 401 and gone.json()["error"] == "unauthorized"


def test_a_key_revoked_by_another_process_stops_reading_tiles_within_the_ttl(tiled: Tiled):
    tile = tiled.fresh_tile()
    tiled.write(tile, road(tile))
    url = f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}.mvt"
    with tiled.dep.admin() as admin:
        created = admin.post("/v1/keys", json={"role": "reader"}).json()
    with tiled.http(created["key"]) as reader:
        assert reader.get(url).status_code == 200
        with tiled.sessions.begin() as session:  # as another API process would revoke it
            from sqlalchemy import text

            session.execute(
                text("UPDATE api_keys SET revoked_at = CURRENT_TIMESTAMP WHERE id = :i"), {"i": created["id"]}
            )
        answer = eventually(
            lambda: reader.get(url), lambda r: r.status_code == 401, within_s=fastpath.KEY_TTL_S + 1.0
        )
        assert answer.status_code == 401
