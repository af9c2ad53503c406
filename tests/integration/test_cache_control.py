"""Map answers need a key, so shared caches must not keep them: ``Cache-Control: private`` by
default (max-age and ``immutable`` as for any cache), ``public`` only with ``CSR_PUBLIC_MAP=true``."""

from __future__ import annotations

import pytest

from tests.integration.conftest import Deployment

pytestmark = pytest.mark.integration

TILE = "/v1/tiles/16/34296/22400"
LIVE = [f"{TILE}.mvt", f"{TILE}.geojson", "/v1/map?bbox=8.40,49.00,8.41,49.01", "/v1/tiles.json"]
PINNED = [f"{TILE}.mvt?v=0", "/v1/map?bbox=8.40,49.00,8.41,49.01&version=0"]


def cache_controls(dep: Deployment) -> dict[str, str]:
    with dep.admin() as http:
        answers = {url: http.get(url) for url in LIVE + PINNED}
    for url, answer in answers.items():
        assert answer.status_code in (200, 204), (url, answer.text)
    return {url: answer.headers["cache-control"] for url, answer in answers.items()}


def test_map_answers_are_private_by_default(deployment: Deployment) -> None:
    expected = {url: "private, max-age=30" for url in LIVE}
    expected |= {url: "private, max-age=31536000, immutable" for url in PINNED}
    assert cache_controls(deployment) == expected


def test_a_public_map_is_cacheable_by_shared_caches(make_isolated) -> None:
    dep: Deployment = make_isolated("embedded", CSR_PUBLIC_MAP="true")
    dep.start_server()
    expected = {url: "public, max-age=30" for url in LIVE}
    expected |= {url: "public, max-age=31536000, immutable" for url in PINNED}
    assert cache_controls(dep) == expected
