"""A database that cannot be reached: every call but ``/healthz`` answers the error contract's JSON
503 ``database_unavailable`` with ``Retry-After`` (never a plain-text 500), and the service answers
normally again once the database is back."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import psycopg
import pytest
from sqlalchemy.engine import make_url

from tests.integration.conftest import PG_ADMIN_URL, Deployment, unique_trip

pytestmark = pytest.mark.integration

CALLS = [
    ("GET", "/v1/jobs/summary"),
    ("GET", "/v1/trips/some-trip"),
    ("GET", "/v1/tiles/16/34296/22400.mvt"),  # the tile fast path in front of the routes
    ("GET", "/v1/tiles/16/34296/22400.geojson?v=1"),
    ("GET", "/v1/map?bbox=8.40,49.00,8.41,49.01"),
    ("GET", "/v1/changes?since=0"),
    ("GET", "/metrics"),
    ("POST", "/v1/process"),
]


@contextmanager
def database_refusing_connections(db_url: str) -> Iterator[None]:
    """The deployment's database refuses new connections and loses its open ones, as in an outage."""
    name = make_url(db_url).database
    with psycopg.connect(PG_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS false')
        admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (name,))
        try:
            yield
        finally:
            admin.execute(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS true')


def test_calls_during_a_database_outage_answer_json_503_with_retry_after(make_isolated) -> None:
    dep: Deployment = make_isolated("distributed")  # PostGIS, jobs in-process (no Redis)
    dep.start_server()
    with dep.admin() as http:
        assert http.get("/v1/tiles/16/34296/22400.mvt").status_code in (200, 204)  # warm caches
        assert dep.upload(unique_trip()).status_code == 202
        with database_refusing_connections(dep.db_url):
            answers = [http.request(method, url) for method, url in CALLS]
            answers.append(dep.upload(unique_trip()))
            for (method, url), answer in zip([*CALLS, ("POST", "/v1/trips")], answers, strict=True):
                assert answer.status_code == 503, (method, url, answer.text)
                assert answer.headers["content-type"].startswith("application/json"), (method, url)
                assert answer.headers["retry-after"].isdigit(), (method, url)
                body = answer.json()
                assert set(body) == {"error", "location", "message"}, (method, url)
                assert (body["error"], body["location"]) == ("database_unavailable", "database"), (
                    method,
                    url,
                )
        assert http.get("/v1/jobs/summary").status_code == 200  # back: the pool reconnects
