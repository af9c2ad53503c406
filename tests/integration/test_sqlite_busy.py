"""The embedded default while another connection holds SQLite's write lock (a long job's write):
reads answer at once from their WAL snapshot, and a write that cannot get the lock within the
busy timeout answers 503 with ``Retry-After`` and the standard error body, never 500."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.integration.conftest import Deployment, unique_trip

pytestmark = pytest.mark.integration

POLLS = 15  # rounds of reads made while the lock is held


@contextmanager
def write_lock_held(dep: Deployment) -> Iterator[sqlite3.Connection]:
    """A write transaction on the deployment's SQLite file, open (uncommitted) for the block."""
    conn = sqlite3.connect(Path(dep.db_url.removeprefix("sqlite:///")), isolation_level=None, timeout=30)
    try:
        conn.execute("BEGIN IMMEDIATE")
        conn.execute("UPDATE trips SET updated_at = updated_at")  # dirty pages in the WAL, not committed
        yield conn
    finally:
        conn.execute("ROLLBACK")
        conn.close()


def test_reads_answer_while_a_write_transaction_holds_the_lock(make_isolated) -> None:
    dep = make_isolated("embedded")
    dep.start_server()
    trip = dep.upload(unique_trip()).raise_for_status().json()
    with write_lock_held(dep), dep.admin() as http:
        for _ in range(POLLS):
            summary = http.get("/v1/jobs/summary")
            assert summary.status_code == 200, summary.text
            assert set(summary.json()) >= {"queued", "running", "failed", "dirty_tiles"}
            got = http.get(f"/v1/trips/{trip['id']}")
            assert got.status_code == 200, got.text
            assert got.json()["id"] == trip["id"]
            tile = http.get("/v1/tiles/16/34322/22423.mvt")  # a render is kept only when the lock is free
            assert tile.status_code in (200, 204), tile.text


def test_a_write_that_cannot_get_the_lock_is_a_503(make_isolated) -> None:
    dep = make_isolated("embedded", CSR_SQLITE_BUSY_TIMEOUT_S="0.5")
    dep.start_server()
    with write_lock_held(dep), dep.admin() as http:
        busy = http.post("/v1/keys", json={"role": "reader"})
        assert busy.status_code == 503, busy.text
        assert int(busy.headers["Retry-After"]) > 0
        body = busy.json()
        assert set(body) == {"error", "location", "message"}
        assert body["error"] == "database_busy"
        assert http.get("/v1/jobs/summary").status_code == 200  # reads go on meanwhile
    with dep.admin() as http:
        assert http.post("/v1/keys", json={"role": "reader"}).status_code == 201
