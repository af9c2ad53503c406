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


def _job_task(kind: str) -> JobTask:
    """The Celery task of one job kind (``csr.<kind>``): it runs the job by id."""

    def run(job_id: str) -> str:
        rt = runtime()
        return run_job(rt.session_factory, rt.settings, job_id)

    run.__name__ = kind
    return app.task(name=f"csr.{kind}", base=JobTask)(run)


ingest_trip = _job_task("ingest_trip")
align_tile = _job_task("align_tile")
correct_tile = _job_task("correct_tile")
merge_tile = _job_task("merge_tile")
