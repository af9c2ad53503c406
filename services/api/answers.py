"""The JSON answers of the routes, as pydantic models for the OpenAPI document only: the routes build
their bodies as dicts (``trip_json``, ``job_json``, ...), and these models describe them
(``responses={200: answer(Model, ...)}``). Each model allows more fields than it names, so that a
field added to a body never makes the document untrue; tests validate real bodies against them."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class Answer(BaseModel):
    model_config = ConfigDict(extra="allow")


def answer(model: type[BaseModel], description: str, **extra: Any) -> dict[str, Any]:
    """A ``responses=`` entry of a JSON answer described by ``model``."""
    return {"model": model, "description": description, **extra}


LOCATION_HEADER = {"Location": {"description": "the URL of what was created", "schema": {"type": "string"}}}


class Health(Answer):
    status: Literal["ok", "degraded", "error"] = Field(
        description="`degraded`: the broker is unreachable (uploads are still accepted)"
    )
    database: str = Field(description="the database's dialect, or why it is unreachable (503)")
    jobs: Literal["embedded", "distributed"] | None = None
    broker: Literal["ok", "unreachable"] | None = Field(None, description="the distributed deployment only")


class Trip(Answer):
    """A trip as stored: the upload's answer; ``GET /v1/trips/{id}`` adds its tiles, reconstruction
    and quality."""

    id: str
    vehicle_id: str
    trip_id: str
    status: str = Field(description="received, ingested, aligned or failed")
    schema_version: str
    started_at: str
    n_frames: int
    body_bytes: int
    received_at: str
    updated_at: str
    length_km: float | None
    error: str | None
    tiles: list[str] | None = Field(None, description="`z/x/y` of the tiles the trip crosses")
    tiles_pending: int | None = Field(None, description="of those, the tiles not yet processed")
    reconstruction: dict[str, Any] | None = Field(
        None, description="the single-trip reconstruction's summary; null until ingested"
    )
    quality: dict[str, Any] | None = Field(
        None, description="the trip's poses tested against its own GNSS; null until ingested"
    )


class Pose(Answer):
    t: float
    lat: float
    lon: float
    heading_deg: float


class Poses(Answer):
    id: str
    frames: list[Pose]


class TripSummary(Answer):
    id: str
    vehicle_id: str
    trip_id: str
    status: str
    length_km: float | None
    received_at: str


class TripsInBbox(Answer):
    trips: list[TripSummary]
    truncated: bool


class KeyCreated(Answer):
    id: str
    key: str = Field(description="the secret: shown only in this answer")
    role: Literal["vehicle", "reader", "admin"]
    vehicle_id: str | None


class JobsSummary(Answer):
    queued: int
    running: int
    failed: int
    dirty_tiles: int


class ScheduledJob(Answer):
    job_id: str
    tile: str


class Processed(Answer):
    scheduled: int
    jobs: list[ScheduledJob]


class Job(Answer):
    id: str
    kind: str
    queue: str
    subject: str
    state: str
    attempts: int
    error: str | None
    created_at: str | None
    dispatched_at: str | None
    started_at: str | None
    finished_at: str | None
    duration_s: float | None
    lease_expires_at: str | None
    retried_by: str | None


class Jobs(Answer):
    jobs: list[Job]
    queues: dict[str, dict[str, int]] = Field(description="job counts per queue and state")


class DirtyTile(Answer):
    tile: str
    z: int
    x: int
    y: int
    first_marked_at: str | None
    last_marked_at: str | None
    job_id: str | None
    job_state: str | None
    pending_trips: int


class DirtyTiles(Answer):
    tiles: list[DirtyTile]


class Correction(Answer):
    id: str
    tile: str
    kind: Literal["reject_pair", "add_pair"]
    payload: dict[str, Any]
    author_key_id: str
    created_at: str
    job_id: str | None
    result_version_id: int | None
    undone_at: str | None
    undone_by: str | None


class Corrections(Answer):
    corrections: list[Correction]


class Changes(Answer):
    since: int
    next: int
    map_version: int
    more: bool
    changes: list[dict[str, Any]]


class TileHistory(Answer):
    tile: str
    latest_version: int
    live_version: int | None
    versions: list[dict[str, Any]]
    next: str | None = Field(description="the URL of the next page; null on the last one")


class MatchPairs(Answer):
    tile: str
    match_pairs: list[dict[str, Any]]
    next: str | None = Field(description="the URL of the next page; null on the last one")


class TileCertificate(Answer):
    """What a tile's map promises about its lateral error (docs/tiles.md, "Accuracy certificate")."""

    tile: str = Field(description="z/x/y")
    map_version: int | None = Field(description="the map version certified (`v`), or null: the live map")
    expected_absolute_error_m: float = Field(
        description="RMS of the elements' `sigma_abs_m`, weighted by their length in the tile: the expected "
        "1-sigma lateral error against the true (GNSS) frame"
    )
    expected_relative_error_m: float = Field(
        description="RMS of the elements' `uncertainty_m`, length-weighted: the error left after a global alignment"
    )
    n_features: int = Field(description="elements certified (those with a `sigma_abs_m`)")
    trips: int = Field(description="distinct trips merged into the tile's versions")
    passes_median: float = Field(description="median support trips per element")
    target_m: float = Field(description="the absolute error the tile is measured against (setting)")
    passes_needed: int | None = Field(
        description="more passes per element until `expected_absolute_error_m` reaches `target_m` (1/sqrt(n) "
        "model); 0 when it does, null when the relative error alone exceeds the target or the tile is empty"
    )


class Feature(Answer):
    """A GeoJSON Feature (RFC 7946)."""

    type: Literal["Feature"]
    geometry: dict[str, Any] | None
    properties: dict[str, Any] | None


class FeatureCollection(Answer):
    """A GeoJSON FeatureCollection (RFC 7946), with the route's own members (``map_version``,
    ``tile``, ...)."""

    type: Literal["FeatureCollection"]
    features: list[Feature]


def geojson(description: str, model: type[BaseModel] = FeatureCollection) -> dict[str, Any]:
    """A ``responses=`` entry of a GeoJSON answer (``application/geo+json``)."""
    return {
        "description": description,
        "content": {"application/geo+json": {"schema": {"$ref": f"#/components/schemas/{model.__name__}"}}},
    }


# Models that ``geojson`` refers to by name: build_document adds them to the components
GEOJSON_MODELS: tuple[type[BaseModel], ...] = (FeatureCollection, Feature)
