"""The Celery app of the distributed deployment: Redis broker, queues ``ingest``, ``align``,
``merge``; late acks, prefetch 1, reject on worker loss, visibility timeout above the job time limit.

``celery -A workers.celery_app worker`` (or ``csr worker``) configures it from the environment
when Celery first needs its configuration, not at import. The main process of a worker also runs
the outbox relay, so that jobs reach Redis even while no API process is up.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

from celery import Celery, signals
from kombu import Exchange, Queue
from sqlalchemy.orm import Session, sessionmaker

from services.db.engine import make_engine, make_session_factory
from services.db.repo import QUEUES
from services.settings import Settings, get_settings
from workers.dispatch import PRIORITY_STEPS

log = logging.getLogger(__name__)


def celery_config(settings: Settings) -> dict[str, Any]:
    if not settings.redis_url:
        raise RuntimeError("the distributed deployment needs CSR_REDIS_URL")
    return {
        "broker_url": settings.redis_url,
        "broker_transport_options": {
            "visibility_timeout": settings.visibility_timeout_s,
            # Sweep for messages of dead workers (unacknowledged past the visibility timeout) every
            # ~tenth of that timeout; kombu's default sweep is every 10 x 10 s.
            "unacked_restore_interval": max(1, min(60, settings.visibility_timeout_s // 10)),
            "unacked_restore_throttle": 1,
            "socket_connect_timeout": 2,
            "socket_timeout": 10,
            # message priorities (workers.dispatch): BRPOP takes the lowest step first across the queues
            "priority_steps": list(PRIORITY_STEPS),
        },
        "broker_connection_retry_on_startup": True,
        "task_queues": tuple(Queue(name, Exchange(name, type="direct"), routing_key=name) for name in QUEUES),
        "task_default_queue": "ingest",
        "task_default_exchange": "ingest",
        "task_default_routing_key": "ingest",
        "task_routes": {
            "csr.ingest_trip": {"queue": "ingest"},
            "csr.align_tile": {"queue": "align"},
            "csr.correct_tile": {"queue": "align"},
            "csr.merge_tile": {"queue": "merge"},
        },
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        "task_time_limit": settings.job_time_limit_s,
        "task_ignore_result": True,  # job state lives in the database
        "task_publish_retry_policy": {
            "max_retries": 2,
            "interval_start": 0,
            "interval_step": 0.2,
            "interval_max": 0.5,
        },
        "task_serializer": "json",
        "accept_content": ["json"],
        "worker_send_task_events": True,  # for Flower
        "task_send_sent_event": True,
        "worker_hijack_root_logger": False,
        # a late-ack task cannot be acknowledged over a lost connection: Redis re-delivers it when it
        # kept its data; when it did not, the job's lease runs out and the outbox relay sends it again
        "worker_cancel_long_running_tasks_on_connection_loss": True,
    }


def make_celery(settings: Settings) -> Celery:
    """A producer app for the API process (tasks are sent by name)."""
    app = Celery("csr")
    app.conf.update(celery_config(settings))
    return app


app = Celery("csr", include=["workers.tasks"])


@app.on_configure.connect
def _configure(sender: Celery, **_: Any) -> None:
    sender.conf.update(celery_config(get_settings()))


@dataclass(frozen=True)
class WorkerRuntime:
    settings: Settings
    session_factory: sessionmaker[Session]


_RUNTIMES: dict[int, WorkerRuntime] = {}


def runtime() -> WorkerRuntime:
    """Settings and database sessions of this process (a forked pool child gets its own engine)."""
    pid = os.getpid()
    if pid not in _RUNTIMES:
        settings = get_settings()
        _RUNTIMES[pid] = WorkerRuntime(settings, make_session_factory(make_engine(settings.sqlalchemy_url)))
    return _RUNTIMES[pid]


@signals.worker_process_init.connect
def _forget_inherited_connections(**_: Any) -> None:
    """In a new pool child: drop the parent's pooled connections without closing them (they are the parent's)."""
    for pid, rt in list(_RUNTIMES.items()):
        if pid != os.getpid():
            rt.session_factory.kw["bind"].dispose(close=False)
            del _RUNTIMES[pid]


_relay = None


@signals.worker_ready.connect
def _start_relay(**_: Any) -> None:
    global _relay
    from workers.outbox import OutboxRelay

    rt = runtime()
    _relay = OutboxRelay(rt.settings, rt.session_factory, app)
    _relay.start()
    log.info("outbox relay started in the worker")


@signals.worker_shutdown.connect
def _stop_relay(**_: Any) -> None:
    if _relay is not None:
        _relay.stop()
