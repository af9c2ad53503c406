"""Content codings of responses (RFC 9110 8.4, 12.5.3): which one an ``Accept-Encoding`` asks
for, the compressors, and the entity tags of the encoded representations.

- **Negotiation.** The codings on offer are ``br``, ``zstd`` and ``gzip`` (``x-gzip`` is read as
  ``gzip``). Each one's weight is its own ``q``, else that of ``*``, else 0 (not listed: not
  acceptable). ``identity`` (no coding) is acceptable unless ``identity;q=0``, or ``*;q=0``
  without an ``identity`` entry, says otherwise; an explicit ``identity;q=`` competes with the
  codings by weight, an implicit one is only the fallback. Highest weight wins; on a tie the
  order above (the smallest output first). No header: identity. Nothing acceptable at all: 406.
- **Entity tags.** An encoded representation has its own strong tag: the identity tag with a
  suffix inside the quotes (``"abc"`` -> ``"abc-br"``), as Apache's ``mod_deflate`` does.
  :func:`identity_if_none_match` maps a request's ``If-None-Match`` back to identity tags, so the
  routes (and the tile fast path) compare their own tags unchanged and answer 304 per encoding.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from enum import Enum

import brotli
import zstandard


class Coding(str, Enum):
    BR = "br"
    ZSTD = "zstd"
    GZIP = "gzip"
    IDENTITY = "identity"


# Server preference on equal weights: the smallest output first (`csr bench-http`: br < zstd < gzip).
OFFERED = (Coding.BR, Coding.ZSTD, Coding.GZIP)
# Levels for bodies compressed per request (encoded tiles are cached by ETag and coding); sizes and
# times per body in BENCHMARKS.md (`csr bench-http`): a 370 KB GeoJSON takes 20-60 ms at these.
BROTLI_QUALITY = 5
ZSTD_LEVEL = 6
GZIP_LEVEL = 6
_ALIASES = {"x-gzip": "gzip"}


@dataclass(frozen=True, slots=True)
class Negotiated:
    """The coding to send, and whether identity may be sent instead (e.g. for a small body)."""

    coding: Coding
    identity_acceptable: bool


def _weights(accept_encoding: str) -> dict[str, float]:
    """``{coding: q}`` of an ``Accept-Encoding`` value; malformed entries are ignored."""
    weights: dict[str, float] = {}
    for item in accept_encoding.split(","):
        name, *params = (part.strip() for part in item.split(";"))
        name = _ALIASES.get(name.lower(), name.lower())
        if not name:
            continue
        q = 1.0
        for param in params:
            key, _, value = param.partition("=")
            if key.strip().lower() == "q":
                try:
                    q = float(value.strip())
                except ValueError:
                    q = -1.0
        if 0.0 <= q <= 1.0:
            weights[name] = max(q, weights.get(name, 0.0))
    return weights


def negotiate(accept_encoding: str | None) -> Negotiated | None:
    """The coding for a request's ``Accept-Encoding`` (``None``: the header's absence), or ``None``
    when no coding on offer and not identity either is acceptable (answer 406)."""
    if accept_encoding is None:
        return Negotiated(Coding.IDENTITY, True)
    weights = _weights(accept_encoding)
    star = weights.get("*")
    identity_q = weights.get("identity", star if star is not None else 1.0)
    best, best_q = Coding.IDENTITY, 0.0
    for coding in OFFERED:
        q = weights.get(coding.value, star if star is not None else 0.0)
        if q > best_q:
            best, best_q = coding, q
    if "identity" in weights and identity_q > best_q:
        best = Coding.IDENTITY
    if best is Coding.IDENTITY and identity_q <= 0.0:
        return None
    return Negotiated(best, identity_q > 0.0)


def compress(body: bytes, coding: Coding) -> bytes:
    """``body`` in ``coding`` (deterministic: the same bytes give the same output, no timestamps)."""
    if coding is Coding.BR:
        return brotli.compress(body, quality=BROTLI_QUALITY)
    if coding is Coding.ZSTD:
        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(body)
    if coding is Coding.GZIP:
        packer = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, 31)  # wbits 31: gzip header, mtime 0
        return packer.compress(body) + packer.flush()
    return body


def encoded_etag(etag: str, coding: Coding) -> str:
    """The tag of ``coding``'s representation: ``"abc"`` -> ``"abc-br"`` (``W/`` kept)."""
    if coding is Coding.IDENTITY or not etag.endswith('"'):
        return etag
    return f'{etag[:-1]}-{coding.value}"'


def identity_if_none_match(if_none_match: str, coding: Coding, *, identity_acceptable: bool) -> str | None:
    """``If-None-Match`` with ``coding``'s tags turned back into identity tags (``None``: no tag
    left). Tags of other codings stay as they are (they match nothing); identity tags stay unless
    identity is not acceptable (then the client's identity copy is no answer to the request)."""
    if if_none_match.strip() == "*" or coding is Coding.IDENTITY:
        return if_none_match
    suffix = f'-{coding.value}"'
    others = tuple(f'-{c.value}"' for c in OFFERED if c is not coding)
    tags = []
    for tag in (t.strip() for t in if_none_match.split(",")):
        if tag.endswith(suffix):
            tags.append(tag[: -len(suffix)] + '"')
        elif tag.endswith(others) or identity_acceptable:
            tags.append(tag)
    return ", ".join(tags) if tags else None


def requested_encoded(if_none_match: str, etag: str, coding: Coding) -> bool:
    """Whether the request's ``If-None-Match`` lists ``etag``'s ``coding`` representation (a 304
    then names that one; otherwise the identity copy the client holds)."""
    if coding is Coding.IDENTITY:
        return False
    wanted = encoded_etag(etag, coding).removeprefix("W/")
    return any(t.strip().removeprefix("W/") == wanted for t in if_none_match.split(","))
