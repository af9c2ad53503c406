"""CORS headers. Keys travel as ``Authorization: Bearer`` (never cookies), so every origin may read
the map and the error answers: ``Access-Control-Allow-Origin: *`` on map answers and on every error
(a browser then shows the error body, e.g. a bad key, instead of an opaque network error)."""

from __future__ import annotations

CORS_HEADERS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Expose-Headers": "ETag, X-Map-Version, Retry-After, Link",
}
PREFLIGHT_HEADERS = {
    **CORS_HEADERS,
    "Access-Control-Allow-Methods": "GET, HEAD, OPTIONS",
    "Access-Control-Allow-Headers": "Authorization, If-None-Match",
    "Access-Control-Max-Age": "86400",
}
