"""Checking and decoding a trip upload frame batch by frame batch, in memory bounded by its size.

Parsing a whole upload into Python objects costs ~800 bytes per frame (dicts, floats and lists;
~6x a small frame's JSON), and ``orjson.loads`` peaks at ~2.5 KB per frame (its document tree
beside the Python one). Here msgspec splits the body into the raw JSON text of each frame
(``msgspec.Raw``: a 48-byte view into the body, nothing parsed), and the frames are validated
(pydantic, the same schema as :func:`csr_core.upload.validate_upload_json`) or decoded
:data:`BATCH_JSON_BYTES` of JSON at a time; a batch's tree is freed before the next is parsed. The checks and
their order are those of :func:`~csr_core.upload.validate_upload_json`, and so are the errors:
a body msgspec cannot split (malformed JSON, ``NaN``, ``frames`` missing, not a list or shorter
than two) is handed to it whole, to be refused with its usual error (that refusal parses the
body whole, up to its first error).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, cast

import msgspec
import numpy as np
import orjson
from pydantic import TypeAdapter, ValidationError

from csr_core.errors import UploadError
from csr_core.types import GnssStatus, PerceivedElement, Trip
from csr_core.upload import (
    _ADAPTER,
    _check_semantics,
    _check_version,
    _decode_element,
    _error_from_pydantic,
    _Frame,
    decode_trip,
    validate_upload,
    validate_upload_json,
)

BATCH_JSON_BYTES = (
    256 * 1024
)  # frames parsed at once: up to this much of their JSON (~2 MB of Python objects)

_TOP_DECODER = msgspec.json.Decoder(dict[str, msgspec.Raw])
_FRAMES_DECODER = msgspec.json.Decoder(list[msgspec.Raw])
_FRAMES_ADAPTER = TypeAdapter(list[_Frame])


@dataclass(frozen=True, slots=True)
class UploadHead:
    """What the service stores of a valid upload besides its bytes."""

    schema_version: str
    vehicle_id: str
    trip_id: str
    started_at: str
    n_frames: int


@dataclass(frozen=True, slots=True)
class _Split:
    top: dict[str, msgspec.Raw]  # the top-level members, unparsed
    frames: list[msgspec.Raw]  # each frame's JSON text, unparsed


def _split(body: bytes | bytearray) -> _Split | None:
    """The upload's members and frames as raw JSON text, or ``None`` when msgspec cannot split it
    (the body is then checked whole, for its error)."""
    try:
        top = _TOP_DECODER.decode(body)
        raw_frames = top.get("frames")
        if raw_frames is None:
            return None
        frames = _FRAMES_DECODER.decode(raw_frames)
    except msgspec.MsgspecError:
        return None
    if len(frames) < 2:
        return None
    return _Split(top, frames)


def _json_array(items: list[msgspec.Raw]) -> bytes:
    return b"[" + b",".join(bytes(item) for item in items) + b"]"


def _batches(frames: list[msgspec.Raw], start: int) -> Iterator[tuple[int, bytes]]:
    """``(index of the batch's first frame, the batch as a JSON array)`` from ``start`` on: as many
    frames as fit in :data:`BATCH_JSON_BYTES` of JSON, at least one."""
    first = start
    while first < len(frames):
        end, size = first + 1, len(frames[first])
        while end < len(frames) and size + len(frames[end]) <= BATCH_JSON_BYTES:
            size += len(frames[end])
            end += 1
        yield first, _json_array(frames[first:end])
        first = end


def _head_json(split: _Split) -> bytes:
    """The upload with only its first two frames: the schema's checks of everything but frames[2:]."""
    members = [orjson.dumps(key) + b":" + bytes(value) for key, value in split.top.items() if key != "frames"]
    members.append(b'"frames":' + _json_array(split.frames[:2]))
    return b"{" + b",".join(members) + b"}"


def _batch_error(exc: ValidationError, first: int) -> UploadError | None:
    """The batch's first error as the whole upload's (frame indices shifted by ``first``), or
    ``None`` for malformed JSON, whose message is only right for the whole body."""
    err = exc.errors(include_url=False)[0]
    if err["type"] == "json_invalid" or not err["loc"] or not isinstance(err["loc"][0], int):
        return None
    loc = ("frames", first + err["loc"][0], *err["loc"][1:])
    try:
        shifted = ValidationError.from_exception_data(
            exc.title, [{"type": err["type"], "loc": loc, "input": err["input"], "ctx": err.get("ctx", {})}]
        )
    except (KeyError, TypeError, ValueError):  # an error kind pydantic cannot rebuild: the whole body's
        return None
    return _error_from_pydantic(shifted)


def _refuse_whole(body: bytes | bytearray) -> UploadError:
    """The error :func:`validate_upload_json` gives the whole body (it is known to have one)."""
    try:
        validate_upload_json(body)
    except UploadError as exc:
        return exc
    return UploadError("the upload could not be checked frame by frame", location="frames")


def _check_frame_count(n_frames: int, max_frames: int | None) -> None:
    if max_frames is not None and n_frames > max_frames:
        raise UploadError(
            f"frames: the trip has {n_frames} frames, over the limit of {max_frames} frames per trip",
            location="frames",
            reason="too_many_frames",
        )


def check_upload_json(body: bytes | bytearray, *, max_frames: int | None = None) -> UploadHead:
    """Validate a raw JSON upload as :func:`~csr_core.upload.validate_upload_json` does, without
    ever holding more than :data:`BATCH_JSON_BYTES` of frames parsed; ``max_frames``: refuse a trip with
    more frames (``reason="too_many_frames"``) before parsing any.

    Raises :class:`UploadError` naming the frame and field of the first problem.
    """
    split = _split(body)
    if split is None:
        doc = validate_upload_json(body)  # small, or refused: the whole body is parsed only here
        _check_frame_count(len(doc["frames"]), max_frames)
        return _head_of(doc, len(doc["frames"]))
    try:
        return _check_split(body, split, max_frames)
    except UploadError as exc:
        error = exc
    # the raw frames hold the body's buffer: the error leaves without the frames that hold them
    del split
    error.__context__ = None  # the pydantic error's traceback holds them too
    raise error.with_traceback(None)


def check_upload_document(doc: Any, *, max_frames: int | None = None) -> UploadHead:
    """Validate an upload already decoded into a document (the compact binary's,
    ``csr_core.upload_binary``) as :func:`check_upload_json` validates raw JSON."""
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if isinstance(frames, list):
        _check_frame_count(len(frames), max_frames)
    valid = validate_upload(doc)
    return _head_of(valid, len(valid["frames"]))


def _check_split(body: bytes | bytearray, split: _Split, max_frames: int | None) -> UploadHead:
    n_frames = len(split.frames)
    _check_frame_count(n_frames, max_frames)
    try:
        head = cast(dict[str, Any], _ADAPTER.validate_json(_head_json(split)))
    except ValidationError as exc:
        raise _error_from_pydantic(exc) from None
    times_s = np.empty(n_frames)
    times_s[:2] = [frame["t"] for frame in head["frames"]]
    for first, batch in _batches(split.frames, 2):
        try:
            frames = _FRAMES_ADAPTER.validate_json(batch)
        except ValidationError as exc:
            error = _batch_error(exc, first)
            raise (error if error is not None else _refuse_whole(body)) from None
        times_s[first : first + len(frames)] = [frame["t"] for frame in frames]
    _check_version(head)
    _check_semantics(head, times_s)
    return _head_of(head, n_frames)


def _head_of(doc: dict[str, Any], n_frames: int) -> UploadHead:
    return UploadHead(
        schema_version=doc["schema_version"],
        vehicle_id=doc["vehicle_id"],
        trip_id=doc["trip_id"],
        started_at=doc["started_at"],
        n_frames=n_frames,
    )


def decode_upload_json(body: bytes | bytearray) -> Trip:
    """A validated raw JSON upload -> :class:`Trip`, parsing :data:`BATCH_JSON_BYTES` of frames at a time
    into the trip's columns (the same result as ``decode_trip(validate_upload_json(body))``)."""
    split = _split(body)
    if split is None:
        return decode_trip(validate_upload_json(body))
    n = len(split.frames)
    nan = float("nan")
    timestamps_s, std_m, heading_deg = np.empty(n), np.full(n, nan), np.full(n, nan)
    lonlat_deg, odom_xyyaw = np.empty((n, 2)), np.empty((n, 3))
    status = np.empty(n, np.uint8)
    elements: list[tuple[PerceivedElement, ...]] = []
    for first, batch in _batches(split.frames, 0):
        for i, frame in enumerate(orjson.loads(batch), start=first):
            gnss, odom = frame["gnss"], frame["odom"]
            timestamps_s[i] = frame["t"]
            lonlat_deg[i] = gnss["lon"], gnss["lat"]
            status[i] = GnssStatus.from_name(gnss["status"])
            std_m[i] = gnss.get("std_m", nan)
            heading_deg[i] = gnss.get("heading_deg", nan)
            odom_xyyaw[i] = odom["x"], odom["y"], odom["yaw"]
            elements.append(tuple(_decode_element(e) for e in frame["elements"]) if frame["elements"] else ())

    def member(key: str, default: Any) -> Any:
        return orjson.loads(bytes(split.top[key])) if key in split.top else default

    return Trip(
        vehicle_id=member("vehicle_id", ""),
        trip_id=member("trip_id", ""),
        started_at=member("started_at", ""),
        timestamps_s=timestamps_s,
        gnss_lonlat_deg=lonlat_deg,
        gnss_status=status,
        gnss_std_m=std_m,
        gnss_heading_deg=heading_deg,
        odom_xyyaw=odom_xyyaw,
        elements=tuple(elements),
        sensor_setup=dict(member("sensor_setup", {})),
    )
