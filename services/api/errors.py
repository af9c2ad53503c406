"""One error shape for every 4xx/5xx: ``{"error": code, "location": where, "message": what}``."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from csr_core.errors import UploadError

# The status of each upload rejection reason (README "Errors").
UPLOAD_ERROR_STATUS = {"json": 400, "schema": 422, "non_finite": 422, "time_order": 422, "version": 422}


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


def _json(error: ApiError) -> JSONResponse:
    return JSONResponse(error.as_dict(), status_code=error.status, headers=error.headers)


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError) -> JSONResponse:
        return _json(exc)

    @app.exception_handler(UploadError)
    async def _upload_error(_: Request, exc: UploadError) -> JSONResponse:
        return _json(as_api_error(exc))

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        return _json(ApiError(exc.status_code, code, str(exc.detail), headers=getattr(exc, "headers", None)))

    @app.exception_handler(RequestValidationError)
    async def _request_invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
        location = ".".join(str(p) for p in first.get("loc", ()))
        return _json(ApiError(422, "invalid_request", f"{location}: {first.get('msg')}", location=location))
