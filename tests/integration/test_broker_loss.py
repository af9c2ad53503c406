"""The distributed deployment losing its broker: Redis (no persistence) killed while a job runs and
others wait in it, uploads accepted while it is down, then Redis started again empty. Every
accepted upload is processed once and the job summary drains: the running job by its lease, the
lost messages by the outbox noticing the broker's lost data."""

from __future__ import annotations

import logging
import time

import httpx
import pytest

from tests.integration.conftest import Deployment, RedisServer, moving_trip, wait_until

pytestmark = pytest.mark.integration

log = logging.getLogger(__name__)

LEASE_S = "3"  # a job whose worker stops renewing its lease is queued again ~3 s later
INGEST_DELAY_S = "6"  # first attempts take this long: long enough to lose Redis mid-job
DRAIN_TIMEOUT_S = 120.0


def _jobs_of(dep: Deployment, trip_pks: list[str]) -> dict[str, list[tuple]]:
    rows = dep.rows("SELECT subject, state FROM jobs WHERE kind = 'ingest_trip'")
    return {pk: sorted(tuple(r[1:]) for r in rows if r[0] == pk) for pk in trip_pks}


def _drained(dep: Deployment) -> bool:
    summary = dep.summary()
    return summary["queued"] == 0 and summary["running"] == 0


def test_redis_lost_mid_job_every_upload_is_processed_once_it_is_back(
    make_isolated, private_redis: RedisServer
):
    dep = make_isolated("distributed", redis_url=private_redis.url, CSR_JOB_LEASE_S=LEASE_S)
    dep.start_server()
    worker = dep.start_worker(CSR_TEST_INGEST_DELAY_S=INGEST_DELAY_S)
    running = dep.upload(moving_trip()).json()["id"]
    wait_until(
        lambda: dep.scalar("SELECT state FROM jobs WHERE subject = :p", p=running) == "running",
        timeout_s=60,
        what="the first job to start",
    )
    in_redis = dep.upload(moving_trip()).json()["id"]
    wait_until(
        lambda: dep.scalar("SELECT count(*) FROM jobs WHERE dispatched_at IS NULL") == 0,
        timeout_s=30,
        what="the second job to reach Redis",
    )

    private_redis.stop()  # its messages are gone: no persistence
    late = dep.upload(moving_trip())
    assert late.status_code == 202
    time.sleep(float(LEASE_S) + 2)  # the running job's worker gave it up; its lease runs out
    private_redis.start()
    back = time.monotonic()

    trip_pks = [running, in_redis, late.json()["id"]]
    wait_until(
        lambda: _drained(dep),
        timeout_s=DRAIN_TIMEOUT_S,
        what=lambda: f"the summary to drain ({dep.summary()}); worker log:\n{worker.log_tail()}",
    )
    log.info("drained %.1f s after Redis was back", time.monotonic() - back)
    assert _jobs_of(dep, trip_pks) == {pk: [("done",)] for pk in trip_pks}
    for pk in trip_pks:
        assert dep.scalar("SELECT status FROM trips WHERE id = :p", p=pk) == "processing"
        assert dep.scalar("SELECT count(*) FROM trip_reconstructions WHERE trip_pk = :p", p=pk) == 1
    assert dep.summary() == {"queued": 0, "running": 0, "failed": 0, "dirty_tiles": 1}


def test_healthz_reports_the_broker(make_isolated, private_redis: RedisServer):
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    health = httpx.get(dep.base_url + "/healthz", timeout=10)
    assert health.status_code == 200
    assert health.json() == {"status": "ok", "database": "postgresql", "jobs": "distributed", "broker": "ok"}
    private_redis.stop()
    health = httpx.get(dep.base_url + "/healthz", timeout=10)
    assert health.status_code == 200  # uploads are still accepted (the outbox keeps their jobs)
    assert health.json()["status"] == "degraded" and health.json()["broker"] == "unreachable"
    private_redis.start()
    wait_until(
        lambda: httpx.get(dep.base_url + "/healthz", timeout=10).json()["status"] == "ok",
        timeout_s=10,
        what="/healthz to report the broker back",
    )
