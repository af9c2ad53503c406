"""Version history (OSM API 0.6 as the model): a tile's versions, one version as GeoJSON, a diff,
the ``changes?since=`` feed, rollback and approval (admin), and one feature across versions."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from sqlalchemy import select
from sqlalchemy.orm import Session, defer

from services.api import answers
from services.api.deps import Admin, Ctx, Reader, ReadSessionDep, SessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.api.pagination import DEFAULT_LIMIT, Cursor, Limit, decode_cursor, keyset_page, page_response
from services.api.params import DbInt
from services.db import versions as vs
from services.db.models import TileVersion
from services.tiles.http import CORS_HEADERS, cache_control, check_tile
from services.tiles.render import feature_collection, feature_json

router = APIRouter(prefix="/v1", tags=["versions"])

NO_VERSION = {404: {"not_found": "the tile has no versions, or not this one."}}
WRITE_ERRORS = errors(
    {
        404: {"not_found": "the tile has no such version."},
        409: {
            "conflict": "another write got there first, or `expected_latest` is stale.",
            "invalid_state": "the version cannot be published so (e.g. not a candidate).",
        },
    }
)

FEED_LIMIT_MAX = 1000


def version_or_404(session: Session, z: int, x: int, y: int, v: int | None, location: str) -> TileVersion:
    """Version ``v`` of the tile (its latest when ``None``); 404 naming the tile when it has no
    versions, or the version when it has not that one."""
    if v is None:
        row = vs.latest_version(session, z=z, x=x, y=y)
        if row is None:
            raise ApiError(404, "not_found", f"tile {z}/{x}/{y} has no versions", location="path")
        return row
    row = vs.get_version(session, z=z, x=x, y=y, version=v)
    if row is None:
        raise ApiError(404, "not_found", f"tile {z}/{x}/{y} has no version {v}", location=location)
    return row


@router.get(
    "/tiles/{z}/{x}/{y}/versions",
    response_class=Response,
    responses={
        200: answers.answer(answers.TileHistory, "A page of the tile's versions, oldest first"),
        **errors({**NO_VERSION, 422: {"invalid_request": "`cursor` is not a cursor of this listing."}}),
    },
)
def tile_history(
    _: Reader,
    request: Request,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Response:
    """A page of a pipeline tile's versions, oldest first: status, reason, job, trips, corrections,
    quality, change counts; ``next`` is the following page's URL (services.api.pagination). The
    versions' topology states (the large column) are not read."""
    check_tile(z, x, y)
    after = decode_cursor(cursor, (int,)) if cursor is not None else None
    stmt = (
        select(TileVersion, TileVersion.version)
        .options(defer(TileVersion.state))
        .where(TileVersion.z == z, TileVersion.x == x, TileVersion.y == y)
    )
    with session.begin():
        head = vs.tile_head(session, z=z, x=x, y=y)
        if head is None:
            raise ApiError(404, "not_found", f"tile {z}/{x}/{y} has no versions", location="path")
        page = keyset_page(session, stmt, (TileVersion.version,), limit=limit, after=after)
        versions = [vs.version_summary(row[0]) for row in page.rows]
    body = {
        "tile": f"{z}/{x}/{y}",
        "latest_version": head.latest_version,
        "live_version": head.live_version,
        "versions": versions,
    }
    return page_response(request, body, page)


@router.get(
    "/tiles/{z}/{x}/{y}/versions/{v}",
    response_class=Response,
    responses={
        200: answers.geojson("The version's features, each with its `change`"),
        **errors(NO_VERSION),
    },
)
def tile_version_geojson(
    _: Reader,
    ctx: Ctx,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    v: int,
    include_removed: Annotated[bool, Query(description="also the removed features (last geometry)")] = False,
) -> Response:
    """One version of a tile as GeoJSON; each feature's ``change`` against the live version before it."""
    with session.begin():
        check_tile(z, x, y)
        row = version_or_404(session, z, x, y, v, "path.v")
        features = vs.version_rows(session, row.id, include_removed)
        body = feature_collection(
            [
                feature_json(
                    vs.MapFeature(vs.as_feature(r), row.id, z, x, y, row.version), extra={"change": r.change}
                )
                for r in features
            ],
            **vs.version_summary(row),
        )
    # a version never changes
    return Response(
        body,
        media_type="application/geo+json",
        headers={
            **CORS_HEADERS,
            "Cache-Control": cache_control(pinned=True, public_map=ctx.settings.public_map),
        },
    )


@router.get("/tiles/{z}/{x}/{y}/diff", responses=errors(NO_VERSION))
def tile_diff(
    _: Reader,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    from_: Annotated[int, Query(alias="from", description="tile version")],
    to: Annotated[int, Query(description="tile version")],
) -> dict:
    """Per feature between two versions of the tile: added, removed, modified (before/after)."""
    with session.begin():
        check_tile(z, x, y)
        version_or_404(session, z, x, y, from_, "query.from")
        version_or_404(session, z, x, y, to, "query.to")
        return vs.diff(session, z=z, x=x, y=y, from_version=from_, to_version=to)


@router.get(
    "/changes",
    response_class=JSONResponse,
    responses={200: answers.answer(answers.Changes, "Tile versions made after map version `since`")},
)
def changes(
    _: Reader,
    session: ReadSessionDep,
    since: Annotated[int, Query(ge=0, description="map version already seen (0: from the start)")] = 0,
    limit: Annotated[int, Query(ge=1, le=FEED_LIMIT_MAX)] = 100,
) -> JSONResponse:
    """The changes feed: tile versions made after map version ``since``, oldest first; continue
    with ``since=next``."""
    with session.begin():
        entries = vs.changes_since(session, since_map_version=since, limit=limit)
        current = vs.current_map_version(session)
    next_cursor = entries[-1]["map_version"] if entries else since
    return JSONResponse(
        {
            "since": since,
            "next": next_cursor,
            "map_version": current,
            "more": next_cursor < current,
            "changes": entries,
        },
        headers=CORS_HEADERS,
    )


class RollbackBody(BaseModel):
    version: DbInt = Field(ge=1, description="the tile version to publish again")
    expected_latest: DbInt | None = Field(
        None, description="the latest version the caller saw (409 if stale)"
    )


class ApproveBody(BaseModel):
    expected_latest: DbInt | None = Field(
        None, description="the latest version the caller saw (409 if stale)"
    )


def _write(action, session: Session, **kwargs) -> JSONResponse:
    z, x, y = kwargs["z"], kwargs["x"], kwargs["y"]
    try:
        with session.begin():
            version = action(session, **kwargs)
            out = vs.version_summary(version)
    except vs.VersionConflict as exc:
        raise ApiError(409, "conflict", str(exc), location="expected_latest") from exc
    except vs.VersionNotFound as exc:
        raise ApiError(404, "not_found", str(exc), location="version") from exc
    except vs.InvalidVersionAction as exc:
        raise ApiError(409, "invalid_state", str(exc), location="version") from exc
    return JSONResponse(
        out, status_code=201, headers={"Location": f"/v1/tiles/{z}/{x}/{y}/versions/{out['version']}"}
    )


@router.post(
    "/tiles/{z}/{x}/{y}/rollback",
    status_code=201,
    response_class=JSONResponse,
    responses={
        201: {"description": "The new version's summary", "headers": answers.LOCATION_HEADER},
        **WRITE_ERRORS,
    },
)
def rollback(caller: Admin, session: SessionDep, z: int, x: int, y: int, body: RollbackBody) -> JSONResponse:
    """Publish an old version again, as a new version (reason ``rollback to vN``); 409 if another
    write got there first (or ``expected_latest`` is stale)."""
    check_tile(z, x, y)
    return _write(
        vs.rollback,
        session,
        z=z,
        x=x,
        y=y,
        to_version=body.version,
        author=caller.key_id,
        expected_latest=body.expected_latest,
    )


@router.post(
    "/tiles/{z}/{x}/{y}/versions/{v}/approve",
    status_code=201,
    response_class=JSONResponse,
    responses={
        201: {"description": "The new version's summary", "headers": answers.LOCATION_HEADER},
        **WRITE_ERRORS,
    },
)
def approve(
    caller: Admin, session: SessionDep, z: int, x: int, y: int, v: int, body: ApproveBody | None = None
) -> JSONResponse:
    """A candidate (failed the publish gate) goes live, as a new version (reason ``approve vN``)."""
    check_tile(z, x, y)
    return _write(
        vs.approve,
        session,
        z=z,
        x=x,
        y=y,
        version=v,
        author=caller.key_id,
        expected_latest=body.expected_latest if body else None,
    )


@router.get(
    "/features/{feature_id}",
    response_class=JSONResponse,
    responses={
        200: answers.answer(answers.Feature, "The feature, with `change`, `live` and `history`"),
        **errors({404: {"not_found": "no feature with this id."}}),
    },
)
def feature(_: Reader, session: ReadSessionDep, feature_id: str) -> JSONResponse:
    """One feature: its geometry and properties in the live map (else its newest version) and its
    history across versions."""
    with session.begin():
        history = vs.feature_history(session, feature_id=feature_id)
        if not history:
            raise ApiError(404, "not_found", f"no feature {feature_id!r}", location="path.feature_id")
        last_row, last_version = history[-1]
        head = vs.tile_head(session, z=last_version.z, x=last_version.x, y=last_version.y)
        live_id = head.live_version_id if head else None
        live = [(r, v) for r, v in history if v.id == live_id]
        row, version = live[0] if live else (last_row, last_version)
        in_live_map = bool(live) and row.change != "removed"
        doc = feature_json(
            vs.MapFeature(vs.as_feature(row), version.id, version.z, version.x, version.y, version.version),
            extra={"change": row.change, "live": in_live_map},
        )
        doc["history"] = [
            {
                "map_version": v.id,
                "version": v.version,
                "status": v.status,
                "reason": v.reason,
                "change": r.change,
                "type": r.type,
                "style": r.style,
                "created_at": vs.iso_utc(v.created_at),
            }
            for r, v in history
        ]
    return JSONResponse(doc, headers=CORS_HEADERS)
