"""Schemathesis hooks of tests/integration/test_schemathesis.py (loaded by ``SCHEMATHESIS_HOOKS``).

One ``filter_failure`` hook drops the "schema-valid request rejected" failures (ST202, the
``positive_data_acceptance`` check) whose rejection rests on a rule JSON Schema cannot state; each
such rule is in :data:`UNSTATABLE`, recognised by the operation, the status and the error body's
``error`` and ``location``, and, where the request shows it, by the request itself. Every other
failure, of every check, fails the run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import orjson
import schemathesis
from schemathesis import Case, HookContext
from schemathesis.core.failures import Failure
from schemathesis.core.transport import Response

POSITIVE_DATA_ACCEPTANCE = "ST202"
TILE_PATH = "/v1/tiles/{z}/{x}/{y}"


@dataclass(frozen=True, slots=True)
class Unstatable:
    """A rule of the service that a schema cannot express, and the rejection it causes."""

    why: str
    status: int
    errors: frozenset[str]
    locations: frozenset[str]
    applies: Callable[[Case], bool]


def _int(value: Any) -> int | None:
    try:
        return int(str(value))
    except ValueError:
        return None


def _beyond_zoom(case: Case) -> bool:
    """``x`` or ``y`` past ``2^z - 1``: the tile does not exist at that zoom."""
    params = {name: _int(value) for name, value in (case.path_parameters or {}).items()}
    z = params.get("z")
    if z is None or not 0 <= z <= 22:
        return False
    return any((value := params.get(n)) is not None and value >= 2**z for n in ("x", "y"))


def _template_in_path(case: Case) -> bool:
    """A tile path filled with TileJSON's URL template (``{z}``) by a link schemathesis inferred from
    ``GET /v1/tiles.json``: not an integer, so not the documented parameter at all."""
    params = case.path_parameters or {}
    return any(name in params and _int(params[name]) is None for name in ("z", "x", "y"))


def _says_gzip(case: Case) -> bool:
    """``Content-Encoding: gzip`` sent over a body schemathesis did not compress."""
    encoding = {k.lower(): v for k, v in (case.headers or {}).items()}.get("content-encoding", "")
    return str(encoding).lower() in ("gzip", "x-gzip")


def _on_tile_path(case: Case) -> bool:
    return case.operation.path.startswith(TILE_PATH)


def _always(case: Case) -> bool:
    return True


UNSTATABLE = (
    Unstatable(
        "a tile's x and y are below 2^z: a relation between two path parameters",
        422,
        frozenset({"invalid_request"}),
        frozenset({"path.x", "path.y"}),
        lambda case: _on_tile_path(case) and _beyond_zoom(case),
    ),
    Unstatable(
        "schemathesis' stateful phase sends TileJSON's `{z}/{x}/{y}` template as the path",
        422,
        frozenset({"invalid_request"}),
        frozenset({"path.z", "path.x", "path.y"}),
        lambda case: _on_tile_path(case) and _template_in_path(case),
    ),
    Unstatable(
        "a bbox is four numbers in order (min < max) and of bounded area, one comma-separated string",
        422,
        frozenset({"invalid_request", "query"}),
        frozenset({"query.bbox", "bbox"}),
        _always,
    ),
    Unstatable(
        "a page cursor is opaque: only a previous page's `next` holds a valid one",
        422,
        frozenset({"invalid_request"}),
        frozenset({"query.cursor"}),
        _always,
    ),
    Unstatable(
        "an upload's frame times strictly increase: a relation between array items",
        422,
        frozenset({"time_order"}),
        frozenset(),
        lambda case: case.operation.path == "/v1/trips",
    ),
    Unstatable(
        "Content-Encoding: gzip promises a gzip body; schemathesis sends the header, never compresses",
        400,
        frozenset({"gzip"}),
        frozenset({""}),
        lambda case: case.operation.path == "/v1/trips" and _says_gzip(case),
    ),
    Unstatable(
        "a correction names trips that exist and cross the tile: state, not shape",
        422,
        frozenset({"invalid"}),
        frozenset({"trip_i", "trip_j", "frames_i", "frames_j"}),
        lambda case: case.operation.path == f"{TILE_PATH}/corrections",
    ),
    Unstatable(
        "a correction's required fields depend on its `kind`: the body is one schema, not one per kind",
        422,
        frozenset({"invalid_request"}),
        frozenset({"body"}),
        lambda case: case.operation.path == f"{TILE_PATH}/corrections",
    ),
)


def _error_body(response: Response) -> dict[str, Any]:
    try:
        body = orjson.loads(response.content)
    except orjson.JSONDecodeError:
        return {}
    return body if isinstance(body, dict) else {}


def unstatable_rule(failure: Failure, case: Case, response: Response) -> Unstatable | None:
    """The rule in :data:`UNSTATABLE` that explains ``failure``, if any."""
    if failure.code != POSITIVE_DATA_ACCEPTANCE:
        return None
    body = _error_body(response)
    for rule in UNSTATABLE:
        if (
            response.status_code == rule.status
            and body.get("error") in rule.errors
            and (not rule.locations or body.get("location") in rule.locations)
            and rule.applies(case)
        ):
            return rule
    return None


@schemathesis.hook
def filter_failure(context: HookContext, failure: Failure, case: Case, response: Response) -> bool:
    return unstatable_rule(failure, case, response) is None
