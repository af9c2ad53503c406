"""Human correction of the alignment (paper III-E; issue on validation and correction).

- ``GET  /v1/tiles/{z}/{x}/{y}/match-pairs``   a tile's accepted match pairs, confidences, residuals
- ``POST /v1/tiles/{z}/{x}/{y}/corrections``   (admin) reject a pair, or add one between two trips'
  frames (or a trip and the pre-built map) with a large weight
- ``GET  /v1/corrections[?z=&x=&y=]``          the audit trail: who, when, what, the version it made
- ``POST /v1/corrections/{id}/undo``           (admin) undo one

A correction is recorded with a ``correct_tile`` job in one transaction: the job re-aligns the whole
tile with every correction in force (Eq. 9 again), then ``merge_tile`` regenerates its topology as a
new version whose ``reason`` is ``correction`` (or ``undo correction``) and which lists the correction.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Annotated, Any, Literal

import numpy as np
import orjson
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, model_validator
from sqlalchemy import Text, cast, select

from services.api import answers
from services.api.deps import Admin, Ctx, Reader, ReadSessionDep, SessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.api.pagination import DEFAULT_LIMIT, Cursor, Limit, decode_cursor, keyset_page, page_response
from services.api.params import IdText, NoteText
from services.db import repo
from services.db.models import Correction, MatchPair, Trip, TripTile, utcnow
from services.tile_frames import record_sides, sides_of, tile_frame

router = APIRouter(prefix="/v1", tags=["corrections"])

Frames = Annotated[
    list[int], Field(min_length=2, max_length=2, description="first and last frame (inclusive)")
]


class CorrectionRequest(BaseModel):
    """``reject_pair``: ``pair_id``. ``add_pair``: ``trip_i`` + ``frames_i`` and ``trip_j`` + ``frames_j``
    (``trip_j`` null: the pre-built map); ``offset_xyyaw``: the pose of j's data in i's (metres,
    radians, the circle's local frame) when the human asserts it, else the two are registered."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["reject_pair", "add_pair"]
    pair_id: IdText | None = None
    trip_i: IdText | None = None
    frames_i: Frames | None = None
    trip_j: IdText | None = None
    frames_j: Frames | None = None
    offset_xyyaw: Annotated[list[float], Field(min_length=3, max_length=3)] | None = None
    note: NoteText | None = None

    @model_validator(mode="after")
    def _fields_of_kind(self) -> CorrectionRequest:
        if self.kind == "reject_pair" and not self.pair_id:
            raise ValueError("reject_pair needs pair_id")
        if self.kind == "add_pair" and (
            self.trip_i is None or self.frames_i is None or self.frames_j is None
        ):
            raise ValueError("add_pair needs trip_i, frames_i, frames_j (and trip_j, or null for the map)")
        return self


# The columns a listed pair is built from (its record as JSON text: parsed with orjson, several
# times faster than the JSON type's json.loads); the listing's sort key (confidence, id) comes last.
PAIR_COLUMNS = (
    MatchPair.status,
    MatchPair.job_id,
    MatchPair.trip_pk_i,
    MatchPair.trip_pk_j,
    MatchPair.residual_rms_m,
    cast(MatchPair.record, Text).label("record_json"),
    MatchPair.created_at,
)
PAIR_ORDER = (MatchPair.confidence, MatchPair.id)


def parse_record(text: str) -> dict[str, Any]:
    """A stored record's JSON text (Python's json writes NaN, which only json.loads reads back)."""
    try:
        return orjson.loads(text)
    except orjson.JSONDecodeError:
        return json.loads(text)


def pair_json(pair: Any, record: dict[str, Any], tile: str, centre_lonlat: Sequence[float]) -> dict[str, Any]:
    """A listed pair: a row of :data:`PAIR_COLUMNS` and :data:`PAIR_ORDER`, its parsed ``record``,
    and the record's ``centre_xy_world`` in lon/lat."""
    (_, frames_i), (_, frames_j) = sides_of(pair.trip_pk_i, pair.trip_pk_j, record)
    return {
        "id": pair.id,
        "tile": tile,
        "status": pair.status,
        "job_id": pair.job_id,
        "trip_i": pair.trip_pk_i,
        "frames_i": list(frames_i),
        "trip_j": pair.trip_pk_j,
        "frames_j": list(frames_j),
        "confidence": pair.confidence,
        "residual_rms_m": pair.residual_rms_m,
        "centre": [float(centre_lonlat[0]), float(centre_lonlat[1])],
        "relative_pose_xyyaw": record["relative_pose_xyyaw"],
        "n_element_matches": len(record["instance_matches"]),
        "human": bool(record.get("human", False)),
        "created_at": pair.created_at.isoformat(),
    }


def pairs_json(pairs: Sequence[Any], z: int, x: int, y: int) -> list[dict[str, Any]]:
    """Pairs of tile z/x/y as listed: their centres projected in one call with the tile's frame
    (a projection built per pair cost ~36 ms each)."""
    if not pairs:
        return []
    records = [parse_record(p.record_json) for p in pairs]
    centres = tile_frame(z, x, y).to_lonlat(np.array([r["centre_xy_world"] for r in records], float))
    tile = f"{z}/{x}/{y}"
    return [pair_json(p, r, tile, c) for p, r, c in zip(pairs, records, centres, strict=True)]


def correction_json(c: Correction) -> dict[str, Any]:
    return {
        "id": c.id,
        "tile": f"{c.z}/{c.x}/{c.y}",
        "kind": c.kind,
        "payload": {k: v for k, v in c.payload.items() if k not in ("undo_job_id", "undo_version_id")},
        "author_key_id": c.author_key_id,
        "created_at": c.created_at.isoformat(),
        "job_id": c.job_id,
        "result_version_id": c.result_version_id,
        "undone_at": c.undone_at.isoformat() if c.undone_at else None,
        "undone_by": c.undone_by,
        "undo_job_id": c.payload.get("undo_job_id"),
        "undo_version_id": c.payload.get("undo_version_id"),
    }


@router.get(
    "/tiles/{z}/{x}/{y}/match-pairs",
    response_class=Response,
    responses={
        200: answers.answer(answers.MatchPairs, "A page of the tile's match pairs"),
        **errors({422: {"invalid_request": "`cursor` is not a cursor of this listing."}}),
    },
)
def list_match_pairs(
    _: Reader,
    request: Request,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    status: Annotated[str | None, Query(description="active, added, rejected or superseded")] = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Response:
    """A page of the tile's match pairs (all but ``superseded``, or those of ``status``), lowest
    confidence first (then by id); ``next`` is the following page's URL (services.api.pagination)."""
    after = decode_cursor(cursor, (float, str)) if cursor is not None else None
    stmt = select(*PAIR_COLUMNS, *PAIR_ORDER).where(MatchPair.z == z, MatchPair.x == x, MatchPair.y == y)
    stmt = stmt.where(MatchPair.status == status) if status else stmt.where(MatchPair.status != "superseded")
    page = keyset_page(session, stmt, PAIR_ORDER, limit=limit, after=after)
    return page_response(
        request, {"tile": f"{z}/{x}/{y}", "match_pairs": pairs_json(page.rows, z, x, y)}, page
    )


def _trip_in_tile(session, trip_pk: str, frames: list[int], z: int, x: int, y: int, field: str) -> None:
    trip = session.get(Trip, trip_pk)
    if trip is None:
        raise ApiError(422, "invalid", f"trip {trip_pk} does not exist", location=field)
    if not 0 <= frames[0] <= frames[1] < trip.n_frames:
        raise ApiError(
            422,
            "invalid",
            f"frames {frames} are not within the trip's {trip.n_frames} frames",
            location=field.replace("trip", "frames"),
        )
    if session.get(TripTile, (trip_pk, z, x, y)) is None:
        raise ApiError(422, "invalid", f"trip {trip_pk} does not cross tile {z}/{x}/{y}", location=field)


@router.post(
    "/tiles/{z}/{x}/{y}/corrections",
    status_code=202,
    responses={
        202: answers.answer(answers.Correction, "The correction, its job queued (`status`: queued)"),
        **errors(
            {
                404: {"not_found": "the tile has no such match pair."},
                409: {"conflict": "the match pair is not active: nothing to reject."},
                422: {"invalid": "a trip that does not exist or cross the tile, or frames outside it."},
            }
        ),
    },
)
def submit_correction(
    caller: Admin, ctx: Ctx, session: SessionDep, z: int, x: int, y: int, body: CorrectionRequest
) -> dict[str, Any]:
    with session.begin():
        payload: dict[str, Any]
        if body.kind == "reject_pair":
            pair = session.get(MatchPair, body.pair_id, with_for_update=True)
            if pair is None or (pair.z, pair.x, pair.y) != (z, x, y):
                raise ApiError(
                    404, "not_found", f"tile {z}/{x}/{y} has no match pair {body.pair_id}", location="pair_id"
                )
            if pair.status not in ("active", "added"):
                raise ApiError(
                    409,
                    "conflict",
                    f"match pair {pair.id} is {pair.status}: nothing to reject",
                    location="pair_id",
                )
            (ti, fi), (tj, fj) = record_sides(pair)
            payload = {
                "pair_id": pair.id,
                "trip_i": ti,
                "frames_i": list(fi),
                "trip_j": tj,
                "frames_j": list(fj),
            }
            pair.status = "rejected"
        else:
            # add_pair: CorrectionRequest's validator requires these
            assert body.trip_i is not None and body.frames_i is not None and body.frames_j is not None
            _trip_in_tile(session, body.trip_i, body.frames_i, z, x, y, "trip_i")
            if body.trip_j is not None:
                _trip_in_tile(session, body.trip_j, body.frames_j, z, x, y, "trip_j")
            payload = {
                "trip_i": body.trip_i,
                "frames_i": body.frames_i,
                "trip_j": body.trip_j,
                "frames_j": body.frames_j,
                "offset_xyyaw": body.offset_xyyaw,
            }
        if body.note:
            payload["note"] = body.note
        job = repo.add_job(session, kind="correct_tile", subject=f"{z}/{x}/{y}")
        correction = Correction(
            id=repo.new_id(),
            z=z,
            x=x,
            y=y,
            kind=body.kind,
            payload=payload,
            author_key_id=caller.key_id,
            created_at=utcnow(),
            job_id=job.id,
        )
        session.add(correction)
        session.flush()
        answer = {**correction_json(correction), "status": "queued"}
    ctx.runner.wake()
    return answer


@router.get(
    "/corrections",
    responses={200: answers.answer(answers.Corrections, "The audit trail, oldest first")},
)
def list_corrections(
    _: Reader, session: ReadSessionDep, z: int | None = None, x: int | None = None, y: int | None = None
) -> dict[str, Any]:
    stmt = select(Correction)
    for column, value in ((Correction.z, z), (Correction.x, x), (Correction.y, y)):
        if value is not None:
            stmt = stmt.where(column == value)
    return {
        "corrections": [correction_json(c) for c in session.scalars(stmt.order_by(Correction.created_at))]
    }


@router.post(
    "/corrections/{correction_id}/undo",
    status_code=202,
    responses={
        202: answers.answer(answers.Correction, "The correction, undone; its job queued"),
        **errors(
            {
                404: {"not_found": "no correction with this id."},
                409: {"conflict": "the correction was already undone."},
            }
        ),
    },
)
def undo_correction(caller: Admin, ctx: Ctx, session: SessionDep, correction_id: str) -> dict[str, Any]:
    with session.begin():
        c = session.get(Correction, correction_id, with_for_update=True)
        if c is None:
            raise ApiError(404, "not_found", f"correction {correction_id} does not exist", location="path")
        if c.undone_at is not None:
            raise ApiError(409, "conflict", f"correction {c.id} was already undone", location="path")
        job = repo.add_job(session, kind="correct_tile", subject=f"{c.z}/{c.x}/{c.y}")
        c.undone_at, c.undone_by = utcnow(), caller.key_id
        c.payload = {**c.payload, "undo_job_id": job.id}
        if c.kind == "reject_pair":  # the pair may come back: the re-alignment decides
            pair = session.get(MatchPair, c.payload.get("pair_id"))
            if pair is not None and pair.status == "rejected":
                pair.status = "superseded"
        answer = {**correction_json(c), "status": "queued"}
    ctx.runner.wake()
    return answer
