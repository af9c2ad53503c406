"""``GET /v1/tiles/{z}/{x}/{y}/held-back`` on PostGIS: the lines a merge held back from a version
(``TopologyResult.suppressed``), read back from the version's topology state.

The scenario is planted at the level of the merge's input, as ``tests/unit/test_topology_ghosts.py``
plants it at the topology's: four trips aligned in one tile (``trip_tile_alignments`` rows, what
``align_tile`` stores) drive a straight road and see its two lane dividers; one of them also sees
a ghost lane divider a lane further out on one side and a ghost road boundary on the other. The
real merge job (``compute_merge_tile`` + ``persist_merge_tile``) fuses them into version 1 and
holds both ghosts back (the three other trips drove alongside without seeing them); the endpoint
must give back exactly the lines that version's ``quality["held_back"]`` counts."""

from __future__ import annotations

import io
import secrets
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import mercantile
import numpy as np
import pytest
from shapely.geometry import shape

from csr_core.types import DividerStyle, ElementNoise, ElementType, TripInstance
from services.db import versions as vs
from services.db.models import TileVersion, Trip, TripTileAlignment
from services.reconstructions import instance_json, noise_json
from services.settings import Settings
from services.tile_frames import tile_frame
from tests.integration.conftest import PgDatabases
from tests.integration.test_tiles import Tiled, start_tiled
from workers import tile_jobs

pytestmark = pytest.mark.integration

LON, LAT = 8.43, 49.01  # Karlsruhe, east of test_tiles' tiles
TILE = mercantile.tile(LON, LAT, 16)
ROAD_LENGTH_M = 200.0  # well inside the tile (~400 m wide at this latitude)
DIVIDER_Y_M = 1.75  # the real dividers, either side of the trips' path
GHOST_DIVIDER_Y_M = 5.25  # one trip's ghost divider, a lane further out (north)
GHOST_BOUNDARY_Y_M = -5.25  # and its ghost road boundary (south)
N_TRIPS = 4  # one sees the ghosts; three drive alongside without (SUPPRESS_MIN_PASSING = 3)
NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}


@dataclass
class Planted:
    """The tile with the planted ghosts, its version 1, and the frame the road was laid out in."""

    tile: mercantile.Tile
    version: int
    quality: dict
    road_origin_xy_m: np.ndarray  # the road's west end in the tile frame (metres)


@pytest.fixture(scope="module")
def tiled(tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Tiled]:
    """A PostGIS deployment of this module's own (API only: the merge runs in the test)."""
    yield from start_tiled("distributed", tmp_path_factory.mktemp("held-back"), pg, shared_redis_url)


def _line_xy_m(
    origin_xy_m: np.ndarray, y_m: float, x0_m: float = 0.0, x1_m: float = ROAD_LENGTH_M
) -> np.ndarray:
    """A straight east-west line ``(N, 2)`` at ``y_m`` north of the road, metre spacing, tile frame."""
    x_m = np.arange(x0_m, x1_m + 1e-9, 1.0)
    return origin_xy_m + np.column_stack([x_m, np.full_like(x_m, y_m)])


def _npz(**arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    # mypy checks the **arrays values against allow_pickle: bool too (no key is named so)
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def _plant_aligned_trips(tiled: Tiled, tile: mercantile.Tile) -> np.ndarray:
    """Four aligned trips of ``tile`` as ``align_tile`` stores them; returns the road's origin (m)."""
    frame = tile_frame(tile.z, tile.x, tile.y)
    centre_xy_m = frame.to_local(np.array([mercantile.ul(tile.x + 0.5, tile.y + 0.5, tile.z)]))[0]
    origin_xy_m = centre_xy_m - np.array([ROAD_LENGTH_M / 2, 0.0])
    path_xy_m = _line_xy_m(origin_xy_m, 0.0)
    poses_xyyaw = np.column_stack([path_xy_m, np.zeros(len(path_xy_m))])
    real = [
        TripInstance(ElementType.LANE_DIVIDER, _line_xy_m(origin_xy_m, y), DividerStyle.SOLID, 10)
        for y in (DIVIDER_Y_M, -DIVIDER_Y_M)
    ]
    ghosts = [
        TripInstance(
            ElementType.LANE_DIVIDER,
            _line_xy_m(origin_xy_m, GHOST_DIVIDER_Y_M, 60.0, 140.0),
            DividerStyle.SOLID,
            10,
        ),
        TripInstance(
            ElementType.ROAD_BOUNDARY, _line_xy_m(origin_xy_m, GHOST_BOUNDARY_Y_M, 50.0, 150.0), None, 10
        ),
    ]
    with tiled.sessions.begin() as session:
        for k in range(N_TRIPS):
            trip = Trip(
                id=f"held-{secrets.token_hex(6)}",
                vehicle_id="veh-h",
                trip_id=f"t{k}",
                content_sha256="0" * 64,
                status="aligned",
                schema_version="1.0",
                started_at=f"2024-05-0{k + 1}T08:00:00Z",
                n_frames=len(poses_xyyaw),
                body_bytes=1,
                json_bytes=1,
            )
            session.add(trip)
            session.flush()
            instances = real + ghosts if k == 0 else real
            session.add(
                TripTileAlignment(
                    trip_pk=trip.id,
                    z=tile.z,
                    x=tile.x,
                    y=tile.y,
                    job_id="job-align-test",
                    origin_lat=frame.origin_lat,
                    origin_lon=frame.origin_lon,
                    arrays=_npz(
                        frame_indices=np.arange(len(poses_xyyaw), dtype=np.int32),
                        poses_xyyaw=poses_xyyaw,
                        weights=np.ones(len(poses_xyyaw), np.float32),
                        residuals_m=np.zeros(len(poses_xyyaw), np.float32),
                    ),
                    instances=[instance_json(i) for i in instances],
                    noise=noise_json(NOISE),
                    failed_reason=None,
                )
            )
    return origin_xy_m


@pytest.fixture(scope="module")
def planted(tiled: Tiled) -> Planted:
    """Version 1 of the tile, made by the real merge job from the planted trips."""
    origin_xy_m = _plant_aligned_trips(tiled, TILE)
    result = tile_jobs.compute_merge_tile(tiled.sessions, Settings(), TILE.z, TILE.x, TILE.y)
    assert not result.nothing_to_do and result.state is not None
    with tiled.sessions.begin() as session:
        tile_jobs.persist_merge_tile(session, "job-merge-test", TILE.z, TILE.x, TILE.y, result)
    with tiled.sessions() as session:
        version = vs.latest_version(session, z=TILE.z, x=TILE.x, y=TILE.y)
        assert version is not None
        return Planted(TILE, version.version, dict(version.quality), origin_xy_m)


def _url(tile: mercantile.Tile, **params) -> str:
    query = "&".join(f"{k}={v}" for k, v in params.items())
    return f"/v1/tiles/{tile.z}/{tile.x}/{tile.y}/held-back" + (f"?{query}" if query else "")


def test_held_back_lines_are_the_ones_the_version_counts(tiled: Tiled, planted: Planted):
    # the scenario held something back, of two types (else the equality below proves little)
    assert planted.quality["held_back"] == {"lane_divider": 1, "road_boundary": 1}, planted.quality
    with tiled.http() as http:
        answer = http.get(_url(planted.tile))
        assert answer.status_code == 200, answer.text
        assert answer.headers["content-type"] == "application/geo+json"
        doc = answer.json()
        assert doc["type"] == "FeatureCollection"
        assert (doc["tile"], doc["version"]) == (f"{TILE.z}/{TILE.x}/{TILE.y}", planted.version)
        # the version's counts, as the history endpoint serves them, agree with the geometry
        history = http.get(f"/v1/tiles/{TILE.z}/{TILE.x}/{TILE.y}/versions").raise_for_status().json()
        stored = history["versions"][-1]["quality"]["held_back"]
        assert Counter(f["properties"]["type"] for f in doc["features"]) == Counter(stored)
        assert all(f["properties"]["status"] == "held_back" for f in doc["features"])
        assert all(f["properties"]["passed_trips"] == N_TRIPS - 1 for f in doc["features"])
        # and the pinned version gives the same lines
        pinned = http.get(_url(planted.tile, version=planted.version))
        assert pinned.status_code == 200 and pinned.json() == doc
        assert "immutable" in pinned.headers["cache-control"]
        # none of them is in the published version
        published = http.get(f"/v1/tiles/{TILE.z}/{TILE.x}/{TILE.y}/versions/{planted.version}").json()
    held_ids = {f["id"] for f in doc["features"]}
    assert held_ids and not held_ids & {f["id"] for f in published["features"]}
    # the two real dividers and the centreline derived between them (the lane the trips drove); no
    # lane is derived beside the held-back ghost divider
    assert Counter(f["properties"]["type"] for f in published["features"]) == {
        "lane_divider": 2,
        "centerline": 1,
    }
    (centre,) = [f for f in published["features"] if f["properties"]["type"] == "centerline"]
    assert (
        centre["properties"]["derived"] == "bounding_lines" and centre["properties"]["direction"] == "driven"
    )

    # each held-back line is where its ghost was planted (tile frame, metres north of the road)
    frame = tile_frame(TILE.z, TILE.x, TILE.y)
    planted_y_m = {"lane_divider": GHOST_DIVIDER_Y_M, "road_boundary": GHOST_BOUNDARY_Y_M}
    for f in doc["features"]:
        xy_m = frame.to_local(np.asarray(shape(f["geometry"]).coords)) - planted.road_origin_xy_m
        assert np.allclose(xy_m[:, 1], planted_y_m[f["properties"]["type"]], atol=0.3), (f["id"], xy_m[:, 1])


def test_unknown_tile_and_unknown_version_are_404_naming_them(tiled: Tiled, planted: Planted):
    empty = mercantile.Tile(TILE.x + 5, TILE.y, 16)
    with tiled.http() as http:
        no_tile = http.get(_url(empty))
        assert no_tile.status_code == 404
        assert no_tile.json()["error"] == "not_found"
        assert f"tile 16/{empty.x}/{empty.y} has no versions" in no_tile.json()["message"]
        no_version = http.get(_url(planted.tile, version=planted.version + 1))
        assert no_version.status_code == 404
        assert no_version.json()["location"] == "query.version"
        assert f"has no version {planted.version + 1}" in no_version.json()["message"]
        assert http.get(_url(planted.tile, version=0)).status_code == 422
        assert http.get("/v1/tiles/16/0/70000/held-back").status_code == 422  # y beyond the zoom


def test_a_version_without_a_readable_state_is_409(tiled: Tiled):
    tile = mercantile.Tile(TILE.x + 3, TILE.y, 16)
    frame = tile_frame(tile.z, tile.x, tile.y)
    for state in (None, b"not a topology state"):
        with tiled.sessions() as session:
            head = vs.tile_head(session, z=tile.z, x=tile.x, y=tile.y)
            latest = head.latest_version if head else None
        with tiled.sessions.begin() as session:
            written: TileVersion = vs.write_tile_version(
                session,
                z=tile.z,
                x=tile.x,
                y=tile.y,
                features=[],
                reason="merge",
                job_id="job-test",
                trips=[],
                corrections=[],
                quality={},
                origin_lat=frame.origin_lat,
                origin_lon=frame.origin_lon,
                state=state,
                publish=True,
                expected_latest=latest,
            )
            number = written.version
        with tiled.http() as http:
            answer = http.get(_url(tile, version=number))
        assert answer.status_code == 409, answer.text
        assert answer.json()["error"] == "state_unavailable"
        assert f"v{number} has no readable topology state" in answer.json()["message"]


def test_reading_held_back_lines_needs_a_reader_key(tiled: Tiled, planted: Planted):
    with tiled.dep.client() as anonymous:
        assert anonymous.get(_url(planted.tile)).status_code == 401
    with tiled.http(tiled.vehicle) as vehicle:
        refused = vehicle.get(_url(planted.tile))
        assert refused.status_code == 403 and refused.json()["error"] == "forbidden"
    with tiled.dep.admin() as admin:
        assert admin.get(_url(planted.tile)).status_code == 200
