"""The transactional outbox relay (distributed deployment): jobs are committed to the database
together with what caused them; this relay hands them to Redis. An upload accepted while Redis is
down stays in the outbox and is sent when Redis is back. A message that reached Redis but whose
dispatch was not recorded is sent again: the tasks are idempotent.

Each round also recovers what a broker outage loses:

- **Running jobs**: a job whose lease ran out (``workers.lease``: its worker died, or Celery
  cancelled it when the broker connection dropped) is queued again.
- **Queued messages**: the relay keeps a marker key in the broker's database
  (:data:`BROKER_MARKER_KEY`). The key lives and dies with the messages: a Redis restarted without
  persistence, or flushed, has lost both. A round that finds it missing marks every queued job as
  not dispatched, so the same round sends them all again, then sets the key. With persistence the
  key survives with the messages and nothing is re-sent. A message sent twice (several relays
  noticing the loss at once, or one sent just before the check) is harmless: a job's result is
  written once (``workers.jobs``). ``CSR_REDISPATCH_AFTER_S`` stays as the backstop for a message lost otherwise.
"""

from __future__ import annotations

import logging
from datetime import timedelta

import redis
from celery import Celery
from sqlalchemy.orm import Session, sessionmaker

from services.db import repo
from services.db.models import utcnow
from services.settings import Settings
from workers import dispatch
from workers.loop import BackgroundLoop

log = logging.getLogger(__name__)

BATCH = 200  # outbox rows per round; one publish is ~0.1 ms on loopback Redis
BROKER_MARKER_KEY = "csr:outbox:broker-marker"
TASK_OF_KIND = {
    "ingest_trip": "csr.ingest_trip",
    "align_tile": "csr.align_tile",
    "correct_tile": "csr.correct_tile",
    "merge_tile": "csr.merge_tile",
}


def relay_once(
    session_factory: sessionmaker[Session],
    celery_app: Celery,
    *,
    redispatch_after_s: float,
    checkerboard: bool = True,
) -> int:
    """Publish up to ``BATCH`` outbox rows, each with its priority (``workers.dispatch``: held-back
    tiles stay in the outbox); returns how many were sent. Raises when the broker is down (rows
    published before the failure are recorded as dispatched)."""
    sent, error = 0, None
    with session_factory.begin() as session:
        plan = dispatch.take_dispatchable(
            session,
            limit=BATCH,
            redispatch_before=utcnow() - timedelta(seconds=redispatch_after_s),
            checkerboard=checkerboard,
        )
        for d in plan:
            job = d.job
            try:
                celery_app.send_task(
                    TASK_OF_KIND[job.kind],
                    args=[job.id],
                    queue=job.queue,
                    task_id=job.id,
                    priority=d.priority,
                )
            except Exception as exc:  # broker down: keep what was sent, the rest stays in the outbox
                error = exc
                break
            job.dispatched_at = utcnow()
            sent += 1
    if error is not None:
        raise error
    return sent


def broker_client(redis_url: str) -> redis.Redis:
    """A client of the broker's Redis database with short timeouts (a down broker answers fast)."""
    return redis.Redis.from_url(redis_url, socket_connect_timeout=1, socket_timeout=2)


def requeue_expired_leases(session_factory: sessionmaker[Session]) -> int:
    """Queue again the running jobs whose lease ran out; returns how many."""
    with session_factory.begin() as session:
        ids = repo.requeue_expired_leases(session, now=utcnow())
    if ids:
        log.warning("queued %d job(s) again whose lease ran out: %s", len(ids), ", ".join(ids))
    return len(ids)


def resend_if_broker_lost_messages(session_factory: sessionmaker[Session], client: redis.Redis) -> int:
    """When the broker's marker key is missing (it lost its data, see the module doc): mark every
    queued job as not dispatched, then set the key; returns how many jobs are to be sent again.
    Raises when the broker is unreachable."""
    if client.exists(BROKER_MARKER_KEY):
        return 0
    with session_factory.begin() as session:
        n = repo.forget_dispatches(session)
    client.set(BROKER_MARKER_KEY, utcnow().isoformat())
    if n:
        log.warning("the broker lost its messages: %d queued job(s) are sent again", n)
    return n


class OutboxRelay(BackgroundLoop):
    name = "csr-outbox-relay"

    def __init__(
        self, settings: Settings, session_factory: sessionmaker[Session], celery_app: Celery
    ) -> None:
        super().__init__(settings, session_factory)
        self.celery_app = celery_app
        self.broker = broker_client(settings.redis_url or "")
        self._broker_down = False

    def broker_reachable(self) -> bool:
        """One PING of the broker (``/healthz``)."""
        try:
            return bool(self.broker.ping())
        except redis.RedisError:
            return False

    def tick(self) -> None:
        requeue_expired_leases(self.session_factory)
        try:
            resend_if_broker_lost_messages(self.session_factory, self.broker)
            sent = relay_once(
                self.session_factory,
                self.celery_app,
                redispatch_after_s=self.settings.redispatch_after_s,
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
