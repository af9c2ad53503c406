"""The embedded default's job runner: the same job functions as the Celery tasks, run in-process
on a thread pool. A dispatcher thread takes outbox rows (jobs not yet dispatched) whenever a
thread is free, in ``workers.dispatch``'s order (merges first, then the biggest tiles; held-back
tiles stay in the outbox), and submits them; nothing is lost across a restart, because jobs left
running are queued again at start. This is not Celery's eager mode: uploads return before their
jobs run."""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from sqlalchemy import update
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from services.db import repo
from services.db.models import Job, utcnow
from services.settings import Settings
from workers import dispatch
from workers.jobs import run_job
from workers.loop import BackgroundLoop

log = logging.getLogger(__name__)

BATCH = 100  # outbox rows read per page
RETRY_AFTER_S = 5.0  # a job that met a database outage is queued again after this


class EmbeddedRunner(BackgroundLoop):
    name = "csr-embedded-dispatch"

    def __init__(self, settings: Settings, session_factory: sessionmaker[Session]) -> None:
        super().__init__(settings, session_factory)
        self._threads = max(1, settings.embedded_workers)
        self._pool = ThreadPoolExecutor(self._threads, thread_name_prefix="csr-job")
        self._in_flight = 0  # jobs submitted and not yet ended
        self._lock = threading.Lock()

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
        with self._lock:
            free = self._threads - self._in_flight
        if free <= 0:  # a job's end wakes this loop again
            return
        with self.session_factory.begin() as session:
            plan = dispatch.take_dispatchable(
                session,
                limit=free,
                redispatch_before=None,
                checkerboard=self.settings.tile_checkerboard,
                page=BATCH,
            )
            now = utcnow()
            for d in plan:
                d.job.dispatched_at = now
            ids = [d.job.id for d in plan]
        with self._lock:
            self._in_flight += len(ids)
        for job_id in ids:
            self._pool.submit(self._run_one, job_id)

    def _run_one(self, job_id: str) -> None:
        try:
            run_job(self.session_factory, self.settings, job_id)
        except OperationalError:
            log.warning("job %s: database unavailable; it runs again later", job_id, exc_info=True)
            self._requeue_later(job_id)
        finally:
            with self._lock:
                self._in_flight -= 1
            self.wake()

    def _requeue_later(self, job_id: str) -> None:
        time.sleep(RETRY_AFTER_S)
        try:
            with self.session_factory.begin() as session:
                session.execute(
                    update(Job)
                    .where(Job.id == job_id, Job.state == "running")
                    .values(state="queued", dispatched_at=None, lease_expires_at=None)
                )
        except OperationalError:
            log.warning("job %s stays running until the next start", job_id)
