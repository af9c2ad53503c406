"""Celery tasks: thin adapters that pass a job id to :func:`workers.jobs.run_job`."""

from __future__ import annotations

from workers.celery_app import app, runtime
from workers.jobs import run_job


@app.task(name="csr.ingest_trip")
def ingest_trip(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)


@app.task(name="csr.align_tile")
def align_tile(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)
