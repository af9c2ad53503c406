"""The app factory: ``create_app(settings)``. At start: migrations, the bootstrap admin key, and
the job runner of the deployment (in-process pool, or the outbox relay to Celery)."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from fastapi import Depends, FastAPI

from services.api.deps import AppContext
from services.api.errors import install_error_handlers
from services.api.http_middleware import ContentEncoding, HeadAsGet
from services.api.metrics import HttpMetrics, Metrics
from services.api.openapi import install_openapi
from services.api.params import check_request_params
from services.api.routes import (
    corrections,
    export,
    held_back,
    jobs,
    keys,
    map_read,
    ops,
    ops_jobs,
    tiles,
    trip_geometry,
    trips,
    vehicles,
    versions,
    web,
)
from services.db import repo
from services.db.engine import make_engine, make_session_factory, migrate, read_only
from services.settings import Settings
from services.tiles.fastpath import TileFastPath

if TYPE_CHECKING:
    from workers.embedded import EmbeddedRunner
    from workers.outbox import OutboxRelay

log = logging.getLogger(__name__)


def start_context(settings: Settings) -> AppContext:
    """Connect, migrate, install the admin key, start the job runner."""
    if not settings.database_url:
        settings.ensure_data_dir()
    engine = make_engine(settings.sqlalchemy_url, busy_timeout_s=settings.sqlite_busy_timeout_s)
    migrate(engine)
    session_factory = make_session_factory(engine)
    with session_factory.begin() as session:
        repo.ensure_bootstrap_admin(session, secret=settings.admin_secret())
    celery = None
    runner: EmbeddedRunner | OutboxRelay
    if settings.embedded_jobs:
        from workers.embedded import EmbeddedRunner

        runner = EmbeddedRunner(settings, session_factory)
    else:
        from workers.celery_app import make_celery
        from workers.outbox import OutboxRelay

        celery = make_celery(settings)
        runner = OutboxRelay(settings, session_factory, celery)
    runner.start()
    log.info(
        "CSR API ready: database %s, jobs %s",
        engine.dialect.name,
        "in-process" if settings.embedded_jobs else "Celery on Redis",
    )
    reads = read_only(session_factory)
    metrics = Metrics(reads, scrape_key=settings.metrics_secret())
    return AppContext(settings, engine, session_factory, reads, metrics, runner, celery)


def stop_context(ctx: AppContext) -> None:
    ctx.runner.stop()
    ctx.engine.dispose()


def create_app(settings: Settings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.ctx = start_context(settings)
        try:
            yield
        finally:
            stop_context(app.state.ctx)

    # every route's path and query parameters pass one check first (services.api.params)
    app = FastAPI(
        title="CSR",
        version="0.1.0",
        description="Crowdsourced road structure: trip uploads in, a versioned tiled vector map out.",
        lifespan=lifespan,
        dependencies=[Depends(check_request_params)],
        servers=[{"url": "/", "description": "this service"}],
        license_info={"name": "Apache-2.0", "identifier": "Apache-2.0"},
    )
    install_error_handlers(app)
    install_openapi(app)
    for module in (
        ops,
        trips,
        keys,
        jobs,
        map_read,
        tiles,
        versions,
        corrections,
        export,
        web,
        ops_jobs,
        trip_geometry,
        held_back,
        vehicles,
    ):
        app.include_router(module.router)
    # Tile GETs answered from in-process caches before FastAPI's routing (docs/tiles.md)
    app.add_middleware(TileFastPath, fastapi_app=app)
    # around it: negotiated compression with ETags per coding, and HEAD on every GET route
    app.add_middleware(ContentEncoding)
    app.add_middleware(HeadAsGet)
    # outermost: every request counted and timed by route template, the fast path's included
    app.add_middleware(HttpMetrics, fastapi_app=app)
    return app
