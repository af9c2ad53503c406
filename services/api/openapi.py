"""The OpenAPI 3.1 document at ``/openapi.json``, describing what the service answers.

FastAPI builds the document from the routes; :func:`install_openapi` then completes it from the same
routes, so that it cannot drift from them:

- **Security.** One HTTP bearer scheme (the API keys of ``POST /v1/keys``). An operation whose
  dependencies include a role check (:func:`services.api.deps.require`) requires it and lists its
  roles under ``x-roles``; every other operation is public (``security: []``).
- **Errors.** Every 4xx/5xx body is :class:`ErrorBody`; the document names, per operation and
  status, the ``error`` codes it can carry (an ``enum`` on ``error``). The statuses every route of a
  kind shares are added here: 401 and 403 from the role check, 422 from the parameter check that
  runs before every route (``services.api.params``), 400 for a route with a JSON body that is not
  JSON, 503 for a route that reads the database. A
  route declares its own (404, 409, ...) with :func:`errors` in its decorator. FastAPI's default
  422 (``HTTPValidationError``, a body the service never sends) is replaced everywhere.
- **Parameters.** The parameter check's rules are written into each path and query parameter's
  schema (``services.api.openapi_params``).
- **Upload body.** ``POST /v1/trips`` reads its body raw (gzip, limits, idempotency): its request
  body is described from the contract's JSON Schema (:func:`upload_request_body`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from functools import cache
from importlib.resources import files
from typing import Any

import orjson
from fastapi import FastAPI
from fastapi.dependencies.models import Dependant
from fastapi.openapi.utils import get_openapi
from fastapi.routing import APIRoute, iter_route_contexts
from pydantic import BaseModel, ConfigDict, Field
from pydantic.json_schema import models_json_schema

from services.api.answers import GEOJSON_MODELS
from services.api.deps import get_read_session, get_session
from services.api.openapi_params import constrain_parameters

BEARER = "bearerAuth"
REF = "#/components/schemas/{model}"
ERROR_BODY_REF = REF.format(model="ErrorBody")
# The upload schema's ``$defs`` become components named with this prefix (``TripUpload.frame``)
UPLOAD_SCHEMA = "TripUpload"
# The contract's upload schema, vendored verbatim (tests/unit/test_contract_schema.py)
UPLOAD_SCHEMA_FILE = files("csr_core") / "schemas" / "trip-upload.schema.json"


class ErrorBody(BaseModel):
    """The body of every 4xx and 5xx answer (``services.api.errors``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"error": "not_found", "location": "id", "message": "no trip 'tr_0001'"},
                {
                    "error": "schema",
                    "location": "frames[1].gnss.lat",
                    "message": "frame 1, field gnss.lat: Input should be less than or equal to 90",
                },
            ]
        }
    )

    error: str = Field(description="what kind of error: a code such as `not_found` or `schema`")
    location: str = Field(
        description="where: a JSON path into the body (`frames[12].gnss.lat`), `path.<name>` or "
        "`query.<name>`, `database`; empty when it is the request as a whole"
    )
    message: str = Field(description="what is wrong, for a human; it names the location")


# The statuses the app adds to the routes of a kind: (status, error codes, when)
UNAUTHORIZED = (401, ("unauthorized",), "No key, an unknown or a revoked key (`WWW-Authenticate: Bearer`).")
INVALID_PARAMETER = (
    422,
    ("invalid_request",),
    "A path or query parameter no database can look up: a control character (NUL included), an "
    "integer outside -2^31..2^31-1, a tile `z/x/y` outside `0..22` / `0..2^z-1` (`location`: "
    "`path.<name>` or `query.<name>`).",
)
NOT_ACCEPTABLE = (
    406,
    ("not_acceptable",),
    "`Accept-Encoding` refuses identity and accepts none of br, zstd, gzip "
    "(`location: header.accept-encoding`).",
)
BODY_INVALID = " A request body that is not the documented one (`location`: `body.<field>`)."
BODY_UNREADABLE = (
    400,
    ("json",),
    "The request body is not JSON text (not UTF-8 included; `location: body`).",
)
DATABASE = (
    503,
    ("database_busy", "database_unavailable"),
    "The database is busy beyond its wait or cannot be reached (`location: database`, `Retry-After`).",
)
RESPONSE_HEADERS = {
    401: {"WWW-Authenticate": {"description": "`Bearer`", "schema": {"type": "string", "const": "Bearer"}}},
    503: {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}},
}


def errors(answers: Mapping[int, Mapping[str, str]]) -> dict[int | str, dict[str, Any]]:
    """``responses=`` of a route's own error answers: for each status, its ``error`` codes and when
    each is sent (``{404: {"not_found": "no trip with this id"}}``)."""
    return {
        status: _error_response(tuple(codes), " ".join(f"`{code}`: {when}" for code, when in codes.items()))
        for status, codes in answers.items()
    }


def _error_response(codes: tuple[str, ...], description: str) -> dict[str, Any]:
    return {
        "description": description,
        "content": {"application/json": {"schema": _error_schema(codes)}},
    }


def _error_schema(codes: tuple[str, ...]) -> dict[str, Any]:
    return {
        "allOf": [{"$ref": ERROR_BODY_REF}],
        "properties": {"error": {"enum": list(codes)}},
    }


def _codes(response: dict[str, Any]) -> list[str]:
    """The ``error`` codes a response built by :func:`_error_response` names (none for another)."""
    schema = response.get("content", {}).get("application/json", {}).get("schema", {})
    if schema.get("allOf") != [{"$ref": ERROR_BODY_REF}]:
        return []
    return list(schema["properties"]["error"]["enum"])


def _add_error(operation: dict[str, Any], status: int, codes: tuple[str, ...], description: str) -> None:
    """Add ``codes`` to the operation's ``status`` answer (merged with the route's own codes)."""
    responses = operation.setdefault("responses", {})
    own = responses.get(str(status))
    known = _codes(own) if own else []
    merged = tuple(dict.fromkeys([*known, *codes]))
    text = f"{own['description']} {description}" if known else description
    responses[str(status)] = _error_response(merged, text)
    if status in RESPONSE_HEADERS:
        responses[str(status)]["headers"] = RESPONSE_HEADERS[status]


# --- what the routes' dependencies say --------------------------------------------------------------


def _calls(dependant: Dependant) -> list[Callable[..., Any]]:
    """Every dependency callable of a route, its dependencies' dependencies included."""
    out: list[Callable[..., Any]] = []
    for sub in dependant.dependencies:
        if sub.call is not None:
            out.append(sub.call)
        out += _calls(sub)
    return out


def roles_of(dependant: Dependant) -> tuple[str, ...] | None:
    """The roles a route accepts (``services.api.deps.require``); ``None`` for a public route."""
    for call in _calls(dependant):
        roles = getattr(call, "roles", None)
        if roles is not None:
            return tuple(roles)
    return None


def reads_database(dependant: Dependant) -> bool:
    """Whether a route opens a session or checks a key (both read the database)."""
    calls = _calls(dependant)
    return roles_of(dependant) is not None or any(c in (get_session, get_read_session) for c in calls)


# --- the upload body --------------------------------------------------------------------------------


@cache
def _upload_schemas() -> dict[str, dict[str, Any]]:
    """The contract's upload schema as components: the document itself and each of its ``$defs``,
    their ``#/$defs/...`` references pointed at the components."""
    schema = orjson.loads(UPLOAD_SCHEMA_FILE.read_bytes())
    text = orjson.dumps(schema).decode().replace('"#/$defs/', f'"#/components/schemas/{UPLOAD_SCHEMA}.')
    schema = orjson.loads(text)
    defs = schema.pop("$defs", {})
    schema.pop("$schema", None)  # OpenAPI 3.1's own dialect is the same draft (2020-12)
    schema.pop("$id", None)  # an $id would change the base of the references above
    return {UPLOAD_SCHEMA: schema, **{f"{UPLOAD_SCHEMA}.{name}": value for name, value in defs.items()}}


def upload_request_body() -> dict[str, Any]:
    """``openapi_extra`` of ``POST /v1/trips``: the contract's JSON document, sent as JSON or in the
    compact binary encoding, optionally gzip-compressed (``Content-Encoding: gzip``)."""
    return {
        "requestBody": {
            "required": True,
            "description": "The trip, as `trip-upload.schema.json` (contract) describes it. It may be "
            "sent gzip-compressed with `Content-Encoding: gzip` (a gzip body is also recognised by its "
            "magic bytes without it). The bytes after decompression are the idempotency key's content: "
            "the same bytes again answer 200 with the same trip. As `application/vnd.csr.trip+cbor`, the "
            "same trip in the compact binary encoding (docs/upload-binary.md), decoded and then "
            "validated as the JSON document is.",
            "content": {
                "application/json": {"schema": {"$ref": REF.format(model=UPLOAD_SCHEMA)}},
                "application/vnd.csr.trip+cbor": {
                    "schema": {"type": "string", "contentMediaType": "application/cbor"}
                },
            },
        },
        "parameters": [
            {
                "name": "Content-Encoding",
                "in": "header",
                "required": False,
                "description": "`gzip` (or `x-gzip`) for a compressed body; absent or `identity` for plain JSON",
                "schema": {"type": "string", "enum": ["gzip", "x-gzip", "identity"]},
            }
        ],
    }


# --- the document -----------------------------------------------------------------------------------


def _only_the_model(responses: dict[str, Any]) -> None:
    """A route that returns a dict describes its answer with a model (``services.api.answers``);
    FastAPI merges the model's ``$ref`` into the schema of the dict (an object of anything), which
    says nothing more: keep the reference alone."""
    for response in responses.values():
        for media in response.get("content", {}).values():
            schema = media.get("schema", {})
            if "$ref" in schema and len(schema) > 1:
                media["schema"] = {"$ref": schema["$ref"]}


def _complete_operation(
    operation: dict[str, Any], dependant: Dependant, *, method: str, has_body: bool
) -> None:
    roles = roles_of(dependant)
    responses = operation.setdefault("responses", {})
    _only_the_model(responses)
    if "422" in responses and not _codes(responses["422"]):
        del responses["422"]  # FastAPI's HTTPValidationError: never sent
    if roles is None:
        operation["security"] = []
    else:
        operation["security"] = [{BEARER: []}]
        operation["x-roles"] = list(roles)
        _add_error(operation, *UNAUTHORIZED)
        if set(roles) != {"vehicle", "reader", "admin"}:
            _add_error(
                operation,
                403,
                ("forbidden",),
                f"A key whose role may not make this call (roles: {', '.join(roles)}).",
            )
    status, codes, description = INVALID_PARAMETER
    _add_error(operation, status, codes, description + (BODY_INVALID if has_body else ""))
    constrain_parameters(operation)
    if has_body:
        _add_error(operation, *BODY_UNREADABLE)
    if reads_database(dependant):
        _add_error(operation, *DATABASE)
    if method == "get":
        _add_error(operation, *NOT_ACCEPTABLE)  # the content-coding middleware, before every GET


def build_document(app: FastAPI) -> dict[str, Any]:
    doc = get_openapi(
        title=app.title,
        version=app.version,
        openapi_version=app.openapi_version,
        summary=app.summary,
        description=app.description,
        routes=app.routes,
        tags=app.openapi_tags,
        servers=app.servers,
        license_info=app.license_info,
    )
    doc = copy.deepcopy(doc)
    # the routes as the app serves them (included routers resolved, their prefixes applied)
    for route in iter_route_contexts(app.routes):
        if not isinstance(route.original_route, APIRoute) or not route.include_in_schema:
            continue
        for method in route.methods or ():
            operation = doc["paths"].get(route.path_format, {}).get(method.lower())
            if operation is not None:
                _complete_operation(
                    operation, route.dependant, method=method.lower(), has_body=route.body_field is not None
                )
    components = doc.setdefault("components", {})
    schemas = components.setdefault("schemas", {})
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    described: tuple[type[BaseModel], ...] = (ErrorBody, *GEOJSON_MODELS)
    _, models = models_json_schema([(model, "serialization") for model in described], ref_template=REF)
    schemas.update(models["$defs"])
    schemas.update(_upload_schemas())
    components["securitySchemes"] = {
        BEARER: {
            "type": "http",
            "scheme": "bearer",
            "description": "An API key (`csr_...`) of role vehicle, reader or admin, created by "
            "`POST /v1/keys`; each operation lists the roles it accepts under `x-roles`.",
        }
    }
    doc["components"] = {key: components[key] for key in sorted(components)}
    return doc


def install_openapi(app: FastAPI) -> None:
    """Serve :func:`build_document` at ``/openapi.json`` (built once, at the first request)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = build_document(app)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
