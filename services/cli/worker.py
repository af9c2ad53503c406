"""`csr worker`: a Celery worker of the distributed deployment (contract section 4), consuming
the ingest, align and merge queues. Needs CSR_DATABASE_URL and CSR_REDIS_URL; migrates at start."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="start a Celery worker (distributed deployment)")
    p.add_argument("--queues", default="ingest,align,merge", help="queues to consume (default: all)")
    p.add_argument(
        "--concurrency", type=int, default=None, help="processes (default CSR_WORKER_CONCURRENCY, 1)"
    )
    p.add_argument("--name", default="csr@%h", help="worker node name")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from services.db.engine import make_engine, migrate
    from services.settings import get_settings
    from workers.celery_app import app

    settings = get_settings()
    if not settings.redis_url or not settings.database_url:
        raise SystemExit(
            "csr worker needs CSR_DATABASE_URL and CSR_REDIS_URL (the embedded default runs jobs in `csr serve`)"
        )
    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine)
    engine.dispose()
    concurrency = args.concurrency or settings.worker_concurrency
    app.worker_main(
        [
            "worker",
            "--queues",
            args.queues,
            "--concurrency",
            str(concurrency),
            "--hostname",
            args.name,
            "--loglevel",
            "INFO",
            "--without-gossip",
            "--without-mingle",
        ]
    )
    return 0
