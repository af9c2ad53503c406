"""The transactional outbox relay (distributed deployment): jobs are committed to the database
together with what caused them; this relay hands them to Redis. An upload accepted while Redis is
down stays in the outbox and is sent when Redis is back. A message that reached Redis but whose
dispatch was not recorded is sent again: the tasks are idempotent."""

from __future__ import annotations

import logging
from datetime import timedelta

from celery import Celery
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import utcnow
from services.settings import Settings
from workers import dispatch
from workers.loop import BackgroundLoop

log = logging.getLogger(__name__)

BATCH = 200  # outbox rows per round; one publish is ~0.1 ms on loopback Redis
TASK_OF_KIND = {
    "ingest_trip": "csr.ingest_trip",
    "align_tile": "csr.align_tile",
    "correct_tile": "csr.correct_tile",
    "merge_tile": "csr.merge_tile",
}


def relay_once(
    session_factory: sessionmaker[Session], celery_app: Celery, *, redispatch_after_s: float,
    checkerboard: bool = True,
) -> int:
    """Publish up to ``BATCH`` outbox rows, each with its priority (``workers.dispatch``: held-back
    tiles stay in the outbox); returns how many were sent. Raises when the broker is down (rows
    published before the failure are recorded as dispatched)."""
    sent, error = 0, None
    with session_factory.begin() as session:
        plan = dispatch.take_dispatchable(
            session, limit=BATCH, redispatch_before=utcnow() - timedelta(seconds=redispatch_after_s),
            checkerboard=checkerboard,
        )
        for d in plan:
            job = d.job
            try:
                celery_app.send_task(TASK_OF_KIND[job.kind], args=[job.id], queue=job.queue, task_id=job.id,
                                     priority=d.priority)
            except Exception as exc:  # broker down: keep what was sent, the rest stays in the outbox
                error = exc
                break
            job.dispatched_at = utcnow()
            sent += 1
    if error is not None:
        raise error
    return sent


class OutboxRelay(BackgroundLoop):
    name = "csr-outbox-relay"

    def __init__(
        self, settings: Settings, session_factory: sessionmaker[Session], celery_app: Celery
    ) -> None:
        super().__init__(settings, session_factory)
        self.celery_app = celery_app
        self._broker_down = False

    def tick(self) -> None:
        try:
            sent = relay_once(
                self.session_factory, self.celery_app, redispatch_after_s=self.settings.redispatch_after_s,
                checkerboard=self.settings.tile_checkerboard,
            )
        except Exception as exc:
            if not self._broker_down:
                log.warning("broker unreachable, jobs stay in the outbox: %s", exc)
            self._broker_down = True
            return
        if self._broker_down:
            log.info("broker reachable again")
        self._broker_down = False
        if sent == BATCH:
            self.wake()
