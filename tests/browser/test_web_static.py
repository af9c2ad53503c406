"""The committed bundle is served with the right types and caching (no browser, no database)."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.api.routes.web import DIST
from services.settings import Settings

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> TestClient:
    # no lifespan: the static routes need neither the database nor the job runner
    return TestClient(create_app(Settings(data_dir=tmp_path_factory.mktemp("data"))))


def test_pages_and_assets(client: TestClient) -> None:
    for page in ("/viewer/", "/ops/"):
        response = client.get(page)
        assert response.status_code == 200
        assert response.headers["content-type"] == "text/html; charset=utf-8"
        assert response.headers["cache-control"] == "no-cache"
        etag = response.headers["etag"]
        assert client.get(page, headers={"If-None-Match": etag}).status_code == 304
        assets = re.findall(r'(?:src|href)="([^"/:]+\.(?:js|css))"', response.text)
        assert len(assets) == 2, assets
        for name in assets:
            asset = client.get(page + name)
            assert asset.status_code == 200, name
            kind = "text/javascript" if name.endswith(".js") else "text/css"
            assert asset.headers["content-type"] == f"{kind}; charset=utf-8"
            assert asset.headers["cache-control"] == "public, max-age=31536000, immutable"
    workers = [p.name for p in DIST.glob("maplibre-gl-worker-*.mjs")]
    assert len(workers) == 1
    worker = client.get(f"/viewer/{workers[0]}")
    assert worker.status_code == 200 and worker.headers["content-type"].startswith("text/javascript")


def test_redirects_and_misses(client: TestClient) -> None:
    for page in ("/viewer", "/ops"):
        response = client.get(page, follow_redirects=False)
        assert response.status_code == 308 and response.headers["location"].endswith(page + "/")
    for name in ("nope.js", "..%2Fweb.py", ".hidden.js", "build.mjs", "index.txt"):
        assert client.get(f"/viewer/{name}").status_code == 404, name


def test_bundle_loads_nothing_from_the_internet() -> None:
    """No CDN and no base map: the pages reference only their own files."""
    for page in ("index.html", "ops.html"):
        html = (DIST / page).read_text()
        assert "http://" not in html and "https://" not in html
