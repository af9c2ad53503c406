"""``GET /v1/map?bbox=minlon,minlat,maxlon,maxlat[&version=N]`` (contract section 3): a GeoJSON
FeatureCollection of the road structure, live or at map version N."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response

from services.api import answers
from services.api.deps import Ctx, Reader, ReadSessionDep
from services.api.openapi import errors
from services.db import versions as vs
from services.tiles.http import (
    CORS_HEADERS,
    cache_control,
    check_map_version,
    parse_bbox,
)
from services.tiles.render import feature_collection, feature_json

router = APIRouter(prefix="/v1", tags=["map"])


@router.get(
    "/map",
    response_class=Response,
    responses={
        200: answers.geojson("The road structure in the bbox, with `map_version` and `bbox`"),
        **errors(
            {
                404: {"not_found": "the map version does not exist (yet)."},
                422: {"invalid_request": "`bbox` malformed, inverted or over the area limit."},
            }
        ),
    },
)
def get_map(
    _: Reader,
    ctx: Ctx,
    session: ReadSessionDep,
    bbox: Annotated[str, Query(description="minlon,minlat,maxlon,maxlat (degrees, EPSG:4326)")],
    version: Annotated[
        int | None,
        Query(description="map version (default: the live map)", json_schema_extra={"minimum": 0}),
    ] = None,
) -> Response:
    """LineString for line types, Polygon for ``crosswalk`` and ``road_marking``; ``properties.type``
    is the element type, ``id`` the stable feature id; ``map_version`` names what was read; ``bbox``
    bounds the features returned (whole features: they may reach past the requested box)."""
    box = parse_bbox(bbox)
    with session.begin():
        pinned = check_map_version(session, version, location="version")
        map_version = pinned if pinned is not None else vs.current_map_version(session)
        versions = vs.contributing_versions(session, bbox_lonlat=box, map_version=pinned)
        features = vs.map_features(session, bbox_lonlat=box, versions=versions)
    body = feature_collection([feature_json(f) for f in features], map_version=map_version)
    headers = {
        **CORS_HEADERS,
        "Cache-Control": cache_control(pinned=pinned is not None, public_map=ctx.settings.public_map),
    }
    headers["X-Map-Version"] = str(map_version)
    return Response(body, media_type="application/geo+json", headers=headers)
