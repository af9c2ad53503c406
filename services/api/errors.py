"""One error shape for every 4xx/5xx: ``{"error": code, "location": where, "message": what}``,
sent with the CORS headers so that a browser on another origin can read it."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import iter_route_contexts
from sqlalchemy.exc import DBAPIError, DisconnectionError, InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

from csr_core.errors import UploadError
from services.api.cors import CORS_HEADERS

# The status of each upload rejection reason (README "Errors").
UPLOAD_ERROR_STATUS = {
    "json": 400,
    "schema": 422,
    "non_finite": 422,
    "time_order": 422,
    "version": 422,
    "too_many_frames": 413,
}
UPLOAD_ERROR_STATUS |= {"cbor": 400, "binary": 422}  # the compact binary upload (docs/upload-binary.md)
# Retry-After of a 503: a database busy or unreachable beyond the service's own waiting
DATABASE_RETRY_AFTER_S = 5
# SQLite's messages for a lock still taken when its busy timeout ran out
_SQLITE_BUSY = ("database is locked", "database table is locked", "database is busy")
# A database that is busy, unreachable or lost its connection: 503, never 500
DATABASE_ERRORS: tuple[type[Exception], ...] = (
    OperationalError,
    InterfaceError,
    DisconnectionError,
    PoolTimeoutError,
)


class ApiError(Exception):
    def __init__(
        self, status: int, error: str, message: str, *, location: str = "", headers: dict | None = None
    ):
        super().__init__(message)
        self.status, self.error, self.message, self.location = status, error, message, location
        self.headers = headers

    def as_dict(self) -> dict[str, str]:
        return {"error": self.error, "location": self.location, "message": self.message}


def as_api_error(exc: UploadError | ApiError) -> ApiError:
    if isinstance(exc, ApiError):
        return exc
    return ApiError(UPLOAD_ERROR_STATUS.get(exc.reason, 422), exc.reason, exc.message, location=exc.location)


def database_error(exc: Exception) -> ApiError:
    """503 for a database that did not answer in time: SQLite's write lock still taken after its
    busy timeout (the service's bounded wait and retry), or a database that cannot be reached."""
    orig = exc.orig if isinstance(exc, DBAPIError) else None
    detail = str(orig) if orig is not None else str(exc)
    busy = any(m in detail for m in _SQLITE_BUSY)
    return ApiError(
        503,
        "database_busy" if busy else "database_unavailable",
        ("the database is busy with a long write; retry later" if busy else "the database is unavailable")
        + f" ({detail.splitlines()[0] if detail else type(exc).__name__})",
        location="database",
        headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)},
    )


def allowed_methods(request: Request) -> list[str]:
    """The methods of every route at the request's path (Starlette's own 405 names only the first
    route's, when two routes share a path: ``GET`` and ``POST /v1/trips``)."""
    path = request.scope["path"]
    methods: set[str] = set()
    for route in iter_route_contexts(request.app.routes):
        regex = getattr(route, "path_regex", None)
        if regex is not None and regex.match(path):
            methods |= set(route.methods or ())
    return sorted(methods)


def error_response(error: ApiError) -> JSONResponse:
    return JSONResponse(
        error.as_dict(), status_code=error.status, headers={**CORS_HEADERS, **(error.headers or {})}
    )


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError) -> JSONResponse:
        return error_response(exc)

    @app.exception_handler(UploadError)
    async def _upload_error(_: Request, exc: UploadError) -> JSONResponse:
        return error_response(as_api_error(exc))

    async def _database_error(_: Request, exc: Exception) -> JSONResponse:
        return error_response(database_error(exc))

    for error_type in DATABASE_ERRORS:
        app.add_exception_handler(error_type, _database_error)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 400:
            # FastAPI's only 400: a JSON body it could not read as text (not UTF-8)
            return error_response(
                ApiError(400, "json", f"body: not JSON text ({exc.detail})", location="body")
            )
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:
            headers = {**(headers or {}), "Allow": ", ".join(allowed_methods(request))}
        return error_response(ApiError(exc.status_code, code, str(exc.detail), headers=headers))

    @app.exception_handler(Exception)
    async def _internal_error(_: Request, exc: Exception) -> JSONResponse:
        # Starlette's outermost middleware calls this for any unhandled exception (and logs it)
        return error_response(
            ApiError(500, "internal", f"internal server error ({type(exc).__name__})", location="server")
        )

    @app.exception_handler(RequestValidationError)
    async def _request_invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
        location = ".".join(str(p) for p in first.get("loc", ()))
        return error_response(
            ApiError(422, "invalid_request", f"{location}: {first.get('msg')}", location=location)
        )
