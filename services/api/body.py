"""Reading an upload body within limits: while streaming (as sent) and while decompressing gzip
(after decompression), so that neither a large body nor a zip bomb can use more memory than the
configured limits. Inflation runs in bounded steps (:data:`INPUT_STEP_BYTES` of input,
:data:`OUTPUT_STEP_BYTES` of output at a time): it stops at the limit without producing more, and
each step's output is reserved first (``reserve``: the process's budget of upload bytes in
flight, :mod:`services.upload_budget`)."""

from __future__ import annotations

import zlib
from collections.abc import AsyncIterator, Callable

from services.api.errors import ApiError

GZIP_MAGIC = b"\x1f\x8b"
INPUT_STEP_BYTES = 64 * 1024  # compressed bytes handed to zlib at once
OUTPUT_STEP_BYTES = 1024 * 1024  # decompressed bytes zlib may produce in one step


def too_large(what: str, limit: int) -> ApiError:
    return ApiError(413, "too_large", f"the body {what} exceeds the limit of {limit} bytes")


def _malformed(detail: str) -> ApiError:
    return ApiError(400, "gzip", f"malformed gzip body: {detail}")


async def read_limited(chunks: AsyncIterator[bytes], *, max_bytes: int) -> bytearray:
    """Collect a streamed body; 413 as soon as it passes ``max_bytes``."""
    body = bytearray()
    async for chunk in chunks:
        body += chunk
        if len(body) > max_bytes:
            raise too_large("as sent", max_bytes)
    return body


def gunzip_limited(
    data: bytes | bytearray, *, max_bytes: int, reserve: Callable[[int], None] | None = None
) -> bytearray:
    """Decompress a (possibly multi-member) gzip body, never producing more than ``max_bytes + 1``
    bytes: 413 past the limit, 400 for a malformed or truncated stream. ``reserve(n)`` is called
    before ``n`` more decompressed bytes are kept (it raises to stop)."""
    out = bytearray()
    try:
        _inflate_into(out, memoryview(data), max_bytes=max_bytes, reserve=reserve)
    except BaseException:
        out.clear()  # frees the output now: the traceback keeps this frame alive for a while
        raise
    return out


def _inflate_into(
    out: bytearray, view: memoryview, *, max_bytes: int, reserve: Callable[[int], None] | None
) -> None:
    inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
    pending: bytes = b""  # input not yet consumed by zlib
    position = 0  # of the next input step in ``view``
    while pending or position < len(view):
        if not pending:
            pending = bytes(view[position : position + INPUT_STEP_BYTES])
            position += INPUT_STEP_BYTES
        if inflater.eof:  # one member ended: the next begins in the pending input
            inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
        try:
            chunk = inflater.decompress(pending, min(OUTPUT_STEP_BYTES, max_bytes + 1 - len(out)))
        except zlib.error as exc:
            raise _malformed(str(exc)) from None
        pending = inflater.unconsumed_tail or (inflater.unused_data if inflater.eof else b"")
        if len(out) + len(chunk) > max_bytes:
            raise too_large("after decompression", max_bytes)
        if reserve is not None:
            reserve(len(chunk))
        out += chunk
    if not inflater.eof:
        raise _malformed("the stream is truncated")
