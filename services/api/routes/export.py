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


def _lonlat_features(rows: list[vs.MapFeature]) -> tuple[list[LonLatFeature], int]:
    """Service rows -> core records (multi-geometries split), one per feature id (a feature read
    from two tile versions is exported once, from the newer), with its provenance in
    ``map_version`` (the map version that made the row) and ``tile_version``; count of rows of
    unknown type."""
    newest: dict[str, vs.MapFeature] = {}
    for row in rows:
        old = newest.get(row.feature.feature_id)
        if old is None or row.tile_version_id > old.tile_version_id:
            newest[row.feature.feature_id] = row
    out, unknown = [], 0
    for row in newest.values():
        f = row.feature
        props = {**(f.properties or {}), "map_version": row.tile_version_id, "tile_version": row.version}
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
            out.append(LonLatFeature(etype, lonlat, style, f.feature_id, props))
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
    version: Annotated[
        int | None,
        Query(description="map version (default: the live map)", json_schema_extra={"minimum": 0}),
    ] = None,
) -> Response:
    """Lanelets from the lane graph with bounds typed from divider styles and boundaries, stop
    lines (with their regulatory elements), crosswalks; the whole bbox across its tiles, each
    feature once; ``version`` pins the map version as ``GET /v1/map?version=`` reads it. Nodes
    carry ``csr:sigma_m`` and ``csr:sigma_abs_m``, lines and lanelets ``csr:trips`` and ``csr:version``. An attachment
    ``csr-lanelet2-<version>.osm``."""
    box = parse_bbox(bbox)
    with session.begin():
        pinned = check_map_version(session, version, location="version")
        map_version = pinned if pinned is not None else vs.current_map_version(session)
        versions = vs.contributing_versions(session, bbox_lonlat=box, map_version=pinned)
        rows = vs.map_features(session, bbox_lonlat=box, versions=versions)
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
