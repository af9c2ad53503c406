"""The embedded default's job runner: the same job functions as the Celery tasks, run in-process
on a thread pool. A dispatcher thread takes outbox rows (jobs not yet dispatched) and submits
them; nothing is lost across a restart, because jobs left running are queued again at start.
This is not Celery's eager mode: uploads return before their jobs run."""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

from sqlalchemy import update
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from services.db import repo
from services.db.models import Job, utcnow
from services.settings import Settings
from workers.jobs import run_job
from workers.loop import BackgroundLoop

log = logging.getLogger(__name__)

BATCH = 100  # outbox rows taken per round
RETRY_AFTER_S = 5.0  # a job that met a database outage is queued again after this


class EmbeddedRunner(BackgroundLoop):
    name = "csr-embedded-dispatch"

    def __init__(self, settings: Settings, session_factory: sessionmaker[Session]) -> None:
        super().__init__(settings, session_factory)
        self._pool = ThreadPoolExecutor(max(1, settings.embedded_workers), thread_name_prefix="csr-job")

    def start(self) -> None:
        with self.session_factory.begin() as session:
            n = repo.reset_running_jobs(session)
        if n:
            log.info("re-queued %d job(s) left running by a previous process", n)
        super().start()

    def stop(self) -> None:
        super().stop()
        self._pool.shutdown(wait=True, cancel_futures=True)

    def tick(self) -> None:
        if self.settings.embedded_workers == 0:  # jobs wait in the database for a process that runs them
            return
        with self.session_factory.begin() as session:
            jobs = repo.jobs_to_dispatch(session, limit=BATCH, redispatch_before=None)
            now = utcnow()
            for job in jobs:
                job.dispatched_at = now
            ids = [job.id for job in jobs]
        for job_id in ids:
            self._pool.submit(self._run_one, job_id)
        if len(ids) == BATCH:
            self.wake()

    def _run_one(self, job_id: str) -> None:
        try:
            run_job(self.session_factory, self.settings, job_id)
        except OperationalError:
            log.warning("job %s: database unavailable; it runs again later", job_id, exc_info=True)
            self._requeue_later(job_id)
        finally:
            self.wake()

    def _requeue_later(self, job_id: str) -> None:
        time.sleep(RETRY_AFTER_S)
        try:
            with self.session_factory.begin() as session:
                session.execute(
                    update(Job)
                    .where(Job.id == job_id, Job.state == "running")
                    .values(state="queued", dispatched_at=None)
                )
        except OperationalError:
            log.warning("job %s stays running until the next start", job_id)
