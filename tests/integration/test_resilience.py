"""The distributed deployment under failure: Redis down during uploads (transactional outbox),
a Celery worker killed with SIGKILL mid-task (late ack + re-delivery, idempotent tasks)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from tests.integration.conftest import Deployment, RedisServer, moving_trip, wait_until

pytestmark = pytest.mark.integration


def _ingest_jobs(dep: Deployment, trip_pk: str) -> list[tuple]:
    return [tuple(r) for r in dep.rows("SELECT state, attempts FROM jobs WHERE subject = :p", p=trip_pk)]


def _reconstructions(dep: Deployment, trip_pk: str) -> int:
    return dep.scalar("SELECT count(*) FROM trip_reconstructions WHERE trip_pk = :p", p=trip_pk)


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def test_uploads_while_redis_is_down_are_processed_once_it_is_back(make_isolated, private_redis: RedisServer):
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    worker = dep.start_worker()
    private_redis.stop()

    responses = [dep.upload(moving_trip()) for _ in range(5)]
    assert [r.status_code for r in responses] == [202] * 5
    trip_pks = [r.json()["id"] for r in responses]
    assert dep.scalar("SELECT count(*) FROM jobs WHERE dispatched_at IS NULL") == 5
    assert dep.summary()["queued"] == 5

    private_redis.start()
    wait_until(
        lambda: dep.scalar("SELECT count(*) FROM trips WHERE status = 'processing'") == 5,
        timeout_s=120,
        what=lambda: f"the uploads to be processed; worker log:\n{worker.log_tail()}",
    )
    for trip_pk in trip_pks:
        assert _ingest_jobs(dep, trip_pk) == [("done", 1)]
        assert _reconstructions(dep, trip_pk) == 1
    assert dep.summary() == {"queued": 0, "running": 0, "failed": 0, "dirty_tiles": 1}


def test_worker_killed_mid_task_the_task_is_redelivered_and_completes_once(
    make_isolated, private_redis: RedisServer
):
    """SIGKILL of the whole worker (main process and pool child, like a crashed machine): the
    message stays unacknowledged in Redis; a new worker restores it after the visibility timeout."""
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    first = dep.start_worker(CSR_TEST_INGEST_DELAY_S="120")
    trip_pk = dep.upload(moving_trip()).json()["id"]
    wait_until(lambda: _ingest_jobs(dep, trip_pk) == [("running", 1)], timeout_s=60, what="the task to start")
    first.kill_group(signal.SIGKILL)
    assert _ingest_jobs(dep, trip_pk) == [("running", 1)]

    second = dep.start_worker(CSR_VISIBILITY_TIMEOUT_S="4", CSR_JOB_TIME_LIMIT_S="3")
    wait_until(
        lambda: _ingest_jobs(dep, trip_pk) == [("done", 2)],
        timeout_s=90,
        what=lambda: f"re-delivery; worker log:\n{second.log_tail()}",
    )
    trip = dep.rows("SELECT status, length_km FROM trips WHERE id = :p", p=trip_pk)[0]
    assert trip[0] == "processing" and trip[1] > 0
    tiles = dep.scalar("SELECT count(*) FROM trip_tiles WHERE trip_pk = :p", p=trip_pk)
    assert tiles == dep.scalar("SELECT count(*) FROM dirty_tiles") == 1
    assert _reconstructions(dep, trip_pk) == 1
    assert "csr.ingest_trip" in second.log_tail(20000)


def test_pool_process_killed_mid_task_is_rejected_and_requeued(make_isolated, private_redis: RedisServer):
    """SIGKILL of the pool child only: the worker sees it lost (reject_on_worker_lost) and requeues
    the message at once; the same worker runs it again."""
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    worker = dep.start_worker(CSR_TEST_INGEST_DELAY_S="120")
    trip_pk = dep.upload(moving_trip()).json()["id"]
    wait_until(lambda: _ingest_jobs(dep, trip_pk) == [("running", 1)], timeout_s=60, what="the task to start")
    children = _children(worker.proc.pid)
    assert len(children) == 1, children
    os.kill(children[0], signal.SIGKILL)
    wait_until(
        lambda: _ingest_jobs(dep, trip_pk) == [("done", 2)],
        timeout_s=60,
        what=lambda: f"requeue; worker log:\n{worker.log_tail()}",
    )
    assert worker.alive()
    assert "WorkerLostError" in worker.log_tail(20000)
    assert dep.scalar("SELECT count(*) FROM trip_tiles WHERE trip_pk = :p", p=trip_pk) == 1
    assert _reconstructions(dep, trip_pk) == 1


def test_job_over_the_hard_time_limit_is_recorded_as_failed(make_isolated, private_redis: RedisServer):
    """Celery kills the pool process at the hard time limit; the task's on_failure records it."""
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    worker = dep.start_worker(
        CSR_TEST_INGEST_DELAY_S="60", CSR_JOB_TIME_LIMIT_S="2", CSR_VISIBILITY_TIMEOUT_S="30"
    )
    trip_pk = dep.upload(moving_trip()).json()["id"]
    wait_until(
        lambda: _ingest_jobs(dep, trip_pk) == [("failed", 1)],
        timeout_s=60,
        what=lambda: f"the time limit; worker log:\n{worker.log_tail()}",
    )
    error, status = dep.rows(
        "SELECT j.error, t.status FROM jobs j JOIN trips t ON t.id = j.subject WHERE t.id = :p", p=trip_pk
    )[0]
    assert "TimeLimitExceeded" in error and status == "failed"
    assert _reconstructions(dep, trip_pk) == 0  # nothing half-written
    assert dep.summary()["failed"] == 1
