"""The ops page in headless Chromium: counts, the queue-depth and job-duration charts, a failed job
with its error, dirty tiles, and the retry of a failed job through the page (a new job that runs)."""

from __future__ import annotations

import pytest
from sqlalchemy.orm import Session

from services.db.models import Job, Trip
from tests.browser.conftest import run_driver
from tests.integration.conftest import moving_trip, unique_trip

pytestmark = pytest.mark.integration


def test_ops_page_lists_and_retries_a_failed_job(browser_ready, make_isolated) -> None:
    dep = make_isolated("embedded")
    dep.start_server()
    bad = dep.upload(unique_trip()).json()["id"]  # fails for real: single-trip cannot orient it
    good = dep.upload(moving_trip()).json()["id"]
    dep.wait_idle()
    with dep.admin() as http:
        job_id = http.get("/v1/jobs", params={"subject": good}).json()["jobs"][0]["id"]
    with Session(dep.engine) as session, session.begin():  # an outage recorded as its failure
        job = session.get(Job, job_id)
        assert job is not None
        job.state, job.error = "failed", "OperationalError: simulated database outage"
        trip = session.get(Trip, good)
        assert trip is not None
        trip.status, trip.error = "failed", "simulated"

    with dep.admin() as http:
        listed = http.get("/v1/jobs", params={"limit": 200}).json()["jobs"]
    finished = [j for j in listed if j["finished_at"] and j["duration_s"] is not None]
    failed_now = [j for j in finished if j["state"] == "failed"]
    done_now = [j for j in finished if j["state"] == "done"]

    result = run_driver("ops", base=dep.base_url, key=dep.admin_key, retry_job=job_id)
    checks = result["checks"]
    assert not result["errors"], result
    assert checks["summary_failed"] == "2"
    assert "simulated database outage" in checks["failed_row"] and "retry" in checks["failed_row"]
    assert checks["dirty_rows"] >= 1
    assert checks["queue_ingest"].split() == ["ingest", "0", "0", "2", "0"]  # queued running failed done
    # the queue depth over time: one sample per refresh, drawn as a line per count
    depth = checks["charts"]["depth-chart"]
    assert set(depth) == {"queued", "running", "dirty_tiles"}
    for series in depth.values():
        assert series["samples"] >= 2 and series["circles"] == series["polyline"] == series["samples"]
    # the job durations: a dot per finished job listed, by state
    durations = checks["charts"]["duration-chart"]
    for state, jobs in (("failed", failed_now), ("done", done_now)):
        assert durations[state]["circles"] == len(jobs), (state, durations, jobs)
    assert durations["failed"]["circles"] >= 1
    assert "retrying ingest_trip" in checks["message"]
    rows = {r["id"]: r for r in checks["rows_for_subject"]}
    assert len(rows) == 2 and rows[job_id]["state"] == "failed" and "retried" in rows[job_id]["text"]
    (new_id,) = set(rows) - {job_id}
    assert rows[new_id]["state"] == "done"
    with dep.admin() as http:
        assert http.get(f"/v1/jobs/{new_id}").json()["attempts"] == 1
        assert http.get(f"/v1/trips/{good}").json()["status"] == "processing"
        failed = http.get("/v1/jobs", params={"state": "failed"}).json()["jobs"]
        assert {j["subject"] for j in failed} == {bad, good}
