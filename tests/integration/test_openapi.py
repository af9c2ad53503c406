"""The served OpenAPI document: Redocly's recommended lint finds nothing in it, and the error and
answer bodies it documents are the ones the service sends (real answers of both deployments,
validated against the document's schemas with jsonschema)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import orjson
import pytest

from tests.integration.conftest import REPO, Deployment, example_doc, unique_trip
from tests.openapi_check import response_schema

pytestmark = pytest.mark.integration

REDOCLY = REPO / "services" / "web" / "node_modules" / ".bin" / "redocly"
CONFIG = REPO / "redocly.yaml"


@pytest.fixture(scope="module")
def served(deployment: Deployment) -> dict[str, Any]:
    with deployment.client() as http:
        response = http.get("/openapi.json")
    assert response.status_code == 200
    return response.json()


@pytest.fixture(scope="module")
def keys(deployment: Deployment) -> dict[str, str]:
    with deployment.admin() as http:
        vehicle = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-oa"}).json()["key"]
        reader = http.post("/v1/keys", json={"role": "reader"}).json()["key"]
    return {"vehicle": vehicle, "reader": reader, "admin": deployment.admin_key}


def test_redocly_lint_finds_no_problem(served: dict[str, Any], tmp_path: Path):
    assert REDOCLY.exists(), f"{REDOCLY} is missing: (cd services/web && npm ci)"
    document = tmp_path / "openapi.json"
    document.write_bytes(orjson.dumps(served))
    run = subprocess.run(
        [str(REDOCLY), "lint", str(document), "--config", str(CONFIG), "--format", "json"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    report = json.loads(run.stdout)
    problems = [
        (p["ruleId"], p["severity"], p["message"], p["location"][0]["pointer"]) for p in report["problems"]
    ]
    assert report["totals"]["errors"] == 0, problems
    assert report["totals"]["warnings"] == 0, problems
    assert run.returncode == 0, run.stderr


def _upload(dep: Deployment, key: str, body: bytes, content_type: str = "application/json"):
    with dep.client(key) as http:
        return http.post("/v1/trips", content=body, headers={"Content-Type": content_type})


def test_error_answers_are_the_documented_ones(
    deployment: Deployment, served: dict[str, Any], keys: dict[str, str]
):
    trip = deployment.upload(unique_trip("veh-oa"), key=keys["vehicle"])
    assert trip.status_code == 202
    trip_pk = trip.json()["id"]
    bad_lat = example_doc(trip_id="t-bad-lat")
    bad_lat["frames"][1]["gnss"]["lat"] = 91.0
    # (documented method and path, key, the request, the status it answers)
    cases = [
        ("GET", "/v1/jobs/summary", None, lambda h: h.get("/v1/jobs/summary"), 401),
        ("GET", "/metrics", "vehicle", lambda h: h.get("/metrics"), 403),
        ("GET", "/v1/map", "reader", lambda h: h.get("/v1/map", params={"bbox": "8.4,49,nope,49.1"}), 422),
        ("GET", "/v1/trips/{trip_pk}", "reader", lambda h: h.get("/v1/trips/no-such-trip"), 404),
        ("GET", "/v1/trips/{trip_pk}/poses", "reader", lambda h: h.get(f"/v1/trips/{trip_pk}/poses"), 409),
        ("GET", "/v1/tiles/{z}/{x}/{y}.mvt", "reader", lambda h: h.get("/v1/tiles/3/8/0.mvt"), 422),
        ("GET", "/healthz", None, lambda h: h.get("/healthz", params={"probe": "a\x00b"}), 422),
        ("DELETE", "/v1/keys/{key_id}", "admin", lambda h: h.delete("/v1/keys/key_none"), 404),
        ("POST", "/v1/keys", "admin", lambda h: h.post("/v1/keys", json={"role": "root"}), 422),
        (
            "GET",
            "/v1/map",
            "reader",
            lambda h: h.get("/v1/map", headers={"Accept-Encoding": "identity;q=0, compress"}),
            406,
        ),
    ]
    for method, path, who, call, status in cases:
        with deployment.client(keys[who] if who else None) as http:
            response = call(http)
        assert response.status_code == status, (method, path, response.text)
        errors = sorted(
            e.message for e in response_schema(served, method, path, status).iter_errors(response.json())
        )
        assert errors == [], (method, path, status, response.json())
    uploads = [
        (_upload(deployment, keys["vehicle"], b"{not json"), 400),
        (_upload(deployment, keys["vehicle"], orjson.dumps(unique_trip("veh-other"))), 403),
        (_upload(deployment, keys["vehicle"], b"{}", content_type="text/plain"), 415),
        (_upload(deployment, keys["admin"], orjson.dumps(bad_lat)), 422),
    ]
    for response, status in uploads:
        assert response.status_code == status, response.text
        check = response_schema(served, "POST", "/v1/trips", status)
        assert sorted(e.message for e in check.iter_errors(response.json())) == [], response.json()


def test_the_body_of_an_undocumented_code_fails_the_documented_schema(served: dict[str, Any]):
    """The check above can fail: a real 404 body under another code is not what the document says."""
    check = response_schema(served, "GET", "/v1/trips/{trip_pk}", 404)
    assert not check.is_valid({"error": "gone", "location": "id", "message": "no trip 'x'"})


CERTIFICATE = "/v1/tiles/{z}/{x}/{y}/certificate"


def test_answers_are_the_documented_ones(
    deployment: Deployment, served: dict[str, Any], keys: dict[str, str]
):
    doc = unique_trip("veh-oa")
    first = deployment.upload(doc, key=keys["vehicle"])
    again = deployment.upload(doc, key=keys["vehicle"])
    assert (first.status_code, again.status_code) == (202, 200)
    trip_pk = first.json()["id"]
    with deployment.client(keys["reader"]) as http:
        answers = [
            ("POST", "/v1/trips", 202, first),
            ("POST", "/v1/trips", 200, again),
            ("GET", "/v1/trips/{trip_pk}", 200, http.get(f"/v1/trips/{trip_pk}")),
            ("GET", "/v1/jobs/summary", 200, http.get("/v1/jobs/summary")),
            ("GET", "/v1/jobs", 200, http.get("/v1/jobs")),
            ("GET", "/v1/tiles/dirty", 200, http.get("/v1/tiles/dirty")),
            ("GET", "/v1/changes", 200, http.get("/v1/changes")),
            ("GET", "/v1/corrections", 200, http.get("/v1/corrections")),
            ("GET", "/v1/trips", 200, http.get("/v1/trips", params={"bbox": "8.3,48.9,8.5,49.1"})),
            ("GET", "/healthz", 200, http.get("/healthz")),
            ("GET", CERTIFICATE, 200, http.get("/v1/tiles/16/34000/22000/certificate")),
            ("GET", CERTIFICATE, 422, http.get("/v1/tiles/16/70000/0/certificate")),
            ("GET", CERTIFICATE, 404, http.get("/v1/tiles/16/0/0/certificate", params={"v": 10**9})),
        ]
    with deployment.admin() as http:
        answers.append(("POST", "/v1/keys", 201, http.post("/v1/keys", json={"role": "reader"})))
        answers.append(("POST", "/v1/process", 202, http.post("/v1/process")))
    for method, path, status, response in answers:
        assert response.status_code == status, (method, path, response.text)
        check = response_schema(served, method, path, status)
        assert sorted(e.message for e in check.iter_errors(response.json())) == [], (method, path)
    with deployment.client(keys["reader"]) as http:
        track = http.get(f"/v1/trips/{trip_pk}/track.geojson")
        metrics = http.get("/metrics")
    assert track.headers["content-type"] == "application/geo+json"
    check = response_schema(served, "GET", "/v1/trips/{trip_pk}/track.geojson", 200, "application/geo+json")
    assert sorted(e.message for e in check.iter_errors(track.json())) == []
    assert (
        metrics.headers["content-type"] in served["paths"]["/metrics"]["get"]["responses"]["200"]["content"]
    )
