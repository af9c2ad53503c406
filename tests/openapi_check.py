"""Checking JSON against the service's OpenAPI document: a schema inside the document, its
``#/components/...`` references resolved against the document itself (jsonschema + referencing)."""

from __future__ import annotations

from typing import Any

from jsonschema import Draft202012Validator
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT202012

DOC_URI = "urn:csr:openapi"


def pointer(*parts: str) -> str:
    """A JSON pointer (RFC 6901) to ``parts`` (``~`` and ``/`` escaped)."""
    return "".join("/" + p.replace("~", "~0").replace("/", "~1") for p in parts)


def validator(doc: dict[str, Any], *parts: str) -> Draft202012Validator:
    """A validator of the schema at ``parts`` inside ``doc`` (OpenAPI 3.1 schemas are 2020-12)."""
    registry: Registry = Registry().with_resource(
        DOC_URI, Resource.from_contents(doc, default_specification=DRAFT202012)
    )
    return Draft202012Validator({"$ref": f"{DOC_URI}#{pointer(*parts)}"}, registry=registry)


def response_schema(
    doc: dict[str, Any], method: str, path: str, status: int, media_type: str = "application/json"
) -> Draft202012Validator:
    """The validator of the documented body of ``method path`` answering ``status``."""
    responses = doc["paths"][path][method.lower()]["responses"]
    assert str(status) in responses, f"{method} {path}: {status} is not documented ({sorted(responses)})"
    content = responses[str(status)]["content"]
    assert media_type in content, f"{method} {path} {status}: no {media_type} body documented"
    return validator(
        doc, "paths", path, method.lower(), "responses", str(status), "content", media_type, "schema"
    )
