"""ASGI middleware in front of every route (the tile fast path included): compressed answers by
``Accept-Encoding`` (``services.api.content_coding``) and ``HEAD`` on every ``GET`` route.

``ContentEncoding`` acts on ``GET`` answers only (``HEAD`` arrives here as ``GET``):

- a ``200`` of a compressible media type without a ``Content-Encoding`` of its own is sent in the
  negotiated coding, with ``Content-Encoding``, its ``Content-Length`` and the coding's ETag, unless
  it is under :data:`MIN_COMPRESS_BYTES` or the coding would not make it smaller (then identity,
  with the identity ETag; both only while identity is acceptable);
- ``If-None-Match`` reaches the routes with identity tags, and a ``304`` names the representation
  the client listed (the coding's or the identity one);
- every answer carries ``Vary: Accept-Encoding``; a request that accepts neither a coding on offer
  nor identity gets 406.

Encoded bodies with a strong ETag (tiles, the web bundle) are kept in an LRU by (ETag, coding),
so a tile is compressed once per coding, not per request.

``HeadAsGet`` answers ``HEAD`` as the ``GET`` would, headers only (``Content-Length`` of the coding
chosen): FastAPI's routes declare ``GET`` alone and would otherwise answer ``HEAD`` with 405.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, MutableMapping
from functools import lru_cache
from typing import Any

import anyio.to_thread

from services.api.content_coding import (
    Coding,
    Negotiated,
    compress,
    encoded_etag,
    identity_if_none_match,
    negotiate,
    requested_encoded,
)
from services.api.errors import ApiError, error_response
from services.tiles.render import TileCache

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

# Below this a body goes as it is: a coding's framing would eat most of the gain.
MIN_COMPRESS_BYTES = 1024
# Bodies from this size on are compressed on a worker thread (a 400 KB GeoJSON takes 20-60 ms).
THREAD_COMPRESS_BYTES = 64 * 1024
# Encoded bodies kept by (strong ETag, coding).
ENCODED_CACHE_BYTES = 32 * 1024 * 1024
ENCODED_CACHE_ENTRIES = 20_000
COMPRESSIBLE = frozenset(
    {
        "application/geo+json",
        "application/json",
        "application/javascript",
        "application/vnd.mapbox-vector-tile",
        "application/x-protobuf",
        "application/xml",
        "image/svg+xml",
    }
)

negotiate_cached = lru_cache(maxsize=256)(negotiate)


def compressible(content_type: str | None) -> bool:
    if not content_type:
        return False
    media = content_type.split(";", 1)[0].strip().lower()
    return media in COMPRESSIBLE or media.startswith("text/")


class ContentEncoding:
    """Negotiated ``gzip`` / ``br`` / ``zstd`` for ``GET`` answers, ETags per coding."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.encoded = TileCache(max_bytes=ENCODED_CACHE_BYTES, max_entries=ENCODED_CACHE_ENTRIES)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "GET":
            await self.app(scope, receive, send)
            return
        accept: list[str] = []
        if_none_match: str | None = None
        for name, value in scope["headers"]:
            if name == b"accept-encoding":
                accept.append(value.decode("latin-1"))
            elif name == b"if-none-match" and if_none_match is None:
                if_none_match = value.decode("latin-1")
        negotiated = negotiate_cached(", ".join(accept) if accept else None)
        if negotiated is None:
            error = ApiError(
                406,
                "not_acceptable",
                "Accept-Encoding: accepts none of br, zstd, gzip and not identity either",
                location="header.accept-encoding",
                headers={"Vary": "Accept-Encoding"},
            )
            await error_response(error)(scope, receive, send)
            return
        if if_none_match is not None and negotiated.coding is not Coding.IDENTITY:
            rewritten = identity_if_none_match(
                if_none_match, negotiated.coding, identity_acceptable=negotiated.identity_acceptable
            )
            headers = [(n, v) for n, v in scope["headers"] if n != b"if-none-match"]
            if rewritten is not None:
                headers.append((b"if-none-match", rewritten.encode("latin-1")))
            scope = {**scope, "headers": headers}
        responder = _Responder(send, negotiated, if_none_match, self.encoded)
        await self.app(scope, receive, responder.send)


class _Responder:
    """The ``send`` of one request: passes messages on, holding a compressible 200 until its end."""

    def __init__(
        self, send: Send, negotiated: Negotiated, if_none_match: str | None, encoded: TileCache
    ) -> None:
        self._send, self._negotiated, self._if_none_match = send, negotiated, if_none_match
        self._encoded = encoded
        self._start: Message | None = None
        self._headers: _RawHeaders | None = None
        self._chunks: list[bytes] = []

    async def send(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            await self._on_start(message)
        elif message["type"] == "http.response.body" and self._start is not None:
            self._chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                chunks = self._chunks
                await self._send_held(chunks[0] if len(chunks) == 1 else b"".join(chunks))
        else:
            await self._send(message)

    async def _on_start(self, message: Message) -> None:
        headers = _RawHeaders(message["headers"])
        headers.add_vary()
        message = {**message, "headers": headers.raw}
        coding = self._negotiated.coding
        status = message["status"]
        etag = headers.get(b"etag")
        if status == 304 and etag and self._if_none_match:
            if requested_encoded(self._if_none_match, etag, coding):
                headers.set(b"etag", encoded_etag(etag, coding))
        elif (
            status == 200
            and coding is not Coding.IDENTITY
            and headers.get(b"content-encoding") is None
            and compressible(headers.get(b"content-type"))
        ):
            self._start, self._headers = message, headers
            return
        await self._send(message)

    async def _send_held(self, body: bytes) -> None:
        assert self._start is not None and self._headers is not None
        headers = self._headers
        coding, identity_ok = self._negotiated.coding, self._negotiated.identity_acceptable
        etag = headers.get(b"etag")
        encoded: bytes | None = None
        if not (identity_ok and len(body) < MIN_COMPRESS_BYTES):
            encoded = await self._encode(body, etag, coding, identity_ok)
        if encoded is not None:
            if etag:
                headers.set(b"etag", encoded_etag(etag, coding))
            headers.set(b"content-encoding", coding.value)
            body = encoded
        headers.set(b"content-length", str(len(body)))
        await self._send(self._start)
        await self._send({"type": "http.response.body", "body": body})

    async def _encode(self, body: bytes, etag: str | None, coding: Coding, identity_ok: bool) -> bytes | None:
        """``body`` in ``coding``; ``None`` when identity is acceptable and no smaller."""
        key = f"{etag}|{coding.value}" if etag and not etag.startswith("W/") else None
        hit, encoded = self._encoded.get(key) if key is not None else (False, None)
        if not hit or encoded is None:
            if len(body) >= THREAD_COMPRESS_BYTES:  # tens of ms: off the event loop
                encoded = await anyio.to_thread.run_sync(compress, body, coding)
            else:
                encoded = compress(body, coding)
            if key is not None:
                self._encoded.put(key, encoded)
        if identity_ok and len(encoded) >= len(body):
            return None
        return encoded


class _RawHeaders:
    """An ASGI header list read and changed in place (lower-case names; Starlette's
    ``MutableHeaders`` costs ~40 us per answer here, this a few)."""

    def __init__(self, raw: list[tuple[bytes, bytes]]) -> None:
        self.raw = list(raw)

    def get(self, name: bytes) -> str | None:
        for key, value in self.raw:
            if key == name:
                return value.decode("latin-1")
        return None

    def set(self, name: bytes, value: str) -> None:
        encoded = value.encode("latin-1")
        for i, (key, _) in enumerate(self.raw):
            if key == name:
                self.raw[i] = (name, encoded)
                return
        self.raw.append((name, encoded))

    def add_vary(self) -> None:
        vary = self.get(b"vary")
        if vary is None:
            self.raw.append((b"vary", b"Accept-Encoding"))
        elif "accept-encoding" not in vary.lower():
            self.set(b"vary", f"{vary}, Accept-Encoding")


class HeadAsGet:
    """``HEAD`` answered as ``GET`` without the body (every header kept, ``Content-Length`` too)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def headers_only(message: Message) -> None:
            if message["type"] == "http.response.body":
                if message.get("more_body", False):
                    return
                message = {"type": "http.response.body", "body": b""}
            await send(message)

        await self.app({**scope, "method": "GET"}, receive, headers_only)
