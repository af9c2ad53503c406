"""``/healthz`` (no key) and ``/metrics`` (Prometheus text format; reader or admin key)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from services.api import answers
from services.api.deps import Ctx, Reader

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


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {
            "description": "The service's metrics in the Prometheus text format",
            "content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}},
        }
    },
)
def metrics(_: Reader, ctx: Ctx) -> Response:
    return Response(generate_latest(ctx.metrics.registry), media_type=CONTENT_TYPE_LATEST)
