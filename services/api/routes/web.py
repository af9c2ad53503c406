"""The map viewer at ``/viewer/`` and the ops page at ``/ops/``: static files from the committed
bundle in ``services/web/dist`` (built by ``npm ci && npm run build`` in ``services/web``; serving
needs no npm). The pages are public (they hold no data); they ask for an API key and send it as
Bearer on every API call.

Caching: the assets carry a content hash in their names (``viewer-4QGCRQXS.js``), so they are
``immutable`` for a year; the two HTML pages are ``no-cache`` (revalidated with their ETag), so a
new build is picked up at the next load.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from fastapi import APIRouter, Request, Response
from fastapi.responses import RedirectResponse

from services.api.errors import ApiError
from services.api.openapi import errors

router = APIRouter(tags=["web"])

# The two pages in the OpenAPI document (the redirects and the bundle's assets are not in it)
PAGE_ANSWERS: dict[int | str, dict] = {
    200: {"description": "The page", "content": {"text/html": {"schema": {"type": "string"}}}},
    304: {"description": "`If-None-Match` names the page's current ETag"},
    **errors({503: {"web_not_built": "the web bundle is missing (`npm ci && npm run build`)."}}),
}

DIST = Path(__file__).resolve().parents[2] / "web" / "dist"
PAGES = {"viewer": "index.html", "ops": "ops.html"}
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".svg": "image/svg+xml",
    ".png": "image/png",
}
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_HASHED = re.compile(r"-[A-Za-z0-9]{8}\.[a-z]+$")
IMMUTABLE = "public, max-age=31536000, immutable"

_cache: dict[str, tuple[tuple[int, int], bytes, str]] = {}  # name -> ((mtime_ns, size), body, etag)


def _read(name: str) -> tuple[bytes, str]:
    """A file of the bundle and its strong ETag (re-read when the file changes)."""
    path = DIST / name
    if not _SAFE_NAME.match(name) or path.suffix not in CONTENT_TYPES or not path.is_file():
        raise ApiError(404, "not_found", f"no file {name!r} in the web bundle")
    stat = path.stat()
    key = (stat.st_mtime_ns, stat.st_size)
    cached = _cache.get(name)
    if cached is None or cached[0] != key:
        body = path.read_bytes()
        cached = (key, body, '"' + hashlib.sha256(body).hexdigest()[:32] + '"')
        _cache[name] = cached
    return cached[1], cached[2]


def _serve(request: Request, name: str) -> Response:
    if not DIST.is_dir():
        raise ApiError(
            503, "web_not_built", "the web bundle is missing: run `npm ci && npm run build` in services/web"
        )
    body, etag = _read(name)
    headers = {
        "ETag": etag,
        "Cache-Control": IMMUTABLE if _HASHED.search(name) else "no-cache",
        "X-Content-Type-Options": "nosniff",
    }
    if etag in [t.strip() for t in request.headers.get("if-none-match", "").split(",")]:
        return Response(status_code=304, headers=headers)
    return Response(body, media_type=CONTENT_TYPES[Path(name).suffix], headers=headers)


@router.get("/viewer", include_in_schema=False)
@router.get("/ops", include_in_schema=False)
def page_without_slash(request: Request) -> RedirectResponse:
    return RedirectResponse(request.url.path + "/", status_code=308)


@router.get("/viewer/", response_class=Response, responses=PAGE_ANSWERS)
def viewer_page(request: Request) -> Response:
    return _serve(request, PAGES["viewer"])


@router.get("/ops/", response_class=Response, responses=PAGE_ANSWERS)
def ops_page(request: Request) -> Response:
    return _serve(request, PAGES["ops"])


@router.get("/viewer/{name}", include_in_schema=False)
@router.get("/ops/{name}", include_in_schema=False)
def asset(request: Request, name: str) -> Response:
    return _serve(request, name)
