"""``GET /v1/export/lanelet2?bbox=minlon,minlat,maxlon,maxlat[&version=N]``: the map in the bbox
(live, or at map version N) as a Lanelet2 OSM file (``csr_core.export``; docs/lanelet2-export.md).
What was written and skipped is in the ``X-Lanelet2-Report`` header (JSON)."""

from __future__ import annotations

from typing import Annotated

import numpy as np
import orjson
from fastapi import APIRouter, Query
from fastapi.responses import Response

from csr_core.errors import CsrError
from csr_core.export import LonLatFeature, export_lanelet2
from csr_core.geo import LocalFrame
from csr_core.types import DividerStyle, ElementType
from services.api.deps import Reader, ReadSessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.db import versions as vs
from services.tiles.http import check_map_version, parse_bbox

router = APIRouter(prefix="/v1/export", tags=["export"])

OSM_XML = "application/xml"


def _lonlat_features(features: list[vs.VersionFeature]) -> tuple[list[LonLatFeature], int]:
    """Service rows -> core records (multi-geometries split); count of rows of unknown type."""
    out, unknown = [], 0
    for f in features:
        try:
            etype = ElementType(f.type)
        except ValueError:
            unknown += 1
            continue
        geoms = getattr(f.geometry, "geoms", [f.geometry])
        for geom in geoms:
            if geom.is_empty:
                continue
            coords = geom.exterior.coords if geom.geom_type == "Polygon" else geom.coords
            lonlat = np.asarray(coords, float)[:, :2]
            if geom.geom_type == "Polygon" and len(lonlat) > 1 and np.array_equal(lonlat[0], lonlat[-1]):
                lonlat = lonlat[:-1]
            style = DividerStyle(f.style) if f.style in DividerStyle._value2member_map_ else None
            out.append(LonLatFeature(etype, lonlat, style, f.feature_id, dict(f.properties or {})))
    return out, unknown


@router.get(
    "/lanelet2",
    response_class=Response,
    responses={
        200: {
            "description": "A Lanelet2 OSM XML file (an attachment); what was written and skipped is "
            "in `X-Lanelet2-Report` (JSON)",
            "content": {OSM_XML: {"schema": {"type": "string"}}},
            "headers": {
                "X-Lanelet2-Report": {
                    "description": "JSON: the export's report",
                    "schema": {"type": "string"},
                },
                "X-Map-Version": {"description": "the map version exported", "schema": {"type": "integer"}},
            },
        },
        **errors(
            {
                404: {"not_found": "the map version does not exist (yet)."},
                422: {
                    "invalid_request": "`bbox` malformed, inverted or over the area limit.",
                    "export": "the map in the bbox cannot be exported.",
                },
            }
        ),
    },
)
def export_lanelet2_osm(
    _: Reader,
    session: ReadSessionDep,
    bbox: Annotated[str, Query(description="minlon,minlat,maxlon,maxlat (degrees, EPSG:4326)")],
    version: Annotated[int | None, Query(description="map version (default: the live map)")] = None,
) -> Response:
    """Lanelets from the lane graph with bounds typed from divider styles and boundaries, stop
    lines, crosswalks; an attachment ``csr-lanelet2-<version>.osm``."""
    box = parse_bbox(bbox)
    with session.begin():
        pinned = check_map_version(session, version, location="version")
        map_version = pinned if pinned is not None else vs.current_map_version(session)
        rows = vs.features_in_bbox(session, bbox_lonlat=box, map_version=pinned)
    features, unknown = _lonlat_features(rows)
    frame = LocalFrame(origin_lat=round((box[1] + box[3]) / 2, 6), origin_lon=round((box[0] + box[2]) / 2, 6))
    try:
        body, lanelet_map = export_lanelet2(features, frame=frame)
    except CsrError as exc:
        raise ApiError(
            422, "export", f"the map in this bbox cannot be exported: {exc}", location="query.bbox"
        ) from exc
    report = {**lanelet_map.report.as_dict(), "features_unknown_type": unknown, "map_version": map_version}
    headers = {
        "Content-Disposition": f'attachment; filename="csr-lanelet2-{map_version}.osm"',
        "X-Map-Version": str(map_version),
        "X-Lanelet2-Report": orjson.dumps(report).decode(),
    }
    return Response(body, media_type=OSM_XML, headers=headers)
