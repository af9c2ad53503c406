"""``Annotated`` dependencies: the app context, a database session, the authenticated caller by role."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Header, Request
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from services.api.metrics import Metrics
from services.auth import Caller, authenticate, authorize
from services.settings import Settings


@dataclass
class AppContext:
    settings: Settings
    engine: Engine
    session_factory: sessionmaker[Session]
    read_session_factory: sessionmaker[Session]  # sessions that only read (services.db.engine.read_only)
    metrics: Metrics
    runner: Any  # EmbeddedRunner | OutboxRelay: woken after new jobs are committed
    celery: Any | None = None


def get_ctx(request: Request) -> AppContext:
    return request.app.state.ctx


Ctx = Annotated[AppContext, Depends(get_ctx)]


def get_session(ctx: Ctx) -> Iterator[Session]:
    """A session that may write: for the calls that change something."""
    with ctx.session_factory() as session:
        yield session


def get_read_session(ctx: Ctx) -> Iterator[Session]:
    """A session that only reads: it never waits for a writer (on SQLite it takes no write lock)."""
    with ctx.read_session_factory() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]
ReadSessionDep = Annotated[Session, Depends(get_read_session)]


def require(*roles: str) -> Callable[..., Caller]:
    """The caller, authenticated by its bearer key, if its role is one of ``roles`` (else 401/403).
    The dependency carries ``roles`` for the OpenAPI document (services.api.openapi); the header is
    described there by the bearer security scheme, not as a parameter."""

    def dependency(
        ctx: Ctx, authorization: Annotated[str | None, Header(include_in_schema=False)] = None
    ) -> Caller:
        return authorize(authenticate(ctx.read_session_factory, authorization), roles)

    dependency.roles = roles  # type: ignore[attr-defined]
    return dependency


Admin = Annotated[Caller, Depends(require("admin"))]
Reader = Annotated[Caller, Depends(require("reader", "admin"))]
Uploader = Annotated[Caller, Depends(require("vehicle", "admin"))]
AnyRole = Annotated[Caller, Depends(require("vehicle", "reader", "admin"))]
