"""The parameter check of every route (``services.api.params``) written into the OpenAPI document,
so that a value the document admits is one the check lets through, and the other way round:

- every string path or query parameter: a ``pattern`` without control characters;
- every integer one: ``minimum`` / ``maximum`` within the databases' 32-bit integer columns;
- a tile address ``z/x/y`` in the path: ``z`` in ``0..MAX_ZOOM``, ``x`` and ``y`` in
  ``0..2^MAX_ZOOM-1``. That ``x`` and ``y`` are below ``2^z`` relates two parameters, which JSON
  Schema cannot say: the parameters' descriptions say it.
"""

from __future__ import annotations

from typing import Any

from services.api.params import DB_INT_MAX, DB_INT_MIN
from services.tiles.mercator import MAX_ZOOM

# The JSON Schema form of services.api.params' control-character rule (C0 controls and DEL)
NO_CONTROL_CHARACTERS = "^[^\\x00-\\x1f\\x7f]*$"
TILE_PATH = ("z", "x", "y")
TILE_RANGE = {
    "z": (0, MAX_ZOOM, f"zoom level, 0..{MAX_ZOOM}"),
    "x": (0, 2**MAX_ZOOM - 1, "tile column, 0..2^z-1"),
    "y": (0, 2**MAX_ZOOM - 1, "tile row, 0..2^z-1"),
}


def _branches(schema: dict[str, Any]) -> list[dict[str, Any]]:
    """The schema itself, or its ``anyOf`` branches (FastAPI writes ``int | None`` as one)."""
    return schema["anyOf"] if "anyOf" in schema else [schema]


def _within(schema: dict[str, Any], low: int, high: int) -> None:
    schema["minimum"] = max(schema.get("minimum", low), low)
    schema["maximum"] = min(schema.get("maximum", high), high)


def constrain_parameter(parameter: dict[str, Any], *, tile_path: bool) -> None:
    """Write the parameter check's rules into one path or query parameter's schema."""
    schema = parameter.get("schema", {})
    for branch in _branches(schema):
        if branch.get("type") == "string" and "enum" not in branch and "pattern" not in branch:
            branch["pattern"] = NO_CONTROL_CHARACTERS
        elif branch.get("type") == "integer":
            _within(branch, DB_INT_MIN, DB_INT_MAX)
            if tile_path and parameter["name"] in TILE_RANGE:
                low, high, description = TILE_RANGE[parameter["name"]]
                _within(branch, low, high)
                parameter.setdefault("description", description)


def constrain_parameters(operation: dict[str, Any]) -> None:
    """:func:`constrain_parameter` on every path and query parameter of ``operation``."""
    parameters = operation.get("parameters", [])
    path_names = {p["name"] for p in parameters if p["in"] == "path"}
    tile_path = set(TILE_PATH) <= path_names
    for parameter in parameters:
        if parameter["in"] in ("path", "query"):
            constrain_parameter(parameter, tile_path=tile_path and parameter["in"] == "path")
