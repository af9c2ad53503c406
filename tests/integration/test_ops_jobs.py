"""Ops endpoints on both deployments: ``GET /v1/jobs`` (with errors), ``GET /v1/jobs/{id}``,
``GET /v1/tiles/dirty`` and ``POST /v1/jobs/{id}/retry`` (a new job through the outbox that really
runs again: in-process pool on the embedded default, a Celery worker on the distributed one)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy.orm import Session

from services.db.models import DirtyTile, Job, Trip
from tests.integration.conftest import Deployment, moving_trip, unique_trip, wait_until

pytestmark = pytest.mark.integration


def _key(dep: Deployment, role: str) -> str:
    body = {"role": role, **({"vehicle_id": "veh-ops"} if role == "vehicle" else {})}
    with dep.admin() as http:
        return http.post("/v1/keys", json=body).raise_for_status().json()["key"]


def _job(dep: Deployment, job_id: str) -> dict:
    with dep.admin() as http:
        return http.get(f"/v1/jobs/{job_id}").raise_for_status().json()


def _final(dep: Deployment, job_id: str) -> dict:
    return wait_until(
        lambda: (j := _job(dep, job_id))["state"] in ("done", "failed") and j,
        timeout_s=90,
        what=f"job {job_id} to finish",
    )


def _ingest_job(dep: Deployment, trip_pk: str) -> dict:
    with dep.admin() as http:
        jobs = (
            http.get("/v1/jobs", params={"kind": "ingest_trip", "subject": trip_pk}).raise_for_status().json()
        )
    assert len(jobs["jobs"]) == 1, jobs
    return jobs["jobs"][0]


def test_jobs_list_failed_job_with_its_error(deployment: Deployment) -> None:
    trip_pk = deployment.upload(unique_trip()).json()["id"]  # the contract example: its ingest fails
    deployment.wait_idle()
    reader = deployment.client(_key(deployment, "reader"))
    with reader:
        listed = reader.get("/v1/jobs", params={"state": "failed", "kind": "ingest_trip", "limit": 500})
        assert listed.status_code == 200, listed.text
        mine = [j for j in listed.json()["jobs"] if j["subject"] == trip_pk]
        assert len(mine) == 1
        job = mine[0]
        assert job["state"] == "failed" and job["queue"] == "ingest" and job["attempts"] == 1
        assert "single-trip reconstruction failed" in job["error"]
        assert job["finished_at"] and job["duration_s"] is not None and job["retried_by"] is None
        queues = listed.json()["queues"]
        assert set(queues) >= {"ingest", "align", "merge"} and queues["ingest"]["failed"] >= 1
        assert reader.get(f"/v1/jobs/{job['id']}").json() == job
        # newest first; filters are checked
        all_jobs = reader.get("/v1/jobs", params={"limit": 500}).json()["jobs"]
        created = [j["created_at"] for j in all_jobs]
        assert created == sorted(created, reverse=True)
        assert reader.get("/v1/jobs", params={"state": "bogus"}).status_code == 422
        assert reader.get("/v1/jobs", params={"kind": "bogus"}).json()["location"] == "kind"
        assert reader.get("/v1/jobs", params={"limit": 0}).status_code == 422
        assert reader.get("/v1/jobs/no-such-job").status_code == 404
        # a reader may look, not retry
        assert reader.post(f"/v1/jobs/{job['id']}/retry").status_code == 403
    with deployment.client() as anonymous:
        assert anonymous.get("/v1/jobs").status_code == 401


def test_dirty_tiles_lists_waiting_tiles(deployment: Deployment) -> None:
    trip_pk = deployment.upload(moving_trip()).json()["id"]
    deployment.wait_idle()
    with deployment.admin() as http:
        tiles = http.get(f"/v1/trips/{trip_pk}").json()["tiles"]
        dirty = {t["tile"]: t for t in http.get("/v1/tiles/dirty").raise_for_status().json()["tiles"]}
    assert tiles and set(tiles) <= set(dirty)
    for name in tiles:
        entry = dirty[name]
        z, x, y = (int(v) for v in name.split("/"))
        assert (entry["z"], entry["x"], entry["y"]) == (z, x, y)
        assert entry["pending_trips"] >= 1
        assert entry["first_marked_at"] <= entry["last_marked_at"]
        assert entry["job_id"] is None  # the quiet period (an hour in the tests) has not passed
    with deployment.client(_key(deployment, "vehicle")) as vehicle:
        assert vehicle.get("/v1/tiles/dirty").status_code == 403


def test_retry_failed_ingest_runs_a_new_job(deployment: Deployment) -> None:
    """A trip whose ingest failed (simulated: an outage recorded as its failure) is retried: a new
    ingest job goes through the outbox, runs, and the trip is processed."""
    trip_pk = deployment.upload(moving_trip()).json()["id"]
    deployment.wait_idle()
    first = _ingest_job(deployment, trip_pk)
    assert first["state"] == "done"
    with Session(deployment.engine) as session, session.begin():
        job = session.get(Job, first["id"])
        assert job is not None
        job.state, job.error = "failed", "OperationalError: simulated outage"
        trip = session.get(Trip, trip_pk)
        assert trip is not None
        trip.status, trip.error = "failed", "simulated outage"

    with deployment.admin() as http:
        answer = http.post(f"/v1/jobs/{first['id']}/retry")
        assert answer.status_code == 202, answer.text
        retry = answer.json()
        assert retry["retry_of"] == first["id"] and retry["id"] != first["id"]
        assert (retry["kind"], retry["subject"], retry["state"]) == ("ingest_trip", trip_pk, "queued")
        assert answer.headers["location"] == f"/v1/jobs/{retry['id']}"
        # the failed job is kept as it was, linked to its retry
        old = http.get(f"/v1/jobs/{first['id']}").json()
        assert old["state"] == "failed" and old["error"] == "OperationalError: simulated outage"
        assert old["retried_by"] == retry["id"]
        # retried once only; only failed jobs
        second = http.post(f"/v1/jobs/{first['id']}/retry")
        assert second.status_code == 409 and second.json()["error"] == "superseded"

    done = _final(deployment, retry["id"])
    assert done["state"] == "done", done
    assert done["attempts"] == 1 and done["started_at"] and done["finished_at"]
    with deployment.admin() as http:
        trip = http.get(f"/v1/trips/{trip_pk}").json()
        assert trip["status"] == "processing" and trip["error"] is None
        assert trip["reconstruction"] is not None
        again = http.post(f"/v1/jobs/{retry['id']}/retry")
        assert again.status_code == 409 and again.json()["error"] == "not_failed"
        assert http.post("/v1/jobs/no-such-job/retry").status_code == 404


def test_retry_failed_tile_job_moves_the_dirty_tile_to_the_new_job(deployment: Deployment) -> None:
    """A failed align_tile job held its dirty tile; the retry's new job takes the tile over (the
    scheduler skips a tile that has a job) and runs."""
    z, x, y = 16, 1, 2 + (0 if deployment.distributed else 1)  # an empty tile of this test's own
    now = datetime.now(UTC)
    failed_id = f"failed-align-{z}-{x}-{y}"
    with Session(deployment.engine) as session, session.begin():
        session.add(
            Job(
                id=failed_id,
                kind="align_tile",
                queue="align",
                subject=f"{z}/{x}/{y}",
                state="failed",
                attempts=1,
                error="RuntimeError: simulated",
                created_at=now,
                dispatched_at=now,
                started_at=now,
                finished_at=now,
                duration_s=0.1,
            )
        )
        session.add(DirtyTile(z=z, x=x, y=y, first_marked_at=now, last_marked_at=now, job_id=failed_id))

    with deployment.admin() as http:
        answer = http.post(f"/v1/jobs/{failed_id}/retry")
        assert answer.status_code == 202, answer.text
        retry = answer.json()
    final = _final(deployment, retry["id"])
    assert final["attempts"] == 1 and final["kind"] == "align_tile" and final["subject"] == f"{z}/{x}/{y}"
    with Session(deployment.engine) as session:
        dirty = session.get(DirtyTile, (z, x, y))
        # done: the job cleared the tile; failed: the tile waits for the new job, not the old one
        assert (
            (dirty is None)
            if final["state"] == "done"
            else (dirty is not None and dirty.job_id == retry["id"])
        )


def test_retry_a_running_job_whose_lease_ran_out(make_isolated) -> None:
    """A job left ``running`` with no worker renewing its lease is retried (202): it is recorded as
    failed and a new job processes the trip. A running job with a live lease is not (409). On the
    embedded default, where no relay re-queues expired leases, the stuck job stays for the call
    (the distributed relay queues such a job again by itself: tests/integration/test_broker_loss.py)."""
    deployment = make_isolated("embedded")
    deployment.start_server()
    trip_pk = deployment.upload(moving_trip()).json()["id"]
    deployment.wait_idle()
    stuck_id = _ingest_job(deployment, trip_pk)["id"]
    now = datetime.now(UTC)
    with Session(deployment.engine) as session, session.begin():
        job = session.get(Job, stuck_id)
        assert job is not None
        job.state, job.lease_expires_at = "running", now - timedelta(seconds=1)
        session.add(
            Job(
                id=f"live-{stuck_id}",
                kind="ingest_trip",
                queue="ingest",
                subject=f"live-{trip_pk}",
                state="running",
                attempts=1,
                created_at=now,
                dispatched_at=now,
                started_at=now,
                lease_expires_at=now + timedelta(hours=1),
            )
        )
    with deployment.admin() as http:
        live = http.post(f"/v1/jobs/live-{stuck_id}/retry")
        assert live.status_code == 409 and live.json()["error"] == "not_failed"
        with Session(deployment.engine) as session, session.begin():
            session.delete(session.get(Job, f"live-{stuck_id}"))
        answer = http.post(f"/v1/jobs/{stuck_id}/retry")
        assert answer.status_code == 202, answer.text
        old = http.get(f"/v1/jobs/{stuck_id}").json()
        assert old["state"] == "failed" and "lease expired" in old["error"]
        assert old["retried_by"] == answer.json()["id"]
    failed_before = deployment.summary()["failed"]
    assert _final(deployment, answer.json()["id"])["state"] == "done"
    assert deployment.wait_idle()["failed"] == failed_before  # the stuck job counts as retried, not failed
