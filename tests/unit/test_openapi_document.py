"""The OpenAPI document (services.api.openapi) is valid OpenAPI 3.1 and says what the routes do:
who may call them, the error body, the upload body and the media types."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import orjson
import pytest
from openapi_spec_validator import validate

from services.api.app import create_app
from services.settings import Settings
from tests.openapi_check import validator

pytestmark = pytest.mark.unit

EXAMPLE = Path(__file__).resolve().parents[1] / "data" / "example-trip.json"
METHODS = ("get", "put", "post", "delete", "patch", "head", "options")


@pytest.fixture(scope="module")
def doc(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The document of an app that is not started (no database is needed to describe it)."""
    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("openapi")))
    return app.openapi()


def operations(doc: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [
        (m.upper(), path, op) for path, item in doc["paths"].items() for m, op in item.items() if m in METHODS
    ]


def test_the_document_is_valid_openapi_3_1(doc: dict[str, Any]):
    assert doc["openapi"].startswith("3.1")
    validate(doc)


def test_every_operation_states_its_security(doc: dict[str, Any]):
    scheme = doc["components"]["securitySchemes"]["bearerAuth"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    public = {f"{m} {p}" for m, p, op in operations(doc) if op["security"] == []}
    assert public == {"GET /healthz", "GET /viewer/", "GET /ops/"}
    for method, path, op in operations(doc):
        if f"{method} {path}" in public:
            assert "401" not in op["responses"], f"{method} {path}"
            continue
        assert op["security"] == [{"bearerAuth": []}], f"{method} {path}"
        assert "401" in op["responses"], f"{method} {path}"
        # the key travels in the security scheme, not as a parameter
        assert all(p["name"].lower() != "authorization" for p in op.get("parameters", [])), f"{method} {path}"


def test_roles_come_from_the_routes_dependencies(doc: dict[str, Any]):
    roles = {f"{m} {p}": op.get("x-roles") for m, p, op in operations(doc)}
    assert roles["GET /metrics"] == ["reader", "admin"]
    assert roles["POST /v1/trips"] == ["vehicle", "admin"]
    assert roles["GET /v1/trips/{trip_pk}"] == ["vehicle", "reader", "admin"]
    assert roles["POST /v1/keys"] == ["admin"]
    assert roles["GET /healthz"] is None
    # every role may call it: no 403 from the role check, and none from the route itself
    assert "403" not in doc["paths"]["/v1/trips"]["get"]["responses"]


def test_errors_are_the_error_body_never_fastapis_default(doc: dict[str, Any]):
    text = orjson.dumps(doc).decode()
    assert "HTTPValidationError" not in text and '"detail"' not in text
    for method, path, op in operations(doc):
        assert "422" in op["responses"], f"{method} {path}: the parameter check answers 422 on every route"
        for status, response in op["responses"].items():
            if int(status) < 400 or path == "/healthz":
                continue
            schema = response["content"]["application/json"]["schema"]
            assert schema["allOf"] == [{"$ref": "#/components/schemas/ErrorBody"}], (
                f"{method} {path} {status}"
            )
            assert schema["properties"]["error"]["enum"], f"{method} {path} {status}: no error codes"
    assert doc["components"]["schemas"]["ErrorBody"]["required"] == ["error", "location", "message"]


def test_an_error_schema_accepts_its_codes_only(doc: dict[str, Any]):
    check = validator(
        doc,
        "paths",
        "/v1/trips/{trip_pk}",
        "get",
        "responses",
        "404",
        "content",
        "application/json",
        "schema",
    )
    assert check.is_valid({"error": "not_found", "location": "id", "message": "no trip 'x'"})
    assert not check.is_valid({"error": "conflict", "location": "id", "message": "no trip 'x'"})
    assert not check.is_valid({"detail": [{"loc": ["path", "trip_pk"], "msg": "x"}]})


def test_the_upload_body_is_the_contract_schema(doc: dict[str, Any]):
    upload = doc["paths"]["/v1/trips"]["post"]
    body = upload["requestBody"]
    assert body["required"] is True
    assert list(body["content"]) == ["application/json", "application/vnd.csr.trip+cbor"]
    assert [p["name"] for p in upload["parameters"] if p["in"] == "header"] == ["Content-Encoding"]
    for status in (400, 409, 413, 415):
        assert str(status) in upload["responses"]
    check = validator(
        doc, "paths", "/v1/trips", "post", "requestBody", "content", "application/json", "schema"
    )
    example = orjson.loads(EXAMPLE.read_bytes())
    assert check.is_valid(example)
    frames = example["frames"]
    broken = {**example, "frames": [{**frames[0], "gnss": {**frames[0]["gnss"], "lat": 91.0}}, *frames[1:]]}
    assert not check.is_valid(broken)  # the frame's $defs are resolved inside the document
    assert not check.is_valid({**example, "extra": 1})


def test_media_types_are_the_ones_served(doc: dict[str, Any]):
    from prometheus_client import CONTENT_TYPE_LATEST

    def content(path: str, status: str = "200", method: str = "get") -> list[str]:
        return list(doc["paths"][path][method]["responses"][status].get("content", {}))

    assert content("/metrics") == [CONTENT_TYPE_LATEST]
    assert content("/v1/tiles/{z}/{x}/{y}.mvt") == ["application/vnd.mapbox-vector-tile"]
    for path in ("/v1/map", "/v1/tiles/{z}/{x}/{y}.geojson", "/v1/trips/{trip_pk}/track.geojson"):
        assert content(path) == ["application/geo+json"], path
    assert content("/v1/export/lanelet2") == ["application/xml"]
    assert content("/viewer/") == ["text/html"]
    assert content("/v1/trips/{trip_pk}") == ["application/json"]
    assert doc["paths"]["/v1/trips/{trip_pk}"]["get"]["responses"]["200"]["content"]["application/json"][
        "schema"
    ] == {"$ref": "#/components/schemas/Trip"}


def test_only_the_web_pages_end_with_a_slash(doc: dict[str, Any]):
    """What redocly.yaml's ``no-path-trailing-slash: off`` leaves to this test."""
    assert sorted(p for p in doc["paths"] if p.endswith("/")) == ["/ops/", "/viewer/"]
