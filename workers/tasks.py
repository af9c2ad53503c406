"""Celery tasks: thin adapters that pass a job id to :func:`workers.jobs.run_job`. A database
outage is retried with backoff; everything else is recorded on the job by ``run_job``."""

from __future__ import annotations

from celery import Task
from sqlalchemy.exc import OperationalError

from workers.celery_app import app, runtime
from workers.jobs import mark_job_failed, run_job


class JobTask(Task):
    """Retries database outages; records on the job what ends a task outside ``run_job``: the
    hard time limit (the pool process is killed) or retries exhausted."""

    autoretry_for = (OperationalError,)
    retry_backoff = True
    retry_backoff_max = 300
    max_retries = 10

    def on_failure(self, exc, task_id, args, kwargs, einfo) -> None:
        mark_job_failed(runtime().session_factory, args[0], exc)


@app.task(name="csr.ingest_trip", base=JobTask)
def ingest_trip(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)


@app.task(name="csr.align_tile", base=JobTask)
def align_tile(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)


@app.task(name="csr.merge_tile", base=JobTask)
def merge_tile(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)


@app.task(name="csr.correct_tile", base=JobTask)
def correct_tile(job_id: str) -> str:
    rt = runtime()
    return run_job(rt.session_factory, rt.settings, job_id)
