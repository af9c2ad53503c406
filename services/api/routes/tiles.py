"""Tiles (contract section 3): ``GET /v1/tiles/{z}/{x}/{y}.mvt`` and ``.geojson``, ``GET
/v1/tiles.json`` (TileJSON 3.0.0). Live tiles: short ``Cache-Control`` and a strong ETag from the
contributing tile versions (304 on ``If-None-Match``); ``?v=<map version>`` pins a tile to a map
version and is cached for a year (immutable). 204 for an empty tile. See docs/tiles.md.

Most tile GETs never reach these routes: ``services.tiles.fastpath`` answers them from its caches
in front of FastAPI and hands over only what it cannot answer exactly as they would (errors,
other parameters, misses of the key cache that turn out 401/403)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import JSONResponse, Response

from services.api import answers
from services.api.deps import Ctx, Reader, ReadSessionDep
from services.api.openapi import errors
from services.tiles import render
from services.tiles.certificate import map_certificate, tile_certificate_at
from services.tiles.http import (
    CORS_HEADERS,
    PREFLIGHT_HEADERS,
    cache_control,
    caches,
    check_map_version,
    check_tile,
    tile_response,
)

router = APIRouter(prefix="/v1", tags=["tiles"])

PinnedVersion = Annotated[
    int | None,
    Query(
        alias="v",
        description="map version: the tile as it was then (immutable, cached forever)",
        json_schema_extra={"minimum": 0},  # checked by check_map_version
    ),
]
IfNoneMatch = Annotated[str | None, Header()]
# The answers a tile shares besides its 200 (OpenAPI)
TILE_ANSWERS: dict[int | str, dict] = {
    204: {"description": "An empty tile"},
    304: {"description": "`If-None-Match` names the tile's current ETag"},
    **errors({404: {"not_found": "the map version `v` does not exist (yet)."}}),
}


def _tile(
    kind: str,
    request: Request,
    ctx: Ctx,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    v: int | None,
    if_none_match: str | None,
) -> Response:
    check_tile(z, x, y)
    cache, pinned_etags = caches(request)
    with session.begin():
        map_version = check_map_version(session, v, location="v")
    tile, not_modified = render.render_then_keep(
        ctx.session_factory,
        cache,
        kind=kind,
        z=z,
        x=x,
        y=y,
        map_version=map_version,
        if_none_match=if_none_match,
        pinned_etags=pinned_etags,
    )
    ctx.metrics.count_tile(tile.source)
    return tile_response(
        tile.body,
        etag=tile.etag,
        media_type=tile.media_type,
        pinned=map_version is not None,
        public_map=ctx.settings.public_map,
        not_modified=not_modified,
        map_version=map_version,
    )


@router.get(
    "/tiles/{z}/{x}/{y}.mvt",
    response_class=Response,
    responses={
        200: {
            "description": "The tile (layer `road`)",
            "content": {"application/vnd.mapbox-vector-tile": {"schema": {"type": "string"}}},
        },
        **TILE_ANSWERS,
    },
)
def tile_mvt(
    _: Reader,
    request: Request,
    ctx: Ctx,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    v: PinnedVersion = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """A Mapbox Vector Tile (web-mercator XYZ, extent 4096, buffer 256) of the road structure: one
    layer ``road``, properties ``id``, ``type``, ``style`` and the elements' scalar properties."""
    return _tile("mvt", request, ctx, session, z, x, y, v, if_none_match)


@router.get(
    "/tiles/{z}/{x}/{y}.geojson",
    response_class=Response,
    responses={
        200: answers.geojson("The tile's features, unclipped, in lon/lat"),
        **TILE_ANSWERS,
    },
)
def tile_geojson(
    _: Reader,
    request: Request,
    ctx: Ctx,
    session: ReadSessionDep,
    z: int,
    x: int,
    y: int,
    v: PinnedVersion = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """The same features as the ``.mvt`` tile as a GeoJSON FeatureCollection (lon/lat, unclipped)."""
    return _tile("geojson", request, ctx, session, z, x, y, v, if_none_match)


@router.get(
    "/tiles/{z}/{x}/{y}/certificate",
    responses={
        200: answers.answer(answers.TileCertificate, "The tile's accuracy certificate"),
        **errors({404: {"not_found": "the map version `v` does not exist (yet)."}}),
    },
)
def tile_certificate(
    _: Reader, ctx: Ctx, session: ReadSessionDep, z: int, x: int, y: int, v: PinnedVersion = None
) -> JSONResponse:
    """The tile's expected absolute and relative lateral error (length-weighted RMS of its elements'
    ``sigma_abs_m`` and ``uncertainty_m``), the trips behind it, and the passes still needed to reach
    the ``certificate_target_m`` setting."""
    check_tile(z, x, y)
    with session.begin():
        map_version = check_map_version(session, v, location="v")
        cert = tile_certificate_at(
            session, z=z, x=x, y=y, map_version=map_version, target_m=ctx.settings.certificate_target_m
        )
    return JSONResponse(
        {"tile": f"{z}/{x}/{y}", "map_version": map_version, **cert.as_dict()},
        headers={
            **CORS_HEADERS,
            "Cache-Control": cache_control(
                pinned=map_version is not None, public_map=ctx.settings.public_map
            ),
        },
    )


@router.get(
    "/tiles.json",
    responses={200: {"description": "TileJSON 3.0.0 of the map (https://github.com/mapbox/tilejson-spec)"}},
)
def tile_json(_: Reader, request: Request, ctx: Ctx, session: ReadSessionDep) -> JSONResponse:
    """TileJSON 3.0.0: the tile URL pinned to the current map version, zooms, data bounds, vector_layers."""
    base = str(request.base_url).rstrip("/")
    with session.begin():
        doc = render.tilejson(session, base_url=base, tile_zoom=ctx.settings.tile_zoom)
        doc["certificate"] = map_certificate(session, target_m=ctx.settings.certificate_target_m).as_dict()
        doc["certificate_tiles"] = [f"{base}/v1/tiles/{{z}}/{{x}}/{{y}}/certificate"]
    return JSONResponse(
        doc,
        headers={
            **CORS_HEADERS,
            "Cache-Control": cache_control(pinned=False, public_map=ctx.settings.public_map),
        },
    )


@router.options("/tiles/{rest:path}", include_in_schema=False)
@router.options("/tiles.json", include_in_schema=False)
@router.options("/map", include_in_schema=False)
def preflight(rest: str = "") -> Response:
    """CORS preflight (browsers send it without the key before a GET with ``Authorization``)."""
    return Response(status_code=204, headers=PREFLIGHT_HEADERS)
