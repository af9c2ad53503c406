"""``POST /v1/trips`` (upload), ``GET /v1/trips/{id}``, ``GET /v1/trips/{id}/poses``,
``GET /v1/trips/{id}/upload`` (the raw upload as kept, gzip)."""

from __future__ import annotations

import time
from datetime import UTC, datetime
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from csr_core.errors import UploadError
from services.api import answers
from services.api.body import read_limited, too_large
from services.api.deps import AnyRole, Ctx, ReadSessionDep, Uploader
from services.api.errors import ApiError, as_api_error
from services.api.openapi import errors, upload_request_body
from services.auth import may_read_trace, may_read_trip
from services.db import repo
from services.db.models import Trip, TripPoses
from services.reconstructions import ALGORITHM_VERSION, decode_arrays
from services.upload_formats import UploadType, upload_type
from services.uploads import accept_upload

router = APIRouter(prefix="/v1/trips", tags=["trips"])

_ENCODINGS = {"": False, "identity": False, "gzip": True, "x-gzip": True}


def _iso_utc(moment: datetime) -> str:
    return (moment if moment.tzinfo else moment.replace(tzinfo=UTC)).isoformat()


def reconstruction_json(summary: dict[str, Any] | None) -> dict[str, Any] | None:
    """The single-trip reconstruction's summary (``None`` until the ingest job stored it)."""
    if summary is None:
        return None
    return {
        "algorithm_version": summary["algorithm_version"],
        "frame": {"origin_lat": summary["origin_lat"], "origin_lon": summary["origin_lon"]},
        "frames": summary["n_frames"],
        "keyframes": summary["n_keyframes"],
        "instances": summary["n_instances"],
        "noise": summary["noise"],
        "created_at": _iso_utc(summary["created_at"]),
    }


def trip_json(
    trip: Trip, *, tiles: list | None = None, reconstruction: dict[str, Any] | None = None
) -> dict[str, Any]:
    out: dict[str, Any] = {
        "id": trip.id,
        "vehicle_id": trip.vehicle_id,
        "trip_id": trip.trip_id,
        "status": trip.status,
        "schema_version": trip.schema_version,
        "started_at": trip.started_at,
        "n_frames": trip.n_frames,
        "body_bytes": trip.body_bytes,
        "received_at": _iso_utc(trip.received_at),
        "updated_at": _iso_utc(trip.updated_at),
        "length_km": trip.length_km,
        "error": trip.error,
        "raw_purged_at": _iso_utc(trip.raw_purged_at) if trip.raw_purged_at is not None else None,
    }
    if tiles is not None:
        out["tiles"] = [f"{t.z}/{t.x}/{t.y}" for t in tiles]
        out["tiles_pending"] = sum(t.processed_job_id is None for t in tiles)
        out["reconstruction"] = reconstruction_json(reconstruction)
        out["quality"] = quality_json(reconstruction)
    return out


def quality_json(summary: dict[str, Any] | None) -> dict[str, Any] | None:
    """The trip's integrity verdict (``csr_core.single_trip.integrity``): its poses tested
    against its own GNSS after single-trip smoothing, and, once a tile job aligned it, after
    alignment. ``None`` until the ingest job stored the reconstruction.

    ``{"verdict": "ok" | "repaired" | "degraded", "degraded": bool, "reason", "stretches_s",
    "worst_z", "z_limit", "median_offset_m", "gnss_median_expected_m", "rejected_share",
    "rmse_to_gnss_m", "alignment": {tile: reason} | null}``"""
    if summary is None:
        return None
    diagnostics = summary.get("diagnostics") or {}
    single = diagnostics.get("quality") or {
        "verdict": "ok",
        "reason": "not tested (reconstructed without the test)",
    }
    return {
        **single,
        "degraded": single.get("verdict") == "degraded",
        "alignment": diagnostics.get("alignment_quality"),
    }


def _check_headers(request: Request, max_body_bytes: int) -> tuple[bool, UploadType]:
    """415 for a wrong content type or encoding, 413 for a declared length over the limit;
    returns whether the body is gzip and the upload's type."""
    content_type = request.headers.get("content-type", "")
    kind = upload_type(content_type)
    if kind is None:
        accepted = " or ".join(t.value for t in UploadType)
        raise ApiError(
            415,
            "content_type",
            f"Content-Type must be {accepted}, not {content_type.split(';')[0].strip() or 'missing'!r}",
        )
    encoding = request.headers.get("content-encoding", "").strip().lower()
    if encoding not in _ENCODINGS:
        raise ApiError(415, "content_encoding", f"Content-Encoding must be gzip or absent, not {encoding!r}")
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > max_body_bytes:
        raise too_large("as sent", max_body_bytes)
    return _ENCODINGS[encoding], kind


@router.post(
    "",
    status_code=202,
    openapi_extra=upload_request_body(),
    responses={
        202: answers.answer(answers.Trip, "A new trip", headers=answers.LOCATION_HEADER),
        200: answers.answer(
            answers.Trip, "The same body again: the trip it made", headers=answers.LOCATION_HEADER
        ),
        **errors(
            {
                400: {
                    "json": "malformed JSON.",
                    "gzip": "malformed or truncated gzip.",
                    "cbor": "a binary body that is not one whole CBOR document.",
                },
                403: {"forbidden": "a vehicle key uploading for another `vehicle_id`."},
                409: {"conflict": "other content under an existing `(vehicle_id, trip_id)`."},
                413: {
                    "too_large": "the body over the limit as sent, or after decompression.",
                    "too_many_frames": "more frames than `CSR_MAX_FRAMES_PER_TRIP` (`location: frames`).",
                },
                415: {
                    "content_type": "neither `application/json` nor `application/vnd.csr.trip+cbor`.",
                    "content_encoding": "an encoding other than gzip.",
                },
                422: {
                    "schema": "a violation of the upload schema (`location`: its JSON path).",
                    "non_finite": "NaN or an infinite number.",
                    "time_order": "`t` not strictly increasing.",
                    "version": "a `schema_version` other than `1.0`.",
                    "binary": "a binary body whose layout is not the encoding's (`location`: its column).",
                },
                503: {
                    "busy": "the uploads in flight hold `CSR_MAX_UPLOAD_BYTES_IN_FLIGHT` (`Retry-After`).",
                },
            }
        ),
    },
)
async def upload_trip(request: Request, caller: Uploader, ctx: Ctx) -> JSONResponse:
    settings, metrics = ctx.settings, ctx.metrics
    try:
        gzipped, kind = _check_headers(request, settings.max_body_bytes)
        body = await read_limited(request.stream(), max_bytes=settings.max_body_bytes)
        started = time.perf_counter()
        accepted = await run_in_threadpool(
            accept_upload,
            session_factory=ctx.session_factory,
            settings=settings,
            caller=caller,
            body=body,
            gzipped=gzipped,
            kind=kind,
        )
    except (ApiError, UploadError) as exc:
        metrics.rejects.labels(as_api_error(exc).error).inc()
        raise
    metrics.upload_seconds.observe(time.perf_counter() - started)
    if accepted.created:
        ctx.runner.wake()
        metrics.uploads.labels("accepted").inc()
        metrics.upload_bytes.labels("sent").inc(len(body))
        metrics.upload_bytes.labels("decompressed").inc(accepted.json_bytes)
    else:
        metrics.uploads.labels("duplicate").inc()
    location = f"/v1/trips/{accepted.trip.id}"
    return JSONResponse(
        trip_json(accepted.trip), status_code=202 if accepted.created else 200, headers={"Location": location}
    )


def _load_trip(session: Session, trip_pk: str) -> Trip:
    trip = repo.get_trip(session, trip_pk=trip_pk)
    if trip is None:
        raise ApiError(404, "not_found", f"no trip {trip_pk!r}", location="id")
    return trip


@router.get(
    "/{trip_pk}",
    responses={
        200: answers.answer(answers.Trip, "The trip, its tiles, reconstruction and quality"),
        **errors(
            {
                403: {"forbidden": "a vehicle key reading another vehicle's trip."},
                404: {"not_found": "no trip with this id."},
            }
        ),
    },
)
def get_trip(trip_pk: str, caller: AnyRole, session: ReadSessionDep) -> dict[str, Any]:
    trip = _load_trip(session, trip_pk)
    may_read_trip(caller, trip.vehicle_id)
    summary = repo.reconstruction_summary(session, trip_pk=trip.id, algorithm_version=ALGORITHM_VERSION)
    return trip_json(trip, tiles=repo.tiles_of_trip(session, trip_pk=trip.id), reconstruction=summary)


@router.get(
    "/{trip_pk}/poses",
    responses={
        200: answers.answer(answers.Poses, "Every uploaded frame's final pose, in upload order"),
        **errors(
            {
                403: {
                    "forbidden": "a vehicle key reading another vehicle's trip; a reader key when "
                    "`CSR_READER_SEES_TRACES` is false."
                },
                404: {"not_found": "no trip with this id."},
                409: {"not_aligned": "the trip is not aligned (yet), or failed (the reason)."},
            }
        ),
    },
)
def get_poses(trip_pk: str, caller: AnyRole, ctx: Ctx, session: ReadSessionDep) -> dict[str, Any]:
    trip = _load_trip(session, trip_pk)
    may_read_trace(caller, trip.vehicle_id, reader_sees_traces=ctx.settings.reader_sees_traces)
    poses = session.get(TripPoses, trip.id) if trip.status == "aligned" else None
    if poses is None:  # contract section 3: 409 before it is aligned
        detail = f": {trip.error}" if trip.status == "failed" and trip.error else ""
        raise ApiError(
            409, "not_aligned", f"trip {trip.id} is {trip.status}: it has no aligned poses{detail}"
        )
    arrays = decode_arrays(poses.arrays)
    rows = zip(
        arrays["t"].tolist(),
        arrays["lat"].tolist(),
        arrays["lon"].tolist(),
        arrays["heading_deg"].tolist(),
        strict=True,
    )
    return {
        "id": trip.id,
        "frames": [{"t": t, "lat": lat, "lon": lon, "heading_deg": h} for t, lat, lon, h in rows],
    }


@router.get(
    "/{trip_pk}/upload",
    response_class=Response,
    responses={
        200: {
            "description": "The raw upload as kept, with `Content-Encoding: gzip`: the contract's JSON, "
            "or the compact binary as sent",
            "content": {
                "application/json": {"schema": {"type": "object"}},
                UploadType.CBOR.value: {"schema": {"type": "string", "contentMediaType": "application/cbor"}},
            },
        },
        **errors(
            {
                403: {
                    "forbidden": "a vehicle key reading another vehicle's trip; a reader key when "
                    "`CSR_READER_SEES_TRACES` is false."
                },
                404: {"not_found": "no trip with this id."},
                410: {"purged": "retention deleted the raw upload (`CSR_RAW_RETENTION_DAYS`)."},
            }
        ),
    },
)
def get_upload(trip_pk: str, caller: AnyRole, ctx: Ctx, session: ReadSessionDep) -> Response:
    """The raw upload as kept (gzip-compressed JSON, sent with ``Content-Encoding: gzip``); 410
    ``purged`` once retention deleted it."""
    trip = _load_trip(session, trip_pk)
    may_read_trace(caller, trip.vehicle_id, reader_sees_traces=ctx.settings.reader_sees_traces)
    upload = repo.raw_upload(session, trip_pk=trip.id)
    if upload is None:
        when = _iso_utc(trip.raw_purged_at) if trip.raw_purged_at is not None else "earlier"
        raise ApiError(410, "purged", f"trip {trip.id}: its raw upload was deleted ({when})", location="id")
    kind = UploadType.CBOR if upload.encoding == UploadType.CBOR.stored_encoding else UploadType.JSON
    return Response(upload.body, media_type=kind.value, headers={"Content-Encoding": "gzip"})
