"""Contract section 3 and the processing jobs: ingest (track, length, tiles), dirty tiles,
``/v1/jobs/summary``, ``POST /v1/process``, the quiet period, ``/healthz`` and ``/metrics``."""

from __future__ import annotations

import secrets
import time

import numpy as np
import pytest

from csr_core.geo import tiles_touched
from services.cli.bench_ingest import straight_trip
from tests.integration.conftest import Deployment, make_deployment, moving_trip, unique_trip, wait_until

pytestmark = pytest.mark.integration


def _trip(dep: Deployment, trip_pk: str) -> dict:
    with dep.admin() as http:
        return http.get(f"/v1/trips/{trip_pk}").raise_for_status().json()


def test_ingest_stores_track_length_and_tiles_then_process_clears_the_dirty_tiles(deployment: Deployment):
    doc = straight_trip(vehicle_id="veh-km", trip_id="km-" + secrets.token_hex(4), length_m=1000.0)
    response = deployment.upload(doc, gzipped=True)
    assert response.status_code == 202, response.text
    trip_pk = response.json()["id"]
    trip = wait_until(
        lambda: (t := _trip(deployment, trip_pk))["status"] == "processing" and t, timeout_s=60, what="ingest"
    )
    assert trip["length_km"] == pytest.approx(1.0, abs=0.005)
    lonlat = [(f["gnss"]["lon"], f["gnss"]["lat"]) for f in doc["frames"]]
    gnss_tiles = [f"{z}/{x}/{y}" for z, x, y in tiles_touched(np.array(lonlat), zoom=16)]
    # tiles own frames by smoothed position: within a metre of the GNSS track, so the same tiles
    # unless the track grazes a tile corner
    expected_tiles = trip["tiles"]
    assert len(expected_tiles) >= 2 and len(set(expected_tiles) ^ set(gnss_tiles)) <= 1, (
        expected_tiles,
        gnss_tiles,
    )
    assert trip["tiles_pending"] == len(expected_tiles)

    assert deployment.engine is not None
    if deployment.engine.dialect.name == "postgresql":
        geometry = deployment.rows(
            "SELECT ST_GeometryType(track), ST_SRID(track), ST_NPoints(track), "
            "ST_Length(track::geography) FROM trips WHERE id = :p",
            p=trip_pk,
        )[0]
        assert geometry[:3] == ("ST_LineString", 4326, len(doc["frames"]))
        assert geometry[3] == pytest.approx(1000.0, abs=5.0)
        indexdef = deployment.scalar("SELECT indexdef FROM pg_indexes WHERE indexname = 'ix_trips_track'")
        assert "USING gist (track)" in indexdef
    else:
        track = deployment.scalar("SELECT track FROM trips WHERE id = :p", p=trip_pk)
        assert track.startswith("SRID=4326;LINESTRING(") and track.count(",") == len(doc["frames"]) - 1

    summary = deployment.wait_idle()
    failed_before = summary["failed"]  # the session's deployment also holds other tests' failed trips
    assert summary["dirty_tiles"] >= len(expected_tiles)
    with deployment.admin() as http:
        scheduled = http.post("/v1/process").json()
    assert scheduled["scheduled"] == summary["dirty_tiles"]
    assert set(expected_tiles) <= {job["tile"] for job in scheduled["jobs"]}
    done = wait_until(
        lambda: (
            (s := deployment.summary())["dirty_tiles"] == 0 and s["queued"] == 0 and s["running"] == 0 and s
        ),
        timeout_s=60,
        what="tile jobs",
    )
    assert done["failed"] == failed_before
    trip = _trip(deployment, trip_pk)
    assert trip["tiles_pending"] == 0
    # alone on its road, the trip has nothing to be aligned with: it keeps its single-trip poses
    assert trip["status"] == "aligned", trip
    with deployment.admin() as http:
        poses = http.get(f"/v1/trips/{trip_pk}/poses").raise_for_status().json()["frames"]
    assert [p["t"] for p in poses] == [f["t"] for f in doc["frames"]]
    kinds = deployment.rows("SELECT kind, state, attempts FROM jobs WHERE subject = :p", p=trip_pk)
    assert [tuple(r) for r in kinds] == [("ingest_trip", "done", 1)]


def test_process_queues_the_busiest_tiles_first(deployment: Deployment):
    """Longest processing time first: a tile with three trips waiting is queued before a tile with
    one (with several workers, the batch ends when its longest job does)."""
    from services.cli.bench_ingest import straight_trip

    def drive(lat: float, lon: float) -> str:
        doc = straight_trip(
            vehicle_id="veh-lpt",
            trip_id="lpt-" + secrets.token_hex(4),
            length_m=120.0,
            origin_lat=lat,
            origin_lon=lon,
            heading_deg=0.0,
        )
        return deployment.upload(doc).json()["id"]

    # the quiet tile is uploaded first and sorts first by z/x/y: only the trip count puts it last
    quiet = drive(47.5101, 9.4301)  # both tiles have x + y odd (the checkerboard colour comes first)
    busy = [drive(47.6101, 9.6101) for _ in range(3)]
    deployment.wait_idle()
    tiles = {pk: _trip(deployment, pk)["tiles"] for pk in (*busy, quiet)}
    with deployment.admin() as http:
        order = [job["tile"] for job in http.post("/v1/process").json()["jobs"]]
    busy_tile, quiet_tile = tiles[busy[0]][0], tiles[quiet][0]
    assert busy_tile in order and quiet_tile in order, (order, tiles)
    assert order.index(busy_tile) < order.index(quiet_tile), order
    deployment.wait_idle()


def test_a_tiles_first_alignment_waits_for_its_neighbours_first_version(deployment: Deployment):
    """Checkerboard: of two edge neighbours both new, the one with x + y odd aligns only once the
    even one has its first version (its map is then the prior in the halo), even with two job
    threads free; its wait does not count as an attempt."""
    from csr_core.geo import tile_bounds_lonlat
    from services.cli.bench_ingest import straight_trip

    z, x_even, y = 16, 34489, 22921  # x + y even; its east neighbour is odd
    assert (x_even + y) % 2 == 0

    def drive(x: int) -> str:
        west, south, east, north = tile_bounds_lonlat(z, x, y)
        doc = straight_trip(
            vehicle_id="veh-chk",
            trip_id="chk-" + secrets.token_hex(4),
            length_m=120.0,
            origin_lat=(south + north) / 2,
            origin_lon=(west + east) / 2,
            heading_deg=0.0,
        )
        return deployment.upload(doc).json()["id"]

    # the odd tile's trips come first and outnumber the even one's: only the checkerboard puts it after
    for _ in range(2):
        drive(x_even + 1)
    drive(x_even)
    deployment.wait_idle()
    with deployment.admin() as http:
        http.post("/v1/process").raise_for_status()
    deployment.wait_idle(timeout_s=180)
    even_version_at = deployment.scalar(
        "SELECT min(created_at) FROM tile_versions WHERE z = :z AND x = :x AND y = :y", z=z, x=x_even, y=y
    )
    odd = deployment.rows(
        "SELECT state, attempts, started_at FROM jobs WHERE kind = 'align_tile' AND subject = :s",
        s=f"{z}/{x_even + 1}/{y}",
    )
    assert even_version_at is not None and len(odd) == 1, odd
    state, attempts, started_at = odd[0]
    assert state == "done" and attempts == 1

    def as_utc(t):
        from datetime import UTC, datetime

        t = datetime.fromisoformat(t) if isinstance(t, str) else t
        return t if t.tzinfo else t.replace(tzinfo=UTC)

    assert as_utc(started_at) >= as_utc(even_version_at), (started_at, even_version_at)


def test_process_with_nothing_dirty_schedules_nothing(deployment: Deployment):
    deployment.wait_idle()
    with deployment.admin() as http:
        http.post("/v1/process")
        wait_until(lambda: deployment.summary()["dirty_tiles"] == 0, what="dirty tiles cleared")
        assert http.post("/v1/process").json() == {"scheduled": 0, "jobs": []}


def test_unknown_trip_is_404(deployment: Deployment):
    with deployment.admin() as http:
        for path in ("/v1/trips/nope", "/v1/trips/nope/poses"):
            response = http.get(path)
            assert response.status_code == 404 and response.json()["error"] == "not_found"


def test_trip_without_any_gnss_fix_fails_visibly(deployment: Deployment):
    doc = unique_trip()
    for frame in doc["frames"]:
        frame["gnss"]["status"] = "none"
    trip_pk = deployment.upload(doc).json()["id"]
    trip = wait_until(
        lambda: (t := _trip(deployment, trip_pk))["status"] == "failed" and t, what="failed ingest"
    )
    assert "GNSS fix" in trip["error"]
    assert deployment.scalar("SELECT state FROM jobs WHERE subject = :p", p=trip_pk) == "failed"
    assert deployment.summary()["failed"] >= 1


def test_healthz_and_metrics(deployment: Deployment):
    with deployment.client() as anonymous:
        health = anonymous.get("/healthz").json()
    assert health["status"] == "ok"
    assert health["jobs"] == ("distributed" if deployment.distributed else "embedded")
    deployment.upload(b"{oops")
    deployment.upload(unique_trip())
    deployment.wait_idle()
    with deployment.admin() as http:
        response = http.get("/metrics")
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    for needle in (
        'csr_uploads_total{result="accepted"}',
        'csr_upload_bytes_total{form="sent"}',
        'csr_upload_rejects_total{reason="json"}',
        'csr_queue_depth{queue="ingest"} 0.0',
        'csr_job_duration_seconds_count{kind="ingest_trip"}',
        "csr_dirty_tiles",
        "csr_upload_duration_seconds_bucket",
    ):
        assert needle in text, needle


def test_quiet_period_processes_dirty_tiles_without_a_trigger(tmp_path, pg, shared_redis_url):
    dep = make_deployment("embedded", tmp_path, pg, shared_redis_url, CSR_QUIET_PERIOD_S="1")
    try:
        dep.start_server()
        trip_pk = dep.upload(moving_trip()).json()["id"]
        wait_until(
            lambda: (t := _trip(dep, trip_pk))["tiles"] and t["tiles_pending"] == 0,
            timeout_s=30,
            what="tile job after the quiet period",
        )
        # the trip's tiles are done once aligned; the merge job that follows may still be running
        idle = {"queued": 0, "running": 0, "failed": 0, "dirty_tiles": 0}
        wait_until(
            lambda: dep.summary() == idle,
            timeout_s=30,
            what=lambda: f"the merge after the quiet period; summary {dep.summary()}",
        )
    finally:
        dep.stop()


def test_embedded_server_killed_mid_job_finishes_the_job_after_restart(tmp_path, pg, shared_redis_url):
    dep = make_deployment("embedded", tmp_path, pg, shared_redis_url)
    try:
        server = dep.start_server(CSR_TEST_INGEST_DELAY_S="60")
        trip_pk = dep.upload(moving_trip()).json()["id"]
        wait_until(
            lambda: dep.scalar("SELECT state FROM jobs WHERE subject = :p", p=trip_pk) == "running",
            what="ingest job running",
        )
        server.kill_group()
        dep.start_server()
        trip = wait_until(
            lambda: (t := _trip(dep, trip_pk))["status"] == "processing" and t, what="ingest after restart"
        )
        assert trip["tiles"]
        jobs = dep.rows("SELECT state, attempts FROM jobs WHERE subject = :p", p=trip_pk)
        assert [tuple(r) for r in jobs] == [("done", 2)]
        assert dep.scalar("SELECT count(*) FROM trips") == 1
        assert dep.scalar("SELECT count(*) FROM trip_reconstructions") == 1
    finally:
        dep.stop()


def test_embedded_without_job_threads_keeps_jobs_queued_until_a_runner_starts(tmp_path, pg, shared_redis_url):
    dep = make_deployment("embedded", tmp_path, pg, shared_redis_url)
    try:
        server = dep.start_server(CSR_EMBEDDED_WORKERS="0")
        trip_pk = dep.upload(moving_trip()).json()["id"]
        time.sleep(2)  # several poll intervals
        assert dep.summary()["queued"] == 1 and _trip(dep, trip_pk)["status"] == "received"
        server.stop()
        dep.start_server()
        wait_until(lambda: _trip(dep, trip_pk)["status"] == "processing", what="the queued job to run")
        assert dep.summary()["queued"] == 0
    finally:
        dep.stop()
