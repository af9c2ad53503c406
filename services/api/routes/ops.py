"""``/healthz`` (no key) and ``/metrics`` (Prometheus text format; reader or admin key)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from services.api.deps import Ctx, Reader

router = APIRouter(tags=["ops"])


@router.get("/healthz")
def healthz(ctx: Ctx) -> JSONResponse:
    try:
        with ctx.read_session_factory() as session:
            session.execute(text("SELECT 1"))
    except Exception as exc:
        return JSONResponse({"status": "error", "database": str(exc)}, status_code=503)
    deployment = "embedded" if ctx.settings.embedded_jobs else "distributed"
    return JSONResponse({"status": "ok", "database": ctx.engine.dialect.name, "jobs": deployment})


@router.get("/metrics")
def metrics(_: Reader, ctx: Ctx) -> Response:
    return Response(generate_latest(ctx.metrics.registry), media_type=CONTENT_TYPE_LATEST)
