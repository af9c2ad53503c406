"""A tile's listings in pages (``limit`` + opaque ``cursor``, ``next`` and ``Link``) on both
deployments: ``GET /v1/tiles/{z}/{x}/{y}/match-pairs`` covers every pair once, in the stable order
(confidence, then id), ``.../versions`` every version in order, and a bad ``limit`` or ``cursor``
is a 422 naming it."""

from __future__ import annotations

import base64
import itertools

import pytest

from services.api.pagination import MAX_LIMIT
from services.cli.bench_match_pairs import write_pairs

pytestmark = pytest.mark.integration

N_PAIRS = 230
_tiles = itertools.count(100)  # a tile of its own for every test of the session's deployments


@pytest.fixture
def tile_with_pairs(deployment):
    """A tile of ``N_PAIRS`` pairs whose confidences (one decimal) tie often; its pairs' ids in
    the listing's order."""
    tile = (16, 34000 + next(_tiles), 22400)
    ids = write_pairs(deployment.db_url, N_PAIRS, tile=tile, seed=tile[1], decimals=1)
    rows = deployment.rows(
        "SELECT id, confidence FROM match_pairs WHERE z = :z AND x = :x AND y = :y",
        z=tile[0],
        x=tile[1],
        y=tile[2],
    )
    assert sorted(r.id for r in rows) == sorted(ids)
    return "/v1/tiles/{}/{}/{}/match-pairs".format(*tile), [
        r.id for r in sorted(rows, key=lambda r: (r[1], r[0]))
    ]


def test_pages_cover_every_pair_once_in_a_stable_order(deployment, tile_with_pairs) -> None:
    url, expected = tile_with_pairs
    seen: list[str] = []
    with deployment.admin() as http:
        whole = http.get(url).raise_for_status()  # the default page holds them all
        assert whole.json()["next"] is None and "link" not in whole.headers
        assert [p["id"] for p in whole.json()["match_pairs"]] == expected
        next_url: str | None = url + "?limit=37"
        pages = 0
        while next_url is not None:
            page = http.get(next_url).raise_for_status()
            body = page.json()
            assert len(body["match_pairs"]) <= 37
            if body["next"] is not None:
                assert page.headers["link"] == f'<{body["next"]}>; rel="next"'
            seen += [p["id"] for p in body["match_pairs"]]
            next_url, pages = body["next"], pages + 1
    assert pages == -(-N_PAIRS // 37)
    assert seen == expected  # every pair once, confidence then id


def test_a_status_filter_pages_too(deployment, tile_with_pairs) -> None:
    url, expected = tile_with_pairs
    with deployment.admin() as http:
        first = http.get(url, params={"status": "active", "limit": 200}).raise_for_status().json()
        rest = http.get(first["next"]).raise_for_status().json()
        assert "status=active" in first["next"]
        assert [p["id"] for p in first["match_pairs"] + rest["match_pairs"]] == expected
        assert rest["next"] is None
        assert http.get(url, params={"status": "rejected"}).raise_for_status().json()["match_pairs"] == []


@pytest.mark.parametrize("limit", ["0", "-3", str(MAX_LIMIT + 1), "many"])
def test_a_bad_limit_is_a_422_naming_it(deployment, tile_with_pairs, limit) -> None:
    url, _ = tile_with_pairs
    with deployment.admin() as http:
        answer = http.get(url, params={"limit": limit})
    assert answer.status_code == 422
    body = answer.json()
    assert body["error"] == "invalid_request" and body["location"] == "query.limit"
    assert "limit" in body["message"]


def _b64(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


@pytest.mark.parametrize("cursor", ["not a cursor!", _b64(b"{}"), _b64(b'["0.5"]'), _b64(b"[0.5, 7]"), "%%%"])
def test_a_bad_cursor_is_a_422_naming_it(deployment, tile_with_pairs, cursor) -> None:
    url, _ = tile_with_pairs
    with deployment.admin() as http:
        answer = http.get(url, params={"cursor": cursor})
    assert answer.status_code == 422
    body = answer.json()
    assert body["error"] == "invalid_request" and body["location"] == "query.cursor"


def write_versions(db_url: str, tile: tuple[int, int, int], n: int) -> None:
    """``n`` published versions of ``tile`` (a few elements each), as the merge job writes them."""
    import mercantile

    from services.cli.bench_tiles import LAT, LON, tile_features
    from services.db import versions as vs
    from services.db.engine import make_engine, make_session_factory

    engine = make_engine(db_url)
    for i in range(n):
        with make_session_factory(engine).begin() as session:
            vs.write_tile_version(
                session,
                z=tile[0],
                x=tile[1],
                y=tile[2],
                features=tile_features(mercantile.Tile(*tile[1:], tile[0]), 3, i),
                reason="merge",
                job_id=None,
                trips=[],
                corrections=[],
                quality={},
                origin_lat=LAT,
                origin_lon=LON,
                state=b"state",
                publish=True,
                expected_latest=i or None,
            )
    engine.dispose()


def test_a_tiles_versions_page_too(deployment) -> None:
    tile = (16, 34000 + next(_tiles), 22400)
    write_versions(deployment.db_url, tile, 5)
    url = "/v1/tiles/{}/{}/{}/versions".format(*tile)
    with deployment.admin() as http:
        whole = http.get(url).raise_for_status().json()
        assert [v["version"] for v in whole["versions"]] == [1, 2, 3, 4, 5] and whole["next"] is None
        numbers, next_url = [], url + "?limit=2"
        while next_url is not None:
            body = http.get(next_url).raise_for_status().json()
            assert body["latest_version"] == 5 and body["live_version"] == 5
            numbers += [v["version"] for v in body["versions"]]
            next_url = body["next"]
        assert numbers == [1, 2, 3, 4, 5]
        bad = http.get(url, params={"cursor": _b64(b'["1"]')})
        assert bad.status_code == 422 and bad.json()["location"] == "query.cursor"
        assert http.get("/v1/tiles/16/1/1/versions").status_code == 404
