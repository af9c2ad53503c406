"""``/healthz`` (no key) and ``/metrics`` (Prometheus text format; a reader or admin key, or the
metrics key of ``CSR_METRICS_KEY_FILE``)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from services.api import answers
from services.api.deps import Ctx
from services.auth import authenticate, authorize

router = APIRouter(tags=["ops"])


@router.get(
    "/healthz",
    response_class=JSONResponse,
    responses={
        200: answers.answer(
            answers.Health, "The service answers (`status`: ok, or degraded without the broker)"
        ),
        503: answers.answer(answers.Health, "The database is unreachable (`status`: error)"),
    },
)
def healthz(ctx: Ctx) -> JSONResponse:
    """200 ``{"status", "database", "jobs"}``; 503 when the database is unreachable. The distributed
    deployment adds ``"broker": "ok" | "unreachable"``: without it the status is ``degraded``, still
    200, since uploads are accepted and their jobs wait in the outbox until the broker is back."""
    try:
        with ctx.read_session_factory() as session:
            session.execute(text("SELECT 1"))
    except Exception as exc:
        return JSONResponse({"status": "error", "database": str(exc)}, status_code=503)
    if ctx.settings.embedded_jobs:
        return JSONResponse({"status": "ok", "database": ctx.engine.dialect.name, "jobs": "embedded"})
    broker = "ok" if ctx.runner.broker_reachable() else "unreachable"
    return JSONResponse(
        {
            "status": "ok" if broker == "ok" else "degraded",
            "database": ctx.engine.dialect.name,
            "jobs": "distributed",
            "broker": broker,
        }
    )


def _scraper(ctx: Ctx, authorization: Annotated[str | None, Header(include_in_schema=False)] = None) -> None:
    """The metrics key (compared in constant time), else a reader or admin key as everywhere."""
    key = ctx.metrics.scrape_key
    if key is not None and authorization is not None:
        scheme, _, secret = authorization.partition(" ")
        if scheme.lower() == "bearer" and hmac.compare_digest(secret.strip().encode(), key.encode()):
            return
    authorize(authenticate(ctx.read_session_factory, authorization), ("reader", "admin"))


_scraper.roles = ("reader", "admin")  # type: ignore[attr-defined]  # the OpenAPI document (the metrics key: operations.md)


@router.get(
    "/metrics",
    dependencies=[Depends(_scraper)],
    response_class=Response,
    responses={
        200: {
            "description": "The service's metrics in the Prometheus text format",
            "content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}},
        }
    },
)
def metrics(ctx: Ctx) -> Response:
    return Response(generate_latest(ctx.metrics.registry), media_type=CONTENT_TYPE_LATEST)
