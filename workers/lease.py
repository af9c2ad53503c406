"""Leases on running jobs (both runners). A job that starts running takes a lease of
``CSR_JOB_LEASE_S``; a heartbeat thread beside the job renews it every third of that until the
job ends. A runner that dies, or a Celery task cancelled because its broker connection was lost,
stops renewing: the outbox relay then finds the lease run out and queues the job again
(``services.db.repo.requeue_expired_leases``), so a job never stays ``running`` without a
worker. The re-run is idempotent like any re-delivery (``workers.jobs``)."""

from __future__ import annotations

import logging
import threading
from datetime import datetime, timedelta
from types import TracebackType
from typing import cast

from sqlalchemy import CursorResult, update
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import Job, utcnow

log = logging.getLogger(__name__)

RENEWALS_PER_LEASE = 3  # renewals within one lease: two may fail before the lease runs out


def lease_until(lease_s: float, *, now: datetime | None = None) -> datetime:
    return (now or utcnow()) + timedelta(seconds=lease_s)


def renew_lease(session_factory: sessionmaker[Session], job_id: str, lease_s: float) -> bool:
    """Extend a running job's lease; False when the job no longer runs (it ended, or was queued again)."""
    with session_factory.begin() as session:
        result = cast(
            CursorResult,
            session.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == "running")
                .values(lease_expires_at=lease_until(lease_s))
            ),
        )
    return bool(result.rowcount)


class LeaseHeartbeat:
    """``with LeaseHeartbeat(...)``: renews one job's lease on a daemon thread while the block runs.
    A renewal that fails (the database unreachable) is logged and tried again at the next beat."""

    def __init__(self, session_factory: sessionmaker[Session], job_id: str, lease_s: float) -> None:
        self.session_factory = session_factory
        self.job_id = job_id
        self.lease_s = lease_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"csr-lease-{job_id[:8]}", daemon=True)

    def __enter__(self) -> LeaseHeartbeat:
        self._thread.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(self.lease_s / RENEWALS_PER_LEASE):
            try:
                if not renew_lease(self.session_factory, self.job_id, self.lease_s):
                    return
            except Exception:
                log.warning("job %s: could not renew its lease; trying again", self.job_id, exc_info=True)
