"""Contract section 2: every endpoint against every kind of caller, on both deployments."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import orjson
import pytest

from tests.integration.conftest import Deployment, unique_trip

pytestmark = pytest.mark.integration

CALLERS = ("none", "unknown", "revoked", "vehicle", "vehicle_other", "reader", "admin")


@dataclass
class World:
    keys: dict[str, str | None]
    trip_pk: str  # a trip of vehicle veh-a


@pytest.fixture(scope="module")
def world(deployment: Deployment) -> World:
    with deployment.admin() as http:

        def key(**body) -> dict[str, Any]:
            response = http.post("/v1/keys", json=body)
            assert response.status_code == 201, response.text
            return response.json()

        vehicle, other, reader, revoked = (
            key(role="vehicle", vehicle_id="veh-a"),
            key(role="vehicle", vehicle_id="veh-b"),
            key(role="reader"),
            key(role="reader"),
        )
        assert http.delete(f"/v1/keys/{revoked['id']}").status_code == 204
    trip = deployment.upload(unique_trip("veh-a"), key=vehicle["key"])
    assert trip.status_code == 202
    keys = {
        "none": None,
        "unknown": "csr_not-a-key",
        "revoked": revoked["key"],
        "vehicle": vehicle["key"],
        "vehicle_other": other["key"],
        "reader": reader["key"],
        "admin": deployment.admin_key,
    }
    return World(keys, trip.json()["id"])


BBOX = "8.39,49.0,8.41,49.02"
# endpoint -> (method, path, request keyword arguments); the tile 16/0/0 is always empty
REQUESTS: dict[str, tuple[str, str, dict[str, Any]]] = {
    "GET /healthz": ("GET", "/healthz", {}),
    "GET /metrics": ("GET", "/metrics", {}),
    "GET /v1/trips": ("GET", "/v1/trips", {"params": {"bbox": BBOX}}),
    "GET /v1/trips/{id}/poses": ("GET", "/v1/trips/{trip}/poses", {}),
    "GET /v1/trips/{id}/track.geojson": ("GET", "/v1/trips/{trip}/track.geojson", {}),
    "GET /v1/trips/{id}/upload": ("GET", "/v1/trips/{trip}/upload", {}),
    "DELETE /v1/vehicles/{id}/data": ("DELETE", "/v1/vehicles/veh-without-trips/data", {}),
    "GET /v1/trips/{id}": ("GET", "/v1/trips/{trip}", {}),
    "GET /v1/jobs/summary": ("GET", "/v1/jobs/summary", {}),
    "GET /v1/jobs": ("GET", "/v1/jobs", {}),
    "GET /v1/jobs/{id}": ("GET", "/v1/jobs/no-such-job", {}),
    "POST /v1/jobs/{id}/retry": ("POST", "/v1/jobs/no-such-job/retry", {}),
    "GET /v1/tiles/dirty": ("GET", "/v1/tiles/dirty", {}),
    "POST /v1/process": ("POST", "/v1/process", {}),
    "POST /v1/keys": ("POST", "/v1/keys", {"json": {"role": "reader"}}),
    "GET /v1/map": ("GET", "/v1/map", {"params": {"bbox": BBOX}}),
    "GET /v1/tiles/{z}/{x}/{y}.mvt": ("GET", "/v1/tiles/16/0/0.mvt", {}),
    "GET /v1/tiles/{z}/{x}/{y}.geojson": ("GET", "/v1/tiles/16/0/0.geojson", {}),
    "GET /v1/tiles.json": ("GET", "/v1/tiles.json", {}),
    "GET /v1/tiles/{z}/{x}/{y}/versions": ("GET", "/v1/tiles/16/0/0/versions", {}),
    "GET /v1/tiles/{z}/{x}/{y}/held-back": ("GET", "/v1/tiles/16/0/0/held-back", {}),
    "GET /v1/tiles/{z}/{x}/{y}/versions/{v}": ("GET", "/v1/tiles/16/0/0/versions/1", {}),
    "GET /v1/tiles/{z}/{x}/{y}/diff": ("GET", "/v1/tiles/16/0/0/diff", {"params": {"from": 1, "to": 2}}),
    "GET /v1/changes": ("GET", "/v1/changes", {}),
    "POST /v1/tiles/{z}/{x}/{y}/rollback": ("POST", "/v1/tiles/16/0/0/rollback", {"json": {"version": 1}}),
    "POST /v1/tiles/{z}/{x}/{y}/versions/{v}/approve": ("POST", "/v1/tiles/16/0/0/versions/1/approve", {}),
    "GET /v1/features/{id}": ("GET", "/v1/features/none", {}),
    "GET /v1/tiles/{z}/{x}/{y}/match-pairs": ("GET", "/v1/tiles/16/0/0/match-pairs", {}),
    "GET /v1/tiles/{z}/{x}/{y}/certificate": ("GET", "/v1/tiles/16/0/0/certificate", {}),
    "POST /v1/tiles/{z}/{x}/{y}/corrections": (
        "POST",
        "/v1/tiles/16/0/0/corrections",
        {"json": {"kind": "reject_pair", "pair_id": "none"}},
    ),
    "GET /v1/corrections": ("GET", "/v1/corrections", {}),
    "POST /v1/corrections/{id}/undo": ("POST", "/v1/corrections/none/undo", {}),
    "GET /v1/export/lanelet2": ("GET", "/v1/export/lanelet2", {"params": {"bbox": BBOX}}),
    "GET /viewer/": ("GET", "/viewer/", {}),
    "GET /ops/": ("GET", "/ops/", {}),
}


def _call(dep: Deployment, world: World, endpoint: str, caller: str):
    key = world.keys[caller]
    with dep.client(key) as http:
        if endpoint == "POST /v1/trips":
            return http.post(
                "/v1/trips",
                content=orjson.dumps(unique_trip("veh-a")),
                headers={"Content-Type": "application/json"},
            )
        if endpoint == "DELETE /v1/keys/{id}":
            with dep.admin() as admin:
                victim = admin.post("/v1/keys", json={"role": "reader"}).json()["id"]
            return http.delete(f"/v1/keys/{victim}")
        method, path, kwargs = REQUESTS[endpoint]
        return http.request(method, path.format(trip=world.trip_pk), **kwargs)


# fmt: off
#                              none  unknown revoked vehicle other  reader admin   (other: a vehicle key of another vehicle)
MATRIX = {
    "GET /healthz":                      (200, 200, 200, 200, 200, 200, 200),
    "GET /metrics":                      (401, 401, 401, 403, 403, 200, 200),
    "POST /v1/trips":                    (401, 401, 401, 202, 403, 403, 202),
    "GET /v1/trips":                     (401, 401, 401, 200, 200, 200, 200),  # a vehicle: its own trips
    "GET /v1/trips/{id}":                (401, 401, 401, 200, 403, 200, 200),
    "GET /v1/trips/{id}/poses":          (401, 401, 401, 409, 403, 409, 409),
    "GET /v1/trips/{id}/track.geojson":  (401, 401, 401, 200, 403, 200, 200),
    "GET /v1/trips/{id}/upload":         (401, 401, 401, 200, 403, 200, 200),
    "DELETE /v1/vehicles/{id}/data":     (401, 401, 401, 403, 403, 403, 200),
    "GET /v1/jobs/summary":              (401, 401, 401, 403, 403, 200, 200),
    "GET /v1/jobs":                      (401, 401, 401, 403, 403, 200, 200),
    "GET /v1/jobs/{id}":                 (401, 401, 401, 403, 403, 404, 404),
    "POST /v1/jobs/{id}/retry":          (401, 401, 401, 403, 403, 403, 404),
    "GET /v1/tiles/dirty":               (401, 401, 401, 403, 403, 200, 200),
    "POST /v1/process":                  (401, 401, 401, 403, 403, 403, 202),
    "POST /v1/keys":                     (401, 401, 401, 403, 403, 403, 201),
    "DELETE /v1/keys/{id}":              (401, 401, 401, 403, 403, 403, 204),
    "GET /v1/map":                       (401, 401, 401, 403, 403, 200, 200),
    "GET /v1/tiles/{z}/{x}/{y}.mvt":     (401, 401, 401, 403, 403, 204, 204),
    "GET /v1/tiles/{z}/{x}/{y}.geojson": (401, 401, 401, 403, 403, 204, 204),
    "GET /v1/tiles.json":                (401, 401, 401, 403, 403, 200, 200),
    "GET /v1/tiles/{z}/{x}/{y}/versions":     (401, 401, 401, 403, 403, 404, 404),
    "GET /v1/tiles/{z}/{x}/{y}/held-back":    (401, 401, 401, 403, 403, 404, 404),
    "GET /v1/tiles/{z}/{x}/{y}/versions/{v}": (401, 401, 401, 403, 403, 404, 404),
    "GET /v1/tiles/{z}/{x}/{y}/diff":    (401, 401, 401, 403, 403, 404, 404),
    "GET /v1/changes":                   (401, 401, 401, 403, 403, 200, 200),
    "POST /v1/tiles/{z}/{x}/{y}/rollback":             (401, 401, 401, 403, 403, 403, 404),
    "POST /v1/tiles/{z}/{x}/{y}/versions/{v}/approve": (401, 401, 401, 403, 403, 403, 404),
    "GET /v1/features/{id}":             (401, 401, 401, 403, 403, 404, 404),
    "GET /v1/tiles/{z}/{x}/{y}/match-pairs":  (401, 401, 401, 403, 403, 200, 200),
    "GET /v1/tiles/{z}/{x}/{y}/certificate":  (401, 401, 401, 403, 403, 200, 200),
    "POST /v1/tiles/{z}/{x}/{y}/corrections": (401, 401, 401, 403, 403, 403, 404),
    "GET /v1/corrections":               (401, 401, 401, 403, 403, 200, 200),
    "POST /v1/corrections/{id}/undo":    (401, 401, 401, 403, 403, 403, 404),
    "GET /v1/export/lanelet2":           (401, 401, 401, 403, 403, 200, 200),
    "GET /viewer/":                      (200, 200, 200, 200, 200, 200, 200),
    "GET /ops/":                         (200, 200, 200, 200, 200, 200, 200),
}
# fmt: on
CASES = [
    (endpoint, caller, expected[i])
    for endpoint, expected in MATRIX.items()
    for i, caller in enumerate(CALLERS)
]


def _generic(path: str) -> str:
    for name in ("{trip_pk}", "{key_id}", "{job_id}", "{feature_id}", "{correction_id}", "{vehicle_id}"):
        path = path.replace(name, "{id}")
    return path


@pytest.fixture(scope="module")
def documented(deployment: Deployment) -> dict[str, dict[str, Any]]:
    """Each endpoint's operation in the served OpenAPI document."""
    with deployment.admin() as http:
        spec = http.get("/openapi.json").json()
    return {
        f"{method.upper()} {_generic(path)}": operation
        for path, item in spec["paths"].items()
        for method, operation in item.items()
    }


def test_the_matrix_names_every_route(documented: dict[str, dict[str, Any]]):
    assert set(documented) == set(MATRIX)


@pytest.mark.parametrize("endpoint,caller,status", CASES, ids=[f"{e}-{c}" for e, c, _ in CASES])
def test_role_matrix(
    deployment: Deployment,
    world: World,
    documented: dict[str, dict[str, Any]],
    endpoint: str,
    caller: str,
    status: int,
):
    response = _call(deployment, world, endpoint, caller)
    assert response.status_code == status, response.text
    # the OpenAPI document names the answer and whether a key is needed
    assert str(status) in documented[endpoint]["responses"]
    assert (documented[endpoint]["security"] == []) == (MATRIX[endpoint][0] != 401)
    if status in (401, 403):
        body = response.json()
        assert body["error"] == {401: "unauthorized", 403: "forbidden"}[status] and body["message"]
    if status == 401:
        assert response.headers["www-authenticate"] == "Bearer"


def test_keys_are_stored_hashed(deployment: Deployment):
    with deployment.admin() as http:
        created = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-h"}).json()
    stored = deployment.rows(
        "SELECT key_sha256, role, vehicle_id FROM api_keys WHERE id = :i", i=created["id"]
    )
    assert len(stored) == 1
    digest, role, vehicle_id = stored[0]
    assert created["key"] not in digest and len(digest) == 64
    assert (role, vehicle_id) == ("vehicle", "veh-h")
    dump = " ".join(str(v) for row in deployment.rows("SELECT * FROM api_keys") for v in row)
    assert created["key"] not in dump and deployment.admin_key not in dump


@pytest.mark.parametrize(
    "body", [{"role": "vehicle"}, {"role": "reader", "vehicle_id": "v"}, {"role": "root"}, {}]
)
def test_invalid_key_requests_are_422(deployment: Deployment, body: dict):
    with deployment.admin() as http:
        response = http.post("/v1/keys", json=body)
    assert response.status_code == 422
    assert response.json()["error"] == "invalid_request"


def test_revoked_key_stops_working_at_once(deployment: Deployment):
    with deployment.admin() as http:
        created = http.post("/v1/keys", json={"role": "reader"}).json()
        with deployment.client(created["key"]) as reader:
            assert reader.get("/v1/jobs/summary").status_code == 200
            assert http.delete(f"/v1/keys/{created['id']}").status_code == 204
            assert reader.get("/v1/jobs/summary").status_code == 401
        assert http.delete(f"/v1/keys/{created['id']}").status_code == 404
