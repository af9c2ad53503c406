"""The OpenAPI document states the parameter check of every route (services.api.params): what its
schemas admit is what the check lets through."""

from __future__ import annotations

import re
from typing import Any

import pytest

from services.api.app import create_app
from services.api.openapi_params import NO_CONTROL_CHARACTERS
from services.api.params import DB_INT_MAX, DB_INT_MIN, has_control_characters
from services.settings import Settings
from services.tiles.mercator import MAX_ZOOM

pytestmark = pytest.mark.unit

METHODS = ("get", "put", "post", "delete", "patch")


@pytest.fixture(scope="module")
def doc(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return create_app(Settings(data_dir=tmp_path_factory.mktemp("openapi-params"))).openapi()


def parameters(doc: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    return [
        (f"{method.upper()} {path}", parameter)
        for path, item in doc["paths"].items()
        for method, op in item.items()
        if method in METHODS
        for parameter in op.get("parameters", [])
        if parameter["in"] in ("path", "query")
    ]


def branches(parameter: dict[str, Any]) -> list[dict[str, Any]]:
    schema = parameter["schema"]
    return schema.get("anyOf", [schema])


def test_the_pattern_is_the_checks_rule():
    pattern = re.compile(NO_CONTROL_CHARACTERS)
    for text in ("tr_0001", "veh-1:a.b", "", "ü ß 中", "a\x7fb", "a\x00b", "a\nb", "\x1f", "a\x80b"):
        assert (pattern.search(text) is None) == has_control_characters(text), repr(text)


def test_every_string_parameter_excludes_control_characters(doc: dict[str, Any]):
    strings = [
        (op, p["name"], b)
        for op, p in parameters(doc)
        for b in branches(p)
        if b.get("type") == "string" and "enum" not in b
    ]
    assert len(strings) >= 10
    for op, name, branch in strings:
        pattern = branch.get("pattern")
        assert pattern is not None, (op, name)
        if pattern != NO_CONTROL_CHARACTERS:  # a route's own, stricter rule: no control character passes
            own = re.compile(pattern)
            assert all(own.search(text) is None for text in ("a\x00b", "a\nb", "\x1f", "a\x7fb")), (op, name)


def test_every_integer_parameter_fits_the_database(doc: dict[str, Any]):
    integers = [(op, p, b) for op, p in parameters(doc) for b in branches(p) if b.get("type") == "integer"]
    assert len(integers) >= 20
    for op, parameter, branch in integers:
        assert DB_INT_MIN <= branch["minimum"] <= branch["maximum"] <= DB_INT_MAX, (op, parameter["name"])


def test_a_tile_address_is_bounded_by_the_zoom_range(doc: dict[str, Any]):
    tile_ops = [(op, p) for op, p in parameters(doc) if "{z}/{x}/{y}" in op and p["in"] == "path"]
    assert {p["name"] for _, p in tile_ops} >= {"z", "x", "y"}
    for op, parameter in tile_ops:
        if parameter["name"] not in ("z", "x", "y"):
            continue
        high = MAX_ZOOM if parameter["name"] == "z" else 2**MAX_ZOOM - 1
        assert (parameter["schema"]["minimum"], parameter["schema"]["maximum"]) == (0, high), op
        if parameter["name"] != "z":
            assert "2^z-1" in parameter["description"], op


def test_map_versions_are_not_negative(doc: dict[str, Any]):
    versions = [(op, p) for op, p in parameters(doc) if p["in"] == "query" and p["name"] in ("v", "version")]
    assert len(versions) >= 4
    for op, parameter in versions:
        (integer,) = [b for b in branches(parameter) if b.get("type") == "integer"]
        assert max(parameter["schema"].get("minimum", DB_INT_MIN), integer["minimum"]) >= 0, op


def test_job_filters_are_enums(doc: dict[str, Any]):
    from services.db import repo

    listed = {p["name"]: p["schema"] for op, p in parameters(doc) if op == "GET /v1/jobs"}
    assert listed["state"]["enum"] == list(repo.JOB_STATES)
    assert listed["kind"]["enum"] == list(repo.QUEUE_OF_KIND)


def test_a_key_body_is_one_shape_per_role(doc: dict[str, Any]):
    body = doc["paths"]["/v1/keys"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    assert set(body["discriminator"]["mapping"]) == {"vehicle", "reader", "admin"}
    vehicle = doc["components"]["schemas"]["VehicleKeyRequest"]
    assert set(vehicle["required"]) == {"role", "vehicle_id"}


def test_a_json_body_that_is_not_json_is_documented(doc: dict[str, Any]):
    for path, item in doc["paths"].items():
        for method, op in item.items():
            body = op.get("requestBody", {}).get("content", {})
            if method in METHODS and "application/json" in body:
                assert "400" in op["responses"], (method, path)
