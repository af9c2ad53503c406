"""Trip geometry for the viewer: ``GET /v1/trips?bbox=&limit=`` (trips whose GNSS track touches a
bbox) and ``GET /v1/trips/{id}/track.geojson`` (the raw GNSS track and, once aligned, the trajectory
of the final poses, as two LineString features).

The bbox query is portable: candidates come from ``trip_tiles`` (a range scan of its ``(z, x, y)``
index at the service's tile zoom, the same on PostGIS and SQLite), then the exact test runs on the
stored track with shapely.
"""

from __future__ import annotations

import io
import math
from typing import Annotated, Any

import numpy as np
import shapely
from fastapi import APIRouter, Query, Response
from sqlalchemy import select

from services.api import answers
from services.api.deps import AnyRole, Ctx, ReadSessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.api.routes.trips import _iso_utc
from services.auth import may_read_trace
from services.db import repo
from services.db import versions as vs
from services.db.models import Trip, TripPoses, TripTile
from services.tiles.render import feature_collection

router = APIRouter(prefix="/v1/trips", tags=["trips"])

GEOJSON = "application/geo+json"
MAX_LIMIT = 1000
MAX_CANDIDATES = 20_000  # trip-tile rows read for one bbox query


def parse_bbox(text: str) -> tuple[float, float, float, float]:
    """``minlon,minlat,maxlon,maxlat`` degrees; 422 naming ``bbox`` when malformed."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise ApiError(422, "query", "bbox must be minlon,minlat,maxlon,maxlat (degrees)", location="bbox")
    west, south, east, north = values
    if not (-180 <= west <= east <= 180 and -90 <= south <= north <= 90):
        raise ApiError(422, "query", "bbox must have minlon <= maxlon and minlat <= maxlat", location="bbox")
    return west, south, east, north


def _tile_xy(lon: float, lat: float, zoom: int) -> tuple[int, int]:
    n = 2**zoom
    lat = max(-85.05112878, min(85.05112878, lat))
    x = int((lon + 180.0) / 360.0 * n)
    lat_r = math.radians(lat)
    y = int((1.0 - math.log(math.tan(lat_r) + 1.0 / math.cos(lat_r)) / math.pi) / 2.0 * n)
    return min(max(x, 0), n - 1), min(max(y, 0), n - 1)


def track_shape(value: Any) -> shapely.LineString | None:
    """The stored track (EWKT text on SQLite, EWKB from PostGIS) as a shapely LineString."""
    if value is None:
        return None
    if isinstance(value, str) and value.startswith("SRID="):
        return shapely.from_wkt(value.split(";", 1)[1])
    data = getattr(value, "data", value)  # GeoAlchemy2's WKBElement
    if isinstance(data, str):
        return shapely.from_wkb(bytes.fromhex(data))
    return shapely.from_wkb(bytes(data))


def trip_summary(trip: Trip) -> dict[str, Any]:
    return {
        "id": trip.id,
        "vehicle_id": trip.vehicle_id,
        "trip_id": trip.trip_id,
        "status": trip.status,
        "length_km": trip.length_km,
        "received_at": _iso_utc(trip.received_at),
    }


@router.get(
    "",
    responses={
        200: answers.answer(answers.TripsInBbox, "Trips whose GNSS track touches the bbox"),
        **errors({422: {"query": "`bbox` is not minlon,minlat,maxlon,maxlat (degrees)."}}),
    },
)
def trips_in_bbox(
    caller: AnyRole,
    ctx: Ctx,
    session: ReadSessionDep,
    bbox: Annotated[str, Query(description="minlon,minlat,maxlon,maxlat")],
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT)] = 100,
) -> dict[str, Any]:
    """Trips whose raw GNSS track touches the bbox, newest first (``truncated`` when over ``limit``);
    a vehicle key sees its own trips only."""
    west, south, east, north = parse_bbox(bbox)
    zoom = ctx.settings.tile_zoom
    x0, y0 = _tile_xy(west, north, zoom)
    x1, y1 = _tile_xy(east, south, zoom)
    query = select(TripTile.trip_pk).where(
        TripTile.z == zoom, TripTile.x.between(x0, x1), TripTile.y.between(y0, y1)
    )
    if caller.role == "vehicle":
        query = query.join(Trip, Trip.id == TripTile.trip_pk).where(Trip.vehicle_id == caller.vehicle_id)
    candidates = list(dict.fromkeys(session.scalars(query.limit(MAX_CANDIDATES))))
    box = shapely.box(west, south, east, north)
    found: list[Trip] = []
    for start in range(0, len(candidates), 500):
        for trip in session.scalars(select(Trip).where(Trip.id.in_(candidates[start : start + 500]))):
            line = track_shape(trip.track)
            if line is not None and line.intersects(box):
                found.append(trip)
    found.sort(key=lambda t: (t.received_at, t.id), reverse=True)
    return {"trips": [trip_summary(t) for t in found[:limit]], "truncated": len(found) > limit}


def _poses_line(arrays: bytes) -> tuple[list[list[float]], dict[str, Any]]:
    with np.load(io.BytesIO(arrays)) as npz:
        lat, lon = np.asarray(npz["lat"], float), np.asarray(npz["lon"], float)
        t = np.asarray(npz["t"], float) if "t" in npz.files else None
    keep = np.isfinite(lat) & np.isfinite(lon)
    coords = np.column_stack([lon[keep], lat[keep]]).round(vs.GEOJSON_DECIMALS).tolist()
    props: dict[str, Any] = {"n_points": len(coords)}
    if t is not None and keep.any():
        props["t_start"], props["t_end"] = float(t[keep][0]), float(t[keep][-1])
    return coords, props


@router.get(
    "/{trip_pk}/track.geojson",
    response_class=Response,
    responses={
        200: answers.geojson("The raw GNSS track and the aligned trajectory"),
        **errors(
            {
                403: {
                    "forbidden": "a vehicle key reading another vehicle's trip; a reader key when "
                    "`CSR_READER_SEES_TRACES` is false."
                },
                404: {"not_found": "no trip with this id."},
            }
        ),
    },
)
def trip_track(trip_pk: str, caller: AnyRole, ctx: Ctx, session: ReadSessionDep) -> Response:
    """FeatureCollection: ``kind: raw`` (GNSS fixes, once ingested) and ``kind: aligned`` (final
    poses, once aligned); each feature is left out until it exists."""
    trip = repo.get_trip(session, trip_pk=trip_pk)
    if trip is None:
        raise ApiError(404, "not_found", f"no trip {trip_pk!r}", location="id")
    may_read_trace(caller, trip.vehicle_id, reader_sees_traces=ctx.settings.reader_sees_traces)
    features: list[dict[str, Any]] = []
    line = track_shape(trip.track)
    if line is not None:
        coords = vs.geometry_json(line)["coordinates"]
        features.append(_feature(trip, "raw", coords, {"n_points": len(coords)}))
    poses = session.get(TripPoses, trip.id)
    if poses is not None:
        coords, props = _poses_line(poses.arrays)
        if len(coords) >= 2:
            features.append(
                _feature(
                    trip,
                    "aligned",
                    coords,
                    {**props, "job_id": poses.job_id, "created_at": _iso_utc(poses.created_at)},
                )
            )
    return Response(feature_collection(features, trip=trip_summary(trip)), media_type=GEOJSON)


def _feature(trip: Trip, kind: str, coords: list, props: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "Feature",
        "id": f"{trip.id}:{kind}",
        "geometry": {"type": "LineString", "coordinates": coords},
        "properties": {"trip": trip.id, "vehicle_id": trip.vehicle_id, "kind": kind, **props},
    }
