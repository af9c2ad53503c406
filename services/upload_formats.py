"""The upload's media types (``Content-Type`` of ``POST /v1/trips``) and how each is decoded,
as received and as stored for reprocessing.

- ``application/json``: the contract's JSON (``csr_core.upload``), stored gzip-compressed
  (``trip_uploads.encoding = "gzip"``);
- ``application/vnd.csr.trip+cbor``: the compact binary (``csr_core.upload_binary``,
  ``docs/upload-binary.md``), stored as received, gzip-compressed (``"cbor+gzip"``).
"""

from __future__ import annotations

import gzip
from enum import Enum
from typing import Any

import orjson

from csr_core import upload_binary
from csr_core.types import Trip
from csr_core.upload import decode_trip
from csr_core.upload_frames import decode_upload_json


class UploadType(str, Enum):
    JSON = "application/json"
    CBOR = upload_binary.MEDIA_TYPE

    @property
    def stored_encoding(self) -> str:
        """``trip_uploads.encoding`` of an upload of this type."""
        return "gzip" if self is UploadType.JSON else "cbor+gzip"


def upload_type(content_type: str) -> UploadType | None:
    """The upload type a ``Content-Type`` header names (parameters and case ignored), or ``None``."""
    media_type = content_type.split(";")[0].strip().lower()
    return next((t for t in UploadType if t.value == media_type), None)


def stored_document(encoding: str, body: bytes) -> dict[str, Any]:
    """The upload document of a stored raw upload (``trip_uploads.encoding``, ``.body``)."""
    raw = gzip.decompress(body)
    if encoding == UploadType.CBOR.stored_encoding:
        return upload_binary.decode(raw)
    return orjson.loads(raw)


def stored_trip(encoding: str, body: bytes) -> Trip:
    """The trip of a stored raw upload; a JSON one is decoded frame batch by frame batch
    (``csr_core.upload_frames``), never held whole as a parsed tree."""
    raw = gzip.decompress(body)
    if encoding == UploadType.CBOR.stored_encoding:
        return decode_trip(upload_binary.decode(raw))
    return decode_upload_json(raw)
