"""One check of every path and query parameter, before any route reads the database.

Both databases must answer the same for a value they cannot store or compare: PostgreSQL rejects a
NUL in text and an integer past its column's 32 bits, SQLite overflows at 64 bits. So, for every
route:

- a control character (NUL included) in any path or query value: 422 naming the parameter;
- an integer parameter outside the 32-bit range of the database's integer columns: 422 naming it;
- a tile address (``z``, ``x``, ``y`` in the path) outside 0..MAX_ZOOM, 0..2^z-1: 422 naming it.

Request bodies use the field types :data:`DbInt`, :data:`IdText` and :data:`NoteText` for the same
rules; page cursors check their keys with :func:`fits_db_int` and :func:`has_control_characters`.
"""

from __future__ import annotations

import re
import types
from typing import Annotated, Any, Union, get_args, get_origin

from fastapi import Request
from fastapi.dependencies.models import Dependant
from pydantic import Field, StringConstraints

from services.api.errors import ApiError
from services.tiles.http import check_tile

# The range of the databases' INTEGER columns (PostgreSQL's are 32 bits).
DB_INT_MIN, DB_INT_MAX = -(2**31), 2**31 - 1
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_INTEGER = re.compile(r"[+-]?[0-9]+")

# The same rules for the ids and integers of request bodies (pydantic field types)
DbInt = Annotated[int, Field(ge=DB_INT_MIN, le=DB_INT_MAX)]
IdText = Annotated[str, StringConstraints(pattern=r"^[^\x00-\x1f\x7f]*$", max_length=200)]
NoteText = Annotated[str, StringConstraints(pattern=r"^[^\x00]*$", max_length=2000)]


def fits_db_int(value: int) -> bool:
    return DB_INT_MIN <= value <= DB_INT_MAX


def has_control_characters(text: str) -> bool:
    return _CONTROL.search(text) is not None


def invalid(location: str, why: str) -> ApiError:
    name = location.split(".", 1)[-1]
    return ApiError(422, "invalid_request", f"{name}: {why}", location=location)


def _is_int_annotation(annotation: Any) -> bool:
    """``int``, ``int | None`` or ``Optional[int]`` (``bool`` is not an integer parameter)."""
    if annotation is int:
        return True
    if get_origin(annotation) in (Union, types.UnionType):
        return int in get_args(annotation)
    return False


def _int_fields(dependant: Dependant) -> set[tuple[str, str]]:
    """(``path`` / ``query``, name) of a dependant's integer parameters, its dependencies' included."""
    own = {
        (where, field.alias)
        for where, fields in (("path", dependant.path_params), ("query", dependant.query_params))
        for field in fields
        if _is_int_annotation(field.field_info.annotation)
    }
    return own.union(*(_int_fields(sub) for sub in dependant.dependencies))


def _int_parameters(request: Request) -> set[tuple[str, str]]:
    """The integer parameters of the route the request was routed to (none for other endpoints)."""
    dependant = getattr(request.scope.get("route"), "dependant", None)
    return _int_fields(dependant) if isinstance(dependant, Dependant) else set()


def _values(request: Request) -> list[tuple[str, str, str]]:
    """(``path`` / ``query``, name, raw value) of every parameter of the request."""
    path = [("path", name, str(value)) for name, value in request.path_params.items()]
    return path + [("query", name, value) for name, value in request.query_params.multi_items()]


def check_int(location: str, raw: str) -> int | None:
    """The integer, ``None`` when ``raw`` is not one (the route's own validation says so), or 422
    when it is outside the databases' integer range."""
    if not _INTEGER.fullmatch(raw.strip()):
        return None
    value = int(raw)
    if not fits_db_int(value):
        raise invalid(location, f"must be between {DB_INT_MIN} and {DB_INT_MAX}, not {raw}")
    return value


def check_request_params(request: Request) -> None:
    """The app-wide dependency: 422 for a parameter no database could look up (module docstring)."""
    int_parameters = _int_parameters(request)
    ints: dict[str, int] = {}
    for where, name, raw in _values(request):
        location = f"{where}.{name}"
        if has_control_characters(raw):
            raise invalid(location, "control characters (such as NUL) are not allowed")
        if (where, name) in int_parameters:
            value = check_int(location, raw)
            if value is not None and where == "path":
                ints[name] = value
    if {"z", "x", "y"} <= ints.keys():
        check_tile(ints["z"], ints["x"], ints["y"])
