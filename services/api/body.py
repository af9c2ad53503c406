"""Reading an upload body within limits: while streaming (as sent) and while decompressing gzip
(after decompression), so that neither a large body nor a zip bomb can use more memory than the
configured limits."""

from __future__ import annotations

import zlib
from collections.abc import AsyncIterator

from services.api.errors import ApiError

GZIP_MAGIC = b"\x1f\x8b"


def too_large(what: str, limit: int) -> ApiError:
    return ApiError(413, "too_large", f"the body {what} exceeds the limit of {limit} bytes")


async def read_limited(chunks: AsyncIterator[bytes], *, max_bytes: int) -> bytearray:
    """Collect a streamed body; 413 as soon as it passes ``max_bytes``."""
    body = bytearray()
    async for chunk in chunks:
        body += chunk
        if len(body) > max_bytes:
            raise too_large("as sent", max_bytes)
    return body


def gunzip_limited(data: bytes | bytearray, *, max_bytes: int) -> bytearray:
    """Decompress a (possibly multi-member) gzip body, never producing more than ``max_bytes + 1``
    bytes: 413 past the limit, 400 for a malformed or truncated stream."""
    out = bytearray()
    rest: bytes | bytearray = data
    while True:
        inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
        try:
            out += inflater.decompress(rest, max_bytes + 1 - len(out))
            while inflater.unconsumed_tail and len(out) <= max_bytes:
                out += inflater.decompress(inflater.unconsumed_tail, max_bytes + 1 - len(out))
        except zlib.error as exc:
            raise ApiError(400, "gzip", f"malformed gzip body: {exc}") from None
        if len(out) > max_bytes:
            raise too_large("after decompression", max_bytes)
        if not inflater.eof:
            raise ApiError(400, "gzip", "malformed gzip body: the stream is truncated")
        rest = inflater.unused_data
        if not rest:
            return out
