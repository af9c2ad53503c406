"""Celery tasks: thin adapters that pass a job id to :func:`workers.jobs.run_job`. A database
outage is retried with backoff; everything else is recorded on the job by ``run_job``."""

from __future__ import annotations

from sqlalchemy.exc import OperationalError

from workers.celery_app import app, runtime
from workers.jobs import run_job

RETRY = {
    "autoretry_for": (OperationalError,),
    "retry_backoff": True,
    "retry_backoff_max": 300,
    "max_retries": 10,
}


@app.task(name="csr.ingest_trip", **RETRY)
def ingest_trip(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)


@app.task(name="csr.align_tile", **RETRY)
def align_tile(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)
