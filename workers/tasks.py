"""Celery tasks: thin adapters that pass a job id to :func:`workers.jobs.run_job`. A database
outage is retried with backoff; everything else is recorded on the job by ``run_job``."""

from __future__ import annotations

import logging

from celery import Task
from sqlalchemy.exc import OperationalError

from workers.celery_app import app, runtime
from workers.jobs import mark_job_failed, run_job
from workers.outbox import relay_once

log = logging.getLogger(__name__)


class JobTask(Task):
    """Retries database outages; records on the job what ends a task outside ``run_job``: the
    hard time limit (the pool process is killed) or retries exhausted."""

    autoretry_for = (OperationalError,)
    retry_backoff = True
    retry_backoff_max = 300
    max_retries = 10

    def on_failure(self, exc, task_id, args, kwargs, einfo) -> None:
        mark_job_failed(runtime().session_factory, args[0], exc)


def _publish_follow_ups(rt) -> None:
    """Hand the jobs this one queued (an alignment's merge) to Redis before the worker takes its
    next message, so that it takes the merge (priority 0, ``workers.dispatch``) and not another
    alignment; otherwise they wait for the outbox relay's next round and then for a free worker.
    A broker error leaves them to the relay."""
    try:
        relay_once(
            rt.session_factory,
            app,
            redispatch_after_s=rt.settings.redispatch_after_s,
            checkerboard=rt.settings.tile_checkerboard,
        )
    except Exception:  # the relay sends them
        log.warning("could not publish the jobs that followed; the outbox relay will", exc_info=True)


def _job_task(kind: str) -> JobTask:
    """The Celery task of one job kind (``csr.<kind>``): it runs the job by id."""

    def run(job_id: str) -> str:
        rt = runtime()
        state = run_job(rt.session_factory, rt.settings, job_id)
        _publish_follow_ups(rt)
        return state

    run.__name__ = kind
    return app.task(name=f"csr.{kind}", base=JobTask)(run)


ingest_trip = _job_task("ingest_trip")
align_tile = _job_task("align_tile")
correct_tile = _job_task("correct_tile")
merge_tile = _job_task("merge_tile")
