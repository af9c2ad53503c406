"""The memory an upload takes in the server (its peak resident memory, VmHWM of `csr serve`), the
budget of upload bytes in flight (503 + Retry-After beyond it) and the per-trip frame limit."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

import httpx
import orjson
import pytest

from services.cli.bench_upload_memory import PeakMemory, gzip_bomb, tiny_frame_trip
from tests.integration.conftest import Deployment, make_deployment, moving_trip

pytestmark = pytest.mark.integration

MIB = 1024 * 1024
DEFAULT_LIMIT_BYTES = 256 * MIB


def _table_counts(dep: Deployment) -> tuple[int, ...]:
    return tuple(dep.scalar(f"SELECT count(*) FROM {t}") for t in ("trips", "trip_uploads", "jobs"))


@pytest.fixture(scope="module")
def memory_server(tmp_path_factory, pg) -> Iterator[tuple[Deployment, PeakMemory]]:
    """An embedded `csr serve` at the default limits whose jobs wait in the database (only the
    upload path runs in it), warmed up by one upload of each kind."""
    dep = make_deployment("embedded", tmp_path_factory.mktemp("memory"), pg, "", CSR_EMBEDDED_WORKERS="0")
    try:
        server = dep.start_server()
        assert dep.upload(tiny_frame_trip(1000, trip_id="warm-up"), gzipped=True).status_code == 202
        assert dep.upload(moving_trip(length_m=1000.0), gzipped=True).status_code == 202
        yield dep, PeakMemory(server.proc.pid)
    finally:
        dep.stop()


@pytest.fixture(scope="module")
def bomb() -> bytes:
    return gzip_bomb(1024)  # 1 GiB of zeros, ~1 MB sent


def _post_gzip(dep: Deployment, body: bytes) -> httpx.Response:
    headers = {"Content-Type": "application/json", "Content-Encoding": "gzip"}
    with dep.admin() as http:
        return http.post("/v1/trips", content=body, headers=headers)


def test_a_gzip_bomb_is_413_and_raises_the_peak_by_about_the_limit(memory_server, bomb):
    dep, peak = memory_server
    before = _table_counts(dep)
    peak.reset()
    response = _post_gzip(dep, bomb)
    assert response.status_code == 413, response.text
    assert response.json()["error"] == "too_large" and "after decompression" in response.json()["message"]
    assert peak.rise_bytes() < 300e6  # the limit (268 MB) and a step; inflating at once held it twice
    assert _table_counts(dep) == before


def test_four_concurrent_gzip_bombs_stay_within_the_budget_of_bytes_in_flight(memory_server, bomb):
    dep, peak = memory_server
    peak.reset()
    with ThreadPoolExecutor(4) as pool:
        responses = list(pool.map(lambda _: _post_gzip(dep, bomb), range(4)))
    assert {r.status_code for r in responses} <= {413, 503}, [r.text for r in responses]
    for refused in (r for r in responses if r.status_code == 503):
        assert refused.json()["error"] == "busy" and int(refused.headers["retry-after"]) > 0
    assert peak.rise_bytes() < 300e6  # four bombs each inflating to the limit would take 1 GB


def test_a_large_upload_of_small_frames_peaks_within_four_times_its_size(memory_server):
    dep, peak = memory_server
    doc = tiny_frame_trip(200_000, trip_id="tiny-200k")
    json_bytes = len(orjson.dumps(doc))
    peak.reset()
    response = dep.upload(doc, gzipped=True)
    assert response.status_code == 202, response.text
    assert response.json()["n_frames"] == 200_000
    # parsed whole, the frames took ~6x their JSON (~800 bytes each)
    assert peak.rise_bytes() <= 4 * json_bytes


@pytest.mark.parametrize("kind", ["embedded", "distributed"])
def test_an_upload_over_the_frame_limit_is_413_naming_both_and_stores_nothing(
    kind, make_isolated, shared_redis_url
):
    dep = make_isolated(kind, redis_url=shared_redis_url, CSR_MAX_FRAMES_PER_TRIP="150")
    dep.start_server()
    doc = moving_trip(length_m=150.0)
    assert len(doc["frames"]) == 151
    before = _table_counts(dep)
    response = dep.upload(doc, gzipped=True)
    assert response.status_code == 413, response.text
    body = response.json()
    assert (body["error"], body["location"]) == ("too_many_frames", "frames")
    assert "151 frames" in body["message"] and "limit of 150" in body["message"]
    assert _table_counts(dep) == before
    doc["frames"] = doc["frames"][:150]
    assert dep.upload(doc).status_code == 202  # at the limit


def test_uploads_beyond_the_bytes_in_flight_answer_503_with_retry_after(make_isolated):
    limit = str(1 * MIB)
    dep = make_isolated(
        "embedded",
        CSR_MAX_DECOMPRESSED_BYTES=limit,
        CSR_MAX_UPLOAD_BYTES_IN_FLIGHT=limit,
        CSR_EMBEDDED_WORKERS="0",
        CSR_SQLITE_BUSY_TIMEOUT_S="60",
    )
    dep.start_server()
    first, second = (moving_trip(length_m=400.0) for _ in range(2))
    sizes = [len(orjson.dumps(d)) for d in (first, second)]
    assert max(sizes) < MIB < sum(sizes)  # each fits alone, not both at once
    # the database's write lock held: an upload keeps its bytes in flight until it can store
    lock = sqlite3.connect(dep.db_url.removeprefix("sqlite:///"), isolation_level=None, timeout=30)
    lock.execute("BEGIN IMMEDIATE")
    try:
        with ThreadPoolExecutor(2) as pool:
            futures = [pool.submit(dep.upload, d, gzipped=True) for d in (first, second)]
            done, _ = wait(futures, timeout=50, return_when=FIRST_COMPLETED)
            refused = next(iter(done)).result()
            assert refused.status_code == 503, refused.text
            assert refused.json()["error"] == "busy" and refused.json()["location"] == "body"
            assert int(refused.headers["retry-after"]) > 0
            lock.execute("ROLLBACK")
            accepted = [f.result() for f in futures if f not in done][0]
    finally:
        lock.close()
    assert accepted.status_code == 202, accepted.text
    again = first if futures[0] in done else second
    assert dep.upload(again).status_code == 202  # sent again after Retry-After: accepted
    assert dep.scalar("SELECT count(*) FROM trips") == 2
